"""Ray casting of instanced convex polyhedra: one thread per pixel, for pictures of a state.

Camera. A pinhole camera at ``eye``; the ray of pixel (row i, column j) of an image of H x W
pixels leaves the eye along ``normalize(forward + u * right + v * up)`` with
``u = 2 (j + 0.5) / W - 1`` and ``v = 1 - 2 (i + 0.5) / H``; ``right`` and ``up`` come scaled by the
tangents of the half fields of view, so the image covers u, v in [-1, 1]. Ray parameters t are
distances from the eye [m] (the direction is a unit vector).

Broad culling. One Warp BVH over the boxes ``x_b -+ r_b`` of the bodies' bounding spheres (centre
and radius about the centroid, so the boxes do not depend on the orientation); a ray walks it with
``bvh_query_ray`` and the search distance shrinks to the nearest hit found so far. The tree holds
the listed bodies only (``bvh_body`` maps a tree item to its body), so hidden bodies cost nothing.

Exact intersection. A convex polyhedron is the intersection of its faces' half-spaces
``n . x <= d`` (body frame). The ray, taken into the body frame, enters half-space f at
``t = (d - n . o) / (n . dir)`` when ``n . dir < 0`` and leaves it there when ``n . dir > 0``; a ray
parallel to a face misses when its origin is outside that face's plane. With t_enter the largest
entering and t_exit the smallest leaving parameter, the ray meets the body iff
``t_enter <= t_exit``, at t_enter, where the normal is the entering face's normal. A body that
holds the eye is not drawn (t_enter < 0).

Walls. Infinite planes ``n . x = offset`` seen from the side n points to (the simulated side) get
a light checker whose contrast fades with the distance; planes seen from behind are not drawn, so
the walls of a box made of planes never hide its content from a camera outside.

Mesh walls. Triangles in world coordinates (posed on the host), counter-clockwise seen from the
front (the simulated side), found through a second Warp BVH over their boxes and hit by the
Moller-Trumbore test; like the planes, a triangle seen from behind is not drawn, so the near side of
a closed drum lets the camera see the grains inside, and its far side shows behind them.

Shading. Lambert with one directional light (``light`` points towards the light) plus an ambient
term and a weak fill from the camera, colour per body; an optional shadow ray from each lit
point towards the light (bodies cast shadows, planes do not). Misses get a sky gradient.

Outputs per pixel: colour (float RGB in [0, 1]), depth t [m] (``MISS_DEPTH`` for the sky) and the
hit item: the body index, ``-2 - p`` for plane p, ``-2 - P - w`` for mesh wall w (P planes), -1
for the sky.

Layout of this file: ``@wp.func`` helpers, the kernels, then the plain launch functions.
"""

import numpy as np
import warp as wp

MISS_DEPTH = wp.constant(1.0e30)
NO_HIT = wp.constant(-1)

AMBIENT = wp.constant(0.30)
FILL = wp.constant(0.12)
DIFFUSE = wp.constant(0.62)

# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------


@wp.func
def ray_convex(
    o: wp.vec3,
    d: wp.vec3,
    face_plane: wp.array(dtype=wp.vec4),
    f_begin: int,
    f_end: int,
    t_max: float,
):
    """Clips the ray o + t d (body frame) by the faces f_begin..f_end-1 over t <= t_max.

    Returns (t_enter, t_exit, entering face); the ray meets the body iff t_enter <= t_exit. The
    entering face is -1 when no face enters (only possible for an unbounded set)."""
    t_enter = float(-MISS_DEPTH)
    t_exit = float(t_max)
    face = int(-1)
    for f in range(f_begin, f_end):
        p = face_plane[f]
        n = wp.vec3(p[0], p[1], p[2])
        denom = wp.dot(n, d)
        gap = p[3] - wp.dot(n, o)  # >= 0 when o is on the inner side of this face
        if denom < 0.0:
            t = gap / denom
            if t > t_enter:
                t_enter = t
                face = f
        elif denom > 0.0:
            t = gap / denom
            if t < t_exit:
                t_exit = t
        elif gap < 0.0:
            t_exit = float(-MISS_DEPTH)
        if t_enter > t_exit:
            break
    return t_enter, t_exit, face


