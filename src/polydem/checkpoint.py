"""Checkpoints: save a running Simulation to a file and continue from it later.

A checkpoint holds everything the dynamics depend on: poses, velocities, the turning volumes of
the normal hysteresis and the friction springs of the persisting contacts (with the keys that
identify their pairs), those of the wall contacts, the energy
dissipated so far, the step count and the time. Resuming gives the same result, bit for bit on
the same device, as a run that was never interrupted: the candidate pairs are found again, and
pairs out of contact contribute exact zeros. So only the pairs that carry a history are kept
(:func:`pairs_with_history`), and the file does not depend on which candidates the broad phase
happened to list: a decomposed run writes the checkpoints of a run of one process.

A checkpoint also records the physics of its scene (:func:`physics_description`: materials, shape
geometry, walls, drums, the kind, shape and material of every body and the fixed and kinematic
bodies' placement and motion, gravity, the time step and the precision; not the free bodies'
initial state, which the checkpoint replaces, nor the output settings or the length of the run),
as JSON and arrays with their SHA-256 ``physics_fingerprint``. :func:`load_checkpoint` refuses a
checkpoint of other physics and names what differs. Every array is checked on reading (shapes,
dtypes, finite values, unit quaternions, step count and time, pair keys), so an edited or damaged
file gives a :class:`CheckpointError` instead of a run from a made-up state.

Checkpoints of the previous format (``polydem-checkpoint-2``, no physics record) are still read:
:func:`load_checkpoint` warns (:class:`CheckpointWarning`) that it cannot check their scene.

A checkpoint may carry a ``run`` record (any JSON object), which ``polydem run`` uses to continue
the summary of a resumed run; :func:`read_checkpoint` returns it.
"""

import dataclasses
import hashlib
import json
import math
import os
import warnings
import weakref

import numpy as np

from polydem.kernels.precision import Precision
from polydem.scene.bodies import KINDS

__all__ = [
    "FORMAT",
    "CheckpointError",
    "CheckpointWarning",
    "load_checkpoint",
    "pairs_with_history",
    "physics_description",
    "physics_differences",
    "read_checkpoint",
    "restore_checkpoint",
    "save_checkpoint",
]

FORMAT = "polydem-checkpoint-3"
OLD_FORMATS = ("polydem-checkpoint-2",)
"""Formats still read: no physics record and no run record (load_checkpoint warns)."""

QUAT_TOLERANCE = 1e-4
"""Largest | |q| - 1 | of a stored orientation (the integrator renormalises q every step)."""

_PHYSICS_ARRAYS = (
    "bodies.shape",
    "bodies.material",
    "bodies.kind",
    "bodies.nonfree",
    "bodies.nonfree.position",
    "bodies.nonfree.orientation",
    "bodies.nonfree.velocity",
    "bodies.nonfree.angular_velocity",
    "bodies.nonfree.pivot",
)
_FIX_OTHER = "give a checkpoint written by polydem (checkpoints/*.npz of a run), or rerun the scene"


class CheckpointError(ValueError):
    """A checkpoint that cannot be read or does not fit the simulation; ``str`` is ``"FILE: MESSAGE"``."""

    def __init__(self, message, path=None):
        super().__init__(message)
        self.message = message
        self.path = None if path is None else os.fspath(path)

    def __str__(self):
        return self.message if self.path is None else f"{self.path}: {self.message}"


class CheckpointWarning(UserWarning):
    """A checkpoint of an older format, whose scene cannot be checked."""


# ---------------------------------------------------------------------- the physics record


def _plain(x):
    if x is None or isinstance(x, str | bool):
        return x
    if isinstance(x, int | np.integer):
        return int(x)
    if isinstance(x, float | np.floating):
        return float(x)
    return [_plain(v) for v in x]


