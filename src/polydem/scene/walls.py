"""Walls: plane walls, triangle-mesh walls, box containers of fixed slabs and rotating drums of kinematic slabs."""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field

import numpy as np

from polydem.meshwall import CELL_TOLERANCE, MAX_SIZE_RATIO, MeshWallError, check_winding, clean_triangles
from polydem.quaternions import quat_from_matrix
from polydem.scene.bodies import KIND_KINEMATIC, BodyKind, append_bodies
from polydem.scene.materials import Material
from polydem.scene.schema import LENGTH, LENGTH_WHY, REQUIRED, SPEED, SPEED_WHY, Key, Table
from polydem.scene.values import as_tuple, read_number, read_string, read_vector, unit_normal
from polydem.shapes import ConvexShape

# Each wall type's table. "type" is read first (its own message lists the types), and written by to_dict.
_TYPE = Key("type", "string", default=REQUIRED, write="never")
_MATERIAL = Key("material", "any", default=REQUIRED)
_CENTER = Key("center", "vector", unit="m", default=REQUIRED)

PLANE = Table(
    "[[walls]] type = 'plane'",
    (
        _TYPE,
        Key("point", "vector", unit="m", default=REQUIRED),
        Key("normal", "vector", default=REQUIRED, check=unit_normal),
        _MATERIAL,
        Key("motion", "string", what="a motion name", hint="the [motions.NAME] (a cycle or a ramp) it follows"),
    ),
)
"""An infinite plane wall: the arguments of :meth:`Scene.add_plane`."""

BOX = Table(
    "[[walls]] type = 'box'",
    (
        _TYPE,
        _CENTER,
        Key("inner_size", "vector", unit="m", label="[lx, ly, lz]", range=LENGTH, why=LENGTH_WHY, default=REQUIRED),
        _MATERIAL,
        Key("wall_thickness", unit="m", range=LENGTH, why=LENGTH_WHY, hint="in m"),
        Key("open_top", "boolean", default=True),
        Key("motion", "string", what="a motion name", hint="the [motions.NAME] its slabs follow"),
    ),
)
"""A box container of fixed slabs (kinematic ones that follow ``motion``): the arguments of
:meth:`Scene.add_box_container`."""

DRUM = Table(
    "[[walls]] type = 'drum'",
    (
        _TYPE,
        _CENTER,
        Key("axis", "vector", default=REQUIRED),
        Key("radius", unit="m", range=LENGTH, why=LENGTH_WHY, default=REQUIRED, hint="inner radius in m"),
        Key(
            "length",
            unit="m",
            range=LENGTH,
            why=LENGTH_WHY,
            default=REQUIRED,
            hint="inner length along the axis in m",
        ),
        _MATERIAL,
        Key("omega", unit="rad/s", range=SPEED, why=SPEED_WHY, hint="angular speed in rad/s"),
        Key("rpm", unit="1/min", range=SPEED, why=SPEED_WHY, hint="revolutions per minute"),
        Key("sides", "integer", range="[3, 1000]", default=24, hint="number of slabs"),
        Key("thickness", unit="m", range=LENGTH, why=LENGTH_WHY, hint="in m"),
        Key("caps", "boolean", default=True),
    ),
)
"""A rotating polygonal drum of kinematic slabs: the arguments of :meth:`Scene.add_drum`."""

