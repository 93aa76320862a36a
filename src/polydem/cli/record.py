"""The record of a run so far, which ``polydem run`` keeps in its checkpoints so that a resumed
run's summary covers the whole run from t = 0: the frame history (time, energies, contacts,
packing fraction), the contact count of each frame, the largest overlap, the initial energy, the
wall time and the files written by each part."""

from __future__ import annotations

import math

import numpy as np

from polydem.cli.diagnostics import body_volumes, relative_depths, relative_overlaps, settled_region

__all__ = ["ENERGY_KEYS", "HISTORY_KEYS", "RUN_RECORD_VERSION", "RunLog", "finite", "run_record_problem"]

HISTORY_KEYS = ("time", "kinetic", "contact", "gravity", "dissipated", "total", "contacts", "packing_fraction")
ENERGY_KEYS = ("kinetic", "contact", "gravity", "dissipated", "total")
RUN_RECORD_VERSION = 1
"""Layout of the run record that ``polydem run`` keeps in its checkpoints (:meth:`RunLog.record`)."""


def finite(x):
    """JSON-safe: non-finite floats become None, numpy scalars plain Python."""
    if isinstance(x, dict):
        return {k: finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [finite(v) for v in x]
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, float | np.floating):
        x = float(x)
        return x if math.isfinite(x) else None
    return x


class RunLog:
    """The frame history of a run and what its summary reports of the frames; ``earlier``: the
    record of the run up to the checkpoint it resumed from (None for a run from t = 0)."""

    def __init__(self, scene, fps: float):
        self.fps = fps
        self.volumes = body_volumes(scene)
        self.history: dict[str, list] = {k: [] for k in HISTORY_KEYS}
        self.frame_contacts: list[int] = []
        self.frame_overlap = 0.0
        self.frame_depth = 0.0
        self.energy_initial = None
        self.earlier = None

    def continue_from(self, checkpoint) -> None:
        """Continue the record of the run that wrote ``checkpoint`` (its history, contact counts,
        largest overlap, initial energy, wall time and files), so the summary covers the whole run."""
        rec = checkpoint.run
        if rec is None:
            return
        self.earlier = rec
        self.history = {k: list(rec["history"][k]) for k in HISTORY_KEYS}
        self.frame_contacts = list(rec["frame_contacts"])
        self.frame_overlap = float(rec["frame_overlap"])
        # Records written before depths were reported have none: the largest depth then covers
        # the frames since the resume.
        self.frame_depth = float(rec.get("frame_depth", 0.0))

    def holds(self, time_s: float, dt: float) -> bool:
        """Whether the history already has a frame at ``time_s`` (a resumed run starts at a frame it may hold)."""
        times = self.history["time"]
        return bool(times) and not time_s > times[-1] + 0.5 * dt

    def add_frame(self, sim, contacts) -> dict:
        """Add the state of ``sim`` (with its ``contacts``) to the history; returns its energies."""
        self.frame_contacts.append(len(contacts["volume"]))
        energy = sim.energy()
        region = settled_region(sim.scene, sim.state(), contacts)
        self.history["time"].append(sim.time)
        for key in ENERGY_KEYS:
            self.history[key].append(energy[key])
        self.history["contacts"].append(len(contacts["volume"]))
        self.history["packing_fraction"].append(region.get("packing_fraction"))
        if len(contacts["volume"]):
            self.frame_overlap = max(self.frame_overlap, float(relative_overlaps(contacts, self.volumes).max()))
            self.frame_depth = max(self.frame_depth, float(relative_depths(contacts, self.volumes).max()))
        return energy

    def record(self, wall: float, part: dict, pictures: list[str], checkpoints: list[str]) -> dict:
        """The record of the run up to now, after this part's ``wall`` time [s], with this ``part``
        and its ``pictures`` and ``checkpoints`` (absolute paths)."""
        e = self.earlier or {}
        return finite(
            {
                "version": RUN_RECORD_VERSION,
                "fps": self.fps,
                "history": self.history,
                "frame_contacts": self.frame_contacts,
                "frame_overlap": self.frame_overlap,
                "frame_depth": self.frame_depth,
                "energy_initial": self.energy_initial,
                "wall_time": e.get("wall_time", 0.0) + wall,
                "pictures": [*e.get("pictures", []), *pictures],
                "checkpoints": list(dict.fromkeys([*e.get("checkpoints", []), *checkpoints])),
                "parts": [*e.get("parts", []), part],
            }
        )


def run_record_problem(rec, fps, time_s, dt) -> str | None:
    """What is wrong with the run record ``rec`` of a checkpoint at ``time_s`` for a run at ``fps``, or None."""

    def number(x, lo=-math.inf):
        return isinstance(x, int | float) and not isinstance(x, bool) and x >= lo

    def strings(x):
        return isinstance(x, list) and all(isinstance(v, str) for v in x)

    damaged = "; the file is damaged or was edited: use another checkpoint of the run or rerun"
    if rec.get("version") != RUN_RECORD_VERSION:
        return f"its run record has version {rec.get('version')!r}, this polydem reads {RUN_RECORD_VERSION}{damaged}"
    history = rec.get("history")
    if not isinstance(history, dict) or set(history) != set(HISTORY_KEYS):
        return f"its run record has no frame history with the entries {', '.join(HISTORY_KEYS)}{damaged}"
    contacts = rec.get("frame_contacts")
    frames = len(contacts) if isinstance(contacts, list) else -1
    if frames < 0 or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in contacts):
        return f"frame_contacts of its run record is not a list of contact counts{damaged}"
    for key in HISTORY_KEYS:
        values = history[key]
        if not isinstance(values, list) or len(values) != frames or not all(v is None or number(v) for v in values):
            return f"history.{key} of its run record is not a list of {frames} numbers{damaged}"
    times = history["time"]
    if None in times or any(b <= a for a, b in zip(times, times[1:], strict=False)):
        return f"history.time of its run record is not increasing{damaged}"
    if times and times[-1] > time_s + 0.5 * dt:
        return f"its run record has a frame at t = {times[-1]:.6g} s, after the checkpoint's {time_s:.6g} s{damaged}"
    energy = rec.get("energy_initial")
    if not (
        isinstance(energy, dict) and all(k in energy and (energy[k] is None or number(energy[k])) for k in ENERGY_KEYS)
    ):
        return f"energy_initial of its run record is not a table of energies{damaged}"
    if not (number(rec.get("frame_overlap"), 0.0) and number(rec.get("wall_time"), 0.0)):
        return f"frame_overlap or wall_time of its run record is not a number >= 0{damaged}"
    if not number(rec.get("frame_depth", 0.0), 0.0):
        return f"frame_depth of its run record is not a number >= 0{damaged}"
    if not (strings(rec.get("pictures")) and strings(rec.get("checkpoints"))):
        return f"pictures or checkpoints of its run record is not a list of file names{damaged}"
    parts = rec.get("parts")

    def part(p):
        steps = (p.get("from_step"), p.get("to_step"))
        whole = all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in steps)
        return whole and isinstance(p.get("folder"), str) and number(p.get("wall_time"), 0.0)

    if not (isinstance(parts, list) and parts and all(isinstance(p, dict) and part(p) for p in parts)):
        return f"parts of its run record is not a list of the parts of the run{damaged}"
    if not number(rec.get("fps"), 0.0) or not math.isclose(rec["fps"], fps, rel_tol=1e-12):
        return (
            f"the run recorded its frames at {rec.get('fps')!r} per simulated second, this one would at {fps:g}: its "
            f"frame history and USD time codes would not fit; give --fps {rec.get('fps')!r} (or leave --fps out)"
        )
    return None
