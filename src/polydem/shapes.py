"""Rigid convex polyhedra described by polygon faces, for the discrete element solver.

A :class:`ConvexShape` is the convex hull of a point set, stored in its *body frame*: the origin is
at the centroid and the axes are the principal axes of inertia. Faces are convex polygons (coplanar
hull triangles merged into one loop per plane) so that the contact kernels can clip polygons against
face planes.

Construction: qhull triangulates the hull; triangles are grouped by plane into
faces; vertices that are redundant within the tolerance are removed and the hull rebuilt until the
polygon mesh is consistent; then mass properties (trimesh) give the body frame.

Tolerances, relative to the size ``L`` = bounding-box diagonal of the input points:

* ``tol`` (default :data:`DEFAULT_TOL` = 1e-9), used as the distance ``tol * L``:

  - triangles whose three vertices all lie within it of a face plane (normals on the same side)
    join that face; the plane is refitted to the face's triangles (area-weighted normal);
  - a vertex within it of the straight line through its two neighbours on a face loop (collinear
    in the middle of an edge), of another vertex, or inside a merged face, is removed;
  - a triangle thinner than it (a sliver) has its vertex opposite the longest edge removed.

  The shape therefore shrinks by about ``tol * L`` at most. Double precision roundoff is ~1e-16,
  so 1e-9 merges only what is coplanar up to roundoff. For float32 sources (binary STL, most scans)
  pass ``tol=1e-6``: float32 rounding (~6e-8 relative) leaves nominally flat faces as triangles at
  ~1e-7 rad to each other, which 1e-9 keeps apart.
* ``tol`` is capped at 1e-3 times the thickness ``3 V / S`` (volume over surface area) so that
  plates and needles are not flattened. If the result fails its consistency checks (possible when
  ``tol`` is below the roundoff of thin triangles' normals, ~1e-16 L / thickness), ``tol`` is raised
  tenfold at a time up to 1e-6 (or the cap) and the build repeated.
* Where triangles near one plane do not cover a single convex polygon (a nearly flat region with
  noise of about the tolerance), that region keeps qhull's own facets.
* Points are rejected as collinear or coplanar when the smallest singular value of the centred
  cloud is below 1e-9 times the largest, and as flat when the hull volume is below 1e-12 * L^3.
* :attr:`ConvexShape.tolerance` = 4 times the distance tolerance actually used: every vertex is
  within it of its faces' planes and satisfies ``n . x <= d + tolerance`` for every face.
"""

from __future__ import annotations

import io
import math
import operator
import warnings
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

# trimesh (0.4 s) and scipy.spatial are imported where they are used, so that importing polydem
# (polydem --help, polydem info) does not pay for them.
if TYPE_CHECKING:
    import trimesh
    from scipy.spatial import ConvexHull

__all__ = ["ConvexShape", "DEFAULT_TOL", "MAX_FACES", "MAX_FACE_VERTICES"]

DEFAULT_TOL = 1e-9
"""Default relative coplanarity tolerance (times the bounding-box diagonal) for merging hull faces."""

# Below this, tolerances stop meaning anything in double precision (coordinates are O(L) and carry
# ~1e-16 relative error through centring and rotation).
_TOL_FLOOR = 1e-13
# Plane refits per face while grouping triangles (see _polygon_hull); two or three suffice in practice.
_MAX_REFITS = 5
# Tolerances are capped at this fraction of the thickness 3 V / S (see _build).
_THICKNESS_FRACTION = 1e-3
# Largest tolerance tried when the requested one fails the consistency checks (see _build).
_TOL_MAX = 1e-6
# Relative thresholds of the degeneracy checks (see the module docstring).
_AFFINE_RTOL = 1e-9
_VOLUME_RTOL = 1e-12
# Relative gap below which principal moments count as equal; the axes inside such a cluster are
# then chosen to follow the input axes instead of whatever eigh happens to return.
_MOMENT_RTOL = 1e-9
# A watertight mesh whose volume differs from its hull's by more than this is reported as not convex.
CONVEX_VOLUME_RTOL = 1e-6
# Limit for sphere(): subdivision 5 already has 20480 faces.
_MAX_SUBDIVISIONS = 5

MAX_FACES = 20480
"""Most faces of a shape (as many as ``sphere(5)``). The narrow phase is compiled for the largest
face count in use and keeps, per thread, a list of that many face planes (4 floats) and ids (1 int):
400 KiB at this limit in float32, within the 512 KiB of local memory a CUDA thread can have."""

MAX_FACE_VERTICES = 1024
"""Most vertices of one face: the narrow phase clips faces in a per-thread buffer of 2 x (face
vertices + 16) points (24 KiB at this limit, beside the plane list of MAX_FACES)."""

# A convex polyhedron with V vertices has at least V / 2 + 2 faces (every vertex has 3 edges or
# more, and V - E + F = 2), so hulls with more vertices than this exceed MAX_FACES.
_MAX_HULL_VERTICES = 2 * (MAX_FACES - 2)


class _HullBuildError(Exception):
    """The polygon hull failed a consistency check at one tolerance (retried with a smaller one)."""


def polygon_areas(vertices, faces, normals) -> np.ndarray:
    """(F,) areas [m^2] of the polygon faces (vertex index loops) of a hull with unit ``normals``."""
    v = np.asarray(vertices, dtype=np.float64)
    return np.array(
        [
            0.5 * abs(float(np.sum(np.cross(v[f], v[np.roll(f, -1)]), axis=0) @ n))
            for f, n in zip(faces, np.asarray(normals, dtype=np.float64), strict=True)
        ]
    )


def largest_face_area(shape) -> float:
    """Area of a shape's largest face [m^2]: of a convex shape's polygons; of a compound grain, the largest
    face of the convex hull of its parts (a flat side made of several parts' faces counts whole). The
    face contact whose stiffness the resolved toe bounds and the time step resolves."""
    if hasattr(shape, "part_vertices"):
        return float(np.max(ConvexShape.from_points(np.concatenate(shape.part_vertices())).face_areas))
    return float(np.max(polygon_areas(shape.vertices, shape.faces, shape.face_normals), initial=0.0))