MESH = Table(
    "[[walls]] type = 'mesh'",
    (
        _TYPE,
        Key("file", "string", what="a file path string", write="never"),
        Key("vertices", "any", unit="m"),
        Key("triangles", "any"),
        _MATERIAL,
        Key("scale", "any", default=1.0, write="never", hint="a factor, e.g. 0.001 for mm"),
        Key("rotation", "rotation", attr="orientation", write="never"),
        Key("orientation", "vector", size=4, write="never"),
        Key("position", "vector", unit="m", default=(0.0, 0.0, 0.0), write="never"),
        Key("flip_normals", "boolean", default=False, write="never"),
        Key("thickness", unit="m", range=LENGTH, why=LENGTH_WHY, hint="depth of the solid in m"),
        Key("velocity", "vector", unit="m/s", range=SPEED, why=SPEED_WHY, default=(0.0, 0.0, 0.0), write="changed"),
        Key(
            "angular_velocity",
            "vector",
            unit="rad/s",
            range=SPEED,
            why=SPEED_WHY,
            default=(0.0, 0.0, 0.0),
            write="changed",
        ),
        Key("pivot", "vector", unit="m"),
        Key("motion", "string", what="a motion name", hint="the [motions.NAME] (a cycle or a ramp) it follows"),
    ),
)
"""A triangle-mesh wall: the arguments of :meth:`Scene.add_mesh_wall`, the mesh given as ``file`` or as
``vertices`` and ``triangles``; written back as its vertices in the world at t = 0 (scale, orientation and
position applied) with its motion."""

WALL_TYPES = {"plane": PLANE, "box": BOX, "drum": DRUM, "mesh": MESH}
"""The ``type`` values of ``[[walls]]`` tables and their declarations."""


@dataclass(frozen=True)
class PlaneWall:
    """An infinite plane wall; bodies are pushed to the side the normal points to.

    Attributes:
        point: (3,) a point on the plane [m].
        normal: (3,) unit normal [-] pointing into the simulated half-space; normalised on
            construction (any non-zero length is accepted).
        material: name of a material registered in the scene.
        motion: the name of the motion (a cycle or a ramp, :mod:`polydem.scene.motions`) that moves the plane
            along its axis from where it is at t = 0, or None: fixed.
    """

    point: tuple
    normal: tuple
    material: str
    motion: str | None = None

    def __post_init__(self):
        values = PLANE.read({"point": self.point, "normal": self.normal}, "plane")
        object.__setattr__(self, "point", as_tuple(values["point"]))
        object.__setattr__(self, "normal", as_tuple(values["normal"]))
        read_string(self.material, "plane.material", what="a material name")

    def to_dict(self) -> dict:
        return {"type": "plane", **PLANE.write(self)}


@dataclass(frozen=True, eq=False)
class MeshWall:
    """A wall made of a triangle mesh, solid behind its triangles (see :mod:`polydem.meshwall`).

    Attributes:
        vertices: (nv, 3) float64 vertices in world coordinates at t = 0 [m] (read-only), after the
            scale, rotation and translation of :meth:`Scene.add_mesh_wall`, merged.
        triangles: (nf, 3) int64 vertex indices, counter-clockwise seen from the front (the side
            the bodies are on); the wall is solid behind them, against their normals.
        material: material name.
        pivot: (3,) origin of the wall's frame [m]; the wall turns about it.
        velocity: (3,) velocity of the whole wall [m/s] (the pivot moves with it).
        angular_velocity: (3,) [rad/s] about the pivot, world axes.
        thickness: depth of the solid behind each triangle [m], or None: the largest bounding
            diameter of the scene's free bodies.
        source: where the mesh came from (a file path, or "vertices" for arrays), for messages.
        scale: (3,) the factors applied to the given coordinates (for messages; ``vertices`` has them).
        motion: the name of the motion (a cycle or a ramp, :mod:`polydem.scene.motions`) that moves the whole
            wall along its axis from where it is at t = 0 (then velocity and angular_velocity are 0), or None.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    material: str
    pivot: tuple
    velocity: tuple = MESH.defaults["velocity"]
    angular_velocity: tuple = MESH.defaults["angular_velocity"]
    thickness: float | None = MESH.defaults["thickness"]
    source: str = "vertices"
    scale: tuple = (1.0, 1.0, 1.0)
    motion: str | None = None

    @property
    def moving(self) -> bool:
        return any(self.velocity) or any(self.angular_velocity)

    def to_dict(self) -> dict:
        return {"type": "mesh", **MESH.write(self)}


def mesh_input(mesh, key, file, base_dir):
    """(vertices, triangles, source) of a mesh given as a file path, a trimesh.Trimesh or a
    ``(vertices, triangles)`` pair."""
    from pathlib import Path

    from polydem.scene.errors import SceneError

    if isinstance(mesh, str | Path):
        from polydem.shapes import load_mesh

        path = Path(mesh).expanduser()
        if not path.is_absolute() and base_dir is not None:
            path = Path(base_dir) / path
        if not path.is_file():
            what = "is not a file" if path.exists() else "not found"
            where = f"; relative paths are taken from the folder of the scene file, '{base_dir}'" if base_dir else ""
            raise SceneError(f"mesh file {str(mesh)!r} {what} (looked for '{path}'{where})", f"{key}.file", file)
        try:
            tm = load_mesh(path)
        except ValueError as exc:
            raise SceneError(str(exc), f"{key}.file", file) from None
        return np.asarray(tm.vertices, dtype=np.float64), np.asarray(tm.faces, dtype=np.int64), str(path)
    if hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces), "trimesh"
    if isinstance(mesh, tuple | list) and len(mesh) == 2:
        try:
            v = np.asarray(mesh[0], dtype=np.float64)
            f = np.asarray(mesh[1])
        except (TypeError, ValueError) as exc:
            raise SceneError(f"cannot read the mesh arrays: {exc}", f"{key}.vertices", file) from None
        if f.size and not np.issubdtype(f.dtype, np.integer):
            if not np.all(np.mod(f, 1) == 0):
                raise SceneError("triangle indices must be integers", f"{key}.triangles", file)
        return v, f.astype(np.int64), "vertices"
    raise SceneError(
        f"expected a mesh file path, a trimesh.Trimesh or (vertices, triangles), got {type(mesh).__name__}",
        f"{key}.file",
        file,
    )


def _sound(vertices, triangles) -> bool:
    """Whether a mesh wall's mesh as given (before its scale and placement) has triangles of consistent winding."""
    try:
        check_winding(*clean_triangles(vertices, triangles, label="mesh"), label="mesh")
    except MeshWallError:
        return False
    return True


