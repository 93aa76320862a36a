"""When a pile is settled: the criterion of a run that stops once its bodies have come to rest.

A :class:`SettleCriterion` holds when the kinetic energy of the free bodies is below
``kinetic_fraction`` of the gravitational energy released since the start (``E_grav(start) -
E_grav(now)``, which must be > 0), and the largest speed of a free body's fastest point (``|v| +
|w| r``, r its bounding radius) is below the speed limit; the run is settled once the criterion has
held at every check for ``hold`` seconds of simulated time. The checks come every
:data:`polydem.simulation.CHUNK_STEPS` steps, at absolute step counts, so that a resumed run checks
at the steps of the unbroken one.

The speed limit is ``max_speed`` where given, else ``speed_fraction * sqrt(|g| r_min)``, r_min the
smallest bounding radius of a free body (:func:`grain_radius`, decided with the run's other settings
by :func:`polydem.run_settings.run_settings`). The kinetic part alone is a sum
over the pile, so one grain in N may move sqrt(N) times faster than the mean it allows: a pile of
27 cubes of 1 cm passed it with a grain at 3.5 cm/s and, in the next steps, a grain's net force at
18% of its weight (a wall's push swung by 30% on an older main). The speed limit takes its scale
from the model: ``sqrt(g r)`` is the speed of a grain moving under gravity, and the slowest motions
that outlast the impacts (a grain rocking on an edge, creeping, a column swaying) have frequencies
near ``sqrt(g / r)``, so a grain at a fraction f of ``sqrt(g r)`` carries a net force of the order
of f times its weight. Measured on the pile of tests/test_settled_pile.py (14 cubes of 1 cm): at
f = 1e-3 the worst grain's net force in the 200 steps after the stop reached 1.06% of its weight
in one step with an earlier state of the contact kernels (0.07% with the current ones), at 3e-4 at
most 0.12% (0.05%). The default :data:`SPEED_FRACTION`, 3e-4 (0.087 mm/s for cubes of 1 cm, 0.87 mm/s for
blocks of 1 m), keeps that margin for 5-20% more simulated time than 1e-3 (0.146 s against 0.139 s;
0.087 s without a speed limit).

This module needs no Warp (the scene and ``polydem validate`` use it); the measurements come from
:meth:`polydem.Simulation.settle_measures`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from polydem.run_settings import RunSettings

__all__ = ["SPEED_FRACTION", "SettleCheck", "SettleCriterion", "SettleResult", "grain_radius"]

#: Default speed limit as a fraction of ``sqrt(|g| r_min)`` (see the module docstring).
SPEED_FRACTION = 3e-4


def grain_radius(settings: RunSettings) -> float:
    """The smallest bounding radius of a free body [m] (the size in the default speed limit), of the
    scene whose :class:`~polydem.run_settings.RunSettings` are ``settings``.

    Raises:
        ValueError: the scene has no free bodies.
    """
    if settings.radius_min is None:
        raise ValueError("the scene has no free bodies: there is nothing to settle")
    return settings.radius_min


def _number(value, name, *, positive=False, nonneg=False, below=None):
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    if positive and v <= 0.0:
        raise ValueError(f"{name} must be > 0, got {v:g}")
    if nonneg and v < 0.0:
        raise ValueError(f"{name} must be >= 0, got {v:g}")
    if below is not None and v >= below:
        raise ValueError(f"{name} must be < {below:g}, got {v:g}")
    return v


@dataclass(frozen=True)
class SettleCriterion:
    """When a run counts as settled (see :mod:`polydem.settle`).

    Args:
        kinetic_fraction: kinetic energy of the free bodies below this fraction of the gravitational
            energy released since the start, in (0, 1); None to check the speed alone (a scene
            without gravity).
        max_speed: largest speed of any free body's fastest point, ``|v| + |w| r`` [m/s], > 0; it
            replaces the limit of ``speed_fraction``. None: the limit is ``speed_fraction``'s.
        hold: how long the criterion must hold without a break [s] of simulated time, >= 0.
        speed_fraction: without ``max_speed``, the speed limit is this fraction of ``sqrt(|g|
            r_min)`` (:func:`grain_radius`), > 0; None (with no ``max_speed``) to leave the speed
            unchecked.

    Raises:
        ValueError: a value out of range, or nothing to check.
    """

    kinetic_fraction: float | None = 1e-4
    max_speed: float | None = None
    hold: float = 0.02
    speed_fraction: float | None = SPEED_FRACTION

    def __post_init__(self):
        if self.kinetic_fraction is not None:
            kf = _number(self.kinetic_fraction, "kinetic_fraction", positive=True, below=1.0)
            object.__setattr__(self, "kinetic_fraction", kf)
        if self.max_speed is not None:
            object.__setattr__(self, "max_speed", _number(self.max_speed, "max_speed", positive=True))
        object.__setattr__(self, "hold", _number(self.hold, "hold", nonneg=True))
        if self.speed_fraction is not None:
            object.__setattr__(self, "speed_fraction", _number(self.speed_fraction, "speed_fraction", positive=True))
        if self.kinetic_fraction is None and self.max_speed is None and self.speed_fraction is None:
            raise ValueError("give kinetic_fraction, max_speed or speed_fraction: with none of them nothing is checked")

    @property
    def scaled_speed(self) -> bool:
        """Whether the speed limit comes from ``speed_fraction`` (the scene's g and grain size)."""
        return self.max_speed is None and self.speed_fraction is not None

    def speed_limit(self, gravity, radius: float) -> float | None:
        """The speed limit [m/s] for gravity (3,) [m/s^2] and grains of smallest bounding radius
        ``radius`` [m]: ``max_speed`` where given, else ``speed_fraction * sqrt(|g| radius)``; None
        when the speed is unchecked. Raises ValueError for a scaled limit without gravity."""
        if self.max_speed is not None:
            return self.max_speed
        if self.speed_fraction is None:
            return None
        self.check_gravity(gravity)
        g = math.sqrt(sum(float(c) ** 2 for c in gravity))
        return self.speed_fraction * math.sqrt(g * float(radius))

    def speed_limit_of(self, scene, settings: RunSettings | None = None) -> float | None:
        """:meth:`speed_limit` for the gravity and the free bodies of ``scene`` (a polydem.Scene), whose
        ``settings`` (a :class:`~polydem.run_settings.RunSettings`; default: decided from ``scene``) give
        the grain size."""
        if not self.scaled_speed:
            return self.max_speed
        self.check_gravity(scene.gravity)
        if settings is None:
            from polydem.run_settings import run_settings  # it imports the scene package, which imports this

            settings = run_settings(scene)
        return self.speed_limit(scene.gravity, grain_radius(settings))

    def to_dict(self) -> dict:
        """The criterion as a table (None for a part left unchecked)."""
        return asdict(self)

    def describe(self, scene=None) -> str:
        """In words; with ``scene``, the speed limit of ``speed_fraction`` in m/s too."""
        parts = []
        if self.kinetic_fraction is not None:
            parts.append(f"kinetic energy < {self.kinetic_fraction:g} of the gravitational energy released")
        if self.max_speed is not None:
            parts.append(f"largest speed < {self.max_speed:g} m/s")
        elif self.speed_fraction is not None:
            scale = f"{self.speed_fraction:g} sqrt(g r_min)"
            if scene is not None:
                try:
                    scale = f"{self.speed_limit_of(scene):.3g} m/s = {scale}"
                except ValueError:
                    pass
            parts.append(f"largest speed < {scale}")
        return " and ".join(parts) + f", held for {self.hold:g} s"

    def check_gravity(self, gravity) -> None:
        """Raises ValueError when a part that needs gravity is asked for in a scene without it: the
        kinetic part, or the speed limit of ``speed_fraction`` (without ``max_speed``)."""
        if any(float(g) != 0.0 for g in gravity):
            return
        if self.kinetic_fraction is not None:
            raise ValueError(
                "the kinetic_fraction criterion compares with the gravitational energy released, and the scene has "
                "no gravity: give max_speed alone (kinetic_fraction=None)"
            )
        if self.scaled_speed:
            raise ValueError(
                "the speed_fraction criterion scales with sqrt(g r_min), and the scene has no gravity: give "
                "max_speed (in m/s)"
            )


@dataclass(frozen=True)
class SettleResult:
    """What :meth:`polydem.Simulation.run_until_settled` found.

    Attributes:
        settled: whether the criterion held for ``hold`` before the maximum duration.
        time: simulated time at which the run stopped [s] (settled: when the criterion had held for
            ``hold``; else the maximum).
        held_from: simulated time of the first check of the stretch in which the criterion held
            without a break [s] (None when it did not hold at the last check).
        steps: steps taken by the call; steps_done: the simulation's step count at the end.
        wall: wall time of the call [s].
        kinetic: kinetic energy of the free bodies at the last check [J].
        released: gravitational energy released since the start [J] at the last check.
        largest_speed: largest ``|v| + |w| r`` of a free body at the last check [m/s].
        speed_limit: the speed limit of the criterion [m/s] (None: the speed was unchecked).
    """

    settled: bool
    time: float
    held_from: float | None
    steps: int
    steps_done: int
    wall: float
    kinetic: float
    released: float
    largest_speed: float
    speed_limit: float | None = None

    @property
    def kinetic_fraction(self) -> float | None:
        """``kinetic / released`` at the last check (None when nothing was released)."""
        return self.kinetic / self.released if self.released > 0.0 else None


class SettleCheck:
    """The running check of a criterion: the reference gravitational energy and the step from which
    the criterion has held. Kept in a run's checkpoints so that a resumed run continues it.

    Args:
        criterion: the :class:`SettleCriterion`.
        gravity_at_start: gravitational energy of the free bodies at the start [J].
        held_since: step of the first check of the current unbroken stretch (None: not holding).
        speed_limit: the criterion's speed limit in the scene [m/s], ``criterion.speed_limit_of(scene)``;
            needed when it comes from ``speed_fraction``, else it must be ``criterion.max_speed``.

    Raises:
        ValueError: ``speed_limit`` missing where the criterion scales it, or not the criterion's.
    """

    def __init__(
        self,
        criterion: SettleCriterion,
        gravity_at_start: float,
        held_since: int | None = None,
        *,
        speed_limit: float | None = None,
    ):
        if criterion.scaled_speed:
            if speed_limit is None or not (math.isfinite(speed_limit) and speed_limit > 0.0):
                raise ValueError(
                    f"the criterion's speed limit is speed_fraction * sqrt(g r_min): give speed_limit > 0 [m/s], "
                    f"criterion.speed_limit_of(scene), got {speed_limit!r}"
                )
        elif speed_limit is not None and speed_limit != criterion.max_speed:
            raise ValueError(f"speed_limit {speed_limit!r} is not the criterion's max_speed {criterion.max_speed!r}")
        self.criterion = criterion
        self.speed_limit = float(speed_limit) if criterion.scaled_speed else criterion.max_speed
        self.gravity_at_start = float(gravity_at_start)
        self.held_since = held_since
        self.kinetic = math.nan
        self.released = math.nan
        self.largest_speed = math.nan
        self.settled_at: int | None = None

    def holds(self, kinetic: float, gravity: float, largest_speed: float) -> bool:
        """Whether the criterion holds for these measurements (which it keeps for the report)."""
        c = self.criterion
        self.kinetic, self.largest_speed = float(kinetic), float(largest_speed)
        self.released = self.gravity_at_start - float(gravity)
        ok = True
        if c.kinetic_fraction is not None:
            ok = self.released > 0.0 and self.kinetic < c.kinetic_fraction * self.released
        if self.speed_limit is not None:
            ok = ok and self.largest_speed < self.speed_limit
        return ok

    def update(self, step: int, dt: float, kinetic: float, gravity: float, largest_speed: float) -> bool:
        """Check at ``step``; returns whether the run is now settled (held for ``hold``)."""
        if not self.holds(kinetic, gravity, largest_speed):
            self.held_since = None
            return False
        if self.held_since is None:
            self.held_since = int(step)
        # Step counts, not float times: a resumed run decides as the unbroken one.
        if (step - self.held_since) * dt >= self.criterion.hold * (1.0 - 1e-12):
            self.settled_at = int(step)
            return True
        return False

    @property
    def kinetic_fraction(self) -> float | None:
        return self.kinetic / self.released if self.released > 0.0 else None

    def record(self) -> dict:
        """What a checkpoint keeps of the check."""
        return {
            "criterion": self.criterion.to_dict(),
            "speed_limit": self.speed_limit,
            "gravity_at_start": self.gravity_at_start,
            "held_since": self.held_since,
            "settled_at": self.settled_at,
        }
