"""Initial overlaps of body pairs on the device: the separating-axis depth of each candidate pair of the first broad
phase, for scenes too large for the host's k-d tree search (:mod:`polydem.scene.overlaps`, whose test this is).

Per candidate pair (one body free, at least), in float64 whatever the run's precision: the overlap of the two bodies'
projections on each face normal of either body, on the line of their centres and, for shapes with few edge
directions, on the cross products of their edge directions; the smallest is the penetration depth, taken over the
thinner body's thickness along that axis (the first axis of least overlap, in the host test's order of axes). A pair
whose depth exceeds ``INITIAL_OVERLAP_WARNING`` of that thickness is written out (an atomic counter; an output too
small for them is detected and the test run again with room for all).
"""

from typing import Any

import numpy as np
import warp as wp
from polydem.kernels.broadphase import for_poses, pose_overloads

# Float64 throughout: the host test's arithmetic, so that the device and the host report the same overlaps.
INF = wp.constant(wp.float64(1.0e300))
# An axis of length 1e-9 or less is dropped, as the host test drops it.
AXIS_MIN = wp.constant(wp.float64(1.0e-9))


@wp.func
def support(vert: wp.array(dtype=wp.vec3d), v0: int, v1: int, q: wp.quatd, p: wp.vec3d, e: wp.vec3d):
    """The interval of a body's vertices (v0..v1, pose (p, q)) along the unit axis ``e``: (min, max) [m]."""
    local = wp.quat_rotate_inv(q, e)  # the axis in the body's frame: one rotation, not one a vertex
    lo = INF
    hi = -INF
    for v in range(v0, v1):
        s = wp.dot(vert[v], local)
        lo = wp.min(lo, s)
        hi = wp.max(hi, s)
    off = wp.dot(p, e)
    return wp.vec2d(lo + off, hi + off)


@wp.func
def face_axes(
    vert: wp.array(dtype=wp.vec3d),
    face_plane: wp.array(dtype=wp.vec4d),
    face_lo: wp.array(dtype=wp.float64),
    f0: int,
    f1: int,
    v0: int,
    v1: int,
    q1: wp.quatd,
    p1: wp.vec3d,
    q2: wp.quatd,
    p2: wp.vec3d,
    best_in: wp.vec2d,
):
    """The face normals of body 1 (faces f0..f1) against body 2's vertices (v0..v1), in body 1's frame:
    ``best_in`` (least overlap, the thinner thickness along its axis) updated where an axis overlaps less."""
    best = best_in
    d = p2 - p1  # body 2's centre from body 1's: no rounding of large world coordinates in the offsets
    for f in range(f0, f1):
        plane = face_plane[f]
        b = support(vert, v0, v1, q2, d, wp.quat_rotate(q1, wp.vec3d(plane[0], plane[1], plane[2])))
        ov = wp.min(plane[3] - b[0], b[1] - face_lo[f])
        if ov < best[0]:
            best = wp.vec2d(ov, wp.min(plane[3] - face_lo[f], b[1] - b[0]))
    return best


@wp.func
def world_axis(
    vert: wp.array(dtype=wp.vec3d),
    va0: int,
    va1: int,
    vb0: int,
    vb1: int,
    qa: wp.quatd,
    pa: wp.vec3d,
    qb: wp.quatd,
    pb: wp.vec3d,
    axis: wp.vec3d,
    best_in: wp.vec2d,
):
    """A world axis (not yet of unit length; dropped at AXIS_MIN or shorter) against both bodies' vertices."""
    length = wp.length(axis)
    if length <= AXIS_MIN:
        return best_in
    e = axis / length
    a = support(vert, va0, va1, qa, pa, e)
    b = support(vert, vb0, vb1, qb, pb, e)
    ov = wp.min(a[1] - b[0], b[1] - a[0])
    if ov < best_in[0]:
        return wp.vec2d(ov, wp.min(a[1] - a[0], b[1] - b[0]))
    return best_in


