"""The ``[simulation]`` table and its ``[simulation.settle]``: the settings of a run, declared once.

:class:`~polydem.scene.Scene` reads its settings through :func:`read_settings` when it is built and
again when it is validated (they are plain attributes a user may change in between); the loader
checks a file's table against :data:`SIMULATION` and ``Scene.to_dict`` writes it back from it.
"""

from __future__ import annotations

import re
from dataclasses import fields

import numpy as np

from polydem.kernels.precision import PRECISIONS
from polydem.scene.errors import SceneError, did_you_mean
from polydem.scene.schema import Key, Table
from polydem.scene.values import F32_HIGH, F32_MARGIN, read_number, read_string, read_vector, typename
from polydem.settle import SPEED_FRACTION, SettleCriterion

MAX_STEPS = 2**31 - 1
"""Most steps of one run: the simulator counts steps in a 32-bit integer."""

_CRITERION = {f.name: f.default for f in fields(SettleCriterion)}

SETTLE = Table(
    "[simulation.settle]",
    (
        Key(
            "kinetic_fraction",
            range="> 0 and < 1",
            default=_CRITERION["kinetic_fraction"],
            off=None,
            hint="a fraction of the gravitational energy released, e.g. 1e-4; false to check max_speed alone",
        ),
        Key(
            "speed_fraction",
            range="> 0",
            default=_CRITERION["speed_fraction"],
            off=None,
            hint=f"the speed limit as a fraction of sqrt(g r_min), e.g. {SPEED_FRACTION:g}; false for none",
        ),
        Key("max_speed", unit="m/s", range="> 0", hint="largest speed in m/s"),
        Key("hold", unit="s", range=">= 0", default=_CRITERION["hold"], hint="how long it must hold, in s"),
    ),
)
"""The settle criterion (:class:`polydem.SettleCriterion`); ``false`` leaves a fraction out."""


def _dt(value, key, file):
    if isinstance(value, str):
        if value != "auto":
            raise SceneError(f'expected a time step in seconds or "auto", got string {value!r}', key, file)
        return "auto"
    return read_number(value, key, file, positive=True, hint=' (time step in s, or "auto")')


def _gravity(value, key, file) -> tuple:
    g = read_vector(value, 3, key, file)
    if np.abs(g).max() > F32_HIGH:
        # Beyond this even a body's weight is not a float64 number; below it the checks of a run name the k
        # that would carry it.
        raise SceneError(
            f"{g.tolist()} m/s^2 is beyond the accelerations a run computes with (float32's range, kept "
            f"{F32_MARGIN:g} times from its end: components up to {F32_HIGH:.3g}); standard gravity is "
            "[0, 0, -9.81]",
            key,
            file,
        )
    return tuple(g.tolist())


def _device(value, key, file):
    device = read_string(value, key, file, what='a device name such as "cpu" or "cuda:0"')
    if not re.fullmatch(r"cpu|cuda(:\d+)?", device):
        raise SceneError(
            f'unknown device {device!r}{did_you_mean(device, ("cpu", "cuda", "cuda:0")) or "."} Give "cpu", '
            '"cuda" (the default GPU) or "cuda:N" (GPU number N), or leave device out to use the GPU when '
            "there is one",
            key,
            file,
        )
    return device


def _settle(value, key, file) -> SettleCriterion | None:
    if value is False or isinstance(value, SettleCriterion):
        return value or None
    if value is True:
        return SettleCriterion()
    if not isinstance(value, dict):
        raise SceneError(
            "expected a table {kinetic_fraction = 1e-4, speed_fraction = 3e-4, max_speed = ..., hold = 0.02}, got "
            f"{typename(value)}",
            key,
            file,
        )
    SETTLE.check(value, key, file)
    values = SETTLE.read({k.attr: k.from_file(value.get(k.name, k.default)) for k in SETTLE.keys}, key, file)
    if all(values[name] is None for name in ("kinetic_fraction", "speed_fraction", "max_speed")):
        raise SceneError(
            "with kinetic_fraction = false and speed_fraction = false give max_speed (in m/s): with none of them "
            "nothing is checked",
            f"{key}.max_speed",
            file,
        )
    return SettleCriterion(**values)


SIMULATION = Table(
    "[simulation]",
    (
        Key("name", "string", default="scene", hint="a label; in a file the default is the file's name"),
        Key("description", "string", default="", write="changed"),
        Key("dt", "any", unit="s", default="auto", check=_dt, hint='the time step in s, or "auto"'),
        Key("gravity", "vector", unit="m/s^2", default=(0.0, 0.0, -9.81), check=_gravity),
        Key(
            "steps",
            "integer",
            range=f"[1, {MAX_STEPS}]",
            hint=f"number of steps; a run counts them in a 32-bit integer, up to {MAX_STEPS}",
        ),
        Key("duration", unit="s", range="> 0", hint="simulated time in s"),
        Key("device", "string", check=_device),
        Key("precision", "choice", choices=PRECISIONS, what="precision", default="mixed"),
        Key("until_settled", "boolean", write="never"),
        Key("settle", "any", check=_settle, write="never"),
    ),
)
"""The ``[simulation]`` table: the arguments of :class:`Scene` of the same names (``until_settled`` is read by
the loader into ``settle``, which ``Scene.to_dict`` writes as a table of :data:`SETTLE`)."""

SETTING_NAMES = tuple(k.attr for k in SIMULATION.keys if k.name != "until_settled")
"""The arguments and attributes of a Scene that :func:`read_settings` reads: the keys of :data:`SIMULATION` but
``until_settled``, which a file gives instead of a ``settle`` table."""


def read_settings(values: dict, file) -> dict:
    """The checked settings ``values`` (by the attribute names of :data:`SETTING_NAMES`) of a scene."""
    steps, duration = values.get("steps"), values.get("duration")
    if steps is not None and duration is not None:
        raise SceneError(
            f"give either steps or duration, not both (got steps = {steps}, duration = {duration})",
            "simulation.duration",
            file,
        )
    return SIMULATION.read(values, "simulation", file)


def write_settings(scene) -> dict:
    """The ``[simulation]`` table of ``scene`` (a Scene)."""
    table = SIMULATION.write(scene)
    if scene.settle is not None:
        table["settle"] = SETTLE.write(scene.settle)
    return table
