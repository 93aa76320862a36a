"""Contact geometry in Warp: the one place where polygons are clipped and overlaps integrated.

The pair kernel (:mod:`polydem.kernels.narrowphase`), the contact step and its diagnostics
(:mod:`polydem.kernels.forces`) and the batch API (:func:`polydem.overlap`) all call the
``@wp.func`` built here:

* primitives (:func:`make_primitives`): frame changes, signed plane distances, the
  Sutherland-Hodgman edge test and cut, the fan triangle, the cone from an apex over a facet,
  and :func:`plane_geometry`, a body against one half-space (a wall);
* :func:`make_geometry`: :func:`pair_geometry`, two convex polyhedra.

For a pair (A, B) one thread clips every face polygon of A by the face planes of B and every
face of B by the planes of A. The surviving pieces are the facets of the overlap polyhedron
A n B. Summed over A's facets k (area A_k, A's outward normal n_k, centroid c_k):

    S_A = sum A_k n_k              (= gradient of the overlap volume V under translation of A)
    M_A = sum A_k (c_k x n_k)      (about A's centre; = gradient of V under rotation of A)

and V with the overlap centroid come from the divergence theorem over all facets.

All clipping happens in A's body frame, so the numbers that meet in a subtraction are of the size
of the shapes whatever the distance from the world origin.

Coincident facets: when a face f of A and a face g of B lie in one plane (every vertex of both
faces within ``tol = tol_rel * min(r_A, r_B) + noise * (r_A + r_B)`` of the other face's plane;
tol_rel 2e-5 in float32 and 1e-10 in float64, noise a few units of rounding, 5e-7 and 1e-15) the
pair is decided once, by one function evaluated identically from both sides:

* same outward normal: f is not clipped by g (nor g by f) and both pieces count with weight 1/2,
  so the shared region is split half to each body and S_A + S_B = 0 holds to rounding;
* opposite outward normals: the bodies merely touch through that plane; both pieces are left out
  of S and M (the overlap there has a thickness below the tolerance, and the linear law would
  otherwise give a finite force at zero overlap) but still count for V, which stays exact.

The shape arrays reach every function as one :func:`shapes_struct` value (see
:class:`polydem.shapeset.ShapeSet` for the meaning of each array).
"""

import functools
from dataclasses import dataclass
from typing import Any

import warp as wp

# Relative tolerance of the coincident-face test, per precision (see the module docstring).
COINCIDENT_TOL = {wp.float32: 2.0e-5, wp.float64: 1.0e-10}
# Plus a few units of rounding of the coordinates, which grow with the larger body (a grain on a
# container wall meets the wall's far corners in its frame).
COORDINATE_NOISE = {wp.float32: 5.0e-7, wp.float64: 1.0e-15}
# Cheap pre-filter before the exact coincidence test: normals within about 2.5 degrees.
PARALLEL_COS = 0.999