# Each mesh wall's cells at its last thickness, and what the checks derived from them: a wall is
# immutable (frozen, its arrays read-only), so they hold as long as it lives.
_CELLS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


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


_SLAB_WHY = (
    f"its slabs are shapes built to {CELL_TOLERANCE:g} of their longest side (as a mesh wall's cells), so its lengths "
    f"may be at most {MAX_SIZE_RATIO:g} times apart"
)


def _apart(name: str, words: str, value: float, far: tuple[str, float], allowed: tuple[float, float], what: str) -> str:
    """The message for a wall's length ``name`` (``words`` for it, ``value`` [m]) more than MAX_SIZE_RATIO from
    ``far`` (its words and value) of ``what`` ("the drum"); ``allowed``: the range that fits its other lengths."""
    low, high = allowed
    fix = f"give a {name} from {low:.3g} to {high:.3g} m" if low <= high else "bring its lengths closer together"
    return (
        f"the {words} {value:.3g} m and {what}'s {far[0]} {far[1]:.3g} m are more than {MAX_SIZE_RATIO:g} times "
        f"apart: {_SLAB_WHY}; {fix}"
    )


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


@dataclass
class WallTable:
    """The walls of a scene, each kind in the order they were added, with the keys they came from (``walls[0]``
    of a scene file, ``planes[1]``, ...: for messages)."""

    planes: list[PlaneWall] = field(default_factory=list)
    plane_keys: list[str] = field(default_factory=list)
    mesh_walls: list[MeshWall] = field(default_factory=list)
    mesh_wall_keys: list[str] = field(default_factory=list)
    drums: list[Drum] = field(default_factory=list)


def wall_motion(scene, motion, key: str) -> str | None:
    """The name of the motion a plane or mesh wall follows (None: none), checked: a cycle or a ramp. A servo is
    refused: it is driven by the force on the bodies it moves, summed from their pair contacts."""
    if motion is None:
        return None
    m = scene.motion_named(motion, key)
    if m.kind == "servo":
        raise scene.error(
            f"motion {motion!r} is a servo, which a plane or mesh wall cannot follow (a servo is driven by the force "
            "the grains push its bodies back with): press with a kinematic body or a box wall that follows it, or "
            "give this wall a cycle or a ramp",
            key,
        )
    return motion


