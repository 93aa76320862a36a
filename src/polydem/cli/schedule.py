"""When a run records its frames and writes its checkpoints, and where it stops to do so.

Everything counts absolute steps from t = 0, so a resumed run keeps the schedule of the run it
continues: frame k is the first state at or after simulated time k / fps.
"""

from __future__ import annotations

import math

from polydem.cli.common import steps_at

__all__ = ["MAX_CHUNK_STEPS", "Schedule"]

MAX_CHUNK_STEPS = 256
"""Most steps between two checks for Ctrl-C (and progress updates on a terminal)."""


class Schedule:
    """The frames (``frame``: the next one to record) and checkpoints (``cp_index``: the next
    periodic one) of a run from step ``start`` to step ``target``."""

    def __init__(
        self, dt: float, fps: float, target: int, start: int, cp_steps=None, cp_seconds=None, check_every=None
    ):
        self.dt = dt
        self.check_every = check_every
        self.fps = fps
        self.frame_dt = 1.0 / fps
        self.target = target
        self.cp_steps = cp_steps
        self.cp_seconds = cp_seconds
        self.frame = self._first_frame(start)
        self.cp_index = self._first_checkpoint(start)

    def frame_step(self, k: int) -> int:
        return steps_at(k * self.frame_dt, self.dt)

    def _first_frame(self, steps: int) -> int:
        k = max(0, math.floor(steps * self.dt / self.frame_dt) - 1)
        while self.frame_step(k) < steps:
            k += 1
        return k

    def cp_step(self, j: int) -> int | None:
        if self.cp_steps is not None:
            return j * self.cp_steps
        if self.cp_seconds is not None:
            return steps_at(j * self.cp_seconds, self.dt)
        return None

    def _first_checkpoint(self, steps: int) -> int:
        j = 1
        if self.cp_steps is not None:
            j = steps // self.cp_steps + 1
        elif self.cp_seconds is not None:
            j = max(1, math.floor(steps * self.dt / self.cp_seconds))
            while self.cp_step(j) <= steps:
                j += 1
        return j

    def at_frame(self, steps: int) -> bool:
        """Whether the next frame is due at ``steps``."""
        return self.frame_step(self.frame) == steps

    def checkpoint_due(self, steps: int) -> bool:
        """Whether a periodic checkpoint is due at ``steps`` (the schedule then moves past it)."""
        due = self.cp_step(self.cp_index)
        if due is None or due > steps:
            return False
        while self.cp_step(self.cp_index) <= steps:
            self.cp_index += 1
        return True

    def settle_check_due(self, steps: int) -> bool:
        """Whether a run until settled checks at ``steps``: every ``check_every`` steps from t = 0, and at the end."""
        return self.check_every is not None and (steps % self.check_every == 0 or steps >= self.target)

    def next_stop(self, steps: int, mark: int | None = None) -> int:
        """The next step at which the run stops: the target, a frame, a checkpoint, a progress
        ``mark``, a settle check, or at most MAX_CHUNK_STEPS on."""
        stops = [self.target, steps + MAX_CHUNK_STEPS, self.frame_step(self.frame)]
        if self.check_every is not None:
            stops.append((steps // self.check_every + 1) * self.check_every)
        cp = self.cp_step(self.cp_index)
        if cp is not None:
            stops.append(cp)
        if mark is not None:
            stops.append(mark)
        return min(s for s in stops if s > steps)