def physics_description(scene, dt):
    """What the dynamics of ``scene`` run at time step ``dt`` depend on: ``(description, arrays)``.

    ``description`` maps keys named like the scene file's (``materials.steel.friction``,
    ``shapes.cube.vertices``, ``planes[0].normal``, ``simulation.gravity``, ...) to JSON values;
    ``arrays`` holds the per-body data (shape, material and kind of every body; index, initial
    pose, velocity, angular velocity and pivot of the fixed and kinematic bodies, which are part of
    the walls, not of the state).
    """
    desc = {"materials": list(scene.material_names)}
    for name in scene.material_names:
        mat = scene.materials[name]
        for field in ("density", "law", "k", "restitution", "friction", "m", "tangential_stiffness"):
            desc[f"materials.{name}.{field}"] = _plain(getattr(mat, field))
    desc["shapes"] = list(scene.shape_names)
    for name in scene.shape_names:
        shape = scene.shapes[name]
        desc[f"shapes.{name}.vertices"] = np.asarray(shape.vertices, dtype=np.float64).tolist()
        desc[f"shapes.{name}.faces"] = [np.asarray(f).tolist() for f in shape.faces]
        if getattr(shape, "is_compound", False):  # the contact sees the parts, not the union's surface
            for k, verts in enumerate(shape.part_vertices()):
                desc[f"shapes.{name}.parts[{k}].vertices"] = np.asarray(verts, dtype=np.float64).tolist()
    desc["planes"] = len(scene.planes)
    for i, plane in enumerate(scene.planes):
        for field in ("point", "normal", "material"):
            desc[f"planes[{i}].{field}"] = _plain(getattr(plane, field))
    drums = getattr(scene, "drums", [])
    desc["drums"] = len(drums)
    for i, drum in enumerate(drums):
        for field in ("center", "axis", "radius", "length", "sides", "thickness", "omega", "material", "caps"):
            desc[f"drums[{i}].{field}"] = _plain(getattr(drum, field))
    walls = getattr(scene, "mesh_walls", [])
    if walls:
        desc["mesh_walls"] = len(walls)
    for i, wall in enumerate(walls):
        digest = hashlib.sha256(np.ascontiguousarray(wall.vertices).tobytes())
        digest.update(np.ascontiguousarray(wall.triangles).tobytes())
        desc[f"mesh_walls[{i}].triangles"] = f"{len(wall.triangles)} triangles, sha256 {digest.hexdigest()[:16]}"
        for field in ("material", "pivot", "velocity", "angular_velocity", "thickness"):
            desc[f"mesh_walls[{i}].{field}"] = _plain(getattr(wall, field))
    motions = getattr(scene, "motions", {})
    if motions:  # what drives the walls and pistons (a scene without motions keeps its former record)
        desc["motions"] = sorted(motions)
        for name in sorted(motions):
            for f in dataclasses.fields(motions[name]):
                if f.name != "name":
                    desc[f"motions.{name}.{f.name}"] = _plain(getattr(motions[name], f.name))
        desc["bodies.motion"] = [[int(i), m] for i, m in sorted(scene.body_motion.items())]  # lists compare
        for i, plane in enumerate(scene.planes):
            desc[f"planes[{i}].motion"] = plane.motion
        for i, wall in enumerate(walls):
            desc[f"mesh_walls[{i}].motion"] = wall.motion
    desc["bodies"] = int(scene.num_bodies)
    desc["simulation.gravity"] = _plain(scene.gravity)
    desc["simulation.precision"] = scene.precision
    desc["simulation.dt"] = float(dt)
    kind = np.asarray(scene.body_kind, dtype=np.int32)
    nonfree = np.flatnonzero(kind != 0)
    arrays = {
        "bodies.shape": np.asarray(scene.body_shape, dtype=np.int32),
        "bodies.material": np.asarray(scene.body_material, dtype=np.int32),
        "bodies.kind": kind,
        "bodies.nonfree": nonfree.astype(np.int64),
        "bodies.nonfree.position": np.asarray(scene.body_position, dtype=np.float64)[nonfree],
        "bodies.nonfree.orientation": np.asarray(scene.body_orientation, dtype=np.float64)[nonfree],
        "bodies.nonfree.velocity": np.asarray(scene.body_velocity, dtype=np.float64)[nonfree],
        "bodies.nonfree.angular_velocity": np.asarray(scene.body_angular_velocity, dtype=np.float64)[nonfree],
        "bodies.nonfree.pivot": np.asarray(scene.body_pivot, dtype=np.float64)[nonfree],
    }
    return desc, arrays