def add_plane(scene, point, normal, material, *, motion: str | None = None, key: str | None = None) -> PlaneWall:
    """:meth:`Scene.add_plane <polydem.scene.Scene.add_plane>` of ``scene``."""
    key = key or f"planes[{len(scene.wall_table.planes)}]"
    values = PLANE.read({"point": point, "normal": normal}, key, scene.file)
    scene.material_index(material, key=f"{key}.material")
    name = material.name if isinstance(material, Material) else material
    motion = wall_motion(scene, motion, f"{key}.motion")
    plane = PlaneWall(point=as_tuple(values["point"]), normal=as_tuple(values["normal"]), material=name, motion=motion)
    scene.wall_table.planes.append(plane)
    scene.wall_table.plane_keys.append(key)
    return plane


def add_mesh_wall(
    scene,
    mesh,
    material,
    *,
    scale=MESH.defaults["scale"],
    orientation=MESH.defaults["orientation"],
    position=MESH.defaults["position"],
    velocity=MESH.defaults["velocity"],
    angular_velocity=MESH.defaults["angular_velocity"],
    pivot=MESH.defaults["pivot"],
    thickness=MESH.defaults["thickness"],
    flip_normals: bool = MESH.defaults["flip_normals"],
    motion: str | None = MESH.defaults["motion"],
    key: str | None = None,
    base_dir=None,
) -> MeshWall:
    """:meth:`Scene.add_mesh_wall <polydem.scene.Scene.add_mesh_wall>` of ``scene``."""
    from polydem.quaternions import quat_to_matrix

    key = key or f"mesh_walls[{len(scene.wall_table.mesh_walls)}]"
    f = scene.file
    scene.material_index(material, key=f"{key}.material")
    name = material.name if isinstance(material, Material) else material
    v, tri, source = mesh_input(mesh, key, f, base_dir)
    if np.ndim(scale) == 0:
        sc = np.full(3, read_number(scale, f"{key}.scale", f, hint=MESH["scale"].hint_text()))
    else:
        sc = read_vector(scale, 3, f"{key}.scale", f)
    if np.any(sc == 0.0) or not np.all(np.isfinite(sc)):
        raise scene.error(
            f"scale {sc.tolist()} has a zero or non-finite factor; give factors such as 0.001", f"{key}.scale"
        )
    given = {"orientation": orientation, "position": position, "flip_normals": flip_normals}
    given.update(thickness=thickness, velocity=velocity, angular_velocity=angular_velocity, pivot=pivot)
    a = MESH.read(given, key, f)
    rot = np.eye(3)
    if a["orientation"] is not None:
        q = a["orientation"]
        norm = float(np.linalg.norm(q))
        if not abs(norm - 1.0) <= 1e-6:
            raise scene.error(
                f"orientation {q.tolist()} is not a unit quaternion xyzw (|q| = {norm:.6g})", f"{key}.orientation"
            )
        rot = quat_to_matrix(q / norm)
    pos, vel, omega, thickness = a["position"], a["velocity"], a["angular_velocity"], a["thickness"]
    motion = wall_motion(scene, motion, f"{key}.motion")
    if motion is not None and (np.any(vel != 0.0) or np.any(omega != 0.0)):
        which = "velocity" if np.any(vel != 0.0) else "angular_velocity"
        raise scene.error(
            f"a mesh wall follows either its motion ({motion!r}) or its velocity and angular_velocity, not both: "
            f"leave out {which} or motion",
            f"{key}.{which}",
        )
    piv = pos if a["pivot"] is None else a["pivot"]
    flip = a["flip_normals"]
    given = v, tri
    if v.ndim == 2 and v.shape[1] == 3:
        with np.errstate(over="ignore", invalid="ignore"):
            v = (v * sc) @ rot.T + pos
    # A mirror (an odd number of negative factors) turns the triangles inside out: re-orient them.
    if (np.prod(np.sign(sc)) < 0) != flip and tri.ndim == 2:
        tri = tri[:, ::-1]
    try:
        v, tri = clean_triangles(v, tri, label=f"mesh {source}")
        check_winding(v, tri, label=f"mesh {source}")
    except MeshWallError as exc:
        # A mesh that is sound as given was spoilt by its scale or by where it was placed: name that.
        v0, tri0 = given
        placed = v0.ndim == 2 and v0.shape[1] == 3 and _sound(v0, tri0)
        with np.errstate(over="ignore", invalid="ignore"):
            if placed and np.any(sc != 1.0) and not _sound(v0 * sc, tri0):
                raise scene.error(
                    f"{exc} after scale {sc.tolist()} (the mesh as given is sound): the scale takes its "
                    "triangles beyond what float64 resolves; give the mesh file's unit in m (0.001 for mm), with "
                    f"factors within {MAX_SIZE_RATIO:g} of each other",
                    f"{key}.scale",
                ) from None
            if placed and _sound((v0 * sc) @ rot.T, tri0):
                far = float(np.abs(pos).max())
                raise scene.error(
                    f"{exc} at position {pos.tolist()} (at the origin it is sound): float64 numbers are "
                    f"{np.spacing(far):.3g} m apart there, too coarse for its triangles; place the scene nearer "
                    "the origin (only relative positions matter)",
                    f"{key}.position",
                ) from None
        raise scene.error(str(exc), f"{key}.file" if source not in ("vertices", "trimesh") else key) from None
    v.setflags(write=False)
    tri.setflags(write=False)
    wall = MeshWall(
        vertices=v,
        triangles=tri,
        material=name,
        pivot=as_tuple(piv),
        velocity=as_tuple(vel),
        angular_velocity=as_tuple(omega),
        thickness=thickness,
        source=source,
        scale=as_tuple(sc),
        motion=motion,
    )
    scene.wall_table.mesh_walls.append(wall)
    scene.wall_table.mesh_wall_keys.append(key)
    return wall


