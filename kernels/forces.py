"""Contact forces: energy-model wrenches, hysteretic normal damping, Coulomb friction, walls.

Per candidate pair one thread computes the overlap geometry (:mod:`polydem.kernels.geometry`) and
turns it into a wrench (:func:`polydem.kernels.response.respond`):

* elastic: force on A ``-W'(V) S_A``, torque about A's centre ``-W'(V) (M_A - x_A x S_A)``;
* normal damping from the restitution coefficient e, as hysteresis in the overlap volume with a
  turning volume V_t kept per pair (and per body and wall). While V grows, or stands above V_t,
  the contact is on the loading branch: pressure W'(V) and V_t follows V. Once V shrinks (dV/dt
  < 0, computed exactly from S_A, M_A and the velocities) below V_t, it unloads along the law
  taken at an elastic volume u = V_t - (V_t - V) / e^2 (du = dV / e^2): pressure W'(u), zero
  once u <= 0, i.e. below V = (1 - e^2) V_t. Why this curve:

  - the force is continuous where the contact turns (u = V_t there). A resting contact whose
    dV/dt jitters about zero therefore keeps its force, and its friction cap, through every
    turn; the older scheme (wrench times e^2 while unloading) dropped both by e^2 at each
    jitter, which let a block with e = 0.3 creep down a slope it should stick on;
  - a full unloading returns exactly e^2 W(V_t), the integral of W'(u) dV, for every law and
    every shape (the wrench stays -W' S_A, so its power is exactly -W' dV/dt): rebound speed e
    times the impact speed, with no switching threshold to bias it;
  - the energy is a state function E(V; V_t): W(V) on the loading branch, and (1 - e^2) W(V_t)
    + e^2 W(u) on the unloading one (what is still to come back, plus what never will), so each
    branch is conservative and the step integrates it as well as an elastic contact.
    Dissipation happens only where the state jumps, and is booked exactly, as the drop of E at
    fixed V: reloading from below V_t (V_t := V) loses E(V; V_t) - W(V) >= 0, the area of the
    loop, and a contact that opens loses the (1 - e^2) W(V_t) it kept. So the energy balance
    closes to the integrator's error instead of to first order in dt.

  A reversal below V_t reloads on the loading curve, not back along the unloading one (that would
  be Walton and Braun's elastic inner loop): each small oscillation of a resting contact then
  traces a loop and loses energy, so piles still come to rest. The prices: the force jumps up
  where a shrinking contact turns back to growing (by (1/e^2 - 1) W'' times the volume lost
  since V_t, small for a small oscillation); the unloading branch is stiffer than the loading
  one by 1/e^2 (the contact's frequency by 1/e), so at dt = "auto" a low e is resolved by fewer
  steps (50 e steps per period at the reference overlap: 15 for e = 0.3; below e of about 0.1
  take a smaller dt); and the force ends before the bodies separate (at V = (1 - e^2) V_t, a
  plastic dent that the bodies then leave freely);
* friction (only in the kernel variant built with friction): an elastic tangential spring xi
  carried from step to step for each persisting pair, turned into the current tangent plane
  (length kept), loaded by the tangential velocity at the contact point, with a dashpot of the
  damping ratio that e gives a linear oscillator, the sum capped at mu times the normal force; it
  acts at the contact point. The slip (at the spring's force), the dashpot's work and the spring
  energy left when a contact opens are counted as dissipated (see :func:`respond`).

Forces are written per pair and gathered per body in a fixed order (the pairs' sorted keys), so
that a run is bit-for-bit repeatable on a device: no floating-point atomics. The gather also adds
the contacts with the infinite planes (walls), which clip the body by one plane with the same
energy model.

Layout: :func:`make_wall_contact` builds the bookkeeping of one body's contact with one wall, which
the gather kernel (plane walls) and :mod:`polydem.kernels.meshwall` (mesh walls) share; the factory
:func:`make_contact_kernels` builds the pair and gather kernels for one contact law and friction
setting from the shared geometry and response functions; :func:`launch_pair_contacts` and
:func:`launch_gather` launch them on what the Protocols :class:`ContactModel`, :class:`BodyState`
and :class:`PairArrays` name (a Model, a State and the Contacts have it). The pair list's own
bookkeeping at a broad-phase rebuild is in :mod:`polydem.kernels.pairlist`.
"""

