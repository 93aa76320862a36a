"""Contacts of bodies with triangle-mesh walls, and the motion of those walls.

A mesh wall is a solid cut into convex cells, one behind each triangle (:mod:`polydem.meshwall`). A
free body's candidate cells are those whose bounds meet the body's bounding box in the wall's frame (a
``wp.Bvh`` over the cells, built once: the cells do not move in their wall's frame) and whose planes do
not all keep the body's bounding sphere out. The body is clipped against each with the exact pair
geometry, and the overlap volume, its first moment, S_A, M_A and the fallback are SUMMED over the cells
before the contact law is applied once (:func:`polydem.kernels.response.respond`). The sum of the exact
overlaps with cells that tile the solid is the exact overlap with the solid: the energy W(V) is that of
the body against the wall as a whole, so a flat region of many triangles acts as one plane and the edges
between triangles add nothing. One friction spring and one turning volume per (body, wall), kept in the
wall columns of ``State.wall_xi`` / ``wall_turn`` after the plane walls.

Two ways to the same motion, bit for bit (:func:`launch_mesh_contacts`; on CUDA the book of the energy lost
may differ in its last bits: the compiler contracts its multiply-adds differently in the two kernels):

* the walk: one thread per free body finds its cells and clips them in turn (the CPU's: one core runs
  the threads in turn anyway);
* the candidate list (:class:`MeshCandidates`, CUDA's): one thread per body lists its cells as (body, cell)
  candidates in a block it reserves, one thread per candidate clips, and one thread per body sums its
  candidates in the walk's order and applies the law. A grain on a fine mesh meets 4 to 6 cells: the walk
  left each thread that many clippings in a row (20x a pair contact on the GPU, BENCHMARKS 8d) where the
  pair kernel has a thread per contact. The list has a fixed
  capacity; where the candidates do not fit, it says so (:meth:`MeshCandidates.overflowed`) and the
  step is redone with room for them all.

A wall moves rigidly: its frame's origin (the pivot) with ``mesh_v``, its orientation turning at
``mesh_w``; :func:`launch_advance_meshes` steps its pose. The contacts come after the gather kernel and
add to the body's force and torque (one thread per body: a fixed order, no atomics).
"""

import functools
from dataclasses import dataclass
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
from polydem.kernels.narrowphase import NARROWPHASE_BLOCK_DIM
from polydem.kernels.precision import scalars
from polydem.kernels.structs import arrays, filled, make_struct, struct_types

# Candidates a body keeps in its thread while it traverses the BVH (a grain on a fine mesh meets 4 to 6 cells);
# one with more traverses it again for the rest.
LISTED_IN_REGISTERS = 8

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
def candidates_struct(C: Any) -> Any:
    """The candidate list of :class:`MeshCandidates`: per body (N,) its number of candidate cells (``count``)
    and where they start (``start``: a block reserved from ``total`` (1,), so the blocks' order varies from run
    to run, each block's does not); per candidate (capacity,) its body, mesh wall and cell (global index) and
    what its clipping gave: ``volume``, ``first_moment``, ``s_a``, ``m_a``, ``fallback`` (C, as
    :func:`polydem.kernels.compound.make_body_geometry`'s ``pair_geometry``) and ``depth`` (the diagnostics and
    report variants only); ``overflow`` (1,): set when they did not fit, ``peak`` (1,) then the most listed."""
    vec3c = wp.types.vector(3, C)
    members = arrays(count=int, start=int, total=int, peak=int, body=int, mesh=int, cell=int, volume=C)
    members |= arrays(first_moment=vec3c, s_a=vec3c, m_a=vec3c, fallback=vec3c, depth=C, overflow=int)
    return make_struct("MeshCandidates", **members)


