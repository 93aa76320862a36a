"""Protocols of packing experiments run on a :class:`polydem.Simulation` (issue 26).

Tapping: a container that follows a motion of taps (``[motions.NAME]`` with a ``period`` longer than a
cycle and a ``count``; :mod:`polydem.scene.motions`) compacts its grains tap by tap, as in the
experiments of Knight et al. (1995) and Philippe and Bideau (2002). :func:`tap` steps through the taps
and measures the exact packing fraction (:func:`polydem.measures.packing_fraction`) at the end of each
relaxation, just before the next tap lifts the container, with the grains' kinetic energy at that time
(a tap whose grains have not come to rest says so).

Compression: a piston (a kinematic body) that follows a ramp (a set speed) or a servo (a set stress)
motion presses the grains in a container. :func:`compress` steps the run and records, at a set interval,
the piston's displacement, the force the grains push it back with and that force over its area, and the
packing fraction: a stress-strain curve. Several servo walls (six around a sample: isotropic compression)
are recorded together.

Friction annealing: grains poured with low friction pack denser; :func:`anneal` fills (runs until
settled) at ``mu_fill``, then gives the grains their final friction and lets them settle again
(:meth:`polydem.Simulation.set_friction`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["AnnealRecord", "CompressionRecord", "TapRecord", "anneal", "compress", "tap"]


def _measuring_box(grains, box, margin: float):
    """``box`` (a Box, or a function of the grains that returns one), or the box around the free grains moved in
    by ``margin`` grain sizes."""
    from polydem import measures

    if box is not None:
        return box(grains) if callable(box) else box
    around = measures.Box.around(grains)
    d = margin * grains.grain_size()
    try:
        return around.shrunk(d)
    except ValueError:
        size = around.upper - around.lower
        raise ValueError(
            f"a margin of {margin:g} grain sizes ({d:.3g} m) leaves nothing of the box around the grains "
            f"({size[0]:.3g} x {size[1]:.3g} x {size[2]:.3g} m) to measure the packing fraction in; give a smaller "
            "margin (or a box)"
        ) from None


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


def tap(sim, motion: str, box=None, *, margin: float = 2.0, lead: float = 0.1, on_record=None) -> list[TapRecord]:
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
        on_record: called with each :class:`TapRecord` as soon as it is measured (``polydem tap`` prints and
            keeps them, so that a run stopped part-way loses none).

    Returns:
        One :class:`TapRecord` before the first tap (where the call starts before it) and one per tap.
    """
    from polydem import measures

    scene = sim.scene
    m = scene.motion_named(motion, "motion")
    if m.kind != "cycle":
        raise ValueError(f"motion {motion!r} is a {m.kind}: taps are cycles (kind = 'cycle', the default)")
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
        where = _measuring_box(grains, box, margin)
        state = sim.state()
        free = grains.free
        v = np.linalg.norm(np.asarray(state["body_velocity"], dtype=np.float64)[free], axis=1)
        kinetic = float(sim.energy()["kinetic"])
        record = TapRecord(k, float(sim.time), measures.packing_fraction(grains, where), kinetic, float(v.max()))
        records.append(record)
        if on_record is not None:
            on_record(record)
    return records


@dataclass(frozen=True)
class CompressionRecord:
    """The state of a compression at one time.

    Attributes:
        time: simulated time [s].
        displacement: how far the piston has moved along its axis since t = 0 [m].
        velocity: its velocity along the axis [m/s].
        force: the force the grains push it back with along -axis in the last step [N].
        stress: ``force`` over the area (the servo's ``area``, else the piston's area across the axis) [Pa].
        strain: ``displacement`` since the first record over the sample's height along the axis then [-].
        packing_fraction: exact solid fraction of the measuring box [-].
        kinetic: kinetic energy of the free grains [J].

    With several motions (isotropic compression), ``displacement``, ``velocity``, ``force``, ``stress`` and
    ``strain`` are (K,) arrays, one value per motion in the order given.
    """

    time: float
    displacement: float | np.ndarray
    velocity: float | np.ndarray
    force: float | np.ndarray
    stress: float | np.ndarray
    strain: float | np.ndarray
    packing_fraction: float
    kinetic: float


def _piston_motions(sim, motion) -> list[str]:
    # Motion names, from names or driven body indices.
    many = isinstance(motion, list | tuple)
    names = []
    for item in motion if many else [motion]:
        if isinstance(item, int | np.integer):
            name = sim.scene.body_motion.get(int(item))
            if name is None:
                raise ValueError(f"body {int(item)} follows no motion: give a piston driven by a ramp or a servo")
            item = name
        m = sim.scene.motion_named(item, "motion")
        if m.kind == "cycle":
            raise ValueError(f"motion {item!r} is a cycle (vibration, taps): a compression needs a ramp or a servo")
        if item not in sim.scene.body_motion.values():
            raise ValueError(f"motion {item!r} drives no body: give a kinematic body motion = {item!r}")
        names.append(item)
    return names


