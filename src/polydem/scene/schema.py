"""The scene file's tables, declared once each: every key's kind, unit, default, range and hint.

A :class:`Table` lists the keys of one scene-file table in the order messages list them. Each
:class:`Key` says how its value is read (through the typed readers of :mod:`.values`, so a value
gets the same message whether it came from a file or from Python), what it defaults to, what
``true`` and ``false`` stand for in a file, and how ``Scene.to_dict`` writes it back. From a
table's declaration come the accepted keys with their did-you-mean, the required ones with their
hints, the defaults (also those of the Python signatures), the type and range checks and the
write-back; the checks that relate several keys stay with the code that uses them.

Each table is declared beside the record or method that uses its values (``MATERIAL`` in
:mod:`.materials`, ``OUTPUT`` in :mod:`.output`, ``SIMULATION`` in :mod:`.settings`, ...). This
module and :mod:`.values` import nothing else of the scene package.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from polydem.scene.errors import SceneError
from polydem.scene.values import (
    F32_HIGH,
    F32_LOW,
    F32_MARGIN,
    RADIUS_HIGH,
    RADIUS_LOW,
    as_given,
    check_keys,
    join_key,
    quat_from_axis_angle,
    read_boolean,
    read_choice,
    read_integer,
    read_number,
    read_string,
    read_table,
    read_vector,
)


class _Required:
    """The default of a key a table must give."""

    def __repr__(self) -> str:
        return "REQUIRED"


REQUIRED: Any = _Required()
"""The default of a required key."""

KINDS = ("number", "integer", "boolean", "string", "choice", "vector", "rotation", "any")
"""How a key's value is read: a finite float, an integer, true/false, a string, one of ``choices``, a vector
of ``size`` numbers, a rotation table ``{axis, degrees | radians}`` (read as a quaternion), or anything
(read by the code that uses it, or by ``check``)."""

WRITES = ("set", "changed", "never")
"""When ``Scene.to_dict`` writes a key: when its value is not None, when it differs from the default, never."""

LENGTH = f"> 0 and >= {F32_LOW:.3g} and <= {F32_HIGH:.3g}"
"""The range of a length a run stores (a shape's sizes, a wall's), with :data:`LENGTH_WHY`: beyond it a shape's
volume and inertia are not even float64 numbers; within it the checks of a run name what is out of reach."""

LENGTH_WHY = (
    f" m (a run holds lengths in float32, kept {F32_MARGIN:g} times from the ends of its range; a shape needs a "
    f"bounding radius from {RADIUS_LOW:.2g} to {RADIUS_HIGH:.2g} m)"
)

SPEED = f"[{-F32_HIGH:.3g}, {F32_HIGH:.3g}]"
"""The range of a velocity's or an angular velocity's components, with :data:`SPEED_WHY`."""

SPEED_WHY = f" (a run computes with velocities in float32, kept {F32_MARGIN:g} times from the end of its range)"

_INTERVAL = re.compile(r"^([\[(])\s*([^,\s]+)\s*,\s*([^\])\s]+)\s*([\])])$")
_SIDE = re.compile(r"^(>=|>|<=|<)\s*(\S+)$")


@dataclass(frozen=True)
class Bound:
    """One condition of a key's range: ``low < x < high`` with each end included or not, as its text says.

    An interval (``"(0, 1]"``) is named as a whole in a message ("must be in (0, 1]"); a one-sided bound
    (``"< 1"``) alone ("must be < 1"), and ``"> 0"`` and ``">= 0"`` in the words of :func:`read_number`
    ("must be positive (> 0)", "must not be negative").
    """

    low: float
    low_in: bool
    high: float
    high_in: bool
    words: str

    @classmethod
    def parse(cls, text: str) -> Bound:
        text = text.strip()
        if m := _INTERVAL.match(text):
            return cls(float(m.group(2)), m.group(1) == "[", float(m.group(3)), m.group(4) == "]", f"in {text}")
        if m := _SIDE.match(text):
            op, x = m.group(1), float(m.group(2))
            if op.startswith(">"):
                return cls(x, op == ">=", math.inf, True, text)
            return cls(-math.inf, True, x, op == "<=", text)
        raise ValueError(f"range {text!r} is not like '> 0', '>= 1', '(0, 1]' or '>= 0 and <= 2'")

    def holds(self, v: float) -> bool:
        return (v > self.low or (self.low_in and v == self.low)) and (
            v < self.high or (self.high_in and v == self.high)
        )

    @property
    def sign(self) -> str:
        """``"positive"`` for ``"> 0"``, ``"nonneg"`` for ``">= 0"``, else ""."""
        if self.low == 0.0 and self.high == math.inf:
            return "nonneg" if self.low_in else "positive"
        return ""


@dataclass(frozen=True)
class Key:
    """One key of a scene-file table.

    Attributes:
        name: the key as the file spells it.
        kind: how its value is read (:data:`KINDS`).
        unit: SI unit of a number or vector ("" for none).
        default: its value when left out; :data:`REQUIRED` for a key the table must give, None for an
            optional key without a value.
        range: allowed numbers: ``"> 0"``, ``">= 1"``, ``"(0, 1]"``, ``"[3, 1000]"`` or conditions joined by
            ``" and "`` (``">= 0 and <= 2"``, each with its own message: see :class:`Bound`); "" for any. A
            vector's range holds for each of its components.
        why: the reason for a bound other than 0, e.g. " (m < 1 gives an infinite force at first touch)";
            a message with it leaves ``hint`` out.
        choices: the allowed values of a ``choice``.
        what: the name of a value in messages: "body kind" for a choice, "a file path string" for a string.
        size, label: length and spelling (``[x, y, z]``) of a vector.
        hint: what the key means, for "missing required key" and after a bad value.
        about: the words after a bad value where they differ from ``hint`` ("" for none).
        on, off: what ``true`` and ``false`` stand for in a file (``usd = true``), where they may be given.
        attr: the name of the value in Python (a record's field or an argument), where it differs.
        write: when ``Scene.to_dict`` writes it (:data:`WRITES`); a value equal to ``off`` is written ``false``.
        check: reads the value instead of the kind's reader: ``check(value, key, file) -> value``.
    """

    name: str
    kind: str = "number"
    unit: str = ""
    default: Any = None
    range: str = ""
    why: str = ""
    choices: tuple = ()
    what: str = ""
    size: int = 3
    label: str | None = None
    hint: str = ""
    about: str | None = None
    on: Any = REQUIRED
    off: Any = REQUIRED
    attr: str = ""
    write: str = "set"
    check: Callable | None = field(default=None, compare=False)
    bounds: tuple[Bound, ...] = field(default=(), init=False, compare=False)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"key {self.name!r}: kind {self.kind!r} is not one of {KINDS}")
        if self.write not in WRITES:
            raise ValueError(f"key {self.name!r}: write {self.write!r} is not one of {WRITES}")
        object.__setattr__(self, "bounds", tuple(Bound.parse(t) for t in self.range.split(" and ") if t.strip()))
        if not self.attr:
            object.__setattr__(self, "attr", self.name)

    @property
    def required(self) -> bool:
        return self.default is REQUIRED

    def hint_text(self) -> str:
        """The words after a bad value: `` (hint)``, or ""."""
        about = self.hint if self.about is None else self.about
        return f" ({about})" if about else ""

    def read(self, value, key: str, file=None):
        """The checked value of this key, given as ``value`` at ``key`` (the full dotted key, for messages)."""
        if self.check is not None:
            return self.check(value, key, file)
        kind, hint = self.kind, self.hint_text()
        if kind == "number":
            signs = {b.sign for b in self.bounds}
            v = read_number(value, key, file, positive="positive" in signs, nonneg="nonneg" in signs, hint=hint)
            return self.within(v, key, file, given=value)
        if kind == "integer":
            low = max((b.low for b in self.bounds), default=-math.inf)
            high = min((b.high for b in self.bounds), default=math.inf)
            return read_integer(
                value,
                key,
                file,
                minimum=None if math.isinf(low) else math.ceil(low),
                maximum=None if math.isinf(high) else math.floor(high),
                hint=hint,
            )
        if kind == "boolean":
            return read_boolean(value, key, file)
        if kind == "string":
            return read_string(value, key, file, what=self.what or "a string")
        if kind == "choice":
            return read_choice(value, self.choices, key, file, what=self.what or "value")
        if kind == "vector":
            v = read_vector(value, self.size, key, file, label=self.label)
            for x in v:
                self.within(x, key, file, each=v)
            return v
        if kind == "rotation":
            return read_rotation(value, key, file)
        return value

    def within(self, v: float, key: str, file=None, *, given=None, each=None) -> float:
        """``v`` if it is within the declared range, else the SceneError of the first bound it breaks;
        ``given``: the value as given (for the message), ``each``: the vector ``v`` is a component of."""
        for b in self.bounds:
            if not b.holds(v):
                tail = "" if self.why else self.hint_text()
                if each is not None:
                    got = f"each component must be {b.words}{self.why}, got {each.tolist()}"
                else:
                    got = f"must be {b.words}{self.why}, got {as_given(v if given is None else given)}"
                raise SceneError(got + tail, key, file)
        return v

    def from_file(self, value):
        """The Python value of a file's ``value``: ``on`` for ``true`` and ``off`` for ``false`` where declared."""
        if value is True and self.on is not REQUIRED:
            return self.on
        if value is False and self.off is not REQUIRED:
            return self.off
        return value

    def optional(self, value) -> bool:
        """Whether ``value`` from Python means "not given" (None where the default is None) or "none" (None
        where ``false`` means None)."""
        return value is None and (self.default is None or self.off is None)

    def to_file(self, value):
        """How ``value`` is written in a file (``false`` for ``off``), or :data:`REQUIRED` to leave it out."""
        if self.write == "never" or (self.write == "changed" and _same(value, self.default)):
            return REQUIRED
        if self.off is not REQUIRED and _same(value, self.off):
            return False
        if value is None:
            return REQUIRED
        return value


def _same(a, b) -> bool:
    try:
        return bool(a == b) and type(a) is type(b)
    except ValueError:  # arrays
        return False


@dataclass(frozen=True)
class Table:
    """The declaration of one scene-file table: its keys in the order messages list them.

    Attributes:
        name: how the documentation names it, e.g. ``"[materials.NAME]"``.
        keys: its :class:`Key` records.
    """

    name: str
    keys: tuple[Key, ...]
    names: tuple[str, ...] = field(default=(), init=False, compare=False)
    required: tuple[str, ...] = field(default=(), init=False, compare=False)
    defaults: Mapping[str, Any] = field(default_factory=dict, init=False, compare=False)
    """Each key's default by name (the Python signatures that take the keys read theirs here)."""
    _by_name: dict[str, Key] = field(default_factory=dict, init=False, compare=False, repr=False)

    def __post_init__(self):
        names = tuple(k.name for k in self.keys)
        if len(set(names)) != len(names):
            raise ValueError(f"table {self.name}: a key is declared twice in {names}")
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "required", tuple(k.name for k in self.keys if k.required))
        object.__setattr__(self, "defaults", MappingProxyType({k.name: k.default for k in self.keys}))
        object.__setattr__(self, "_by_name", dict(zip(names, self.keys, strict=True)))

    def __getitem__(self, name: str) -> Key:
        return self._by_name[name]

    def __contains__(self, name) -> bool:
        return name in self._by_name

    def check(self, table: Mapping, where: str | None, file=None, *, context: str = "", extra: tuple = ()):
        """Refuse unknown keys (with did-you-mean and the valid ones) and report a missing required one.

        ``extra``: keys accepted beyond the declared ones (a compound's part also takes its placement).
        """
        hints = {k.name: k.hint for k in self.keys if k.hint}
        allowed = (*self.names, *extra) if extra else self.names
        check_keys(table, allowed, where, file, required=self.required, hints=hints, context=context)

    def arguments(self, table: Mapping, where: str | None, file=None, *, skip: tuple = ()) -> dict:
        """The keyword arguments of a file's table for the Python call that takes it: each given key under its
        ``attr``, with ``true``/``false`` as declared and a rotation table as its quaternion; the keys in
        ``skip`` are left to the caller, those not given to the call's defaults."""
        out = {}
        for name, value in table.items():
            if name in self and name not in skip:
                k = self[name]
                out[k.attr] = (
                    read_rotation(value, join_key(where, name), file) if k.kind == "rotation" else k.from_file(value)
                )
        return out

    def read(self, values: Mapping, where: str | None, file=None) -> dict:
        """The checked values of a Python call's arguments ``values`` (by ``attr``), in the declared order.

        A ``rotation`` key is another spelling of its ``attr`` (a quaternion), which :meth:`arguments` made of it.
        """
        out = {}
        for k in self.keys:
            if k.attr in values and k.kind != "rotation":
                value = values[k.attr]
                out[k.attr] = None if k.optional(value) else k.read(value, join_key(where, k.name), file)
        return out

    def write_rows(self, columns: Mapping[str, list]) -> list[dict]:
        """One table per row of ``columns`` (by ``attr``, plain lists): ``[[bodies]]`` from the scene's arrays."""
        keys = [k for k in self.keys if k.write != "never"]
        rows = zip(*(columns[k.attr] for k in keys), strict=True)
        if all(k.write == "set" and k.off is REQUIRED for k in keys):
            # Each key written unless None: the same tables as write's, at a fraction of its cost per row.
            names = [k.name for k in keys]
            return [{n: v for n, v in zip(names, row, strict=True) if v is not None} for row in rows]
        attrs = [k.attr for k in keys]
        return [self.write(dict(zip(attrs, row, strict=True))) for row in rows]

    def write(self, source) -> dict:
        """The table of a file for ``source`` (a record or a mapping, read by each key's ``attr``)."""
        get = source.get if isinstance(source, Mapping) else lambda name: getattr(source, name)
        out = {}
        for k in self.keys:
            if k.write == "never":
                continue
            value = k.to_file(get(k.attr))
            if value is REQUIRED:
                continue
            if isinstance(value, np.ndarray):
                value = value.tolist()
            out[k.name] = list(value) if isinstance(value, tuple) else value
        return out