class MeshCandidates:
    """The (body, cell) candidates of one step's mesh-wall contacts on the device (:func:`candidates_struct`):
    room for ``capacity`` of them, grown by :meth:`grow` after a step that did not fit (its results are
    wrong: redo it). 68 bytes a candidate in the float32 and mixed precisions (124 in float64), 8 a body."""

    def __init__(self, num_bodies: int, capacity: int, precision: str, device: Any) -> None:
        if num_bodies < 1 or capacity < 1:
            raise ValueError(f"a candidate list needs bodies and room: got {num_bodies} bodies, capacity {capacity}")
        self.num_bodies = int(num_bodies)
        self.precision = precision
        self.device = device
        self.generation = 0
        self._allocate(int(capacity))

    def _allocate(self, capacity: int) -> None:
        _, C = scalars(self.precision)
        vec3c = wp.types.vector(3, C)
        n, dev = self.num_bodies, self.device
        self.capacity = capacity
        per_candidate = {"body": int, "mesh": int, "cell": int, "volume": C, "depth": C}
        per_candidate |= dict.fromkeys(("first_moment", "s_a", "m_a", "fallback"), vec3c)
        self.arrays = {k: wp.zeros(capacity, dtype=dtype, device=dev) for k, dtype in per_candidate.items()}
        self.arrays |= {k: wp.zeros(n, dtype=int, device=dev) for k in ("count", "start")}
        self.arrays |= {k: wp.zeros(1, dtype=int, device=dev) for k in ("total", "peak", "overflow")}
        self.candidates = filled(candidates_struct(C), **self.arrays)

    def needed(self) -> int:
        """Host: the most candidates a listing found since the last :meth:`grow` (fitted or not): the last
        listing's, or more where one that did not fit found more (the steps after it apply no mesh-wall force,
        so theirs may be fewer)."""
        return max(int(self.arrays["total"].numpy()[0]), int(self.arrays["peak"].numpy()[0]))

    def overflowed(self) -> bool:
        """Host: whether a listing since the last :meth:`grow` found more candidates than there is room for."""
        return bool(int(self.arrays["overflow"].numpy()[0]))

    def grow(self) -> None:
        """Room for half as many again as :meth:`needed`, at least twice the room there was (so that a redone
        step that finds more again grows on; new arrays: recapture a graph)."""
        self._allocate(max(2 * self.capacity, int(1.5 * self.needed()) + 1))
        self.generation += 1

    @property
    def nbytes(self) -> int:
        return sum(a.capacity for a in self.arrays.values())


@dataclass(frozen=True, eq=False)
class MeshKernels:
    """The mesh-wall kernels of one contact variant (:func:`make_mesh_kernels`): the walk (``contact``), the
    candidate list's passes (``list``, ``clip``, ``apply``) and the walls' motion (``advance``)."""

    contact: wp.Kernel
    list: wp.Kernel
    clip: wp.Kernel
    apply: wp.Kernel
    advance: wp.Kernel


