"""Bodies: kinds, the :class:`Body` record, the :class:`BodyTable` of a scene's body arrays and the functions
that add bodies to a scene and read them back."""

from __future__ import annotations

import enum
import numbers
from dataclasses import dataclass, field

import numpy as np

from polydem.quaternions import quat_conjugate, quat_multiply, quat_rotate, quat_to_matrix
from polydem.scene.schema import REQUIRED, SPEED, SPEED_WHY, Key, Table
from polydem.scene.values import (
    F32_HIGH,
    as_tuple,
    check_quats,
    read_choice,
    read_rows,
    read_string,
    read_vector,
)


class BodyKind(enum.IntEnum):
    """The kinds of body, by the code that :attr:`Scene.body_kind` and the model's ``body_flags`` hold (an
    ``int`` enum: ``BodyKind.FIXED == 1``, so the arrays, the kernels and the checkpoints keep their codes);
    a scene file names a kind by its :attr:`label`."""

    FREE = 0
    FIXED = 1
    KINEMATIC = 2

    @property
    def label(self) -> str:
        """The name a scene file gives the kind: "free", "fixed" or "kinematic"."""
        return self.name.lower()


KINDS = tuple(kind.label for kind in BodyKind)
"""Body kinds by label; the code of a :class:`BodyKind` is its index in this tuple."""
KIND_FREE, KIND_FIXED, KIND_KINEMATIC = BodyKind.FREE, BodyKind.FIXED, BodyKind.KINEMATIC

MAX_BODIES = 10**8 + 10**6
"""Most bodies of one scene: 10^8 grains (the largest run one GPU holds: about 1 KB a body on the device, an
H200's 141 GB) and up to 10^6 walls and containers beside them; low enough that a mistyped count fails at once
instead of allocating tens of gigabytes (every body holds some hundred bytes in the scene alone), and that the
device's int32 indices (up to 10 broad-phase keys a body) stay in range."""

BODY = Table(
    "[[bodies]]",
    (
        Key("shape", "any", default=REQUIRED),
        Key("material", "any", default=REQUIRED),
        Key("position", "vector", unit="m", default=REQUIRED),
        Key("orientation", "vector", size=4, default=(0.0, 0.0, 0.0, 1.0)),
        Key("rotation", "rotation", attr="orientation", write="never"),
        Key("velocity", "vector", unit="m/s", range=SPEED, why=SPEED_WHY, default=(0.0, 0.0, 0.0)),
        Key("angular_velocity", "vector", unit="rad/s", range=SPEED, why=SPEED_WHY, default=(0.0, 0.0, 0.0)),
        Key("kind", "choice", choices=KINDS, what="body kind", default="free"),
        Key("pivot", "vector", unit="m"),
        Key("motion", "string", what="a motion name", hint="the [motions.NAME] a kinematic body follows"),
    ),
)
"""A ``[[bodies]]`` table: the arguments of :meth:`Scene.add_body` (``rotation`` is read into ``orientation``)."""

BODY_FIELDS = (
    ("shape", np.int32, ()),
    ("material", np.int32, ()),
    ("position", np.float64, (3,)),
    ("orientation", np.float64, (4,)),
    ("velocity", np.float64, (3,)),
    ("angular_velocity", np.float64, (3,)),
    ("kind", np.int32, ()),
    ("pivot", np.float64, (3,)),
)


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
    orientation: tuple = BODY.defaults["orientation"]
    velocity: tuple = BODY.defaults["velocity"]
    angular_velocity: tuple = BODY.defaults["angular_velocity"]
    kind: str = BODY.defaults["kind"]
    centroid: tuple | None = field(default=None, compare=False)
    body_orientation: tuple | None = field(default=None, compare=False)
    pivot: tuple | None = None

    def __post_init__(self):
        read_string(self.shape, "body.shape", what="a shape name")
        if self.pivot is not None:
            object.__setattr__(self, "pivot", as_tuple(read_vector(self.pivot, 3, "body.pivot")))
        read_string(self.material, "body.material", what="a material name")
        read_choice(self.kind, KINDS, "body.kind", what="body kind")
        q = check_quats(
            read_vector(self.orientation, 4, "body.orientation")[None, :], lambda i: "body.orientation", None
        )
        object.__setattr__(self, "orientation", as_tuple(q[0]))
        for name in ("position", "velocity", "angular_velocity"):
            object.__setattr__(self, name, as_tuple(read_vector(getattr(self, name), 3, f"body.{name}")))