@wp.func
def ray_front_triangle(o: wp.vec3, d: wp.vec3, a: wp.vec3, b: wp.vec3, c: wp.vec3, t_max: float):
    """Parameter t of the ray o + t d on triangle abc seen from its front (counter-clockwise side),
    ``t_max`` when it misses, is seen from behind or lies outside 0 < t < t_max."""
    e1 = b - a
    e2 = c - a
    p = wp.cross(d, e2)
    det = wp.dot(e1, p)  # = -d . (e1 x e2): positive when the ray meets the front
    t_hit = float(t_max)
    if det > 0.0:
        s = o - a
        u = wp.dot(s, p)
        if u >= 0.0 and u <= det:
            q = wp.cross(s, e1)
            v = wp.dot(d, q)
            if v >= 0.0 and u + v <= det:
                t = wp.dot(e2, q) / det
                if t > 0.0 and t < t_max:
                    t_hit = t
    return t_hit


@wp.func
def checker(x: wp.vec3, u: wp.vec3, v: wp.vec3):
    """0 or 1 on the squares of a checker with axes u, v (scaled by 1 / square size)."""
    a = int(wp.floor(wp.dot(x, u)))
    b = int(wp.floor(wp.dot(x, v)))
    return float((a + b) & 1)


@wp.func
def sky(d: wp.vec3, up: wp.vec3):
    s = wp.clamp(wp.dot(d, up), 0.0, 1.0)
    horizon = wp.vec3(0.93, 0.94, 0.96)
    zenith = wp.vec3(0.62, 0.72, 0.86)
    return horizon + (zenith - horizon) * wp.sqrt(s)


@wp.func
def shade(albedo: wp.vec3, n: wp.vec3, d: wp.vec3, light: wp.vec3, lit: float):
    """Lambert with ambient and a camera fill; lit is 0 in shadow and 1 in the light."""
    ndl = wp.max(wp.dot(n, light), 0.0)
    facing = wp.max(-wp.dot(n, d), 0.0)
    k = AMBIENT + FILL * facing + DIFFUSE * ndl * lit
    c = albedo * k
    return wp.vec3(wp.min(c[0], 1.0), wp.min(c[1], 1.0), wp.min(c[2], 1.0))


@wp.func
def occluded(
    bvh_id: wp.uint64,
    origin: wp.vec3,
    light: wp.vec3,
    skip: int,
    shape_face_start: wp.array(dtype=int),
    face_plane: wp.array(dtype=wp.vec4),
    body_shape: wp.array(dtype=int),
    bvh_body: wp.array(dtype=int),
    body_q: wp.array(dtype=wp.transform),
):
    """Whether a body other than ``skip`` meets the ray origin + t light, t > 0."""
    found = bool(False)
    query = wp.bvh_query_ray(bvh_id, origin, light)
    item = int(0)
    while wp.bvh_query_next(query, item):
        b = bvh_body[item]
        if b != skip:
            tf = body_q[b]
            q = wp.transform_get_rotation(tf)
            o = wp.quat_rotate_inv(q, origin - wp.transform_get_translation(tf))
            d = wp.quat_rotate_inv(q, light)
            s = body_shape[b]
            t_enter, t_exit, face = ray_convex(
                o, d, face_plane, shape_face_start[s], shape_face_start[s + 1], MISS_DEPTH
            )
            if t_enter <= t_exit and t_exit > 0.0:
                found = True
                break
    return found


# ---------------------------------------------------------------------------------------------
# Kernels
# ---------------------------------------------------------------------------------------------


@wp.kernel(enable_backward=False)
def body_bounds_kernel(
    # Model
    shape_radius: wp.array(dtype=float),
    body_shape: wp.array(dtype=int),
    bvh_body: wp.array(dtype=int),
    # State in
    body_q: wp.array(dtype=wp.transform),
    # Out
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
):
    """Box of the bounding sphere of tree item k (body ``bvh_body[k]``)."""
    k = wp.tid()
    b = bvh_body[k]
    x = wp.transform_get_translation(body_q[b])
    r = shape_radius[body_shape[b]]
    # A relative pad keeps float32 rounding of the box from cutting a grazing ray's hit.
    pad = r * 1.0001 + 1.0e-7 * wp.length(x)
    e = wp.vec3(pad, pad, pad)
    lowers[k] = x - e
    uppers[k] = x + e


@wp.kernel(enable_backward=False)
def triangle_bounds_kernel(
    # Model
    tri_vertex: wp.array(dtype=wp.vec3),
    # Out
    lowers: wp.array(dtype=wp.vec3),
    uppers: wp.array(dtype=wp.vec3),
):
    """Box of triangle k (vertices ``tri_vertex[3k .. 3k+2]``), padded against float32 rounding."""
    k = wp.tid()
    a = tri_vertex[3 * k]
    b = tri_vertex[3 * k + 1]
    c = tri_vertex[3 * k + 2]
    lo = wp.min(wp.min(a, b), c)
    hi = wp.max(wp.max(a, b), c)
    pad = 1.0e-6 * wp.length(hi - lo) + 1.0e-7 * (wp.length(lo) + wp.length(hi))
    e = wp.vec3(pad, pad, pad)
    lowers[k] = lo - e
    uppers[k] = hi + e