@functools.cache
def make_mesh_kernels(kernels: ContactKernels) -> MeshKernels:
    """The mesh-wall kernels of the variant of ``kernels`` (the contact kernels of one law, friction setting,
    polygon capacity and precision, :func:`polydem.kernels.forces.make_contact_kernels`: the step variant,
    or the diagnostics one that reports and changes nothing, or the report one that steps and reports; with
    ``compound`` each part of a body is clipped against each cell), made of the same geometry and wall
    contact, and the kernel that moves the mesh walls."""
    S, C = scalars(kernels.precision)
    vec3s = wp.types.vector(3, S)
    vec3c = wp.types.vector(3, C)
    quat_s = wp.types.quaternion(S)
    transform_s = wp.types.transformation(S)
    T = struct_types(kernels.precision)
    Candidates = candidates_struct(C)
    listed_t = wp.types.vector(LISTED_IN_REGISTERS, int)
    diagnostics, report = kernels.diagnostics, kernels.report
    geom, body_geom, wall_contact = kernels.geometry, kernels.body_geometry, kernels.wall_contact
    zero3 = wp.constant(vec3c(C(0.0), C(0.0), C(0.0)))

    # -- helpers: the walk and the candidate list share them, so that both give the same bits --------------

    @wp.func
    def query_pad(xm: transform_s, pa: vec3s, r: float):
        # The body's centre in the wall's frame (where the cells' BVH lives), float32, and the half-width of
        # its bounding box there.
        local = wp.transform_point(wp.transform_inverse(xm), pa)
        lf = wp.vec3(float(local[0]), float(local[1]), float(local[2]))
        pad = r * (1.0 + QUERY_ROUNDING) + QUERY_ROUNDING * wp.length(lf)
        return lf, pad

    @wp.func
    def cell_pose(meshes: T.MeshWalls, xm: transform_s, cell: int):
        # The cell's frame in the world: its origin carried by the wall's pose, the wall's orientation.
        return transform_s(wp.transform_point(xm, meshes.cell_center[cell]), wp.transform_get_rotation(xm))

    @wp.func
    def cell_apart(shapes: geom.shapes, sb: int, pa: vec3s, xb: transform_s, pad: float):
        # A cheap test before the clipping: the body's bounding sphere wholly in front of one of the cell's
        # planes cannot overlap it (the box query is coarser: a cell's bounds span its whole thickness).
        c_cell = wp.vec3d(wp.quat_rotate_inv(wp.transform_get_rotation(xb), pa - wp.transform_get_translation(xb)))
        apart = int(0)
        for fp in range(shapes.shape_face_start[sb], shapes.shape_face_start[sb + 1]):
            pl = shapes.face_plane64[fp]
            if pl[0] * c_cell[0] + pl[1] * c_cell[1] + pl[2] * c_cell[2] - pl[3] > wp.float64(pad):
                apart = 1
        return apart

    @wp.func
    def cell_depth(shapes: geom.shapes, meshes: T.MeshWalls, s: int, xa: transform_s, xm: transform_s, cell: int):
        # How far the body reaches behind the plane of the triangle the cell lies behind (the cells of
        # concave edges and corners have none: 0).
        fr = meshes.cell_front[cell]
        depth = C(0.0)
        if fr[0] != S(0.0) or fr[1] != S(0.0) or fr[2] != S(0.0):
            n_w = wp.quat_rotate(wp.transform_get_rotation(xm), vec3s(fr[0], fr[1], fr[2]))
            off = fr[3] + wp.dot(n_w, wp.transform_get_translation(xm))
            depth = C(body_geom.plane_depth(shapes, s, xa, n_w, off))
        return depth

    @wp.func
    def wants_depth(report_bits: int):
        # The depth and normal only for the diagnostics and a report of the contacts (not for the sums).
        want = wp.static(diagnostics)
        if wp.static(report):
            want = (report_bits & REPORT_CONTACTS) != 0
        return want

    @wp.func
    def apply_wall(
        shapes: geom.shapes,
        model: T.BodyModel,
        materials: T.Materials,
        dt: C,
        meshes: T.MeshWalls,
        mesh_q: wp.array(dtype=transform_s),
        bodies: T.Bodies,
        walls: T.WallHistory,
        wall_out: T.WallOutputs,
        report_bits: int,
        wall_sums: ContactSums,
        i: int,
        m: int,
        scale: C,
        vol: C,
        first_moment: vec3c,
        s_a: vec3c,
        m_a: vec3c,
        fb_a: vec3c,
        depth: C,
        f: vec3s,
        t: vec3s,
        lost: S,
    ):
        # Body i's contact with mesh wall m from the sums over its cells: the law once, into the body's sums.
        xm = mesh_q[m]
        j = meshes.first_column + m
        pa = wp.transform_get_translation(bodies.q[i])
        s = model.shape[i]
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
            if wants_depth(report_bits) and vol > C(0.0):
                wall_out.normal[i, j] = n
        return f, t, lost

    @wp.func
    def add_to_body(bodies: T.Bodies, i: int, f: vec3s, t: vec3s, lost: S):
        if wp.static(not diagnostics):
            bodies.f[i] = bodies.f[i] + f
            bodies.t[i] = bodies.t[i] + t
            bodies.dissipated[i] = bodies.dissipated[i] + lost

    # -- the walk: one thread per body -----------------------------------------------------------------------

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
        scale = C(damping_scale(body_damping[i], wp.float32(0.0)))
        f = vec3s(S(0.0), S(0.0), S(0.0))
        t = vec3s(S(0.0), S(0.0), S(0.0))
        lost = S(0.0)
        want_depth = wants_depth(report_bits)
        for m in range(meshes.bvh.shape[0]):
            xm = mesh_q[m]
            lf, pad = query_pad(xm, pa, model.radius[i])
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
            while wp.bvh_query_next(query, k):
                cell = base + k
                sb = meshes.cell_shape[cell]
                xb = cell_pose(meshes, xm, cell)
                if cell_apart(shapes, sb, pa, xb, pad) != 0:
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
                        if want_depth:
                            depth = wp.max(depth, cell_depth(shapes, meshes, s, xa, xm, cell))
            f, t, lost = apply_wall(
                shapes, model, materials, dt, meshes, mesh_q, bodies, walls, wall_out, report_bits, wall_sums,
                i, m, scale, vol, first_moment, s_a, m_a, fb_a, depth, f, t, lost,
            )  # fmt: skip
        add_to_body(bodies, i, f, t, lost)

    # -- the candidate list: list, clip, apply --------------------------------------------------------------

    @wp.kernel(enable_backward=False, module="unique")
    def list_kernel(
        # Model
        shapes: geom.shapes,
        model: T.BodyModel,
        meshes: T.MeshWalls,
        # State in
        mesh_q: wp.array(dtype=transform_s),
        bodies: T.Bodies,
        # In/out: total (zeroed before); out: count, start and the candidates (body, mesh, cell) where they fit,
        # else overflow
        cand: Candidates,
    ):
        """Each free body's candidate cells, by wall and in the BVH's order (the walk's), in a block of its own:
        one traversal remembers the first LISTED_IN_REGISTERS, a second one (rare) finds the rest."""
        i = wp.tid()
        n = int(0)
        kept_cell = listed_t()
        kept_mesh = listed_t()
        pa = wp.transform_get_translation(bodies.q[i])
        if model.flags[i] == 0:
            for m in range(meshes.bvh.shape[0]):
                xm = mesh_q[m]
                lf, pad = query_pad(xm, pa, model.radius[i])
                ext = wp.vec3(pad, pad, pad)
                query = wp.bvh_query_aabb(meshes.bvh[m], lf - ext, lf + ext)
                k = int(0)
                while wp.bvh_query_next(query, k):
                    cell = meshes.cell_start[m] + k
                    if cell_apart(shapes, meshes.cell_shape[cell], pa, cell_pose(meshes, xm, cell), pad) == 0:
                        if n < LISTED_IN_REGISTERS:
                            kept_cell[n] = cell
                            kept_mesh[n] = m
                        n += 1
        cand.count[i] = n
        if n == 0:
            return
        c = wp.atomic_add(cand.total, 0, n)
        cand.start[i] = c
        if c + n > cand.body.shape[0]:
            cand.overflow[0] = 1
            wp.atomic_max(cand.peak, 0, c + n)
            return
        for h in range(wp.min(n, LISTED_IN_REGISTERS)):
            cand.body[c + h] = i
            cand.mesh[c + h] = kept_mesh[h]
            cand.cell[c + h] = kept_cell[h]
        if n > LISTED_IN_REGISTERS:
            h = int(0)
            for m in range(meshes.bvh.shape[0]):
                xm = mesh_q[m]
                lf, pad = query_pad(xm, pa, model.radius[i])
                ext = wp.vec3(pad, pad, pad)
                query = wp.bvh_query_aabb(meshes.bvh[m], lf - ext, lf + ext)
                k = int(0)
                while wp.bvh_query_next(query, k):
                    cell = meshes.cell_start[m] + k
                    if cell_apart(shapes, meshes.cell_shape[cell], pa, cell_pose(meshes, xm, cell), pad) == 0:
                        if h >= LISTED_IN_REGISTERS:
                            cand.body[c + h] = i
                            cand.mesh[c + h] = m
                            cand.cell[c + h] = cell
                        h += 1

    # The pair kernel's register cap: the same clipping code.
    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=kernels.max_registers)
    def clip_kernel(
        # Model
        shapes: geom.shapes,
        model: T.BodyModel,
        meshes: T.MeshWalls,
        # State in
        mesh_q: wp.array(dtype=transform_s),
        bodies: T.Bodies,
        overflow: wp.array(dtype=int),
        # In: the candidates; out: their geometry
        cand: Candidates,
        report_bits: int,
    ):
        """One candidate's clipping: the body against the cell."""
        c = wp.tid()
        # Not all listed: the step is redone (stale entries are not clipped, their polygons could not overflow)
        if c >= cand.total[0] or cand.overflow[0] != 0:
            return
        i = cand.body[c]
        m = cand.mesh[c]
        cell = cand.cell[c]
        xa = bodies.q[i]
        s = model.shape[i]
        xm = mesh_q[m]
        v_c, fm_c, sa_c, ma_c, sb_c, mb_c, fb_c, of = body_geom.pair_geometry(
            shapes, s, meshes.cell_shape[cell], xa, cell_pose(meshes, xm, cell)
        )
        if of != 0:
            wp.atomic_max(overflow, 0, 1)
        cand.volume[c] = v_c
        cand.first_moment[c] = fm_c
        cand.s_a[c] = sa_c
        cand.m_a[c] = ma_c
        cand.fallback[c] = fb_c
        if wp.static(diagnostics or report):
            depth = C(0.0)
            if v_c > C(0.0) and wants_depth(report_bits):
                depth = cell_depth(shapes, meshes, s, xa, xm, cell)
            cand.depth[c] = depth

    @wp.kernel(enable_backward=False, module="unique")
    def apply_kernel(
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
        # In: the candidates and their geometry
        cand: Candidates,
        # Out (diagnostics)
        wall_out: T.WallOutputs,
        # Report (the report variant only)
        report_bits: int,
        wall_sums: ContactSums,
    ):
        """Each free body's candidates summed per wall in the walk's order, the law applied once per wall."""
        i = wp.tid()
        # Not all candidates listed: the step is redone (its ranges may reach past the list).
        if model.flags[i] != 0 or cand.overflow[0] != 0:
            return
        scale = C(damping_scale(body_damping[i], wp.float32(0.0)))
        f = vec3s(S(0.0), S(0.0), S(0.0))
        t = vec3s(S(0.0), S(0.0), S(0.0))
        lost = S(0.0)
        c = cand.start[i]
        end = c + cand.count[i]
        for m in range(meshes.bvh.shape[0]):
            vol = C(0.0)
            first_moment = zero3
            s_a = zero3
            m_a = zero3
            fb_a = zero3
            depth = C(0.0)
            while c < end and cand.mesh[c] == m:
                v_c = cand.volume[c]
                if v_c > C(0.0):
                    vol += v_c
                    first_moment += cand.first_moment[c]
                    s_a += cand.s_a[c]
                    m_a += cand.m_a[c]
                    fb_a += cand.fallback[c]
                    if wp.static(diagnostics or report):
                        depth = wp.max(depth, cand.depth[c])
                c += 1
            f, t, lost = apply_wall(
                shapes, model, materials, dt, meshes, mesh_q, bodies, walls, wall_out, report_bits, wall_sums,
                i, m, scale, vol, first_moment, s_a, m_a, fb_a, depth, f, t, lost,
            )  # fmt: skip
        add_to_body(bodies, i, f, t, lost)

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

    return MeshKernels(
        contact=mesh_contact_kernel,
        list=list_kernel,
        clip=clip_kernel,
        apply=apply_kernel,
        advance=advance_meshes_kernel,
    )