import functools
from dataclasses import dataclass, fields
from typing import Any, Protocol, Self

import warp as wp
from polydem.kernels.compound import make_body_geometry
from polydem.kernels.geometry import make_geometry
from polydem.kernels.narrowphase import NARROWPHASE_BLOCK_DIM
from polydem.kernels.precision import scalars
from polydem.kernels.response import make_response

# What the report variant of the step kernels (``report=True``) does besides the step, by bits of
# its ``report`` argument: write each contact's geometry and force into the diagnostics outputs (what
# Simulation.contacts() reads), and add each contact's force to the sums of an averaging interval.
REPORT_CONTACTS = wp.constant(1)
REPORT_SUMS = wp.constant(2)

# The default CUDA register cap of the pair kernel. Uncapped it takes about 200 registers, which
# leaves 12% of the warp slots active; at 128 twice as many warps hide the local-memory latency
# despite the spills (BENCHMARKS.md section 7c).
PAIR_MAX_REGISTERS = 128


@wp.struct
class ContactSums:
    """Per contact (a pair, or a (body, wall) at ``body * W + wall``), sums over the steps of an
    averaging interval, in float64 whatever the precision (a float32 sum of 10^6 steps would keep
    only a few digits): ``force`` on A [N] (normal and tangential), ``tangential`` force on A [N],
    ``normal`` force magnitude [N], contact ``point`` [m] (world), and the ``steps`` in contact."""

    force: wp.array(dtype=wp.vec3d)
    tangential: wp.array(dtype=wp.vec3d)
    normal: wp.array(dtype=wp.float64)
    point: wp.array(dtype=wp.vec3d)
    steps: wp.array(dtype=int)


@wp.func
def add_to_sums(sums: ContactSums, k: int, force: wp.vec3d, ft: wp.vec3d, fn: wp.float64, point: wp.vec3d):
    # One thread per contact (pair or body): plain adds, no atomics, the same order every run.
    sums.force[k] = sums.force[k] + force
    sums.tangential[k] = sums.tangential[k] + ft
    sums.normal[k] = sums.normal[k] + fn
    sums.point[k] = sums.point[k] + point
    sums.steps[k] = sums.steps[k] + 1


@dataclass(frozen=True)
class ContactKernels:
    """The contact kernels of one law, friction setting and polygon capacity."""

    law: str
    friction: bool
    diagnostics: bool
    precision: str
    report: bool
    geometry: Any  # polydem.kernels.geometry.Geometry
    respond: Any
    pair_contact_kernel: Any
    gather_kernel: Any


# What the launch functions read, by name: a polydem Model, State and Contacts have these members
# (kernels/ does not import the host package; any object with them will do, as Stepper.report's).


class ShapeArgs(Protocol):
    """A shape set (:class:`polydem.shapeset.ShapeSet`): the geometry kernels' ``shapes`` struct."""

    def kernel_args(self) -> list[Any]: ...


class ContactModel(Protocol):
    """The static arrays the contact kernels read (:class:`polydem.model.Model`): shapes, bodies,
    the material table (M x M, row-major by A's and B's material) and the plane walls."""

    num_bodies: int
    shapes: ShapeArgs
    body_shape: wp.array
    body_material: wp.array
    body_flags: wp.array
    body_inv_mass: wp.array
    num_materials: int
    material_k: wp.array
    material_e: wp.array
    material_mu: wp.array
    material_kt: wp.array
    law_m: float
    plane_normal: wp.array
    plane_offset: wp.array
    plane_material: wp.array


class BodyState(Protocol):
    """The bodies' arrays a step's force stage reads and writes (:class:`polydem.state.State`)."""

    body_q: wp.array
    body_v: wp.array
    body_w: wp.array
    plane_xi: wp.array
    plane_turn: wp.array
    body_dissipated: wp.array
    body_f: wp.array
    body_t: wp.array


