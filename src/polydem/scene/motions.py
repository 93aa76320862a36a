"""Prescribed motions of containers and pistons: vibration, taps and compression (``[motions.NAME]``; issue 26).

A :class:`Motion` moves the bodies and walls that name it (a box container's slabs, kinematic bodies, plane
and mesh walls) together along its ``axis`` by a displacement d(t), by one of three kinds (plane and mesh
walls follow cycles and ramps):

* ``kind = "cycle"`` (the default): cycle after cycle, each one period of ``d(s) = A (1 - cos(2 pi f s))``:
  from rest in place, up by 2 A and back to rest (kernels/motion.py). Its peak acceleration is
  ``A (2 pi f)^2``, given as ``amplitude`` A [m] or as ``gamma`` in units of the scene's |g| (the
  dimensionless tap intensity of the packing literature). A ``period`` of one cycle (the default) is a
  continuous vibration; a longer one is a train of taps with the container at rest between them, the
  time the grains have to come to rest before the next.
* ``kind = "ramp"``: a piston at a set speed, ``d = speed (t - start)`` for ``duration`` seconds (or until
  it has gone ``distance``; neither: no end), then holding still: compression at a set strain rate.
* ``kind = "servo"``: a wall held at a set stress: it moves along its axis at ``v = gain (F_target - F)``,
  at most ``max_speed``, where F is the force the grains push the driven bodies back with along the axis
  (measured each step on the device) and F_target is ``force`` [N] or ``stress`` [Pa] times ``area``
  (default the driven bodies' area across the axis). The wall comes to rest where the grains push back
  with F_target.

The axis of a ramp or a servo points the way the wall moves to compress (``[0, 0, -1]`` for a lid pressing
down). Both start at ``start``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from polydem.scene.errors import SceneError
from polydem.scene.schema import Key, Table
from polydem.scene.values import read_vector

KINDS = ("cycle", "ramp", "servo")
"""The kinds of motion, in the order of their index on the device (kernels/motion.py)."""

MOTION = Table(
    "[motions.NAME]",
    (
        Key(
            "kind",
            "choice",
            default="cycle",
            choices=KINDS,
            what="motion kind",
            write="changed",
            hint='"cycle" (vibration, taps), "ramp" (a set speed) or "servo" (a set stress)',
        ),
        Key("frequency", unit="Hz", range="> 0", hint="cycle: cycles per second of the motion, e.g. 30"),
        Key("amplitude", unit="m", range="> 0", hint="cycle: A in m: each cycle lifts by 2 A; or give gamma"),
        Key("gamma", range="> 0", hint="cycle: peak acceleration A (2 pi f)^2 over |g|; or give amplitude"),
        Key("axis", "vector", default=(0.0, 0.0, 1.0), hint="direction of the motion (of compression); normalised"),
        Key("start", unit="s", range=">= 0", default=0.0, hint="time the motion starts in s"),
        Key("period", unit="s", range="> 0", hint="cycle: time between cycle starts in s; default one cycle"),
        Key("count", "integer", range=">= 0", default=0, write="changed", hint="cycle: number of cycles, 0 for no end"),
        Key("speed", unit="m/s", range="> 0", hint="ramp: the speed along axis in m/s, e.g. 0.01"),
        Key("duration", unit="s", range="> 0", hint="ramp: how long it moves in s; or give distance; neither: no end"),
        Key("distance", unit="m", range="> 0", hint="ramp: how far it moves in m; or give duration"),
        Key("stress", unit="Pa", range="> 0", hint="servo: the stress to hold, on area; or give force"),
        Key("force", unit="N", range="> 0", hint="servo: the force to hold, the grains pushing back along -axis"),
        Key("area", unit="m^2", range="> 0", hint="servo: the area of stress; default the driven bodies' across axis"),
        Key(
            "gain",
            unit="m/(N s)",
            range="> 0",
            hint="servo: speed per newton of force error; keep gain * stiffness * dt well below 1",
        ),
        Key("max_speed", unit="m/s", range="> 0", hint="servo: the largest speed of the wall in m/s"),
    ),
)
"""A ``[motions.NAME]`` table: the fields of :class:`Motion` but its name."""


# The keys of each kind beyond axis and start, and what a motion of that kind needs (for the messages).
OWN_KEYS = {
    "cycle": ("frequency", "amplitude", "gamma", "period", "count"),
    "ramp": ("speed", "duration", "distance"),
    "servo": ("stress", "force", "area", "gain", "max_speed"),
}
NEEDS = {
    "cycle": "a cycle motion needs frequency (Hz) and amplitude (m) or gamma, and may have period and count",
    "ramp": 'a ramp motion (kind = "ramp") needs speed (m/s), and may have duration (s) or distance (m)',
    "servo": 'a servo motion (kind = "servo") needs stress (Pa) or force (N), gain (m/(N s)) and max_speed (m/s), '
    "and may have area (m^2)",
}


@dataclass(frozen=True, kw_only=True)
class Motion:
    """A prescribed motion (module docstring).

    Attributes:
        name: label, named by the containers and bodies it moves.
        kind: "cycle", "ramp" or "servo".
        frequency: f [Hz] of each cycle; a cycle lasts 1 / f (cycle only).
        amplitude: A [m] (each cycle lifts by 2 A), or None where ``gamma`` gives it.
        gamma: peak acceleration over |g| [-], or None where ``amplitude`` is given.
        axis: (3,) unit direction [-]; for a ramp or a servo, the way it moves to compress.
        start: time the motion starts [s].
        period: time between the starts of two cycles [s], >= 1 / f; None: 1 / f (a continuous vibration).
        count: number of cycles; 0: no end.
        speed: a ramp's speed [m/s].
        duration, distance: how long [s] or how far [m] a ramp moves, or None (at most one is given).
        stress: a servo's target stress [Pa], or None where ``force`` is given.
        force: a servo's target force [N], or None where ``stress`` is given.
        area: the area [m^2] ``stress`` acts on, or None: the driven bodies' area across the axis.
        gain: a servo's speed per newton of force error [m/(N s)].
        max_speed: a servo's largest speed [m/s].
    """

    name: str
    kind: str = MOTION.defaults["kind"]
    frequency: float | None = None
    amplitude: float | None = None
    gamma: float | None = None
    axis: tuple = MOTION.defaults["axis"]
    start: float = MOTION.defaults["start"]
    period: float | None = None
    count: int = MOTION.defaults["count"]
    speed: float | None = None
    duration: float | None = None
    distance: float | None = None
    stress: float | None = None
    force: float | None = None
    area: float | None = None
    gain: float | None = None
    max_speed: float | None = None

    def __post_init__(self):
        key = f"motions.{self.name}"
        values = MOTION.read({name: getattr(self, name) for name in MOTION.names}, key)
        kind = values["kind"]
        for other, names in OWN_KEYS.items():
            for name in names:
                given = values[name] is not None and not (name == "count" and values[name] == 0)
                if other != kind and given:
                    raise SceneError(f"{name} is a key of {other} motions, and this one is kind = {kind!r}: "
                                     f"{NEEDS[kind]}", f"{key}.{name}")  # fmt: skip
        getattr(self, f"_check_{kind}")(values, key)
        axis = np.asarray(read_vector(values["axis"], 3, f"{key}.axis"), dtype=np.float64)
        norm = float(np.linalg.norm(axis))
        if not norm > 0.0:
            raise SceneError(f"axis {axis.tolist()} has no direction: give a non-zero vector", f"{key}.axis")
        for name, value in values.items():
            object.__setattr__(self, name, value)
        object.__setattr__(self, "axis", tuple(float(x) for x in axis / norm))

    @staticmethod
    def _check_cycle(values, key):
        if values["frequency"] is None:
            raise SceneError(f"missing frequency: {NEEDS['cycle']} (or give kind = \"ramp\" or \"servo\")",
                             f"{key}.frequency")  # fmt: skip
        if (values["amplitude"] is None) == (values["gamma"] is None):
            raise SceneError("give the motion's size as amplitude (in m) or as gamma (over |g|), one of the two",
                             f"{key}.amplitude")  # fmt: skip
        cycle = 1.0 / values["frequency"]
        if values["period"] is not None and values["period"] < cycle * (1.0 - 1e-12):
            raise SceneError(
                f"period {values['period']:g} s is shorter than one cycle ({cycle:g} s at {values['frequency']:g} Hz):"
                f" cycles cannot overlap; give a period of at least {cycle:g} s, or leave it out for a continuous "
                "vibration",
                f"{key}.period",
            )

    @staticmethod
    def _check_ramp(values, key):
        if values["speed"] is None:
            raise SceneError(f"missing speed: {NEEDS['ramp']}", f"{key}.speed")
        if values["duration"] is not None and values["distance"] is not None:
            raise SceneError("give how far the ramp goes as duration (in s) or as distance (in m), not both",
                             f"{key}.distance")  # fmt: skip

    @staticmethod
    def _check_servo(values, key):
        if (values["stress"] is None) == (values["force"] is None):
            raise SceneError("give the servo's target as stress (in Pa, on its area) or as force (in N), one of the "
                             "two", f"{key}.stress")  # fmt: skip
        if values["area"] is not None and values["stress"] is None:
            raise SceneError("area is the area the stress acts on: give stress with it, or leave it out with force",
                             f"{key}.area")  # fmt: skip
        for name in ("gain", "max_speed"):
            if values[name] is None:
                raise SceneError(f"missing {name}: {NEEDS['servo']}", f"{key}.{name}")

    @property
    def omega(self) -> float:
        """Angular frequency 2 pi f [rad/s] of a cycle (0 for the other kinds)."""
        return 0.0 if self.frequency is None else 2.0 * math.pi * self.frequency

    def amplitude_in(self, gravity) -> float:
        """A [m] in a scene of ``gravity`` (3,) [m/s^2]: ``amplitude``, or ``gamma |g| / (2 pi f)^2`` (0 for
        the kinds other than cycles)."""
        if self.kind != "cycle":
            return 0.0
        if self.amplitude is not None:
            return float(self.amplitude)
        g = float(np.linalg.norm(np.asarray(gravity, dtype=np.float64)))
        if not g > 0.0:
            raise SceneError(
                "gamma is a peak acceleration over |g|, and the scene has no gravity: give amplitude (in m)",
                f"motions.{self.name}.gamma",
            )
        return self.gamma * g / self.omega**2

    def peak_speed(self, gravity) -> float:
        """The fastest it moves what follows it [m/s]: a cycle's A w, a ramp's speed, a servo's max_speed."""
        if self.kind == "cycle":
            return self.amplitude_in(gravity) * self.omega
        return float(self.speed if self.kind == "ramp" else self.max_speed)

    def cycle_period(self) -> float:
        """Time between the starts of two cycles [s] (1 for the kinds other than cycles)."""
        if self.frequency is None:
            return 1.0
        return 1.0 / self.frequency if self.period is None else float(self.period)

    def ramp_duration(self) -> float:
        """How long a ramp moves [s]: ``duration``, or ``distance / speed``, or inf (no end; 0 for the other kinds)."""
        if self.kind != "ramp":
            return 0.0
        if self.duration is not None:
            return float(self.duration)
        return math.inf if self.distance is None else float(self.distance) / float(self.speed)

    def target_force(self, area: float | None) -> float:
        """A servo's target force [N]: ``force``, or ``stress`` times ``area`` (the motion's own where it has one,
        else the ``area`` given [m^2]: the driven bodies' across the axis)."""
        if self.kind != "servo":
            raise ValueError(f"motion {self.name!r} is a {self.kind}, not a servo: it has no target force")
        if self.force is not None:
            return float(self.force)
        area = self.area if self.area is not None else area
        if area is None or not area > 0.0:
            raise SceneError(
                f"the stress {self.stress:g} Pa needs an area to act on, and the bodies it drives have none across "
                "its axis: give area (in m^2), or force (in N) in place of stress",
                f"motions.{self.name}.area",
            )
        return float(self.stress) * float(area)

    def to_dict(self) -> dict:
        """The ``[motions.NAME]`` table of a scene file (without the name)."""
        return MOTION.write(self)