def _physics_json(desc) -> str:
    return json.dumps(desc, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _fingerprint(text: str, arrays) -> str:
    h = hashlib.sha256(text.encode())
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"\0{name}\0{a.dtype.str}\0{a.shape}\0".encode())
        h.update(a.tobytes())
    return h.hexdigest()


_PHYSICS_RECORDS = weakref.WeakKeyDictionary()
"""The physics record of each Model, computed once (a run writes many checkpoints)."""


def _sim_physics(sim):
    """(description, json text, arrays, fingerprint) of a simulation's physics."""
    cached = _PHYSICS_RECORDS.get(sim.model)
    if cached is None:
        desc, arrays = physics_description(sim.scene, sim.dt)
        text = _physics_json(desc)
        cached = (desc, text, arrays, _fingerprint(text, arrays))
        _PHYSICS_RECORDS[sim.model] = cached
    return cached


def _fmt(x) -> str:
    if isinstance(x, float):
        return f"{x:.6g}"
    if isinstance(x, list | tuple | np.ndarray):
        return "[" + ", ".join(_fmt(v) for v in (x.tolist() if isinstance(x, np.ndarray) else x)) + "]"
    if isinstance(x, np.floating):
        return f"{float(x):.6g}"
    return repr(x) if isinstance(x, str) else str(x)


def _pair(a, b):
    """``a`` and ``b`` as text that tells them apart (6 digits, or all where those agree)."""
    ta, tb = _fmt(a), _fmt(b)
    if ta == tb:
        ta, tb = repr(a), repr(b)
    return ta, tb


def _close(a, b) -> bool:
    if isinstance(a, bool) or isinstance(b, bool) or isinstance(a, str) or isinstance(b, str):
        return a == b
    if a is None or b is None:
        return a is b
    if isinstance(a, int | float) and isinstance(b, int | float):
        return math.isclose(a, b, rel_tol=1e-12, abs_tol=0.0)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_close(x, y) for x, y in zip(a, b, strict=True))
    return False


def _extent(vertices) -> str:
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    size = v.max(axis=0) - v.min(axis=0) if len(v) else np.zeros(3)
    return f"{len(v)} vertices within {' x '.join(f'{s:.6g}' for s in size)} m"


