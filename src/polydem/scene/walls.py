"""Walls: plane walls, triangle-mesh walls, box containers of fixed slabs and rotating drums of kinematic slabs."""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import numpy as np

from polydem.meshwall import MeshWallError, check_winding, clean_triangles
from polydem.quaternions import quat_from_matrix
from polydem.scene.bodies import KIND_KINEMATIC
from polydem.scene.materials import Material
from polydem.scene.values import (
    as_tuple,
    read_boolean,
    read_integer,
    read_number,
    read_string,
    read_vector,
    unit_normal,
)
from polydem.shapes import ConvexShape


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
        object.__setattr__(self, "point", as_tuple(read_vector(self.point, 3, "plane.point")))
        object.__setattr__(self, "normal", as_tuple(unit_normal(self.normal, "plane.normal", None)))
        read_string(self.material, "plane.material", what="a material name")

    def to_dict(self) -> dict:
        return {"type": "plane", "point": list(self.point), "normal": list(self.normal), "material": self.material}


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
    """

    vertices: np.ndarray
    triangles: np.ndarray
    material: str
    pivot: tuple
    velocity: tuple = (0.0, 0.0, 0.0)
    angular_velocity: tuple = (0.0, 0.0, 0.0)
    thickness: float | None = None
    source: str = "vertices"
    scale: tuple = (1.0, 1.0, 1.0)

    @property
    def moving(self) -> bool:
        return any(self.velocity) or any(self.angular_velocity)

    def to_dict(self) -> dict:
        d = {
            "type": "mesh",
            "vertices": self.vertices.tolist(),
            "triangles": self.triangles.tolist(),
            "material": self.material,
            "pivot": list(self.pivot),
        }
        if self.moving:
            d["velocity"] = list(self.velocity)
            d["angular_velocity"] = list(self.angular_velocity)
        if self.thickness is not None:
            d["thickness"] = self.thickness
        return d


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


class WallMethods:
    """The :class:`~polydem.scene.Scene` methods that add plane walls, box containers and drums."""

    def __init__(self):
        # The state of this group; Scene.__init__ reaches every group's __init__ through super().
        self._planes: list[PlaneWall] = []
        self._plane_keys: list[str] = []
        self._mesh_walls: list[MeshWall] = []
        self._mesh_wall_keys: list[str] = []
        self.drums: list[Drum] = []
        super().__init__()

    @property
    def planes(self) -> list[PlaneWall]:
        """Plane walls (a copy of the list)."""
        return list(self._planes)

    @property
    def plane_keys(self) -> list[str]:
        """Where each plane wall came from, e.g. ``walls[0]`` of a scene file or ``planes[1]`` (for messages)."""
        return list(self._plane_keys)

    def add_plane(self, point, normal, material, *, key: str | None = None) -> PlaneWall:
        """Add an infinite plane through ``point`` [m] facing ``normal`` (normalised; non-zero).

        ``key`` is where the value came from, for error messages (default ``planes[N]``).
        """
        key = key or f"planes[{len(self._planes)}]"
        p = read_vector(point, 3, f"{key}.point", self.file)
        n = unit_normal(normal, f"{key}.normal", self.file)
        self.material_index(material, key=f"{key}.material")
        name = material.name if isinstance(material, Material) else material
        plane = PlaneWall(point=as_tuple(p), normal=as_tuple(n), material=name)
        self._planes.append(plane)
        self._plane_keys.append(key)
        return plane

    @property
    def mesh_walls(self) -> list[MeshWall]:
        """Triangle-mesh walls (a copy of the list)."""
        return list(self._mesh_walls)

    @property
    def mesh_wall_keys(self) -> list[str]:
        """Where each mesh wall came from, e.g. ``walls[2]`` (for messages)."""
        return list(self._mesh_wall_keys)

    def add_mesh_wall(
        self,
        mesh,
        material,
        *,
        scale=1.0,
        orientation=None,
        position=(0.0, 0.0, 0.0),
        velocity=(0.0, 0.0, 0.0),
        angular_velocity=(0.0, 0.0, 0.0),
        pivot=None,
        thickness=None,
        flip_normals: bool = False,
        key: str | None = None,
        base_dir=None,
    ) -> MeshWall:
        """Add a wall made of a triangle mesh: open or closed, convex or not (see :mod:`polydem.meshwall`).

        The wall is solid behind its triangles (against their normals, i.e. the bodies are on the
        side a counter-clockwise triangle faces), ``thickness`` [m] deep (default: the largest
        bounding diameter of the free bodies); ``flip_normals`` reverses every triangle. Keep the
        thickness below half the thinnest part of a closed wall, or the cells behind one side
        reach out of the other (:meth:`validate` warns where they do), and within a factor of
        10^6 of the triangles' sizes (validation refuses others: the cells are built to 10^-9 of
        their size). Validation also refuses free bodies that start deep in the solid (as for
        plane walls) and warns of a wall moving faster than the bodies it hits can take.

        Args:
            mesh: a mesh file (STL, OBJ, PLY; relative paths from ``base_dir``), a trimesh.Trimesh,
                or ``(vertices, triangles)`` arrays.
            material: a material name registered in the scene.
            scale: a factor or (sx, sy, sz) applied to the file's coordinates first.
            orientation: unit quaternion xyzw applied after the scale (default: none).
            position: translation applied last [m].
            velocity: (3,) [m/s]; angular_velocity: (3,) [rad/s] about ``pivot`` (default
                ``position``): a kinematic wall, e.g. a turning mixer.
            key: where the values came from, for messages (default ``mesh_walls[N]``).
        """
        from polydem.quaternions import quat_to_matrix

        key = key or f"mesh_walls[{len(self._mesh_walls)}]"
        f = self.file
        self.material_index(material, key=f"{key}.material")
        name = material.name if isinstance(material, Material) else material
        v, tri, source = mesh_input(mesh, key, f, base_dir)
        if np.ndim(scale) == 0:
            sc = np.full(3, read_number(scale, f"{key}.scale", f, hint=" (a factor, e.g. 0.001 for mm)"))
        else:
            sc = read_vector(scale, 3, f"{key}.scale", f)
        if np.any(sc == 0.0) or not np.all(np.isfinite(sc)):
            raise self.error(
                f"scale {sc.tolist()} has a zero or non-finite factor; give factors such as 0.001", f"{key}.scale"
            )
        rot = np.eye(3)
        if orientation is not None:
            q = read_vector(orientation, 4, f"{key}.orientation", f)
            norm = float(np.linalg.norm(q))
            if not abs(norm - 1.0) <= 1e-6:
                raise self.error(
                    f"orientation {q.tolist()} is not a unit quaternion xyzw (|q| = {norm:.6g})", f"{key}.orientation"
                )
            rot = quat_to_matrix(q / norm)
        pos = read_vector(position, 3, f"{key}.position", f)
        vel = read_vector(velocity, 3, f"{key}.velocity", f)
        omega = read_vector(angular_velocity, 3, f"{key}.angular_velocity", f)
        piv = pos if pivot is None else read_vector(pivot, 3, f"{key}.pivot", f)
        if thickness is not None:
            thickness = read_number(thickness, f"{key}.thickness", f, positive=True, hint=" (depth of the solid in m)")
        flip = read_boolean(flip_normals, f"{key}.flip_normals", f)
        if v.ndim == 2 and v.shape[1] == 3:
            v = (v * sc) @ rot.T + pos
        # A mirror (an odd number of negative factors) turns the triangles inside out: re-orient them.
        if (np.prod(np.sign(sc)) < 0) != flip and tri.ndim == 2:
            tri = tri[:, ::-1]
        try:
            v, tri = clean_triangles(v, tri, label=f"mesh {source}")
            check_winding(v, tri, label=f"mesh {source}")
        except MeshWallError as exc:
            raise self.error(str(exc), f"{key}.file" if source not in ("vertices", "trimesh") else key) from None
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
        )
        self._mesh_walls.append(wall)
        self._mesh_wall_keys.append(key)
        return wall

    def mesh_wall_thickness(self, wall: MeshWall) -> float:
        """The depth [m] of a mesh wall's solid: its ``thickness``, or by default the largest bounding
        diameter of the free bodies' shapes (of all shapes where no body is free), as the Model takes it."""
        if wall.thickness is not None:
            return float(wall.thickness)
        shapes = list(self.shapes.values())
        kind = np.asarray(self.body_kind)
        used = np.unique(np.asarray(self.body_shape)[kind == 0]) if (kind == 0).any() else range(len(shapes))
        return 2.0 * max(shapes[int(k)].radius for k in used)

    def mesh_wall_cells(self, wall: MeshWall, thickness: float):
        """The :class:`~polydem.meshwall.MeshCells` of ``wall`` at ``thickness`` [m], in the wall's own frame
        (world axes at t = 0, origin at its pivot: what the Model steps), kept for the next call (the checks
        run at every validation and the Model reuses them; the cells only change with the thickness)."""
        from polydem.meshwall import build_cells

        key = self.mesh_wall_keys[[id(w) for w in self._mesh_walls].index(id(wall))]
        kept = _CELLS.get(wall)
        if kept is None or kept[0] != thickness:
            try:
                pivot = np.asarray(wall.pivot, dtype=np.float64)
                label = f"mesh wall {key} ({wall.source})"
                cells = build_cells(wall.vertices - pivot, wall.triangles, thickness, label=label)
            except MeshWallError as exc:
                raise self.error(str(exc), key) from None
            kept = _CELLS[wall] = (thickness, cells, {})
        return kept[1]

    def mesh_wall_memo(self, wall: MeshWall, thickness: float) -> dict:
        """A dict kept with the cells of ``wall`` at ``thickness`` (see :meth:`mesh_wall_cells`), for the
        checks' results that depend on nothing else."""
        self.mesh_wall_cells(wall, thickness)
        return _CELLS[wall][2]

    def add_box_container(
        self, center, inner_size, material, wall_thickness=None, open_top: bool = True, *, key: str | None = None
    ) -> list[int]:
        """Add an axis-aligned box container made of fixed box-shaped bodies; returns their indices.

        The cavity is ``inner_size`` = (lx, ly, lz) [m] centred on ``center`` [m], z up. The walls,
        ``wall_thickness`` [m] thick (default 10% of the smallest inner size), are: a floor plate
        covering the whole outer footprint, two x walls spanning the outer y extent, two y walls
        between them, and a lid like the floor unless ``open_top``. Walls touch but do not overlap.
        The needed box shapes are registered as ``"wall_box_{sx}x{sy}x{sz}"``. ``key`` is where the
        value came from, for error messages (default ``box_container``).
        """
        key = key or "box_container"
        f = self.file
        c = read_vector(center, 3, f"{key}.center", f)
        size = read_vector(inner_size, 3, f"{key}.inner_size", f, label="[lx, ly, lz]")
        if size.min() <= 0.0:
            raise self.error(f"inner sizes must be positive, got {size.tolist()}", f"{key}.inner_size")
        if wall_thickness is None:
            t = 0.1 * float(size.min())
        else:
            t = read_number(wall_thickness, f"{key}.wall_thickness", f, positive=True, hint=" (in m)")
        open_top = read_boolean(open_top, f"{key}.open_top", f)
        self.material_index(material, key=f"{key}.material")
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
        return self._shape_for_spec(name, {"type": "box", "size": dims}, lambda nm: ConvexShape.box(*dims, name=nm))

    def _shape_for_spec(self, name, spec, build) -> str:
        """Name of the registered shape of this spec: ``name``, or ``name_2``, ... where ``name`` is taken by
        another spec; ``build(name)`` makes it when there is none yet."""
        base, k = name, 1
        while name in self.shape_names and self.shape_spec(name) != spec:
            k += 1
            name = f"{base}_{k}"
        if name not in self.shape_names:
            self.add_shape(name, build(name), spec=spec)
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
        key: str | None = None,
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
            key: where the value came from, for error messages (default ``drums[N]``).
        """
        key = key or f"drums[{len(self.drums)}]"
        f = self.file
        c = read_vector(center, 3, f"{key}.center", f)
        a = read_vector(axis, 3, f"{key}.axis", f)
        if np.linalg.norm(a) < 1e-12:
            raise self.error(
                f"axis {a.tolist()} is zero; give the direction of the drum axis, e.g. [0, 1, 0]", f"{key}.axis"
            )
        a = a / np.linalg.norm(a)
        r = read_number(radius, f"{key}.radius", f, positive=True, hint=" (inner radius in m)")
        length = read_number(length, f"{key}.length", f, positive=True, hint=" (inner length along the axis in m)")
        n = read_integer(sides, f"{key}.sides", f, minimum=3, maximum=1000, hint=" (number of slabs)")
        t = (
            0.1 * r
            if thickness is None
            else read_number(thickness, f"{key}.thickness", f, positive=True, hint=" (in m)")
        )
        caps = read_boolean(caps, f"{key}.caps", f)
        if (omega is None) == (rpm is None):
            raise self.error(
                "give the rotation speed as exactly one of omega (rad/s) or rpm (revolutions per minute)",
                f"{key}.omega" if omega is None else f"{key}.rpm",
            )
        if omega is not None:
            w = read_number(omega, f"{key}.omega", f, hint=" (angular speed in rad/s)")
        else:
            w = read_number(rpm, f"{key}.rpm", f, hint=" (revolutions per minute)") * 2.0 * math.pi / 60.0
        mat = self.material_index(material, key=f"{key}.material")
        name = self.material_names[mat]
        radial = _drum_radial(a, n)
        tangent = np.cross(np.broadcast_to(a, radial.shape), radial)
        slab = self._box_shape((2.0 * r * math.tan(math.pi / n), length, t))
        quats = np.array([quat_from_matrix(np.column_stack([tangent[k], a, radial[k]])) for k in range(n)])
        omega_vec = np.broadcast_to(w * a, (n, 3))
        zeros = np.zeros((n, 3))
        idx = [
            self.append_bodies(
                self.shape_index(slab),
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
            idx.append(self._drum_caps(c, a, n, r, t, length, w, mat, key))
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
        self.drums.append(drum)
        return drum

    def _drum_caps(self, c, a, n, r, t, length, w, mat, key) -> np.ndarray:
        """Add the two end plates of a drum (see :meth:`add_drum`); returns their indices."""
        rho = (r + t) / math.cos(math.pi / n) ** 2
        spec = {"type": "prism", "n": n, "radius": rho, "height": t}
        cap_name = self._shape_for_spec(
            f"drum_cap_{n}_{rho:.6g}x{t:.6g}", spec, lambda nm: ConvexShape.prism(n, rho, t, name=nm)
        )
        e1, e2 = _perpendicular_basis(a)
        q_cap = quat_from_matrix(np.column_stack([e1, e2, a]))
        ends = np.array([c + (0.5 * length + 0.5 * t) * a, c - (0.5 * length + 0.5 * t) * a])
        return self.append_bodies(
            self.shape_index(cap_name),
            mat,
            ends,
            np.tile(q_cap, (2, 1)),
            np.zeros((2, 3)),
            np.tile(w * a, (2, 1)),
            KIND_KINEMATIC,
            lambda i: key,
            np.tile(c, (2, 1)),
        )
