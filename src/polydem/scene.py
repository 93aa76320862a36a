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
angular velocity and are not pushed by contacts. A kinematic body may name a ``pivot``: a fixed
point its pose turns about at its angular velocity (the parts of a rotating drum); its velocity is
then ``angular_velocity x (centroid - pivot)`` at the start and is derived, not given.

Scene files (TOML; examples in ``scenes/``). Every table and key is checked; an unknown key gets a
did-you-mean and the list of valid keys, and every error names the file and the key::

    [simulation]     name, description, steps | duration, dt (seconds or "auto"), gravity,
                     device ("cpu", "cuda", "cuda:N"; optional), precision ("float32")
    [materials.NAME] density, law, k, restitution, friction (+ m, tangential_stiffness)
    [shapes.NAME]    type = box | tetrahedron | ... | mesh | points, and its parameters
    [[bodies]]       shape, material, position, orientation | rotation, velocity, angular_velocity,
                     kind (free | fixed | kinematic), pivot (kinematic bodies turning about a point)
    [[walls]]        type = "plane" (point, normal, material), "box" (an open or closed container
                     of fixed slabs) or "drum" (a rotating polygonal drum of kinematic slabs)
    [[emitters]]     many bodies placed without overlaps in a box region (see Scene.emit)
    [output]         usd, fps, summary, pictures, checkpoint, vtk (see Output)