def physics_differences(stored, stored_arrays, desc, arrays) -> list[str]:
    """What differs between a checkpoint's physics (``stored``) and a scene's, one phrase each
    ("materials.steel.friction differs: checkpoint 0.3, scene 0.5"), most specific first."""
    out = []
    skip = set()
    for key in ("materials", "shapes", "planes", "drums", "mesh_walls", "bodies"):
        if stored.get(key, 0 if key == "mesh_walls" else None) != desc.get(key, 0 if key == "mesh_walls" else None):
            unit = f" {key}" if key in ("planes", "drums", "mesh_walls", "bodies") else ""
            out.append(f"{key} differ: checkpoint {_fmt(stored.get(key))}{unit}, scene {_fmt(desc.get(key))}")
            skip.add(key)
    for key, value in desc.items():
        if key in ("materials", "shapes", "planes", "drums", "mesh_walls", "bodies") or key not in stored:
            continue
        old = stored[key]
        if _close(old, value):
            continue
        if key.endswith(".vertices"):
            a, b = _extent(old), _extent(value)
            if a == b:
                a, b = "other vertices", "other vertices"
            out.append(f"{key} differ: checkpoint {a}, scene {b}")
        elif key.endswith(".faces"):
            out.append(f"{key} differ: checkpoint {len(old)} faces, scene {len(value)}")
        elif key == "simulation.precision" and isinstance(old, str):
            # Checkpoints of scenes that gave no precision were float32 before "mixed" became the default.
            out.append(
                f'{key} differs: checkpoint {old!r}, scene {value!r} (to resume in {old}, add precision = "{old}" '
                f'to the scene\'s [simulation] table, or Scene(precision="{old}"), or pass --precision {old})'
            )
        else:
            a, b = _pair(old, value)
            out.append(f"{key} differs: checkpoint {a}, scene {b}")
    if "bodies" in skip:
        return out
    names = {
        "bodies.shape": (stored.get("shapes", []), desc.get("shapes", [])),
        "bodies.material": (stored.get("materials", []), desc.get("materials", [])),
        "bodies.kind": (KINDS, KINDS),
    }
    for key, (old_names, new_names) in names.items():
        a, b = np.asarray(stored_arrays[key]), np.asarray(arrays[key])
        bad = np.flatnonzero(a != b)
        if len(bad):
            i = int(bad[0])
            label = [n[int(x)] if 0 <= int(x) < len(n) else int(x) for n, x in ((old_names, a[i]), (new_names, b[i]))]
            field = key.split(".")[1]
            more = f" ({len(bad)} bodies differ)" if len(bad) > 1 else ""
            out.append(f"bodies[{i}].{field} differs: checkpoint {label[0]!r}, scene {label[1]!r}{more}")
            skip.add("kind" if key == "bodies.kind" else key)
    if "kind" in skip:
        return out
    index = np.asarray(arrays["bodies.nonfree"])
    kind = np.asarray(arrays["bodies.kind"])
    for key in _PHYSICS_ARRAYS[4:]:
        a, b = np.asarray(stored_arrays[key], dtype=np.float64), np.asarray(arrays[key], dtype=np.float64)
        same = np.isclose(a, b, rtol=1e-12, atol=0.0, equal_nan=True)
        bad = np.flatnonzero(~same.reshape(len(a), -1).all(axis=1)) if len(a) else []
        if len(bad):
            j = int(bad[0])
            body = int(index[j])
            x, y = _pair(a[j], b[j])
            field = key.rsplit(".", 1)[1]
            out.append(f"bodies[{body}].{field} of a {KINDS[int(kind[body])]} body differs: checkpoint {x}, scene {y}")
    return out


# ---------------------------------------------------------------------- writing


def _bits_set(a) -> np.ndarray:
    # -0.0 counts as a value: the run carries its sign on, a pair restored without it gets +0.0.
    a = np.asarray(a)
    return (a != 0) | np.signbit(a)


def pairs_with_history(history: dict) -> dict:
    """The pairs of ``history`` (``pair_key``, ``pair_xi``, ``pair_turn`` as ``history_numpy`` gives them)
    that carry a history (a friction spring or a turning volume other than +0.0), each key once, ascending.

    What a checkpoint keeps of the pair list. The others are candidate pairs out of contact; a pair missing
    from the checkpoint is found again on resuming and starts from zeros, so dropping them changes nothing,
    and it makes the file independent of which candidates the broad phase happened to list: a decomposed run
    rebuilds each rank's list at its own times, so its candidates differ from a run of one process while the
    histories are the same bits.
    """
    key = np.asarray(history["pair_key"], dtype=np.int64)
    xi, turn = np.asarray(history["pair_xi"]), np.asarray(history["pair_turn"])
    live = _bits_set(turn)
    if len(xi):
        live |= _bits_set(xi).any(axis=1)
    key, first = np.unique(key[live], return_index=True)
    return {
        "pair_key": key,
        "pair_xi": xi[live][first] if len(xi) else xi,
        "pair_turn": turn[live][first],
    }


def _has_travel(sim) -> bool:
    # A decomposed run's gathered state has no motion arrays (it refuses servos).
    return getattr(sim.model, "has_measured_motions", False) and hasattr(sim.current_state, "motion_travel")