class PairArrays(Protocol):
    """The candidate pairs and their per-pair arrays (:class:`polydem.contacts.Contacts`): ``capacity``
    entries each (``pair_xi``: 1 without friction), the first ``pair_count[0]`` of them pairs."""

    capacity: int

    # Read-only: the Contacts forward them from their broad phase.
    @property
    def pair_a(self) -> wp.array: ...
    @property
    def pair_b(self) -> wp.array: ...
    @property
    def pair_count(self) -> wp.array: ...

    pair_xi: wp.array
    pair_turn: wp.array
    pair_force: wp.array
    pair_torque_a: wp.array
    pair_dissipated: wp.array
    pair_by_b: wp.array
    body_pairs_a: wp.array
    body_pairs_b: wp.array


@dataclass
class ContactOutputs:
    """What the diagnostics and report variants write per contact: ``pair_*`` per candidate pair,
    ``plane_*`` per (body, wall column). The contact points are in the state's scalar (world
    positions), the rest in the contact scalar; ``plane_normal`` is written for the mesh walls only
    (a plane's normal is the plane's). The step variant takes them and writes none."""

    pair_volume: wp.array
    pair_energy: wp.array
    pair_normal: wp.array
    pair_point: wp.array
    pair_fn: wp.array
    pair_ft: wp.array
    pair_depth: wp.array
    plane_volume: wp.array
    plane_energy: wp.array
    plane_point: wp.array
    plane_fn: wp.array
    plane_ft: wp.array
    plane_depth: wp.array
    plane_normal: wp.array

    @classmethod
    def zeros(cls, pairs: int, bodies: int, walls: int, precision: str, device: Any) -> Self:
        """Zero arrays for ``pairs`` candidate pairs and ``bodies`` x ``walls`` wall columns."""
        S, C = scalars(precision)
        vec3s, vec3c = wp.types.vector(3, S), wp.types.vector(3, C)
        dtypes = {"volume": C, "energy": C, "normal": vec3c, "point": vec3s, "fn": C, "ft": vec3c, "depth": C}
        arrays = {}
        for f in fields(cls):
            prefix, quantity = f.name.split("_", 1)
            shape = pairs if prefix == "pair" else (bodies, walls)
            arrays[f.name] = wp.zeros(shape, dtype=dtypes[quantity], device=device)
        return cls(**arrays)

    def arrays(self) -> dict[str, wp.array]:
        """The arrays by name."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


@functools.cache
def make_wall_contact(law: str, friction: bool, diagnostics: bool, precision: str, report: bool):
    """``wall_contact``: one body's contact with one wall column, from its overlap geometry (with one
    plane, or summed over a mesh wall's cells) to the body's force, torque and energy dissipated, the
    column's turning volume and spring, and what the diagnostics and report variants write. The gather
    kernel runs it for the plane walls and the mesh-wall kernel for the mesh walls, so that both keep
    their books alike. Arguments as for :func:`make_contact_kernels`."""
    S, C = scalars(precision)
    vec3s = wp.types.vector(3, S)
    vec3c = wp.types.vector(3, C)
    resp = make_response(C, law, friction, diagnostics)
    law_energy = resp.law_energy
    toe_volume = resp.toe_volume
    respond = resp.respond
    zero3 = wp.constant(vec3c(C(0.0), C(0.0), C(0.0)))

    @wp.func
    def wall_contact(
        # The contact: body i, wall column j, material pair mat
        i: int,
        j: int,
        mat: int,
        # Its geometry (positions relative to the body's centre, world axes) and depth
        vol: C,
        first_moment: vec3c,
        s_a: vec3c,
        m_a: vec3c,
        fb_a: vec3c,
        depth: C,
        # The body (A) and the wall (B): B's reference point from A, the velocities, A's centre
        r_ab: vec3c,
        v_a: vec3c,
        w_a: vec3c,
        v_b: vec3c,
        w_b: vec3c,
        origin: vec3s,
        radius: C,
        face_area: C,
        inv_mass: C,
        # Model
        material_k: wp.array(dtype=C),
        material_e: wp.array(dtype=C),
        material_mu: wp.array(dtype=C),
        material_kt: wp.array(dtype=C),
        law_m: C,
        dt: C,
        # State in/out
        plane_xi: wp.array2d(dtype=vec3c),
        plane_turn: wp.array2d(dtype=C),
        # Out (diagnostics)
        plane_volume: wp.array2d(dtype=C),
        plane_energy: wp.array2d(dtype=C),
        plane_fn: wp.array2d(dtype=C),
        plane_point: wp.array2d(dtype=vec3s),
        plane_ft: wp.array2d(dtype=vec3c),
        plane_depth: wp.array2d(dtype=C),
        # Report (the report variant only)
        report_bits: int,
        wall_sums: ContactSums,
        # The body's sums so far
        f: vec3s,
        t: vec3s,
        lost: S,
    ):
        # Returns the body's sums with this contact and the contact's normal (zero when open).
        if vol <= C(0.0):
            # What the last impact never gave back (see the pair kernel) is dissipated as it opens.
            e_mat = material_e[mat]
            vc = toe_volume(material_k[mat], law_m, e_mat, dt, face_area, radius, inv_mass)
            kept = (C(1.0) - e_mat * e_mat) * law_energy(plane_turn[i, j], material_k[mat], law_m, vc)
            if wp.static(diagnostics):
                plane_volume[i, j] = C(0.0)
                plane_energy[i, j] = kept
                plane_fn[i, j] = C(0.0)
                plane_ft[i, j] = zero3
                plane_depth[i, j] = C(0.0)
            else:
                lost += S(kept)
                plane_turn[i, j] = C(0.0)
                if wp.static(friction):
                    xi = plane_xi[i, j]
                    lost += S(C(0.5) * material_kt[mat] * wp.dot(xi, xi))
                    plane_xi[i, j] = zero3
                if wp.static(report):
                    if (report_bits & REPORT_CONTACTS) != 0:
                        plane_volume[i, j] = C(0.0)
            return f, t, lost, zero3
        xi_in = zero3
        if wp.static(friction):
            xi_in = plane_xi[i, j]
        force, torque, xi, turn, energy, dl, n, point, fn, ft = respond(
            vol, first_moment, s_a, m_a, fb_a, r_ab, v_a, w_a, v_b, w_b,
            material_k[mat], law_m, material_e[mat], material_mu[mat], material_kt[mat], xi_in,
            plane_turn[i, j], dt, radius, face_area, inv_mass,
        )  # fmt: skip
        if wp.static(diagnostics):
            plane_volume[i, j] = vol
            plane_energy[i, j] = energy
            plane_fn[i, j] = fn
            plane_point[i, j] = vec3s(point) + origin
            plane_ft[i, j] = ft
            plane_depth[i, j] = depth
        else:
            if wp.static(friction):
                plane_xi[i, j] = xi
            plane_turn[i, j] = turn
            f += vec3s(force)
            t += vec3s(torque)
            lost += S(dl)
            if wp.static(report):
                world_point = vec3s(point) + origin
                if (report_bits & REPORT_CONTACTS) != 0:
                    plane_volume[i, j] = vol
                    plane_fn[i, j] = fn
                    plane_point[i, j] = world_point
                    plane_ft[i, j] = ft
                    plane_depth[i, j] = depth
                if (report_bits & REPORT_SUMS) != 0:
                    k = i * plane_turn.shape[1] + j
                    add_to_sums(wall_sums, k, wp.vec3d(force), wp.vec3d(ft), wp.float64(fn), wp.vec3d(world_point))
        return f, t, lost, n

    return wall_contact


@functools.cache
def make_contact_kernels(
    law: str,
    friction: bool,
    max_poly: int,
    max_faces: int,
    *,
    diagnostics: bool = False,
    precision: str = "float32",
    max_registers: int | None = PAIR_MAX_REGISTERS,
    compound: bool = False,
    report: bool = False,
) -> ContactKernels:
    """Kernels for one contact law ("linear", "hertz" or "power"), with or without friction.

    ``diagnostics`` builds the variant that reports contacts and energies without stepping.
    ``report`` builds the step variant that can also, by the bits of its ``report`` argument, write
    each contact as the step computed it into the diagnostics outputs (REPORT_CONTACTS: volume,
    normal, point, normal and tangential force, depth; no energy) and add its force to the sums of
    an averaging interval (REPORT_SUMS, :class:`ContactSums`); the plain step variant takes the same
    arguments and ignores them, so that it pays nothing for them.
    ``precision`` (:mod:`polydem.kernels.precision`) sets the scalar S of the body state (poses,
    velocities, body forces, torques and dissipated energy, wall normals and offsets, contact
    points) and the scalar C of the geometry, the response, the material table and the per-pair
    and per-wall arrays. In "mixed" (S float64, C float32) each pair is clipped in a frame centred
    on A, and each wall contact in one centred on the body, so that the float32 geometry sees
    coordinates of the bodies' size however far they are from the origin. ``max_registers`` caps
    the pair kernel's CUDA registers per thread (None: the compiler's choice; the results do not
    depend on it). ``compound`` builds the variant whose bodies may be compound grains
    (:mod:`polydem.kernels.compound`: the geometry loops over their parts).
    """
    S, C = scalars(precision)
    vec3s = wp.types.vector(3, S)
    vec3c = wp.types.vector(3, C)
    transform_s = wp.types.transformation(S)
    resp = make_response(C, law, friction, diagnostics)
    law_energy = resp.law_energy
    toe_volume = resp.toe_volume
    respond = resp.respond
    wall_contact = make_wall_contact(law, friction, diagnostics, precision, report)
    geom = make_geometry(C, max_poly, max_faces, pose_scalar=S)
    body_geom = make_body_geometry(geom, compound)
    Shapes = geom.shapes
    pair_geometry = body_geom.pair_geometry
    plane_geometry = body_geom.plane_geometry
    pair_depth_of = body_geom.pair_depth
    plane_depth_of = body_geom.plane_depth
    zero3 = wp.constant(vec3c(C(0.0), C(0.0), C(0.0)))

    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=max_registers)
    def pair_contact_kernel(
        # Model
        shapes: Shapes,
        body_shape: wp.array(dtype=int),
        body_material: wp.array(dtype=int),
        body_inv_mass: wp.array(dtype=S),
        num_materials: int,
        material_k: wp.array(dtype=C),
        material_e: wp.array(dtype=C),
        material_mu: wp.array(dtype=C),
        material_kt: wp.array(dtype=C),
        law_m: C,
        dt: C,
        # State in
        body_q: wp.array(dtype=transform_s),
        body_v: wp.array(dtype=vec3s),
        body_w: wp.array(dtype=vec3s),
        pair_a: wp.array(dtype=int),
        pair_b: wp.array(dtype=int),
        pair_count: wp.array(dtype=int),
        # State in/out
        pair_xi: wp.array(dtype=vec3c),
        pair_turn: wp.array(dtype=C),
        # Out (step)
        pair_force: wp.array(dtype=vec3c),
        pair_torque_a: wp.array(dtype=vec3c),
        pair_dissipated: wp.array(dtype=C),
        overflow: wp.array(dtype=int),
        # Out (diagnostics)
        pair_volume: wp.array(dtype=C),
        pair_energy: wp.array(dtype=C),
        pair_normal: wp.array(dtype=vec3c),
        pair_point: wp.array(dtype=vec3s),
        pair_fn: wp.array(dtype=C),
        pair_ft: wp.array(dtype=vec3c),
        pair_depth: wp.array(dtype=C),
        # Report (the report variant only)
        report_bits: int,
        pair_sums: ContactSums,
    ):
        """The step variant writes the wrench on A, the spring and the energy dissipated; the
        diagnostics variant (run on request only) writes what energy() reports, at the current
        state, and changes nothing; the report variant steps and reports (see the factory)."""
        p = wp.tid()
        if p >= pair_count[0]:
            return
        a = pair_a[p]
        b = pair_b[p]
        xa = body_q[a]
        xb = body_q[b]
        vol, first_moment, s_a, m_a, s_b, m_b, fb_a, of = pair_geometry(shapes, body_shape[a], body_shape[b], xa, xb)
        if of != 0:
            wp.atomic_max(overflow, 0, 1)
        mat = body_material[a] * num_materials + body_material[b]
        if vol <= C(0.0):
            # What the last impact never gave back, (1 - e^2) W(turn), is dissipated when the
            # contact opens (its force may have ended before, at u = 0); until the step books it,
            # it is still part of the contact's energy.
            e_mat = material_e[mat]
            r_min = wp.min(shapes.shape_radius[body_shape[a]], shapes.shape_radius[body_shape[b]])
            area = wp.min(shapes.shape_face_area[body_shape[a]], shapes.shape_face_area[body_shape[b]])
            vc = toe_volume(material_k[mat], law_m, e_mat, dt, area, r_min, C(body_inv_mass[a] + body_inv_mass[b]))
            kept = (C(1.0) - e_mat * e_mat) * law_energy(pair_turn[p], material_k[mat], law_m, vc)
            if wp.static(diagnostics):
                pair_volume[p] = C(0.0)
                pair_energy[p] = kept
                pair_fn[p] = C(0.0)
                pair_ft[p] = zero3
                pair_depth[p] = C(0.0)
            else:
                lost = kept
                pair_turn[p] = C(0.0)
                if wp.static(friction):
                    xi = pair_xi[p]
                    lost += C(0.5) * material_kt[mat] * wp.dot(xi, xi)  # the spring lets go
                    pair_xi[p] = zero3
                pair_force[p] = zero3
                pair_torque_a[p] = zero3
                pair_dissipated[p] = lost
                if wp.static(report):
                    if (report_bits & REPORT_CONTACTS) != 0:
                        pair_volume[p] = C(0.0)
            return
        r_ab = vec3c(wp.transform_get_translation(xb) - wp.transform_get_translation(xa))
        xi_in = zero3
        if wp.static(friction):
            xi_in = pair_xi[p]
        force, torque, xi, turn, energy, lost, n, point, fn, ft = respond(
            vol, first_moment, s_a, m_a, fb_a, r_ab,
            vec3c(body_v[a]), vec3c(body_w[a]), vec3c(body_v[b]), vec3c(body_w[b]),
            material_k[mat], law_m, material_e[mat], material_mu[mat], material_kt[mat], xi_in, pair_turn[p], dt,
            wp.min(shapes.shape_radius[body_shape[a]], shapes.shape_radius[body_shape[b]]),
            wp.min(shapes.shape_face_area[body_shape[a]], shapes.shape_face_area[body_shape[b]]),
            C(body_inv_mass[a] + body_inv_mass[b]),
        )  # fmt: skip
        if wp.static(diagnostics):
            pair_volume[p] = vol
            pair_energy[p] = energy
            pair_normal[p] = n
            pair_point[p] = vec3s(point) + wp.transform_get_translation(xa)
            pair_fn[p] = fn
            pair_ft[p] = ft
            pair_depth[p] = C(pair_depth_of(shapes, body_shape[a], body_shape[b], xa, xb))
        else:
            if wp.static(friction):
                pair_xi[p] = xi
            pair_turn[p] = turn
            pair_force[p] = force
            pair_torque_a[p] = torque
            pair_dissipated[p] = lost
            if wp.static(report):
                world_point = vec3s(point) + wp.transform_get_translation(xa)
                if (report_bits & REPORT_CONTACTS) != 0:
                    pair_volume[p] = vol
                    pair_normal[p] = n
                    pair_point[p] = world_point
                    pair_fn[p] = fn
                    pair_ft[p] = ft
                    pair_depth[p] = C(pair_depth_of(shapes, body_shape[a], body_shape[b], xa, xb))
                if (report_bits & REPORT_SUMS) != 0:
                    add_to_sums(pair_sums, p, wp.vec3d(force), wp.vec3d(ft), wp.float64(fn), wp.vec3d(world_point))

    @wp.kernel(enable_backward=False, module="unique")
    def gather_kernel(
        # Model
        shapes: Shapes,
        body_shape: wp.array(dtype=int),
        body_material: wp.array(dtype=int),
        body_flags: wp.array(dtype=int),
        body_inv_mass: wp.array(dtype=S),
        num_materials: int,
        material_k: wp.array(dtype=C),
        material_e: wp.array(dtype=C),
        material_mu: wp.array(dtype=C),
        material_kt: wp.array(dtype=C),
        law_m: C,
        dt: C,
        plane_normal: wp.array(dtype=vec3s),
        plane_offset: wp.array(dtype=S),
        plane_material: wp.array(dtype=int),
        # State in
        body_q: wp.array(dtype=transform_s),
        body_v: wp.array(dtype=vec3s),
        body_w: wp.array(dtype=vec3s),
        pair_a: wp.array(dtype=int),
        pair_b: wp.array(dtype=int),
        body_pairs_a: wp.array(dtype=wp.vec2i),
        body_pairs_b: wp.array(dtype=wp.vec2i),
        pair_by_b: wp.array(dtype=int),
        pair_force: wp.array(dtype=vec3c),
        pair_torque_a: wp.array(dtype=vec3c),
        pair_dissipated: wp.array(dtype=C),
        # State in/out
        plane_xi: wp.array2d(dtype=vec3c),
        plane_turn: wp.array2d(dtype=C),
        body_dissipated: wp.array(dtype=S),
        # Out (step)
        body_f: wp.array(dtype=vec3s),
        body_t: wp.array(dtype=vec3s),
        # Out (diagnostics)
        plane_volume: wp.array2d(dtype=C),
        plane_energy: wp.array2d(dtype=C),
        plane_fn: wp.array2d(dtype=C),
        plane_point: wp.array2d(dtype=vec3s),
        plane_ft: wp.array2d(dtype=vec3c),
        plane_depth: wp.array2d(dtype=C),
        # Report (the report variant only)
        report_bits: int,
        wall_sums: ContactSums,
    ):
        """Sums each body's pair wrenches in key order and adds its wall contacts (step variant);
        the diagnostics variant only reports the wall contacts; the report variant steps and reports
        its wall contacts (see the factory)."""
        i = wp.tid()
        f = vec3s(S(0.0), S(0.0), S(0.0))
        t = vec3s(S(0.0), S(0.0), S(0.0))
        lost = S(0.0)
        xi_pos = wp.transform_get_translation(body_q[i])
        # A fixed or kinematic body needs no force, and a container wall may touch a whole pile:
        # it skips its pairs (one thread would walk them all), and its free partners book the
        # energy lost in full.
        if wp.static(not diagnostics) and body_flags[i] == 0:
            ra = body_pairs_a[i]
            for p in range(ra[0], ra[1]):
                f += vec3s(pair_force[p])
                t += vec3s(pair_torque_a[p])
                share = S(0.5)
                if body_flags[pair_b[p]] != 0:
                    share = S(1.0)
                lost += share * S(pair_dissipated[p])
            rb = body_pairs_b[i]
            for k in range(rb[0], rb[1]):
                p = pair_by_b[k]
                fa = vec3s(pair_force[p])
                a = pair_a[p]
                r_ab = xi_pos - wp.transform_get_translation(body_q[a])
                f -= fa
                t += wp.cross(r_ab, fa) - vec3s(pair_torque_a[p])
                share = S(0.5)
                if body_flags[a] != 0:
                    share = S(1.0)
                lost += share * S(pair_dissipated[p])
        if body_flags[i] == 0:
            xa = body_q[i]
            s = body_shape[i]
            # The depth only for the diagnostics and a report of the contacts (not for the sums).
            want_depth = wp.static(diagnostics)
            if wp.static(report):
                want_depth = (report_bits & REPORT_CONTACTS) != 0
            for j in range(plane_normal.shape[0]):
                pn = plane_normal[j]
                vol, first_moment, s_a, m_a, fb_a = plane_geometry(shapes, s, xa, pn, plane_offset[j])
                mat = body_material[i] * num_materials + plane_material[j]
                depth = C(0.0)
                if wp.static(diagnostics or report):
                    if want_depth and vol > C(0.0):
                        depth = C(plane_depth_of(shapes, s, xa, pn, plane_offset[j]))
                f, t, lost, _ = wall_contact(
                    i, j, mat, vol, first_moment, s_a, m_a, fb_a, depth,
                    -vec3c(pn), vec3c(body_v[i]), vec3c(body_w[i]), zero3, zero3, xi_pos,
                    shapes.shape_radius[s], shapes.shape_face_area[s], C(body_inv_mass[i]),
                    material_k, material_e, material_mu, material_kt, law_m, dt,
                    plane_xi, plane_turn,
                    plane_volume, plane_energy, plane_fn, plane_point, plane_ft, plane_depth,
                    report_bits, wall_sums, f, t, lost,
                )  # fmt: skip
        if wp.static(not diagnostics):
            body_f[i] = f
            body_t[i] = t
            body_dissipated[i] = body_dissipated[i] + lost

    return ContactKernels(
        law=law,
        friction=friction,
        diagnostics=diagnostics,
        precision=precision,
        report=report,
        geometry=geom,
        respond=respond,
        pair_contact_kernel=pair_contact_kernel,
        gather_kernel=gather_kernel,
    )


# ---------------------------------------------------------------------------------------------
# Launch functions
# ---------------------------------------------------------------------------------------------


def material_args(model: ContactModel, dt: float) -> list[Any]:
    """The material table, the law's exponent and the step, in the order every contact kernel takes them."""
    m = model
    return [m.num_materials, m.material_k, m.material_e, m.material_mu, m.material_kt, m.law_m, dt]