@functools.cache
def shapes_struct(scalar):
    """The ``wp.struct`` holding a shape set's arrays for one precision (``wp.float32`` or ``wp.float64``)."""
    vec3 = wp.types.vector(3, scalar)
    vec4 = wp.types.vector(4, scalar)
    fields = {
        "shape_vert_start": wp.array(dtype=int),
        "shape_face_start": wp.array(dtype=int),
        "shape_radius": wp.array(dtype=scalar),
        "face_plane": wp.array(dtype=vec4),
        "face_sphere": wp.array(dtype=vec4),
        "face_loop_start": wp.array(dtype=int),
        "face_loop": wp.array(dtype=int),
        "vert": wp.array(dtype=vec3),
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
    plane_to_frame: Any
    point_to_frame: Any
    plane_distance: Any
    crosses: Any
    edge_cut: Any
    support: Any
    all_outside: Any
    sphere_misses: Any
    twice_area: Any
    fan_add: Any
    fan_push: Any
    fan_close: Any
    cone: Any
    plane_geometry: Any


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


@functools.cache
def make_primitives(scalar) -> Primitives:
    """Frame changes, plane tests, the clipping step, fan triangles, cones and the wall overlap."""
    vec3 = wp.types.vector(3, scalar)
    vec4 = wp.types.vector(4, scalar)
    mat33 = wp.types.matrix(shape=(3, 3), dtype=scalar)
    transform = wp.types.transformation(scalar)
    Shapes = shapes_struct(scalar)
    zero3 = wp.constant(vec3(scalar(0.0), scalar(0.0), scalar(0.0)))

    @wp.func
    def plane_to_frame(plane: vec4, rot: mat33, pos: vec3):
        # A plane n.x = d of B, expressed in A's frame where B's points are rot x + pos.
        n = rot * vec3(plane[0], plane[1], plane[2])
        return n, plane[3] + wp.dot(n, pos)

    @wp.func
    def point_to_frame(rot: mat33, pos: vec3, x: vec3):
        # A point of B in A's frame.
        return rot * x + pos

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
        # Where the edge prev -> v, of signed distances s_prev and s, meets the plane.
        return prev + (s_prev / (s_prev - s)) * (v - prev)

    @wp.func
    def support(vert: wp.array(dtype=vec3), v0: int, v1: int, u: vec3, floor: scalar):
        # The reach of the vertices v0 <= i < v1 along u (the largest u.x), at least `floor`.
        h = floor
        for iv in range(v0, v1):
            h = wp.max(h, wp.dot(u, vert[iv]))
        return h

    @wp.func
    def all_outside(vert: wp.array(dtype=vec3), v0: int, v1: int, n: vec3, d: scalar):
        # Whether every vertex v0 <= i < v1 lies beyond the plane n.x = d: a separating plane.
        for iv in range(v0, v1):
            if wp.dot(n, vert[iv]) <= d:
                return False
        return True

    @wp.func
    def sphere_misses(c: vec3, r: scalar, u: vec3, lo: scalar, hi: scalar, centre: vec3, reach: scalar):
        # Whether the sphere (c, r) around a face misses the slab lo <= u.x <= hi or the other
        # body's bounding sphere (centre, reach): then the face cannot bound the overlap.
        uc = wp.dot(u, c)
        return uc + r < lo or uc - r > hi or wp.length_sq(c - centre) > (r + reach) * (r + reach)

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
    def plane_geometry(shapes: Shapes, s: int, xa: transform, normal: vec3, offset: scalar):
        """Overlap of shape ``s`` at pose ``xa`` with the half-space n.x <= offset (a wall).

        Returns (V, V * centroid, S_A, M_A about x_A), positions relative to x_A, world axes.
        Each face is clipped by the one plane while its vertices stream past, so no polygon buffer.
        """
        q = wp.transform_get_rotation(xa)
        dd = offset - wp.dot(normal, wp.transform_get_translation(xa))
        if dd <= -shapes.shape_radius[s]:
            return scalar(0.0), zero3, zero3, zero3
        nb = wp.quat_rotate_inv(q, normal)
        origin = dd * nb  # on the plane, so the cap facet's cone is flat and adds nothing
        vol = scalar(0.0)
        vol_c = zero3
        s_a = zero3
        m_a = zero3
        for f in range(shapes.shape_face_start[s], shapes.shape_face_start[s + 1]):
            pl = shapes.face_plane[f]
            nf = vec3(pl[0], pl[1], pl[2])
            begin = shapes.face_loop_start[f]
            count = shapes.face_loop_start[f + 1] - begin
            sum_a2 = scalar(0.0)
            sum_c = zero3
            emitted = int(0)
            first = zero3
            prev = zero3
            vp = shapes.vert[shapes.face_loop[begin + count - 1]]
            sp = plane_distance(nb, dd, vp)
            for k in range(count):
                v = shapes.vert[shapes.face_loop[begin + k]]
                sv = plane_distance(nb, dd, v)
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
                dv, dv_c = cone(area, area_c, pl, origin)
                vol += dv
                vol_c += dv_c
        return vol, wp.quat_rotate(q, vol_c), wp.quat_rotate(q, s_a), wp.quat_rotate(q, m_a)

    return Primitives(
        scalar=scalar,
        vec3=vec3,
        vec4=vec4,
        shapes=Shapes,
        plane_to_frame=plane_to_frame,
        point_to_frame=point_to_frame,
        plane_distance=plane_distance,
        crosses=crosses,
        edge_cut=edge_cut,
        support=support,
        all_outside=all_outside,
        sphere_misses=sphere_misses,
        twice_area=twice_area,
        fan_add=fan_add,
        fan_push=fan_push,
        fan_close=fan_close,
        cone=cone,
        plane_geometry=plane_geometry,
    )


@functools.cache
def make_geometry(scalar, max_poly: int, max_faces: int, coincident_tol: float | None = None) -> Geometry:
    """:func:`pair_geometry` for one precision and polygon capacity.

    Args:
        scalar: ``wp.float32`` or ``wp.float64``.
        max_poly: capacity of the per-thread polygon buffer (vertices of one clipped facet). A
            facet that would exceed it raises the returned ``overflow`` flag; the host then
            rebuilds with a larger capacity and runs again.
        max_faces: the most faces of any shape in use (capacity of the per-thread plane lists).
        coincident_tol: relative tolerance of the coincident-face test (default per precision).
    """
    prim = make_primitives(scalar)
    vec3 = prim.vec3
    vec4 = prim.vec4
    mat33 = wp.types.matrix(shape=(3, 3), dtype=scalar)
    quat = wp.types.quaternion(scalar)
    transform = wp.types.transformation(scalar)
    Shapes = prim.shapes
    poly_t = wp.types.matrix(shape=(2 * max_poly, 3), dtype=scalar)
    planes_t = wp.types.matrix(shape=(max_faces, 4), dtype=scalar)
    ids_t = wp.types.vector(length=max_faces, dtype=int)
    tol_rel = float(COINCIDENT_TOL[scalar] if coincident_tol is None else coincident_tol)
    noise_rel = float(COORDINATE_NOISE[scalar])
    parallel_cos = PARALLEL_COS
    plane_to_frame = prim.plane_to_frame
    point_to_frame = prim.point_to_frame
    plane_distance = prim.plane_distance
    crosses = prim.crosses
    edge_cut = prim.edge_cut
    fan_add = prim.fan_add
    fan_close = prim.fan_close
    support = prim.support
    all_outside = prim.all_outside
    sphere_misses = prim.sphere_misses
    cone = prim.cone

    @wp.func
    def coplanar_relation(
        shapes: Shapes,
        fa: int,
        gb: int,
        rot: mat33,
        pos: vec3,
        tol: scalar,
    ):
        # Decides whether face fa of A and face gb of B share a plane: +1 same outward normal,
        # -1 opposite normals, 0 otherwise. Evaluated in A's frame with the same expressions
        # whichever side calls it, so both sides reach the same decision bit for bit.
        pa = shapes.face_plane[fa]
        na = vec3(pa[0], pa[1], pa[2])
        nb, db = plane_to_frame(shapes.face_plane[gb], rot, pos)
        c = wp.dot(na, nb)
        if wp.abs(c) < scalar(parallel_cos):
            return 0
        for k in range(shapes.face_loop_start[fa], shapes.face_loop_start[fa + 1]):
            if wp.abs(plane_distance(nb, db, shapes.vert[shapes.face_loop[k]])) > tol:
                return 0
        for k in range(shapes.face_loop_start[gb], shapes.face_loop_start[gb + 1]):
            if wp.abs(plane_distance(na, pa[3], point_to_frame(rot, pos, shapes.vert[shapes.face_loop[k]]))) > tol:
                return 0
        if c > scalar(0.0):
            return 1
        return -1

    @wp.func
    def pair_geometry_in_a(
        shapes: Shapes,
        sa: int,
        sb: int,
        xa: transform,
        xb: transform,
    ):
        """:func:`pair_geometry`, clipping in A's frame."""
        zero3 = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        ra = shapes.shape_radius[sa]
        rb = shapes.shape_radius[sb]
        qa = wp.transform_get_rotation(xa)
        qa_inv = wp.quat_inverse(qa)
        pos = wp.quat_rotate(qa_inv, wp.transform_get_translation(xb) - wp.transform_get_translation(xa))
        dist2 = wp.length_sq(pos)
        if dist2 >= (ra + rb) * (ra + rb):
            return scalar(0.0), zero3, zero3, zero3, zero3, zero3, 0
        rot = wp.quat_to_matrix(qa_inv * wp.transform_get_rotation(xb))
        rot_t = wp.transpose(rot)
        pos_b = -(rot_t * pos)  # A's centre in B's frame
        tol = scalar(tol_rel) * wp.min(ra, rb) + scalar(noise_rel) * (ra + rb)
        fa0 = shapes.shape_face_start[sa]
        fa1 = shapes.shape_face_start[sa + 1]
        fb0 = shapes.shape_face_start[sb]
        fb1 = shapes.shape_face_start[sb + 1]
        va0 = shapes.shape_vert_start[sa]
        va1 = shapes.shape_vert_start[sa + 1]
        vb0 = shapes.shape_vert_start[sb]
        vb1 = shapes.shape_vert_start[sb + 1]

        # The overlap lies in the slab lo <= u.x <= hi across the line of centres u: beyond the
        # reach of B's support towards A and A's towards B. An empty slab separates the bodies;
        # otherwise faces (and their planes) that miss the slab cannot bound the overlap.
        dist = wp.sqrt(dist2)
        u = vec3(scalar(0.0), scalar(0.0), scalar(1.0))
        lo = -(ra + rb)
        hi = ra + rb
        if dist > tol:
            u = pos / dist
            h_a = support(shapes.vert, va0, va1, u, -(ra + rb))
            h_b = support(shapes.vert, vb0, vb1, -(rot_t * u), -(ra + rb))
            lo = dist - h_b - tol
            hi = h_a + tol
            if lo > hi:
                return scalar(0.0), zero3, zero3, zero3, zero3, zero3, 0

        # Separating face planes, by bounding spheres first and exactly (all of the other body's
        # vertices outside) only for planes the other body's centre lies outside of. Meanwhile find
        # where the line of centres leaves A (tau_a, as a fraction of the way from A's centre to
        # B's) and enters B (tau_b): the cones that integrate V start from the middle of that
        # stretch, inside the overlap whenever the line crosses it, so the cone volumes do not
        # cancel and V and its centroid keep their precision for shallow overlaps.
        tau_a = scalar(1.0)
        tau_b = scalar(0.0)
        ids_a = ids_t()
        num_a = int(0)
        for f in range(fa0, fa1):
            pl = shapes.face_plane[f]
            n = vec3(pl[0], pl[1], pl[2])
            sigma = wp.dot(n, pos)
            if sigma * tau_a > pl[3]:  # d / sigma < tau_a: the line leaves A earlier here
                tau_a = pl[3] / sigma
            s = sigma - pl[3]
            if s > rb:
                return scalar(0.0), zero3, zero3, zero3, zero3, zero3, 0
            if s > scalar(0.0):
                # The other body's centre lies outside: is the plane separating?
                if all_outside(shapes.vert, vb0, vb1, rot_t * n, pl[3] - wp.dot(n, pos)):
                    return scalar(0.0), zero3, zero3, zero3, zero3, zero3, 0
            if s <= -rb:
                continue  # B lies wholly inside this plane: the face cannot reach B
            sph = shapes.face_sphere[f]
            if sphere_misses(vec3(sph[0], sph[1], sph[2]), sph[3], u, lo, hi, pos, rb):
                continue
            ids_a[num_a] = f
            num_a += 1
        planes_b = planes_t()
        ids_b = ids_t()
        num_b = int(0)
        for g in range(fb0, fb1):
            pl = shapes.face_plane[g]
            n = vec3(pl[0], pl[1], pl[2])
            sigma = wp.dot(n, pos_b)
            if sigma * (scalar(1.0) - tau_b) > pl[3]:  # 1 - d / sigma > tau_b: it enters B later here
                tau_b = scalar(1.0) - pl[3] / sigma
            s = sigma - pl[3]
            if s > ra:
                return scalar(0.0), zero3, zero3, zero3, zero3, zero3, 0
            na, da = plane_to_frame(pl, rot, pos)
            if s > scalar(0.0):
                if all_outside(shapes.vert, va0, va1, na, da):
                    return scalar(0.0), zero3, zero3, zero3, zero3, zero3, 0
            if s <= -ra:
                continue
            sph = shapes.face_sphere[g]
            if sphere_misses(point_to_frame(rot, pos, vec3(sph[0], sph[1], sph[2])), sph[3], u, lo, hi, zero3, ra):
                continue
            planes_b[num_b] = vec4(na[0], na[1], na[2], da)
            ids_b[num_b] = g
            num_b += 1

        origin = pos * (scalar(0.5) * (tau_a + tau_b))
        if tau_b > tau_a:
            # The line of centres misses the overlap (it leaves A before it enters B: a body lying
            # on a big face of the other, away from its centre). The apex would lie outside the
            # overlap, up to metres from it, and in float32 the facets close only to ~1e-3 of their
            # area: that gap times the apex's distance came out as V errors of 10-100x for shallow
            # face contacts of a cube on a floor box (and flickering forces). Take instead the foot
            # of B's centre on the active plane of A it lies farthest above: within B's sphere, and
            # on the contact face, whose cones then vanish exactly.
            s_top = -(ra + rb)
            foot = pos
            for j in range(num_a):
                pl = shapes.face_plane[ids_a[j]]
                n = vec3(pl[0], pl[1], pl[2])
                sj = wp.dot(n, pos) - pl[3]
                if sj > s_top:
                    s_top = sj
                    foot = pos - sj * n
            origin = pos
            if s_top > scalar(0.0):
                origin = foot
        vol = scalar(0.0)
        vol_c = zero3
        s_a = zero3
        m_a = zero3
        s_b = zero3
        m_b = zero3
        overflow = int(0)
        # Clip each active face polygon by the other body's active planes and integrate the
        # surviving piece. This loop is written out here rather than in a helper called per face:
        # a @wp.func takes its arguments by value, and the per-thread buffers (polygon, planes, ids)
        # live in local memory, so a call per face copied and zero-filled them again each time.
        # One polygon buffer serves every face; its halves [0, max_poly) and [max_poly, 2 max_poly)
        # take turns as input and output of the Sutherland-Hodgman passes.
        poly = poly_t()
        for j in range(num_a + num_b):
            face_is_a = j < num_a
            face = int(0)
            num_planes = int(0)
            if face_is_a:
                face = ids_a[j]
                num_planes = num_b
            else:
                face = ids_b[j - num_a]
                num_planes = num_a
            begin = shapes.face_loop_start[face]
            count = shapes.face_loop_start[face + 1] - begin
            sph = shapes.face_sphere[face]
            centre = vec3(sph[0], sph[1], sph[2])
            pf = shapes.face_plane[face]
            nf = vec3(pf[0], pf[1], pf[2])
            if not face_is_a:
                centre = point_to_frame(rot, pos, centre)
                nf = rot * nf
            for k in range(count):
                v = shapes.vert[shapes.face_loop[begin + k]]
                if not face_is_a:
                    v = point_to_frame(rot, pos, v)
                poly[k] = v
            weight = scalar(1.0)
            surface = int(1)  # 0: a face merely touching an opposite face of the other body
            alive = bool(True)
            cur = int(0)  # row offset of the live polygon in `poly`: 0 or max_poly
            for i in range(num_planes):
                pl = vec4()
                plane_id = int(0)
                if face_is_a:
                    pl = planes_b[i]
                    plane_id = ids_b[i]
                else:
                    plane_id = ids_a[i]
                    pl = shapes.face_plane[plane_id]  # A's own planes are read where they are
                n = vec3(pl[0], pl[1], pl[2])
                d = pl[3]
                dist = plane_distance(n, d, centre)
                if dist <= -sph[3]:
                    continue  # the whole face lies inside this plane
                if dist > sph[3]:
                    alive = False
                    break
                if wp.abs(wp.dot(nf, n)) >= scalar(parallel_cos):
                    # Coincident or touching faces: decided by one function evaluated the same way
                    # from both sides (A's face first), so both sides agree bit for bit.
                    rel = int(0)
                    if face_is_a:
                        rel = coplanar_relation(shapes, face, plane_id, rot, pos, tol)
                    else:
                        rel = coplanar_relation(shapes, plane_id, face, rot, pos, tol)
                    if rel == 1:
                        weight = scalar(0.5)
                        continue
                    if rel == -1:
                        surface = int(0)
                        continue
                # Sutherland-Hodgman against n.x <= d, from rows [cur, cur+count) into the other half.
                out = max_poly - cur
                n_out = int(0)
                full = int(0)
                prev = poly[cur + count - 1]
                s_prev = plane_distance(n, d, prev)
                for k in range(count):
                    v = poly[cur + k]
                    sk = plane_distance(n, d, v)
                    if crosses(s_prev, sk):
                        if n_out >= max_poly:
                            full = 1
                            break
                        poly[out + n_out] = edge_cut(prev, s_prev, v, sk)
                        n_out += 1
                    if sk <= scalar(0.0):
                        if n_out >= max_poly:
                            full = 1
                            break
                        poly[out + n_out] = v
                        n_out += 1
                    prev = v
                    s_prev = sk
                if full != 0:
                    overflow = 1
                if n_out < 3 or full != 0:
                    alive = False
                    break
                cur = out
                count = n_out
            if not alive:
                continue
            # Fan triangulation: facet area and area-weighted centroid.
            p0 = poly[cur]
            sum_a2 = scalar(0.0)
            sum_c = zero3
            for k in range(1, count - 1):
                sum_a2, sum_c = fan_add(p0, poly[cur + k], poly[cur + k + 1], nf, sum_a2, sum_c)
            area, area_c = fan_close(sum_a2, sum_c, weight)
            plane = vec4()
            if face_is_a:
                plane = pf
            else:
                plane = planes_b[j - num_a]
            dv, dv_c = cone(area, area_c, plane, origin)
            vol += dv
            vol_c += dv_c
            if surface != 0:
                n = vec3(plane[0], plane[1], plane[2])
                if face_is_a:
                    s_a += area * n
                    m_a += wp.cross(area_c, n)
                else:
                    s_b += area * n
                    m_b += wp.cross(area_c, n)
        rot_a = wp.quat_to_matrix(qa)
        return vol, rot_a * vol_c, rot_a * s_a, rot_a * m_a, rot_a * s_b, rot_a * m_b, overflow

    @wp.func
    def pair_geometry(shapes: Shapes, sa: int, sb: int, xa: transform, xb: transform):
        """Overlap geometry of shape ``sa`` at pose ``xa`` and shape ``sb`` at pose ``xb``.

        Returns ``(V, first moment of V, S_A, M_A, S_B, M_B, overflow)``, with vectors in world
        axes and every position relative to A's centre (the first moment is V times the overlap
        centroid; M_A and M_B are about A's centre).

        The clipping runs in the frame of the larger body, whose big faces are then exact: in the
        small body's frame the far corners of, say, a container wall carry rounding that moves
        the wall's face polygon off its plane (in float32 a 1 cm cube on a 6 m floor had S wrong
        by 17% that way).
        """
        in_a = shapes.shape_radius[sb] <= shapes.shape_radius[sa]
        s1 = sa
        s2 = sb
        x1 = xa
        x2 = xb
        if not in_a:
            s1 = sb
            s2 = sa
            x1 = xb
            x2 = xa
        vol, vol_c, s_1, m_1, s_2, m_2, overflow = pair_geometry_in_a(shapes, s1, s2, x1, x2)
        if in_a:
            return vol, vol_c, s_1, m_1, s_2, m_2, overflow
        # Positions came relative to B's centre: move them to A's.
        r = wp.transform_get_translation(xb) - wp.transform_get_translation(xa)
        return vol, vol_c + vol * r, s_2, m_2 + wp.cross(r, s_2), s_1, m_1 + wp.cross(r, s_1), overflow

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
    )
