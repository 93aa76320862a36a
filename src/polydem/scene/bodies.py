"""Bodies: kinds, the :class:`Body` record, and the Scene methods that store bodies as arrays."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field

import numpy as np

from polydem.quaternions import quat_conjugate, quat_multiply, quat_rotate, quat_to_matrix
from polydem.scene.errors import SceneError
from polydem.scene.values import as_tuple, check_quats, read_choice, read_number, read_rows, read_string, read_vector

KINDS = ("free", "fixed", "kinematic")
"""Body kinds; the integer code stored in :attr:`Scene.body_kind` is the index in this tuple."""
KIND_FREE, KIND_FIXED, KIND_KINEMATIC = 0, 1, 2

MAX_BODIES = 10**8
"""Most bodies of one scene: 100 times the largest scenes the simulator is meant for (10^6), low
enough that a mistyped count fails at once instead of allocating tens of gigabytes (every body holds
some hundred bytes in the scene alone, more on the device)."""

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


def quat_from_axis_angle(axis, angle: float) -> np.ndarray:
    """Unit xyzw quaternion of a rotation by ``angle`` [rad] about ``axis`` (any non-zero length)."""
    a = read_vector(list(axis) if not isinstance(axis, np.ndarray) else axis, 3, "axis")
    n = float(np.linalg.norm(a))
    if n == 0.0:
        raise SceneError("rotation axis is zero; give a non-zero direction such as [0, 0, 1]", "axis")
    angle = read_number(angle, "angle")
    return np.concatenate([a / n * math.sin(0.5 * angle), [math.cos(0.5 * angle)]])


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


class BodyMethods:
    """The :class:`~polydem.scene.Scene` methods that add bodies and read them back."""

    def __init__(self):
        # The state of this group; Scene.__init__ reaches every group's __init__ through super().
        self._n = 0
        self._cap = 0
        self._arrays = {name: np.empty((0, *shape), dtype) for name, dtype, shape in BODY_FIELDS}
        super().__init__()

    def body_arrays(self) -> dict[str, np.ndarray]:
        """The stored body arrays by field name (see BODY_FIELDS), trimmed to the bodies: not copies, for reading."""
        return {name: self._arrays[name][: self._n] for name, _, _ in BODY_FIELDS}

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
        key: str | None = None,
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
            key: where the value came from, for error messages (default ``bodies[N]``).
        """
        key = key or f"bodies[{self._n}]"
        f = self.file
        s = self.resolve_shape(shape, f"{key}.shape")
        m = self.material_index(material, key=f"{key}.material")
        kind_code = KINDS.index(read_choice(kind, KINDS, f"{key}.kind", f, what="body kind"))
        p = read_vector(position, 3, f"{key}.position", f)
        q = read_vector(orientation, 4, f"{key}.orientation", f)
        v = read_vector(velocity, 3, f"{key}.velocity", f)
        w = read_vector(angular_velocity, 3, f"{key}.angular_velocity", f)
        piv = None if pivot is None else read_vector(pivot, 3, f"{key}.pivot", f)[None]
        return int(self.append_bodies(s, m, p[None], q[None], v[None], w[None], kind_code, lambda i: key, piv)[0])

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
        p = read_rows(positions, 3, f"bodies[{start}:].position", f)
        n = p.shape[0]
        label = f"bodies[{start}:{start + n}]"
        s = self.resolve_shape(shape, f"{label}.shape")
        m = self.material_index(material, key=f"{label}.material")
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
        return self.append_bodies(s, m, p, q, v, w, kind_code, lambda i: f"bodies[{start + i}]", piv)

    def append_bodies(self, s, m, p, q, v, w, kind_code, rowkey, pivot=None) -> np.ndarray:
        """Store n bodies. ``s`` and ``m`` are one index or (n,) arrays; p, q, v, w are (n, k)."""
        n = p.shape[0]
        if self._n + n > MAX_BODIES:
            raise self.error(
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
                raise self.error(f"expected finite numbers, got {arr[i].tolist()}", f"{rowkey(i)}.{name}")
        q = check_quats(q, lambda i: f"{rowkey(i)}.orientation", self.file)
        if kind_code == KIND_FIXED and (np.any(v != 0.0) or np.any(w != 0.0)):
            moving = np.flatnonzero(np.any(v != 0.0, axis=1) | np.any(w != 0.0, axis=1))
            if moving.size:
                i = int(moving[0])
                which, val = ("velocity", v[i]) if np.any(v[i] != 0.0) else ("angular_velocity", w[i])
                raise self.error(
                    f"a fixed body cannot move, but its {which} is {val.tolist()}; set it to [0, 0, 0], or use "
                    "kind = 'kinematic' for a body that moves at a prescribed velocity",
                    f"{rowkey(i)}.{which}",
                )
        if pivot is not None:
            if kind_code != KIND_KINEMATIC:
                raise self.error(
                    f"only a kinematic body can turn about a pivot, this one is {KINDS[kind_code]!r}; use kind = "
                    "'kinematic' or leave pivot out",
                    f"{rowkey(0)}.pivot",
                )
            moving = np.flatnonzero(np.any(v != 0.0, axis=1))
            if moving.size:
                i = int(moving[0])
                raise self.error(
                    f"a body turning about a pivot has the velocity angular_velocity x (centroid - pivot), derived "
                    f"from its pose; leave velocity out (got {v[i].tolist()})",
                    f"{rowkey(i)}.velocity",
                )
        if np.ndim(s) == 0:
            q_in, t_in = self.shape_input_frames()[int(s)]
        else:
            s = np.asarray(s, dtype=np.int32)
            frames = self.shape_input_frames()
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
            v = np.cross(w, centroid - pivot)
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
        for name, dtype, shape in BODY_FIELDS:
            new = np.zeros((cap, *shape), dtype)
            new[: self._n] = self._arrays[name][: self._n]
            self._arrays[name] = new
        self._cap = cap

    def body_label(self, i: int) -> str:
        """``body 12 (shape 'cube', free, from emitters[0])``: how messages name a body."""
        s = self.shape_names[int(self.body_shape[i])]
        kind = KINDS[int(self.body_kind[i])]
        where = next((f", from {e['key']}" for e in self.emitters if e["first"] <= i <= e["last"]), "")
        return f"body {i} (shape {s!r}, {kind}{where})"

    def body(self, i: int) -> Body:
        """Body ``i`` as a :class:`Body` (input-frame pose as given, plus its centroid and body frame)."""
        if not isinstance(i, numbers.Integral) or not -self._n <= int(i) < self._n:
            raise IndexError(f"body index {i!r} out of range for a scene with {self._n} bodies")
        i = int(i) % self._n
        a = self._arrays
        s = int(a["shape"][i])
        q_in, t_in = self.shape_input_frames()[s]
        q_body = a["orientation"][i]
        q_user = quat_multiply(q_body, quat_conjugate(q_in))
        q_user /= np.linalg.norm(q_user)
        pos = a["position"][i] - quat_rotate(q_user, t_in)
        return Body(
            shape=self.shape_names[s],
            material=self.material_names[int(a["material"][i])],
            position=as_tuple(pos),
            orientation=as_tuple(q_user),
            velocity=as_tuple(a["velocity"][i]),
            angular_velocity=as_tuple(a["angular_velocity"][i]),
            kind=KINDS[int(a["kind"][i])],
            centroid=as_tuple(a["position"][i]),
            body_orientation=as_tuple(q_body),
            pivot=None if np.isnan(a["pivot"][i]).any() else as_tuple(a["pivot"][i]),
        )

    def input_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) positions [m] and (N, 4) xyzw orientations of the bodies' input frames: the poses as
        given to :meth:`add_body` (see the module docstring of :mod:`polydem.scene` for the frames)."""
        n = self._n
        a = {name: self._arrays[name][:n] for name in ("shape", "position", "orientation")}
        frames = self.shape_input_frames()
        q_in = np.array([fr[0] for fr in frames]).reshape(-1, 4)[a["shape"]]
        t_in = np.array([fr[1] for fr in frames]).reshape(-1, 3)[a["shape"]]
        q_user = quat_multiply(a["orientation"], quat_conjugate(q_in))
        q_user /= np.sqrt(np.einsum("ij,ij->i", q_user, q_user))[:, None]
        return a["position"] - quat_rotate(q_user, t_in), q_user

    def body_vertices(self, i: int) -> np.ndarray:
        """(nv, 3) world coordinates of body ``i``'s vertices [m]."""
        shape = self.shapes[self.shape_names[int(self.body_shape[i])]]
        return shape.vertices @ quat_to_matrix(self.body_orientation[i]).T + self.body_position[i]

    def body_mass(self) -> np.ndarray:
        """(N,) mass of each body [kg] (density times volume, whatever the kind)."""
        vol = np.array([s.volume for s in self.shapes.values()])
        rho = np.array([m.density for m in self.materials.values()])
        return rho[self.body_material] * vol[self.body_shape]

    def body_inertia(self) -> np.ndarray:
        """(N, 3) principal moments of inertia of each body [kg m^2], about its body-frame axes."""
        inertia = np.array([s.inertia for s in self.shapes.values()]).reshape(-1, 3)
        rho = np.array([m.density for m in self.materials.values()])
        return rho[self.body_material][:, None] * inertia[self.body_shape]
