"""Typed readers of scene values: each returns the checked value or raises SceneError naming the key.

The loader (scene files) and the Python API (``Scene.add_*``, the dataclasses) read every number,
vector, name and table through these, so a value gets the same message whichever way it came in.
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from polydem.scene.errors import SceneError, did_you_mean

QUAT_TOL = 1e-6
"""Largest accepted | |q| - 1 | of an orientation quaternion; accepted ones are normalised exactly."""

# The simulator stores masses, inertias, stiffnesses and the contact integrals (overlap volumes and
# their first moments, ~ size^4) in float32. Values must be normal float32 numbers, and products of
# them (inertia times angular velocity squared, k times volume powers, ...) must stay normal too,
# so they are kept this factor away from both ends of the range: 1.2e-32 to 3.4e32.
F32_MARGIN = 1.0e6
F32_LOW = float(np.finfo(np.float32).tiny) * F32_MARGIN
F32_HIGH = float(np.finfo(np.float32).max) / F32_MARGIN
# A shape's overlap volumes and their moments go as its bounding radius^4, so the radius needs r^4 in
# [F32_LOW, F32_HIGH].
RADIUS_LOW = F32_LOW**0.25
RADIUS_HIGH = F32_HIGH**0.25


def typename(v) -> str:
    """How a value reads in an error message, in TOML's words."""
    if isinstance(v, bool | np.bool_):
        return f"boolean {str(bool(v)).lower()}"
    if isinstance(v, str):
        return f"string {v!r}"
    if isinstance(v, numbers.Integral):
        return f"integer {as_integer(int(v))}"
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


def is_number(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool | np.bool_)


def as_given(value) -> str:
    """A number for a message with every digit it was given (1.0000001, where :g prints 1), as :g prints it
    otherwise (-1, not -1.0)."""
    text = repr(float(value))
    return text[:-2] if text.endswith(".0") else text


def _float(value) -> float:
    """``float(value)``, infinite for an integer past the floats (a scene file may give one)."""
    try:
        return float(value)
    except OverflowError:
        return math.inf if value > 0 else -math.inf


def read_number(value, key, file=None, *, positive=False, nonneg=False, hint="") -> float:
    """A finite float; ``positive`` requires > 0 and ``nonneg`` >= 0."""
    if not is_number(value):
        raise SceneError(f"expected a number, got {typename(value)}{hint}", key, file)
    v = _float(value)
    if not math.isfinite(v):
        got = as_integer(int(value)) if isinstance(value, numbers.Integral) else v
        raise SceneError(f"expected a finite number, got {got}{hint}", key, file)
    if positive and v <= 0.0:
        raise SceneError(f"must be positive (> 0), got {as_given(value)}{hint}", key, file)
    if nonneg and v < 0.0:
        raise SceneError(f"must not be negative, got {as_given(value)}{hint}", key, file)
    return v


def as_integer(v: int) -> str:
    """An integer for a message: its digits, or beyond 16 of them (1e300 read as an integer, or an integer past
    the floats) as :g prints a float, ``1e+400``."""
    if abs(v) < 10**16:
        return str(v)
    digits = str(abs(v))
    return f"{'-' if v < 0 else ''}{int(digits[:3]) / 100:g}e+{len(digits) - 1}"


def read_integer(value, key, file=None, *, minimum=None, maximum=None, hint="") -> int:
    """An integer (integral floats such as 3.0 are accepted) within [minimum, maximum]."""
    if isinstance(value, numbers.Integral) and not isinstance(value, bool | np.bool_):
        v = int(value)
    elif is_number(value) and math.isfinite(float(value)) and float(value).is_integer():
        v = int(value)
    else:
        raise SceneError(f"expected an integer, got {typename(value)}{hint}", key, file)
    if minimum is not None and v < minimum:
        raise SceneError(f"must be an integer >= {minimum}, got {as_integer(v)}{hint}", key, file)
    if maximum is not None and v > maximum:
        raise SceneError(f"must be an integer <= {maximum}, got {as_integer(v)}{hint}", key, file)
    return v


def read_boolean(value, key, file=None) -> bool:
    if not isinstance(value, bool | np.bool_):
        raise SceneError(f"expected true or false, got {typename(value)}", key, file)
    return bool(value)


def read_string(value, key, file=None, *, what="a string") -> str:
    if not isinstance(value, str):
        raise SceneError(f"expected {what}, got {typename(value)}", key, file)
    return value


def read_choice(value, choices, key, file=None, *, what="value") -> str:
    choices = tuple(choices)
    if not isinstance(value, str):
        raise SceneError(f"expected a {what} name (one of {', '.join(choices)}), got {typename(value)}", key, file)
    if value not in choices:
        raise SceneError(
            f"unknown {what} {value!r}{did_you_mean(value, choices) or '.'} Valid {what}s: {', '.join(choices)}",
            key,
            file,
        )
    return value


_LABELS = {3: "[x, y, z]", 4: "[x, y, z, w]"}


def read_vector(value, n, key, file=None, *, label=None) -> np.ndarray:
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
            if not is_number(x):
                raise SceneError(f"expected a number at position {i} of {label}, got {typename(x)}", key, file)
            if not math.isfinite(_float(x)) and isinstance(x, numbers.Integral):
                raise SceneError(f"expected a finite number at position {i} of {label}, got {typename(x)}", key, file)
        arr = np.array(value, dtype=np.float64)
    else:
        raise SceneError(f"expected an array of {n} numbers {label}, got {typename(value)}", key, file)
    if not np.all(np.isfinite(arr)):
        raise SceneError(f"expected finite numbers, got {arr.tolist()}", key, file)
    return arr