def save_checkpoint(sim, path, run=None):
    """Write the state of ``sim`` to ``path`` (a ``.npz`` file), atomically.

    ``run``: an optional JSON object stored with the state (``polydem run`` keeps the record of
    the run so far in it, for the summary of a resumed run).
    """
    path = os.fspath(path)
    if not path.endswith(".npz"):
        raise ValueError(f"checkpoint path must end with .npz, got {path!r}")
    _, text, arrays, fingerprint = _sim_physics(sim)
    data = {
        "format": np.array(FORMAT),
        "num_bodies": np.array(sim.num_bodies),
        "steps_done": np.array(sim.steps_done),
        "time": np.array(sim.time),
        "dt": np.array(sim.dt),
        **sim.current_state.numpy(_STATE),
        **({"mesh_q": sim.current_state.mesh_q.numpy()} if sim.model.num_mesh_walls else {}),
        # A servo's displacement is summed step by step: a resumed run needs it (and the ramps' record).
        **({"motion_travel": sim.current_state.motion_travel.numpy()} if _has_travel(sim) else {}),
        **pairs_with_history(sim.current_contacts.history_numpy()),
        "physics_fingerprint": np.array(fingerprint),
        "physics_json": np.array(text),
    }
    for name, a in arrays.items():
        data[f"physics_{name}"] = a
    if run is not None:
        data["run_json"] = np.array(json.dumps(run, allow_nan=False))
    tmp = path + ".tmp.npz"
    try:
        np.savez(tmp, **data)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


# ---------------------------------------------------------------------- reading


class Checkpoint:
    """A checkpoint read and checked by :func:`read_checkpoint`.

    Attributes: ``path``, ``format``, ``num_bodies``, ``steps_done``, ``time`` [s], ``dt`` [s],
    ``arrays`` (the state, in the dtypes of the recorded precision (float32 for the older format):
    ``body_q`` (N, 7), ``body_v``, ``body_w``, ``body_dissipated``,
    ``wall_xi``, ``wall_turn``, ``step_count``, ``pair_key``, ``pair_xi``, ``pair_turn``),
    ``physics`` (the description, None for the old format), ``physics_arrays``, ``fingerprint``
    and ``run`` (the run record, or None).
    """

    def __init__(self, **kw):
        self.__dict__.update(kw)


_STATE = ("body_q", "body_v", "body_w", "body_dissipated", "wall_xi", "wall_turn", "step_count")
_PAIRS = ("pair_key", "pair_xi", "pair_turn")
# Names that checkpoints written before the wall arrays were renamed use (they hold mesh walls too).
_OLD_NAMES = {"plane_xi": "wall_xi", "plane_turn": "wall_turn"}
_SCALARS = ("format", "num_bodies", "steps_done", "time", "dt")


def _open(path):
    """All members of the npz file ``path`` as numpy arrays (CheckpointError if it is not one)."""
    try:
        data = np.load(path, allow_pickle=False)
    except (PermissionError, IsADirectoryError, FileNotFoundError):
        raise  # the file system's answer, not the file's content
    except Exception as err:  # not a zip or npy file
        # numpy takes any other file for a pickle, and its message suggests unpickling it: not here.
        why = "neither an .npz archive nor an .npy array" if "pickle" in str(err) else f"{type(err).__name__}: {err}"
        raise CheckpointError(f"not a polydem checkpoint ({why}); {_FIX_OTHER}", path) from None
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise CheckpointError(
            f"not a polydem checkpoint (a single .npy array, not an .npz archive); {_FIX_OTHER}", path
        )
    out = {}
    with data:
        for name in data.files:
            try:
                out[name] = data[name]
            except Exception as err:  # a truncated member, or an object (pickled) array
                raise CheckpointError(
                    f"the file is damaged: array {name!r} cannot be read ({type(err).__name__}: {err}); use another "
                    "checkpoint of the run (checkpoints/step_*.npz) or rerun the scene",
                    path,
                ) from None
    return out


def _damaged(path, what):
    return CheckpointError(
        f"{what}; the file is damaged or was edited: use another checkpoint of the run or rerun", path
    )


def _scalar(path, data, name, kind):
    a = data[name]
    if a.shape != ():
        raise _damaged(path, f"{name} is an array of shape {a.shape}, not a single value")
    if kind == "str":
        if a.dtype.kind != "U":
            raise _damaged(path, f"{name} is not a string (dtype {a.dtype})")
        return str(a)
    if kind == "int":
        if a.dtype.kind not in "iu":
            raise _damaged(path, f"{name} = {a.item()!r} is not a whole number (dtype {a.dtype})")
        return int(a)
    if a.dtype.kind not in "iuf":
        raise _damaged(path, f"{name} is not a real number (dtype {a.dtype})")
    return float(a)