def compress(sim, motion, duration: float, interval: float, box=None, *, on_record=None) -> list[CompressionRecord]:
    """Run a compression for ``duration`` more seconds and record it every ``interval`` seconds.

    Args:
        sim: a :class:`polydem.Simulation` whose scene drives a piston by a ramp or servo motion.
        motion: the motion's name, or the index of a body it drives; or a list of them (several walls).
        duration: simulated time to run [s].
        interval: time between records [s] (rounded to whole steps); a record is also taken at the start.
        box: the :class:`polydem.measures.Box` of the packing fraction, or a function of the
            :class:`polydem.measures.Grains` at each record that returns it; default the box around the
            free grains (in a container closed by the piston: the sample).
        on_record: called with each :class:`CompressionRecord` as soon as it is taken.

    Returns:
        The :class:`CompressionRecord` at the start and after each interval.
    """
    from polydem import measures

    names = _piston_motions(sim, motion)
    duration, interval = float(duration), float(interval)
    if not (math.isfinite(duration) and duration >= 0.0):
        raise ValueError(f"duration must be a time >= 0 [s], got {duration!r}")
    if not (math.isfinite(interval) and interval > 0.0):
        raise ValueError(f"interval must be a time > 0 [s], got {interval!r}")
    model = sim.model
    rows = [model.motion_names.index(name) for name in names]
    axes = np.array([sim.scene.motions[name].axis for name in names], dtype=np.float64)
    area = np.array([sim.scene.motions[name].area or model.motion_area[k] for name, k in zip(names, rows, strict=True)])
    every = max(1, round(interval / sim.dt))
    end = sim.steps_done + max(0, round(duration / sim.dt))
    records, height = [], None
    while True:
        grains = measures.Grains.from_simulation(sim)
        around = measures.Box.around(grains)
        where = around if box is None else (box(grains) if callable(box) else box)
        travel = sim.current_state.motion_travel.numpy()[rows].astype(np.float64)
        if height is None:
            d0 = travel[:, 0].copy()
            height = np.abs(axes) @ (around.upper - around.lower)
        force = travel[:, 2]
        values = {
            "displacement": travel[:, 0],
            "velocity": travel[:, 1],
            "force": force,
            "stress": np.divide(force, area, out=np.full_like(force, np.nan), where=area > 0.0),
            "strain": (travel[:, 0] - d0) / height,
        }
        if len(names) == 1 and not isinstance(motion, list | tuple):
            values = {k: float(v[0]) for k, v in values.items()}
        kinetic = float(sim.energy()["kinetic"])
        fraction = measures.packing_fraction(grains, where)
        record = CompressionRecord(float(sim.time), **values, packing_fraction=fraction, kinetic=kinetic)
        records.append(record)
        if on_record is not None:
            on_record(record)
        if sim.steps_done >= end:
            return records
        sim.step(min(every, end - sim.steps_done))


@dataclass(frozen=True)
class AnnealRecord:
    """The packing at the end of one stage of :func:`anneal`.

    Attributes:
        stage: "fill" (at the reduced friction) or "final" (after the friction was restored).
        friction: the friction coefficient of the stage [-].
        time: simulated time at its end [s].
        settled: whether the grains came to rest in the time allowed.
        packing_fraction: exact solid fraction of the measuring box [-].
        kinetic: kinetic energy of the free grains [J].
    """

    stage: str
    friction: float
    time: float
    settled: bool
    packing_fraction: float
    kinetic: float


def anneal(
    sim, mu_fill: float, mu_final: float | None, fill_time: float, settle_time: float, *, material=None,
    box=None, margin: float = 2.0, criterion=None, on_record=None,
) -> list[AnnealRecord]:  # fmt: skip
    """Fill at one friction, then restore the final one: below it a denser packing than a fill at the final
    friction, above it a looser one.

    Sets the friction of ``material`` (default every material) to ``mu_fill``, runs until the grains
    have settled (at most ``fill_time`` seconds; :meth:`polydem.Simulation.run_until_settled` with
    ``criterion``), then sets ``mu_final`` (None: each material's friction in the scene) and runs until
    they have settled again (at most ``settle_time``; the kinetic energy compared with the energy released
    since the fill began). The simulation must be built with friction where either value is > 0
    (:meth:`polydem.Simulation.set_friction`).

    Args:
        box: as for :func:`tap`: a :class:`polydem.measures.Box`, or a function of the grains; default
            the box around the free grains moved in by ``margin`` grain sizes.
        on_record: called with each :class:`AnnealRecord` as soon as its stage has ended.

    Returns:
        Two :class:`AnnealRecord`: the end of the fill and the end of the final settling. With
        ``mu_final`` None the final record's ``friction`` is the scene's where the materials set to it share
        one coefficient, else nan.
    """
    from polydem import measures
    from polydem.settle import SettleCheck

    names = sim.scene.material_names if material is None else [material]
    if material is not None and material not in names:
        raise ValueError(f"unknown material {material!r}; the scene's materials are {', '.join(names)}")
    scene_mu = {name: float(sim.scene.materials[name].friction) for name in names}
    records = []
    first = None
    for stage, mu, limit in (("fill", mu_fill, fill_time), ("final", mu_final, settle_time)):
        if mu is None:
            for name, value in scene_mu.items():
                sim.set_friction(value, name)
            mu = scene_mu[names[0]] if len(set(scene_mu.values())) == 1 else math.nan
        else:
            sim.set_friction(mu, material)
        check = sim.settle_check(criterion)
        if first is None:
            first = check
        else:
            # A fresh hold, against the energy released since the fill began: the grains at rest release
            # none after it, and the criterion compares the kinetic energy with the energy released.
            check = SettleCheck(first.criterion, first.gravity_at_start, speed_limit=first.speed_limit)
        result = sim.run_until_settled(limit, check=check)
        grains = measures.Grains.from_simulation(sim)
        where = _measuring_box(grains, box, margin)
        fraction = measures.packing_fraction(grains, where)
        kinetic = float(sim.energy()["kinetic"])
        record = AnnealRecord(stage, float(mu), float(sim.time), bool(result.settled), fraction, kinetic)
        records.append(record)
        if on_record is not None:
            on_record(record)
    return records
