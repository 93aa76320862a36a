"""Contacts of bodies with triangle-mesh walls, and the motion of those walls.

A mesh wall is a solid cut into convex cells, one behind each triangle (:mod:`polydem.meshwall`). Per
free body one thread walks every mesh wall: it finds the cells whose bounds meet the body's bounding
box in the wall's frame (a ``wp.Bvh`` over the cells, built once: the cells do not move in their
wall's frame), clips the body against each with the exact pair geometry, and SUMS the overlap
volume, its first moment, S_A, M_A and the fallback over the cells before applying the contact law
once (:func:`polydem.kernels.response.respond`). The sum of the exact overlaps with cells that tile
the solid is the exact overlap with the solid: the energy W(V) is that of the body against the
wall as a whole, so a flat region of many triangles acts as one plane and the edges between
triangles add nothing. One friction spring and one turning volume per (body, wall), kept in the
wall columns of ``State.wall_xi`` / ``wall_turn`` after the plane walls.

A wall moves rigidly: its frame's origin (the pivot) with ``mesh_v``, its orientation turning at
``mesh_w``; :func:`launch_advance_meshes` steps its pose. The thread runs after the gather kernel and adds
to the body's force and torque (one thread per body: a fixed order, no atomics).
"""

import functools
from typing import Any, Protocol

import warp as wp
from polydem.kernels.forces import (
    REPORT_CONTACTS,
    BodyState,
    ContactKernels,
    ContactModel,
    ContactOutputs,
    ContactSums,
    damping_scale,
)
from polydem.kernels.precision import scalars
from polydem.kernels.structs import struct_types

# Rounding allowance of the float32 BVH query box, relative to the body's distance from the wall's
# origin plus its radius (the box is cast from the state's scalar).
QUERY_ROUNDING = 4.0e-7


class MeshWallModel(ContactModel, Protocol):
    """What the mesh-wall kernel reads of a model besides the contact arrays (:class:`polydem.model.Model`):
    the struct of the mesh walls (``meshes``, :func:`polydem.kernels.structs.mesh_walls_struct`: their
    cells' BVHs, shapes, frames and fronts, materials and motion, and the first wall column)."""

    meshes: Any  # mesh_walls_struct(S)


class MeshWallState(BodyState, Protocol):
    """A state with the poses of the mesh walls (:class:`polydem.state.State`)."""

    mesh_q: wp.array


