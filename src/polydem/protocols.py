"""Protocols of packing experiments run on a :class:`polydem.Simulation` (issue 26).

Tapping: a container that follows a motion of taps (``[motions.NAME]`` with a ``period`` longer than a
cycle and a ``count``; :mod:`polydem.scene.motions`) compacts its grains tap by tap, as in the
experiments of Knight et al. (1995) and Philippe and Bideau (2002). :func:`tap` steps through the taps
and measures the exact packing fraction (:func:`polydem.measures.packing_fraction`) at the end of each
relaxation, just before the next tap lifts the container, with the grains' kinetic energy at that time
(a tap whose grains have not come to rest says so).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["TapRecord", "tap"]


@dataclass(frozen=True)
class TapRecord:
    """The packing after one tap.

    Attributes:
        tap: 0 before the first tap, then 1, 2, ...
        time: simulated time of the measurement [s].
        packing_fraction: exact solid fraction of the measuring box [-].
        kinetic: kinetic energy of the free grains [J] (near 0 once they rest).
        fastest: the largest speed of a free grain [m/s].
    """

    tap: int
    time: float
    packing_fraction: float
    kinetic: float
    fastest: float


def tap(sim, motion: str, box=None, *, margin: float = 2.0, lead: float = 0.1) -> list[TapRecord]:
    """Step ``sim`` through the taps of its scene's ``motion`` and measure the packing after each.

    Args:
        sim: a :class:`polydem.Simulation` whose scene has ``motion`` driving its container; at the time
            of the call, before the first tap or between two.
        motion: the name of a motion with a ``count`` of taps and a ``period`` longer than a cycle.
        box: the :class:`polydem.measures.Box` to measure in, or a function of the
            :class:`polydem.measures.Grains` at each measurement that returns it; default the box around the
            free grains at each measurement, moved in by ``margin`` grain sizes (away from the walls and the
            loose top).
        lead: how long before the next tap (as a fraction of the rest between taps) to measure.

    Returns:
        One :class:`TapRecord` before the first tap (where the call starts before it) and one per tap.
    """
    from polydem import measures

    scene = sim.scene
    m = scene.motion_named(motion, "motion")
    if m.count < 1:
        raise ValueError(f"motion {motion!r} has no end (count = 0): taps need a count")
    period, cycle = m.cycle_period(), 1.0 / m.frequency
    rest = period - cycle
    if not rest > 0.0:
        raise ValueError(f"motion {motion!r} is a continuous vibration (period = one cycle): taps need a longer period")
    if not 0.0 < lead < 1.0:
        raise ValueError(f"lead must be in (0, 1), a fraction of the rest between taps, got {lead!r}")
    records = []
    # The measuring times: just before each tap starts, and as long after the last tap as the others had.
    times = [m.start + k * period - lead * rest for k in range(m.count + 1)]
    for k, t in enumerate(times):
        if t < sim.time:
            continue
        steps = max(0, math.ceil((t - sim.time) / sim.dt - 1e-9))
        if steps:
            sim.step(steps)
        grains = measures.Grains.from_simulation(sim)
        if box is None:
            where = measures.Box.around(grains).shrunk(margin * grains.grain_size())
        else:
            where = box(grains) if callable(box) else box
        state = sim.state()
        free = grains.free
        v = np.linalg.norm(np.asarray(state["body_velocity"], dtype=np.float64)[free], axis=1)
        kinetic = float(sim.energy()["kinetic"])
        records.append(TapRecord(k, float(sim.time), measures.packing_fraction(grains, where), kinetic, float(v.max())))
    return records