Bodies are added in the file's order of sections: ``[[bodies]]``, then ``[[walls]]``, then
``[[emitters]]`` (so emitters avoid every body and wall given before them), each in its order.
"""

from __future__ import annotations

import difflib
import math
import numbers
import re
import tomllib
import warnings
from dataclasses import dataclass, field, fields
from os import PathLike
from pathlib import Path

import numpy as np

from polydem.shapes import MAX_FACE_VERTICES, MAX_FACES, ConvexShape

__all__ = [
    "Body",
    "Drum",
    "Output",
    "PRECISIONS",
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
    "SceneWarning",
    "SHAPE_TYPES",
    "TimeStep",
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

PRECISIONS = ("float32", "float64")
"""Values of ``[simulation] precision``; the simulator runs float32 only (float64 is rejected with
a message pointing to :func:`polydem.overlap`, which offers it for contact geometry)."""

ORIENTATIONS = ("random", "aligned")
"""Emitter orientations: uniformly random, or every body with its input axes along the world axes."""

FILLS = ("bottom", "random")
"""Emitter fill orders: the lowest cells first (against gravity), or cells anywhere in the region."""

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


class SceneWarning(UserWarning):
    """A scene that runs but probably not as meant, e.g. bodies that start overlapping moderately.

    :meth:`Scene.validate` issues these with :func:`warnings.warn` (category SceneWarning);
    ``polydem validate`` prints them as ``polydem: warning: ...`` lines.
    """


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
        pivot: (3,) fixed point a kinematic body turns about [m], or None (see :meth:`Scene.add_body`).
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
    pivot: tuple | None = None

    def __post_init__(self):
        _string(self.shape, "body.shape", what="a shape name")
        if self.pivot is not None:
            object.__setattr__(self, "pivot", _tuple(_vector(self.pivot, 3, "body.pivot")))
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


# ---------------------------------------------------------------------- output settings


_USD_SUFFIXES = (".usd", ".usda", ".usdc")
_OUTPUT_KEYS = ("usd", "fps", "summary", "pictures", "checkpoint", "vtk")
_CHECKPOINT_KEYS = ("steps", "seconds", "path")


@dataclass(frozen=True, kw_only=True)
class Output:
    """What a run writes: the ``[output]`` table of a scene file (validated on construction).

    The scene only stores these settings; the ``polydem`` command acts on them. Paths are relative
    to the output folder of the run (``polydem run --out DIR``) and must stay inside it: absolute
    paths and paths that lead out of it with ``..`` are refused (a scene file must not overwrite
    files elsewhere; the folder itself is the user's choice on the command line).

    Attributes:
        usd: USD file of the trajectory (``.usd``, ``.usda`` or ``.usdc``), or None for none. In a
            scene file ``usd = true`` means ``"trajectory.usd"`` and ``usd = false`` none.
        fps: frames per simulated second of the USD file and of the picture frames, > 0 [1/s].
        summary: JSON summary file, or None for none. In a scene file ``summary = true`` (the
            default) means ``"summary.json"``; ``false`` none; a string is the path.
        pictures: frame numbers to render as pictures (frame k is the state at time k / fps), as a
            sorted tuple of distinct integers >= 0, or ``"last"`` for the final state; ``()`` for none.
            In a scene file ``pictures = true`` means ``"last"`` and ``false`` none; ``polydem run``
            renders the last frame when the scene file does not mention ``pictures``.
        checkpoint_steps: write a checkpoint every so many steps, or None.
        checkpoint_seconds: write a checkpoint every so many simulated seconds, or None (at most
            one of the two is set). In a scene file: ``checkpoint = {steps = 10000}`` or
            ``checkpoint = {seconds = 0.1}``, optionally with ``path``.
        checkpoint_path: folder of the checkpoints.
        vtk: write VTK files for ParaView (``vtk/`` in the output folder: :mod:`polydem.vtk`) at
            every frame; ``polydem run --vtk`` turns it on too.
    """

    usd: str | None = None
    fps: float = 60.0
    summary: str | None = "summary.json"
    pictures: tuple | str = ()
    checkpoint_steps: int | None = None
    checkpoint_seconds: float | None = None
    checkpoint_path: str = "checkpoints"
    vtk: bool = False

    def __post_init__(self):
        usd = self.usd
        if usd is not None:
            usd = _string(usd, "output.usd", what="a file path string such as 'trajectory.usd' (or true / false)")
            if not usd.strip():
                raise SceneError("the USD path is empty; give a file name such as 'trajectory.usd'", "output.usd")
            if Path(usd).suffix.lower() not in _USD_SUFFIXES:
                raise SceneError(
                    f"the USD file {usd!r} must end in {', '.join(_USD_SUFFIXES)} (e.g. 'trajectory.usd')", "output.usd"
                )
        fps = _number(self.fps, "output.fps", positive=True, hint=" (frames per simulated second, e.g. fps = 60)")
        summary = self.summary
        if summary is not None:
            summary = _string(summary, "output.summary", what="a file path string (or true / false)")
            if not summary.strip():
                raise SceneError("the summary path is empty; give a file name such as 'summary.json'", "output.summary")
        pictures = self.pictures
        hint = ' (frame numbers at fps, e.g. pictures = [0, 30, 60], or pictures = "last")'
        if isinstance(pictures, str):
            if pictures != "last":
                raise SceneError(
                    f'expected a list of frame numbers or "last", got {pictures!r}{hint}', "output.pictures"
                )
        elif isinstance(pictures, list | tuple | np.ndarray):
            frames = [_integer(x, f"output.pictures[{i}]", minimum=0, hint=hint) for i, x in enumerate(pictures)]
            pictures = tuple(sorted(set(frames)))
        else:
            raise SceneError(
                f'expected a list of frame numbers or "last", got {_typename(pictures)}{hint}', "output.pictures"
            )
        steps, seconds = self.checkpoint_steps, self.checkpoint_seconds
        if steps is not None and seconds is not None:
            raise SceneError(
                "give the checkpoint interval in steps or in seconds, not both", "output.checkpoint.seconds"
            )
        if steps is not None:
            steps = _integer(steps, "output.checkpoint.steps", minimum=1, hint=" (a checkpoint every so many steps)")
        if seconds is not None:
            seconds = _number(
                seconds, "output.checkpoint.seconds", positive=True, hint=" (a checkpoint every so many simulated s)"
            )
        path = _string(self.checkpoint_path, "output.checkpoint.path", what="a folder path string")
        vtk = _boolean(self.vtk, "output.vtk")

        def inside(value, key, example):
            # Backslashes count as separators too, so that a scene written on Windows is judged alike.
            parts = value.replace("\\", "/").split("/")
            if Path(value).is_absolute() or value.startswith(("/", "\\")) or re.match(r"[A-Za-z]:", value):
                raise SceneError(
                    f"{value!r} is an absolute path; outputs stay inside the output folder (polydem run --out DIR): "
                    f"give a path relative to it, e.g. {example}",
                    key,
                )
            depth = 0
            for part in parts:
                depth += -1 if part == ".." else 0 if part in ("", ".") else 1
                if depth < 0:
                    raise SceneError(
                        f"{value!r} leads out of the output folder with '..'; outputs stay inside it: give a path "
                        f"inside it, e.g. {example}, and choose the folder with polydem run --out DIR",
                        key,
                    )

        if usd is not None:
            inside(usd, "output.usd", "usd = 'trajectory.usd'")
        if summary is not None:
            inside(summary, "output.summary", "summary = 'summary.json'")
        inside(path, "output.checkpoint.path", "checkpoint = {steps = 10000, path = 'checkpoints'}")
        for name, value in (
            ("usd", usd),
            ("fps", fps),
            ("summary", summary),
            ("pictures", pictures),
            ("checkpoint_steps", steps),
            ("checkpoint_seconds", seconds),
            ("checkpoint_path", path),
            ("vtk", vtk),
        ):
            object.__setattr__(self, name, value)

    @classmethod
    def from_dict(cls, table, file=None) -> Output:
        """Settings from an ``[output]`` table (errors name ``output.KEY`` and ``file``)."""
        try:
            table = _table(table, "output", file, what="an [output] table")
            _check_keys(table, _OUTPUT_KEYS, "output", file)
            kw = {}
            if "usd" in table:
                usd = table["usd"]
                kw["usd"] = ("trajectory.usd" if usd else None) if isinstance(usd, bool) else usd
            if "fps" in table:
                kw["fps"] = table["fps"]
            if "summary" in table:
                summary = table["summary"]
                kw["summary"] = ("summary.json" if summary else None) if isinstance(summary, bool) else summary
            if "pictures" in table:
                pictures = table["pictures"]
                kw["pictures"] = ("last" if pictures else ()) if isinstance(pictures, bool) else pictures
            if "vtk" in table:
                kw["vtk"] = table["vtk"]
            if "checkpoint" in table:
                cp = _table(
                    table["checkpoint"],
                    "output.checkpoint",
                    file,
                    what="a table such as checkpoint = {steps = 10000} or checkpoint = {seconds = 0.1}",
                )
                _check_keys(cp, _CHECKPOINT_KEYS, "output.checkpoint", file)
                if "steps" not in cp and "seconds" not in cp:
                    raise SceneError(
                        "give the checkpoint interval, e.g. checkpoint = {steps = 10000} or {seconds = 0.1}",
                        "output.checkpoint",
                        file,
                    )
                kw.update(checkpoint_steps=cp.get("steps"), checkpoint_seconds=cp.get("seconds"))
                if "path" in cp:
                    kw["checkpoint_path"] = cp["path"]
            return cls(**kw)
        except SceneError as err:
            if err.file is None:
                err.file = file
            raise

    def to_dict(self) -> dict:
        """The ``[output]`` table of a scene file."""
        d = {"fps": self.fps, "summary": self.summary if self.summary is not None else False}
        d["usd"] = self.usd if self.usd is not None else False
        if self.pictures:
            d["pictures"] = self.pictures if isinstance(self.pictures, str) else list(self.pictures)
        if self.checkpoint_steps is not None or self.checkpoint_seconds is not None:
            cp = {"path": self.checkpoint_path}
            if self.checkpoint_steps is not None:
                cp["steps"] = self.checkpoint_steps
            else:
                cp["seconds"] = self.checkpoint_seconds
            d["checkpoint"] = cp
        if self.vtk:
            d["vtk"] = True
        return d


# ---------------------------------------------------------------------- drums


@dataclass(frozen=True)
class Drum:
    """A rotating polygonal drum built by :meth:`Scene.add_drum` (a record of what was built).

    A hollow drum is not convex, so it is made of ``sides`` kinematic box slabs whose inner faces
    form a regular polygon of inradius ``radius`` around the axis, and (``caps``) two kinematic
    polygonal plates closing its ends. Every part has the angular velocity ``omega * axis`` and
    the drum centre as its ``pivot``; a slab's velocity is ``omega x r`` with r from the axis to
    the slab's centre (the caps, centred on the axis, only spin).

    Attributes:
        center: (3,) middle of the drum on its axis [m].
        axis: (3,) unit direction of the axis [-]; the drum turns by the right-hand rule about it.
        radius: inradius of the polygon of inner faces [m].
        length: inner length along the axis [m].
        sides: number of slabs.
        thickness: slab and cap thickness [m].
        omega: angular speed about ``axis`` [rad/s] (negative turns the other way).
        material: material name.
        caps: whether the ends are closed by rotating plates.
        bodies: indices of the slabs, then of the caps.
    """

    center: tuple
    axis: tuple
    radius: float
    length: float
    sides: int
    thickness: float
    omega: float
    material: str
    caps: bool
    bodies: tuple

    @property
    def angular_velocity(self) -> np.ndarray:
        """(3,) angular velocity of every part [rad/s]."""
        return self.omega * np.asarray(self.axis)

    def interior_planes(self) -> tuple[np.ndarray, np.ndarray]:
        """Half-spaces ``u . x <= e`` whose intersection is the (convex) inside of the drum.

        Returns ``(u, e)``: (K, 3) outward unit normals and (K,) offsets [m]; the radial planes
        of the slabs' inner faces and, with caps, the two end planes.
        """
        c, a = np.asarray(self.center), np.asarray(self.axis)
        radial = _drum_radial(a, self.sides)
        u = list(radial)
        e = list(radial @ c + self.radius)
        if self.caps:
            u += [a, -a]
            e += [a @ c + 0.5 * self.length, -(a @ c) + 0.5 * self.length]
        return np.array(u), np.array(e)


def _perpendicular_basis(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors e1, e2 with (e1, e2, axis) right-handed; e1 = axis x z (x when axis ~ z)."""
    ref = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(axis, ref)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def _drum_radial(axis: np.ndarray, sides: int) -> np.ndarray:
    """(sides, 3) outward radial unit vectors of the slabs (slab k at angle 2 pi k / sides from e1)."""
    e1, e2 = _perpendicular_basis(axis)
    ang = 2.0 * np.pi * np.arange(sides) / sides
    return np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2


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
    "n": f"number of sides of the base polygon, an integer from 3 to {MAX_FACE_VERTICES}",
    "radius": "circumscribed radius in m",
    "height": "prism height in m",
    "n_points": f"number of hull vertices, an integer from 4 to {MAX_FACES // 2 + 2}",
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

    def count(k, minimum, maximum=None, why=""):
        return _integer(spec[k], f"{key}.{k}", file, minimum=minimum, maximum=maximum, hint=why)

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
            why = f" (the contact kernels take faces of at most {MAX_FACE_VERTICES} vertices; use a smaller n)"
            out.update(n=count("n", 3, MAX_FACE_VERTICES, why), radius=pos("radius"), height=pos("height"))
            shape = ConvexShape.prism(out["n"], out["radius"], out["height"], name=name)
        elif kind == "rock":
            why = f" (its hull has 2 n_points - 4 faces, and the contact kernels take at most {MAX_FACES})"
            out.update(n_points=count("n_points", 4, MAX_FACES // 2 + 2, why), size=pos("size"))
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


# ---------------------------------------------------------------------- emitter helpers


_MAX_EMITTER_CELLS = 20_000_000  # grid cells an emitter may scan (random fill) or hold in one layer
_EMITTER_CHUNK = 1 << 20  # grid cells tested at a time
_PAIR_BATCH = 1 << 20  # (obstacle, cell) pairs tested at a time


def _region(region, key, file) -> tuple[np.ndarray, np.ndarray]:
    """``(min, max)`` corners of an emitter region given as {min = [..], max = [..]} or a pair."""
    hint = "region = {min = [x0, y0, z0], max = [x1, y1, z1]} in m"
    if isinstance(region, dict):
        _check_keys(region, ("min", "max"), key, file, required=("min", "max"), hints={"min": hint, "max": hint})
        lo = _vector(region["min"], 3, f"{key}.min", file)
        hi = _vector(region["max"], 3, f"{key}.max", file)
    elif isinstance(region, list | tuple) and len(region) == 2:
        lo = _vector(region[0], 3, f"{key}.min", file)
        hi = _vector(region[1], 3, f"{key}.max", file)
    else:
        raise SceneError(f"expected a box, {hint}, got {_typename(region)}", key, file)
    bad = np.flatnonzero(hi <= lo)
    if bad.size:
        ax = int(bad[0])
        raise SceneError(
            f"max must exceed min along every axis, but along {'xyz'[ax]} min = {lo[ax]:g} and max = {hi[ax]:g} m",
            f"{key}.max",
            file,
        )
    return lo, hi


def _largest_remainder(count: int, frac: np.ndarray) -> np.ndarray:
    """Integer counts summing to ``count`` in the proportions ``frac`` (largest remainders get the rest)."""
    raw = count * frac
    out = np.floor(raw).astype(np.int64)
    rest = count - int(out.sum())
    order = np.lexsort((np.arange(len(frac)), -(raw - out)))
    out[order[:rest]] += 1
    return out


def _scale_sampler(scale, scale_range, scale_lognormal, bins: int, key: str, file):
    """A function ``(rng, n) -> (bin index per body, factor per bin)`` for an emitter's sizes."""
    given = [
        k
        for k, v in (("scale", scale), ("scale_range", scale_range), ("scale_lognormal", scale_lognormal))
        if v is not None
    ]
    if len(given) > 1:
        raise SceneError(
            f"give one size distribution: scale, scale_range or scale_lognormal, not both {given[0]} and {given[1]}",
            f"{key}.{given[1]}",
            file,
        )

    def single(value):
        return lambda rng, n: (np.zeros(n, dtype=np.int64), np.array([value]))

    if scale_range is not None:
        lo, hi = _vector(scale_range, 2, f"{key}.scale_range", file, label="[lo, hi]")
        if lo <= 0.0 or hi < lo:
            raise SceneError(f"expected 0 < lo <= hi (size factors), got [{lo:g}, {hi:g}]", f"{key}.scale_range", file)
        if hi == lo:
            return single(float(lo))
        values = lo + (np.arange(bins) + 0.5) * (hi - lo) / bins

        def uniform(rng, n):
            u = rng.uniform(lo, hi, size=n)
            return np.clip(np.floor((u - lo) / (hi - lo) * bins).astype(np.int64), 0, bins - 1), values

        return uniform
    if scale_lognormal is not None:
        lk = f"{key}.scale_lognormal"
        hint = "scale_lognormal = {mean = 1.0, sigma = 0.2}: the mean size factor and the spread of its logarithm"
        if isinstance(scale_lognormal, list | tuple) and len(scale_lognormal) == 2:
            scale_lognormal = {"mean": scale_lognormal[0], "sigma": scale_lognormal[1]}
        table = _table(scale_lognormal, lk, file, what=f"a table, {hint}")
        _check_keys(table, ("mean", "sigma"), lk, file, required=("mean", "sigma"), hints={"mean": hint, "sigma": hint})
        mean = _number(table["mean"], f"{lk}.mean", file, positive=True, hint=" (mean size factor)")
        sigma = _number(table["sigma"], f"{lk}.sigma", file, nonneg=True, hint=" (standard deviation of ln(factor))")
        if sigma > 2.0:
            raise SceneError(
                f"must be <= 2 (factors from e^-6 to e^6 times the median), got {sigma:g}", f"{lk}.sigma", file
            )
        if sigma == 0.0:
            return single(mean)
        mu = math.log(mean) - 0.5 * sigma * sigma
        a, width = mu - 3.0 * sigma, 6.0 * sigma
        values = np.exp(a + (np.arange(bins) + 0.5) * width / bins)

        def lognormal(rng, n):
            x = rng.normal(mu, sigma, size=n)
            return np.clip(np.floor((x - a) / width * bins).astype(np.int64), 0, bins - 1), values

        return lognormal
    if scale is None:
        return single(1.0)
    return single(_number(scale, f"{key}.scale", file, positive=True, hint=" (size factor of the shapes)"))


_SCALED_KEYS = {
    "box": ("size",),
    "tetrahedron": ("edge",),
    "octahedron": ("edge",),
    "dodecahedron": ("edge",),
    "icosahedron": ("edge",),
    "prism": ("radius", "height"),
    "rock": ("size",),
    "sphere": ("radius",),
    "mesh": ("scale",),
}


def _scaled_spec(spec: dict | None, factor: float) -> dict | None:
    """The spec of a shape scaled by ``factor`` about its input origin, or None (then written as points)."""
    if spec is None:
        return None
    out = dict(spec)
    kind = spec["type"]
    if kind == "points":
        out["points"] = [[factor * x for x in p] for p in spec["points"]]
        return out
    for k in _SCALED_KEYS.get(kind, ()):
        value = spec.get(k, 1.0)
        out[k] = [factor * x for x in value] if isinstance(value, list) else factor * value
    return out


def _cell_index(layer, m, k, ax_a, ax_b, nb, nk, ascending) -> np.ndarray:
    """(N, 3) grid indices of cells given by layer (counted against gravity) and index in the layer."""
    gi = np.empty((len(layer), 3), dtype=np.int64)
    gi[:, k] = layer if ascending else nk - 1 - layer
    gi[:, ax_a] = m // nb
    gi[:, ax_b] = m % nb
    return gi


class _Obstacles:
    """What an emitter's grid cells must keep clear of: plane walls, the scene's bodies, drums.

    A cell (a cube of side ``cell``) is blocked when it reaches behind a plane, when it is not
    separated from a body by one of the body's face planes (conservative near edges and corners),
    or when it lies beside a drum (within its axial span) but not wholly inside it. A body in a free
    cell therefore touches none of them.
    """

    def __init__(self, scene, grid_lo, grid_hi, cell):
        self.origin = grid_lo
        self.n = np.rint((grid_hi - grid_lo) / cell).astype(np.int64)
        self.cell = cell
        self.h = 0.5 * cell
        self.tol = 1e-9 * cell
        planes = scene.planes
        self.plane_n = np.array([p.normal for p in planes], dtype=np.float64).reshape(-1, 3)
        self.plane_e = np.array([np.dot(p.normal, p.point) for p in planes], dtype=np.float64)
        self.shapes = list(scene.shapes.values())
        self.body = np.zeros(0, dtype=np.int64)
        if scene.num_bodies:
            radius = np.array([s.radius for s in self.shapes])[scene.body_shape]
            pos = scene.body_position
            d = pos - np.clip(pos, grid_lo, grid_hi)
            self.body = np.flatnonzero(np.einsum("ij,ij->i", d, d) < radius * radius)
            self.pos = pos[self.body]
            self.rad = radius[self.body]
            self.shape = np.asarray(scene.body_shape)[self.body]
            self.rot = quat_to_matrix(scene.body_orientation[self.body])
        self.drums = []
        reach = self.h * math.sqrt(3.0)
        for drum in scene.drums:
            u, e = drum.interior_planes()
            axial = 0.5 * drum.length + (drum.thickness if drum.caps else 0.0) + reach
            self.drums.append((np.asarray(drum.center), np.asarray(drum.axis), axial, u, e))

    def blocked(self, centres, krange, k, local_of) -> np.ndarray:
        """Which of the cells at ``centres`` are blocked; ``krange`` bounds their grid index along
        axis ``k`` and ``local_of`` maps (M, 3) grid indices to positions in ``centres``."""
        h, tol = self.h, self.tol
        out = np.zeros(len(centres), dtype=bool)
        for nrm, e in zip(self.plane_n, self.plane_e, strict=True):
            out |= centres @ nrm - e - h * np.abs(nrm).sum() < -tol
        for c, a, axial, u, e in self.drums:
            z = (centres - c) @ a
            near = np.flatnonzero(np.abs(z) < axial)
            if near.size:
                inside = np.all(centres[near] @ u.T + h * np.abs(u).sum(axis=1) <= e + tol, axis=1)
                out[near[~inside]] = True
        if self.body.size:
            self._block_bodies(out, krange, k, local_of)
        return out

    def _block_bodies(self, out, krange, k, local_of):
        cell, n = self.cell, self.n
        ilo = np.clip(np.floor((self.pos - self.rad[:, None] - self.origin) / cell), 0, n - 1).astype(np.int64)
        ihi = np.clip(np.floor((self.pos + self.rad[:, None] - self.origin) / cell), 0, n - 1).astype(np.int64)
        ilo[:, k] = np.maximum(ilo[:, k], krange[0])
        ihi[:, k] = np.minimum(ihi[:, k], krange[1])
        dims = ihi - ilo + 1
        sel = np.flatnonzero(np.all(dims > 0, axis=1))
        if not sel.size:
            return
        ilo, dims = ilo[sel], dims[sel]
        sizes = np.prod(dims, axis=1)
        big = np.flatnonzero(sizes > _PAIR_BATCH)
        if big.size:  # a wall spanning the whole chunk: cut its block into slices along its longest axis
            pieces = [(sel[i : i + 1], ilo[i : i + 1], dims[i : i + 1]) for i in np.flatnonzero(sizes <= _PAIR_BATCH)]
            for i in big:
                ax = int(np.argmax(dims[i]))
                step = max(1, _PAIR_BATCH // (int(sizes[i]) // int(dims[i, ax])))
                for s0 in range(0, int(dims[i, ax]), step):
                    lo_, d_ = ilo[i].copy(), dims[i].copy()
                    lo_[ax] += s0
                    d_[ax] = min(step, int(dims[i, ax]) - s0)
                    pieces.append((sel[i : i + 1], lo_[None], d_[None]))
            sel = np.concatenate([pc[0] for pc in pieces])
            ilo = np.concatenate([pc[1] for pc in pieces])
            dims = np.concatenate([pc[2] for pc in pieces])
            sizes = np.prod(dims, axis=1)
        ends = np.cumsum(sizes)
        start = 0
        while start < sel.size:
            base = ends[start - 1] if start else 0
            stop = max(start + 1, int(np.searchsorted(ends, base + _PAIR_BATCH, side="right")))
            self._block_pairs(out, sel[start:stop], ilo[start:stop], dims[start:stop], sizes[start:stop], local_of)
            start = stop

    def _block_pairs(self, out, obs, ilo, dims, sizes, local_of):
        """Test every (obstacle, cell) pair of the index blocks ``ilo + [0, dims)``, one per entry of
        ``obs`` (an obstacle may have several blocks)."""
        h, tol = self.h, self.tol
        ob = np.repeat(np.arange(len(obs)), sizes)
        local = np.arange(int(sizes.sum()), dtype=np.int64) - np.repeat(np.cumsum(sizes) - sizes, sizes)
        dz, dy = dims[ob, 2], dims[ob, 1]
        gi = np.empty((len(ob), 3), dtype=np.int64)
        gi[:, 2] = local % dz
        local //= dz
        gi[:, 1] = local % dy
        gi[:, 0] = local // dy
        gi += ilo[ob]
        j = obs[ob]
        rel = self.origin + (gi + 0.5) * self.cell - self.pos[j]
        # Bounding sphere against the cube first: most far pairs end here.
        gap = np.maximum(np.abs(rel) - h, 0.0)
        close = np.flatnonzero(np.einsum("ij,ij->i", gap, gap) < self.rad[j] ** 2)
        if not close.size:
            return
        gi, j, rel = gi[close], j[close], rel[close]
        for sid in np.unique(self.shape[j]):
            pick = np.flatnonzero(self.shape[j] == sid)
            shape = self.shapes[int(sid)]
            bodies, which = np.unique(j[pick], return_inverse=True)
            normals = np.einsum("bij,fj->bfi", self.rot[bodies], shape.face_normals)  # world normals
            support = h * np.abs(normals).sum(axis=2)  # (bodies, faces): half extent of the cube along each
            r = rel[pick]
            sep = np.full(len(pick), -np.inf)
            for face in range(shape.num_faces):
                nw = normals[which, face]
                s = np.einsum("ij,ij->i", r, nw) - shape.face_offsets[face] - support[which, face]
                np.maximum(sep, s, out=sep)
            hit = pick[sep < -tol]
            if hit.size:
                out[local_of(gi[hit])] = True


# ---------------------------------------------------------------------- time step and float32 limits

# The time step resolves a contact oscillation at the reference overlap (0.1% of a body's size,
# over its face area) in this many steps; above 1/8 of the period symplectic Euler loses accuracy
# fast (it is unstable past 1/pi of it).
STEPS_PER_CONTACT_PERIOD = 50
MAX_DT_FRACTION = 1.0 / 8.0
REFERENCE_DEPTH = 0.001

MAX_STEPS = 2**31 - 1
"""Most steps of one run: the simulator counts steps in a 32-bit integer."""

MAX_BODIES = 10**8
"""Most bodies of one scene: 100 times the largest scenes the simulator is meant for (10^6), low
enough that a mistyped count fails at once instead of allocating tens of gigabytes (every body holds
some hundred bytes in the scene alone, more on the device)."""

# The simulator stores masses, inertias, stiffnesses and the contact integrals (overlap volumes and
# their first moments, ~ size^4) in float32. Values must be normal float32 numbers, and products of
# them (inertia times angular velocity squared, k times volume powers, ...) must stay normal too,
# so they are kept this factor away from both ends of the range: 1.2e-32 to 3.4e32.
_F32_MARGIN = 1.0e6
F32_LOW = float(np.finfo(np.float32).tiny) * _F32_MARGIN
F32_HIGH = float(np.finfo(np.float32).max) / _F32_MARGIN

# Expected overlap depths (of a face contact under a body's weight or at the initial speeds), as a
# fraction of the body's size V^(1/3): above the first a warning, above the second an error.
OVERLAP_WARNING = 0.1
OVERLAP_ERROR = 0.5
# Initial overlaps, as a fraction of the thinner body's thickness along the separating axis.
INITIAL_OVERLAP_WARNING = 0.01
INITIAL_OVERLAP_ERROR = 0.5


def reference_stiffness(law, k, exponent, volume):
    """Secant normal stiffness [N/m] of a face contact of area V^(2/3) at 0.1% of the size V^(1/3).

    With W'(V) the law, a face of area A pressed to depth d gives V = A d and a force W'(A d) A;
    the secant stiffness is that force over d. Computed in float64 numpy (never an OverflowError:
    out-of-range values become 0 or inf, which :meth:`Scene.validate` rejects beforehand).
    """
    volume = np.float64(volume)
    with np.errstate(all="ignore"):
        area = volume ** (2.0 / 3.0)
        depth = REFERENCE_DEPTH * np.cbrt(volume)
        v = area * depth
        if law == "linear":
            dw = np.asarray(k, dtype=np.float64)
        elif law == "hertz":
            dw = np.asarray(k, dtype=np.float64) * np.sqrt(v)
        else:
            dw = np.asarray(k, dtype=np.float64) * v ** (np.float64(exponent) - 1.0)
        return dw * area / depth


@dataclass(frozen=True)
class TimeStep:
    """The time step of a run (see :meth:`Scene.time_step`).

    Attributes:
        dt: the step a run uses [s]: the scene's dt, or ``recommended`` for dt = "auto".
        recommended: 1/50 of the period of the stiffest contact of the lightest free body at the
            reference overlap (0.1% of its size) [s].
        limit: 1/8 of that period, the largest accurate step [s].
        period: that period [s].
        lightest: index of the body whose mass sets the period.
        tangential_stiffness: (M, M) tangential stiffness of every material pair [N/m], the derived
            value (the reference normal stiffness) where the materials give none.
    """

    dt: float
    recommended: float
    limit: float
    period: float
    lightest: int
    tangential_stiffness: np.ndarray


def _ln(x) -> float:
    """Natural log of a positive float, -inf for 0 (log-space arithmetic of the range checks)."""
    return math.log(x) if x > 0.0 else -math.inf


def _exp(x) -> float:
    return math.exp(min(x, 700.0))


def _fmt_exp(x) -> str:
    """exp(x) for a message, also beyond the range of a float."""
    return f"{math.exp(x):.3g}" if abs(x) < 700.0 else f"1e{x / math.log(10.0):+.0f}"


def _face_overlap(load, m, ln_k, ln_a, ln_l) -> float:
    """ln(A d) of a face contact (area A, size L, law W = k V^m / m) under a load.

    ``load > 0`` is a force F: W'(A d) A = F, so k (A d)^(m - 1) = F / A; for m = 1 the force
    k A does not depend on d, and d / L = F / (k A) stands in (see Scene._check_loads).
    ``load < 0`` is an energy E = -load: W(A d) = E, so (A d)^m = m E / k.
    """
    if load < 0.0:
        return (_ln(-m * load) - ln_k) / m
    if m == 1.0:
        return _ln(load) - ln_k + ln_l  # ln(A d) with d / L = F / (k A)
    return (_ln(load) - ln_a - ln_k) / (m - 1.0)


def _stiffness_for(load, m, ln_ad, ln_a, ln_l) -> float:
    """ln k for which a face contact under ``load`` has ln(A d) = ``ln_ad`` (inverse of _face_overlap)."""
    if load < 0.0:
        return _ln(-m * load) - m * ln_ad
    if m == 1.0:
        return _ln(load) - ln_a - (ln_ad - ln_a - ln_l)
    return _ln(load) - ln_a - (m - 1.0) * ln_ad


# ---------------------------------------------------------------------- the scene


_SIM_KEYS = ("name", "description", "dt", "gravity", "steps", "duration", "device", "precision")
_TOP_KEYS = ("simulation", "materials", "shapes", "bodies", "walls", "emitters", "output")
_BODY_KEYS = (
    "shape",
    "material",
    "position",
    "orientation",
    "rotation",
    "velocity",
    "angular_velocity",
    "kind",
    "pivot",
)
_WALL_KEYS = {
    "plane": ("type", "point", "normal", "material"),
    "box": ("type", "center", "inner_size", "material", "wall_thickness", "open_top"),
    "drum": ("type", "center", "axis", "radius", "length", "material", "omega", "rpm", "sides", "thickness", "caps"),
}
_WALL_REQUIRED = {
    "plane": ("point", "normal", "material"),
    "box": ("center", "inner_size", "material"),
    "drum": ("center", "axis", "radius", "length", "material"),
}
_EMITTER_KEYS = (
    "shape",
    "weights",
    "material",
    "count",
    "region",
    "orientation",
    "seed",
    "velocity",
    "velocity_jitter",
    "scale",
    "scale_range",
    "scale_lognormal",
    "scale_bins",
    "kind",
    "spacing",
    "jitter",
    "fill",
)
_EMITTER_HINTS = {
    "shape": "a shape name, a list of names, or a table of weights such as {cube = 2, rock = 1}",
    "material": "a material name",
    "count": "number of bodies, an integer >= 1",
    "region": "the box to fill: region = {min = [x0, y0, z0], max = [x1, y1, z1]} in m",
}
_BODY_FIELDS = (
    ("shape", np.int32, ()),
    ("material", np.int32, ()),
    ("position", np.float64, (3,)),
    ("orientation", np.float64, (4,)),
    ("velocity", np.float64, (3,)),
    ("angular_velocity", np.float64, (3,)),
    ("kind", np.int32, ()),
    ("pivot", np.float64, (3,)),
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
        device: Warp device to run on (``"cpu"``, ``"cuda"``, ``"cuda:N"``), or None for the default;
            a command-line ``--device`` overrides it.
        precision: ``"float32"``, the simulator's only precision (``"float64"`` raises
            :class:`SceneError`; :func:`polydem.overlap` offers float64 contact geometry).
        output: what a run writes (:class:`Output`); default ``Output()`` (a summary only).

    Other attributes: :attr:`drums` (the :class:`Drum` records of :meth:`add_drum`),
    :attr:`emitters` (one dict per :meth:`emit` call: key, count, first and last body index) and
    :attr:`warnings` (the :class:`SceneWarning` messages of the last :meth:`validate`).
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
        device: str | None = None,
        precision: str = "float32",
        output: Output | None = None,
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
        self.device = self._check_device(device)
        self.precision = self._check_precision(precision)
        self.output = self._check_output(output)
        self.drums: list[Drum] = []
        self.emitters: list[dict] = []
        self._scaled: dict[tuple[int, float], int] = {}
        self._shapes: dict[str, ConvexShape] = {}
        self._shape_index: dict[str, int] = {}
        self._shape_specs: dict[str, dict] = {}
        self._shape_frames: list[tuple[np.ndarray, np.ndarray]] = []  # (q(R_in), t_in) per shape
        self._materials: dict[str, Material] = {}
        self._material_index: dict[str, int] = {}
        self._planes: list[PlaneWall] = []
        self._plane_keys: list[str] = []  # where each plane came from, for messages
        self.warnings: list[str] = []  # of the last validate()
        self._warned: list[str] = []
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

    def _check_device(self, device):
        if device is None:
            return None
        device = _string(device, "simulation.device", self.file, what='a device name such as "cpu" or "cuda:0"')
        if not re.fullmatch(r"cpu|cuda(:\d+)?", device):
            raise SceneError(
                f'unknown device {device!r}{_did_you_mean(device, ("cpu", "cuda", "cuda:0")) or "."} Give "cpu", '
                '"cuda" (the default GPU) or "cuda:N" (GPU number N), or leave device out to use the GPU when '
                "there is one",
                "simulation.device",
                self.file,
            )
        return device

    def _check_precision(self, precision):
        precision = _choice(precision, PRECISIONS, "simulation.precision", self.file, what="precision")
        if precision == "float64":
            raise SceneError(
                'the simulator runs in float32 only; use precision = "float32" (or leave it out). Float64 is offered '
                'for contact geometry by polydem.overlap(..., precision="float64")',
                "simulation.precision",
                self.file,
            )
        return precision

    def _check_output(self, output):
        if output is None:
            return Output()
        if not isinstance(output, Output):
            raise SceneError(
                f"expected a polydem.scene.Output, got {_typename(output)}; build one with Output(usd=...)",
                "output",
                self.file,
            )
        return output

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

    @property
    def body_pivot(self) -> np.ndarray:
        """(N, 3) fixed point each kinematic body turns about [m]; NaN rows for bodies without one.

        A body with a pivot p and angular velocity w moves rigidly about p: after a time t its
        centroid is ``p + Rot(w t) (x0 - p)`` and its velocity ``w x (x - p)``. The parts of a
        :meth:`add_drum` drum have the drum centre as their pivot.
        """
        return self._view("pivot")

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
        pivot=None,
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
            pivot: (3,) for a kinematic body only: a fixed point [m] the body turns about at
                ``angular_velocity``; its velocity is then derived, ``angular_velocity x (centroid -
                pivot)``, so leave ``velocity`` at zero.
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
        piv = None if pivot is None else _vector(pivot, 3, f"{key}.pivot", f)[None]
        return int(self._append(s, m, p[None], q[None], v[None], w[None], kind_code, lambda i: key, piv)[0])

    def add_bodies(
        self,
        shape,
        material,
        positions,
        orientations=None,
        velocities=None,
        angular_velocities=None,
        kind: str = "free",
        *,
        pivots=None,
    ) -> np.ndarray:
        """Add N bodies of one shape and material at once; returns their indices (int64, (N,)).

        Args:
            positions: (N, 3) world positions of the input-frame origins [m].
            orientations: (N, 4) or (4,) unit xyzw quaternions; default identity.
            velocities: (N, 3) or (3,) [m/s]; default zero.
            angular_velocities: (N, 3) or (3,) world axes [rad/s]; default zero.
            kind: one kind for all of them.
            pivots: (N, 3) or (3,) fixed points the (kinematic) bodies turn about [m], or None; see
                :meth:`add_body`.
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
        piv = None if pivots is None else _rows(pivots, 3, f"{label}.pivot", f, n=n)
        return self._append(s, m, p, q, v, w, kind_code, lambda i: f"bodies[{start + i}]", piv)

    def _append(self, s, m, p, q, v, w, kind_code, rowkey, pivot=None) -> np.ndarray:
        """Store n bodies. ``s`` and ``m`` are one index or (n,) arrays; p, q, v, w are (n, k)."""
        n = p.shape[0]
        if self._n + n > MAX_BODIES:
            raise self._err(
                f"{n} more bodies would make {self._n + n:.3g}, more than a scene can hold ({MAX_BODIES:.0e})",
                rowkey(0),
            )
        arrays = [("position", p), ("orientation", q), ("velocity", v), ("angular_velocity", w)]
        if pivot is not None:
            arrays.append(("pivot", pivot))
        for name, arr in arrays:
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
        if pivot is not None:
            if kind_code != KIND_KINEMATIC:
                raise self._err(
                    f"only a kinematic body can turn about a pivot, this one is {KINDS[kind_code]!r}; use kind = "
                    "'kinematic' or leave pivot out",
                    f"{rowkey(0)}.pivot",
                )
            moving = np.flatnonzero(np.any(v != 0.0, axis=1))
            if moving.size:
                i = int(moving[0])
                raise self._err(
                    f"a body turning about a pivot has the velocity angular_velocity x (centroid - pivot), derived "
                    f"from its pose; leave velocity out (got {v[i].tolist()})",
                    f"{rowkey(i)}.velocity",
                )
        if np.ndim(s) == 0:
            q_in, t_in = self._shape_frames[int(s)]
        else:
            s = np.asarray(s, dtype=np.int32)
            frames = self._shape_frames
            q_in = np.array([frames[k][0] for k in range(len(frames))])[s]
            t_in = np.array([frames[k][1] for k in range(len(frames))])[s]
        # Most generated shapes are built in their principal frame: skip the no-op transforms.
        centroid = p if not np.any(t_in) else p + _quat_rotate(q, np.broadcast_to(t_in, p.shape))
        if np.all(q_in == (0.0, 0.0, 0.0, 1.0)):
            q_body = q
        else:
            q_body = _quat_mul(q, q_in)
            q_body /= np.sqrt(np.einsum("ij,ij->i", q_body, q_body))[:, None]
        if pivot is not None:
            v = _cross(w, centroid - pivot)
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
        a["pivot"][sl] = np.nan if pivot is None else pivot
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
            pivot=None if np.isnan(a["pivot"][i]).any() else _tuple(a["pivot"][i]),
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
        self._plane_keys.append(key)
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

    # ------------------------------------------------------------------ drums

    def add_drum(
        self,
        center,
        axis,
        radius,
        length,
        material,
        *,
        omega=None,
        rpm=None,
        sides=24,
        thickness=None,
        caps=True,
        _key: str | None = None,
    ) -> Drum:
        """Add a rotating polygonal drum made of kinematic bodies; returns its :class:`Drum` record.

        A hollow drum is not convex, so it is built from ``sides`` box slabs, ``thickness`` thick
        and ``length`` long, whose inner faces are the sides of a regular polygon of inradius
        ``radius`` around the axis (adjacent slabs meet along the polygon's corners and open up
        outwards, so the inside is closed). With ``caps`` two polygonal plates (prisms centred on
        the axis, covering the slabs' outer corners) close the ends at ``+-length / 2``.

        Every part is a kinematic body with angular velocity ``omega * axis`` and the drum centre
        as its pivot (:attr:`body_pivot`); a slab's velocity is ``omega x r``, r from the axis to
        the slab's centre, and the caps only spin. The registered shapes are
        ``"wall_box_{w}x{length}x{thickness}"`` (w = 2 radius tan(pi / sides)) and
        ``"drum_cap_{sides}_{r}x{thickness}"``.

        Args:
            center: (3,) middle of the drum on its axis [m].
            axis: (3,) direction of the axis (any non-zero length) [-]; the drum turns by the
                right-hand rule about it.
            radius: inradius of the inner polygon [m], > 0.
            length: inner length along the axis [m], > 0.
            material: material name.
            omega: angular speed [rad/s] (negative turns the other way); or give ``rpm``.
            rpm: revolutions per minute (2 pi / 60 rad/s each); or give ``omega``.
            sides: number of slabs, >= 3 (default 24).
            thickness: slab and cap thickness [m], default a tenth of ``radius``.
            caps: close the ends with rotating plates (default True).
        """
        key = _key or f"drums[{len(self.drums)}]"
        f = self.file
        c = _vector(center, 3, f"{key}.center", f)
        a = _vector(axis, 3, f"{key}.axis", f)
        if np.linalg.norm(a) < 1e-12:
            raise self._err(
                f"axis {a.tolist()} is zero; give the direction of the drum axis, e.g. [0, 1, 0]", f"{key}.axis"
            )
        a = a / np.linalg.norm(a)
        r = _number(radius, f"{key}.radius", f, positive=True, hint=" (inner radius in m)")
        length = _number(length, f"{key}.length", f, positive=True, hint=" (inner length along the axis in m)")
        n = _integer(sides, f"{key}.sides", f, minimum=3, maximum=1000, hint=" (number of slabs)")
        t = 0.1 * r if thickness is None else _number(thickness, f"{key}.thickness", f, positive=True, hint=" (in m)")
        caps = _boolean(caps, f"{key}.caps", f)
        if (omega is None) == (rpm is None):
            raise self._err(
                "give the rotation speed as exactly one of omega (rad/s) or rpm (revolutions per minute)",
                f"{key}.omega" if omega is None else f"{key}.rpm",
            )
        if omega is not None:
            w = _number(omega, f"{key}.omega", f, hint=" (angular speed in rad/s)")
        else:
            w = _number(rpm, f"{key}.rpm", f, hint=" (revolutions per minute)") * 2.0 * math.pi / 60.0
        mat = self._lookup_material(material, f"{key}.material")
        name = self.material_names[mat]
        radial = _drum_radial(a, n)
        tangent = _cross(np.broadcast_to(a, radial.shape), radial)
        slab = self._box_shape((2.0 * r * math.tan(math.pi / n), length, t))
        quats = np.array([_quat_from_matrix(np.column_stack([tangent[k], a, radial[k]])) for k in range(n)])
        omega_vec = np.broadcast_to(w * a, (n, 3))
        zeros = np.zeros((n, 3))
        idx = [
            self._append(
                self._shape_index[slab],
                mat,
                c + (r + 0.5 * t) * radial,
                quats,
                zeros,
                omega_vec,
                KIND_KINEMATIC,
                lambda i: key,
                np.broadcast_to(c, (n, 3)),
            )
        ]
        if caps:
            rho = (r + t) / math.cos(math.pi / n) ** 2
            cap_name = f"drum_cap_{n}_{rho:.6g}x{t:.6g}"
            spec = {"type": "prism", "n": n, "radius": rho, "height": t}
            base, k = cap_name, 1
            while cap_name in self._shapes and self._shape_specs.get(cap_name) != spec:
                k += 1
                cap_name = f"{base}_{k}"
            if cap_name not in self._shapes:
                self.add_shape(cap_name, ConvexShape.prism(n, rho, t, name=cap_name), _spec=spec)
            e1, e2 = _perpendicular_basis(a)
            q_cap = _quat_from_matrix(np.column_stack([e1, e2, a]))
            ends = np.array([c + (0.5 * length + 0.5 * t) * a, c - (0.5 * length + 0.5 * t) * a])
            idx.append(
                self._append(
                    self._shape_index[cap_name],
                    mat,
                    ends,
                    np.tile(q_cap, (2, 1)),
                    np.zeros((2, 3)),
                    np.tile(w * a, (2, 1)),
                    KIND_KINEMATIC,
                    lambda i: key,
                    np.tile(c, (2, 1)),
                )
            )
        drum = Drum(
            center=_tuple(c),
            axis=_tuple(a),
            radius=r,
            length=length,
            sides=n,
            thickness=t,
            omega=w,
            material=name,
            caps=caps,
            bodies=tuple(int(i) for i in np.concatenate(idx)),
        )
        self.drums.append(drum)
        return drum

    # ------------------------------------------------------------------ emitters

    def emit(
        self,
        shape,
        material,
        count,
        region,
        *,
        weights=None,
        orientation="random",
        seed=0,
        velocity=(0.0, 0.0, 0.0),
        velocity_jitter=0.0,
        scale=None,
        scale_range=None,
        scale_lognormal=None,
        scale_bins=8,
        kind="free",
        spacing=1.1,
        jitter=0.9,
        fill="bottom",
        _key: str | None = None,
    ) -> np.ndarray:
        """Place ``count`` bodies in a box region without overlaps; returns their indices.

        This is the ``[[emitters]]`` table of a scene file (same argument names).

        Placement. Each body gets a cell of a cubic grid filling the region (centred in it); the
        cell side is ``spacing`` times the largest bounding diameter among the emitted bodies, and
        each body's centre of mass is moved from its cell centre by up to ``jitter`` times its free
        room (half the cell minus its bounding radius) along each axis, uniformly at random. So
        every bounding sphere stays inside its own cell: no two emitted bodies overlap and none
        crosses the region's faces. Cells that would cross a plane wall, any body already in the
        scene (a container's slabs, a drum's slabs, earlier bodies and emitters; tested against
        the body's face planes) or that lie beside a drum (within its axial span) without being
        wholly inside it are left out.
        ``fill = "bottom"`` takes the lowest cells first (layers against gravity; within the last
        layer at random), ``fill = "random"`` cells anywhere in the region. Bodies are stored in
        the grid order of their cells. If the region cannot hold ``count`` bodies, SceneError
        (key ``.count``, or ``.region`` when not even one cell fits) says how many fit.

        Everything is deterministic for a given ``seed`` (independent random streams for the
        shape mix, the sizes, the cells, the jitter, the orientations and the velocities) and
        vectorised: 10^6 bodies take a few seconds.

        Args:
            shape: a shape name (or :class:`ConvexShape`), a list of names (a mix; ``weights``
                gives their proportions, equal by default), or a dict name -> weight. The counts
                follow the weights exactly (largest remainders), in random order.
            material: material name.
            count: number of bodies, >= 1.
            region: the box to fill, ``{"min": (x0, y0, z0), "max": (x1, y1, z1)}`` or a pair
                ``(min, max)`` [m].
            weights: proportions of a list of shapes (non-negative, not all zero).
            orientation: ``"random"`` (uniform) or ``"aligned"`` (input axes along world axes).
            seed: integer >= 0.
            velocity: (3,) initial velocity of every body [m/s].
            velocity_jitter: each velocity component gets a uniform random addition in
                ``[-velocity_jitter, velocity_jitter]`` [m/s].
            scale: one size factor for all bodies (default 1), or
            scale_range: ``(lo, hi)``, factors uniform in [lo, hi], or
            scale_lognormal: ``{"mean": m, "sigma": s}``: ln(factor) normal with standard deviation
                s, its mean chosen so that the factors average m; truncated at 3 s either side.
            scale_bins: a distribution is quantised into this many equal bins (in log for the
                lognormal), each body taking its bin's centre, so at most ``scale_bins`` new shapes
                per base shape are registered (``ConvexShape.scaled``, named ``"{name}_x{factor}"``).
                Factors scale about each shape's input origin (its centroid but for rocks).
            kind: ``"free"`` (default), ``"fixed"`` or ``"kinematic"``.
            spacing: cell side over the largest bounding diameter, >= 1 (default 1.1).
            jitter: fraction of each body's free room used for its random offset, in [0, 1].
            fill: ``"bottom"`` (default) or ``"random"``.
        """
        key = _key or f"emitters[{len(self.emitters)}]"
        f = self.file
        count = _integer(count, f"{key}.count", f, minimum=1, hint=" (number of bodies to place)")
        lo, hi = _region(region, f"{key}.region", f)
        base, frac = self._emitter_shapes(shape, weights, key)
        mat = self._lookup_material(material, f"{key}.material")
        kind_code = KINDS.index(_choice(kind, KINDS, f"{key}.kind", f, what="body kind"))
        orientation = _choice(orientation, ORIENTATIONS, f"{key}.orientation", f, what="orientation")
        fill = _choice(fill, FILLS, f"{key}.fill", f, what="fill order")
        seed = _integer(seed, f"{key}.seed", f, minimum=0)
        vel = _vector(velocity, 3, f"{key}.velocity", f)
        vj = _number(velocity_jitter, f"{key}.velocity_jitter", f, nonneg=True, hint=" (in m/s)")
        spacing = _number(spacing, f"{key}.spacing", f, hint=" (cell side over the largest bounding diameter)")
        if spacing < 1.0:
            raise self._err(
                f"must be >= 1 (narrower cells would let bounding spheres overlap), got {spacing:g}",
                f"{key}.spacing",
            )
        jitter = _number(jitter, f"{key}.jitter", f, nonneg=True)
        if jitter > 1.0:
            raise self._err(f"must be in [0, 1] (a fraction of each body's free room), got {jitter:g}", f"{key}.jitter")
        bins = _integer(scale_bins, f"{key}.scale_bins", f, minimum=1, maximum=64)
        sample_scales = _scale_sampler(scale, scale_range, scale_lognormal, bins, key, f)
        if kind_code == KIND_FIXED and (vj > 0.0 or np.any(vel != 0.0)):
            raise self._err(
                "fixed bodies cannot move; remove velocity and velocity_jitter or use kind = 'kinematic'",
                f"{key}.velocity",
            )
        self._check_capacity(count, lo, hi, base, frac, sample_scales, spacing, key)

        streams = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(6)]
        rng_shape, rng_scale, rng_cells, rng_jitter, rng_orient, rng_vel = streams
        label = rng_shape.permutation(np.repeat(np.arange(len(base)), _largest_remainder(count, frac)))
        bin_index, values = sample_scales(rng_scale, count)
        combo, inverse = np.unique(label * len(values) + bin_index, return_inverse=True)
        combo_shape = np.array(
            [self._scaled_shape(base[int(cb) // len(values)], float(values[int(cb) % len(values)])) for cb in combo],
            dtype=np.int32,
        )
        shapes = list(self._shapes.values())
        combo_radius = np.array([shapes[s].radius for s in combo_shape])
        rows = combo_shape[inverse]
        radius = combo_radius[inverse]
        r_max = float(combo_radius.max())
        cell = spacing * 2.0 * r_max
        centres = self._emitter_cells(lo, hi, cell, count, fill, rng_cells, key, r_max, spacing)
        room = jitter * np.maximum(0.5 * cell - radius, 0.0)
        centres = centres + rng_jitter.uniform(-1.0, 1.0, size=(count, 3)) * room[:, None]
        if orientation == "random":
            q = rng_orient.normal(size=(count, 4))
            norm = np.sqrt(np.einsum("ij,ij->i", q, q))
            q = np.where(norm[:, None] > 1e-12, q / np.maximum(norm, 1e-300)[:, None], [0.0, 0.0, 0.0, 1.0])
        else:
            q = np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0]), (count, 4))
        v = np.broadcast_to(vel, (count, 3))
        if vj > 0.0:
            v = v + rng_vel.uniform(-vj, vj, size=(count, 3))
        t_in = np.array([self._shape_frames[s][1] for s in range(len(self._shape_frames))])[rows]
        positions = centres - _quat_rotate(q, t_in) if np.any(t_in) else centres
        idx = self._append(rows, mat, positions, q, v, np.zeros((count, 3)), kind_code, lambda i: key)
        self.emitters.append({"key": key, "count": count, "first": int(idx[0]), "last": int(idx[-1])})
        return idx

    def _check_capacity(self, count, lo, hi, base, frac, sample_scales, spacing, key):
        """Reject a count the scene or the region cannot hold, by arithmetic before any per-body array.

        Every cell is at least ``spacing`` times the largest bounding diameter among the shapes that
        get bodies, each at its smallest size factor, so the region holds at most that many cells.
        """
        if self._n + count > MAX_BODIES:
            raise self._err(
                f"count = {count} would make {self._n + count:.3g} bodies, more than a scene can hold "
                f"({MAX_BODIES:.0e}); lower count",
                f"{key}.count",
            )
        per_shape = _largest_remainder(count, frac)
        _, factors = sample_scales(np.random.default_rng(0), 0)
        shapes = list(self._shapes.values())
        r_low = max(shapes[b].radius for b, c in zip(base, per_shape, strict=True) if c > 0) * float(np.min(factors))
        cell = spacing * 2.0 * r_low
        cells = np.floor((hi - lo) / cell * (1.0 + 1e-12))
        capacity = math.prod(int(c) for c in cells)
        # The grid scan gives the exact number (walls and bodies block cells) and the better message;
        # only counts whose per-body arrays would be large are cut here.
        if count > capacity and count > _EMITTER_CHUNK and capacity > 0:
            raise self._err(
                f"the region holds at most {capacity} bodies, fewer than count = {count}: it fits at most "
                f"{' x '.join(str(int(c)) for c in cells)} cells of {cell:.4g} m (spacing {spacing:g} x the largest "
                f"bounding diameter at the smallest size, {2.0 * r_low:.4g} m); lower count or enlarge the region",
                f"{key}.count",
            )

    def _emitter_shapes(self, shape, weights, key) -> tuple[list[int], np.ndarray]:
        """Shape indices and normalised weights of an emitter's ``shape`` (and ``weights``)."""
        f = self.file
        if isinstance(shape, dict):
            if weights is not None:
                raise self._err("give the weights either in the shape table or as weights, not both", f"{key}.weights")
            names = list(shape)
            weights = [shape[n] for n in names]
            wkey = [f"{key}.shape.{n}" for n in names]
        elif isinstance(shape, list | tuple):
            names = list(shape)
            wkey = [f"{key}.weights[{i}]" for i in range(len(names))]
        else:
            if weights is not None:
                raise self._err(
                    "weights go with a list of shapes, e.g. shape = ['cube', 'rock'] and weights = [2, 1]",
                    f"{key}.weights",
                )
            names, weights, wkey = [shape], None, [f"{key}.weights"]
        if not names:
            raise self._err("the list of shapes is empty; give at least one shape name", f"{key}.shape")
        index = []
        for i, name in enumerate(names):
            sub = f"{key}.shape" if len(names) == 1 else f"{key}.shape[{i}]"
            if isinstance(shape, dict):
                sub = f"{key}.shape.{name}"
            s = self._resolve_shape(name, sub)
            if s in index:
                raise self._err(f"shape {self.shape_names[s]!r} is listed twice; list each shape once", sub)
            index.append(s)
        if weights is None:
            frac = np.full(len(index), 1.0 / len(index))
        else:
            if not isinstance(weights, list | tuple | np.ndarray) or len(weights) != len(index):
                raise self._err(
                    f"expected {len(index)} weights, one per shape, got {_typename(weights)}", f"{key}.weights"
                )
            frac = np.array([_number(wt, wkey[i], f, nonneg=True) for i, wt in enumerate(weights)])
            if frac.sum() <= 0.0:
                raise self._err("the weights are all zero; give at least one positive weight", f"{key}.weights")
            frac = frac / frac.sum()
        return index, frac

    def _scaled_shape(self, base: int, factor: float) -> int:
        """Index of shape ``base`` scaled by ``factor`` (registered once as ``"{name}_x{factor}"``)."""
        if factor == 1.0:
            return base
        cache = (base, factor)
        if cache in self._scaled:
            return self._scaled[cache]
        src = self.shape_names[base]
        name = stem = f"{src}_x{factor:.6g}"
        k = 1
        while name in self._shapes:
            k += 1
            name = f"{stem}_{k}"
        shape = list(self._shapes.values())[base].scaled(factor)
        shape.name = name
        self.add_shape(name, shape, _spec=_scaled_spec(self._shape_specs.get(src), factor))
        self._scaled[cache] = self._shape_index[name]
        return self._scaled[cache]

    def _emitter_cells(self, lo, hi, cell, count, fill, rng, key, r_max, spacing) -> np.ndarray:
        """(count, 3) centres of the free grid cells chosen for an emitter (see :meth:`emit`)."""
        ext = hi - lo
        n = np.floor(ext / cell * (1.0 + 1e-12)).astype(np.int64)
        sizes = f"cells of {cell:.4g} m (spacing {spacing:g} x the largest bounding diameter {2.0 * r_max:.4g} m)"
        if np.any(n < 1):
            ax = int(np.flatnonzero(n < 1)[0])
            raise self._err(
                f"the region is {ext[ax]:.4g} m along {'xyz'[ax]}, too small for one body: bodies are placed in "
                f"{sizes}; make the region at least {cell:.4g} m along {'xyz'[ax]}, or use smaller shapes or a "
                "smaller spacing",
                f"{key}.region",
            )
        origin = lo + 0.5 * (ext - n * cell)
        g = np.asarray(self.gravity, dtype=np.float64)
        up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0.0 else np.array([0.0, 0.0, 1.0])
        k = int(np.argmax(np.abs(up)))
        ascending = bool(up[k] >= 0.0)
        ax_a, ax_b = (i for i in range(3) if i != k)
        nb_, nk = int(n[ax_b]), int(n[k])
        per_layer = int(n[ax_a]) * nb_
        total = per_layer * nk
        if per_layer > _MAX_EMITTER_CELLS or (fill == "random" and total > _MAX_EMITTER_CELLS):
            what = "one layer of" if per_layer > _MAX_EMITTER_CELLS else "the"
            raise self._err(
                f"{what} region holds {per_layer if what != 'the' else total:.3g} {sizes}, far more than "
                f"{count} bodies need (the limit is {_MAX_EMITTER_CELLS:.0e} cells); make the region smaller"
                + (' or use fill = "bottom"' if fill == "random" else ""),
                f"{key}.region",
            )
        obstacles = _Obstacles(self, origin, origin + n * cell, cell)
        chunk_layers = max(1, _EMITTER_CHUNK // per_layer)
        found, got_layer, got_m = 0, [], []
        for l0 in range(0, nk, chunk_layers):
            l1 = min(nk, l0 + chunk_layers)
            layer = np.repeat(np.arange(l0, l1, dtype=np.int64), per_layer)
            m = np.tile(np.arange(per_layer, dtype=np.int64), l1 - l0)
            gi = _cell_index(layer, m, k, ax_a, ax_b, nb_, nk, ascending)
            krange = (l0, l1 - 1) if ascending else (nk - l1, nk - 1 - l0)

            def local_of(g, l0=l0):
                lay = g[:, k] if ascending else nk - 1 - g[:, k]
                return (lay - l0) * per_layer + g[:, ax_a] * nb_ + g[:, ax_b]

            blocked = obstacles.blocked(origin + (gi + 0.5) * cell, krange, k, local_of)
            keep = ~blocked
            got_layer.append(layer[keep])
            got_m.append(m[keep])
            found += int(keep.sum())
            if fill == "bottom" and found >= count:
                break
        if found < count:
            per = found / nk if found else per_layer
            need = math.ceil(count / max(per, 1e-300)) * cell
            msg = (
                f"the region holds at most {found} bodies, fewer than count = {count}: it is a grid of "
                f"{n[0]} x {n[1]} x {n[2]} {sizes}"
            )
            if total > found:
                msg += f", and {total - found} of its {total} cells cross walls or bodies already in the scene"
            msg += (
                f". Lower count to {found}, or enlarge the region (to about {need:.3g} m along {'xyz'[k]} at this "
                "width, or wider), or lower spacing"
            )
            raise self._err(msg, f"{key}.count")
        layer = np.concatenate(got_layer)
        m = np.concatenate(got_m)
        if fill == "bottom":
            pick = np.lexsort((rng.random(found), layer))[:count]
        else:
            pick = rng.choice(found, size=count, replace=False)
        pick.sort()
        gi = _cell_index(layer[pick], m[pick], k, ax_a, ax_b, nb_, nk, ascending)
        return origin + (gi + 0.5) * cell

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

    def time_step(self) -> TimeStep:
        """The time step of a run and its bounds (host-only: ``polydem validate`` needs no Warp).

        The period is ``2 pi sqrt(m / k_n)`` of the lightest free body (mass m) against the stiffest
        pair: ``k_n`` is the secant stiffness of a face contact of area ``V^(2/3)`` pressed to 0.1%
        of the size ``V^(1/3)`` (:func:`reference_stiffness`), or a larger tangential stiffness.
        ``dt = "auto"`` takes 1/50 of it; a given dt must not exceed 1/8 of it (SceneError, key
        ``simulation.dt``).
        """
        if self._n == 0:
            raise self._err("the scene has no bodies; add at least one with [[bodies]] or Scene.add_body()", "bodies")
        table = self.pair_table()
        law, m = table["law"], float(table["exponent"])
        k = np.asarray(table["k"], dtype=np.float64)
        kt = np.asarray(table["tangential_stiffness"], dtype=np.float64)
        shapes = list(self._shapes.values())
        mass = np.asarray(self.body_mass(), dtype=np.float64)
        free = self.body_kind == KIND_FREE
        # The lightest free body (or, with none, the lightest body with a mass) and the stiffest pair
        # set the time step and default spring.
        pool = free if free.any() else mass > 0.0
        if not pool.any():
            raise self._err(
                "no body has a mass (all are fixed with zero volume), so no time step can be derived; add a free "
                "body or give dt in seconds",
                "simulation.dt",
            )
        light = int(np.argmin(np.where(pool, mass, np.inf)))
        v_ref = shapes[int(self.body_shape[light])].volume
        k_n = reference_stiffness(law, k, m, v_ref)
        kt = np.where(np.isnan(kt), k_n, kt)
        with np.errstate(all="ignore"):
            stiffest = max(float(np.max(k_n)), float(np.max(kt)))
            period = float(2.0 * np.pi * np.sqrt(mass[light] / stiffest))
        recommended = period / STEPS_PER_CONTACT_PERIOD
        limit = period * MAX_DT_FRACTION
        if not (math.isfinite(period) and period > 0.0):
            raise self._err(
                f"the contact period 2 pi sqrt(m / k) of body {light} (mass {mass[light]:.3g} kg, stiffest contact "
                f"{stiffest:.3g} N/m) is {period:.3g} s, so no time step can be derived; check the materials' density "
                "and k",
                "simulation.dt",
            )
        if self.dt == "auto":
            dt = recommended
        else:
            dt = float(self.dt)
            if dt > limit:
                raise self._err(
                    f"time step {dt:.3g} s is above the stable limit {limit:.3g} s for the stiffest contact and the "
                    f'lightest body (recommended {recommended:.3g} s); use dt = "auto" or a smaller value',
                    "simulation.dt",
                )
        return TimeStep(
            dt=dt, recommended=recommended, limit=limit, period=period, lightest=light, tangential_stiffness=kt
        )

    def _body_label(self, i: int) -> str:
        """``body 12 (shape 'cube', free, from emitters[0])``: how messages name a body."""
        s = self.shape_names[int(self._arrays["shape"][i])]
        kind = KINDS[int(self._arrays["kind"][i])]
        where = next((f", from {e['key']}" for e in self.emitters if e["first"] <= i <= e["last"]), "")
        return f"body {i} (shape {s!r}, {kind}{where})"

    def _check_float32(self, a):
        """Shapes, masses, inertias, stiffnesses and the power law within float32 (see F32_LOW)."""
        lo, hi = F32_LOW, F32_HIGH
        shapes = list(self._shapes.values())
        names = self.shape_names
        # Overlap volumes and their first moments (~ size^4) are the largest powers of a length the
        # narrow phase sums, so the bounding radius r needs r^4 within [lo, hi].
        r_lo, r_hi = lo**0.25, hi**0.25
        for s in np.unique(a["shape"]):
            sh = shapes[int(s)]
            if not r_lo <= sh.radius <= r_hi:
                i = int(np.flatnonzero(a["shape"] == s)[0])
                raise self._err(
                    f"shape {names[s]!r} (used by body {i}) has a bounding radius of {sh.radius:.3g} m: too "
                    f"{'small' if sh.radius < 1.0 else 'large'} for the simulator's float32 arithmetic, whose overlap "
                    f"volumes and their moments (~ radius^4) must stay between {lo:.2g} and {hi:.2g}; give the shape a "
                    f"bounding radius between {r_lo:.2g} m and {r_hi:.2g} m",
                    f"shapes.{names[s]}",
                )
        mats = list(self._materials.values())
        for mat in mats:
            for attr in ("k", "tangential_stiffness"):
                value = getattr(mat, attr)
                if value is not None and not lo <= value <= hi:
                    raise self._err(
                        f"{value:g} is outside the range the simulator's float32 arithmetic can use ({lo:.2g} to "
                        f"{hi:.2g}, float32's normal range with a margin of {_F32_MARGIN:g} for products); give a "
                        "value in that range",
                        f"materials.{mat.name}.{attr}",
                    )
        free = a["kind"] == KIND_FREE
        if not free.any():
            return
        combo = np.unique(a["shape"][free].astype(np.int64) * len(mats) + a["material"][free])
        for c in combo.tolist():
            sh, mat = shapes[c // len(mats)], mats[c % len(mats)]
            mass = mat.density * sh.volume
            inertia = mat.density * np.asarray(sh.inertia)
            if lo <= mass <= hi and lo <= inertia.min() and inertia.max() <= hi:
                continue
            i = int(np.flatnonzero(free & (a["shape"] == c // len(mats)) & (a["material"] == c % len(mats)))[0])
            rho_lo = max(lo / sh.volume, lo / float(np.min(sh.inertia)))
            rho_hi = min(hi / sh.volume, hi / float(np.max(sh.inertia)))
            fix = (
                f"use a density between {rho_lo:.3g} and {rho_hi:.3g} kg/m^3 for this shape"
                if rho_lo <= rho_hi
                else "no density works for this shape: make it less elongated or change its size"
            )
            raise self._err(
                f"{self._body_label(i)} of material {mat.name!r} would have a mass of {mass:.3g} kg and principal "
                f"moments of inertia of {inertia.min():.3g} to {inertia.max():.3g} kg m^2; the simulator stores them "
                f"in float32, which needs values between {lo:.2g} and {hi:.2g} (float32's normal range with a margin "
                f"of {_F32_MARGIN:g} for products); {fix}",
                f"materials.{mat.name}.density",
            )
        law, m = mats[0].law, mats[0].exponent
        if law != "power":
            return
        # The kernels evaluate W = k V^m / m and W' = k V^(m-1) in float32; at the reference
        # overlap (0.1% of a free body's volume) V^m must stay in range, which bounds m.
        vols = np.array([sh.volume for sh in shapes])[np.unique(a["shape"][free])]
        caps = []
        v_small, v_large = REFERENCE_DEPTH * vols.min(), REFERENCE_DEPTH * vols.max()
        if v_small < 1.0:
            caps.append((_ln(lo) / _ln(v_small), v_small))
        if v_large > 1.0:
            caps.append((_ln(hi) / _ln(v_large), v_large))
        if caps:
            m_max, v_ref = min(caps)
            if m > m_max:
                raise self._err(
                    f"m = {m:g} is too large for the simulator's float32 arithmetic with these bodies: at the "
                    f"reference overlap of a contact (0.1% of a free body's volume, V = {v_ref:.3g} m^3) the law's "
                    f"V^m = {_fmt_exp(m * _ln(v_ref))} is outside {lo:.2g} to {hi:.2g}; use m between 1 and "
                    f"{m_max:.3g} for bodies of these sizes (or law = 'hertz')",
                    f"materials.{mats[0].name}.m",
                )

    def _check_loads(self, a, ts: TimeStep) -> list[str]:
        """Contacts stiff enough for the bodies' weight and initial speeds; returns warnings.

        For each free (shape, material) the overlap depth d of a face contact (area A = V^(2/3),
        size L = V^(1/3)) is solved from the law W = k V^m / m (k of the softest pair it can
        meet): under the body's weight M g, where something can carry it (a plane or a fixed or
        kinematic body), W'(A d) A = M g; at the fastest initial speed v, where something can be
        hit, W(A d) = M v^2 / 2. The linear law's force k A does not grow with depth: the weight
        needs the contact area M g / k, which an edge or corner contact reaches at about
        d / L = M g / (k A). Then:

        * weight, d / L above OVERLAP_ERROR, dt = "auto": SceneError: the body sinks through what
          carries it, and the automatic time step (set at 0.1% overlap) is far longer than the
          time the body takes to fall its own size. The fix names the k that keeps d / L at
          OVERLAP_WARNING.
        * weight, m > 2 (stiffening laws): SceneError where the step is unstable at d,
          dt > 2 sqrt(M / K(d)) with the tangent stiffness K(d) = k (m - 1) (A d)^(m - 2) A^2
          (1/pi of the local period).
        * otherwise d / L above OVERLAP_WARNING (or an unstable step at the impact overlap): a
          warning. Initial speeds only warn: the bodies need not meet anything.
        """
        free = a["kind"] == KIND_FREE
        if not free.any():
            return []
        table = self.pair_table()
        mats = list(self._materials.values())
        law, m = table["law"], float(table["exponent"])
        k_pair = np.asarray(table["k"], dtype=np.float64)
        present = set(np.unique(a["material"]).tolist())
        present.update(self._material_index[p.material] for p in self._planes)
        present = np.array(sorted(present))
        support = bool(self._planes) or bool((a["kind"] != KIND_FREE).any())
        partners = bool(self._planes) or self._n >= 2
        g = float(np.linalg.norm(self.gravity))
        speeds = np.linalg.norm(a["velocity"][a["kind"] != KIND_FIXED], axis=1)
        v_hit = float(speeds.max()) if partners and speeds.size else 0.0
        if not ((support and g > 0.0) or v_hit > 0.0):
            return []
        shapes = list(self._shapes.values())
        dt = ts.dt
        out = []
        combo = np.unique(a["shape"][free].astype(np.int64) * len(mats) + a["material"][free])
        for c in combo.tolist():
            sh, mi = shapes[c // len(mats)], c % len(mats)
            mat = mats[mi]
            i = int(np.flatnonzero(free & (a["shape"] == c // len(mats)) & (a["material"] == mi))[0])
            mass = mat.density * sh.volume
            ln_a, ln_l = (2.0 / 3.0) * _ln(sh.volume), _ln(sh.volume) / 3.0
            j = int(present[np.argmin(k_pair[mi, present])])
            k = float(k_pair[mi, j])
            soft = min((mats[mi], mats[j]), key=lambda x: x.k).name
            label = f"{self._body_label(i)} of material {mat.name!r}"
            label += f" against {mats[j].name!r}" if j != mi else ""
            loads = []
            if support and g > 0.0:
                t_scale = math.sqrt(2.0 * _exp(ln_l) / g)
                loads.append(
                    (
                        mass * g,
                        f"under its own weight ({mass * g:.3g} N) it would sink",
                        "into what carries it",
                        f"the {t_scale:.3g} s it takes to fall its own size",
                        t_scale,
                    )
                )
            if v_hit > 0.0:
                t_scale = _exp(ln_l) / v_hit
                loads.append(
                    (
                        -0.5 * mass * v_hit * v_hit,  # negative: an energy, not a force
                        f"hitting a body or wall at the scene's fastest initial speed ({v_hit:.3g} m/s) it would sink",
                        "into what it hits",
                        f"the {t_scale:.3g} s it takes to cross its own size at that speed",
                        t_scale,
                    )
                )
            for load, cause, into, scale, t_scale in loads:
                ln_ad = _face_overlap(load, m, _ln(k), ln_a, ln_l)
                rel = _exp(ln_ad - ln_a - ln_l)
                ln_target = _ln(OVERLAP_WARNING) + ln_a + ln_l
                unstable = False
                if m > 2.0:
                    ln_kt = _ln(k) + _ln(m - 1.0) + (m - 2.0) * ln_ad + 2.0 * ln_a
                    unstable = ln_kt > _ln(4.0 * mass) - 2.0 * _ln(dt)
                    if self.dt == "auto":
                        # The auto step goes like 1/sqrt(k), so K(d) dt^2 / k depends on d only: the fix
                        # keeps d where dt is at most 1/8 of the local period, K dt^2 <= M (pi / 4)^2.
                        ln_bound = 2.0 * _ln(math.pi / 4.0) + _ln(mass) - 2.0 * _ln(dt) - _ln(k) - _ln(m - 1.0)
                        ln_target = min(ln_target, (ln_bound - 2.0 * ln_a) / (m - 2.0))
                depth = f"{cause} about {_fmt_exp(ln_ad - ln_a - ln_l)} times its size ({_exp(ln_l):.3g} m) {into}"
                if not unstable and rel <= OVERLAP_WARNING:
                    continue
                ln_need = _stiffness_for(load, m, ln_target, ln_a, ln_l)
                weight = load > 0.0
                if unstable:
                    k_tan = _exp(_ln(k) + _ln(m - 1.0) + (m - 2.0) * ln_ad + 2.0 * ln_a)
                    depth += (
                        f", where the law (m = {m:g} > 2 stiffens with depth) has a stiffness of {k_tan:.3g} N/m "
                        f"and the time step {dt:.3g} s is above the stable {2.0 * math.sqrt(mass / k_tan):.3g} s"
                    )
                if ln_need > _ln(F32_HIGH):
                    fix = f"no k within float32's range (up to {F32_HIGH:.2g}) is stiff enough: " + (
                        "use a smaller m (W = k V^m / m gives almost no force at small overlaps when m is large)"
                        if law == "power"
                        else "use smaller densities or larger bodies"
                    )
                elif unstable and self.dt != "auto":
                    fix = 'lower dt (or use dt = "auto" with a larger k)'
                else:
                    fix = f"raise k of {soft!r} to at least {_exp(ln_need):.3g} {_LAW_UNITS[law]}"
                if weight and (unstable or (rel > OVERLAP_ERROR and self.dt == "auto")):
                    why = (
                        f" (the automatic time step, {dt:.3g} s, is {dt / t_scale:.3g} times {scale})"
                        if self.dt == "auto" and not unstable
                        else ""
                    )
                    head = "too soft" if rel > OVERLAP_ERROR else "unstable at this time step"
                    raise self._err(
                        f"the contacts of {label} are {head}: {depth}{why}; {fix}"
                        + (" (a pair's k is the harmonic mean of its materials' k)" if fix.startswith("raise") else ""),
                        "simulation.dt" if fix.startswith("lower") else f"materials.{soft}.k",
                    )
                out.append((rel, f"the contacts of {label} are soft: {depth}; {fix} (materials.{soft}.k)"))
        if not out:
            return []
        # One line for the scene: the softest case, and how many more there are.
        out.sort(key=lambda x: -x[0])
        more = f" ({len(out) - 1} more shapes or materials are soft too)" if len(out) > 1 else ""
        return [out[0][1] + more]

    def validate(self) -> Scene:
        """Check the whole scene; raise :class:`SceneError` on the first problem, else return self.

        Checks: simulation settings; all materials share one contact law; at least one body; every
        body's shape and material index exists; all numbers finite; unit quaternions; valid kinds;
        fixed bodies at rest; free bodies have a shape with positive volume and inertia; planes use
        registered materials and have unit normals; only kinematic bodies have pivots; precision is
        float32; the device name and the output settings are valid. Then what a run needs:

        * float32: shape sizes, masses, inertias, stiffnesses and the power law's V^m within
          [F32_LOW, F32_HIGH] (float32's normal range, 10^6 from both ends);
        * the time step (:meth:`time_step`): finite, a given dt within the stable limit, and the
          steps of the run (``duration / dt``) at most MAX_STEPS;
        * contacts stiff enough for the bodies' weight and initial speeds (see ``_check_loads``);
        * initial overlaps: a free body deep behind a plane wall or deep inside another body
          (by more than INITIAL_OVERLAP_ERROR of its thickness) is an error; overlaps above
          INITIAL_OVERLAP_WARNING are warnings.

        Warnings are issued as :class:`SceneWarning` (:func:`warnings.warn`; not again by a
        repeated call that finds the same) and kept in :attr:`warnings` (a list of strings).
        """
        self.warnings = []
        f = self.file
        self.gravity = tuple(_vector(list(self.gravity), 3, "simulation.gravity", f).tolist())
        self.dt = self._check_dt(self.dt)
        self.device = self._check_device(self.device)
        self.precision = self._check_precision(self.precision)
        self.output = self._check_output(self.output)
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
        pivoted = np.flatnonzero(~np.isnan(a["pivot"]).any(axis=1) & (a["kind"] != KIND_KINEMATIC))
        if pivoted.size:
            i = int(pivoted[0])
            raise self._err(
                "only a kinematic body can turn about a pivot; use kind = 'kinematic' or leave pivot out",
                f"bodies[{i}].pivot",
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
        self._check_float32(a)
        ts = self.time_step()
        self._check_steps(ts)
        found = self._check_loads(a, ts)
        found += self._check_initial_overlaps(a)
        # A run validates twice (loading the file, building the Model): say each thing once.
        if found != self._warned:
            for message in found:
                warnings.warn(f"{self.file}: {message}" if self.file else message, SceneWarning, stacklevel=2)
        self._warned = found
        self.warnings = found
        return self

    def _check_steps(self, ts: TimeStep):
        if self.duration is not None:
            steps, key = math.ceil(self.duration / ts.dt - 1e-9), "simulation.duration"
        elif self.steps is not None:
            steps, key = self.steps, "simulation.steps"
        else:
            return
        if steps > MAX_STEPS:
            raise self._err(
                f"a run of {steps:.3g} steps of {ts.dt:.3g} s is more than the simulator counts ({MAX_STEPS}, a "
                "32-bit step counter); shorten the run"
                + (" or use a larger time step (a softer k gives a longer automatic one)" if self.duration else ""),
                key,
            )

    def _check_initial_overlaps(self, a) -> list[str]:
        """Free bodies that start behind a plane wall or inside another body (see :meth:`validate`).

        Plane walls: the exact depth of the body's lowest vertex behind the plane, over the body's
        thickness along the normal. Body pairs: candidates from a k-d tree on the centres (bounding
        spheres that meet, one body free), then the separating-axis test over both bodies' face
        normals, the line of centres and, for bodies with few edge directions, the cross products
        of their edges: the smallest overlap of the projections is the penetration depth (an upper
        bound where edge axes are skipped), taken over the thinner body's thickness along that axis.
        """
        records = _plane_overlaps(self, a) + _pair_overlaps(self, a)
        if not records:
            return []
        records.sort(key=lambda r: -r[0])
        deep = [r for r in records if r[0] > INITIAL_OVERLAP_ERROR]
        if deep:
            rel, depth, i, what, basis, fix = deep[0]
            more = f" ({len(deep) - 1} more bodies start this deep)" if len(deep) > 1 else ""
            share = "wholly" if rel >= 1.0 else f"{rel:.0%} of {basis}"
            raise self._err(
                f"{self._body_label(i)} starts {depth:.3g} m {what} ({share}): the contact would throw it out at a "
                f"high speed{more}; {fix}",
                f"bodies[{i}].position",
            )
        shown = "; ".join(
            f"{self._body_label(i)} {d:.3g} m {what} ({rel:.1%})" for rel, d, i, what, _, _ in records[:3]
        )
        more = f", and {len(records) - 3} more" if len(records) > 3 else ""
        return [
            f"{len(records)} initial overlaps of more than {INITIAL_OVERLAP_WARNING:.0%} of a body's thickness, "
            f"pushed apart at the start: {shown}{more}; move the bodies apart"
        ]

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
            device=sim.get("device"),
            precision=sim.get("precision", "float32"),
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
            if "pivot" in body and "velocity" in body:
                raise SceneError(
                    "a body turning about a pivot gets its velocity from angular_velocity x (centroid - pivot); "
                    "give either velocity or pivot, not both",
                    f"{key}.velocity",
                    file,
                )
            scene.add_body(
                body["shape"],
                body["material"],
                position=body["position"],
                orientation=orientation,
                velocity=body.get("velocity", (0.0, 0.0, 0.0)),
                angular_velocity=body.get("angular_velocity", (0.0, 0.0, 0.0)),
                kind=body.get("kind", "free"),
                pivot=body.get("pivot"),
                _key=key,
            )
        walls = data.get("walls", [])
        if not isinstance(walls, list):
            raise SceneError(f"expected an array of tables [[walls]], got {_typename(walls)}", "walls", file)
        for j, wall in enumerate(walls):
            key = f"walls[{j}]"
            wall = _table(wall, key, file, what="a [[walls]] table")
            if "type" not in wall:
                raise SceneError("missing required key 'type' ('plane', 'box' or 'drum')", f"{key}.type", file)
            kind = _choice(wall["type"], _WALL_KEYS, f"{key}.type", file, what="wall type")
            _check_keys(
                wall, _WALL_KEYS[kind], key, file, required=_WALL_REQUIRED[kind], context=f" for type = {kind!r}"
            )
            if kind == "plane":
                scene.add_plane(wall["point"], wall["normal"], wall["material"], _key=key)
            elif kind == "box":
                scene.add_box_container(
                    wall["center"],
                    wall["inner_size"],
                    wall["material"],
                    wall_thickness=wall.get("wall_thickness"),
                    open_top=wall.get("open_top", True),
                    _key=key,
                )
            else:
                scene.add_drum(
                    wall["center"],
                    wall["axis"],
                    wall["radius"],
                    wall["length"],
                    wall["material"],
                    omega=wall.get("omega"),
                    rpm=wall.get("rpm"),
                    sides=wall.get("sides", 24),
                    thickness=wall.get("thickness"),
                    caps=wall.get("caps", True),
                    _key=key,
                )
        emitters = data.get("emitters", [])
        if not isinstance(emitters, list):
            raise SceneError(f"expected an array of tables [[emitters]], got {_typename(emitters)}", "emitters", file)
        for j, emitter in enumerate(emitters):
            key = f"emitters[{j}]"
            emitter = _table(emitter, key, file, what="an [[emitters]] table")
            _check_keys(
                emitter,
                _EMITTER_KEYS,
                key,
                file,
                required=("shape", "material", "count", "region"),
                hints=_EMITTER_HINTS,
            )
            scene.emit(**emitter, _key=key)
        if "output" in data:
            scene.output = Output.from_dict(data["output"], file)
        if validate:
            scene.validate()
        return scene

    def to_dict(self) -> dict:
        """The scene as the nested dict of a scene file (``Scene.from_dict(scene.to_dict())`` rebuilds it).

        Shapes built from a scene file keep their spec; others (including the scaled shapes of
        emitters) are written as ``type = "points"`` with their vertices in the input frame. Box
        containers, drums and emitters come back as the bodies they made (drum parts as kinematic
        bodies with their pivot).
        """
        sim = {"name": self.name, "dt": self.dt, "gravity": list(self.gravity), "precision": self.precision}
        if self.description:
            sim["description"] = self.description
        if self.steps is not None:
            sim["steps"] = self.steps
        if self.duration is not None:
            sim["duration"] = self.duration
        if self.device is not None:
            sim["device"] = self.device
        shapes = {}
        for name, shape in self._shapes.items():
            spec = self._shape_specs.get(name)
            if spec is None:
                spec = {"type": "points", "points": shape.to_input_frame(shape.vertices).tolist()}
            shapes[name] = dict(spec)
        n = self._n
        a = {name: self._arrays[name][:n] for name, _, _ in _BODY_FIELDS}
        frames = self._shape_frames
        q_in = np.array([fr[0] for fr in frames]).reshape(-1, 4)[a["shape"]]
        t_in = np.array([fr[1] for fr in frames]).reshape(-1, 3)[a["shape"]]
        q_user = _quat_mul(a["orientation"], _quat_conj(q_in))
        q_user /= np.sqrt(np.einsum("ij,ij->i", q_user, q_user))[:, None]
        pos = a["position"] - _quat_rotate(q_user, t_in)
        shape_names, material_names = self.shape_names, self.material_names
        has_pivot = ~np.isnan(a["pivot"]).any(axis=1)
        bodies = []
        for s, m, p, q, v, w, kind, pivoted, pivot in zip(
            a["shape"].tolist(),
            a["material"].tolist(),
            pos.tolist(),
            q_user.tolist(),
            a["velocity"].tolist(),
            a["angular_velocity"].tolist(),
            a["kind"].tolist(),
            has_pivot.tolist(),
            a["pivot"].tolist(),
            strict=True,
        ):
            body = {
                "shape": shape_names[s],
                "material": material_names[m],
                "position": p,
                "orientation": q,
                "velocity": v,
                "angular_velocity": w,
                "kind": KINDS[kind],
            }
            if pivoted:
                del body["velocity"]
                body["pivot"] = pivot
            bodies.append(body)
        return {
            "simulation": sim,
            "materials": {name: m.to_dict() for name, m in self._materials.items()},
            "shapes": shapes,
            "bodies": bodies,
            "walls": [p.to_dict() for p in self._planes],
            "output": self.output.to_dict(),
        }

    def describe(self) -> str:
        """A human-readable summary."""
        g = ", ".join(f"{x:g}" for x in self.gravity)
        dt = self.dt if self.dt == "auto" else f"{self.dt:g} s"
        run = f", {self.steps} steps" if self.steps is not None else ""
        run += f", duration {self.duration:g} s" if self.duration is not None else ""
        run += f", {self.precision}" + (f", device {self.device}" if self.device else "")
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
        for d in self.drums:
            centre = ", ".join(f"{x:g}" for x in d.center)
            axis = ", ".join(f"{x:.4g}" for x in d.axis)
            lines.append(
                f"  drum: centre [{centre}], axis [{axis}],"
                f" radius {d.radius:g} m, length {d.length:g} m, {d.sides} slabs{' and 2 caps' if d.caps else ''}, "
                f"omega {d.omega:.4g} rad/s ({d.omega * 60.0 / (2.0 * math.pi):.4g} rpm)"
            )
        for e in self.emitters:
            lines.append(f"  {e['key']}: {e['count']} bodies (indices {e['first']} to {e['last']})")
        o = self.output
        out = [f"summary {o.summary}" if o.summary else "no summary"]
        if o.usd:
            out.append(f"USD {o.usd} at {o.fps:g} fps")
        if o.pictures:
            out.append(f"pictures {o.pictures if isinstance(o.pictures, str) else list(o.pictures)}")
        if o.checkpoint_steps is not None:
            out.append(f"checkpoint every {o.checkpoint_steps} steps")
        if o.checkpoint_seconds is not None:
            out.append(f"checkpoint every {o.checkpoint_seconds:g} s")
        if o.vtk:
            out.append("VTK files in vtk/")
        lines.append("  output: " + ", ".join(out))
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (
            f"Scene(name={self.name!r}, bodies={self._n}, shapes={len(self._shapes)}, "
            f"materials={len(self._materials)}, planes={len(self._planes)})"
        )


# ---------------------------------------------------------------------- initial overlaps

_BLOCK = 1 << 22  # floats per block of the vectorised overlap tests (32 MiB)
_MAX_EDGE_AXES = 4096  # edge-direction pairs tested per body pair; beyond, face normals only


def _blocks(n: int, per_item: int):
    step = max(1, _BLOCK // max(1, per_item))
    for start in range(0, n, step):
        yield slice(start, min(n, start + step))


def _plane_overlaps(scene, a) -> list[tuple]:
    """(relative depth, depth, body, where, of what, fix) of free bodies reaching behind a plane wall."""
    free = np.flatnonzero(a["kind"] == KIND_FREE)
    if not scene._planes or not free.size:
        return []
    shapes = list(scene._shapes.values())
    sid = a["shape"][free]
    reach = np.array([s.radius for s in shapes])[sid]
    out = []
    for plane, key in zip(scene._planes, scene._plane_keys, strict=True):
        nrm = np.asarray(plane.normal, dtype=np.float64)
        height = a["position"][free] @ nrm - float(nrm @ np.asarray(plane.point))
        near = np.flatnonzero(height < reach)
        for s in np.unique(sid[near]).tolist():
            verts = shapes[s].vertices
            rows = near[sid[near] == s]
            for blk in _blocks(len(rows), len(verts)):
                pick = rows[blk]
                local = np.einsum("pji,j->pi", quat_to_matrix(a["orientation"][free[pick]]), nrm)
                proj = local @ verts.T
                low = height[pick] + proj.min(axis=1)
                thick = proj.max(axis=1) - proj.min(axis=1)
                rel = -low / thick
                for h in np.flatnonzero(rel > INITIAL_OVERLAP_WARNING).tolist():
                    normal = ", ".join(f"{x:.3g}" for x in nrm)
                    out.append(
                        (
                            float(rel[h]),
                            float(-low[h]),
                            int(free[pick[h]]),
                            f"behind the plane wall {key}",
                            "its thickness",
                            f"move it by at least {-low[h]:.3g} m along the wall's normal [{normal}], to the side it "
                            "points to, or move the wall",
                        )
                    )
    return out


def _candidate_pairs(pos: np.ndarray, rad: np.ndarray) -> np.ndarray:
    """(K, 2) body pairs whose bounding spheres meet, from k-d trees on the centres.

    Bodies more than 4 times the median radius (container slabs, drums, boulders) would make one
    tree's search radius huge, so they search the tree of the others one by one instead.
    """
    from scipy.spatial import cKDTree

    n = len(pos)
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64)
    big_mask = rad > 4.0 * float(np.median(rad))
    small, big = np.flatnonzero(~big_mask), np.flatnonzero(big_mask)
    parts = []
    tree = cKDTree(pos[small]) if small.size else None
    if small.size >= 2:
        parts.append(small[tree.query_pairs(2.0 * float(rad[small].max()), output_type="ndarray")])
    if big.size and small.size:
        found = tree.query_ball_point(pos[big], rad[big] + float(rad[small].max()), return_sorted=False)
        counts = np.fromiter((len(x) for x in found), dtype=np.int64, count=len(big))
        if counts.sum():
            others = np.concatenate([np.asarray(x, dtype=np.int64) for x in found if len(x)])
            parts.append(np.column_stack([np.repeat(big, counts), small[others]]))
    if big.size >= 2:
        if big.size <= 2048:
            ii, jj = np.triu_indices(big.size, 1)
            parts.append(np.column_stack([big[ii], big[jj]]))
        else:
            parts.append(big[cKDTree(pos[big]).query_pairs(2.0 * float(rad[big].max()), output_type="ndarray")])
    if not parts:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = np.concatenate(parts).astype(np.int64)
    d = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1)
    return pairs[d < rad[pairs[:, 0]] + rad[pairs[:, 1]]]


def _edge_directions(shape) -> np.ndarray:
    """(k, 3) unit edge directions of a shape (body frame), parallel edges once."""
    v = shape.vertices
    loops = shape.faces
    starts = np.concatenate([lp for lp in loops])
    ends = np.concatenate([np.roll(lp, -1) for lp in loops])
    e = v[ends] - v[starts]
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    lead = np.take_along_axis(e, np.argmax(np.abs(e) > 1e-9, axis=1)[:, None], axis=1)
    e *= np.sign(lead)
    return np.unique(np.round(e, 9), axis=0)


def _interval_overlap(a_lo, a_hi, b_lo, b_hi):
    """Overlap of projection intervals (> 0: they overlap) and the thinner one's length."""
    return np.minimum(a_hi - b_lo, b_hi - a_lo), np.minimum(a_hi - a_lo, b_hi - b_lo)


def _sat_depth(shape_a, shape_b, ca, cb, ra, rb, edges_a, edges_b):
    """Penetration depth of P pairs by the separating-axis test (<= 0: apart), over the thinner body's
    thickness along the axis of least overlap. ca, cb: (P, 3) centres; ra, rb: (P, 3, 3) rotations."""
    va, vb = shape_a.vertices, shape_b.vertices
    best = np.full(len(ca), np.inf)
    thin = np.ones(len(ca))

    def take(ov, th):
        ov = np.where(np.isnan(ov), np.inf, ov)
        k = np.argmin(ov, axis=1)
        o = np.take_along_axis(ov, k[:, None], axis=1)[:, 0]
        better = o < best
        best[better] = o[better]
        thin[better] = np.take_along_axis(th, k[:, None], axis=1)[better, 0]

    # Face normals of A, in A's frame (then of B in B's frame): the other body's vertices moved there.
    for s1, s2, c1, c2, r1, r2 in ((shape_a, shape_b, ca, cb, ra, rb), (shape_b, shape_a, cb, ca, rb, ra)):
        n1 = s1.face_normals
        lo1 = (s1.vertices @ n1.T).min(axis=0)
        rel_rot = np.einsum("pji,pjk->pik", r1, r2)
        t = np.einsum("pji,pj->pi", r1, c2 - c1)
        x = s2.vertices @ rel_rot.transpose(0, 2, 1) + t[:, None, :]
        proj = x @ n1.T
        take(*_interval_overlap(lo1, s1.face_offsets, proj.min(axis=1), proj.max(axis=1)))
    # The line of centres, and the cross products of edge directions.
    wa = va @ ra.transpose(0, 2, 1) + ca[:, None, :]
    wb = vb @ rb.transpose(0, 2, 1) + cb[:, None, :]
    axes = (cb - ca)[:, None, :]
    if len(edges_a) * len(edges_b) <= _MAX_EDGE_AXES:
        ea = np.einsum("pij,kj->pki", ra, edges_a)
        eb = np.einsum("pij,kj->pki", rb, edges_b)
        cross = np.cross(ea[:, :, None, :], eb[:, None, :, :]).reshape(len(ca), -1, 3)
        axes = np.concatenate([axes, cross], axis=1)
    length = np.linalg.norm(axes, axis=2, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        axes = np.where(length > 1e-9, axes / length, np.nan)
    axes_t = np.ascontiguousarray(axes.transpose(0, 2, 1))
    pa = wa @ axes_t
    pb = wb @ axes_t
    take(*_interval_overlap(pa.min(axis=1), pa.max(axis=1), pb.min(axis=1), pb.max(axis=1)))
    return best, thin


def _pair_overlaps(scene, a) -> list[tuple]:
    """(relative depth, depth, body, where, of what, fix) of body pairs (one free at least) that overlap."""
    n = len(a["kind"])
    if n < 2:
        return []
    shapes = list(scene._shapes.values())
    rad = np.array([s.radius for s in shapes])[a["shape"]]
    pairs = _candidate_pairs(a["position"], rad)
    free = a["kind"] == KIND_FREE
    pairs = pairs[free[pairs[:, 0]] | free[pairs[:, 1]]]
    if not len(pairs):
        return []
    sid = a["shape"].astype(np.int64)
    group = sid[pairs[:, 0]] * len(shapes) + sid[pairs[:, 1]]
    edges = {}
    out = []
    for g in np.unique(group).tolist():
        sa, sb = shapes[g // len(shapes)], shapes[g % len(shapes)]
        for s in (g // len(shapes), g % len(shapes)):
            if s not in edges:
                edges[s] = _edge_directions(shapes[s])
        ea, eb = edges[g // len(shapes)], edges[g % len(shapes)]
        n_axes = 1 + (len(ea) * len(eb) if len(ea) * len(eb) <= _MAX_EDGE_AXES else 0)
        per_pair = max(len(sb.vertices) * sa.num_faces, len(sa.vertices) * sb.num_faces)
        per_pair = max(per_pair, (len(sa.vertices) + len(sb.vertices)) * n_axes)
        rows = pairs[group == g]
        # Most candidates (a small body beside a container slab) are apart along a face normal of
        # one body even when the other is replaced by its bounding sphere: a cheap first cut.
        for blk in _blocks(len(rows), 9 + sa.num_faces + sb.num_faces):
            i, j = rows[blk, 0], rows[blk, 1]
            d = a["position"][j] - a["position"][i]
            gap = (_quat_rotate(_quat_conj(a["orientation"][i]), d) @ sa.face_normals.T - sa.face_offsets).max(axis=1)
            near = np.flatnonzero(gap < sb.radius)
            if near.size:
                d_local = _quat_rotate(_quat_conj(a["orientation"][j[near]]), -d[near])
                gap = (d_local @ sb.face_normals.T - sb.face_offsets).max(axis=1)
                near = near[gap < sa.radius]
            if not near.size:
                continue
            i, j = i[near], j[near]
            ra = quat_to_matrix(a["orientation"][i])
            rb = quat_to_matrix(a["orientation"][j])
            for sub in _blocks(len(i), 4 * per_pair):
                ii, jj = i[sub], j[sub]
                depth, thin = _sat_depth(sa, sb, a["position"][ii], a["position"][jj], ra[sub], rb[sub], ea, eb)
                rel = depth / thin
                for h in np.flatnonzero(rel > INITIAL_OVERLAP_WARNING).tolist():
                    b1, b2 = (int(ii[h]), int(jj[h])) if free[ii[h]] else (int(jj[h]), int(ii[h]))
                    out.append(
                        (
                            float(rel[h]),
                            float(depth[h]),
                            b1,
                            f"into {scene._body_label(b2)}",
                            "the thinner one's thickness",
                            f"move the two apart by at least {depth[h]:.3g} m",
                        )
                    )
    return out


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