ROTATION = Table(
    "rotation",
    (
        Key("axis", "vector", default=REQUIRED),
        Key("degrees", unit="deg"),
        Key("radians", unit="rad"),
    ),
)
"""A ``rotation = {axis = [ax, ay, az], degrees = angle}`` (or ``radians = angle``) table."""


def read_rotation(value, key, file):
    """Quaternion of a ``rotation = {axis = [..], degrees = a}`` (or ``radians = a``) table."""
    value = read_table(value, key, file, what="a table {axis = [ax, ay, az], degrees = angle}")
    ROTATION.check(value, key, file)
    if ("degrees" in value) == ("radians" in value):
        raise SceneError(
            "give the angle as exactly one of degrees or radians, e.g. rotation = {axis = [0, 1, 0], degrees = 20}",
            f"{key}.degrees",
            file,
        )
    axis = ROTATION["axis"].read(value["axis"], f"{key}.axis", file)
    if np.linalg.norm(axis) == 0.0:
        raise SceneError("rotation axis is zero; give a direction such as [0, 0, 1]", f"{key}.axis", file)
    if "degrees" in value:
        angle = math.radians(ROTATION["degrees"].read(value["degrees"], f"{key}.degrees", file))
    else:
        angle = ROTATION["radians"].read(value["radians"], f"{key}.radians", file)
    return quat_from_axis_angle(axis, angle)