@functools.cache
def make_mesh_kernels(kernels: ContactKernels) -> tuple[wp.Kernel, wp.Kernel]:
    """The mesh-wall contact kernel of the variant of ``kernels`` (the contact kernels of one law, friction
    setting, polygon capacity and precision, :func:`polydem.kernels.forces.make_contact_kernels`: the step
    variant, or the diagnostics one that reports and changes nothing, or the report one that steps and
    reports; with ``compound`` each part of a body is clipped against each cell), made of the same
    geometry and wall contact; and the kernel that moves the mesh walls."""
    S, C = scalars(kernels.precision)
    vec3s = wp.types.vector(3, S)
    vec3c = wp.types.vector(3, C)
    quat_s = wp.types.quaternion(S)
    transform_s = wp.types.transformation(S)
    T = struct_types(kernels.precision)
    diagnostics, report = kernels.diagnostics, kernels.report
    geom, body_geom, wall_contact = kernels.geometry, kernels.body_geometry, kernels.wall_contact
    zero3 = wp.constant(vec3c(C(0.0), C(0.0), C(0.0)))

    @wp.kernel(enable_backward=False, module="unique")
    def mesh_contact_kernel(
        # Model
        shapes: geom.shapes,
        model: T.BodyModel,
        materials: T.Materials,
        dt: C,
        meshes: T.MeshWalls,
        # State in: the walls' poses; in/out: the bodies (their force, torque and energy lost added to)
        # and the wall contacts' history
        mesh_q: wp.array(dtype=transform_s),
        bodies: T.Bodies,
        walls: T.WallHistory,
        body_damping: wp.array(dtype=wp.float32),
        overflow: wp.array(dtype=int),
        # Out (diagnostics)
        wall_out: T.WallOutputs,
        # Report (the report variant only)
        report_bits: int,
        wall_sums: ContactSums,
    ):
        i = wp.tid()
        if model.flags[i] != 0:
            return
        xa = bodies.q[i]
        pa = wp.transform_get_translation(xa)
        s = model.shape[i]
        r = model.radius[i]
        scale = C(damping_scale(body_damping[i], wp.float32(0.0)))
        f = vec3s(S(0.0), S(0.0), S(0.0))
        t = vec3s(S(0.0), S(0.0), S(0.0))
        lost = S(0.0)
        # The depth and normal only for the diagnostics and a report of the contacts (not for the sums).
        want_depth = wp.static(diagnostics)
        if wp.static(report):
            want_depth = (report_bits & REPORT_CONTACTS) != 0
        for m in range(meshes.bvh.shape[0]):
            xm = mesh_q[m]
            j = meshes.first_column + m
            # The body's bounding box in the wall's frame (where the cells' BVH lives).
            local = wp.transform_point(wp.transform_inverse(xm), pa)
            lf = wp.vec3(float(local[0]), float(local[1]), float(local[2]))
            pad = r * (1.0 + QUERY_ROUNDING) + QUERY_ROUNDING * wp.length(lf)
            ext = wp.vec3(pad, pad, pad)
            query = wp.bvh_query_aabb(meshes.bvh[m], lf - ext, lf + ext)
            k = int(0)
            vol = C(0.0)
            first_moment = zero3
            s_a = zero3
            m_a = zero3
            fb_a = zero3
            depth = C(0.0)
            base = meshes.cell_start[m]
            rot = wp.transform_get_rotation(xm)
            while wp.bvh_query_next(query, k):
                cell = base + k
                sb = meshes.cell_shape[cell]
                xb = transform_s(wp.transform_point(xm, meshes.cell_center[cell]), rot)
                # A cheap test before the clipping: the body's bounding sphere wholly in front of one
                # of the cell's planes cannot overlap it (the box query is coarser: a cell's bounds
                # span its whole thickness).
                c_cell = wp.vec3d(wp.quat_rotate_inv(rot, pa - wp.transform_get_translation(xb)))
                apart = int(0)
                for fp in range(shapes.shape_face_start[sb], shapes.shape_face_start[sb + 1]):
                    pl = shapes.face_plane64[fp]
                    if pl[0] * c_cell[0] + pl[1] * c_cell[1] + pl[2] * c_cell[2] - pl[3] > wp.float64(pad):
                        apart = 1
                if apart != 0:
                    continue
                v_c, fm_c, sa_c, ma_c, sb_c, mb_c, fb_c, of = body_geom.pair_geometry(shapes, s, sb, xa, xb)
                if of != 0:
                    wp.atomic_max(overflow, 0, 1)
                if v_c > C(0.0):
                    vol += v_c
                    first_moment += fm_c
                    s_a += sa_c
                    m_a += ma_c
                    fb_a += fb_c
                    if wp.static(diagnostics or report):
                        # How far the body reaches behind the plane of the triangle the cell lies
                        # behind (the cells of concave edges and corners have none).
                        fr = meshes.cell_front[cell]
                        if want_depth and (fr[0] != S(0.0) or fr[1] != S(0.0) or fr[2] != S(0.0)):
                            n_w = wp.quat_rotate(rot, vec3s(fr[0], fr[1], fr[2]))
                            off = fr[3] + wp.dot(n_w, wp.transform_get_translation(xm))
                            depth = wp.max(depth, C(body_geom.plane_depth(shapes, s, xa, n_w, off)))
            mat = model.material[i] * materials.count + meshes.material[m]
            # B's motion about the wall's origin: r_ab from the body to it, its velocity there.
            r_ab = vec3c(wp.transform_get_translation(xm) - pa)
            f, t, lost, n = wall_contact(
                i, j, mat, vol, first_moment, s_a, m_a, fb_a, depth,
                r_ab, vec3c(bodies.v[i]), vec3c(bodies.w[i]), vec3c(meshes.v[m]), vec3c(meshes.w[m]), pa,
                shapes.shape_radius[s], shapes.shape_face_area[s], C(model.inv_mass[i]), scale,
                materials, dt, walls, wall_out, report_bits, wall_sums, f, t, lost,
            )  # fmt: skip
            if wp.static(diagnostics or report):
                if want_depth and vol > C(0.0):
                    wall_out.normal[i, j] = n
        if wp.static(not diagnostics):
            bodies.f[i] = bodies.f[i] + f
            bodies.t[i] = bodies.t[i] + t
            bodies.dissipated[i] = bodies.dissipated[i] + lost

    @wp.kernel(enable_backward=False, module="unique")
    def advance_meshes_kernel(meshes: T.MeshWalls, dt: S, mesh_q: wp.array(dtype=transform_s)):
        m = wp.tid()
        x = mesh_q[m]
        w = meshes.w[m]
        angle = wp.length(w) * dt
        rot = wp.transform_get_rotation(x)
        if angle > S(0.0):
            rot = wp.normalize(wp.quat_from_axis_angle(wp.normalize(w), angle) * rot)
        mesh_q[m] = transform_s(wp.transform_get_translation(x) + meshes.v[m] * dt, quat_s(rot))

    return mesh_contact_kernel, advance_meshes_kernel


# ---------------------------------------------------------------------------------------------
# Launch functions
# ---------------------------------------------------------------------------------------------


def launch_mesh_contacts(
    kernel: wp.Kernel,
    *,
    model: MeshWallModel,
    state: MeshWallState,
    dt: float,
    overflow: wp.array,
    out: ContactOutputs,
    report_bits: int,
    wall_sums: ContactSums,
    meshes: Any = None,
) -> None:
    """The mesh-wall contact kernel (``make_mesh_kernels(...)[0]``), one thread per body, after the
    gather: adds each free body's mesh-wall contacts to ``state.body_f`` and ``body_t`` (the step and
    report variants) or writes them into the wall columns of ``out`` (diagnostics; the report variant
    by ``report_bits``), as :func:`polydem.kernels.forces.launch_gather` does for the planes. ``meshes``:
    the mesh walls with their velocities now (default the model's)."""
    m = model
    meshes = m.meshes if meshes is None else meshes
    wp.launch(
        kernel,
        dim=m.num_bodies,
        inputs=[
            *m.shapes.kernel_args(),
            m.bodies,
            m.materials,
            dt,
            meshes,
            state.mesh_q,
            state.bodies,
            state.walls,
            state.body_damping,
        ],
        outputs=[overflow, out.walls, int(report_bits), wall_sums],
        device=state.mesh_q.device,
    )


def launch_advance_meshes(kernel: wp.Kernel, *, meshes: Any, dt: float, mesh_q: wp.array) -> None:
    """The wall-motion kernel (``make_mesh_kernels(...)[1]``): each mesh wall's pose ``mesh_q`` moved by
    ``dt`` at its velocity ``meshes.v`` and turned at its angular velocity ``meshes.w`` (one thread per wall;
    ``meshes``: :func:`polydem.kernels.structs.mesh_walls_struct`; ``mesh_q`` may hold a placeholder more)."""
    wp.launch(kernel, dim=meshes.v.shape[0], inputs=[meshes, dt, mesh_q], device=mesh_q.device)
