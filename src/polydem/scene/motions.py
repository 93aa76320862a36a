"""Prescribed motions of containers: vibration and taps (``[motions.NAME]``; issue 26).

A :class:`Motion` moves the bodies that name it (a box container's slabs, kinematic bodies) together
along its ``axis``, cycle after cycle, each cycle one period of ``d(s) = A (1 - cos(2 pi f s))``: from
rest in place, up by 2 A and back to rest (kernels/motion.py). Its peak acceleration is
``A (2 pi f)^2``, given as ``amplitude`` A [m] or as ``gamma`` in units of the scene's |g| (the
dimensionless tap intensity of the packing literature). A ``period`` of one cycle (the default) is a
continuous vibration; a longer one is a train of taps with the container at rest between them, the
time the grains have to come to rest before the next.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from polydem.scene.errors import SceneError
from polydem.scene.schema import REQUIRED, Key, Table
from polydem.scene.values import read_vector

MOTION = Table(
    "[motions.NAME]",
    (
        Key("frequency", unit="Hz", range="> 0", default=REQUIRED, hint="cycles per second of the motion, e.g. 30"),
        Key("amplitude", unit="m", range="> 0", hint="A in m: each cycle lifts by 2 A; or give gamma"),
        Key("gamma", range="> 0", hint="peak acceleration A (2 pi f)^2 over |g|; or give amplitude"),
        Key("axis", "vector", default=(0.0, 0.0, 1.0), hint="direction of the motion; normalised"),
        Key("start", unit="s", range=">= 0", default=0.0, hint="time of the first cycle in s"),
        Key("period", unit="s", range="> 0", hint="time from one cycle's start to the next in s; default one cycle"),
        Key("count", "integer", range=">= 0", default=0, hint="number of cycles, 0 for no end"),
    ),
)
"""A ``[motions.NAME]`` table: the fields of :class:`Motion` but its name."""


@dataclass(frozen=True, kw_only=True)
class Motion:
    """A container's prescribed motion (module docstring).

    Attributes:
        name: label, named by the containers and bodies it moves.
        frequency: f [Hz] of each cycle; a cycle lasts 1 / f.
        amplitude: A [m] (each cycle lifts by 2 A), or None where ``gamma`` gives it.
        gamma: peak acceleration over |g| [-], or None where ``amplitude`` is given.
        axis: (3,) unit direction [-].
        start: time of the first cycle [s].
        period: time between the starts of two cycles [s], >= 1 / f; None: 1 / f (a continuous vibration).
        count: number of cycles; 0: no end.
    """

    name: str
    frequency: float
    amplitude: float | None = None
    gamma: float | None = None
    axis: tuple = MOTION.defaults["axis"]
    start: float = MOTION.defaults["start"]
    period: float | None = None
    count: int = MOTION.defaults["count"]

    def __post_init__(self):
        key = f"motions.{self.name}"
        values = MOTION.read({name: getattr(self, name) for name in MOTION.names}, key)
        if (values["amplitude"] is None) == (values["gamma"] is None):
            raise SceneError("give the motion's size as amplitude (in m) or as gamma (over |g|), one of the two",
                             f"{key}.amplitude")  # fmt: skip
        axis = np.asarray(read_vector(values["axis"], 3, f"{key}.axis"), dtype=np.float64)
        norm = float(np.linalg.norm(axis))
        if not norm > 0.0:
            raise SceneError(f"axis {axis.tolist()} has no direction: give a non-zero vector", f"{key}.axis")
        cycle = 1.0 / values["frequency"]
        if values["period"] is not None and values["period"] < cycle * (1.0 - 1e-12):
            raise SceneError(
                f"period {values['period']:g} s is shorter than one cycle ({cycle:g} s at {values['frequency']:g} Hz):"
                f" cycles cannot overlap; give a period of at least {cycle:g} s, or leave it out for a continuous "
                "vibration",
                f"{key}.period",
            )
        for name, value in values.items():
            object.__setattr__(self, name, value)
        object.__setattr__(self, "axis", tuple(float(x) for x in axis / norm))

    @property
    def omega(self) -> float:
        """Angular frequency 2 pi f [rad/s]."""
        return 2.0 * math.pi * self.frequency

    def amplitude_in(self, gravity) -> float:
        """A [m] in a scene of ``gravity`` (3,) [m/s^2]: ``amplitude``, or ``gamma |g| / (2 pi f)^2``."""
        if self.amplitude is not None:
            return float(self.amplitude)
        g = float(np.linalg.norm(np.asarray(gravity, dtype=np.float64)))
        if not g > 0.0:
            raise SceneError(
                "gamma is a peak acceleration over |g|, and the scene has no gravity: give amplitude (in m)",
                f"motions.{self.name}.gamma",
            )
        return self.gamma * g / self.omega**2

    def cycle_period(self) -> float:
        """Time between the starts of two cycles [s]."""
        return 1.0 / self.frequency if self.period is None else float(self.period)

    def to_dict(self) -> dict:
        """The ``[motions.NAME]`` table of a scene file (without the name)."""
        return MOTION.write(self)