def mesh_wall_thickness(scene, wall: MeshWall) -> float:
    """:meth:`Scene.mesh_wall_thickness <polydem.scene.Scene.mesh_wall_thickness>` of ``scene``."""
    if wall.thickness is not None:
        return float(wall.thickness)
    shapes = list(scene.shapes.values())
    kind = np.asarray(scene.body_kind)
    free = kind == BodyKind.FREE
    used = np.unique(np.asarray(scene.body_shape)[free]) if free.any() else range(len(shapes))
    return 2.0 * max(shapes[int(k)].radius for k in used)


def mesh_wall_cells(scene, wall: MeshWall, thickness: float):
    """:meth:`Scene.mesh_wall_cells <polydem.scene.Scene.mesh_wall_cells>` of ``scene``."""
    from polydem.meshwall import build_cells

    key = scene.mesh_wall_keys[[id(w) for w in scene.wall_table.mesh_walls].index(id(wall))]
    kept = _CELLS.get(wall)
    if kept is None or kept[0] != thickness:
        try:
            pivot = np.asarray(wall.pivot, dtype=np.float64)
            label = f"mesh wall {key} ({wall.source})"
            cells = build_cells(wall.vertices - pivot, wall.triangles, thickness, label=label)
        except MeshWallError as exc:
            if not _sound(wall.vertices - pivot, wall.triangles):
                far = float(np.abs(wall.vertices - pivot).max())
                raise scene.error(
                    f"{exc} in the frame of its pivot {list(wall.pivot)}, where its cells are built: float64 "
                    f"numbers {far:.3g} m from the pivot are {np.spacing(far):.3g} m apart, too coarse for its "
                    "triangles; give a pivot nearer the wall",
                    f"{key}.pivot",
                ) from None
            raise scene.error(str(exc), key) from None
        kept = _CELLS[wall] = (thickness, cells, {})
    return kept[1]