def read_rows(value, width, key, file=None, *, n=None) -> np.ndarray:
    """An (n, width) float64 array; a single row of shape (width,) is broadcast to n rows."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise SceneError(
            f"expected an array of shape (N, {width}) of numbers, got {typename(value)}: {exc}", key, file
        ) from None
    if arr.ndim == 1 and arr.shape[0] == width:
        arr = arr[None, :] if n is None else np.broadcast_to(arr, (n, width))
    if arr.ndim != 2 or arr.shape[1] != width or (n is not None and arr.shape[0] != n):
        want = f"({'N' if n is None else n}, {width})"
        raise SceneError(
            f"expected an array of shape {want} (or ({width},) for all rows), got shape {arr.shape}", key, file
        )
    return arr  # may be a broadcast view; callers copy it into their own storage


def check_keys(table, allowed, key, file=None, *, required=(), hints=None, context=""):
    """Reject unknown keys (with did-you-mean and the valid list) and report missing required ones."""
    for k in table:
        if k not in allowed:
            raise SceneError(
                f"unknown key {k!r}{did_you_mean(k, allowed) or '.'} Valid keys{context}: {', '.join(allowed)}",
                join_key(key, k),
                file,
            )
    for k in required:
        if k not in table:
            hint = (hints or {}).get(k, "")
            raise SceneError(f"missing required key {k!r}{' (' + hint + ')' if hint else ''}", join_key(key, k), file)


def read_table(value, key, file=None, *, what="a table"):
    if not isinstance(value, dict):
        raise SceneError(f"expected {what}, got {typename(value)}", key, file)
    return value


def join_key(prefix, k) -> str:
    return f"{prefix}.{k}" if prefix else str(k)


def row_norms(x: np.ndarray) -> np.ndarray:
    """The Euclidean norm of each row of an (N, 3) array: ``np.linalg.norm(x, axis=1)`` bit for bit (its sum over
    three entries runs in this order), without its slow reduction over a short axis (some 5x at 1e6 rows)."""
    x = np.asarray(x)
    return np.sqrt(x[:, 0] * x[:, 0] + x[:, 1] * x[:, 1] + x[:, 2] * x[:, 2])


FEW_CODES = 8
"""Up to this many wanted codes :func:`first_with_code` compares the codes once per wanted code."""


def distinct_codes(codes, size: int) -> np.ndarray:
    """The distinct values of the int array ``codes`` (each in [0, size): shape or material indices, or pairs of
    them), ascending, as ``np.unique`` gives them: one counting pass instead of a sort of every body's code."""
    codes = np.asarray(codes).reshape(-1)
    if not codes.size:
        return np.zeros(0, dtype=np.int64)
    return np.flatnonzero(np.bincount(codes, minlength=size))


def body_codes(shape, material, n_shapes: int, n_materials: int) -> np.ndarray:
    """Each body's (shape, material) code ``shape * n_materials + material`` (indices in range): in int32 where
    every code and one past the last fit it (half the memory traffic of int64 over every body), else in int64."""
    shape = np.asarray(shape)
    material = np.asarray(material)
    dtype = np.int32 if n_shapes * n_materials < 2**31 - 1 else np.int64
    codes = shape.astype(dtype, copy=True)
    codes *= dtype(n_materials)
    codes += material.astype(dtype, copy=False)
    return codes


def first_of_each_code(codes, size: int) -> np.ndarray:
    """(size + 1,) int64: the first index of each code in [0, size] of the int array ``codes``, ``len(codes)``
    where it does not occur; one pass that keeps the least index of every code (never a sort)."""
    codes = np.asarray(codes).reshape(-1)
    first = np.full(size + 1, codes.size, dtype=np.int64)
    np.minimum.at(first, codes, np.arange(codes.size, dtype=np.int64))
    return first


def first_with_code(codes, wanted, size: int) -> int:
    """The first index i with ``codes[i]`` in ``wanted`` (int codes in [0, size]; wanted codes outside that
    range never match), or -1 where there is none.

    A few wanted codes cost a comparison pass each; more take :func:`first_of_each_code`."""
    codes = np.asarray(codes).reshape(-1)
    wanted = np.unique(np.asarray(wanted, dtype=np.int64).reshape(-1))
    wanted = wanted[(wanted >= 0) & (wanted <= size)]
    if not codes.size or not wanted.size:
        return -1
    if wanted.size <= FEW_CODES:
        hits = [int(np.argmax(codes == c)) for c in wanted.tolist()]
        hits = [i for i, c in zip(hits, wanted.tolist(), strict=True) if codes[i] == c]
        return min(hits) if hits else -1
    i = int(first_of_each_code(codes, size)[wanted].min())
    return i if i < codes.size else -1


def check_quats(q: np.ndarray, rowkey, file) -> np.ndarray:
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


def quat_from_axis_angle(axis, angle: float) -> np.ndarray:
    """Unit xyzw quaternion of a rotation by ``angle`` [rad] about ``axis`` (any non-zero length)."""
    a = read_vector(list(axis) if not isinstance(axis, np.ndarray) else axis, 3, "axis")
    n = float(np.linalg.norm(a))
    if n == 0.0:
        raise SceneError("rotation axis is zero; give a non-zero direction such as [0, 0, 1]", "axis")
    angle = read_number(angle, "angle")
    return np.concatenate([a / n * math.sin(0.5 * angle), [math.cos(0.5 * angle)]])


def unit_normal(value, key, file) -> np.ndarray:
    n = read_vector(value, 3, key, file)
    length = float(np.linalg.norm(n))
    if length < 1e-12:
        raise SceneError(f"normal {n.tolist()} is zero; give the direction the wall faces, e.g. [0, 0, 1]", key, file)
    return n / length


def as_tuple(a) -> tuple[float, ...]:
    return tuple(float(x) for x in a)