def launch_pair_contacts(
    kernels: ContactKernels,
    *,
    model: ContactModel,
    state: BodyState,
    pairs: PairArrays,
    dt: float,
    overflow: wp.array,
    out: ContactOutputs,
    report_bits: int,
    pair_sums: ContactSums,
) -> None:
    """The pair kernel of ``kernels``, one thread per candidate pair: each pair's wrench on A, spring,
    turning volume and energy dissipated into ``pairs`` (the step and report variants), its contact
    into ``out`` (the diagnostics variant; the report variant by ``report_bits``), its force into
    ``pair_sums`` (the report variant, ``REPORT_SUMS``). A clipped polygon that did not fit sets
    ``overflow``. ``out`` and ``pair_sums`` may be placeholders of one entry where nothing is written
    to them."""
    m = model
    wp.launch(
        kernels.pair_contact_kernel,
        dim=pairs.capacity,
        inputs=[
            # Model
            *m.shapes.kernel_args(),
            m.body_shape,
            m.body_material,
            m.body_inv_mass,
            *material_args(m, dt),
            # State in
            state.body_q,
            state.body_v,
            state.body_w,
            pairs.pair_a,
            pairs.pair_b,
            pairs.pair_count,
            # State in/out
            pairs.pair_xi,
            pairs.pair_turn,
        ],
        outputs=[
            # Out (step)
            pairs.pair_force,
            pairs.pair_torque_a,
            pairs.pair_dissipated,
            overflow,
            # Out (diagnostics)
            out.pair_volume,
            out.pair_energy,
            out.pair_normal,
            out.pair_point,
            out.pair_fn,
            out.pair_ft,
            out.pair_depth,
            # Report
            int(report_bits),
            pair_sums,
        ],
        device=state.body_q.device,
        block_dim=NARROWPHASE_BLOCK_DIM,
    )