def mesh_wall_memo(scene, wall: MeshWall, thickness: float) -> dict:
    """A dict kept with the cells of ``wall`` at ``thickness`` (see :func:`mesh_wall_cells`), for the
    checks' results that depend on nothing else."""
    mesh_wall_cells(scene, wall, thickness)
    return _CELLS[wall][2]


def add_box_container(
    scene,
    center,
    inner_size,
    material,
    wall_thickness=BOX.defaults["wall_thickness"],
    open_top: bool = BOX.defaults["open_top"],
    *,
    motion: str | None = None,
    key: str | None = None,
) -> list[int]:
    """:meth:`Scene.add_box_container <polydem.scene.Scene.add_box_container>` of ``scene``."""
    key = key or "box_container"
    a = BOX.read({"center": center, "inner_size": inner_size}, key, scene.file)
    c, size = a["center"], a["inner_size"]
    a = BOX.read({"wall_thickness": wall_thickness, "open_top": open_top}, key, scene.file)
    t = 0.1 * float(size.min()) if a["wall_thickness"] is None else a["wall_thickness"]
    if size.max() > MAX_SIZE_RATIO * size.min():
        raise scene.error(
            f"the inner sizes {size.tolist()} m are more than {MAX_SIZE_RATIO:g} times apart: {_SLAB_WHY}; give "
            f"inner sizes within a factor of {MAX_SIZE_RATIO:g} of each other",
            f"{key}.inner_size",
        )
    if not size.max() / MAX_SIZE_RATIO <= t <= size.min() * MAX_SIZE_RATIO:
        words = "wall_thickness"
        if a["wall_thickness"] is None:
            words = "default wall_thickness (a tenth of the smallest inner size)"
        far = ("smallest inner size", size.min()) if t > size.min() else ("largest inner size", size.max())
        allowed = (size.max() / MAX_SIZE_RATIO, size.min() * MAX_SIZE_RATIO)
        raise scene.error(_apart("wall_thickness", words, t, far, allowed, "the container"), f"{key}.wall_thickness")
    open_top = a["open_top"]
    scene.material_index(material, key=f"{key}.material")
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
    if motion is not None:
        scene.motion_named(motion, f"{key}.motion")
    indices = []
    for dims, offset in walls:
        name = _box_shape(scene, dims)
        kind = "fixed" if motion is None else "kinematic"
        indices.append(scene.add_body(name, material, position=c + np.array(offset), kind=kind))
    if motion is not None:
        scene.drive(indices, motion, key=f"{key}.motion")
    return indices


def _box_shape(scene, dims) -> str:
    dims = [float(d) for d in dims]
    name = "wall_box_" + "x".join(f"{d:.6g}" for d in dims)
    return _shape_for_spec(scene, name, {"type": "box", "size": dims}, lambda nm: ConvexShape.box(*dims, name=nm))


def _shape_for_spec(scene, name, spec, build) -> str:
    """Name of the registered shape of this spec: ``name``, or ``name_2``, ... where ``name`` is taken by
    another spec; ``build(name)`` makes it when there is none yet."""
    base, k = name, 1
    while name in scene.shape_names and scene.shape_spec(name) != spec:
        k += 1
        name = f"{base}_{k}"
    if name not in scene.shape_names:
        scene.add_shape(name, build(name), spec=spec)
    return name


# ------------------------------------------------------------------ drums


