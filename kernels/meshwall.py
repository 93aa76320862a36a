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
wall columns of ``State.plane_xi`` / ``plane_turn`` after the plane walls.

A wall moves rigidly: its frame's origin (the pivot) with ``mesh_v``, its orientation turning at
``mesh_w``; :func:`launch_advance_meshes` steps its pose. The thread runs after the gather kernel and adds
to the body's force and torque (one thread per body: a fixed order, no atomics).
"""

import functools
from typing import Protocol

import warp as wp
from polydem.kernels.compound import make_body_geometry
from polydem.kernels.forces import (
    REPORT_CONTACTS,
    BodyState,
    ContactModel,
    ContactOutputs,
    ContactSums,
    make_wall_contact,
    material_args,
)
from polydem.kernels.geometry import make_geometry
from polydem.kernels.precision import scalars

# Rounding allowance of the float32 BVH query box, relative to the body's distance from the wall's
# origin plus its radius (the box is cast from the state's scalar).
QUERY_ROUNDING = 4.0e-7


class MeshWallModel(ContactModel, Protocol):
    """What the mesh-wall kernel reads of a model besides the contact arrays (:class:`polydem.model.Model`):
    the bodies' bounding radii, the walls' cells (their BVHs, shapes, frames and fronts), materials
    and motion, and the number of planes (the mesh walls' columns come after theirs)."""

    body_radius: wp.array
    mesh_bvh: wp.array
    mesh_cell_start: wp.array
    mesh_material: wp.array
    mesh_v: wp.array
    mesh_w: wp.array
    cell_shape: wp.array
    cell_center: wp.array
    cell_front: wp.array
    num_planes: int


class MeshWallState(BodyState, Protocol):
    """A state with the poses of the mesh walls (:class:`polydem.state.State`)."""

    mesh_q: wp.array


@functools.cache
def make_mesh_kernels(
    law: str,
    friction: bool,
    max_poly: int,
    max_faces: int,
    *,
    diagnostics: bool = False,
    precision: str = "float32",
    compound: bool = False,
    report: bool = False,
):
    """The mesh-wall contact kernel of one law, friction setting, polygon capacity and precision
    (the step variant, or with ``diagnostics`` the one that reports and changes nothing, or with
    ``report`` the step variant that also reports, as :func:`polydem.kernels.forces.make_contact_kernels`);
    ``compound``: bodies may be compound grains (each part is clipped against each cell)."""
    S, C = scalars(precision)
    vec3s = wp.types.vector(3, S)
    vec3c = wp.types.vector(3, C)
    quat_s = wp.types.quaternion(S)
    transform_s = wp.types.transformation(S)
    wall_contact = make_wall_contact(law, friction, diagnostics, precision, report)
    geom = make_geometry(C, max_poly, max_faces, pose_scalar=S)
    body_geom = make_body_geometry(geom, compound)
    Shapes = geom.shapes
    pair_geometry = body_geom.pair_geometry
    plane_depth_of = body_geom.plane_depth
    zero3 = wp.constant(vec3c(C(0.0), C(0.0), C(0.0)))

    @wp.kernel(enable_backward=False, module="unique")
    def mesh_contact_kernel(
        # Model
        shapes: Shapes,
        body_shape: wp.array(dtype=int),
        body_material: wp.array(dtype=int),
        body_flags: wp.array(dtype=int),
        body_inv_mass: wp.array(dtype=S),
        body_radius: wp.array(dtype=float),
        num_materials: int,
        material_k: wp.array(dtype=C),
        material_e: wp.array(dtype=C),
        material_mu: wp.array(dtype=C),
        material_kt: wp.array(dtype=C),
        law_m: C,
        dt: C,
        mesh_bvh: wp.array(dtype=wp.uint64),
        mesh_cell_start: wp.array(dtype=int),
        mesh_material: wp.array(dtype=int),
        mesh_v: wp.array(dtype=vec3s),
        mesh_w: wp.array(dtype=vec3s),
        cell_shape: wp.array(dtype=int),
        cell_center: wp.array(dtype=vec3s),
        cell_front: wp.array(dtype=wp.types.vector(4, S)),
        first_column: int,
        # State in
        body_q: wp.array(dtype=transform_s),
        body_v: wp.array(dtype=vec3s),
        body_w: wp.array(dtype=vec3s),
        mesh_q: wp.array(dtype=transform_s),
        # State in/out
        plane_xi: wp.array2d(dtype=vec3c),
        plane_turn: wp.array2d(dtype=C),
        body_dissipated: wp.array(dtype=S),
        body_f: wp.array(dtype=vec3s),
        body_t: wp.array(dtype=vec3s),
        overflow: wp.array(dtype=int),
        # Out (diagnostics)
        plane_volume: wp.array2d(dtype=C),
        plane_energy: wp.array2d(dtype=C),
        plane_fn: wp.array2d(dtype=C),
        plane_point: wp.array2d(dtype=vec3s),
        plane_ft: wp.array2d(dtype=vec3c),
        plane_depth: wp.array2d(dtype=C),
        plane_normal: wp.array2d(dtype=vec3c),
        # Report (the report variant only)
        report_bits: int,
        wall_sums: ContactSums,
    ):
        i = wp.tid()
        if body_flags[i] != 0:
            return
        xa = body_q[i]
        pa = wp.transform_get_translation(xa)
        s = body_shape[i]
        r = body_radius[i]
        f = vec3s(S(0.0), S(0.0), S(0.0))
        t = vec3s(S(0.0), S(0.0), S(0.0))
        lost = S(0.0)
        # The depth and normal only for the diagnostics and a report of the contacts (not for the sums).
        want_depth = wp.static(diagnostics)
        if wp.static(report):
            want_depth = (report_bits & REPORT_CONTACTS) != 0
        for m in range(mesh_bvh.shape[0]):
            xm = mesh_q[m]
            j = first_column + m
            # The body's bounding box in the wall's frame (where the cells' BVH lives).
            local = wp.transform_point(wp.transform_inverse(xm), pa)
            lf = wp.vec3(float(local[0]), float(local[1]), float(local[2]))
            pad = r * (1.0 + QUERY_ROUNDING) + QUERY_ROUNDING * wp.length(lf)
            ext = wp.vec3(pad, pad, pad)
            query = wp.bvh_query_aabb(mesh_bvh[m], lf - ext, lf + ext)
            k = int(0)
            vol = C(0.0)
            first_moment = zero3
            s_a = zero3
            m_a = zero3
            fb_a = zero3
            depth = C(0.0)
            base = mesh_cell_start[m]
            rot = wp.transform_get_rotation(xm)
            while wp.bvh_query_next(query, k):
                cell = base + k
                sb = cell_shape[cell]
                xb = transform_s(wp.transform_point(xm, cell_center[cell]), rot)
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
                v_c, fm_c, sa_c, ma_c, sb_c, mb_c, fb_c, of = pair_geometry(shapes, s, sb, xa, xb)
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
                        fr = cell_front[cell]
                        if want_depth and (fr[0] != S(0.0) or fr[1] != S(0.0) or fr[2] != S(0.0)):
                            n_w = wp.quat_rotate(rot, vec3s(fr[0], fr[1], fr[2]))
                            off = fr[3] + wp.dot(n_w, wp.transform_get_translation(xm))
                            depth = wp.max(depth, C(plane_depth_of(shapes, s, xa, n_w, off)))
            mat = body_material[i] * num_materials + mesh_material[m]
            # B's motion about the wall's origin: r_ab from the body to it, its velocity there.
            r_ab = vec3c(wp.transform_get_translation(xm) - pa)
            f, t, lost, n = wall_contact(
                i, j, mat, vol, first_moment, s_a, m_a, fb_a, depth,
                r_ab, vec3c(body_v[i]), vec3c(body_w[i]), vec3c(mesh_v[m]), vec3c(mesh_w[m]), pa,
                shapes.shape_radius[s], shapes.shape_face_area[s], C(body_inv_mass[i]),
                material_k, material_e, material_mu, material_kt, law_m, dt,
                plane_xi, plane_turn,
                plane_volume, plane_energy, plane_fn, plane_point, plane_ft, plane_depth,
                report_bits, wall_sums, f, t, lost,
            )  # fmt: skip
            if wp.static(diagnostics or report):
                if want_depth and vol > C(0.0):
                    plane_normal[i, j] = n
        if wp.static(not diagnostics):
            body_f[i] = body_f[i] + f
            body_t[i] = body_t[i] + t
            body_dissipated[i] = body_dissipated[i] + lost

    @wp.kernel(enable_backward=False, module="unique")
    def advance_meshes_kernel(
        mesh_v: wp.array(dtype=vec3s),
        mesh_w: wp.array(dtype=vec3s),
        dt: S,
        mesh_q: wp.array(dtype=transform_s),
    ):
        m = wp.tid()
        x = mesh_q[m]
        w = mesh_w[m]
        angle = wp.length(w) * dt
        rot = wp.transform_get_rotation(x)
        if angle > S(0.0):
            rot = wp.normalize(wp.quat_from_axis_angle(wp.normalize(w), angle) * rot)
        mesh_q[m] = transform_s(wp.transform_get_translation(x) + mesh_v[m] * dt, quat_s(rot))

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
) -> None:
    """The mesh-wall contact kernel (``make_mesh_kernels(...)[0]``), one thread per body, after the
    gather: adds each free body's mesh-wall contacts to ``state.body_f`` and ``body_t`` (the step and
    report variants) or writes them into the wall columns of ``out`` (diagnostics; the report variant
    by ``report_bits``), as :func:`polydem.kernels.forces.launch_gather` does for the planes."""
    m = model
    wp.launch(
        kernel,
        dim=m.num_bodies,
        inputs=[
            # Model
            *m.shapes.kernel_args(),
            m.body_shape,
            m.body_material,
            m.body_flags,
            m.body_inv_mass,
            m.body_radius,
            *material_args(m, dt),
            m.mesh_bvh,
            m.mesh_cell_start,
            m.mesh_material,
            m.mesh_v,
            m.mesh_w,
            m.cell_shape,
            m.cell_center,
            m.cell_front,
            m.num_planes,
            # State in
            state.body_q,
            state.body_v,
            state.body_w,
            state.mesh_q,
            # State in/out
            state.plane_xi,
            state.plane_turn,
            state.body_dissipated,
            state.body_f,
            state.body_t,
            overflow,
        ],
        outputs=[
            # Out (diagnostics)
            out.plane_volume,
            out.plane_energy,
            out.plane_fn,
            out.plane_point,
            out.plane_ft,
            out.plane_depth,
            out.plane_normal,
            # Report
            int(report_bits),
            wall_sums,
        ],
        device=state.body_q.device,
    )


def launch_advance_meshes(
    kernel: wp.Kernel, *, mesh_v: wp.array, mesh_w: wp.array, dt: float, mesh_q: wp.array
) -> None:
    """The wall-motion kernel (``make_mesh_kernels(...)[1]``): each mesh wall's pose ``mesh_q`` moved by
    ``dt`` at its velocity ``mesh_v`` and turned at its angular velocity ``mesh_w`` (one thread per wall of
    ``mesh_v``; ``mesh_q`` may hold a placeholder more)."""
    wp.launch(kernel, dim=mesh_v.shape[0], inputs=[mesh_v, mesh_w, dt, mesh_q], device=mesh_q.device)