@wp.kernel(enable_backward=False)
def raycast_kernel(
    # Model
    shape_face_start: wp.array(dtype=int),
    face_plane: wp.array(dtype=wp.vec4),
    body_shape: wp.array(dtype=int),
    body_color: wp.array(dtype=wp.vec3),
    bvh_body: wp.array(dtype=int),
    plane_normal: wp.array(dtype=wp.vec3),
    plane_offset: wp.array(dtype=float),
    plane_u: wp.array(dtype=wp.vec3),
    plane_v: wp.array(dtype=wp.vec3),
    tri_vertex: wp.array(dtype=wp.vec3),
    tri_wall: wp.array(dtype=int),
    tri_bvh_id: wp.uint64,
    # State in
    body_q: wp.array(dtype=wp.transform),
    bvh_id: wp.uint64,
    # Camera and light
    eye: wp.vec3,
    forward: wp.vec3,
    right: wp.vec3,
    up: wp.vec3,
    world_up: wp.vec3,
    light: wp.vec3,
    shadows: int,
    shadow_offset: float,
    fade_distance: float,
    # Out
    color: wp.array2d(dtype=wp.vec3),
    depth: wp.array2d(dtype=float),
    hit: wp.array2d(dtype=int),
):
    i, j = wp.tid()
    height = color.shape[0]
    width = color.shape[1]
    u = 2.0 * (float(j) + 0.5) / float(width) - 1.0
    v = 1.0 - 2.0 * (float(i) + 0.5) / float(height)
    d = wp.normalize(forward + u * right + v * up)

    best = float(MISS_DEPTH)
    item = int(NO_HIT)
    normal = wp.vec3(0.0, 0.0, 0.0)

    # Walls first: they bound the search of the bodies.
    for p in range(plane_offset.shape[0]):
        n = plane_normal[p]
        denom = wp.dot(n, d)
        if denom < 0.0:
            t = (plane_offset[p] - wp.dot(n, eye)) / denom
            if t > 0.0 and t < best:
                best = t
                item = -2 - p
                normal = n
    num_planes = plane_offset.shape[0]
    if tri_wall.shape[0] > 0:
        query_t = wp.bvh_query_ray(tri_bvh_id, eye, d)
        k_t = int(0)
        while wp.bvh_query_next(query_t, k_t, best):
            ta = tri_vertex[3 * k_t]
            tb = tri_vertex[3 * k_t + 1]
            tc = tri_vertex[3 * k_t + 2]
            t_tri = ray_front_triangle(eye, d, ta, tb, tc, best)
            if t_tri < best:
                best = t_tri
                item = -2 - num_planes - tri_wall[k_t]
                normal = wp.normalize(wp.cross(tb - ta, tc - ta))

    if bvh_body.shape[0] > 0:
        query = wp.bvh_query_ray(bvh_id, eye, d)
        k = int(0)
        while wp.bvh_query_next(query, k, best):
            b = bvh_body[k]
            tf = body_q[b]
            q = wp.transform_get_rotation(tf)
            o_b = wp.quat_rotate_inv(q, eye - wp.transform_get_translation(tf))
            d_b = wp.quat_rotate_inv(q, d)
            s = body_shape[b]
            t_enter, t_exit, face = ray_convex(o_b, d_b, face_plane, shape_face_start[s], shape_face_start[s + 1], best)
            if face >= 0 and t_enter >= 0.0 and t_enter <= t_exit and t_enter < best:
                best = t_enter
                item = b
                fp = face_plane[face]
                normal = wp.quat_rotate(q, wp.vec3(fp[0], fp[1], fp[2]))

    c = sky(d, world_up)
    if item != NO_HIT:
        x = eye + best * d
        albedo = wp.vec3(0.0, 0.0, 0.0)
        skip = int(NO_HIT)
        origin = x
        if item >= 0:
            albedo = body_color[item]
            skip = item
        else:
            p = -2 - item
            chk = float(0.5)
            if p < num_planes:
                chk = checker(x, plane_u[p], plane_v[p])
            contrast = 1.0 / (1.0 + (best / fade_distance) * (best / fade_distance))
            albedo = wp.vec3(0.80, 0.80, 0.79) + wp.vec3(0.08, 0.08, 0.08) * ((chk - 0.5) * contrast)
            origin = x + normal * shadow_offset
        lit = float(1.0)
        if shadows != 0 and wp.dot(normal, light) > 0.0 and bvh_body.shape[0] > 0:
            if occluded(bvh_id, origin, light, skip, shape_face_start, face_plane, body_shape, bvh_body, body_q):
                lit = 0.0
        c = shade(albedo, normal, d, light, lit)

    color[i, j] = c
    depth[i, j] = best
    hit[i, j] = item


