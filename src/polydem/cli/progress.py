"""The progress of a run on stderr, with the wall time left.

A line shows the number of contacts and the kinetic energy, which take a diagnostics pass over
every pair. So that a refresh costs nothing next to the steps, a line reuses the numbers of the
frame just recorded when it is at the same step (:meth:`Progress.note`); on a terminal, where the
line is redrawn every ``TTY_REFRESH_S``, it shows those of the last frame; off a terminal it
computes them only for the lines it prints (one per 5% of the steps, or one a minute).
"""

from __future__ import annotations

import math
import time
from collections import deque

__all__ = [
    "ETA_AFTER_S",
    "ETA_WINDOW",
    "FIRST_LINE_S",
    "LINE_EVERY_S",
    "PROGRESS_LINES",
    "TTY_REFRESH_S",
    "Progress",
    "duration",
]

PROGRESS_LINES = 20
"""Progress lines of a run whose stderr is not a terminal (one per 5% of the steps)."""

TTY_REFRESH_S = 0.25
"""Shortest wall time between two updates of the progress line on a terminal [s]."""

FIRST_LINE_S = 10.0
LINE_EVERY_S = 60.0
"""Off a terminal, the first progress line comes after at most FIRST_LINE_S of wall time, the
others at most LINE_EVERY_S apart (besides one per 5% of the steps) [s]."""

ETA_AFTER_S = 0.5
"""The time left is shown once the steps after the first chunk took this much wall time [s]."""

ETA_WINDOW = 0.3
"""The time left follows the rate over this fraction of the wall time so far (the recent past)."""


def duration(seconds: float) -> str:
    """``"4.2 s"``, ``"42 s"``, ``"3 min 05 s"``, ``"2 h 07 min"``."""
    if seconds < 9.95:
        return f"{max(0.0, seconds):.1f} s"
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


class Progress:
    """Progress on stderr: one line updated in place on a terminal, else one line per 5% (and at
    least one a minute); both with the wall time left once it can be estimated."""

    def __init__(self, stream, start: int, target: int, dt: float, enabled: bool):
        self.stream = stream
        self.start = start
        self.target = target
        self.dt = dt
        self.enabled = enabled
        try:
            self.tty = bool(stream.isatty())
        except (AttributeError, ValueError):
            self.tty = False
        self.t0 = time.perf_counter()
        self.last = -math.inf
        self.last_line = self.t0  # wall time of the last line written (not on a terminal)
        self.lines = 0
        self.last_steps = None
        self.width = 0
        self.settle_note = ""  # e.g. "  kinetic/released 3.1e-05" in a run until settled
        self.noted: tuple[int, int, float] | None = None  # (steps, contacts, kinetic energy) of the last frame
        self.samples: deque = deque()  # (wall time, steps) after each chunk, over the recent past
        self.marks = [start + math.ceil(j * (target - start) / PROGRESS_LINES) for j in range(1, PROGRESS_LINES + 1)]

    def next_mark(self, steps: int) -> int | None:
        """The next step at which a line is due (None on a terminal: lines follow the wall clock)."""
        if not self.enabled or self.tty:
            return None
        later = [m for m in self.marks if m > steps]
        return later[0] if later else None

    def note(self, steps: int, contacts: int, kinetic: float) -> None:
        """The number of contacts and the kinetic energy at ``steps`` (a frame), for the lines to reuse."""
        self.noted = (steps, contacts, kinetic)

    def sample(self, steps: int, now: float) -> None:
        """Note the progress after a chunk; keep the samples of the last ETA_WINDOW of the run."""
        samples = self.samples
        samples.append((now, steps))
        window = max(ETA_AFTER_S, ETA_WINDOW * (now - samples[0][0]))
        while len(samples) > 2 and samples[1][0] <= now - window:
            samples.popleft()

    def eta(self, steps: int, now: float) -> float | None:
        """Wall time left [s] at the rate of the recent past (a pour slows down as its contacts grow;
        the first chunk, with the start-up costs, is left out); None until it can be estimated."""
        if not self.samples:
            return None
        t_ref, s_ref = self.samples[0]
        if steps <= s_ref or now - t_ref < ETA_AFTER_S:
            return None
        return (self.target - steps) * (now - t_ref) / (steps - s_ref)

    def _numbers(self, sim, steps: int, force: bool) -> tuple[int, float]:
        """Contacts and kinetic energy for a line: the noted frame's where they serve, else computed."""
        noted = self.noted
        if noted is not None and (noted[0] == steps or (self.tty and not force)):
            return noted[1], noted[2]
        return len(sim.contacts()["volume"]), sim.energy()["kinetic"]

    def update(self, sim, force=False) -> None:
        if not self.enabled:
            return
        steps = sim.steps_done
        now = time.perf_counter()
        self.sample(steps, now)
        if self.tty:
            if not force and now - self.last < TTY_REFRESH_S:
                return
        else:
            due = any(self.start < m <= steps for m in self.marks)
            gap = now - self.last_line
            if not (due or force or gap >= (LINE_EVERY_S if self.lines else FIRST_LINE_S)):
                return
            self.marks = [m for m in self.marks if m > steps]
        self.last = now
        self.last_steps = steps
        contacts, kinetic = self._numbers(sim, steps, force)
        self.stream.write(self._line(sim.time, steps, now, contacts, kinetic))
        if not self.tty:
            self.last_line = now
            self.lines += 1
        self.stream.flush()

    def _line(self, t: float, steps: int, now: float, contacts: int, kinetic: float) -> str:
        rate = (steps - self.start) / max(now - self.t0, 1e-9)
        frac = (steps - self.start) / max(self.target - self.start, 1)
        t_end = self.target * self.dt
        left = self.eta(steps, now)
        if steps >= self.target:
            left_text = f"  took {duration(now - self.t0)}"
        else:
            left_text = f"  {duration(left)} left" if left is not None else ""
        if not self.tty:
            return (
                f"  {100 * frac:5.1f}%  t = {t:.4g} of {t_end:.4g} s  step {steps}/{self.target}  "
                f"{rate:.1f} steps/s{left_text}  {contacts} contacts  kinetic {kinetic:.3e} J{self.settle_note}\n"
            )
        bar = "#" * int(round(20 * frac))
        line = (
            f"  [{bar:<20}] {100 * frac:5.1f}%  t {t:.4g}/{t_end:.4g} s  {rate:8.1f} steps/s{left_text}  "
            f"{contacts} contacts  kinetic {kinetic:.3e} J{self.settle_note}"
        )
        pad = max(0, self.width - len(line))
        self.width = len(line)
        return "\r" + line + " " * pad

    def finish(self, sim=None) -> None:
        """Ends the line on a terminal, after a last update at the state of ``sim`` (if given)."""
        if sim is not None and self.enabled and self.tty and self.last_steps != sim.steps_done:
            self.update(sim, force=True)
        if self.enabled and self.tty and self.width:
            self.stream.write("\n")
            self.stream.flush()
            self.width = 0