@wp.kernel(enable_backward=False)
def pair_overlap_kernel(
    # Model
    shape_vert_start: wp.array(dtype=int),
    shape_face_start: wp.array(dtype=int),
    shape_edge_start: wp.array(dtype=int),
    vert: wp.array(dtype=wp.vec3d),
    face_plane: wp.array(dtype=wp.vec4d),
    face_lo: wp.array(dtype=wp.float64),
    edge_dir: wp.array(dtype=wp.vec3d),
    max_edge_axes: int,
    shape_big: wp.array(dtype=int),
    body_shape: wp.array(dtype=int),
    body_flags: wp.array(dtype=int),
    threshold: wp.float64,
    # State in
    body_q: wp.array(dtype=Any),
    # Pairs
    pair_a: wp.array(dtype=int),
    pair_b: wp.array(dtype=int),
    pair_count: wp.array(dtype=int),
    # Out
    out_count: wp.array(dtype=int),
    out_body: wp.array(dtype=wp.vec2i),
    out_rel_depth: wp.array(dtype=wp.vec2d),
):
    t = wp.tid()
    if t >= pair_count[0]:
        return
    # The host test's order of a pair (polydem.scene.overlaps): a big body (BIG_RADIUS_RATIO times the median radius:
    # a container's slab) first, else the lower index first; the free one of the two is the record's body.
    i = pair_a[t]
    j = pair_b[t]
    sa = body_shape[i]
    sb = body_shape[j]
    if (shape_big[sb] != 0 and shape_big[sa] == 0) or (shape_big[sa] == shape_big[sb] and j < i):
        k = i
        i = j
        j = k
        k = sa
        sa = sb
        sb = k
    if body_flags[i] != 0 and body_flags[j] != 0:
        return
    # float32 poses (a float32 run) are widened: the test itself stays in float64
    pa = wp.vec3d(wp.transform_get_translation(body_q[i]))
    qa = wp.quatd(wp.transform_get_rotation(body_q[i]))
    pb = wp.vec3d(wp.transform_get_translation(body_q[j]))
    qb = wp.quatd(wp.transform_get_rotation(body_q[j]))
    va0 = shape_vert_start[sa]
    va1 = shape_vert_start[sa + 1]
    vb0 = shape_vert_start[sb]
    vb1 = shape_vert_start[sb + 1]
    best = wp.vec2d(INF, wp.float64(1.0))
    best = face_axes(
        vert, face_plane, face_lo, shape_face_start[sa], shape_face_start[sa + 1], vb0, vb1, qa, pa, qb, pb, best
    )
    # Apart along an axis (no overlap): the depth can only fall further, none to report.
    if best[0] <= wp.float64(0.0):
        return
    best = face_axes(
        vert, face_plane, face_lo, shape_face_start[sb], shape_face_start[sb + 1], va0, va1, qb, pb, qa, pa, best
    )
    if best[0] <= wp.float64(0.0):
        return
    best = world_axis(vert, va0, va1, vb0, vb1, qa, pa, qb, pb, pb - pa, best)
    ea0 = shape_edge_start[sa]
    ea1 = shape_edge_start[sa + 1]
    eb0 = shape_edge_start[sb]
    eb1 = shape_edge_start[sb + 1]
    if (ea1 - ea0) * (eb1 - eb0) <= max_edge_axes:
        for ea in range(ea0, ea1):
            da = wp.quat_rotate(qa, edge_dir[ea])
            for eb in range(eb0, eb1):
                if best[0] > wp.float64(0.0):
                    best = world_axis(
                        vert, va0, va1, vb0, vb1, qa, pa, qb, pb, wp.cross(da, wp.quat_rotate(qb, edge_dir[eb])), best
                    )
    rel = best[0] / best[1]
    if rel > threshold:
        # counted past the room, so that the caller knows how much to give the next launch
        slot = wp.atomic_add(out_count, 0, 1)
        if slot < out_body.shape[0]:
            if body_flags[i] == 0:
                out_body[slot] = wp.vec2i(i, j)
            else:
                out_body[slot] = wp.vec2i(j, i)
            out_rel_depth[slot] = wp.vec2d(rel, best[0])


pose_overloads(pair_overlap_kernel)


def launch_pair_overlaps(
    geometry, body_shape, body_flags, body_q, pair_a, pair_b, pair_count, capacity, threshold, room
):
    """Body pairs of the candidate list (``pair_a``, ``pair_b``, ``pair_count`` of at most ``capacity``) that overlap
    by more than ``threshold`` of the thinner body's thickness: ``(bodies (K, 2): the free one first, rel (K,),
    depth (K,) [m])`` on the host. ``geometry``: the shapes' arrays on the device
    (:class:`polydem.overlap_check.OverlapGeometry`). The output holds ``room`` records; where more overlap, the
    test runs again with room for all of them (none is dropped)."""
    device = body_q.device
    out_count = wp.zeros(1, dtype=int, device=device)
    while True:
        out_body = wp.empty(max(1, room), dtype=wp.vec2i, device=device)
        out_rel_depth = wp.empty(max(1, room), dtype=wp.vec2d, device=device)
        out_count.zero_()
        wp.launch(
            for_poses(pair_overlap_kernel, body_q),
            dim=capacity,
            inputs=[
                geometry.shapeset.shape_vert_start,
                geometry.shapeset.shape_face_start,
                geometry.shape_edge_start,
                geometry.shapeset.vert64,
                geometry.shapeset.face_plane64,
                geometry.face_lo,
                geometry.edge_dir,
                geometry.max_edge_axes,
                geometry.shape_big,
                body_shape,
                body_flags,
                wp.float64(threshold),
                body_q,
                pair_a,
                pair_b,
                pair_count,
            ],
            outputs=[out_count, out_body, out_rel_depth],
            device=device,
        )
        k = int(out_count.numpy()[0])
        if k <= room:
            break
        room = k
    if k == 0:
        return np.zeros((0, 2), dtype=np.int64), np.zeros(0), np.zeros(0)
    bodies = out_body[:k].numpy().astype(np.int64)
    rel_depth = out_rel_depth[:k].numpy()
    return bodies, rel_depth[:, 0].copy(), rel_depth[:, 1].copy()