class BodyTable:
    """The bodies of a scene: a column per field of :data:`BODY_FIELDS` (``arrays``), with room for more; the
    first ``n`` rows are the bodies."""

    def __init__(self):
        self.n = 0
        self.arrays = {name: np.empty((0, *shape), dtype) for name, dtype, shape in BODY_FIELDS}
        self._cap = 0

    def trimmed(self) -> dict[str, np.ndarray]:
        """The arrays by field name, trimmed to the bodies: not copies, for reading."""
        return {name: self.arrays[name][: self.n] for name, _, _ in BODY_FIELDS}

    def view(self, name: str) -> np.ndarray:
        """The read-only column ``name`` of the bodies."""
        v = self.arrays[name][: self.n]
        v.setflags(write=False)
        return v

    def reserve(self, extra: int):
        """Room for ``extra`` more bodies (the columns grow by doubling)."""
        need = self.n + extra
        if need <= self._cap:
            return
        cap = max(need, 2 * self._cap, 16)
        for name, dtype, shape in BODY_FIELDS:
            new = np.zeros((cap, *shape), dtype)
            new[: self.n] = self.arrays[name][: self.n]
            self.arrays[name] = new
        self._cap = cap


def add_body(
    scene,
    shape,
    material,
    position=(0.0, 0.0, 0.0),
    orientation=BODY.defaults["orientation"],
    velocity=BODY.defaults["velocity"],
    angular_velocity=BODY.defaults["angular_velocity"],
    kind: str = BODY.defaults["kind"],
    *,
    pivot=BODY.defaults["pivot"],
    key: str | None = None,
) -> int:
    """:meth:`Scene.add_body <polydem.scene.Scene.add_body>` of ``scene``."""
    key = key or f"bodies[{scene.body_table.n}]"
    s = scene.resolve_shape(shape, f"{key}.shape")
    m = scene.material_index(material, key=f"{key}.material")
    given = {"kind": kind, "position": position, "orientation": orientation, "velocity": velocity}
    a = BODY.read({**given, "angular_velocity": angular_velocity, "pivot": pivot}, key, scene.file)
    piv = None if a["pivot"] is None else a["pivot"][None]
    rows = [a[name][None] for name in ("position", "orientation", "velocity", "angular_velocity")]
    return int(append_bodies(scene, s, m, *rows, KINDS.index(a["kind"]), lambda i: key, piv)[0])