class ConvexShape:
    """Rigid convex polyhedron in its body frame, with polygon faces.

    Array attributes are read-only numpy arrays (float64 unless stated) in the body frame: origin at
    the centroid, axes along the principal axes of inertia (right-handed), sorted so that
    ``inertia[0] <= inertia[1] <= inertia[2]``.

    Attributes:
        name: str, label used in messages and output.
        vertices: (nv, 3) hull vertices [m]; no interior or duplicate points.
        faces: list of nf int64 arrays; face ``f`` is a loop of indices into ``vertices``,
            counter-clockwise seen from outside (the right-hand rule gives the outward normal).
            There is exactly one face per plane.
        face_normals: (nf, 3) unit outward normals [-].
        face_offsets: (nf,) plane offsets ``d`` [m] with ``n . x = d`` on the face; ``d > 0``.
        face_centers: (nf, 3) mean of each face's vertices [m].
        face_radii: (nf,) largest distance from the face center to the face's vertices [m].
        volume: float, volume [m^3].
        inertia: (3,) principal moments of inertia per unit density [m^5]; multiply by the density
            [kg/m^3] to get kg m^2.
        radius: float, largest vertex distance from the centroid [m] (bounding sphere).
        input_transform: (4, 4) homogeneous transform from body frame to the input frame:
            ``x_input = R @ x_body + t``.
        input_rotation: (3, 3) view of ``R`` in ``input_transform`` [-], det +1; its columns are the
            principal axes expressed in the input frame.
        input_translation: (3,) view of ``t`` in ``input_transform`` [m]: the centroid in the input
            frame.
        tolerance: float, absolute geometric tolerance [m] (4 x the merge distance used, see the
            module docstring): every vertex lies within it of each of its faces' planes and
            satisfies ``n . x <= d + tolerance`` for every face.
    """

    def __init__(self, points, name: str | None = None, *, tol: float = DEFAULT_TOL):
        """Build the convex hull of ``points`` ((n, 3) array-like [m]); see :meth:`from_points`."""
        pts = _validate_points(points)
        tol = _validate_tol(tol)
        self._set(name="convex" if name is None else str(name), **_build(pts, tol))

    # ------------------------------------------------------------------ constructors

    @classmethod
    def from_points(cls, points, name: str | None = None, *, tol: float = DEFAULT_TOL) -> ConvexShape:
        """Convex hull of a point cloud.

        Args:
            points: (n, 3) array-like of coordinates [m] in the input frame; n >= 4, spanning a volume.
            name: label; defaults to ``"convex"``.
            tol: relative coplanarity tolerance (see the module docstring).

        Raises:
            ValueError: wrong shape, non-finite values, fewer than 4 points, points that are all
                collinear or coplanar, or a (near) zero hull volume.
        """
        return cls(points, name=name, tol=tol)

    @classmethod
    def from_mesh(cls, mesh: trimesh.Trimesh, name: str | None = None, *, tol: float = DEFAULT_TOL) -> ConvexShape:
        """Shape from a :class:`trimesh.Trimesh`; a non-convex mesh is replaced by its hull with a warning.

        Convexity is judged by comparing the volume of a watertight mesh with its hull's (relative
        difference above 1e-6). A mesh that is not watertight has no volume, so it also warns.

        Args:
            mesh: triangle mesh in the input frame [m].
            name: label; defaults to the mesh's ``metadata["name"]`` or ``"mesh"``.
            tol: relative coplanarity tolerance (see the module docstring).

        Raises:
            TypeError: ``mesh`` is not a :class:`trimesh.Trimesh`.
            ValueError: the mesh has no vertices, or its vertices fail the checks of :meth:`from_points`.
        """
        return cls._from_mesh(mesh, name, tol, stacklevel=3)

    @classmethod
    def from_file(cls, path: str | PathLike, name: str | None = None, *, tol: float = DEFAULT_TOL) -> ConvexShape:
        """Shape from a mesh file (OBJ, STL, PLY, or anything else :func:`trimesh.load` reads).

        Args:
            path: file path; coordinates are taken as metres.
            name: label; defaults to the file name without extension.
            tol: relative coplanarity tolerance; pass ~1e-6 for float32 formats such as STL so that
                nominally flat faces merge (see the module docstring).

        Raises:
            FileNotFoundError: the path does not exist.
            ValueError: the path is not a file; the file cannot be read or parsed ("cannot read mesh file
                X: not a valid OBJ file (...)"); a vertex is not finite (naming its line in an OBJ file,
                its index otherwise); or the file holds no vertices.
        """
        path = Path(path)
        if not path.exists():
            raise FileNotFoundError(f"shape file not found: '{path}' (absolute: '{path.absolute()}'); check the path")
        if not path.is_file():
            raise ValueError(f"shape path '{path}' is not a regular file; pass the path of an OBJ, STL or PLY file")
        mesh = _load_mesh(path)
        return cls._from_mesh(mesh, path.stem if name is None else name, tol, stacklevel=3)

    @classmethod
    def _from_mesh(cls, mesh, name, tol, stacklevel) -> ConvexShape:
        import trimesh

        if not isinstance(mesh, trimesh.Trimesh):
            raise TypeError(
                f"from_mesh expects a trimesh.Trimesh, got {type(mesh).__name__}; "
                "convert a Scene with scene.to_mesh() first"
            )
        if len(mesh.vertices) == 0:
            raise ValueError("mesh has no vertices; a convex shape needs at least 4 non-coplanar points")
        if name is None:
            name = mesh.metadata.get("name") or "mesh"
        has_faces = len(mesh.faces) > 0
        # Unreferenced vertices are leftovers of editing, not part of the surface the user sees.
        points = mesh.vertices[mesh.referenced_vertices] if has_faces else mesh.vertices
        shape = cls(np.asarray(points, dtype=np.float64), name=name, tol=tol)
        if has_faces and mesh.is_watertight:
            mesh_volume = abs(float(mesh.volume))
            rel = abs(shape.volume - mesh_volume) / shape.volume
            if rel > CONVEX_VOLUME_RTOL:
                warnings.warn(
                    f"mesh '{name}' is not convex: mesh volume {mesh_volume:.6g} m^3, convex hull volume "
                    f"{shape.volume:.6g} m^3 (relative difference {rel:.3%}); using the convex hull",
                    stacklevel=stacklevel,
                )
        else:
            what = "has no faces" if not has_faces else "is not watertight"
            warnings.warn(
                f"mesh '{name}' {what}, so its volume is undefined and its convexity cannot be checked; "
                f"using the convex hull of its vertices (volume {shape.volume:.6g} m^3)",
                stacklevel=stacklevel,
            )
        return shape

    @classmethod
    def box(
        cls, sx: float, sy: float | None = None, sz: float | None = None, *, name: str | None = None
    ) -> ConvexShape:
        """Rectangular box with full edge lengths ``sx, sy, sz`` [m]; a single value gives a cube."""
        if (sy is None) != (sz is None):
            raise ValueError(f"box: give one edge length for a cube or all three (sx, sy, sz); got sy={sy}, sz={sz}")
        if sy is None:
            sy = sz = sx
        half = 0.5 * np.array([_positive("box", "sx", sx), _positive("box", "sy", sy), _positive("box", "sz", sz)])
        corners = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=np.float64)
        return cls(corners * half, name="box" if name is None else name)

    @classmethod
    def tetrahedron(cls, edge: float = 1.0, *, name: str | None = None) -> ConvexShape:
        """Regular tetrahedron with edge length ``edge`` [m]."""
        a = _positive("tetrahedron", "edge", edge)
        pts = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], dtype=np.float64)
        return cls(pts * (a / (2.0 * math.sqrt(2.0))), name="tetrahedron" if name is None else name)

    @classmethod
    def octahedron(cls, edge: float = 1.0, *, name: str | None = None) -> ConvexShape:
        """Regular octahedron with edge length ``edge`` [m]."""
        a = _positive("octahedron", "edge", edge)
        pts = np.vstack([np.eye(3), -np.eye(3)])
        return cls(pts * (a / math.sqrt(2.0)), name="octahedron" if name is None else name)

    @classmethod
    def dodecahedron(cls, edge: float = 1.0, *, name: str | None = None) -> ConvexShape:
        """Regular dodecahedron with edge length ``edge`` [m]."""
        a = _positive("dodecahedron", "edge", edge)
        phi = 0.5 * (1.0 + math.sqrt(5.0))
        pts = [[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)]
        for s in (-1, 1):
            for t in (-1, 1):
                pts += [[0, s / phi, t * phi], [s / phi, t * phi, 0], [s * phi, 0, t / phi]]
        # The edge of this standard embedding is 2 / phi.
        return cls(np.array(pts) * (a * phi / 2.0), name="dodecahedron" if name is None else name)

    @classmethod
    def icosahedron(cls, edge: float = 1.0, *, name: str | None = None) -> ConvexShape:
        """Regular icosahedron with edge length ``edge`` [m]."""
        a = _positive("icosahedron", "edge", edge)
        phi = 0.5 * (1.0 + math.sqrt(5.0))
        pts = []
        for s in (-1, 1):
            for t in (-1, 1):
                pts += [[0, s, t * phi], [s, t * phi, 0], [t * phi, 0, s]]
        # The edge of this standard embedding is 2.
        return cls(np.array(pts, dtype=np.float64) * (a / 2.0), name="icosahedron" if name is None else name)

    @classmethod
    def prism(cls, n: int, radius: float = 0.5, height: float = 1.0, *, name: str | None = None) -> ConvexShape:
        """Right prism on a regular ``n``-gon (n >= 3).

        Args:
            n: number of sides, 3 to MAX_FACE_VERTICES (1024): the two n-gon faces must fit the narrow
                phase's face buffer.
            radius: radius of the n-gon's circumscribed circle [m].
            height: prism height along the input z axis [m].
        """
        n = _count("prism", "n", n, 3, MAX_FACE_VERTICES, "the most vertices of a face the contact kernels take")
        r = _positive("prism", "radius", radius)
        h = _positive("prism", "height", height)
        ang = 2.0 * np.pi * np.arange(n) / n
        ring = np.column_stack([r * np.cos(ang), r * np.sin(ang)])
        pts = np.vstack([np.column_stack([ring, np.full(n, -0.5 * h)]), np.column_stack([ring, np.full(n, 0.5 * h)])])
        return cls(pts, name=f"prism{n}" if name is None else name)

    @classmethod
    def rock(
        cls,
        n_points: int = 20,
        size: float = 1.0,
        seed=0,
        elongation=(1.0, 1.0, 1.0),
        *,
        roughness: float = 0.3,
        name: str | None = None,
    ) -> ConvexShape:
        """Irregular rock: hull of seeded random points in an ellipsoid; deterministic for a given seed.

        Directions are uniform on the sphere and radii are drawn from ``[1 - roughness, 1]`` of the
        ellipsoid; points that end up inside the hull are pushed out to the ellipsoid surface (where
        they are always hull vertices) until every point is a vertex, so the shape has
        ``n_points`` vertices (unless two land within the merge tolerance of each other).

        Args:
            n_points: number of points (= hull vertices), 4 to 10242 (a hull of n points has 2 n - 4
                triangles, at most MAX_FACES = 20480).
            size: largest diameter of the ellipsoid [m].
            seed: seed for :func:`numpy.random.default_rng`.
            elongation: relative ellipsoid diameters along x, y, z [-]; scaled so the largest is ``size``.
            roughness: radial jitter in [0, 1) [-]; 0 puts every point on the ellipsoid.
        """
        n = _count("rock", "n_points", n_points, 4, MAX_FACES // 2 + 2, f"a hull of at most {MAX_FACES} faces")
        size = _positive("rock", "size", size)
        try:
            e = np.asarray(elongation, dtype=np.float64).reshape(3)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"rock: elongation must be three positive numbers (x, y, z); got {elongation!r}") from exc
        if not np.all(np.isfinite(e) & (e > 0)):
            raise ValueError(f"rock: elongation must be three positive, finite numbers; got {elongation!r}")
        roughness = float(roughness)
        if not 0.0 <= roughness < 1.0:
            raise ValueError(f"rock: roughness must be in [0, 1); got {roughness}")
        from scipy.spatial import ConvexHull, QhullError

        rng = np.random.default_rng(seed)
        dirs = rng.normal(size=(n, 3))
        dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-300)
        radial = 1.0 - roughness * rng.random(n)
        semi_axes = 0.5 * size * e / e.max()
        for _ in range(n):
            pts = dirs * radial[:, None] * semi_axes
            try:
                inside = np.setdiff1d(np.arange(n), ConvexHull(pts).vertices)
            except QhullError:
                break  # degenerate draw; the constructor reports it properly
            if inside.size == 0:
                break
            radial[inside] = 1.0
        return cls(pts, name="rock" if name is None else name)

    @classmethod
    def sphere(cls, subdivisions: int = 1, radius: float = 0.5, *, name: str | None = None) -> ConvexShape:
        """Hull of an icosphere: 20 * 4**subdivisions triangles (1 -> 80, 2 -> 320, 3 -> 1280).

        Args:
            subdivisions: icosahedron subdivision level, 0 to 5.
            radius: circumscribed radius [m].
        """
        s = _count("sphere", "subdivisions", subdivisions, 0)
        if s > _MAX_SUBDIVISIONS:
            raise ValueError(f"sphere: subdivisions must be <= {_MAX_SUBDIVISIONS} (20480 faces); got {s}")
        r = _positive("sphere", "radius", radius)
        import trimesh

        pts = trimesh.creation.icosphere(subdivisions=s, radius=r).vertices
        return cls(np.asarray(pts, dtype=np.float64), name=f"sphere{s}" if name is None else name)

    # ------------------------------------------------------------------ derived data

    @property
    def num_vertices(self) -> int:
        """Number of vertices."""
        return len(self.vertices)

    @property
    def num_faces(self) -> int:
        """Number of polygon faces."""
        return len(self.faces)

    @property
    def max_face_vertices(self) -> int:
        """Length of the longest face loop."""
        return max(len(f) for f in self.faces)

    @property
    def face_areas(self) -> np.ndarray:
        """(F,) area of each face [m^2]."""
        return polygon_areas(self.vertices, self.faces, self.face_normals)

    @property
    def input_rotation(self) -> np.ndarray:
        """(3, 3) rotation part of :attr:`input_transform` (a read-only view)."""
        return self.input_transform[:3, :3]

    @property
    def input_translation(self) -> np.ndarray:
        """(3,) translation part of :attr:`input_transform` [m] (a read-only view)."""
        return self.input_transform[:3, 3]

    def to_input_frame(self, points) -> np.ndarray:
        """Map (..., 3) body-frame points [m] to the input frame: ``R @ x + t``."""
        return np.asarray(points, dtype=np.float64) @ self.input_rotation.T + self.input_translation

    def to_trimesh(self) -> trimesh.Trimesh:
        """Triangulated copy in the body frame (each face fanned from its first vertex)."""
        import trimesh

        return trimesh.Trimesh(vertices=self.vertices.copy(), faces=_fan(self.faces), process=False)

    def scaled(self, factor: float) -> ConvexShape:
        """New shape scaled by ``factor`` (> 0) about the input-frame origin.

        This equals building the shape from the input points times ``factor``: lengths scale by
        ``factor``, volume by ``factor**3``, inertia by ``factor**5``, and the input translation by
        ``factor`` (useful for unit conversion, e.g. ``scaled(1e-3)`` for a file in millimetres).
        """
        f = _positive("scaled", "factor", factor, "a dimensionless scale factor")
        transform = self.input_transform.copy()
        transform[:3, 3] *= f
        new = object.__new__(type(self))
        new._set(
            name=self.name,
            vertices=self.vertices * f,
            faces=self.faces,
            face_normals=self.face_normals,
            face_offsets=self.face_offsets * f,
            face_centers=self.face_centers * f,
            face_radii=self.face_radii * f,
            volume=self.volume * f**3,
            inertia=self.inertia * f**5,
            radius=self.radius * f,
            input_transform=transform,
            tolerance=self.tolerance * f,
        )
        return new

    def placed(self, rotation, translation) -> ConvexShape:
        """The same shape with its input frame moved: the new input coordinates are
        ``rotation @ x_in + translation`` of this shape's (``rotation`` (3, 3) orthonormal, det +1;
        ``translation`` (3,) [m]). The body frame, mass properties and faces are unchanged; used to
        place a part in a :class:`~polydem.CompoundShape`."""
        rot = np.asarray(rotation, dtype=np.float64)
        t = np.asarray(translation, dtype=np.float64)
        if rot.shape != (3, 3) or not np.allclose(rot @ rot.T, np.eye(3), atol=1e-9) or np.linalg.det(rot) <= 0:
            raise ValueError("rotation must be a (3, 3) rotation matrix (orthonormal, determinant +1)")
        if t.shape != (3,) or not np.isfinite(t).all():
            raise ValueError(f"translation must be [x, y, z] in m, got {translation!r}")
        move = np.eye(4)
        move[:3, :3] = rot
        move[:3, 3] = t
        new = object.__new__(type(self))
        new._set(
            name=self.name,
            vertices=self.vertices,
            faces=self.faces,
            face_normals=self.face_normals,
            face_offsets=self.face_offsets,
            face_centers=self.face_centers,
            face_radii=self.face_radii,
            volume=self.volume,
            inertia=self.inertia,
            radius=self.radius,
            input_transform=move @ self.input_transform,
            tolerance=self.tolerance,
        )
        return new

    def __repr__(self) -> str:
        return (
            f"ConvexShape(name={self.name!r}, vertices={self.num_vertices}, faces={self.num_faces}, "
            f"volume={self.volume:.4g} m^3, radius={self.radius:.4g} m)"
        )

    def _set(
        self,
        *,
        name,
        vertices,
        faces,
        face_normals,
        face_offsets,
        face_centers,
        face_radii,
        volume,
        inertia,
        radius,
        input_transform,
        tolerance,
    ):
        # Arrays are frozen because the derived data (planes, inertia, transform) must stay consistent
        # with the vertices; build a new shape (e.g. scaled()) instead of editing one.
        self.name = name
        self.vertices = _frozen(vertices, np.float64)
        self.faces = [_frozen(f, np.int64) for f in faces]
        self.face_normals = _frozen(face_normals, np.float64)
        self.face_offsets = _frozen(face_offsets, np.float64)
        self.face_centers = _frozen(face_centers, np.float64)
        self.face_radii = _frozen(face_radii, np.float64)
        self.volume = float(volume)
        self.inertia = _frozen(inertia, np.float64)
        self.radius = float(radius)
        self.input_transform = _frozen(input_transform, np.float64)
        self.tolerance = float(tolerance)


