"""Host-side description of a simulation: materials, shapes, bodies and walls.

Data flows one way: a scene file (TOML) or Python calls -> :class:`Scene` -> ``Model``/``State``
(device arrays). A Scene holds only numpy arrays and plain Python objects; it never touches Warp.
Every user error raises :class:`SceneError`, which names the file (if any), the offending key
(e.g. ``bodies[3].material``) and says how to fix it.

Units are SI throughout: m, s, kg, rad (the scene file also takes ``degrees`` where it says so).
Quaternions are ``[x, y, z, w]`` (Warp's order) and must be unit quaternions.

Poses. A :class:`~polydem.ConvexShape` lives in its *body frame* (origin at the centroid, axes along
the principal axes of inertia), which in general is not the frame its points were given in (the
*input frame*; ``shape.input_transform`` maps body -> input coordinates: ``x_in = R_in x_b + t_in``).
Users place a shape by its input frame: ``position`` is where the input-frame origin goes and
``orientation`` rotates the input axes. So a box of size (0.3, 0.1, 0.2) with the identity
orientation has its 0.3 m edge along world x, and a mesh placed at the origin sits exactly where it
is in its file. For every generated shape except ``rock`` the input origin is the centroid. The
scene stores the pose of the body frame, which is what the simulator integrates::

    body_position    = position + R(orientation) @ t_in        (the centre of mass) [m]
    body_orientation = orientation * q(R_in)                     (body frame -> world)

``velocity`` is the velocity of the centre of mass [m/s] and ``angular_velocity`` is in world axes
[rad/s], whichever frame the pose was given in.

Body kinds: ``free`` bodies move under gravity and contacts; ``fixed`` bodies never move (their
velocities must be zero); ``kinematic`` bodies move with their prescribed (constant) velocity and
angular velocity and are not pushed by contacts.
"""

from __future__ import annotations

import difflib
import math
import numbers
import tomllib
from dataclasses import dataclass, field, fields
from os import PathLike
from pathlib import Path

import numpy as np

from polydem.shapes import ConvexShape

__all__ = [
    "Body",
    "KINDS",
    "KIND_FIXED",
    "KIND_FREE",
    "KIND_KINEMATIC",
    "LAWS",
    "Material",
    "PairMaterial",
    "PlaneWall",
    "Scene",
    "SceneError",
    "SHAPE_TYPES",
    "pair_material",
    "quat_from_axis_angle",
    "quat_to_matrix",
]

LAWS = ("linear", "hertz", "power")
"""Contact laws W(V): linear W = k V; hertz W = 2/3 k V^1.5; power W = k V^m / m."""

KINDS = ("free", "fixed", "kinematic")
"""Body kinds; the integer code stored in :attr:`Scene.body_kind` is the index in this tuple."""
KIND_FREE, KIND_FIXED, KIND_KINEMATIC = 0, 1, 2

SHAPE_TYPES = (
    "box",
    "tetrahedron",
    "octahedron",
    "dodecahedron",
    "icosahedron",
    "prism",
    "rock",
    "sphere",
    "mesh",
    "points",
)
"""Shape ``type`` values of a scene file's ``[shapes.NAME]`` tables."""

QUAT_TOL = 1e-6
"""Largest accepted | |q| - 1 | of an orientation quaternion; accepted ones are normalised exactly."""

_LAW_UNITS = {"linear": "Pa", "hertz": "J/m^4.5", "power": "J/m^(3m)"}
_MAX_LISTED = 20


# ---------------------------------------------------------------------- errors


class SceneError(ValueError):
    """A user error in a scene: bad value, unknown name, malformed scene file.

    Attributes:
        message: what is wrong and how to fix it.
        key: where, as a dotted path into the scene file, e.g. ``"bodies[3].material"`` or
            ``"materials.steel.k"``; None when the whole file is concerned.
        file: the scene file (as given), or None for scenes built in Python.

    ``str(err)`` reads ``"FILE: KEY: MESSAGE"``, leaving out the parts that are None.
    """

    def __init__(self, message: str, key: str | None = None, file: str | PathLike | None = None):
        super().__init__(message)
        self.message = message
        self.key = key
        self.file = file

    def __str__(self) -> str:
        parts = [str(p) for p in (self.file, self.key) if p not in (None, "")]
        return ": ".join([*parts, self.message])

    def __reduce__(self):
        return (type(self), (self.message, self.key, self.file))


def _did_you_mean(word, candidates) -> str:
    if not isinstance(word, str):
        return ""
    close = difflib.get_close_matches(word, [str(c) for c in candidates], n=3, cutoff=0.6)
    if not close:
        return ""
    return "; did you mean " + " or ".join(repr(c) for c in close) + "?"


def _listing(names) -> str:
    names = [str(n) for n in names]
    if len(names) > _MAX_LISTED:
        return ", ".join(names[:_MAX_LISTED]) + f", ... ({len(names)} in all)"
    return ", ".join(names)


def _unknown_name(word, known, what: str, how: str) -> str:
    """Message for an unknown name: did-you-mean plus the known names, or how to define one."""
    known = list(known)
    if not known:
        return f"unknown {what} {word!r}: no {what}s are defined; {how}"
    return f"unknown {what} {word!r}{_did_you_mean(word, known) or '.'} Known {what}s: {_listing(known)}"


# ---------------------------------------------------------------------- value checks


def _typename(v) -> str:
    """How a value reads in an error message, in TOML's words."""
    if isinstance(v, bool | np.bool_):
        return f"boolean {str(bool(v)).lower()}"
    if isinstance(v, str):
        return f"string {v!r}"
    if isinstance(v, numbers.Integral):
        return f"integer {int(v)}"
    if isinstance(v, numbers.Real):
        return f"float {float(v)!r}"
    if isinstance(v, dict):
        return "table {" + ", ".join(str(k) for k in list(v)[:5]) + ("}" if len(v) <= 5 else ", ...}")
    if isinstance(v, list | tuple):
        return f"array of length {len(v)}"
    if isinstance(v, np.ndarray):
        return f"array of shape {v.shape}"
    if v is None:
        return "nothing (None)"
    return f"{type(v).__name__} {v!r}"


def _is_number(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool | np.bool_)


def _number(value, key, file=None, *, positive=False, nonneg=False, hint="") -> float:
    """A finite float; ``positive`` requires > 0 and ``nonneg`` >= 0."""
    if not _is_number(value):
        raise SceneError(f"expected a number, got {_typename(value)}{hint}", key, file)
    v = float(value)
    if not math.isfinite(v):
        raise SceneError(f"expected a finite number, got {v}{hint}", key, file)
    if positive and v <= 0.0:
        raise SceneError(f"must be positive (> 0), got {v:g}{hint}", key, file)
    if nonneg and v < 0.0:
        raise SceneError(f"must not be negative, got {v:g}{hint}", key, file)
    return v


def _integer(value, key, file=None, *, minimum=None, maximum=None, hint="") -> int:
    """An integer (integral floats such as 3.0 are accepted) within [minimum, maximum]."""
    if isinstance(value, numbers.Integral) and not isinstance(value, bool | np.bool_):
        v = int(value)
    elif _is_number(value) and math.isfinite(float(value)) and float(value).is_integer():
        v = int(value)
    else:
        raise SceneError(f"expected an integer, got {_typename(value)}{hint}", key, file)
    if minimum is not None and v < minimum:
        raise SceneError(f"must be an integer >= {minimum}, got {v}{hint}", key, file)
    if maximum is not None and v > maximum:
        raise SceneError(f"must be an integer <= {maximum}, got {v}{hint}", key, file)
    return v


def _boolean(value, key, file=None) -> bool:
    if not isinstance(value, bool | np.bool_):
        raise SceneError(f"expected true or false, got {_typename(value)}", key, file)
    return bool(value)


def _string(value, key, file=None, *, what="a string") -> str:
    if not isinstance(value, str):
        raise SceneError(f"expected {what}, got {_typename(value)}", key, file)
    return value


def _choice(value, choices, key, file=None, *, what="value") -> str:
    choices = tuple(choices)
    if not isinstance(value, str):
        raise SceneError(f"expected a {what} name (one of {', '.join(choices)}), got {_typename(value)}", key, file)
    if value not in choices:
        raise SceneError(
            f"unknown {what} {value!r}{_did_you_mean(value, choices) or '.'} Valid {what}s: {', '.join(choices)}",
            key,
            file,
        )
    return value


_LABELS = {3: "[x, y, z]", 4: "[x, y, z, w]"}