# ---------------------------------------------------------------------------------------------
# Launch functions
# ---------------------------------------------------------------------------------------------


def launch_mesh_contacts(
    kernels: MeshKernels,
    *,
    model: MeshWallModel,
    state: MeshWallState,
    dt: float,
    overflow: wp.array,
    out: ContactOutputs,
    report_bits: int,
    wall_sums: ContactSums,
    meshes: Any = None,
    candidates: MeshCandidates | None = None,
) -> None:
    """The mesh-wall contacts of ``kernels`` (:func:`make_mesh_kernels`), after the gather: adds each free
    body's mesh-wall contacts to ``state.body_f`` and ``body_t`` (the step and report variants) or writes them
    into the wall columns of ``out`` (diagnostics; the report variant by ``report_bits``), as
    :func:`polydem.kernels.forces.launch_gather` does for the planes. ``meshes``: the mesh walls with their
    velocities now (default the model's). ``candidates``: through this candidate list (three launches, a
    thread per (body, cell) for the clipping; the same motion; :meth:`MeshCandidates.overflowed` says whether
    they fitted), or None: the walk (one launch, a thread per body)."""
    m = model
    meshes = m.meshes if meshes is None else meshes
    dev = state.mesh_q.device
    n = m.num_bodies
    shapes = m.shapes.kernel_args()
    if candidates is None:
        inputs = [*shapes, m.bodies, m.materials, dt, meshes, state.mesh_q, state.bodies, state.walls]
        wp.launch(
            kernels.contact,
            dim=n,
            inputs=[*inputs, state.body_damping],
            outputs=[overflow, out.walls, int(report_bits), wall_sums],
            device=dev,
        )
        return
    cand = candidates.candidates
    where = [*shapes, m.bodies, meshes, state.mesh_q, state.bodies]
    candidates.arrays["total"].zero_()
    wp.launch(kernels.list, dim=n, inputs=where, outputs=[cand], device=dev)
    wp.launch(
        kernels.clip,
        dim=candidates.capacity,
        inputs=[*where, overflow, cand, int(report_bits)],
        device=dev,
        block_dim=NARROWPHASE_BLOCK_DIM,  # the pair kernel's
    )
    wp.launch(
        kernels.apply,
        dim=n,
        inputs=[*shapes, m.bodies, m.materials, dt, meshes, state.mesh_q, state.bodies, state.walls,
                state.body_damping, cand],
        outputs=[out.walls, int(report_bits), wall_sums],
        device=dev,
    )  # fmt: skip


def launch_advance_meshes(kernel: wp.Kernel, *, meshes: Any, dt: float, mesh_q: wp.array) -> None:
    """The wall-motion kernel (``make_mesh_kernels(...).advance``): each mesh wall's pose ``mesh_q`` moved by
    ``dt`` at its velocity ``meshes.v`` and turned at its angular velocity ``meshes.w`` (one thread per wall;
    ``meshes``: :func:`polydem.kernels.structs.mesh_walls_struct`; ``mesh_q`` may hold a placeholder more)."""
    wp.launch(kernel, dim=meshes.v.shape[0], inputs=[meshes, dt, mesh_q], device=mesh_q.device)