# ---------------------------------------------------------------------- argument checks


def _frozen(a, dtype) -> np.ndarray:
    out = np.array(a, dtype=dtype, copy=True)
    out.setflags(write=False)
    return out


def _positive(func: str, arg: str, value, what: str = "a length in metres") -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{func}: {arg} must be a positive number ({what}), got {value!r}") from None
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{func}: {arg} must be positive and finite ({what}), got {value!r}")
    return v


def _count(func: str, arg: str, value, minimum: int, maximum: int | None = None, why: str = "") -> int:
    try:
        if isinstance(value, bool):
            raise TypeError
        v = operator.index(value)
    except TypeError:
        raise ValueError(f"{func}: {arg} must be an integer >= {minimum}, got {value!r}") from None
    if v < minimum:
        raise ValueError(f"{func}: {arg} must be an integer >= {minimum}, got {v}")
    if maximum is not None and v > maximum:
        raise ValueError(f"{func}: {arg} must be at most {maximum} ({why}), got {v}; use a smaller {arg}")
    return v


def _validate_tol(tol) -> float:
    try:
        t = float(tol)
    except (TypeError, ValueError):
        t = math.nan
    if not (math.isfinite(t) and 0.0 <= t <= 1e-3):
        raise ValueError(f"tol must be a relative tolerance in [0, 1e-3] (default {DEFAULT_TOL}), got {tol!r}")
    return t