def launch_gather(
    kernels: ContactKernels,
    *,
    model: ContactModel,
    state: BodyState,
    pairs: PairArrays,
    dt: float,
    out: ContactOutputs,
    report_bits: int,
    wall_sums: ContactSums,
) -> None:
    """The gather kernel of ``kernels``, one thread per body, after :func:`launch_pair_contacts`: each
    body's pair wrenches in key order plus its plane-wall contacts into ``state.body_f`` and
    ``body_t`` (the step and report variants), its wall contacts into ``out`` and ``wall_sums`` as
    the pair kernel does."""
    m = model
    wp.launch(
        kernels.gather_kernel,
        dim=m.num_bodies,
        inputs=[
            # Model
            *m.shapes.kernel_args(),
            m.body_shape,
            m.body_material,
            m.body_flags,
            m.body_inv_mass,
            *material_args(m, dt),
            m.plane_normal,
            m.plane_offset,
            m.plane_material,
            # State in
            state.body_q,
            state.body_v,
            state.body_w,
            pairs.pair_a,
            pairs.pair_b,
            pairs.body_pairs_a,
            pairs.body_pairs_b,
            pairs.pair_by_b,
            pairs.pair_force,
            pairs.pair_torque_a,
            pairs.pair_dissipated,
            # State in/out
            state.plane_xi,
            state.plane_turn,
            state.body_dissipated,
        ],
        outputs=[
            # Out (step)
            state.body_f,
            state.body_t,
            # Out (diagnostics)
            out.plane_volume,
            out.plane_energy,
            out.plane_fn,
            out.plane_point,
            out.plane_ft,
            out.plane_depth,
            # Report
            int(report_bits),
            wall_sums,
        ],
        device=state.body_q.device,
    )