def add_bodies(
    scene,
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
    """:meth:`Scene.add_bodies <polydem.scene.Scene.add_bodies>` of ``scene``."""
    start, f = scene.body_table.n, scene.file
    p = read_rows(positions, 3, f"bodies[{start}:].position", f)
    n = p.shape[0]
    label = f"bodies[{start}:{start + n}]"
    s = scene.resolve_shape(shape, f"{label}.shape")
    m = scene.material_index(material, key=f"{label}.material")
    kind_code = KINDS.index(read_choice(kind, KINDS, f"{label}.kind", f, what="body kind"))
    q = read_rows((0.0, 0.0, 0.0, 1.0) if orientations is None else orientations, 4, f"{label}.orientation", f, n=n)
    v = read_rows((0.0, 0.0, 0.0) if velocities is None else velocities, 3, f"{label}.velocity", f, n=n)
    w = read_rows(
        (0.0, 0.0, 0.0) if angular_velocities is None else angular_velocities,
        3,
        f"{label}.angular_velocity",
        f,
        n=n,
    )
    piv = None if pivots is None else read_rows(pivots, 3, f"{label}.pivot", f, n=n)
    return append_bodies(scene, s, m, p, q, v, w, kind_code, lambda i: f"bodies[{start + i}]", piv)


def append_bodies(scene, s, m, p, q, v, w, kind_code, rowkey, pivot=None) -> np.ndarray:
    """Store n bodies in ``scene``: ``s`` and ``m`` are one index or (n,) arrays, p, q, v, w are (n, k); the
    checks every way of adding bodies shares (``rowkey(i)``: the key of row i, for messages)."""
    n = p.shape[0]
    if scene.body_table.n + n > MAX_BODIES:
        raise scene.error(
            f"{n} more bodies would make {scene.body_table.n + n:,}, more than a scene can hold ({MAX_BODIES:,})",
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
            raise scene.error(f"expected finite numbers, got {arr[i].tolist()}", f"{rowkey(i)}.{name}")
    for name, arr in (("velocity", v), ("angular_velocity", w)):
        # As BODY declares them, for the arrays of add_bodies that do not pass through it (finite, as checked).
        if not arr.size or np.abs(arr).max() <= F32_HIGH:
            continue
        fast = np.flatnonzero(~(np.abs(arr) <= F32_HIGH).all(axis=1))
        if fast.size:
            i = int(fast[0])
            x = float(arr[i][np.argmax(np.abs(arr[i]))])
            BODY[name].within(x, f"{rowkey(i)}.{name}", scene.file, each=arr[i])
    q = check_quats(q, lambda i: f"{rowkey(i)}.orientation", scene.file)
    if kind_code == KIND_FIXED and (np.any(v != 0.0) or np.any(w != 0.0)):
        moving = np.flatnonzero(np.any(v != 0.0, axis=1) | np.any(w != 0.0, axis=1))
        if moving.size:
            i = int(moving[0])
            which, val = ("velocity", v[i]) if np.any(v[i] != 0.0) else ("angular_velocity", w[i])
            raise scene.error(
                f"a fixed body cannot move, but its {which} is {val.tolist()}; set it to [0, 0, 0], or use "
                "kind = 'kinematic' for a body that moves at a prescribed velocity",
                f"{rowkey(i)}.{which}",
            )
    if pivot is not None:
        if kind_code != KIND_KINEMATIC:
            raise scene.error(
                f"only a kinematic body can turn about a pivot, this one is {KINDS[kind_code]!r}; use kind = "
                "'kinematic' or leave pivot out",
                f"{rowkey(0)}.pivot",
            )
        moving = np.flatnonzero(np.any(v != 0.0, axis=1))
        if moving.size:
            i = int(moving[0])
            raise scene.error(
                f"a body turning about a pivot has the velocity angular_velocity x (centroid - pivot), derived "
                f"from its pose; leave velocity out (got {v[i].tolist()})",
                f"{rowkey(i)}.velocity",
            )
    if np.ndim(s) == 0:
        q_in, t_in = scene.shape_input_frames()[int(s)]
    else:
        s = np.asarray(s, dtype=np.int32)
        frames = scene.shape_input_frames()
        q_in = np.array([frames[k][0] for k in range(len(frames))])[s]
        t_in = np.array([frames[k][1] for k in range(len(frames))])[s]
    # Most generated shapes are built in their principal frame: skip the no-op transforms.
    centroid = p if not np.any(t_in) else p + quat_rotate(q, np.broadcast_to(t_in, p.shape))
    if np.all(q_in == (0.0, 0.0, 0.0, 1.0)):
        q_body = q
    else:
        q_body = quat_multiply(q, q_in)
        q_body /= np.sqrt(np.einsum("ij,ij->i", q_body, q_body))[:, None]
    if pivot is not None:
        with np.errstate(over="ignore", invalid="ignore"):
            v = np.cross(w, centroid - pivot)
        fast = np.flatnonzero(~(np.abs(v) <= F32_HIGH).all(axis=1))
        if fast.size:
            i = int(fast[0])
            # Of the two points whose distance makes the speed, blame the one far out.
            far = "position" if np.abs(centroid[i]).max() > np.abs(pivot[i]).max() else "pivot"
            raise scene.error(
                f"turning at {w[i].tolist()} rad/s about the pivot {pivot[i].tolist()} from {centroid[i].tolist()} "
                f"(its centroid), the body would move at {v[i].tolist()} m/s (angular_velocity x (centroid - "
                f"pivot)), beyond the velocities a run computes with (components up to {F32_HIGH:.3g} m/s); give "
                "a pivot and a position nearer each other or a smaller angular_velocity",
                f"{rowkey(i)}.{far}",
            )
    scene.body_table.reserve(n)
    sl = slice(scene.body_table.n, scene.body_table.n + n)
    a = scene.body_table.arrays
    a["shape"][sl] = s
    a["material"][sl] = m
    a["position"][sl] = centroid
    a["orientation"][sl] = q_body
    a["velocity"][sl] = v
    a["angular_velocity"][sl] = w
    a["kind"][sl] = kind_code
    a["pivot"][sl] = np.nan if pivot is None else pivot
    scene.body_table.n += n
    return np.arange(sl.start, sl.stop, dtype=np.int64)


def body_label(scene, i: int) -> str:
    """:meth:`Scene.body_label <polydem.scene.Scene.body_label>` of ``scene``."""
    s = scene.shape_names[int(scene.body_shape[i])]
    kind = KINDS[int(scene.body_kind[i])]
    where = next((f", from {e['key']}" for e in scene.emitters if e["first"] <= i <= e["last"]), "")
    return f"body {i} (shape {s!r}, {kind}{where})"


def body(scene, i: int) -> Body:
    """:meth:`Scene.body <polydem.scene.Scene.body>` of ``scene``."""
    if not isinstance(i, numbers.Integral) or not -scene.body_table.n <= int(i) < scene.body_table.n:
        raise IndexError(f"body index {i!r} out of range for a scene with {scene.body_table.n} bodies")
    i = int(i) % scene.body_table.n
    a = scene.body_table.arrays
    s = int(a["shape"][i])
    q_in, t_in = scene.shape_input_frames()[s]
    q_body = a["orientation"][i]
    q_user = quat_multiply(q_body, quat_conjugate(q_in))
    q_user /= np.linalg.norm(q_user)
    pos = a["position"][i] - quat_rotate(q_user, t_in)
    return Body(
        shape=scene.shape_names[s],
        material=scene.material_names[int(a["material"][i])],
        position=as_tuple(pos),
        orientation=as_tuple(q_user),
        velocity=as_tuple(a["velocity"][i]),
        angular_velocity=as_tuple(a["angular_velocity"][i]),
        kind=KINDS[int(a["kind"][i])],
        centroid=as_tuple(a["position"][i]),
        body_orientation=as_tuple(q_body),
        pivot=None if np.isnan(a["pivot"][i]).any() else as_tuple(a["pivot"][i]),
    )


def input_poses(scene) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`Scene.input_poses <polydem.scene.Scene.input_poses>` of ``scene``."""
    n = scene.body_table.n
    a = {name: scene.body_table.arrays[name][:n] for name in ("shape", "position", "orientation")}
    frames = scene.shape_input_frames()
    q_in = np.array([fr[0] for fr in frames]).reshape(-1, 4)[a["shape"]]
    t_in = np.array([fr[1] for fr in frames]).reshape(-1, 3)[a["shape"]]
    q_user = quat_multiply(a["orientation"], quat_conjugate(q_in))
    q_user /= np.sqrt(np.einsum("ij,ij->i", q_user, q_user))[:, None]
    return a["position"] - quat_rotate(q_user, t_in), q_user


def body_vertices(scene, i: int) -> np.ndarray:
    """:meth:`Scene.body_vertices <polydem.scene.Scene.body_vertices>` of ``scene``."""
    shape = scene.shapes[scene.shape_names[int(scene.body_shape[i])]]
    return shape.vertices @ quat_to_matrix(scene.body_orientation[i]).T + scene.body_position[i]


def body_mass(scene) -> np.ndarray:
    """:meth:`Scene.body_mass <polydem.scene.Scene.body_mass>` of ``scene``."""
    vol = np.array([s.volume for s in scene.shapes.values()])
    rho = np.array([m.density for m in scene.materials.values()])
    return rho[scene.body_material] * vol[scene.body_shape]


def body_inertia(scene) -> np.ndarray:
    """:meth:`Scene.body_inertia <polydem.scene.Scene.body_inertia>` of ``scene``."""
    inertia = np.array([s.inertia for s in scene.shapes.values()]).reshape(-1, 3)
    rho = np.array([m.density for m in scene.materials.values()])
    return rho[scene.body_material][:, None] * inertia[scene.body_shape]