# ---------------------------------------------------------------------------------------------
# Launch functions
# ---------------------------------------------------------------------------------------------


def _bounds_bvh(bounds_kernel, count, inputs, device):
    """A ``wp.Bvh`` over the boxes that ``bounds_kernel`` writes for ``count`` items, and its id
    (None and 0 where there are none)."""
    if count == 0:
        return None, wp.uint64(0)
    lowers = wp.empty(count, dtype=wp.vec3, device=device)
    uppers = wp.empty(count, dtype=wp.vec3, device=device)
    wp.launch(bounds_kernel, dim=count, inputs=inputs, outputs=[lowers, uppers], device=device)
    bvh = wp.Bvh(lowers, uppers)
    return bvh, bvh.id


def launch_raycast(
    shapes,
    body_shape,
    body_color,
    bvh_body,
    planes,
    body_q,
    camera,
    light,
    world_up,
    width,
    height,
    shadows=True,
    shadow_offset=1.0e-6,
    fade_distance=1.0e30,
    device=None,
    triangles=None,
):
    """Builds the BVH and casts one ray per pixel; returns (color, depth, hit, bvh).

    ``color`` (H, W) vec3, ``depth`` (H, W) float and ``hit`` (H, W) int are device arrays (see the
    module docstring); ``bvh`` holds the trees (of the bodies and of the triangles, None where empty), to be kept
    alive until they are read.

    Args:
        shapes: a float32 :class:`~polydem.shapeset.ShapeSet` (``shape_face_start``,
            ``face_plane``, ``shape_radius``).
        body_shape: (N,) int32 device array, shape index of each body.
        body_color: (N,) vec3 device array, RGB in [0, 1] of each body.
        bvh_body: (M,) int32 device array, the bodies to draw (M may be 0).
        planes: (plane_normal, plane_offset, plane_u, plane_v) device arrays, P entries each
            (P may be 0); u and v are the checker axes divided by the square size.
        body_q: (N,) transform device array, body poses (centroid, xyzw body -> world).
        camera: (eye, forward, right, up) as 3-sequences; right and up scaled by the tangents of
            the half fields of view.
        light: unit vector towards the light; world_up: unit up vector (for the sky).
        width, height: image size [pixels].
        shadows: cast shadow rays; shadow_offset [m] lifts their origin off the walls.
        fade_distance: distance [m] at which the checker contrast has halved.
        triangles: (tri_vertex, tri_wall) device arrays of the mesh walls: (3T,) vec3 world
            vertices of T triangles (counter-clockwise from the front) and (T,) int wall index; or
            None: no mesh walls.
    """
    device = wp.get_device(device)
    bvh, bvh_id = _bounds_bvh(
        body_bounds_kernel, bvh_body.shape[0], [shapes.shape_radius, body_shape, bvh_body, body_q], device
    )
    if triangles is None:
        triangles = (wp.zeros(0, dtype=wp.vec3, device=device), wp.zeros(0, dtype=int, device=device))
    tri_vertex, tri_wall = triangles
    tri_bvh, tri_bvh_id = _bounds_bvh(triangle_bounds_kernel, tri_wall.shape[0], [tri_vertex], device)
    color = wp.empty((height, width), dtype=wp.vec3, device=device)
    depth = wp.empty((height, width), dtype=float, device=device)
    hit = wp.empty((height, width), dtype=int, device=device)
    eye, forward, right, up = (wp.vec3(*np.asarray(a, dtype=np.float32)) for a in camera)
    plane_normal, plane_offset, plane_u, plane_v = planes
    wp.launch(
        raycast_kernel,
        dim=(height, width),
        inputs=[
            shapes.shape_face_start,
            shapes.face_plane,
            body_shape,
            body_color,
            bvh_body,
            plane_normal,
            plane_offset,
            plane_u,
            plane_v,
            tri_vertex,
            tri_wall,
            tri_bvh_id,
            body_q,
            bvh_id,
            eye,
            forward,
            right,
            up,
            wp.vec3(*np.asarray(world_up, dtype=np.float32)),
            wp.vec3(*np.asarray(light, dtype=np.float32)),
            int(bool(shadows)),
            float(shadow_offset),
            float(fade_distance),
        ],
        outputs=[color, depth, hit],
        device=device,
    )
    # The trees must outlive the launch: the caller keeps them until it has read the outputs.
    return color, depth, hit, (bvh, tri_bvh)