def _vector(value, n, key, file=None, *, label=None) -> np.ndarray:
    """A finite float64 vector of length n, with a precise message for each way it can be wrong."""
    label = label or _LABELS.get(n, f"{n} numbers")
    if isinstance(value, np.ndarray):
        if value.shape != (n,):
            raise SceneError(f"expected {n} numbers {label}, got an array of shape {value.shape}", key, file)
        try:
            arr = value.astype(np.float64)
        except (TypeError, ValueError):
            raise SceneError(f"expected {n} numbers {label}, got an array of {value.dtype}", key, file) from None
    elif isinstance(value, list | tuple):
        if len(value) != n:
            raise SceneError(f"expected {n} numbers {label}, got {len(value)}: {list(value)!r}", key, file)
        for i, x in enumerate(value):
            if not _is_number(x):
                raise SceneError(f"expected a number at position {i} of {label}, got {_typename(x)}", key, file)
        arr = np.array(value, dtype=np.float64)
    else:
        raise SceneError(f"expected an array of {n} numbers {label}, got {_typename(value)}", key, file)
    if not np.all(np.isfinite(arr)):
        raise SceneError(f"expected finite numbers, got {arr.tolist()}", key, file)
    return arr


def _rows(value, width, key, file=None, *, n=None) -> np.ndarray:
    """An (n, width) float64 array; a single row of shape (width,) is broadcast to n rows."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise SceneError(
            f"expected an array of shape (N, {width}) of numbers, got {_typename(value)}: {exc}", key, file
        ) from None
    if arr.ndim == 1 and arr.shape[0] == width:
        arr = arr[None, :] if n is None else np.broadcast_to(arr, (n, width))
    if arr.ndim != 2 or arr.shape[1] != width or (n is not None and arr.shape[0] != n):
        want = f"({'N' if n is None else n}, {width})"
        raise SceneError(
            f"expected an array of shape {want} (or ({width},) for all rows), got shape {arr.shape}", key, file
        )
    return arr  # may be a broadcast view; callers copy it into their own storage


def _check_keys(table, allowed, key, file=None, *, required=(), hints=None, context=""):
    """Reject unknown keys (with did-you-mean and the valid list) and report missing required ones."""
    for k in table:
        if k not in allowed:
            raise SceneError(
                f"unknown key {k!r}{_did_you_mean(k, allowed) or '.'} Valid keys{context}: {', '.join(allowed)}",
                _join(key, k),
                file,
            )
    for k in required:
        if k not in table:
            hint = (hints or {}).get(k, "")
            raise SceneError(f"missing required key {k!r}{' (' + hint + ')' if hint else ''}", _join(key, k), file)


def _table(value, key, file=None, *, what="a table"):
    if not isinstance(value, dict):
        raise SceneError(f"expected {what}, got {_typename(value)}", key, file)
    return value


def _join(prefix, k) -> str:
    return f"{prefix}.{k}" if prefix else str(k)


# ---------------------------------------------------------------------- quaternions (xyzw)


def _quat_mul(a, b):
    """Hamilton product of (..., 4) xyzw quaternions."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def _quat_conj(q):
    q = np.array(q, dtype=np.float64)
    q[..., :3] *= -1.0
    return q


def _cross(a, b):
    """Row-wise cross product of (..., 3) arrays (faster than np.cross for large N)."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], axis=-1)


def _quat_rotate(q, v):
    """Rotate (..., 3) vectors by (..., 4) unit quaternions."""
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    u, w = q[..., :3], q[..., 3:4]
    t = 2.0 * _cross(u, v)
    return v + w * t + _cross(u, t)


def _quat_from_matrix(r) -> np.ndarray:
    """Unit xyzw quaternion of a 3x3 rotation matrix (Shepperd's method)."""
    r = np.asarray(r, dtype=np.float64)
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
    q = np.array(q)
    return q / np.linalg.norm(q)


def quat_to_matrix(q) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) unit xyzw quaternions."""
    q = np.asarray(q, dtype=np.float64)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )


def quat_from_axis_angle(axis, angle: float) -> np.ndarray:
    """Unit xyzw quaternion of a rotation by ``angle`` [rad] about ``axis`` (any non-zero length)."""
    a = _vector(list(axis) if not isinstance(axis, np.ndarray) else axis, 3, "axis")
    n = float(np.linalg.norm(a))
    if n == 0.0:
        raise SceneError("rotation axis is zero; give a non-zero direction such as [0, 0, 1]", "axis")
    angle = _number(angle, "angle")
    return np.concatenate([a / n * math.sin(0.5 * angle), [math.cos(0.5 * angle)]])


def _check_quats(q: np.ndarray, rowkey, file) -> np.ndarray:
    """Validate (N, 4) quaternions (zero, non-unit beyond QUAT_TOL) and return them normalised."""
    norms = np.sqrt(np.einsum("ij,ij->i", q, q))
    bad = np.flatnonzero(~(np.abs(norms - 1.0) <= QUAT_TOL))
    if bad.size:
        i = int(bad[0])
        given = ", ".join(f"{x:.9g}" for x in q[i])
        if norms[i] == 0.0:
            raise SceneError(
                f"orientation [{given}] is zero; give a unit quaternion [x, y, z, w], "
                "e.g. [0, 0, 0, 1] for no rotation",
                rowkey(i),
                file,
            )
        unit = ", ".join(f"{x:.12g}" for x in q[i] / norms[i])
        raise SceneError(
            f"orientation [{given}] is not a unit quaternion (norm {norms[i]:.9g}, allowed 1 +- {QUAT_TOL:g}); "
            f"quaternions are [x, y, z, w] with x^2 + y^2 + z^2 + w^2 = 1. Normalised it is [{unit}]; or give "
            "rotation = {axis = [ax, ay, az], degrees = angle} in a scene file (quat_from_axis_angle() in Python)",
            rowkey(i),
            file,
        )
    return q / norms[:, None]


# ---------------------------------------------------------------------- materials


_MATERIAL_HINTS = {
    "density": "density in kg/m^3, e.g. density = 7800.0 for steel",
    "law": "contact law: law = 'linear', 'hertz' or 'power'",
    "k": "contact stiffness, e.g. k = 1.0e10 (Pa for linear, J/m^4.5 for hertz, J/m^(3m) for power)",
    "m": "power-law exponent, m >= 1",
    "restitution": "coefficient of restitution e in (0, 1], e.g. restitution = 0.5",
    "friction": "Coulomb friction coefficient mu >= 0, e.g. friction = 0.3",
    "tangential_stiffness": "tangential spring stiffness in N/m, or leave it out to have the simulator derive it",
}


@dataclass(frozen=True, kw_only=True)
class Material:
    """Bulk and contact properties of a material (keyword-only fields, validated on construction).

    Attributes:
        name: label, referenced by bodies and walls.
        density: mass density [kg/m^3], > 0.
        law: contact energy W(V) of the overlap volume V [m^3]: ``"linear"`` W = k V; ``"hertz"``
            W = 2/3 k V^1.5; ``"power"`` W = k V^m / m.
        k: contact stiffness, > 0; units depend on the law: linear Pa (= J/m^3), hertz J/m^4.5,
            power J/m^(3m).
        restitution: normal coefficient of restitution e in (0, 1] [-] (1 = elastic).
        friction: Coulomb friction coefficient mu >= 0 [-].
        m: exponent of the power law, >= 1 (m < 1 gives an infinite force at first touch); only for
            ``law = "power"``, None otherwise.
        tangential_stiffness: tangential (friction) spring stiffness [N/m], > 0, or None to let the
            simulator derive it from the normal stiffness.
    """

    name: str
    density: float
    law: str
    k: float
    restitution: float
    friction: float
    m: float | None = None
    tangential_stiffness: float | None = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise SceneError(f"material name must be a non-empty string, got {_typename(self.name)}", "materials")
        key = f"materials.{self.name}"
        h = _MATERIAL_HINTS
        law = _choice(self.law, LAWS, f"{key}.law", what="contact law")
        density = _number(self.density, f"{key}.density", positive=True, hint=f" ({h['density']})")
        k = _number(self.k, f"{key}.k", positive=True, hint=f" (stiffness in {_LAW_UNITS[law]} for law = {law!r})")
        e = _number(self.restitution, f"{key}.restitution", hint=f" ({h['restitution']})")
        if not 0.0 < e <= 1.0:
            raise SceneError(f"must be in (0, 1], got {e:g} ({h['restitution']})", f"{key}.restitution")
        mu = _number(self.friction, f"{key}.friction", nonneg=True, hint=f" ({h['friction']})")
        m = self.m
        if law == "power":
            if m is None:
                raise SceneError("law = 'power' needs the exponent m (W = k V^m / m), e.g. m = 2.0", f"{key}.m")
            m = _number(m, f"{key}.m", hint=f" ({h['m']})")
            if m < 1.0:
                raise SceneError(f"must be >= 1 (m < 1 gives an infinite force at first touch), got {m:g}", f"{key}.m")
        elif m is not None:
            raise SceneError(
                f"m is only used by law = 'power'; law = {law!r} has the fixed exponent "
                f"{1.0 if law == 'linear' else 1.5:g}: remove m or use law = 'power'",
                f"{key}.m",
            )
        kt = self.tangential_stiffness
        if kt is not None:
            kt = _number(kt, f"{key}.tangential_stiffness", positive=True, hint=f" ({h['tangential_stiffness']})")
        for name, value in (
            ("law", law),
            ("density", density),
            ("k", k),
            ("restitution", e),
            ("friction", mu),
            ("m", m),
            ("tangential_stiffness", kt),
        ):
            object.__setattr__(self, name, value)

    @property
    def exponent(self) -> float:
        """Exponent m of W = k V^m / m: 1 for linear, 1.5 for hertz, ``m`` for power."""
        return {"linear": 1.0, "hertz": 1.5}.get(self.law, self.m)

    def contact_law(self):
        """This material's :class:`polydem.contact.ContactLaw` (for contacts with itself)."""
        from polydem.contact import ContactLaw  # imports Warp; keep the scene module host-only

        return ContactLaw(kind=self.law, k=self.k, m=self.exponent)

    def to_dict(self) -> dict:
        """The ``[materials.NAME]`` table of a scene file (without the name)."""
        d = {
            "density": self.density,
            "law": self.law,
            "k": self.k,
            "restitution": self.restitution,
            "friction": self.friction,
        }
        if self.m is not None:
            d["m"] = self.m
        if self.tangential_stiffness is not None:
            d["tangential_stiffness"] = self.tangential_stiffness
        return d


