"""Contact geometry in Warp: the one place where polygons are clipped and overlaps integrated.

The pair kernel (:mod:`polydem.kernels.narrowphase`), the contact step and its diagnostics
(:mod:`polydem.kernels.forces`) and the batch API (:func:`polydem.overlap`) all call the
``@wp.func`` built here:

* primitives (:func:`make_primitives`): float64 promotion and casts, signed plane distances, the
  Sutherland-Hodgman edge test and cut, the fan triangle, the cone from an apex over a facet,
  :func:`plane_geometry`, a body against one half-space (a wall), and :func:`plane_depth`;
* :func:`make_geometry`: :func:`pair_geometry`, two convex polyhedra, and :func:`pair_depth`.

For a pair (A, B) one thread clips every face polygon of A by the face planes of B and every
face of B by the planes of A. The surviving pieces are the facets of the overlap polyhedron
A n B. Summed over A's facets k (area A_k, A's outward normal n_k, centroid c_k):

    S_A = sum A_k n_k              (= gradient of the overlap volume V under translation of A)
    M_A = sum A_k (c_k x n_k)      (about A's centre; = gradient of V under rotation of A)

and V with the overlap centroid come from the divergence theorem over all facets.

Precision. The set-up of a pair (relative pose, the plane offsets and vertex positions of both
bodies) runs in float64 whatever the precision, from poses promoted to float64 (exact) and the
float64 shape tables (``vert64``, ``face_plane64``: a float32 size of 0.018 m is 4e-10 m off), and
the clipping, in the geometry's precision, runs in a pair-local frame: the larger body's axes (its big
faces stay exact: their vertices share their coordinates along the normal) with the origin at the
apex of the cones, which lies within the smaller body. Numbers are rounded to the clipping
precision only after the subtraction, so a flat contact 1e-8 m deep under a floor box whose
centre is 0.5 m (or a kilometre from the origin) away keeps its depth in float32. Edges are cut
from their end nearer the plane. The poses may come in float64 while the clipping runs in float32
(``pose_scalar``, the mixed mode).

Coincident facets: when a face g of the smaller body lies in the plane of a face f of the larger
one with the same outward normal (every vertex of g within ``tol_rel * r_min + noise * (|v| +
|d|)`` of f's plane in the pair-local frame: a tolerance of the smaller body and of the rounding
of the numbers the test meets; tol_rel 1e-7 in float32 and 1e-13 in float64, noise two units of
rounding), f is not clipped by g's plane nor g by f's, and both pieces count with weight 1/2: the
shared region is split half to each body, and S_A + S_B = 0 holds to rounding. One function
decides, evaluated with the same arguments from both sides, so both reach the same decision.

Faces with opposite outward normals in one plane need no rule of their own: the bodies overlap
through that plane by some thickness, and both faces are clipped like any other, so a flat contact
of any positive thickness has S_A = area * n (exactly touching faces give V = 0 and no contact). But
that thickness (the depth of a resting contact: nanometres) must survive the rounding: the pair-local
frame is turned so that the face of body 1 in such a flat contact (of the active faces with opposite
normals, the pair whose planes lie nearest) is a coordinate plane through the apex, and the apex is
moved onto it. Every coordinate across the thin overlap is then a small number, exact to its own
size, and both bodies' pieces of it agree. In body 1's own axes an oblique face (a rock's, a
tetrahedron's, a mesh-wall cell's) had its vertices rounded off its plane by units of the body's size.

Enclosed pairs: when |S_A| < ENCLOSED_RATIO V^(2/3) (one body (nearly) wholly inside the other,
or two identical bodies on top of each other), :func:`pair_geometry` also returns a fallback area
vector, which :func:`polydem.kernels.response.contact_frame` uses in place of S_A: the direction
of least penetration u (among the face normals of both bodies, the one along which the shorter
translation of A, along -u, separates the bodies) times the projected area of the smaller body
along it, 1/2 sum |u.n_f| A_f. A body wholly inside a wall gets -(its projected area along the
wall's normal n) n.

Depth (:func:`pair_depth`, :func:`plane_depth`): the penetration depth, the shortest translation
that separates the pair. For convex polyhedra it lies along a face normal of either body or the
cross product of an edge of each (the separating-axis theorem): the least overlap of the two
bodies' extents over those axes. For a corner pressed into a face it is that corner's depth below
the face; for two crossing edges, their distance. The deepest vertex alone would miss both a
face-to-face overlap of two aligned cubes (their vertices lie on each other's faces) and crossing
edges (no vertex inside); the face normals alone overestimate crossing edges. For a wall, offset - min n.v.
Computed in float64, for the diagnostics only (E_A E_B axes: not in the step).

The shape arrays reach every function as one :func:`shapes_struct` value (see
:class:`polydem.shapeset.ShapeSet` for the meaning of each array).
"""

import functools
from dataclasses import dataclass
from typing import Any

import warp as wp

# Tolerance of the coincident-face test relative to the smaller body's radius, per precision (see
# the module docstring): below the rounding, which the set-up in float64 keeps to a few units.
COINCIDENT_TOL = {wp.float32: 1.0e-7, wp.float64: 1.0e-13}
# Plus two units of rounding of the numbers each test meets: a vertex of the smaller body and the
# plane offset, in the pair-local frame (of the size of the smaller body, not of the larger).
COORDINATE_NOISE = {wp.float32: 2.4e-7, wp.float64: 4.5e-16}
# Margin of the culling of faces that cannot bound the overlap, relative to the smaller body:
# generous, since a face kept in vain is only clipped away.
CULL_MARGIN = 1.0e-5
# ... plus this many units of rounding of the pair's separation: the culling runs in the clipping
# precision, and only its decisions (never its numbers) reach the result.
CULL_ROUNDING = {wp.float32: 8.0 * 2.0**-24, wp.float64: 8.0 * 2.0**-53}
# Cheap pre-filter before the exact coincidence test: normals within about 2.5 degrees.
PARALLEL_COS = 0.999
# A pair whose |S_A| falls below this fraction of V^(2/3) is "enclosed" (one body (nearly) inside
# the other, or two identical bodies on top of each other: the gradient of V vanishes); the
# geometry then also returns the fallback area vector that contact_frame pushes along.
ENCLOSED_RATIO = 1.0e-4

vec3d = wp.types.vector(3, wp.float64)
quatd = wp.types.quaternion(wp.float64)
mat33d = wp.types.matrix(shape=(3, 3), dtype=wp.float64)


@functools.cache
def shapes_struct(scalar):
    """The ``wp.struct`` holding a shape set's arrays for one precision (``wp.float32`` or ``wp.float64``)."""
    vec3 = wp.types.vector(3, scalar)
    vec4 = wp.types.vector(4, scalar)
    fields = {
        "shape_vert_start": wp.array(dtype=int),
        "shape_face_start": wp.array(dtype=int),
        "shape_radius": wp.array(dtype=scalar),
        # The largest face area of each shape (of its parts for a compound grain) [m^2]: the face
        # contact whose stiffness the resolved toe bounds (kernels/response.py, toe_volume).
        "shape_face_area": wp.array(dtype=scalar),
        "face_plane": wp.array(dtype=vec4),
        "face_sphere": wp.array(dtype=vec4),
        "face_loop_start": wp.array(dtype=int),
        "face_loop": wp.array(dtype=int),
        # 1 for a face inside its grain (a compound's cut plane): a coincident face of another body
        # takes the whole shared region (see pair_geometry).
        "face_internal": wp.array(dtype=int),
        "vert": wp.array(dtype=vec3),
        # The same in float64 (the same arrays in float64), for the pair set-up.
        "face_plane64": wp.array(dtype=wp.types.vector(4, wp.float64)),
        "vert64": wp.array(dtype=vec3d),
        # Compound grains: shape s is made of the parts shape_part_start[s] .. [s + 1], part k the
        # convex shape part_shape[k] at pose part_q[k] in s's body frame (a convex shape is its
        # own single part at the identity).
        "shape_part_start": wp.array(dtype=int),
        "part_shape": wp.array(dtype=int),
        "part_q": wp.array(dtype=wp.types.transformation(wp.float64)),
    }
    name = f"Shapes{wp.types.type_size_in_bytes(scalar) * 8}"
    cls = type(name, (), {"__annotations__": fields, "__module__": __name__, "__qualname__": name})
    return wp.struct(cls)