def _validate_points(points) -> np.ndarray:
    try:
        pts = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"points must be a numeric array of shape (n, 3), one x, y, z row per point: {exc}") from exc
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(
            f"points must be an array of shape (n, 3), one x, y, z row per point; got shape {pts.shape}. "
            "Reshape with points.reshape(-1, 3) if the coordinates are flattened."
        )
    bad_rows = np.flatnonzero(~np.isfinite(pts).all(axis=1))
    if bad_rows.size:
        shown = ", ".join(str(i) for i in bad_rows[:10]) + (", ..." if bad_rows.size > 10 else "")
        raise ValueError(
            f"points contain non-finite coordinates (NaN or inf) in {bad_rows.size} row(s) [{shown}]; "
            "remove or fix those rows"
        )
    if len(pts) < 4:
        raise ValueError(
            f"at least 4 points are needed for a 3D convex hull, got {len(pts)}; add points so that they span a volume"
        )
    s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    if s[0] == 0.0:
        raise ValueError(f"all {len(pts)} points are identical; a convex polyhedron needs points that span a volume")
    if s[1] < _AFFINE_RTOL * s[0]:
        raise ValueError(
            f"all {len(pts)} points are (nearly) collinear (singular values {s[0]:.3g}, {s[1]:.3g}, {s[2]:.3g}); "
            "add points off their line and off their plane so that they span a volume"
        )
    if s[2] < _AFFINE_RTOL * s[0]:
        raise ValueError(
            f"all {len(pts)} points are (nearly) coplanar: fewer than 4 affinely independent points "
            f"(singular values {s[0]:.3g}, {s[1]:.3g}, {s[2]:.3g}, smallest below {_AFFINE_RTOL:g} x largest); "
            "add at least one point off their plane"
        )
    return pts