_MATERIAL_FIELDS = tuple(f.name for f in fields(Material) if f.name != "name")
_MATERIAL_REQUIRED = ("density", "law", "k", "restitution", "friction")


@dataclass(frozen=True)
class PairMaterial:
    """Contact properties of a pair of materials (see :func:`pair_material`).

    Attributes:
        law: contact law shared by both materials.
        exponent: exponent m of W = k V^m / m [-].
        k: combined stiffness (units of the law).
        restitution: combined coefficient of restitution [-].
        friction: combined friction coefficient [-].
        tangential_stiffness: combined tangential stiffness [N/m] or None (derived by the simulator).
    """

    law: str
    exponent: float
    k: float
    restitution: float
    friction: float
    tangential_stiffness: float | None

    def contact_law(self):
        """The pair's :class:`polydem.contact.ContactLaw`."""
        from polydem.contact import ContactLaw

        return ContactLaw(kind=self.law, k=self.k, m=self.exponent)


def _harmonic(a: float, b: float) -> float:
    return 2.0 * a * b / (a + b)


def pair_material(a: Material, b: Material) -> PairMaterial:
    """Mixing rule for a contact between materials ``a`` and ``b``.

    * The law and its exponent must agree (a contact has a single W(V)); otherwise SceneError. A
      scene therefore requires all its materials to share the law and exponent (checked by
      :meth:`Scene.validate`).
    * ``k = 2 k_a k_b / (k_a + k_b)``: the harmonic mean, i.e. twice the stiffness of the two
      springs in series, so equal materials give ``k``.
    * ``restitution = min(e_a, e_b)`` and ``friction = min(mu_a, mu_b)``: the weaker material rules.
    * ``tangential_stiffness``: harmonic mean when both are given, else None (derived later by the
      simulator).
    """
    if (a.law, a.exponent) != (b.law, b.exponent):
        raise SceneError(
            f"materials {a.name!r} (law {a.law!r}, exponent {a.exponent:g}) and {b.name!r} (law {b.law!r}, exponent "
            f"{b.exponent:g}) can meet in a contact but use different contact laws; a contact needs one W(V), so give "
            "all materials of a scene the same law (and the same m for law = 'power')",
            f"materials.{b.name}.law",
        )
    kt = None
    if a.tangential_stiffness is not None and b.tangential_stiffness is not None:
        kt = _harmonic(a.tangential_stiffness, b.tangential_stiffness)
    return PairMaterial(
        law=a.law,
        exponent=a.exponent,
        k=_harmonic(a.k, b.k),
        restitution=min(a.restitution, b.restitution),
        friction=min(a.friction, b.friction),
        tangential_stiffness=kt,
    )


# ---------------------------------------------------------------------- bodies and walls


def _tuple(a) -> tuple[float, ...]:
    return tuple(float(x) for x in a)


@dataclass(frozen=True)
class Body:
    """One body, as given to :meth:`Scene.add_body` (a convenience view; the scene stores arrays).

    Attributes:
        shape: name of a shape registered in the scene.
        material: name of a material registered in the scene.
        position: (3,) world position of the shape's input-frame origin [m] (the centroid for all
            generated shapes except ``rock``).
        orientation: (4,) unit quaternion xyzw rotating the shape's input axes into world axes
            [-]; normalised on construction, rejected when zero or off unit length by more than 1e-6.
        velocity: (3,) velocity of the centre of mass [m/s].
        angular_velocity: (3,) angular velocity in world axes [rad/s].
        kind: ``"free"``, ``"fixed"`` or ``"kinematic"``.
        centroid: (3,) world position of the centre of mass [m] (filled in by :meth:`Scene.body`).
        body_orientation: (4,) xyzw orientation of the body (principal) frame (filled in by
            :meth:`Scene.body`).
    """

    shape: str
    material: str
    position: tuple = (0.0, 0.0, 0.0)
    orientation: tuple = (0.0, 0.0, 0.0, 1.0)
    velocity: tuple = (0.0, 0.0, 0.0)
    angular_velocity: tuple = (0.0, 0.0, 0.0)
    kind: str = "free"
    centroid: tuple | None = field(default=None, compare=False)
    body_orientation: tuple | None = field(default=None, compare=False)

    def __post_init__(self):
        _string(self.shape, "body.shape", what="a shape name")
        _string(self.material, "body.material", what="a material name")
        _choice(self.kind, KINDS, "body.kind", what="body kind")
        q = _check_quats(_vector(self.orientation, 4, "body.orientation")[None, :], lambda i: "body.orientation", None)
        object.__setattr__(self, "orientation", _tuple(q[0]))
        for name in ("position", "velocity", "angular_velocity"):
            object.__setattr__(self, name, _tuple(_vector(getattr(self, name), 3, f"body.{name}")))


@dataclass(frozen=True)
class PlaneWall:
    """An infinite plane wall; bodies are pushed to the side the normal points to.

    Attributes:
        point: (3,) a point on the plane [m].
        normal: (3,) unit normal [-] pointing into the simulated half-space; normalised on
            construction (any non-zero length is accepted).
        material: name of a material registered in the scene.
    """

    point: tuple
    normal: tuple
    material: str

    def __post_init__(self):
        object.__setattr__(self, "point", _tuple(_vector(self.point, 3, "plane.point")))
        object.__setattr__(self, "normal", _tuple(_unit_normal(self.normal, "plane.normal", None)))
        _string(self.material, "plane.material", what="a material name")

    def to_dict(self) -> dict:
        return {"type": "plane", "point": list(self.point), "normal": list(self.normal), "material": self.material}


def _unit_normal(value, key, file) -> np.ndarray:
    n = _vector(value, 3, key, file)
    length = float(np.linalg.norm(n))
    if length < 1e-12:
        raise SceneError(f"normal {n.tolist()} is zero; give the direction the wall faces, e.g. [0, 0, 1]", key, file)
    return n / length


# ---------------------------------------------------------------------- shapes from specs