def _dtypes(data):
    """(dtype of the body arrays, dtype of the contact history) of the precision the checkpoint
    records; float32 for a checkpoint of the older format (a damaged record is refused later)."""
    try:
        precision = json.loads(str(data["physics_json"]))["simulation.precision"]
    except Exception:
        precision = Precision.FLOAT32
    body = np.float64 if precision in (Precision.MIXED, Precision.FLOAT64) else np.float32
    return body, np.float64 if precision == Precision.FLOAT64 else np.float32


def _real(path, data, name, shape, dtype=np.float32):
    """``data[name]`` as ``dtype`` after checking its shape (None entries match any size) and values."""
    a = data[name]
    if a.dtype.kind not in "iuf":
        raise _damaged(path, f"{name} holds {a.dtype} values, expected real numbers ({np.dtype(dtype).name})")
    if a.ndim != len(shape) or any(s is not None and s != t for s, t in zip(shape, a.shape, strict=True)):
        want = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ")"
        raise _damaged(path, f"{name} has shape {a.shape}, expected {want}")
    with np.errstate(over="ignore", invalid="ignore"):
        b = a.astype(dtype)
    bad = ~np.isfinite(b)
    if bad.any():
        where = np.argwhere(bad)[0]
        raise _damaged(path, f"{name}{where.tolist()} is {a[tuple(where)].item()!r}: every value must be finite")
    return b