@dataclass(frozen=True)
class Primitives:
    """The geometric ``@wp.func`` of one precision (see :func:`make_primitives`)."""

    scalar: Any
    vec3: Any
    vec4: Any
    shapes: Any  # the wp.struct type of the shape arrays
    plane_distance: Any
    crosses: Any
    edge_cut: Any
    twice_area: Any
    fan_add: Any
    fan_push: Any
    fan_close: Any
    cone: Any
    plane_geometry: Any
    to_scalar3: Any
    to_f64: Any
    pose_to_f64: Any
    face_area: Any
    projected_area: Any
    plane_depth: Any
    pose_scalar: Any


@dataclass(frozen=True)
class Geometry:
    """The pair geometry of one precision and polygon capacity (see :func:`make_geometry`)."""

    scalar: Any
    vec3: Any
    vec4: Any
    transform: Any
    quat: Any
    shapes: Any
    max_poly: int
    max_faces: int
    tol_rel: float
    primitives: Primitives
    pair_geometry: Any
    pair_depth: Any
    pose_scalar: Any


@functools.cache
def make_primitives(scalar, pose_scalar=None) -> Primitives:
    """Plane tests, the clipping step, fan triangles, cones, precision casts and the wall overlap.

    ``pose_scalar`` (default ``scalar``) is the precision of the poses, wall normals and offsets
    that :func:`plane_geometry` and :func:`plane_depth` take: ``wp.float64`` with a ``wp.float32``
    ``scalar`` is the mixed mode (float64 positions, float32 clipping).
    """
    if pose_scalar is None:
        pose_scalar = scalar
    vec3 = wp.types.vector(3, scalar)
    vec4 = wp.types.vector(4, scalar)
    transform = wp.types.transformation(pose_scalar)
    vec3p = wp.types.vector(3, pose_scalar)
    Shapes = shapes_struct(scalar)
    zero3 = wp.constant(vec3(scalar(0.0), scalar(0.0), scalar(0.0)))
    zero3d = wp.constant(vec3d(0.0, 0.0, 0.0))
    enclosed_ratio = ENCLOSED_RATIO

    @wp.func
    def to_scalar3(v: vec3d):
        # float64 set-up numbers, small once relative to the pair-local origin, to the clipping precision.
        return vec3(scalar(v[0]), scalar(v[1]), scalar(v[2]))

    @wp.func
    def to_f64(v: vec3):
        return vec3d(wp.float64(v[0]), wp.float64(v[1]), wp.float64(v[2]))

    @wp.func
    def pose_to_f64(x: transform):
        # A pose promoted to float64 (exact), its quaternion renormalised: a float32 quaternion is
        # unit only to ~1e-7, which would scale a body's vertices about its centre by as much.
        p = wp.transform_get_translation(x)
        q = wp.transform_get_rotation(x)
        q64 = wp.normalize(quatd(wp.float64(q[0]), wp.float64(q[1]), wp.float64(q[2]), wp.float64(q[3])))
        return vec3d(wp.float64(p[0]), wp.float64(p[1]), wp.float64(p[2])), q64

    @wp.func
    def face_area(shapes: Shapes, f: int):
        # Area of face f (its fan's cross products, in float64).
        begin = shapes.face_loop_start[f]
        end = shapes.face_loop_start[f + 1]
        p0 = shapes.vert64[shapes.face_loop[begin]]
        a = zero3d
        for k in range(begin + 1, end - 1):
            e1 = shapes.vert64[shapes.face_loop[k]] - p0
            a += wp.cross(e1, shapes.vert64[shapes.face_loop[k + 1]] - p0)
        return wp.float64(0.5) * wp.length(a)

    @wp.func
    def projected_area(shapes: Shapes, s: int, u: vec3d):
        # Area of the shadow of shape s (body frame) along the unit vector u: half the sum of
        # |u . n_f| A_f over its faces.
        total = wp.float64(0.0)
        for f in range(shapes.shape_face_start[s], shapes.shape_face_start[s + 1]):
            pl = shapes.face_plane64[f]
            c = pl[0] * u[0] + pl[1] * u[1] + pl[2] * u[2]
            total += wp.abs(c) * face_area(shapes, f)
        return wp.float64(0.5) * total

    @wp.func
    def plane_distance(n: vec3, d: scalar, x: vec3):
        # Signed distance of x from the plane n.x = d (unit n), positive outside.
        return wp.dot(n, x) - d

    @wp.func
    def crosses(s_prev: scalar, s: scalar):
        # Whether the edge between points of signed distances s_prev and s crosses the plane (the
        # inside, <= 0, of one end and the outside of the other): a Sutherland-Hodgman test.
        return (s <= scalar(0.0)) != (s_prev <= scalar(0.0))

    @wp.func
    def edge_cut(prev: vec3, s_prev: scalar, v: vec3, s: scalar):
        # Where the edge prev -> v, of signed distances s_prev and s, meets the plane. Stepping from
        # the end nearer the plane keeps the cut's precision that of the nearer point: from the far
        # end, a cut 1e-8 m from the near end of a 1 cm edge came out with ~5e-10 m of rounding
        # (the height of a resting cube's side strips, 2/3 of its shallow overlap V).
        if wp.abs(s) < wp.abs(s_prev):
            return v + (s / (s - s_prev)) * (prev - v)
        return prev + (s_prev / (s_prev - s)) * (v - prev)

    @wp.func
    def twice_area(p0: vec3, p1: vec3, p2: vec3, n: vec3):
        # Twice the signed area of the triangle (p0, p1, p2) seen along n.
        return wp.dot(wp.cross(p1 - p0, p2 - p0), n)

    @wp.func
    def fan_add(p0: vec3, p1: vec3, p2: vec3, nf: vec3, sum_a2: scalar, sum_c: vec3):
        # Adds the fan triangle (p0, p1, p2) to the running sums of twice the area and of twice the
        # area times three times the centroid; fan_close scales them once per facet, not per triangle.
        a2 = twice_area(p0, p1, p2, nf)
        return sum_a2 + a2, sum_c + a2 * (p0 + p1 + p2)

    @wp.func
    def fan_push(v: vec3, first: vec3, prev: vec3, count: int, nf: vec3, sum_a2: scalar, sum_c: vec3):
        # Appends vertex v to a polygon that streams past without a buffer: the fan from its first
        # vertex gains the triangle (first, prev, v) once two vertices came before.
        if count == 0:
            first = v
        if count >= 2:
            sum_a2, sum_c = fan_add(first, prev, v, nf, sum_a2, sum_c)
        return first, v, count + 1, sum_a2, sum_c

    @wp.func
    def fan_close(sum_a2: scalar, sum_c: vec3, weight: scalar):
        # The facet's area and area-weighted centroid, times weight, from the sums of fan_add.
        return weight * scalar(0.5) * sum_a2, (weight * scalar(0.5) / scalar(3.0)) * sum_c

    @wp.func
    def cone(area: scalar, area_c: vec3, plane: vec4, origin: vec3):
        # Volume and first moment of the pyramid from `origin` over a facet of the given area and
        # area-weighted centroid in `plane` (its centroid lies 3/4 of the way to the facet's).
        h = plane[3] - wp.dot(vec3(plane[0], plane[1], plane[2]), origin)
        v = area * h / scalar(3.0)
        return v, (h / scalar(3.0)) * (scalar(0.25) * area * origin + scalar(0.75) * area_c)

    @wp.func
    def plane_geometry(shapes: Shapes, s: int, xa: transform, normal: vec3p, offset: pose_scalar):
        """Overlap of shape ``s`` at pose ``xa`` with the half-space n.x <= offset (a wall).

        Returns (V, V * centroid, S_A, M_A about x_A, fallback area vector), positions relative
        to x_A, world axes. The fallback is zero unless the body lies (almost) wholly inside the
        half-space (|S_A| < ENCLOSED_RATIO V^(2/3)); then it is -(projected area along n) n, the
        effective S_A of :func:`polydem.kernels.response.contact_frame`.

        The set-up runs in float64 and the clipping relative to the foot of the body's centre on
        the wall, so that a resting body's face, a depth below the wall, has coordinates of the
        size of the depth rather than of the body (or of the wall's distance from the origin).
        Each face is clipped by the one plane while its vertices stream past, so no polygon buffer.
        """
        x64, q64 = pose_to_f64(xa)
        n64 = vec3d(wp.float64(normal[0]), wp.float64(normal[1]), wp.float64(normal[2]))
        dd = wp.float64(offset) - wp.dot(n64, x64)
        if dd <= -wp.float64(shapes.shape_radius[s]):
            return scalar(0.0), zero3, zero3, zero3, zero3
        nb64 = wp.quat_rotate_inv(q64, n64)
        foot = dd * nb64  # on the plane: the local origin, so the cap facet's cone is flat
        nb = to_scalar3(nb64)
        zero = scalar(0.0)
        vol = scalar(0.0)
        vol_c = zero3
        s_a = zero3
        m_a = zero3
        for f in range(shapes.shape_face_start[s], shapes.shape_face_start[s + 1]):
            pl = shapes.face_plane[f]
            nf = vec3(pl[0], pl[1], pl[2])
            p64 = shapes.face_plane64[f]
            d_local = p64[3] - wp.dot(vec3d(p64[0], p64[1], p64[2]), foot)
            pl_local = vec4(pl[0], pl[1], pl[2], scalar(d_local))
            begin = shapes.face_loop_start[f]
            count = shapes.face_loop_start[f + 1] - begin
            sum_a2 = scalar(0.0)
            sum_c = zero3
            emitted = int(0)
            first = zero3
            prev = zero3
            vp = to_scalar3(shapes.vert64[shapes.face_loop[begin + count - 1]] - foot)
            sp = plane_distance(nb, zero, vp)
            for k in range(count):
                v = to_scalar3(shapes.vert64[shapes.face_loop[begin + k]] - foot)
                sv = plane_distance(nb, zero, v)
                if crosses(sp, sv):
                    cut = edge_cut(vp, sp, v, sv)
                    first, prev, emitted, sum_a2, sum_c = fan_push(cut, first, prev, emitted, nf, sum_a2, sum_c)
                if sv <= scalar(0.0):
                    first, prev, emitted, sum_a2, sum_c = fan_push(v, first, prev, emitted, nf, sum_a2, sum_c)
                vp = v
                sp = sv
            if emitted >= 3:
                area, area_c = fan_close(sum_a2, sum_c, scalar(1.0))
                s_a += area * nf
                m_a += wp.cross(area_c, nf)
                dv, dv_c = cone(area, area_c, pl_local, zero3)
                vol += dv
                vol_c += dv_c
        # Back to the body's centre and world axes, in float64.
        s64 = to_f64(s_a)
        vol_c64 = to_f64(vol_c) + wp.float64(vol) * foot
        m64 = to_f64(m_a) + wp.cross(foot, s64)
        fallback = zero3
        if vol > scalar(0.0):
            if wp.length(s_a) < scalar(enclosed_ratio) * wp.pow(vol, scalar(2.0) / scalar(3.0)):
                # Wholly inside the wall: pushed out along its normal (module docstring).
                fallback = to_scalar3(-projected_area(shapes, s, nb64) * n64)
        return (
            vol,
            to_scalar3(wp.quat_rotate(q64, vol_c64)),
            to_scalar3(wp.quat_rotate(q64, s64)),
            to_scalar3(wp.quat_rotate(q64, m64)),
            fallback,
        )

    @wp.func
    def plane_depth(shapes: Shapes, s: int, xa: transform, normal: vec3p, offset: pose_scalar):
        """Penetration depth [m] of shape ``s`` at pose ``xa`` into the half-space n.x <= offset:
        offset - min n.v over its vertices, 0 when it does not reach the wall (float64 inside)."""
        x64, q64 = pose_to_f64(xa)
        n64 = vec3d(wp.float64(normal[0]), wp.float64(normal[1]), wp.float64(normal[2]))
        dd = wp.float64(offset) - wp.dot(n64, x64)
        nb64 = wp.quat_rotate_inv(q64, n64)
        depth = wp.float64(0.0)
        for iv in range(shapes.shape_vert_start[s], shapes.shape_vert_start[s + 1]):
            depth = wp.max(depth, dd - wp.dot(nb64, shapes.vert64[iv]))
        return scalar(depth)

    return Primitives(
        scalar=scalar,
        vec3=vec3,
        vec4=vec4,
        shapes=Shapes,
        plane_distance=plane_distance,
        crosses=crosses,
        edge_cut=edge_cut,
        twice_area=twice_area,
        fan_add=fan_add,
        fan_push=fan_push,
        fan_close=fan_close,
        cone=cone,
        plane_geometry=plane_geometry,
        to_scalar3=to_scalar3,
        to_f64=to_f64,
        pose_to_f64=pose_to_f64,
        face_area=face_area,
        projected_area=projected_area,
        plane_depth=plane_depth,
        pose_scalar=pose_scalar,
    )