_SHAPE_KEYS = {
    "box": ("size",),
    "tetrahedron": ("edge",),
    "octahedron": ("edge",),
    "dodecahedron": ("edge",),
    "icosahedron": ("edge",),
    "prism": ("n", "radius", "height"),
    "rock": ("n_points", "size", "seed", "elongation", "roughness"),
    "sphere": ("subdivisions", "radius"),
    "mesh": ("file", "scale", "tol"),
    "points": ("points", "tol"),
}
_SHAPE_REQUIRED = {
    "box": ("size",),
    "prism": ("n", "radius", "height"),
    "rock": ("n_points", "size"),
    "sphere": ("subdivisions", "radius"),
    "mesh": ("file",),
    "points": ("points",),
}
_SHAPE_HINTS = {
    "size": "edge length(s) in m: size = 0.1 for a cube or size = [sx, sy, sz]; for rock the largest diameter in m",
    "edge": "edge length in m, e.g. edge = 0.1",
    "n": "number of sides of the base polygon, an integer >= 3",
    "radius": "circumscribed radius in m",
    "height": "prism height in m",
    "n_points": "number of hull vertices, an integer >= 4",
    "subdivisions": "icosphere subdivision level, 0 to 5",
    "file": "mesh file (OBJ, STL, PLY) relative to the scene file, e.g. file = 'meshes/rock.obj'",
    "points": "array of [x, y, z] points in m",
}


def _build_shape(name: str, spec: dict, key: str, file, base_dir: Path) -> tuple[ConvexShape, dict]:
    """Build a shape from a ``[shapes.NAME]`` table; returns it and the normalised spec."""
    spec = _table(spec, key, file, what=f"a table [shapes.{name}] with a 'type' key")
    if "type" not in spec:
        raise SceneError(f"missing required key 'type' (one of {', '.join(SHAPE_TYPES)})", f"{key}.type", file)
    kind = _choice(spec["type"], SHAPE_TYPES, f"{key}.type", file, what="shape type")
    edge_required = ("edge",) if kind in ("tetrahedron", "octahedron", "dodecahedron", "icosahedron") else ()
    _check_keys(
        spec,
        ("type", *_SHAPE_KEYS[kind]),
        key,
        file,
        required=_SHAPE_REQUIRED.get(kind, edge_required),
        hints=_SHAPE_HINTS,
        context=f" for type = {kind!r}",
    )

    def pos(k):
        return _number(spec[k], f"{key}.{k}", file, positive=True, hint=f" ({_SHAPE_HINTS.get(k, 'in m')})")

    def count(k, minimum, maximum=None):
        return _integer(spec[k], f"{key}.{k}", file, minimum=minimum, maximum=maximum)

    def tol():
        if "tol" not in spec:
            return {}
        t = _number(spec["tol"], f"{key}.tol", file, nonneg=True)
        if t > 1e-3:
            raise SceneError(
                f"relative tolerance must be in [0, 1e-3], got {t:g} (use ~1e-6 for STL files)", f"{key}.tol", file
            )
        return {"tol": t}

    out = {"type": kind}
    try:
        if kind == "box":
            size = spec["size"]
            if _is_number(size):
                s = [pos("size")] * 3
            else:
                s = _vector(size, 3, f"{key}.size", file, label="[sx, sy, sz]").tolist()
                if min(s) <= 0.0:
                    raise SceneError(f"box edge lengths must be positive, got {s}", f"{key}.size", file)
            out["size"] = s
            shape = ConvexShape.box(*s, name=name)
        elif kind in ("tetrahedron", "octahedron", "dodecahedron", "icosahedron"):
            out["edge"] = pos("edge")
            shape = getattr(ConvexShape, kind)(out["edge"], name=name)
        elif kind == "prism":
            out.update(n=count("n", 3), radius=pos("radius"), height=pos("height"))
            shape = ConvexShape.prism(out["n"], out["radius"], out["height"], name=name)
        elif kind == "rock":
            out.update(n_points=count("n_points", 4), size=pos("size"))
            out["seed"] = count("seed", 0) if "seed" in spec else 0
            extra = {}
            if "elongation" in spec:
                el = _vector(spec["elongation"], 3, f"{key}.elongation", file, label="[ex, ey, ez]")
                if el.min() <= 0.0:
                    raise SceneError(
                        f"elongation factors must be positive, got {el.tolist()}", f"{key}.elongation", file
                    )
                extra["elongation"] = el.tolist()
            if "roughness" in spec:
                r = _number(spec["roughness"], f"{key}.roughness", file, nonneg=True)
                if r >= 1.0:
                    raise SceneError(f"roughness must be in [0, 1), got {r:g}", f"{key}.roughness", file)
                extra["roughness"] = r
            out.update(extra)
            shape = ConvexShape.rock(out["n_points"], out["size"], out["seed"], name=name, **extra)
        elif kind == "sphere":
            out.update(subdivisions=count("subdivisions", 0, 5), radius=pos("radius"))
            shape = ConvexShape.sphere(out["subdivisions"], out["radius"], name=name)
        elif kind == "mesh":
            rel = _string(spec["file"], f"{key}.file", file, what="a file path string")
            path = Path(rel).expanduser()
            if not path.is_absolute():
                path = base_dir / path
            if not path.is_file():
                what = "is not a file" if path.exists() else "not found"
                raise SceneError(
                    f"mesh file {rel!r} {what} (looked for '{path}'; relative paths are taken from the folder of the "
                    f"scene file, '{base_dir}')",
                    f"{key}.file",
                    file,
                )
            out["file"] = str(path.resolve())
            t = tol()
            out.update(t)
            shape = ConvexShape.from_file(path, name=name, **t)
            if "scale" in spec:
                out["scale"] = _number(
                    spec["scale"],
                    f"{key}.scale",
                    file,
                    positive=True,
                    hint=" (factor applied to the file's coordinates, e.g. 0.001 for mm)",
                )
                shape = shape.scaled(out["scale"])
        else:  # points
            pts = spec["points"]
            if not isinstance(pts, list | tuple | np.ndarray) or len(pts) < 4:
                raise SceneError(
                    f"expected an array of at least 4 [x, y, z] points, got {_typename(pts)}", f"{key}.points", file
                )
            rows = [_vector(p, 3, f"{key}.points[{i}]", file) for i, p in enumerate(pts)]
            out["points"] = [r.tolist() for r in rows]
            t = tol()
            out.update(t)
            shape = ConvexShape.from_points(np.array(rows), name=name, **t)
    except SceneError:
        raise
    except (ValueError, OSError) as exc:  # geometry rejected by ConvexShape (degenerate, unreadable file)
        raise SceneError(f"cannot build the {kind} shape: {exc}", key, file) from exc
    return shape, out


# ---------------------------------------------------------------------- the scene


_SIM_KEYS = ("name", "description", "dt", "gravity", "steps", "duration")
_TOP_KEYS = ("simulation", "materials", "shapes", "bodies", "walls")
_BODY_KEYS = ("shape", "material", "position", "orientation", "rotation", "velocity", "angular_velocity", "kind")
_WALL_KEYS = {
    "plane": ("type", "point", "normal", "material"),
    "box": ("type", "center", "inner_size", "material", "wall_thickness", "open_top"),
}
_WALL_REQUIRED = {"plane": ("point", "normal", "material"), "box": ("center", "inner_size", "material")}
_BODY_FIELDS = (
    ("shape", np.int32, ()),
    ("material", np.int32, ()),
    ("position", np.float64, (3,)),
    ("orientation", np.float64, (4,)),
    ("velocity", np.float64, (3,)),
    ("angular_velocity", np.float64, (3,)),
    ("kind", np.int32, ()),
)