def add_drum(
    scene,
    center,
    axis,
    radius,
    length,
    material,
    *,
    omega=DRUM.defaults["omega"],
    rpm=DRUM.defaults["rpm"],
    sides=DRUM.defaults["sides"],
    thickness=DRUM.defaults["thickness"],
    caps=DRUM.defaults["caps"],
    key: str | None = None,
) -> Drum:
    """:meth:`Scene.add_drum <polydem.scene.Scene.add_drum>` of ``scene``."""
    key = key or f"drums[{len(scene.wall_table.drums)}]"
    v = DRUM.read({"center": center, "axis": axis}, key, scene.file)
    c, a = v["center"], v["axis"]
    if np.linalg.norm(a) < 1e-12:
        raise scene.error(
            f"axis {a.tolist()} is zero; give the direction of the drum axis, e.g. [0, 1, 0]", f"{key}.axis"
        )
    a = a / np.linalg.norm(a)
    v = DRUM.read(
        {"radius": radius, "length": length, "sides": sides, "thickness": thickness, "caps": caps}, key, scene.file
    )
    r, length, n, caps = v["radius"], v["length"], v["sides"], v["caps"]
    t = 0.1 * r if v["thickness"] is None else v["thickness"]
    lengths = {"radius": r, "length": length, "thickness": t}
    small, large = min(lengths, key=lengths.get), max(lengths, key=lengths.get)
    if lengths[large] > MAX_SIZE_RATIO * lengths[small]:
        if v["thickness"] is None:
            # The default thickness follows the radius: blame what was given.
            name = large if small == "thickness" else small if large == "thickness" else "radius"
        else:
            # The odd one out: the end of the pair farther from the third length.
            (middle,) = (x for k, x in lengths.items() if k not in (small, large))
            name = large if lengths[large] * lengths[small] >= middle * middle else small
        others = {k: x for k, x in lengths.items() if k != name}
        far = min(others.items(), key=lambda kx: kx[1] if lengths[name] > kx[1] else -kx[1])
        allowed = (max(others.values()) / MAX_SIZE_RATIO, min(others.values()) * MAX_SIZE_RATIO)
        raise scene.error(_apart(name, name, lengths[name], far, allowed, "the drum"), f"{key}.{name}")
    if (omega is None) == (rpm is None):
        raise scene.error(
            "give the rotation speed as exactly one of omega (rad/s) or rpm (revolutions per minute)",
            f"{key}.omega" if omega is None else f"{key}.rpm",
        )
    v = DRUM.read({"omega": omega, "rpm": rpm}, key, scene.file)
    w = v["omega"] if omega is not None else v["rpm"] * 2.0 * math.pi / 60.0
    mat = scene.material_index(material, key=f"{key}.material")
    name = scene.material_names[mat]
    radial = _drum_radial(a, n)
    tangent = np.cross(np.broadcast_to(a, radial.shape), radial)
    slab = _box_shape(scene, (2.0 * r * math.tan(math.pi / n), length, t))
    quats = np.array([quat_from_matrix(np.column_stack([tangent[k], a, radial[k]])) for k in range(n)])
    omega_vec = np.broadcast_to(w * a, (n, 3))
    zeros = np.zeros((n, 3))
    idx = [
        append_bodies(
            scene,
            scene.shape_index(slab),
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
        idx.append(_drum_caps(scene, c, a, n, r, t, length, w, mat, key))
    drum = Drum(
        center=as_tuple(c),
        axis=as_tuple(a),
        radius=r,
        length=length,
        sides=n,
        thickness=t,
        omega=w,
        material=name,
        caps=caps,
        bodies=tuple(int(i) for i in np.concatenate(idx)),
    )
    scene.wall_table.drums.append(drum)
    return drum


def _drum_caps(scene, c, a, n, r, t, length, w, mat, key) -> np.ndarray:
    """Add the two end plates of a drum (see :meth:`Scene.add_drum`); returns their indices."""
    rho = (r + t) / math.cos(math.pi / n) ** 2
    spec = {"type": "prism", "n": n, "radius": rho, "height": t}
    cap_name = _shape_for_spec(
        scene, f"drum_cap_{n}_{rho:.6g}x{t:.6g}", spec, lambda nm: ConvexShape.prism(n, rho, t, name=nm)
    )
    e1, e2 = _perpendicular_basis(a)
    q_cap = quat_from_matrix(np.column_stack([e1, e2, a]))
    ends = np.array([c + (0.5 * length + 0.5 * t) * a, c - (0.5 * length + 0.5 * t) * a])
    return append_bodies(
        scene,
        scene.shape_index(cap_name),
        mat,
        ends,
        np.tile(q_cap, (2, 1)),
        np.zeros((2, 3)),
        np.tile(w * a, (2, 1)),
        KIND_KINEMATIC,
        lambda i: key,
        np.tile(c, (2, 1)),
    )
