"""When a pile is settled: the criterion of a run that stops once its bodies have come to rest.

A :class:`SettleCriterion` holds when the kinetic energy of the free bodies is below
``kinetic_fraction`` of the gravitational energy released since the start (``E_grav(start) -
E_grav(now)``, which must be > 0), and, when ``max_speed`` is given, the largest speed of a free
body's fastest point (``|v| + |w| r``, r its bounding radius) is below it; the run is settled once
the criterion has held at every check for ``hold`` seconds of simulated time. The checks come every
:data:`polydem.simulation.CHUNK_STEPS` steps, at absolute step counts, so that a resumed run checks
at the steps of the unbroken one.

This module needs no Warp (the scene and ``polydem validate`` use it); the measurements come from
:meth:`polydem.Simulation.settle_measures`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

__all__ = ["SettleCheck", "SettleCriterion", "SettleResult"]


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
            energy released since the start, in (0, 1); None to check ``max_speed`` alone (a scene
            without gravity).
        max_speed: largest speed of any free body's fastest point, ``|v| + |w| r`` [m/s], > 0; None
            to leave it unchecked.
        hold: how long the criterion must hold without a break [s] of simulated time, >= 0.

    Raises:
        ValueError: a value out of range, or neither ``kinetic_fraction`` nor ``max_speed``.
    """

    kinetic_fraction: float | None = 1e-4
    max_speed: float | None = None
    hold: float = 0.02

    def __post_init__(self):
        if self.kinetic_fraction is not None:
            kf = _number(self.kinetic_fraction, "kinetic_fraction", positive=True, below=1.0)
            object.__setattr__(self, "kinetic_fraction", kf)
        if self.max_speed is not None:
            object.__setattr__(self, "max_speed", _number(self.max_speed, "max_speed", positive=True))
        object.__setattr__(self, "hold", _number(self.hold, "hold", nonneg=True))
        if self.kinetic_fraction is None and self.max_speed is None:
            raise ValueError("give kinetic_fraction, max_speed or both: with neither nothing is checked")

    def to_dict(self) -> dict:
        """The criterion as a table (None for a part left unchecked)."""
        return asdict(self)

    def describe(self) -> str:
        parts = []
        if self.kinetic_fraction is not None:
            parts.append(f"kinetic energy < {self.kinetic_fraction:g} of the gravitational energy released")
        if self.max_speed is not None:
            parts.append(f"largest speed < {self.max_speed:g} m/s")
        return " and ".join(parts) + f", held for {self.hold:g} s"

    def check_gravity(self, gravity) -> None:
        """Raises ValueError when the kinetic part is asked for in a scene without gravity."""
        if self.kinetic_fraction is not None and not any(float(g) != 0.0 for g in gravity):
            raise ValueError(
                "the kinetic_fraction criterion compares with the gravitational energy released, and the scene has "
                "no gravity: give max_speed alone (kinetic_fraction=None)"
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
    """

    def __init__(self, criterion: SettleCriterion, gravity_at_start: float, held_since: int | None = None):
        self.criterion = criterion
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
        if c.max_speed is not None:
            ok = ok and self.largest_speed < c.max_speed
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
            "gravity_at_start": self.gravity_at_start,
            "held_since": self.held_since,
            "settled_at": self.settled_at,
        }