class Scene:
    """Validated, host-only description of a simulation (see the module docstring for frames).

    Bodies are stored as per-body numpy arrays (read-only views; scenes reach 10^6 bodies):
    :attr:`body_shape`, :attr:`body_material` (int32 indices into :attr:`shapes` and
    :attr:`materials` in insertion order), :attr:`body_position` (N, 3) centre of mass [m],
    :attr:`body_orientation` (N, 4) xyzw of the body (principal) frame, :attr:`body_velocity`
    (N, 3) [m/s], :attr:`body_angular_velocity` (N, 3) world axes [rad/s] and :attr:`body_kind`
    (int32, 0 free, 1 fixed, 2 kinematic). :meth:`body` returns one body as a :class:`Body`.

    Args:
        gravity: (3,) gravitational acceleration [m/s^2].
        dt: time step [s], > 0, or ``"auto"`` to let the simulator choose from the stiffest contact.
        name: label.
        steps: number of steps to run (optional), > 0.
        duration: simulated time to run [s] (optional), > 0; not together with ``steps``.
        description: free text.
        file: scene file the scene came from (used in error messages), or None.
    """

    def __init__(
        self,
        gravity=(0.0, 0.0, -9.81),
        dt="auto",
        name: str = "scene",
        *,
        steps: int | None = None,
        duration: float | None = None,
        description: str = "",
        file=None,
    ):
        self.file = file
        self.name = _string(name, "simulation.name", file)
        self.description = _string(description, "simulation.description", file)
        self.gravity = tuple(_vector(gravity, 3, "simulation.gravity", file).tolist())
        self.dt = self._check_dt(dt)
        if steps is not None and duration is not None:
            raise SceneError(
                f"give either steps or duration, not both (got steps = {steps}, duration = {duration})",
                "simulation.duration",
                file,
            )
        self.steps = None if steps is None else _integer(steps, "simulation.steps", file, minimum=1)
        self.duration = (
            None
            if duration is None
            else _number(duration, "simulation.duration", file, positive=True, hint=" (simulated time in s)")
        )
        self._shapes: dict[str, ConvexShape] = {}
        self._shape_index: dict[str, int] = {}
        self._shape_specs: dict[str, dict] = {}
        self._shape_frames: list[tuple[np.ndarray, np.ndarray]] = []  # (q(R_in), t_in) per shape
        self._materials: dict[str, Material] = {}
        self._material_index: dict[str, int] = {}
        self._planes: list[PlaneWall] = []
        self._n = 0
        self._cap = 0
        self._arrays = {name: np.empty((0, *shape), dtype) for name, dtype, shape in _BODY_FIELDS}

    def _check_dt(self, dt):
        if isinstance(dt, str):
            if dt != "auto":
                raise SceneError(
                    f'expected a time step in seconds or "auto", got string {dt!r}', "simulation.dt", self.file
                )
            return "auto"
        return _number(dt, "simulation.dt", self.file, positive=True, hint=' (time step in s, or "auto")')

    def _err(self, message, key) -> SceneError:
        return SceneError(message, key, self.file)

    # ------------------------------------------------------------------ registries

    @property
    def shapes(self) -> dict[str, ConvexShape]:
        """Registered shapes, name -> :class:`ConvexShape`, in insertion (= index) order (a copy)."""
        return dict(self._shapes)

    @property
    def materials(self) -> dict[str, Material]:
        """Registered materials, name -> :class:`Material`, in insertion (= index) order (a copy)."""
        return dict(self._materials)

    @property
    def planes(self) -> list[PlaneWall]:
        """Plane walls (a copy of the list)."""
        return list(self._planes)

    @property
    def shape_names(self) -> list[str]:
        return list(self._shapes)

    @property
    def material_names(self) -> list[str]:
        return list(self._materials)

    def shape_index(self, name: str) -> int:
        """Index of a shape in :attr:`shapes` (the value stored in :attr:`body_shape`)."""
        return self._lookup_shape(name, "shape")

    def material_index(self, name: str) -> int:
        """Index of a material in :attr:`materials` (the value stored in :attr:`body_material`)."""
        return self._lookup_material(name, "material")

    def _lookup_shape(self, name, key) -> int:
        if not isinstance(name, str):
            raise self._err(f"expected a shape name, got {_typename(name)}", key)
        if name not in self._shape_index:
            raise self._err(
                _unknown_name(name, self._shapes, "shape", "define one with [shapes.NAME] or Scene.add_shape()"), key
            )
        return self._shape_index[name]

    def _lookup_material(self, name, key) -> int:
        if isinstance(name, Material):
            if self._materials.get(name.name) is not name:
                raise self._err(f"material {name.name!r} is not registered in this scene; use add_material()", key)
            name = name.name
        if not isinstance(name, str):
            raise self._err(f"expected a material name, got {_typename(name)}", key)
        if name not in self._material_index:
            raise self._err(
                _unknown_name(
                    name, self._materials, "material", "define one with [materials.NAME] or Scene.add_material()"
                ),
                key,
            )
        return self._material_index[name]

    def add_material(self, name: str, **props) -> Material:
        """Register a material; ``props`` are the :class:`Material` fields (density, law, k,
        restitution, friction, and m / tangential_stiffness where needed)."""
        key = f"materials.{name}"
        _check_keys(props, _MATERIAL_FIELDS, key, self.file, required=_MATERIAL_REQUIRED, hints=_MATERIAL_HINTS)
        if name in self._materials:
            raise self._err(f"material {name!r} is already defined; choose another name", key)
        try:
            mat = Material(name=name, **props)
        except SceneError as err:
            err.file = self.file
            raise
        self._material_index[name] = len(self._materials)
        self._materials[name] = mat
        return mat

    def add_shape(self, name: str, shape: ConvexShape, *, _spec: dict | None = None) -> ConvexShape:
        """Register ``shape`` under ``name`` (bodies refer to it by name); returns the shape.

        Registering the same object again under the same name is a no-op.
        """
        key = f"shapes.{name}"
        if not isinstance(name, str) or not name:
            raise self._err(f"shape name must be a non-empty string, got {_typename(name)}", "shapes")
        if not isinstance(shape, ConvexShape):
            raise self._err(
                f"expected a polydem.ConvexShape, got {_typename(shape)}; build one with e.g. ConvexShape.box(0.1)", key
            )
        if name in self._shapes:
            if self._shapes[name] is shape:
                return shape
            raise self._err(f"a different shape is already registered as {name!r}; choose another name", key)
        self._shape_index[name] = len(self._shapes)
        self._shapes[name] = shape
        if _spec is not None:
            self._shape_specs[name] = _spec
        self._shape_frames.append((_quat_from_matrix(shape.input_rotation), np.array(shape.input_translation)))
        return shape

    def _resolve_shape(self, shape, key) -> int:
        if isinstance(shape, ConvexShape):
            for name, s in self._shapes.items():
                if s is shape:
                    return self._shape_index[name]
            self.add_shape(shape.name, shape)
            return self._shape_index[shape.name]
        return self._lookup_shape(shape, key)

    # ------------------------------------------------------------------ bodies

    @property
    def num_bodies(self) -> int:
        return self._n

    def _view(self, name) -> np.ndarray:
        v = self._arrays[name][: self._n]
        v.setflags(write=False)
        return v

    @property
    def body_shape(self) -> np.ndarray:
        """(N,) int32 shape index (into :attr:`shapes`)."""
        return self._view("shape")

    @property
    def body_material(self) -> np.ndarray:
        """(N,) int32 material index (into :attr:`materials`)."""
        return self._view("material")

    @property
    def body_position(self) -> np.ndarray:
        """(N, 3) world position of each body's centre of mass [m]."""
        return self._view("position")

    @property
    def body_orientation(self) -> np.ndarray:
        """(N, 4) unit xyzw quaternion of each body's principal (body) frame, body -> world."""
        return self._view("orientation")

    @property
    def body_velocity(self) -> np.ndarray:
        """(N, 3) velocity of the centre of mass [m/s]."""
        return self._view("velocity")

    @property
    def body_angular_velocity(self) -> np.ndarray:
        """(N, 3) angular velocity in world axes [rad/s]."""
        return self._view("angular_velocity")

    @property
    def body_kind(self) -> np.ndarray:
        """(N,) int32 kind code: 0 free, 1 fixed, 2 kinematic (see :data:`KINDS`)."""
        return self._view("kind")

    def add_body(
        self,
        shape,
        material,
        position=(0.0, 0.0, 0.0),
        orientation=(0.0, 0.0, 0.0, 1.0),
        velocity=(0.0, 0.0, 0.0),
        angular_velocity=(0.0, 0.0, 0.0),
        kind: str = "free",
        *,
        _key: str | None = None,
    ) -> int:
        """Add one body; returns its index.

        Args:
            shape: name of a registered shape, or a :class:`ConvexShape` (registered under its
                ``name`` if it is not yet).
            material: name of a registered material.
            position: (3,) world position of the shape's input-frame origin [m].
            orientation: (4,) unit quaternion xyzw of the shape's input axes.
            velocity: (3,) velocity of the centre of mass [m/s].
            angular_velocity: (3,) world axes [rad/s].
            kind: ``"free"``, ``"fixed"`` (velocities must be zero) or ``"kinematic"``.
        """
        key = _key or f"bodies[{self._n}]"
        f = self.file
        s = self._resolve_shape(shape, f"{key}.shape")
        m = self._lookup_material(material, f"{key}.material")
        kind_code = KINDS.index(_choice(kind, KINDS, f"{key}.kind", f, what="body kind"))
        p = _vector(position, 3, f"{key}.position", f)
        q = _vector(orientation, 4, f"{key}.orientation", f)
        v = _vector(velocity, 3, f"{key}.velocity", f)
        w = _vector(angular_velocity, 3, f"{key}.angular_velocity", f)
        return int(self._append(s, m, p[None], q[None], v[None], w[None], kind_code, lambda i: key)[0])

    def add_bodies(
        self,
        shape,
        material,
        positions,
        orientations=None,
        velocities=None,
        angular_velocities=None,
        kind: str = "free",
    ) -> np.ndarray:
        """Add N bodies of one shape and material at once; returns their indices (int64, (N,)).

        Args:
            positions: (N, 3) world positions of the input-frame origins [m].
            orientations: (N, 4) or (4,) unit xyzw quaternions; default identity.
            velocities: (N, 3) or (3,) [m/s]; default zero.
            angular_velocities: (N, 3) or (3,) world axes [rad/s]; default zero.
            kind: one kind for all of them.
        """
        start, f = self._n, self.file
        p = _rows(positions, 3, f"bodies[{start}:].position", f)
        n = p.shape[0]
        label = f"bodies[{start}:{start + n}]"
        s = self._resolve_shape(shape, f"{label}.shape")
        m = self._lookup_material(material, f"{label}.material")
        kind_code = KINDS.index(_choice(kind, KINDS, f"{label}.kind", f, what="body kind"))
        q = _rows((0.0, 0.0, 0.0, 1.0) if orientations is None else orientations, 4, f"{label}.orientation", f, n=n)
        v = _rows((0.0, 0.0, 0.0) if velocities is None else velocities, 3, f"{label}.velocity", f, n=n)
        w = _rows(
            (0.0, 0.0, 0.0) if angular_velocities is None else angular_velocities,
            3,
            f"{label}.angular_velocity",
            f,
            n=n,
        )
        return self._append(s, m, p, q, v, w, kind_code, lambda i: f"bodies[{start + i}]")

    def _append(self, s, m, p, q, v, w, kind_code, rowkey) -> np.ndarray:
        n = p.shape[0]
        for name, arr in (("position", p), ("orientation", q), ("velocity", v), ("angular_velocity", w)):
            if np.isfinite(arr).all():
                continue
            bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
            if bad.size:
                i = int(bad[0])
                raise self._err(f"expected finite numbers, got {arr[i].tolist()}", f"{rowkey(i)}.{name}")
        q = _check_quats(q, lambda i: f"{rowkey(i)}.orientation", self.file)
        if kind_code == KIND_FIXED and (np.any(v != 0.0) or np.any(w != 0.0)):
            moving = np.flatnonzero(np.any(v != 0.0, axis=1) | np.any(w != 0.0, axis=1))
            if moving.size:
                i = int(moving[0])
                which, val = ("velocity", v[i]) if np.any(v[i] != 0.0) else ("angular_velocity", w[i])
                raise self._err(
                    f"a fixed body cannot move, but its {which} is {val.tolist()}; set it to [0, 0, 0], or use "
                    "kind = 'kinematic' for a body that moves at a prescribed velocity",
                    f"{rowkey(i)}.{which}",
                )
        q_in, t_in = self._shape_frames[s]
        # Most generated shapes are built in their principal frame: skip the no-op transforms.
        centroid = p if not np.any(t_in) else p + _quat_rotate(q, np.broadcast_to(t_in, p.shape))
        if np.array_equal(q_in, (0.0, 0.0, 0.0, 1.0)):
            q_body = q
        else:
            q_body = _quat_mul(q, q_in)
            q_body /= np.sqrt(np.einsum("ij,ij->i", q_body, q_body))[:, None]
        self._reserve(n)
        sl = slice(self._n, self._n + n)
        a = self._arrays
        a["shape"][sl] = s
        a["material"][sl] = m
        a["position"][sl] = centroid
        a["orientation"][sl] = q_body
        a["velocity"][sl] = v
        a["angular_velocity"][sl] = w
        a["kind"][sl] = kind_code
        self._n += n
        return np.arange(sl.start, sl.stop, dtype=np.int64)

    def _reserve(self, extra: int):
        need = self._n + extra
        if need <= self._cap:
            return
        cap = max(need, 2 * self._cap, 16)
        for name, dtype, shape in _BODY_FIELDS:
            new = np.zeros((cap, *shape), dtype)
            new[: self._n] = self._arrays[name][: self._n]
            self._arrays[name] = new
        self._cap = cap

    def body(self, i: int) -> Body:
        """Body ``i`` as a :class:`Body` (input-frame pose as given, plus its centroid and body frame)."""
        if not isinstance(i, numbers.Integral) or not -self._n <= int(i) < self._n:
            raise IndexError(f"body index {i!r} out of range for a scene with {self._n} bodies")
        i = int(i) % self._n
        a = self._arrays
        s = int(a["shape"][i])
        q_in, t_in = self._shape_frames[s]
        q_body = a["orientation"][i]
        q_user = _quat_mul(q_body, _quat_conj(q_in))
        q_user /= np.linalg.norm(q_user)
        pos = a["position"][i] - _quat_rotate(q_user, t_in)
        return Body(
            shape=self.shape_names[s],
            material=self.material_names[int(a["material"][i])],
            position=_tuple(pos),
            orientation=_tuple(q_user),
            velocity=_tuple(a["velocity"][i]),
            angular_velocity=_tuple(a["angular_velocity"][i]),
            kind=KINDS[int(a["kind"][i])],
            centroid=_tuple(a["position"][i]),
            body_orientation=_tuple(q_body),
        )

    def body_vertices(self, i: int) -> np.ndarray:
        """(nv, 3) world coordinates of body ``i``'s vertices [m]."""
        shape = self._shapes[self.shape_names[int(self.body_shape[i])]]
        return shape.vertices @ quat_to_matrix(self.body_orientation[i]).T + self.body_position[i]

    def body_mass(self) -> np.ndarray:
        """(N,) mass of each body [kg] (density times volume, whatever the kind)."""
        vol = np.array([s.volume for s in self._shapes.values()])
        rho = np.array([m.density for m in self._materials.values()])
        return rho[self.body_material] * vol[self.body_shape]

    def body_inertia(self) -> np.ndarray:
        """(N, 3) principal moments of inertia of each body [kg m^2], about its body-frame axes."""
        inertia = np.array([s.inertia for s in self._shapes.values()]).reshape(-1, 3)
        rho = np.array([m.density for m in self._materials.values()])
        return rho[self.body_material][:, None] * inertia[self.body_shape]

    # ------------------------------------------------------------------ walls

    def add_plane(self, point, normal, material, *, _key: str | None = None) -> PlaneWall:
        """Add an infinite plane through ``point`` [m] facing ``normal`` (normalised; non-zero)."""
        key = _key or f"planes[{len(self._planes)}]"
        p = _vector(point, 3, f"{key}.point", self.file)
        n = _unit_normal(normal, f"{key}.normal", self.file)
        self._lookup_material(material, f"{key}.material")
        name = material.name if isinstance(material, Material) else material
        plane = PlaneWall(point=_tuple(p), normal=_tuple(n), material=name)
        self._planes.append(plane)
        return plane

    def add_box_container(
        self, center, inner_size, material, wall_thickness=None, open_top: bool = True, *, _key: str | None = None
    ) -> list[int]:
        """Add an axis-aligned box container made of fixed box-shaped bodies; returns their indices.

        The cavity is ``inner_size`` = (lx, ly, lz) [m] centred on ``center`` [m], z up. The walls,
        ``wall_thickness`` [m] thick (default 10% of the smallest inner size), are: a floor plate
        covering the whole outer footprint, two x walls spanning the outer y extent, two y walls
        between them, and a lid like the floor unless ``open_top``. Walls touch but do not overlap.
        The needed box shapes are registered as ``"wall_box_{sx}x{sy}x{sz}"``.
        """
        key = _key or "box_container"
        f = self.file
        c = _vector(center, 3, f"{key}.center", f)
        size = _vector(inner_size, 3, f"{key}.inner_size", f, label="[lx, ly, lz]")
        if size.min() <= 0.0:
            raise self._err(f"inner sizes must be positive, got {size.tolist()}", f"{key}.inner_size")
        if wall_thickness is None:
            t = 0.1 * float(size.min())
        else:
            t = _number(wall_thickness, f"{key}.wall_thickness", f, positive=True, hint=" (in m)")
        open_top = _boolean(open_top, f"{key}.open_top", f)
        self._lookup_material(material, f"{key}.material")
        lx, ly, lz = size
        walls = [
            ((lx + 2 * t, ly + 2 * t, t), (0.0, 0.0, -0.5 * (lz + t))),  # floor
            ((t, ly + 2 * t, lz), (-0.5 * (lx + t), 0.0, 0.0)),  # -x
            ((t, ly + 2 * t, lz), (0.5 * (lx + t), 0.0, 0.0)),  # +x
            ((lx, t, lz), (0.0, -0.5 * (ly + t), 0.0)),  # -y
            ((lx, t, lz), (0.0, 0.5 * (ly + t), 0.0)),  # +y
        ]
        if not open_top:
            walls.append(((lx + 2 * t, ly + 2 * t, t), (0.0, 0.0, 0.5 * (lz + t))))
        indices = []
        for dims, offset in walls:
            name = self._box_shape(dims)
            indices.append(self.add_body(name, material, position=c + np.array(offset), kind="fixed"))
        return indices

    def _box_shape(self, dims) -> str:
        dims = [float(d) for d in dims]
        name = "wall_box_" + "x".join(f"{d:.6g}" for d in dims)
        spec = {"type": "box", "size": dims}
        base, k = name, 1
        while name in self._shapes and self._shape_specs.get(name) != spec:
            k += 1
            name = f"{base}_{k}"
        if name not in self._shapes:
            self.add_shape(name, ConvexShape.box(*dims, name=name), _spec=spec)
        return name

    # ------------------------------------------------------------------ checks and mixing

    def pair_material(self, a, b) -> PairMaterial:
        """Contact properties between two materials (names or :class:`Material`); see :func:`pair_material`."""
        ma = self._materials[self.material_names[self._lookup_material(a, "material")]]
        mb = self._materials[self.material_names[self._lookup_material(b, "material")]]
        try:
            return pair_material(ma, mb)
        except SceneError as err:
            err.file = self.file
            raise

    def pair_table(self) -> dict:
        """Mixed contact properties of every material pair, as (M, M) float64 arrays indexed like
        :attr:`materials`: ``k``, ``restitution``, ``friction``, ``tangential_stiffness`` (NaN where
        the simulator derives it); plus ``law`` (str) and ``exponent`` (float) shared by all."""
        mats = list(self._materials.values())
        if not mats:
            raise self._err("the scene has no materials; add one with [materials.NAME] or add_material()", "materials")
        self._check_laws()
        nm = len(mats)
        out = {k: np.empty((nm, nm)) for k in ("k", "restitution", "friction", "tangential_stiffness")}
        for i, a in enumerate(mats):
            for j, b in enumerate(mats):
                pm = pair_material(a, b)
                out["k"][i, j] = pm.k
                out["restitution"][i, j] = pm.restitution
                out["friction"][i, j] = pm.friction
                kt = pm.tangential_stiffness
                out["tangential_stiffness"][i, j] = np.nan if kt is None else kt
        out["law"] = mats[0].law
        out["exponent"] = mats[0].exponent
        return out

    def _check_laws(self):
        mats = list(self._materials.values())
        if not mats:
            return
        ref = mats[0]
        for mat in mats[1:]:
            if (mat.law, mat.exponent) != (ref.law, ref.exponent):
                raise self._err(
                    f"material {mat.name!r} uses law {mat.law!r} (exponent {mat.exponent:g}) but material {ref.name!r} "
                    f"uses law {ref.law!r} (exponent {ref.exponent:g}); all materials of a scene must share one "
                    f"contact law and exponent, since a contact between two of them needs a single W(V): use law = "
                    f"{ref.law!r}"
                    + (f" with m = {ref.exponent:g}" if ref.law == "power" else "")
                    + f" for {mat.name!r} (and convert its k)",
                    f"materials.{mat.name}.law",
                )

    def validate(self) -> Scene:
        """Check the whole scene; raise :class:`SceneError` on the first problem, else return self.

        Checks: simulation settings; all materials share one contact law; at least one body; every
        body's shape and material index exists; all numbers finite; unit quaternions; valid kinds;
        fixed bodies at rest; free bodies have a shape with positive volume and inertia; planes use
        registered materials and have unit normals.
        """
        f = self.file
        self.gravity = tuple(_vector(list(self.gravity), 3, "simulation.gravity", f).tolist())
        self.dt = self._check_dt(self.dt)
        if self.steps is not None and self.duration is not None:
            raise self._err("give either steps or duration, not both", "simulation.duration")
        if self.steps is not None:
            self.steps = _integer(self.steps, "simulation.steps", f, minimum=1)
        if self.duration is not None:
            self.duration = _number(self.duration, "simulation.duration", f, positive=True)
        self._check_laws()
        n = self._n
        if n == 0:
            raise self._err(
                "the scene has no bodies; add at least one with a [[bodies]] table in the scene file or "
                "Scene.add_body() / add_bodies() in Python",
                "bodies",
            )
        a = {name: self._arrays[name][:n] for name, _, _ in _BODY_FIELDS}
        for name, count in (("shape", len(self._shapes)), ("material", len(self._materials))):
            bad = np.flatnonzero((a[name] < 0) | (a[name] >= count))
            if bad.size:
                i = int(bad[0])
                raise self._err(
                    f"{name} index {int(a[name][i])} out of range: the scene has {count} {name}s", f"bodies[{i}].{name}"
                )
        for name in ("position", "orientation", "velocity", "angular_velocity"):
            bad = np.flatnonzero(~np.isfinite(a[name]).all(axis=1))
            if bad.size:
                i = int(bad[0])
                raise self._err(f"expected finite numbers, got {a[name][i].tolist()}", f"bodies[{i}].{name}")
        _check_quats(a["orientation"], lambda i: f"bodies[{i}].orientation", f)
        bad = np.flatnonzero((a["kind"] < 0) | (a["kind"] >= len(KINDS)))
        if bad.size:
            i = int(bad[0])
            raise self._err(
                f"kind code {int(a['kind'][i])} is not one of 0 (free), 1 (fixed), 2 (kinematic)", f"bodies[{i}].kind"
            )
        fixed = a["kind"] == KIND_FIXED
        moving = np.flatnonzero(
            fixed & (np.any(a["velocity"] != 0, axis=1) | np.any(a["angular_velocity"] != 0, axis=1))
        )
        if moving.size:
            i = int(moving[0])
            raise self._err(
                "a fixed body cannot move; set its velocity and angular_velocity to zero or use kind = 'kinematic'",
                f"bodies[{i}].velocity",
            )
        shapes = list(self._shapes.values())
        massless = np.array(
            [
                not (
                    s.volume > 0.0
                    and math.isfinite(s.volume)
                    and np.all(np.asarray(s.inertia) > 0.0)
                    and np.all(np.isfinite(s.inertia))
                )
                for s in shapes
            ]
        )
        bad = np.flatnonzero((a["kind"] == KIND_FREE) & massless[a["shape"]])
        if bad.size:
            i = int(bad[0])
            s = shapes[int(a["shape"][i])]
            raise self._err(
                f"free body uses shape {s.name!r} with volume {s.volume:g} m^3 and inertia {np.asarray(s.inertia)}; a "
                "free body needs a positive volume and inertia to have mass: use a solid shape or kind = 'fixed'",
                f"bodies[{i}].shape",
            )
        for j, plane in enumerate(self._planes):
            self._lookup_material(plane.material, f"planes[{j}].material")
            nrm = np.asarray(plane.normal)
            if not (np.all(np.isfinite(nrm)) and abs(np.linalg.norm(nrm) - 1.0) < 1e-9):
                raise self._err(f"normal {list(plane.normal)} is not a unit vector", f"planes[{j}].normal")
        return self

    # ------------------------------------------------------------------ scene files

    @classmethod
    def from_toml(cls, path: str | PathLike, *, validate: bool = True) -> Scene:
        """Load a scene file (TOML; see ``scenes/*.toml`` for examples) and validate it.

        Relative mesh paths are taken from the folder of the scene file. Every problem raises
        :class:`SceneError` naming the file and the key.
        """
        path = Path(path)
        if not path.exists():
            raise SceneError(f"scene file not found (looked for '{path.absolute()}'); check the path", None, path)
        if not path.is_file():
            raise SceneError("scene path is not a file; give the path of a .toml scene file", None, path)
        try:
            with open(path, "rb") as fh:
                data = tomllib.load(fh)
        except tomllib.TOMLDecodeError as exc:
            raise SceneError(f"invalid TOML syntax: {exc}", None, path) from exc
        except UnicodeDecodeError as exc:
            raise SceneError(f"the file is not UTF-8 text: {exc}", None, path) from exc
        except OSError as exc:
            raise SceneError(f"cannot read the scene file: {exc}", None, path) from exc
        return cls.from_dict(data, file=path, base_dir=path.parent, validate=validate)

    @classmethod
    def from_dict(cls, data: dict, *, file=None, base_dir=None, validate: bool = True) -> Scene:
        """Build a scene from the parsed contents of a scene file (the layout of :meth:`to_dict`)."""
        try:
            return cls._from_dict(data, file, Path.cwd() if base_dir is None else Path(base_dir), validate)
        except SceneError as err:
            if err.file is None:
                err.file = file
            raise

    @classmethod
    def _from_dict(cls, data, file, base_dir: Path, validate) -> Scene:
        _table(data, None, file, what="a table of scene sections")
        _check_keys(data, _TOP_KEYS, "", file)
        sim = _table(data.get("simulation", {}), "simulation", file, what="a [simulation] table")
        _check_keys(sim, _SIM_KEYS, "simulation", file)
        scene = cls(
            gravity=sim.get("gravity", (0.0, 0.0, -9.81)),
            dt=sim.get("dt", "auto"),
            name=sim.get("name", Path(file).stem if file is not None else "scene"),
            steps=sim.get("steps"),
            duration=sim.get("duration"),
            description=sim.get("description", ""),
            file=file,
        )
        materials = _table(
            data.get("materials", {}), "materials", file, what="tables [materials.NAME], one per material"
        )
        for name, props in materials.items():
            props = _table(
                props,
                f"materials.{name}",
                file,
                what=f"a table [materials.{name}] with density, law, k, restitution, friction",
            )
            scene.add_material(name, **props)
        shapes = _table(data.get("shapes", {}), "shapes", file, what="tables [shapes.NAME], one per shape")
        for name, spec in shapes.items():
            shape, spec = _build_shape(name, spec, f"shapes.{name}", file, base_dir)
            scene.add_shape(name, shape, _spec=spec)
        bodies = data.get("bodies", [])
        if not isinstance(bodies, list):
            raise SceneError(f"expected an array of tables [[bodies]], got {_typename(bodies)}", "bodies", file)
        for j, body in enumerate(bodies):
            key = f"bodies[{j}]"
            body = _table(body, key, file, what="a [[bodies]] table")
            _check_keys(body, _BODY_KEYS, key, file, required=("shape", "material", "position"))
            if "orientation" in body and "rotation" in body:
                raise SceneError(
                    "give either orientation (quaternion) or rotation (axis and angle), not both",
                    f"{key}.rotation",
                    file,
                )
            orientation = body.get("orientation", (0.0, 0.0, 0.0, 1.0))
            if "rotation" in body:
                orientation = _rotation(body["rotation"], f"{key}.rotation", file)
            scene.add_body(
                body["shape"],
                body["material"],
                position=body["position"],
                orientation=orientation,
                velocity=body.get("velocity", (0.0, 0.0, 0.0)),
                angular_velocity=body.get("angular_velocity", (0.0, 0.0, 0.0)),
                kind=body.get("kind", "free"),
                _key=key,
            )
        walls = data.get("walls", [])
        if not isinstance(walls, list):
            raise SceneError(f"expected an array of tables [[walls]], got {_typename(walls)}", "walls", file)
        for j, wall in enumerate(walls):
            key = f"walls[{j}]"
            wall = _table(wall, key, file, what="a [[walls]] table")
            if "type" not in wall:
                raise SceneError("missing required key 'type' ('plane' or 'box')", f"{key}.type", file)
            kind = _choice(wall["type"], _WALL_KEYS, f"{key}.type", file, what="wall type")
            _check_keys(
                wall, _WALL_KEYS[kind], key, file, required=_WALL_REQUIRED[kind], context=f" for type = {kind!r}"
            )
            if kind == "plane":
                scene.add_plane(wall["point"], wall["normal"], wall["material"], _key=key)
            else:
                scene.add_box_container(
                    wall["center"],
                    wall["inner_size"],
                    wall["material"],
                    wall_thickness=wall.get("wall_thickness"),
                    open_top=wall.get("open_top", True),
                    _key=key,
                )
        if validate:
            scene.validate()
        return scene

    def to_dict(self) -> dict:
        """The scene as the nested dict of a scene file (``Scene.from_dict(scene.to_dict())`` rebuilds it).

        Shapes built from a scene file keep their spec; others are written as ``type = "points"``
        with their vertices in the input frame. Box containers come back as fixed bodies.
        """
        sim = {"name": self.name, "dt": self.dt, "gravity": list(self.gravity)}
        if self.description:
            sim["description"] = self.description
        if self.steps is not None:
            sim["steps"] = self.steps
        if self.duration is not None:
            sim["duration"] = self.duration
        shapes = {}
        for name, shape in self._shapes.items():
            spec = self._shape_specs.get(name)
            if spec is None:
                spec = {"type": "points", "points": shape.to_input_frame(shape.vertices).tolist()}
            shapes[name] = dict(spec)
        bodies = []
        for i in range(self._n):
            b = self.body(i)
            bodies.append(
                {
                    "shape": b.shape,
                    "material": b.material,
                    "position": list(b.position),
                    "orientation": list(b.orientation),
                    "velocity": list(b.velocity),
                    "angular_velocity": list(b.angular_velocity),
                    "kind": b.kind,
                }
            )
        return {
            "simulation": sim,
            "materials": {name: m.to_dict() for name, m in self._materials.items()},
            "shapes": shapes,
            "bodies": bodies,
            "walls": [p.to_dict() for p in self._planes],
        }

    def describe(self) -> str:
        """A human-readable summary."""
        g = ", ".join(f"{x:g}" for x in self.gravity)
        dt = self.dt if self.dt == "auto" else f"{self.dt:g} s"
        run = f", {self.steps} steps" if self.steps is not None else ""
        run += f", duration {self.duration:g} s" if self.duration is not None else ""
        lines = [
            f"Scene {self.name!r}" + (f" from {self.file}" if self.file else ""),
            f"  gravity [{g}] m/s^2, dt {dt}{run}",
        ]
        if self.description:
            lines.append(f"  {self.description}")
        lines.append(f"  materials ({len(self._materials)}):")
        for m in self._materials.values():
            extra = f", m={m.m:g}" if m.m is not None else ""
            extra += f", kt={m.tangential_stiffness:g} N/m" if m.tangential_stiffness is not None else ""
            lines.append(
                f"    {m.name}: density {m.density:g} kg/m^3, {m.law} k={m.k:g} {_LAW_UNITS[m.law]}{extra}, "
                f"e={m.restitution:g}, mu={m.friction:g}"
            )
        lines.append(f"  shapes ({len(self._shapes)}):")
        counts = np.bincount(self.body_shape, minlength=len(self._shapes)) if self._n else [0] * len(self._shapes)
        for (name, s), c in zip(self._shapes.items(), counts, strict=True):
            kind = self._shape_specs.get(name, {}).get("type", "custom")
            lines.append(
                f"    {name}: {kind}, {s.num_vertices} vertices, {s.num_faces} faces, volume {s.volume:.4g} "
                f"m^3, radius {s.radius:.4g} m; {int(c)} bodies"
            )
        kinds = np.bincount(self.body_kind, minlength=3) if self._n else [0, 0, 0]
        lines.append(f"  bodies: {self._n} ({kinds[0]} free, {kinds[1]} fixed, {kinds[2]} kinematic)")
        lines.append(f"  planes ({len(self._planes)}):")
        for p in self._planes:
            lines.append(
                f"    point [{', '.join(f'{x:g}' for x in p.point)}], normal "
                f"[{', '.join(f'{x:.4g}' for x in p.normal)}], material {p.material}"
            )
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (
            f"Scene(name={self.name!r}, bodies={self._n}, shapes={len(self._shapes)}, "
            f"materials={len(self._materials)}, planes={len(self._planes)})"
        )


def _rotation(value, key, file) -> np.ndarray:
    """Quaternion of a ``rotation = {axis = [..], degrees = a}`` (or ``radians = a``) table."""
    value = _table(value, key, file, what="a table {axis = [ax, ay, az], degrees = angle}")
    _check_keys(value, ("axis", "degrees", "radians"), key, file, required=("axis",))
    if ("degrees" in value) == ("radians" in value):
        raise SceneError(
            "give the angle as exactly one of degrees or radians, e.g. rotation = {axis = [0, 1, 0], degrees = 20}",
            f"{key}.degrees",
            file,
        )
    axis = _vector(value["axis"], 3, f"{key}.axis", file)
    if np.linalg.norm(axis) == 0.0:
        raise SceneError("rotation axis is zero; give a direction such as [0, 0, 1]", f"{key}.axis", file)
    if "degrees" in value:
        angle = math.radians(_number(value["degrees"], f"{key}.degrees", file))
    else:
        angle = _number(value["radians"], f"{key}.radians", file)
    return quat_from_axis_angle(axis, angle)