def read_checkpoint(path) -> Checkpoint:
    """Read and check the checkpoint ``path``; raises :class:`CheckpointError` naming what is wrong.

    Checks what needs no scene: the format, that every array is there with its shape and dtype, that
    all values are finite, the orientations unit quaternions, the step count a whole number >= 0
    matching the time, and the pair keys real pairs (a < b < N), increasing, without repeats.
    """
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"checkpoint {path!r} does not exist")
    data = _open(path)
    for old, new in _OLD_NAMES.items():
        if old in data and new not in data:
            data[new] = data.pop(old)
    if "format" not in data:
        raise CheckpointError(f"not a polydem checkpoint (it has no 'format' entry); {_FIX_OTHER}", path)
    fmt = _scalar(path, data, "format", "str")
    if fmt != FORMAT and fmt not in OLD_FORMATS:
        raise CheckpointError(
            f"checkpoint format {fmt!r}, this polydem reads {FORMAT!r} (and {', '.join(map(repr, OLD_FORMATS))}); "
            "rerun the scene with this polydem",
            path,
        )
    needed = _SCALARS + _STATE + _PAIRS
    if fmt == FORMAT:
        needed += ("physics_fingerprint", "physics_json") + tuple(f"physics_{k}" for k in _PHYSICS_ARRAYS)
    missing = [k for k in needed if k not in data]
    if missing:
        raise _damaged(path, f"it lacks {', '.join(missing)}")
    n = _scalar(path, data, "num_bodies", "int")
    if n < 1:
        raise _damaged(path, f"num_bodies = {n}, expected at least 1")
    steps = _scalar(path, data, "steps_done", "int")
    if steps < 0:
        raise _damaged(path, f"steps_done = {steps} is negative")
    dt = _scalar(path, data, "dt", "float")
    if not (math.isfinite(dt) and dt > 0.0):
        raise _damaged(path, f"dt = {dt!r}, expected a time step > 0 s")
    t = _scalar(path, data, "time", "float")
    if not math.isfinite(t):
        raise _damaged(path, f"time = {t!r} s is not a finite time")
    if not (abs(t - steps * dt) <= 1e-6 * steps * dt + 1e-3 * dt):
        raise _damaged(
            path, f"time = {t!r} s does not match steps_done = {steps} at dt = {dt:.6g} s ({steps * dt:.6g} s)"
        )
    arrays = {}
    body, history = _dtypes(data) if "physics_json" in data else (np.float32, np.float32)
    arrays["body_q"] = q = _real(path, data, "body_q", (n, 7), body)
    norm = np.linalg.norm(q[:, 3:].astype(np.float64), axis=1)
    bad = np.flatnonzero(np.abs(norm - 1.0) > QUAT_TOLERANCE)
    if len(bad):
        i = int(bad[0])
        raise _damaged(
            path,
            f"the orientation of body {i} (body_q[{i}, 3:7] = {_fmt(q[i, 3:])}) has length {norm[i]:.6g}, not 1"
            + (f" ({len(bad)} bodies)" if len(bad) > 1 else ""),
        )
    for name in ("body_v", "body_w"):
        arrays[name] = _real(path, data, name, (n, 3), body)
    arrays["body_dissipated"] = _real(path, data, "body_dissipated", (n,), body)
    wall_turn = arrays["wall_turn"] = _real(path, data, "wall_turn", (n, None), history)
    xi = data["wall_xi"]
    arrays["wall_xi"] = _real(path, data, "wall_xi", (1, 1, 3) if xi.shape[:2] == (1, 1) else (n, None, 3), history)
    if arrays["wall_xi"].shape[:2] not in ((1, 1), wall_turn.shape):
        raise _damaged(path, f"wall_xi has shape {xi.shape}, wall_turn {wall_turn.shape}: they do not fit")
    if "mesh_q" in data:
        # The poses of the mesh walls (only in checkpoints of scenes that have them).
        arrays["mesh_q"] = _real(path, data, "mesh_q", (None, 7), body)
    if "motion_travel" in data:
        # The ramps' and servos' (d, v, F) (only in checkpoints of scenes that have them).
        arrays["motion_travel"] = _real(path, data, "motion_travel", (None, 3), np.float64)
    step_count = data["step_count"]
    if step_count.shape != (1,) or step_count.dtype.kind not in "iu" or int(step_count[0]) != steps:
        raise _damaged(path, f"step_count = {step_count.tolist()} does not match steps_done = {steps}")
    arrays["step_count"] = step_count.astype(np.int32)
    key = data["pair_key"]
    if key.ndim != 1 or key.dtype.kind not in "iu":
        raise _damaged(path, f"pair_key has shape {key.shape} and dtype {key.dtype}, expected whole numbers (C,)")
    key = key.astype(np.int64)
    count = len(key)
    a, b = key // n, key % n
    bad = np.flatnonzero((key < 0) | (a >= b))
    if len(bad):
        i = int(bad[0])
        raise _damaged(
            path,
            f"pair_key[{i}] = {int(key[i])} (bodies {int(a[i])}, {int(b[i])}) is not a pair of bodies a < b < {n} "
            f"(key = a * {n} + b)",
        )
    if count > 1:
        step = np.diff(key)
        bad = np.flatnonzero(step <= 0)
        if len(bad):
            i = int(bad[0]) + 1
            what = "repeats" if step[i - 1] == 0 else "is smaller than the one before"
            raise _damaged(path, f"pair_key[{i}] = {int(key[i])} (bodies {int(a[i])}, {int(b[i])}) {what}")
    arrays["pair_key"] = key
    arrays["pair_turn"] = _real(path, data, "pair_turn", (count,), history)
    pair_xi = data["pair_xi"]
    arrays["pair_xi"] = _real(path, data, "pair_xi", (0 if len(pair_xi) == 0 else count, 3), history)
    ck = Checkpoint(
        path=path,
        format=fmt,
        num_bodies=n,
        steps_done=steps,
        time=t,
        dt=dt,
        arrays=arrays,
        physics=None,
        physics_arrays=None,
        fingerprint=None,
        run=None,
    )
    if fmt == FORMAT:
        _read_physics(path, data, ck)
    if "run_json" in data:
        try:
            run = json.loads(_scalar(path, data, "run_json", "str"))
        except json.JSONDecodeError as err:
            raise _damaged(path, f"its run record is not JSON ({err})") from None
        if not isinstance(run, dict):
            raise _damaged(path, "its run record is not a JSON object")
        ck.run = run
    return ck