SHARED_POLY_BLOCK = 64
"""Threads a block of a kernel built with make_geometry's ``shared_poly`` (the pair kernels' block,
:data:`polydem.kernels.narrowphase.NARROWPHASE_BLOCK_DIM`): each thread has its rows of the block's buffer."""
SHARED_POLY_BYTES = 48 * 1024 - 4 * SHARED_POLY_BLOCK
"""The static shared memory a CUDA block may hold (48 KB) less Warp's tile storage, one word a thread, which every
kernel declares (ptxas refused a 64-vertex buffer, 49152 B, by those 256 B: BENCHMARKS.md section 30)."""


def shared_poly_fits(scalar, max_poly: int) -> bool:
    """Whether make_geometry's ``shared_poly`` takes clipping in ``scalar`` with polygons of ``max_poly`` vertices."""
    return scalar == wp.float32 and 3 * 4 * int(max_poly) * SHARED_POLY_BLOCK <= SHARED_POLY_BYTES


@functools.cache
def make_geometry(
    scalar,
    max_poly: int,
    max_faces: int,
    coincident_tol: float | None = None,
    pose_scalar=None,
    count_work: bool = False,
    setup_only: bool = False,
    shared_poly: bool = False,
) -> Geometry:
    """:func:`pair_geometry` and :func:`pair_depth` for one precision and polygon capacity.

    Args:
        scalar: ``wp.float32`` or ``wp.float64``: the precision of the clipping and of the results.
        max_poly: capacity of the per-thread polygon buffer (vertices of one clipped facet). A
            facet that would exceed it raises the returned ``overflow`` flag; the host then
            rebuilds with a larger capacity and runs again.
        max_faces: the most faces of any shape in use (capacity of the per-thread lists of active
            faces).
        coincident_tol: relative tolerance of the coincident-face test (default per precision).
        pose_scalar: precision of the poses taken (default ``scalar``); ``wp.float64`` with a
            ``wp.float32`` ``scalar`` is the mixed mode.
        count_work: a measuring variant (benchmarks/pair_latency.py): ``overflow`` also carries the pair's path
            through the clipping, bits 1-8 and 9-16 the active faces of body 1 and body 2 (at most 255), bits
            17-30 the polygon vertices the Sutherland-Hodgman passes read (at most 16383).
        setup_only: a measuring variant (benchmarks/pair_latency.py --setup-only): a touching pair's set-up alone
            (the culling of its faces and planes, the flat contact, the apex and the pair-local frame), none of its
            clipping; the results are numbers that keep the set-up's work, not its overlap. What the clipping of
            its faces in parallel could at most save of a pair's latency.
        shared_poly: a variant (benchmarks/pair_kernel.py --clips polygon,shared) whose polygon buffer lies in the
            block's shared memory on a GPU (blocks of :data:`SHARED_POLY_BLOCK` threads, each with its own rows: the
            same arithmetic and results), not in per-thread local memory, which the pair kernel's throughput waits
            on (BENCHMARKS.md section 1b); :func:`shared_poly_fits` says where it applies. On the CPU one static
            buffer.
    """
    if shared_poly and not shared_poly_fits(scalar, max_poly):
        raise ValueError(
            f"the shared polygon buffer needs float32 clipping and at most {SHARED_POLY_BYTES} bytes a block "
            f"(got {scalar.__name__}, {max_poly} vertices a polygon)"
        )
    if pose_scalar is None:
        pose_scalar = scalar
    prim = make_primitives(scalar, pose_scalar)
    vec3 = prim.vec3
    vec4 = prim.vec4
    quat = wp.types.quaternion(pose_scalar)
    transform = wp.types.transformation(pose_scalar)
    Shapes = prim.shapes
    # The per-thread buffers of pair_pieces: one polygon (the Sutherland-Hodgman passes clip it in
    # place), and each body's list of active faces, a face's offset from its shape's first face in a
    # lane of 8 bits, four to an int word (where a shape has more than 256 faces: 16 bits, two to a
    # word; more than 65536: one): a quarter of the stack, and of its zero-fill, of a list of ints.
    ids_log = 2 if max_faces <= 256 else (1 if max_faces <= 65536 else 0)
    ids_bits = 32 >> ids_log
    ids_lane = (1 << ids_log) - 1
    ids_mask = (1 << ids_bits) - 1 if ids_bits < 32 else -1
    poly_t = wp.types.matrix(shape=(max_poly, 3), dtype=scalar)
    ids_t = wp.types.vector(length=(max_faces + ids_lane) >> ids_log, dtype=int)
    tol_rel = float(COINCIDENT_TOL[scalar] if coincident_tol is None else coincident_tol)
    noise_rel = float(COORDINATE_NOISE[scalar])
    cull_margin = CULL_MARGIN
    cull_rounding = CULL_ROUNDING[scalar]
    mat33 = wp.types.matrix(shape=(3, 3), dtype=scalar)
    parallel_cos = PARALLEL_COS
    enclosed_ratio = ENCLOSED_RATIO
    plane_distance = prim.plane_distance
    crosses = prim.crosses
    edge_cut = prim.edge_cut
    fan_add = prim.fan_add
    fan_close = prim.fan_close
    cone = prim.cone
    to_scalar3 = prim.to_scalar3
    to_f64 = prim.to_f64
    pose_to_f64 = prim.pose_to_f64
    projected_area = prim.projected_area
    zero3d = wp.constant(vec3d(0.0, 0.0, 0.0))

    # The shared variant's polygon buffer: row k of this thread's polygon, read (write 0) or written (write 1, which
    # returns v). Component c of row k of thread t lies at (c max_poly + k) B + t: a warp's threads read 32
    # consecutive words. A __shared__ variable of a device function is one per block, whichever call reaches it. On
    # the CPU, whose kernels run one thread after another, one static buffer (Warp's CPU JIT has no thread_local).
    poly_rw = finish_pass_shared = None
    if shared_poly:
        poly_rw_code = f"""
#if defined(__CUDA_ARCH__)
    __shared__ float polydem_poly[3 * {max_poly} * {SHARED_POLY_BLOCK}];
    float* row = polydem_poly + k * {SHARED_POLY_BLOCK} + threadIdx.x;
    const int stride = {max_poly} * {SHARED_POLY_BLOCK};
#else
    static float polydem_poly[3 * {max_poly}];
    float* row = polydem_poly + k;
    const int stride = {max_poly};
#endif
    if (write) {{
        row[0] = v[0];
        row[stride] = v[1];
        row[2 * stride] = v[2];
        return v;
    }}
    return wp::vec3(row[0], row[stride], row[2 * stride]);
"""

        @wp.func_native(poly_rw_code)
        def poly_rw(k: int, v: wp.vec3, write: int) -> wp.vec3: ...

    # The entries of the face lists, written and read through these (an entry is a value, the lists stay
    # where they are declared): entry n is lane n & ids_lane of word n >> ids_log.

    @wp.func
    def slot(n: int):
        return n >> ids_log

    @wp.func
    def with_face(word: int, n: int, f: int, first: int):
        # The word of entry n once face f is entered there (the entries before it kept).
        lane = n & ids_lane
        if lane == 0:
            return f - first
        return word | ((f - first) << (lane * ids_bits))

    @wp.func
    def face_of(word: int, n: int, first: int):
        return ((word >> ((n & ids_lane) * ids_bits)) & ids_mask) + first

    @wp.func
    def plane64(shapes: Shapes, f: int):
        pl = shapes.face_plane64[f]
        return vec3d(pl[0], pl[1], pl[2]), pl[3]

    @wp.func
    def plane_row_1(shapes: Shapes, f: int, turned: bool, frame: quatd, apex: vec3d):
        # Plane of face f of body 1 in the pair-local frame (axes `frame` times body 1's where
        # `turned`, else body 1's; origin at the apex), rounded to the clipping precision.
        n, d = plane64(shapes, f)
        n1 = n
        if turned:
            n1 = wp.quat_rotate(frame, n)
        return vec4(scalar(n1[0]), scalar(n1[1]), scalar(n1[2]), scalar(d - wp.dot(n, apex)))

    @wp.func
    def plane_row_2(shapes: Shapes, g: int, rot: mat33d, off_2: vec3d):
        # Plane of face g of body 2 (at rot x + off_2) in the pair-local frame, rounded.
        n, d = plane64(shapes, g)
        n1 = rot * n
        return vec4(scalar(n1[0]), scalar(n1[1]), scalar(n1[2]), scalar(d + wp.dot(n1, off_2)))

    @wp.func
    def face_vertex(
        shapes: Shapes, of_1: bool, k: int, turned: bool, frame: quatd, rot: mat33d, off_2: vec3d, apex: vec3d
    ):
        # Vertex face_loop[k] of body 1 (of_1) or body 2 in the pair-local frame, rounded.
        v = shapes.vert64[shapes.face_loop[k]]
        if of_1:
            if turned:
                return to_scalar3(wp.quat_rotate(frame, v - apex))
            return to_scalar3(v - apex)
        return to_scalar3(rot * v + off_2)

    @wp.func
    def support64(shapes: Shapes, v0: int, v1: int, rot: mat33d, off: vec3d, u: vec3d, floor: wp.float64):
        # The reach along u of the vertices v0 <= i < v1 placed at rot v + off, at least `floor`.
        h = floor
        for iv in range(v0, v1):
            h = wp.max(h, wp.dot(u, rot * shapes.vert64[iv] + off))
        return h

    @wp.func
    def support_c(shapes: Shapes, v0: int, v1: int, u: vec3):
        # The reach of the vertices v0 <= i < v1 (own frame) along u, in the clipping precision.
        h = wp.dot(u, shapes.vert[v0])
        for iv in range(v0 + 1, v1):
            h = wp.max(h, wp.dot(u, shapes.vert[iv]))
        return h

    @wp.func
    def all_outside_c(shapes: Shapes, v0: int, v1: int, n: vec3, d: scalar):
        # Whether every vertex v0 <= i < v1 (own frame) lies beyond the plane n.x = d.
        for iv in range(v0, v1):
            if wp.dot(n, shapes.vert[iv]) <= d:
                return False
        return True

    @wp.func
    def sphere_misses_c(c: vec3, r: scalar, u: vec3, lo: scalar, hi: scalar, centre: vec3, reach: scalar):
        # Whether the sphere (c, r) around a face misses the slab lo <= u.x <= hi or the other
        # body's bounding sphere (centre, reach): then the face cannot bound the overlap.
        uc = wp.dot(u, c)
        return uc + r < lo or uc - r > hi or wp.length_sq(c - centre) > (r + reach) * (r + reach)

    @wp.func
    def coincident(shapes: Shapes, pl: vec4, gs: int, rot: mat33d, off: vec3d, tol: scalar):
        # Whether face gs of the smaller body lies in the plane pl (pair-local) of a face of the
        # larger one with the same outward normal: every vertex of gs within tol of pl. Only the
        # smaller face is tested, so the tolerance and the rounding met are those of the smaller
        # body. Called with the same arguments from both sides, so both reach the same decision.
        nl = vec3(pl[0], pl[1], pl[2])
        n64, d64 = plane64(shapes, gs)
        if wp.dot(nl, to_scalar3(rot * n64)) < scalar(parallel_cos):
            return False
        for k in range(shapes.face_loop_start[gs], shapes.face_loop_start[gs + 1]):
            v = to_scalar3(rot * shapes.vert64[shapes.face_loop[k]] + off)
            t = tol + scalar(noise_rel) * (wp.length(v) + wp.abs(pl[3]))
            if wp.abs(plane_distance(nl, pl[3], v)) > t:
                return False
        return True

    @wp.func
    def extent_overlaps(shapes: Shapes, s1: int, s2: int, rot: mat33d, pos: vec3d, u: vec3d):
        # How far body 1 (own frame) reaches past body 2 (at rot x + pos) along the unit vector u,
        # and body 2 past body 1: the translations of body 1 along -u and along +u that separate
        # them (negative: u separates them already).
        big = wp.float64(1.0e300)
        eye = wp.identity(n=3, dtype=wp.float64)
        v10 = shapes.shape_vert_start[s1]
        v11 = shapes.shape_vert_start[s1 + 1]
        v20 = shapes.shape_vert_start[s2]
        v21 = shapes.shape_vert_start[s2 + 1]
        sup1 = support64(shapes, v10, v11, eye, zero3d, u, -big)
        inf1 = -support64(shapes, v10, v11, eye, zero3d, -u, -big)
        sup2 = support64(shapes, v20, v21, rot, pos, u, -big)
        inf2 = -support64(shapes, v20, v21, rot, pos, -u, -big)
        return sup1 - inf2, sup2 - inf1

    @wp.func
    def least_penetration(shapes: Shapes, s1: int, s2: int, rot: mat33d, pos: vec3d):
        # Among the face normals of both bodies (body 1's frame, body 2 at rot x + pos), the unit
        # direction u along which the shortest translation of body 1 (along -u) separates them,
        # and the length of that translation.
        best = wp.float64(1.0e300)
        best_u = vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(1.0))
        f10 = shapes.shape_face_start[s1]
        f11 = shapes.shape_face_start[s1 + 1]
        f21 = shapes.shape_face_start[s2 + 1]
        for f in range(f10, f21 - shapes.shape_face_start[s2] + f11):
            u = vec3d()
            if f < f11:
                n, d = plane64(shapes, f)
                u = n
            else:
                n, d = plane64(shapes, f - f11 + shapes.shape_face_start[s2])
                u = rot * n
            o1, o2 = extent_overlaps(shapes, s1, s2, rot, pos, u)
            if o1 < best:
                best = o1
                best_u = u
            if o2 < best:
                best = o2
                best_u = -u
        return best_u, best

    @wp.func
    def axes_onto(n: vec3d):
        # A rotation (a quaternion: it stays live through the clipping loop, in fewer registers than a
        # matrix) taking the unit vector n onto the coordinate axis nearest it.
        # e = sign(n_k) along the axis k of the largest |n_k| (the first of equals), chosen without
        # indexing by k: a runtime index puts a vector in local memory.
        zero = wp.float64(0.0)
        e = vec3d(wp.sign(n[0]), zero, zero)
        big = wp.abs(n[0])
        if wp.abs(n[1]) > big:
            e = vec3d(zero, wp.sign(n[1]), zero)
            big = wp.abs(n[1])
        if wp.abs(n[2]) > big:
            e = vec3d(zero, zero, wp.sign(n[2]))
        # Half-way between n and e: c = n . e >= 1/sqrt(3) here, so 1 + c is far from 0.
        v = wp.cross(n, e)
        return wp.normalize(quatd(v[0], v[1], v[2], wp.float64(1.0) + wp.dot(n, e)))

    @wp.func
    def finish_pass(
        poly: poly_t, out: wp.ref[poly_t], count: int, k0: int, n_out: int,
        prev: vec3, s_prev: scalar, v: vec3, ncut: vec3, dcut: scalar,
    ):  # fmt: skip
        # Steps k0.. of an in-place Sutherland-Hodgman pass whose output would overrun input not yet
        # read: the rest out of place, into a buffer of its own, then back into `out` (the same polygon
        # buffer, by reference; `poly`, its copy, is what is read). Rows [0, n_out) hold the output so
        # far, rows > k0 the input not yet read, v the input at k0. Rare: its buffer is declared (and
        # zero-filled) only when it runs.
        spare = poly_t()
        for i in range(n_out):
            spare[i] = poly[i]
        full = int(0)
        for k in range(k0, count):
            if k > k0:
                v = poly[k]
            sk = plane_distance(ncut, dcut, v)
            if crosses(s_prev, sk):
                if n_out >= max_poly:
                    full = 1
                    break
                spare[n_out] = edge_cut(prev, s_prev, v, sk)
                n_out += 1
            if sk <= scalar(0.0):
                if n_out >= max_poly:
                    full = 1
                    break
                spare[n_out] = v
                n_out += 1
            prev = v
            s_prev = sk
        for i in range(n_out):
            out[i] = spare[i]
        return n_out, full

    if shared_poly:

        @wp.func
        def finish_pass_shared(
            count: int, k0: int, n_out: int, prev: vec3, s_prev: scalar, v: vec3, ncut: vec3, dcut: scalar,
        ):  # fmt: skip
            # finish_pass for the shared polygon buffer (shared_poly), its reads and writes through poly_rw: written
            # out again because finish_pass on a per-thread copy of the rows put two polygons on every thread's
            # stack (ptxas: a rock pair's 560 B frame became 1016 B), which the shared buffer is there to avoid.
            spare = poly_t()
            for i in range(n_out):
                spare[i] = poly_rw(i, v, 0)
            full = int(0)
            for k in range(k0, count):
                if k > k0:
                    v = poly_rw(k, v, 0)
                sk = plane_distance(ncut, dcut, v)
                if crosses(s_prev, sk):
                    if n_out >= max_poly:
                        full = 1
                        break
                    spare[n_out] = edge_cut(prev, s_prev, v, sk)
                    n_out += 1
                if sk <= scalar(0.0):
                    if n_out >= max_poly:
                        full = 1
                        break
                    spare[n_out] = v
                    n_out += 1
                prev = v
                s_prev = sk
            for i in range(n_out):
                poly_rw(i, spare[i], 1)
            return n_out, full

    @wp.func
    def pair_pieces(
        shapes: Shapes, s1: int, s2: int, in_a: bool, xa64: vec3d, xb64: vec3d, q1: quatd, r2: wp.float64,
        pos: vec3d, rot: mat33d, pos_c: vec3, rot_c: mat33, r1_c: scalar, r2_c: scalar, slack: scalar,
        uc: vec3, lo_c: scalar, hi_c: scalar, f10: int, f11: int, f20: int, f21: int,
        v10: int, v11: int, v20: int, v21: int,
    ):  # fmt: skip
        # pair_geometry past its bounding-sphere and slab tests: the culling of faces and planes, the
        # pair-local frame, the clipping, and the results in world axes.
        # The per-thread buffers first: Warp zero-fills each where the function starts, and an
        # assignment next to that is the same fill (a later one was a second).
        ids_1 = ids_t()
        ids_2 = ids_t()
        if wp.static(not shared_poly):
            poly = poly_t()
        zero3 = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        rot_ct = wp.transpose(rot_c)
        # Separating face planes, by bounding spheres first and exactly (all of the other body's
        # vertices outside, by more than the slack) only for planes the other body's centre lies
        # outside of. Meanwhile find where the line of centres leaves body 1 (tau_1, as a
        # fraction of the way from its centre to body 2's) and enters body 2 (tau_2): the cones
        # that integrate V start from the middle of that stretch, inside the overlap whenever the
        # line crosses it, so the cone volumes do not cancel and V and its centroid keep their
        # precision for shallow overlaps. The tau are only an apex: the clipping precision will do.
        tau_1c = scalar(1.0)
        tau_2c = scalar(0.0)
        # The active faces of each body, a list in per-thread memory (packed: slot, with_face, face_of),
        # in increasing index order.
        num_1 = int(0)
        word = int(0)  # the list's last word, as written
        for f in range(f10, f11):
            plc = shapes.face_plane[f]
            nc = vec3(plc[0], plc[1], plc[2])
            dc = plc[3]
            sigma_c = wp.dot(nc, pos_c)
            if sigma_c * tau_1c > dc:  # d / sigma < tau_1: the line leaves body 1 earlier here
                tau_1c = dc / sigma_c
            sc = sigma_c - dc
            if sc > r2_c + slack:
                return scalar(0.0), zero3, zero3, zero3, zero3, zero3, zero3, 0
            if sc > scalar(0.0):
                # The other body's centre lies outside: is the plane separating?
                if all_outside_c(shapes, v20, v21, rot_ct * nc, dc - sigma_c + slack):
                    return scalar(0.0), zero3, zero3, zero3, zero3, zero3, zero3, 0
            if sc <= -(r2_c + slack):
                continue  # body 2 lies wholly inside this plane: the face cannot reach it
            sph_c = shapes.face_sphere[f]
            if sphere_misses_c(vec3(sph_c[0], sph_c[1], sph_c[2]), sph_c[3] + slack, uc, lo_c, hi_c, pos_c, r2_c):
                continue
            word = with_face(word, num_1, f, f10)
            ids_1[slot(num_1)] = word
            num_1 += 1
        num_2 = int(0)
        word = int(0)
        pos_2c = -(rot_ct * pos_c)  # body 1's centre in body 2's frame
        for g in range(f20, f21):
            plc = shapes.face_plane[g]
            nc = vec3(plc[0], plc[1], plc[2])
            dc = plc[3]
            sigma_c = wp.dot(nc, pos_2c)
            if sigma_c * (scalar(1.0) - tau_2c) > dc:  # 1 - d / sigma > tau_2: it enters body 2 later
                tau_2c = scalar(1.0) - dc / sigma_c
            sc = sigma_c - dc
            if sc > r1_c + slack:
                return scalar(0.0), zero3, zero3, zero3, zero3, zero3, zero3, 0
            n1c = rot_c * nc
            if sc > scalar(0.0):
                if all_outside_c(shapes, v10, v11, n1c, dc + wp.dot(n1c, pos_c) + slack):
                    return scalar(0.0), zero3, zero3, zero3, zero3, zero3, zero3, 0
            if sc <= -(r1_c + slack):
                continue
            sph_c = shapes.face_sphere[g]
            cc = rot_c * vec3(sph_c[0], sph_c[1], sph_c[2]) + pos_c
            if sphere_misses_c(cc, sph_c[3] + slack, uc, lo_c, hi_c, zero3, r1_c):
                continue
            word = with_face(word, num_2, g, f20)
            ids_2[slot(num_2)] = word
            num_2 += 1
        tau_1 = wp.float64(tau_1c)
        tau_2 = wp.float64(tau_2c)

        # A flat contact: of the active faces with opposite outward normals (within PARALLEL_COS),
        # the pair whose planes lie nearest each other. The pair-local frame then turns body 1's
        # face onto a coordinate plane through the apex: the coordinates across the thin overlap
        # are small numbers, exact to their own size, so both faces' pieces agree on it. In body
        # 1's axes an oblique face (a rock's, a tetrahedron's, a cell of a tilted mesh wall) had
        # vertices rounded off its own plane by units of the body's size, as far as the depth of a
        # resting contact: the facets of the two bodies disagreed and V came out 1e9 times off.
        frame = quatd(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0), wp.float64(1.0))
        turned = bool(False)  # frame is not the identity: body 1's planes and vertices are rotated
        flat = int(-1)
        gap = scalar(1.0e30)
        for j in range(num_1):
            f = face_of(ids_1[slot(j)], j, f10)
            pf = shapes.face_plane[f]
            # n_f in body 2's frame, where body 2's planes are read as stored
            nf2 = rot_ct * vec3(pf[0], pf[1], pf[2])
            for jj in range(num_2):
                g = face_of(ids_2[slot(jj)], jj, f20)
                pg = shapes.face_plane[g]
                ng = vec3(pg[0], pg[1], pg[2])
                if wp.dot(nf2, ng) < -scalar(parallel_cos):
                    # the slab between the two planes along n_f: d_f + d_g - n_g . (body 1's centre in 2's frame)
                    slab = wp.abs(pf[3] + pg[3] - wp.dot(ng, pos_2c))
                    if slab < gap:
                        gap = slab
                        flat = f
        apex = pos * (wp.float64(0.5) * (tau_1 + tau_2))
        if tau_2 > tau_1:
            # The line of centres misses the overlap (it leaves body 1 before it enters body 2: a
            # body lying on a big face of the other, away from its centre). An apex there would lie
            # outside the overlap, up to metres from it (in float32 the facets close only to ~1e-3
            # of their area: that gap times the apex's distance came out as V errors of 10-100x
            # for shallow face contacts of a cube on a floor box). Take instead the foot of body 2's
            # centre on body 1: projected onto the active plane of body 1 it lies farthest above, then
            # again while it lies above another (a box's closest point in at most three rounds). On
            # the contact face, whose cones then vanish exactly, and next to the overlap where body 2
            # overhangs an edge or a corner of body 1: the foot on one side plane alone lay up to a
            # body's size above the overlap, and float32 coordinates of that size round a shallow
            # overlap's facets apart (V off by 1e7 times at 1e-8 m deep).
            apex = pos
            for _round in range(3):
                s_top = wp.float64(0.0)
                n_top = vec3d()
                for j in range(num_1):
                    n, d = plane64(shapes, face_of(ids_1[slot(j)], j, f10))
                    sj = wp.dot(n, apex) - d
                    if sj > s_top:
                        s_top = sj
                        n_top = n
                if s_top <= wp.float64(0.0):
                    break
                apex = apex - s_top * n_top
        if flat >= 0:
            n_flat, d_flat = plane64(shapes, flat)
            apex = apex - (wp.dot(n_flat, apex) - d_flat) * n_flat
            # An axis-aligned face (a box's) keeps body 1's axes: no rotation to pay per plane and vertex.
            turned = n_flat[0] * n_flat[1] != wp.float64(0.0) or n_flat[1] * n_flat[2] != wp.float64(0.0)
            turned = turned or n_flat[0] * n_flat[2] != wp.float64(0.0)
            if turned:
                frame = axes_onto(n_flat)
        # The pair-local frame: `frame` times body 1's axes, origin at the apex. Planes and vertices
        # are moved there in float64 and only then rounded to the clipping precision (plane_row_1,
        # plane_row_2, face_vertex) wherever they are read: recomputed, not kept in per-thread tables
        # (BENCHMARKS.md section 7c). `rot_l` and `off_2` place body 2 there; `rot` and `pos` still
        # place it in body 1's frame.
        rot_l = wp.quat_to_matrix(frame) * rot
        off_2 = wp.quat_rotate(frame, pos - apex)  # body 2's centre, pair-local
        tol_c = scalar(tol_rel) * scalar(r2)  # coincident-face tolerance, before the rounding
        if wp.static(setup_only):
            kept = to_scalar3(off_2) + vec3(scalar(num_1 + num_2), tol_c, scalar(rot_l[0, 0]))
            return scalar(1.0), kept, zero3, zero3, zero3, zero3, zero3, 0

        vol = scalar(0.0)
        vol_c = zero3
        s_1 = zero3
        m_1 = zero3
        s_2 = zero3
        m_2 = zero3
        overflow = int(0)
        if wp.static(count_work):
            steps = int(0)
        # Clip each active face polygon by the other body's active planes and integrate the
        # surviving piece. This loop is written out here rather than in a helper called per face: a
        # @wp.func takes its arguments by value (a wp.ref[T] argument is read whole wherever one
        # element of it is), and the per-thread buffers (polygon, ids) live in local memory, so a
        # call per face copied them again each time. One polygon buffer (declared above) serves
        # every face, and each Sutherland-Hodgman pass clips it in place.
        for j in range(num_1 + num_2):
            face_is_1 = j < num_1
            face = int(0)
            num_planes = int(0)
            plane = vec4()
            if face_is_1:
                face = face_of(ids_1[slot(j)], j, f10)
                num_planes = num_2
                plane = plane_row_1(shapes, face, turned, frame, apex)
            else:
                face = face_of(ids_2[slot(j - num_1)], j - num_1, f20)
                num_planes = num_1
                plane = plane_row_2(shapes, face, rot_l, off_2)
            nf = vec3(plane[0], plane[1], plane[2])
            begin = shapes.face_loop_start[face]
            count = shapes.face_loop_start[face + 1] - begin
            sph = shapes.face_sphere[face]
            c64 = vec3d(wp.float64(sph[0]), wp.float64(sph[1]), wp.float64(sph[2]))
            centre = zero3
            if face_is_1:
                if turned:
                    centre = to_scalar3(wp.quat_rotate(frame, c64 - apex))
                else:
                    centre = to_scalar3(c64 - apex)
            else:
                centre = to_scalar3(rot_l * c64 + off_2)
            for k in range(count):
                if wp.static(shared_poly):
                    poly_rw(k, face_vertex(shapes, face_is_1, begin + k, turned, frame, rot_l, off_2, apex), 1)
                else:
                    poly[k] = face_vertex(shapes, face_is_1, begin + k, turned, frame, rot_l, off_2, apex)
            weight = scalar(1.0)
            alive = bool(True)
            for t in range(num_planes):
                other = int(0)
                if face_is_1:
                    other = face_of(ids_2[slot(t)], t, f20)
                else:
                    other = face_of(ids_1[slot(t)], t, f10)
                pl = vec4()
                if face_is_1:
                    pl = plane_row_2(shapes, other, rot_l, off_2)
                else:
                    pl = plane_row_1(shapes, other, turned, frame, apex)
                nc = vec3(pl[0], pl[1], pl[2])
                dc = pl[3]
                dist_c = plane_distance(nc, dc, centre)
                if dist_c <= -sph[3]:
                    continue  # the whole face lies inside this plane
                if dist_c > sph[3]:
                    alive = False
                    break
                if wp.dot(nf, nc) >= scalar(parallel_cos):
                    # Coincident faces with the same outward normal: shared half and half, decided
                    # by one function evaluated the same way from both sides (body 1's plane, body
                    # 2's face), so both sides agree bit for bit. Opposite normals are no special
                    # case: a flat contact of any thickness is clipped like any other.
                    same = bool(False)
                    if face_is_1:
                        same = coincident(shapes, plane, other, rot_l, off_2, tol_c)
                    else:
                        same = coincident(shapes, pl, face, rot_l, off_2, tol_c)
                    if same:
                        # Half to each body; but where one of the two faces lies inside its grain (a
                        # compound's cut plane), the other is the boundary of the union there and
                        # takes it all. The same rule read from both sides: the weights sum to 1.
                        inside_face = shapes.face_internal[face]
                        inside_other = shapes.face_internal[other]
                        weight = scalar(0.5)
                        if inside_face != inside_other:
                            weight = scalar(1.0)
                            if inside_face != 0:
                                weight = scalar(0.0)
                        continue
                # Sutherland-Hodgman against ncut.x <= dcut (the plane nc, dc, read again: with nc and
                # dc themselves the kernel compiles otherwise than the one timed in BENCHMARKS.md 7c),
                # in place: the output overwrites the input behind the reading, which runs one vertex
                # ahead (v_k+1 is read before step k writes): a convex polygon's output stays within
                # rows <= k+1 at step k. A vertex already in its row is not written again, so a plane
                # that cuts nothing writes nothing. A polygon rounded off convex can cross the plane
                # more than twice: before its output would overrun input not yet read, finish_pass
                # does the rest of the pass out of place.
                ncut = vec3(pl[0], pl[1], pl[2])
                dcut = pl[3]
                n_out = int(0)
                full = int(0)
                if wp.static(shared_poly):
                    prev = poly_rw(count - 1, zero3, 0)
                else:
                    prev = poly[count - 1]
                s_prev = plane_distance(ncut, dcut, prev)
                if wp.static(shared_poly):
                    v = poly_rw(0, zero3, 0)
                else:
                    v = poly[0]
                if wp.static(count_work):
                    steps += count
                for k in range(count):
                    ahead = v
                    if k + 1 < count:
                        if wp.static(shared_poly):
                            ahead = poly_rw(k + 1, zero3, 0)
                        else:
                            ahead = poly[k + 1]
                    sk = plane_distance(ncut, dcut, v)
                    cut = crosses(s_prev, sk)
                    keep = sk <= scalar(0.0)
                    # The output would overrun the next row not yet read (row k + 2; row k + 1 is in `ahead`):
                    # before step k n_out <= k + 1, so only where this step writes two rows and n_out is k + 1.
                    if k + 2 < count and cut and keep and n_out > k:
                        if wp.static(shared_poly):
                            n_out, full = finish_pass_shared(count, k, n_out, prev, s_prev, v, ncut, dcut)
                        else:
                            n_out, full = finish_pass(poly, poly, count, k, n_out, prev, s_prev, v, ncut, dcut)
                        break
                    if cut:
                        if n_out >= max_poly:
                            full = 1
                            break
                        if wp.static(shared_poly):
                            poly_rw(n_out, edge_cut(prev, s_prev, v, sk), 1)
                        else:
                            poly[n_out] = edge_cut(prev, s_prev, v, sk)
                        n_out += 1
                    if keep:
                        if n_out >= max_poly:
                            full = 1
                            break
                        if n_out != k:
                            if wp.static(shared_poly):
                                poly_rw(n_out, v, 1)
                            else:
                                poly[n_out] = v
                        n_out += 1
                    prev = v
                    s_prev = sk
                    v = ahead
                if full != 0:
                    overflow = 1
                if n_out < 3 or full != 0:
                    alive = False
                    break
                count = n_out
            if not alive:
                continue
            # Fan triangulation: facet area and area-weighted centroid, each vertex read once (a
            # triangle's second vertex is the previous one's third).
            sum_a2 = scalar(0.0)
            sum_c = zero3
            if wp.static(shared_poly):
                p0 = poly_rw(0, zero3, 0)
                p1 = poly_rw(1, zero3, 0)
            else:
                p0 = poly[0]
                p1 = poly[1]
            for k in range(1, count - 1):
                if wp.static(shared_poly):
                    p2 = poly_rw(k + 1, zero3, 0)
                else:
                    p2 = poly[k + 1]
                sum_a2, sum_c = fan_add(p0, p1, p2, nf, sum_a2, sum_c)
                p1 = p2
            area, area_c = fan_close(sum_a2, sum_c, weight)
            dv, dv_c = cone(area, area_c, plane, zero3)
            vol += dv
            vol_c += dv_c
            if face_is_1:
                s_1 += area * nf
                m_1 += wp.cross(area_c, nf)
            else:
                s_2 += area * nf
                m_2 += wp.cross(area_c, nf)

        # Enclosed: the fallback area vector of body 1 (module docstring), body 1's frame.
        fb_1 = zero3d
        if vol > scalar(0.0):
            if wp.length(s_1) < scalar(enclosed_ratio) * wp.pow(vol, scalar(2.0) / scalar(3.0)):
                # Body 2's pose in body 1's frame again, from the pair-local one: keeping the originals
                # live through the clipping loop cost registers, and spills, in every pair.
                rot_b = wp.quat_to_matrix(wp.quat_inverse(frame)) * rot_l
                pos_b = wp.quat_rotate_inv(frame, off_2) + apex
                u_best, sep = least_penetration(shapes, s1, s2, rot_b, pos_b)
                fb_1 = projected_area(shapes, s2, wp.transpose(rot_b) * u_best) * u_best
        # Back to body 1's axes and centre (float64), then to world axes and A's centre.
        vol64 = wp.float64(vol)
        s1_64 = wp.quat_rotate_inv(frame, to_f64(s_1))
        s2_64 = wp.quat_rotate_inv(frame, to_f64(s_2))
        vol_c64 = wp.quat_rotate(q1, wp.quat_rotate_inv(frame, to_f64(vol_c)) + vol64 * apex)
        m1_64 = wp.quat_rotate(q1, wp.quat_rotate_inv(frame, to_f64(m_1)) + wp.cross(apex, s1_64))
        m2_64 = wp.quat_rotate(q1, wp.quat_rotate_inv(frame, to_f64(m_2)) + wp.cross(apex, s2_64))
        s1_64 = wp.quat_rotate(q1, s1_64)
        s2_64 = wp.quat_rotate(q1, s2_64)
        fb_1 = wp.quat_rotate(q1, fb_1)
        if wp.static(count_work):
            overflow = overflow | (wp.min(num_1, 255) << 1) | (wp.min(num_2, 255) << 9) | (wp.min(steps, 16383) << 17)
        if in_a:
            return (
                vol,
                to_scalar3(vol_c64),
                to_scalar3(s1_64),
                to_scalar3(m1_64),
                to_scalar3(s2_64),
                to_scalar3(m2_64),
                to_scalar3(fb_1),
                overflow,
            )
        # Positions came relative to B's centre: move them to A's.
        r = xb64 - xa64
        return (
            vol,
            to_scalar3(vol_c64 + vol64 * r),
            to_scalar3(s2_64),
            to_scalar3(m2_64 + wp.cross(r, s2_64)),
            to_scalar3(s1_64),
            to_scalar3(m1_64 + wp.cross(r, s1_64)),
            to_scalar3(-fb_1),
            overflow,
        )

    @wp.func
    def pair_geometry(shapes: Shapes, sa: int, sb: int, xa: transform, xb: transform):
        """Overlap geometry of shape ``sa`` at pose ``xa`` and shape ``sb`` at pose ``xb``.

        Returns ``(V, first moment of V, S_A, M_A, S_B, M_B, fallback_A, overflow)``, with vectors
        in world axes and every position relative to A's centre (the first moment is V times the
        overlap centroid; M_A and M_B are about A's centre). ``fallback_A`` is zero unless the
        pair is enclosed (|S_A| < ENCLOSED_RATIO V^(2/3)); then it is the effective area vector of
        :func:`polydem.kernels.response.contact_frame`: the direction of least penetration times
        the projected area of the smaller body along it.

        The set-up (relative pose, plane offsets, vertex positions) runs in float64 and the
        clipping in a pair-local frame: the larger body's axes, whose big faces are then exact
        (in the small body's axes the far corners of, say, a container wall carry rounding that
        moves the wall's face off its plane), with the origin at the apex of the cones, which lies
        within the smaller body: the numbers that meet in the clipping are of the size of the
        smaller body, and a depth of 1e-8 m under a floor box whose centre is 0.5 m away is not
        lost to the rounding of 0.5 m.
        """
        zero3 = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        # Body 1 is the larger (its frame is the pair's), body 2 the smaller.
        in_a = shapes.shape_radius[sb] <= shapes.shape_radius[sa]
        s1 = sa
        s2 = sb
        if not in_a:
            s1 = sb
            s2 = sa
        xa64, qa64 = pose_to_f64(xa)
        xb64, qb64 = pose_to_f64(xb)
        x1 = xa64
        q1 = qa64
        x2 = xb64
        q2 = qb64
        if not in_a:
            x1 = xb64
            q1 = qb64
            x2 = xa64
            q2 = qa64
        r1 = wp.float64(shapes.shape_radius[s1])
        r2 = wp.float64(shapes.shape_radius[s2])
        q1_inv = wp.quat_inverse(q1)
        pos = wp.quat_rotate(q1_inv, x2 - x1)  # body 2's centre in body 1's frame
        dist2 = wp.length_sq(pos)
        if dist2 >= (r1 + r2) * (r1 + r2):
            return scalar(0.0), zero3, zero3, zero3, zero3, zero3, zero3, 0
        rot = wp.quat_to_matrix(q1_inv * q2)
        f10 = shapes.shape_face_start[s1]
        f11 = shapes.shape_face_start[s1 + 1]
        f20 = shapes.shape_face_start[s2]
        f21 = shapes.shape_face_start[s2 + 1]
        v10 = shapes.shape_vert_start[s1]
        v11 = shapes.shape_vert_start[s1 + 1]
        v20 = shapes.shape_vert_start[s2]
        v21 = shapes.shape_vert_start[s2 + 1]

        # Culling runs in the clipping precision: it only decides which faces and planes can bound
        # the overlap (and whether there is one), so it need not be exact, only conservative. Its
        # slack covers the rounding of numbers of the size of the pair's separation, and a face
        # kept in vain is only clipped away. (In float64 throughout, the loops over every vertex
        # and face of the separated candidates cost a third of the pair kernel's throughput.)
        pos_c = to_scalar3(pos)
        rot_c = mat33(rot)
        rot_ct = wp.transpose(rot_c)
        r1_c = scalar(r1)
        r2_c = scalar(r2)
        dist = wp.sqrt(dist2)
        slack = scalar(cull_margin) * r2_c + scalar(cull_rounding) * (scalar(dist) + r1_c + r2_c)

        # The overlap lies in the slab lo <= u.x <= hi across the line of centres u: beyond the
        # reach of body 2's support towards body 1 and body 1's towards body 2. An empty slab
        # separates the bodies; otherwise faces (and their planes) that miss the slab cannot bound
        # the overlap.
        uc = vec3(scalar(0.0), scalar(0.0), scalar(1.0))
        lo_c = -(r1_c + r2_c)
        hi_c = r1_c + r2_c
        if scalar(dist) > slack:
            uc = wp.normalize(pos_c)
            h_1 = support_c(shapes, v10, v11, uc)
            h_2 = support_c(shapes, v20, v21, -(rot_ct * uc))
            lo_c = wp.dot(uc, pos_c) - h_2 - slack
            hi_c = h_1 + slack
            if lo_c > hi_c:
                return scalar(0.0), zero3, zero3, zero3, zero3, zero3, zero3, 0

        # The rest, with the per-thread buffers, in a function of its own: Warp declares (and zero-fills)
        # a function's local buffers where it starts, and most separated candidates have left by now.
        return pair_pieces(
            shapes, s1, s2, in_a, xa64, xb64, q1, r2, pos, rot,
            pos_c, rot_c, r1_c, r2_c, slack, uc, lo_c, hi_c,
            f10, f11, f20, f21, v10, v11, v20, v21,
        )  # fmt: skip

    @wp.func
    def loop_edge(shapes: Shapes, f: int, e: int):
        # The edge from face_loop[e] to the next vertex of its face's loop, where f is the face of
        # entry e - 1 (the entries of a shape's loops follow each other, face after face): the face of
        # e, whether the edge runs from the lower vertex index to the higher (each edge is taken from
        # the one face where it does), and its vector (body frame, float64).
        if e == shapes.face_loop_start[f + 1]:
            f += 1
        nxt = e + 1
        if nxt == shapes.face_loop_start[f + 1]:
            nxt = shapes.face_loop_start[f]
        i0 = shapes.face_loop[e]
        i1 = shapes.face_loop[nxt]
        return f, i0 < i1, shapes.vert64[i1] - shapes.vert64[i0]

    @wp.func
    def edge_pair_overlap(shapes: Shapes, s1: int, s2: int, rot: mat33d, pos: vec3d, best: wp.float64):
        # The least of `best` and the overlaps along every cross product of an edge of body 1 and
        # an edge of body 2: with the face normals, the axes that hold the least separating
        # translation of two convex polyhedra. Each edge is taken once (from the face where it runs
        # from the lower vertex index to the higher).
        f = shapes.shape_face_start[s1]
        for e in range(shapes.face_loop_start[f], shapes.face_loop_start[shapes.shape_face_start[s1 + 1]]):
            f, first_1, e1 = loop_edge(shapes, f, e)
            if first_1:
                g = shapes.shape_face_start[s2]
                for ee in range(shapes.face_loop_start[g], shapes.face_loop_start[shapes.shape_face_start[s2 + 1]]):
                    g, first_2, e2 = loop_edge(shapes, g, ee)
                    if first_2:
                        e2 = rot * e2
                        axis = wp.cross(e1, e2)
                        norm = wp.length(axis)
                        # Parallel edges give no new axis (their cross product is noise).
                        if norm > wp.float64(1.0e-9) * wp.length(e1) * wp.length(e2):
                            o1, o2 = extent_overlaps(shapes, s1, s2, rot, pos, axis / norm)
                            best = wp.min(best, wp.min(o1, o2))
        return best

    @wp.func
    def pair_depth(shapes: Shapes, sa: int, sb: int, xa: transform, xb: transform):
        """Penetration depth [m] of the pair: the shortest translation that separates them, the
        least overlap of their extents over the separating-axis candidates (the face normals of
        both bodies and the cross products of their edges), 0 when they do not overlap. Float64
        inside whatever the precision."""
        xa64, qa64 = pose_to_f64(xa)
        xb64, qb64 = pose_to_f64(xb)
        r = wp.float64(shapes.shape_radius[sa] + shapes.shape_radius[sb])
        qa_inv = wp.quat_inverse(qa64)
        pos = wp.quat_rotate(qa_inv, xb64 - xa64)
        if wp.length_sq(pos) >= r * r:
            return scalar(0.0)
        rot = wp.quat_to_matrix(qa_inv * qb64)
        u, depth = least_penetration(shapes, sa, sb, rot, pos)
        depth = edge_pair_overlap(shapes, sa, sb, rot, pos, depth)
        return scalar(wp.max(depth, wp.float64(0.0)))

    return Geometry(
        scalar=scalar,
        vec3=vec3,
        vec4=vec4,
        transform=transform,
        quat=quat,
        shapes=Shapes,
        max_poly=max_poly,
        max_faces=max_faces,
        tol_rel=tol_rel,
        primitives=prim,
        pair_geometry=pair_geometry,
        pair_depth=pair_depth,
        pose_scalar=pose_scalar,
    )