# ---------------------------------------------------------------------- mesh files

_MESH_HINT = "re-export it as OBJ, STL or PLY (e.g. from the modelling program or with trimesh)"


def load_mesh(path):
    """A :class:`trimesh.Trimesh` (vertices merged) from a mesh file, or ValueError saying what is
    wrong with the file (the reader of mesh shapes and of mesh walls)."""
    return _load_mesh(Path(path))


def _load_mesh(path: Path):
    """A :class:`trimesh.Trimesh` from a mesh file, or ValueError saying what is wrong with the file."""
    import trimesh

    suffix = path.suffix.lower().lstrip(".")
    fmt = suffix.upper() or "mesh"
    if suffix not in trimesh.available_formats():
        raise ValueError(
            f"cannot read mesh file '{path}': unknown mesh format {path.suffix!r}; use an .obj, .stl or .ply file"
        )
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"cannot read mesh file '{path}': {exc.strerror or exc}") from exc
    if suffix == "obj":
        data = _check_obj(data, path)
    elif suffix == "stl":
        _check_stl(data, path)
    try:
        # process=False keeps every vertex as read (trimesh would drop non-finite ones silently).
        mesh = trimesh.load(io.BytesIO(data), file_type=suffix, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for bad files; all mean "unreadable"
        detail = f"{type(exc).__name__}: {exc}"
        if isinstance(exc, ImportError):  # trimesh wants charset_normalizer to guess a text encoding
            detail = "the file is not UTF-8 text"
        raise ValueError(f"cannot read mesh file '{path}': not a valid {fmt} file ({detail}); {_MESH_HINT}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.vertices) == 0:
        raise ValueError(
            f"mesh file '{path}' holds no vertices (empty, truncated, corrupt, or not a mesh); "
            "export the shape as OBJ, STL or PLY with at least 4 non-coplanar vertices"
        )
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    bad = np.flatnonzero(~np.isfinite(verts).all(axis=1))
    if bad.size:
        raise ValueError(
            f"mesh file '{path}': vertex {bad[0]} (counting from 0) has non-finite coordinates {verts[bad[0]].tolist()}"
            f"{f' ({bad.size} such vertices)' if bad.size > 1 else ''}; fix those vertices or remove them and the "
            "faces that use them"
        )
    # Merge duplicate vertices as trimesh.load does by default (an STL repeats them per triangle), so
    # that watertightness and the volume can be checked.
    merged = trimesh.Trimesh(vertices=verts, faces=np.asarray(mesh.faces), process=True)
    distinct = len(np.unique(verts, axis=0))
    extent = float(np.ptp(verts, axis=0).max())
    if len(merged.vertices) < 4 <= distinct and extent < 100.0 * trimesh.tol.merge:
        # The merge tolerance is absolute: a mesh not much larger than it collapses to a point or two, which
        # the hull would then report as "got 1 point" (a flat mesh of any size is the hull's to report).
        raise ValueError(
            f"mesh file '{path}': its {distinct} vertices span only {extent:.3g} m, too little against the distance "
            f"within which vertices are merged ({trimesh.tol.merge:g} m), so they merge into "
            f"{len(merged.vertices)}; export the mesh in larger units (e.g. micrometres) and scale it down with the "
            "shape's scale"
        )
    return merged


def _check_obj(data: bytes, path: Path) -> bytes:
    """OBJ text as UTF-8, after checking that every vertex line holds three finite numbers."""
    nul = data.find(b"\0")
    if nul >= 0:
        raise ValueError(
            f"cannot read mesh file '{path}': not a valid OBJ file (binary data at byte {nul}, where an OBJ file is "
            f"text); {_MESH_HINT}"
        )
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        text = data.decode("latin-1")  # only comments and names can hold non-ASCII text
    count = 0
    for number, line in enumerate(text.splitlines(), 1):
        fields = line.split()
        if not fields or fields[0] != "v":
            continue
        count += 1
        try:
            xyz = [float(x) for x in fields[1:4]]
        except ValueError:
            xyz = []
        if len(xyz) < 3:
            raise ValueError(
                f"mesh file '{path}', line {number}: vertex {count} {line.strip()!r} does not hold three numbers "
                "x y z; fix the line"
            )
        if not all(math.isfinite(x) for x in xyz):
            raise ValueError(
                f"mesh file '{path}', line {number}: vertex {count} {line.strip()!r} has a non-finite coordinate; "
                "give finite x y z numbers, or remove the vertex and the faces that use it"
            )
    return text.encode("utf-8")


def _check_stl(data: bytes, path: Path) -> None:
    """Binary STL of the right length, or text starting with 'solid' (ASCII STL)."""
    if len(data) >= 84:
        n = int.from_bytes(data[80:84], "little")
        if len(data) == 84 + 50 * n:
            return
        binary = f"as binary STL it declares {n} triangles ({84 + 50 * n} bytes) but has {len(data)} bytes"
    else:
        binary = f"it has {len(data)} bytes, fewer than the 84 of a binary STL header"
    if data.lstrip()[:5].lower() == b"solid" and b"\0" not in data:
        try:
            data.decode("utf-8")
            return
        except UnicodeDecodeError:
            pass
    raise ValueError(
        f"cannot read mesh file '{path}': not a valid STL file ({binary}, and it is not ASCII STL text starting "
        f"with 'solid'; truncated or not an STL file); {_MESH_HINT}"
    )


# ---------------------------------------------------------------------- hull construction


def _build(points: np.ndarray, tol: float) -> dict:
    """Polygon hull, mass properties and body frame of validated points (see the module docstring)."""
    from scipy.spatial import ConvexHull, QhullError

    origin = 0.5 * (points.min(axis=0) + points.max(axis=0))
    # Centring first keeps qhull and the mass integrals accurate for shapes placed far from the origin.
    centred = points - origin
    size = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    try:
        first_hull = ConvexHull(centred)
    except QhullError as exc:
        raise ValueError(f"the convex hull of the points could not be computed (degenerate input?): {exc}") from exc
    if len(first_hull.vertices) > _MAX_HULL_VERTICES:
        raise ValueError(
            f"the convex hull of the points has {len(first_hull.vertices)} vertices, so at least "
            f"{len(first_hull.vertices) // 2 + 2} faces: more than the {MAX_FACES} faces the contact kernels take; "
            "simplify the shape (fewer points, or decimate the mesh, e.g. with trimesh's simplify_quadric_decimation)"
        )
    if first_hull.volume < _VOLUME_RTOL * size**3:
        raise ValueError(
            f"hull volume {first_hull.volume:.3g} m^3 is below {_VOLUME_RTOL:g} * bbox_diagonal^3 = "
            f"{_VOLUME_RTOL * size**3:.3g} m^3: the points are (nearly) flat; check their spread and units"
        )
    # A tolerance must stay well below the shape's thickness, or merging flattens a thin plate or
    # needle altogether; 3 V / S (the inradius for shapes whose faces all touch one inscribed sphere)
    # measures it.
    cap = max(_TOL_FLOOR, _THICKNESS_FRACTION * 3.0 * first_hull.volume / first_hull.area / size)
    # A tolerance can also be too small for the input: a triangle only a little thicker than tol * L
    # has a normal whose roundoff error (~1e-16 L / thickness) exceeds tol itself. Larger tolerances
    # remove such triangles (as slivers), so on failure retry with tol raised tenfold at a time.
    ladder = [min(max(tol, _TOL_FLOOR), cap)]
    while ladder[-1] < min(_TOL_MAX, cap):
        ladder.append(min(10.0 * ladder[-1], cap))
    errors = []
    for rel in ladder:
        try:
            verts, loops = _polygon_hull(centred, rel * size, first_hull)
            out = _body_frame(verts, loops, origin, 4.0 * rel * size)
            break
        except _HullBuildError as exc:
            errors.append(f"tol={rel:g}: {exc}")
    else:
        raise RuntimeError("could not build a consistent polygon hull; " + "; ".join(errors))
    longest = max(len(lp) for lp in out["faces"])
    if len(out["faces"]) > MAX_FACES or longest > MAX_FACE_VERTICES:
        raise ValueError(
            f"the shape has {len(out['faces'])} faces, the longest with {longest} vertices: the contact kernels take "
            f"at most {MAX_FACES} faces of at most {MAX_FACE_VERTICES} vertices; simplify the shape (fewer points, "
            "or decimate the mesh, e.g. with trimesh's simplify_quadric_decimation)"
        )
    return out


def _polygon_hull(points: np.ndarray, dist_tol: float, first_hull: ConvexHull) -> tuple[np.ndarray, list[np.ndarray]]:
    """Hull vertices and CCW face loops, merging hull triangles that share a plane within ``dist_tol``.

    Vertices found to be redundant (inside a merged face, or within ``dist_tol`` of the line through
    their loop neighbours) are removed and the hull rebuilt, so that every face and its neighbours
    agree on the vertex set. ``first_hull`` is the qhull hull of all ``points``.
    """
    from scipy.spatial import ConvexHull, QhullError

    active = np.arange(len(points))
    hull = first_hull
    for _ in range(len(points)):
        if hull is None:
            if len(active) < 4:
                raise _HullBuildError("fewer than 4 vertices left after removing redundant ones")
            try:
                hull = ConvexHull(points[active])
            except QhullError as exc:
                raise _HullBuildError(f"qhull failed: {exc}") from exc
        pts = hull.points
        tri = hull.simplices.copy()
        qn = hull.equations[:, :3]
        qd = -hull.equations[:, 3]
        cross = np.cross(pts[tri[:, 1]] - pts[tri[:, 0]], pts[tri[:, 2]] - pts[tri[:, 0]])
        # qhull's simplices have arbitrary winding, but its facet normals point outward.
        flip = np.einsum("ij,ij->i", cross, qn) < 0.0
        tri[flip] = tri[flip][:, [0, 2, 1]]
        cross[flip] *= -1.0
        twice_area = np.linalg.norm(cross, axis=1)
        edge_len = np.linalg.norm(pts[tri[:, [1, 2, 0]]] - pts[tri], axis=2)
        longest = edge_len.argmax(axis=1)
        # A triangle thinner than dist_tol (a sliver) has its vertex opposite the longest edge within
        # dist_tol of that edge (the other two angles are acute), so that vertex is redundant: nearly
        # on an edge or nearly a duplicate. Slivers have no reliable normal and would leave gaps
        # between faces, so such vertices are removed and the hull rebuilt until there are none.
        slivers = np.flatnonzero(twice_area <= dist_tol * edge_len[np.arange(len(tri)), longest])
        if slivers.size:
            drop, keep = set(), set()
            for t in slivers[np.argsort(twice_area[slivers], kind="stable")]:
                mid = tri[t, (longest[t] + 2) % 3]
                ends = {tri[t, longest[t]], tri[t, (longest[t] + 1) % 3]}
                # Only drop a vertex if the edge it is measured against stays, so errors do not add up.
                if mid in keep or ends & drop:
                    continue
                drop.add(mid)
                keep |= ends
            active = active[np.setdiff1d(hull.vertices, np.fromiter(drop, dtype=np.int64))]
            hull = None
            continue

        # Vertex -> incident triangles (CSR), to find a plane's candidate triangles from its vertices.
        corner_order = np.argsort(tri.ravel(), kind="stable")
        tris_of = corner_order // 3
        first = np.searchsorted(tri.ravel()[corner_order], np.arange(len(pts) + 1))
        hull_vids = hull.vertices
        hull_pts = pts[hull_vids]
        near = np.zeros(len(pts), dtype=bool)
        group = np.full(len(tri), -1)
        n_groups = 0
        # Largest triangles first, so each face plane is seeded by its most reliable triangle; a seed
        # claims every free triangle whose three vertices lie within dist_tol of its plane. A seed's
        # plane can be tilted by noise in its own vertices, enough to miss far parts of a large face,
        # so the plane is refitted to the claimed triangles and the claim repeated until it settles.
        for t in np.argsort(-twice_area, kind="stable"):
            if group[t] >= 0:
                continue
            normal, offset = qn[t], qd[t]
            members = np.array([t])
            for _ in range(_MAX_REFITS):
                near_vids = hull_vids[np.abs(hull_pts @ normal - offset) <= dist_tol]
                near[near_vids] = True
                cand = np.unique(np.concatenate([tris_of[first[v] : first[v + 1]] for v in near_vids] + [[t]]))
                ok = (group[cand] < 0) & near[tri[cand]].all(axis=1) & (qn[cand] @ normal > 0.0)
                near[near_vids] = False
                claimed = np.union1d(cand[ok], [t])
                if np.array_equal(claimed, members):
                    break
                members = claimed
                area_sum = cross[members].sum(axis=0)
                normal = area_sum / np.linalg.norm(area_sum)
                heights = pts[np.unique(tri[members])] @ normal
                offset = 0.5 * (heights.max() + heights.min())
            group[members] = n_groups
            n_groups += 1

        loops = []
        drop, keep = set(), set()
        order = np.argsort(group, kind="stable")
        bounds = np.searchsorted(group[order], np.arange(n_groups + 1))
        pending = [order[bounds[g] : bounds[g + 1]] for g in range(n_groups)]
        facet_of = None
        for members in pending:  # grows while iterating when a group is split
            if len(members) == 1:
                # A lone triangle is already a valid loop: it is no sliver, so each vertex is farther
                # than dist_tol from the opposite side, and tri is oriented outward.
                loop, extra = tri[members[0]], []
            else:
                found = _face_loop(pts, tri[members], cross[members], dist_tol)
                if found is None:
                    # The triangles near one plane do not cover a single convex polygon: a nearly
                    # flat region with noise of about dist_tol, where the plane test alone cannot
                    # tell faces apart. Fall back to qhull's own facets for these triangles.
                    if facet_of is None:
                        facet_of = np.unique(hull.equations, axis=0, return_inverse=True)[1].ravel()
                    ids = facet_of[members]
                    if np.all(ids == ids[0]):
                        raise _HullBuildError("a qhull facet does not form one convex polygon")
                    pending.extend(members[ids == k] for k in np.unique(ids))
                    continue
                loop, extra = found
            loops.append(loop)
            # Two faces can each find the other's vertex redundant (two near-duplicates, one on each
            # face); dropping both would cut a real corner. So a face's drops are taken only if they
            # spare the loops that justified earlier drops and its own loop is spared by those drops;
            # the rest wait for the rebuilt hull. The first face with drops always gets them.
            if extra and not (keep.intersection(extra) or drop.intersection(loop.tolist())):
                drop.update(extra)
                keep.update(loop.tolist())
        if not drop:
            used = np.unique(np.concatenate(loops))
            remap = np.full(len(pts), -1)
            remap[used] = np.arange(len(used))
            return pts[used], [remap[lp] for lp in loops]
        active = active[np.setdiff1d(hull.vertices, np.fromiter(drop, dtype=np.int64))]
        hull = None
    raise _HullBuildError("redundant-vertex removal did not converge")


def _face_loop(pts, tris, crosses, dist_tol):
    """CCW loop of a group of coplanar triangles and the group's vertices left off it.

    Returns None when the triangles do not cover the convex polygon of their vertices (their area
    falls short of the polygon's by more than a strip of width 4 * dist_tol along its boundary). More
    area than the polygon is accepted: qhull's triangulation of a facet with a vertex in its interior
    can overlap itself, and that vertex is dropped anyway.
    """
    vids = np.unique(tris)
    normal = crosses.sum(axis=0)
    normal /= np.linalg.norm(normal)
    u, w = _plane_basis(normal)
    q = pts[vids] @ np.column_stack([u, w])
    keep = _convex_polygon_2d(q, dist_tol)
    if len(keep) < 3:
        return None
    poly = q[keep] - q[keep].mean(axis=0)
    nxt = np.roll(poly, -1, axis=0)
    poly_area = 0.5 * np.sum(poly[:, 0] * nxt[:, 1] - poly[:, 1] * nxt[:, 0])
    perimeter = np.linalg.norm(nxt - poly, axis=1).sum()
    covered = 0.5 * np.sum(crosses @ normal)
    if poly_area - covered > 4.0 * dist_tol * perimeter:
        return None
    loop = vids[keep]
    return loop, (np.setdiff1d(vids, loop).tolist() if len(loop) < len(vids) else [])


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors u, w with (u, w, normal) right-handed, so CCW in (u, w) is CCW about the normal."""
    nx, ny, nz = normal
    # Cross with the coordinate axis least aligned with the normal, written out (np.cross is slow on
    # single vectors and this runs once per face).
    k = int(np.argmin(np.abs(normal)))
    u = np.array([(0.0, -nz, ny), (nz, 0.0, -nx), (-ny, nx, 0.0)][k])
    u /= math.sqrt(u @ u)
    w = np.array([ny * u[2] - nz * u[1], nz * u[0] - nx * u[2], nx * u[1] - ny * u[0]])
    return u, w


def _convex_polygon_2d(q: np.ndarray, eps: float) -> np.ndarray:
    """Indices of the CCW convex polygon of 2D points ``q``, without points within ``eps`` of an edge.

    First the exact hull (monotone chain) drops interior and exactly collinear points; then, one at
    a time and smallest first, vertices within ``eps`` of the chord between their two neighbours (or
    of their successor) are removed. Removing the flattest vertex first drops the middle one of a
    nearly collinear triple, never a corner, whatever the orientation of the polygon.
    """
    order = np.lexsort((q[:, 1], q[:, 0]))

    def chain(indices):
        out = []
        for i in indices:
            bx, by = q[i]
            while len(out) >= 2:
                ox, oy = q[out[-2]]
                ax, ay = q[out[-1]]
                if (ax - ox) * (by - oy) - (ay - oy) * (bx - ox) > 0.0:
                    break
                out.pop()
            out.append(i)
        return out

    loop = np.array(chain(order)[:-1] + chain(order[::-1])[:-1], dtype=np.int64)
    while len(loop) >= 3:
        p = q[loop]
        prev = np.roll(p, 1, axis=0)
        nxt = np.roll(p, -1, axis=0)
        chord = nxt - prev
        turn = (p[:, 0] - prev[:, 0]) * chord[:, 1] - (p[:, 1] - prev[:, 1]) * chord[:, 0]
        dev = turn / np.maximum(np.hypot(chord[:, 0], chord[:, 1]), np.finfo(float).tiny)
        dev[np.hypot(*(nxt - p).T) <= eps] = -np.inf
        i = int(np.argmin(dev))
        if dev[i] > eps:
            break
        loop = np.delete(loop, i)
    return loop


def _fan(loops) -> np.ndarray:
    tris = [np.column_stack([np.full(len(lp) - 2, lp[0]), lp[1:-1], lp[2:]]) for lp in loops]
    return np.concatenate(tris).astype(np.int64)


def principal_frame(tensor: np.ndarray) -> np.ndarray:
    """Rotation (det +1) whose columns are principal axes, sorted by ascending moment.

    Within a cluster of equal moments (cube, regular polyhedra, prisms) any orthonormal basis is
    principal; the one closest to the input axes is chosen so symmetric shapes keep their orientation.
    """
    moments, vecs = np.linalg.eigh(0.5 * (tensor + tensor.T))
    scale = max(abs(moments).max(), np.finfo(float).tiny)
    axes = vecs.copy()
    start = 0
    for i in range(1, 4):
        if i == 3 or moments[i] - moments[i - 1] > _MOMENT_RTOL * scale:
            if i - start > 1:
                axes[:, start:i] = _closest_basis(vecs[:, start:i])
            start = i
    for j in range(3):
        # Sign convention: the largest component of each axis is positive (deterministic output).
        if axes[np.argmax(np.abs(axes[:, j])), j] < 0.0:
            axes[:, j] *= -1.0
    if np.linalg.det(axes) < 0.0:
        axes[:, 2] *= -1.0
    return axes


def _closest_basis(span: np.ndarray) -> np.ndarray:
    """Orthonormal basis of the column space of ``span`` built from the best-projected input axes."""
    k = span.shape[1]
    proj = span @ span.T
    picks = np.sort(np.argsort(-np.diag(proj), kind="stable")[:k])
    basis = []
    for i in picks:
        v = proj[:, i].copy()
        for b in basis:
            v -= (b @ v) * b
        norm = np.linalg.norm(v)
        if norm < 1e-6:
            return span
        basis.append(v / norm)
    return np.column_stack(basis)


def _body_frame(verts: np.ndarray, loops: list[np.ndarray], origin: np.ndarray, check_tol: float) -> dict:
    """Mass properties, body-frame geometry and consistency checks of a polygon hull."""
    nv = len(verts)
    edges = np.concatenate([np.column_stack([lp, np.roll(lp, -1)]) for lp in loops])
    keys = edges[:, 0] * nv + edges[:, 1]
    # A closed, consistently oriented polygon mesh has every directed edge once and its reverse once.
    if len(np.unique(keys)) != len(keys) or not np.isin(edges[:, 1] * nv + edges[:, 0], keys).all():
        raise _HullBuildError("face loops do not form a closed, consistently oriented surface")
    if nv - len(edges) // 2 + len(loops) != 2:
        raise _HullBuildError("face loops do not satisfy Euler's formula V - E + F = 2")

    import trimesh

    props = trimesh.triangles.mass_properties(verts[_fan(loops)], density=1.0)
    if not props.volume > 0.0:
        raise _HullBuildError(f"non-positive volume {props.volume}")
    rot = principal_frame(np.asarray(props.inertia))
    centre = np.asarray(props.center_mass)
    body = (verts - centre) @ rot
    inertia = np.diag(rot.T @ props.inertia @ rot)

    # Per-face sums as segmented reductions over the concatenated loops (faces can number thousands).
    lengths = np.array([len(lp) for lp in loops])
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    face_of = np.repeat(np.arange(len(loops)), lengths)
    p = body[np.concatenate(loops)]
    centers = np.add.reduceat(p, starts) / lengths[:, None]
    # Coordinates relative to the face center keep the cross products small, which matters for the
    # normals of thin faces (their relative error grows like roundoff * length^2 / area).
    rel = p - centers[face_of]
    rel_next = body[np.concatenate([np.roll(lp, -1) for lp in loops])] - centers[face_of]
    # Newell's vector area equals the sum of the merged triangles' area vectors (area-weighted normal).
    area_vec = 0.5 * np.add.reduceat(np.cross(rel, rel_next), starts)
    normals = area_vec / np.linalg.norm(area_vec, axis=1, keepdims=True)
    offsets = np.einsum("ij,ij->i", centers, normals)  # = mean of n . v over the face's vertices
    radii = np.maximum.reduceat(np.linalg.norm(rel, axis=1), starts)
    off_plane = np.abs(np.einsum("ij,ij->i", rel, normals[face_of]))
    if off_plane.max() > check_tol:
        f = face_of[np.argmax(off_plane)]
        raise _HullBuildError(f"face {f} is not planar within {check_tol:.3g} m (deviation {off_plane.max():.3g} m)")
    # Blocks of faces keep the (nv, nf) table of signed distances small for hulls of 10^4 faces.
    block = max(1, 4_000_000 // nv)
    for f0 in range(0, len(loops), block):
        if (body @ normals[f0 : f0 + block].T - offsets[f0 : f0 + block]).max() > check_tol:
            raise _HullBuildError(f"a vertex lies outside a face plane by more than {check_tol:.3g} m")
    if offsets.min() <= 0.0:
        raise _HullBuildError("the centroid is not strictly inside every face plane")

    transform = np.eye(4)
    transform[:3, :3] = rot
    transform[:3, 3] = origin + centre
    return {
        "vertices": body,
        "faces": loops,
        "face_normals": normals,
        "face_offsets": offsets,
        "face_centers": centers,
        "face_radii": radii,
        "volume": float(props.volume),
        "inertia": inertia,
        "radius": float(np.linalg.norm(body, axis=1).max()),
        "input_transform": transform,
        "tolerance": check_tol,
    }