def _read_physics(path, data, ck):
    text = _scalar(path, data, "physics_json", "str")
    stored = _scalar(path, data, "physics_fingerprint", "str")
    arrays = {k: data[f"physics_{k}"] for k in _PHYSICS_ARRAYS}
    if _fingerprint(text, arrays) != stored:
        raise _damaged(path, "its record of the scene's physics does not match its physics_fingerprint")
    try:
        desc = json.loads(text)
    except json.JSONDecodeError as err:
        raise _damaged(path, f"its record of the scene's physics is not JSON ({err})") from None
    if not isinstance(desc, dict):
        raise _damaged(path, "its record of the scene's physics is not a JSON object")
    ck.physics, ck.physics_arrays, ck.fingerprint = desc, arrays, stored


# ---------------------------------------------------------------------- checking against a scene, restoring


def check_scene(ck, sim, fix="use the scene the checkpoint was written from") -> None:
    """CheckpointError unless the checkpoint ``ck`` fits ``sim``: body count, then the physics."""
    if ck.num_bodies != sim.num_bodies:
        raise CheckpointError(
            f"checkpoint has {ck.num_bodies} bodies but the scene has {sim.num_bodies}; {fix}", ck.path
        )
    if ck.physics is not None:
        desc, _, arrays, fingerprint = _sim_physics(sim)
        if fingerprint != ck.fingerprint:
            try:
                diffs = physics_differences(ck.physics, ck.physics_arrays, desc, arrays)
            except Exception:  # a record of an unexpected layout (its fingerprint is consistent)
                diffs = ["the physics fingerprint differs"]
            if diffs:
                more = f" (and {len(diffs) - 3} more)" if len(diffs) > 3 else ""
                raise CheckpointError(
                    f"the checkpoint was written for other physics: {'; '.join(diffs[:3])}{more}; {fix}", ck.path
                )
    elif not math.isclose(ck.dt, sim.dt, rel_tol=1e-12):
        raise CheckpointError(
            f"checkpoint time step {ck.dt:.6g} s differs from the scene's {sim.dt:.6g} s; {fix}", ck.path
        )
    arrays = ck.arrays
    state = sim.current_state
    if arrays["wall_turn"].shape != tuple(state.wall_turn.shape) or (
        arrays["wall_xi"].shape[:2] != tuple(state.wall_xi.shape)
    ):
        raise CheckpointError(
            f"wall contacts of shape {arrays['wall_turn'].shape} do not fit this scene's walls; {fix}", ck.path
        )
    meshes = sim.model.num_mesh_walls
    if meshes and arrays.get("mesh_q", np.zeros((0, 7))).shape != (meshes, 7):
        have = len(arrays["mesh_q"]) if "mesh_q" in arrays else 0
        raise CheckpointError(f"the checkpoint has poses of {have} mesh walls, this scene has {meshes}; {fix}", ck.path)
    springs = len(arrays["pair_xi"])
    if sim.model.friction and springs != len(arrays["pair_key"]):
        raise CheckpointError(
            f"the checkpoint has {springs} friction springs for {len(arrays['pair_key'])} pairs, but this scene has "
            f"friction; {fix}",
            ck.path,
        )


def restore_checkpoint(sim, ck):
    """Put the state of the checked checkpoint ``ck`` (:func:`read_checkpoint`) into ``sim``."""
    sim.restore_from_arrays(ck.arrays, ck.steps_done, ck.time)
    return sim


def load_checkpoint(sim, path):
    """Put the state saved in ``path`` into ``sim``, which must be built from the same scene.

    Raises :class:`CheckpointError` (a ValueError) when the file is not a sound checkpoint or its
    physics differ from ``sim``'s (naming what differs); warns (:class:`CheckpointWarning`) for a
    checkpoint of the older format, whose physics cannot be checked.
    """
    ck = read_checkpoint(path)
    if ck.physics is None:
        warnings.warn(
            f"{ck.path}: a checkpoint of the older format {ck.format!r} holds no record of its scene's physics: "
            "it cannot be checked to come from this scene",
            CheckpointWarning,
            stacklevel=2,
        )
    check_scene(ck, sim)
    return restore_checkpoint(sim, ck)
