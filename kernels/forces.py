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

Layout: the factory :func:`make_contact_kernels` builds the pair and gather kernels for one contact
law and friction setting from the shared geometry and response functions; the pair bookkeeping
kernels of a broad-phase rebuild follow it.
"""

import functools
from dataclasses import dataclass
from typing import Any

import warp as wp
from polydem.kernels.compound import make_body_geometry
from polydem.kernels.geometry import DEFAULT_PAIR_VARIANT, make_geometry
from polydem.kernels.precision import scalars
from polydem.kernels.response import make_response

# What the report variant of the step kernels (``report=True``) does besides the step, by bits of
# its ``report`` argument: write each contact's geometry and force into the diagnostics outputs (what
# Simulation.contacts() reads), and add each contact's force to the sums of an averaging interval.
REPORT_CONTACTS = wp.constant(1)
REPORT_SUMS = wp.constant(2)


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


# CUDA register cap of the step's pair kernel (None: the compiler's choice). Uncapped it takes about
# 200 registers, which leaves 12% of the warp slots active; at 128 twice as many warps hide the
# local-memory latency despite the spills (BENCHMARKS.md section 7). A module setting so that
# benchmarks can compare caps (benchmarks/settle.py --max-registers).
PAIR_MAX_REGISTERS: int | None = 128


def make_contact_kernels(*args, max_registers: int | None = None, **kwargs):
    """:func:`_make_contact_kernels` with the register cap resolved (see there)."""
    return _make_contact_kernels(
        *args, max_registers=PAIR_MAX_REGISTERS if max_registers is None else max_registers, **kwargs
    )


@functools.cache
def _make_contact_kernels(
    law: str,
    friction: bool,
    max_poly: int,
    max_faces: int,
    diagnostics: bool = False,
    precision: str = "float32",
    max_registers: int | None = None,
    variant: str = DEFAULT_PAIR_VARIANT,
    compound: bool = False,
    report: bool = False,
):
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
    coordinates of the bodies' size however far they are from the origin. ``variant`` picks how
    the pair geometry holds its working set (:func:`polydem.kernels.geometry.make_geometry`).
    ``max_registers`` caps the pair kernel's CUDA registers per thread (default
    :data:`PAIR_MAX_REGISTERS`). ``compound`` builds the variant whose bodies may be compound
    grains (:mod:`polydem.kernels.compound`: the geometry loops over their parts).
    """
    S, C = scalars(precision)
    vec3s = wp.types.vector(3, S)
    vec3c = wp.types.vector(3, C)
    transform_s = wp.types.transformation(S)
    resp = make_response(C, law, friction, diagnostics)
    law_energy = resp.law_energy
    toe_volume = resp.toe_volume
    respond = resp.respond
    geom = make_geometry(C, max_poly, max_faces, pose_scalar=S, variant=variant)
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
            for j in range(plane_normal.shape[0]):
                pn = plane_normal[j]
                vol, first_moment, s_a, m_a, fb_a = plane_geometry(shapes, s, xa, pn, plane_offset[j])
                mat = body_material[i] * num_materials + plane_material[j]
                if vol <= C(0.0):
                    e_mat = material_e[mat]
                    area = shapes.shape_face_area[s]
                    r_s = shapes.shape_radius[s]
                    vc = toe_volume(material_k[mat], law_m, e_mat, dt, area, r_s, C(body_inv_mass[i]))
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
                    continue
                xi_in = zero3
                if wp.static(friction):
                    xi_in = plane_xi[i, j]
                force, torque, xi, turn, energy, dl, n, point, fn, ft = respond(
                    vol, first_moment, s_a, m_a, fb_a, -vec3c(pn), vec3c(body_v[i]), vec3c(body_w[i]), zero3, zero3,
                    material_k[mat], law_m, material_e[mat], material_mu[mat], material_kt[mat], xi_in,
                    plane_turn[i, j], dt,
                    shapes.shape_radius[s], shapes.shape_face_area[s], C(body_inv_mass[i]),
                )  # fmt: skip
                if wp.static(diagnostics):
                    plane_volume[i, j] = vol
                    plane_energy[i, j] = energy
                    plane_fn[i, j] = fn
                    plane_point[i, j] = vec3s(point) + xi_pos
                    plane_ft[i, j] = ft
                    plane_depth[i, j] = C(plane_depth_of(shapes, s, xa, pn, plane_offset[j]))
                else:
                    if wp.static(friction):
                        plane_xi[i, j] = xi
                    plane_turn[i, j] = turn
                    f += vec3s(force)
                    t += vec3s(torque)
                    lost += S(dl)
                    if wp.static(report):
                        world_point = vec3s(point) + xi_pos
                        if (report_bits & REPORT_CONTACTS) != 0:
                            plane_volume[i, j] = vol
                            plane_fn[i, j] = fn
                            plane_point[i, j] = world_point
                            plane_ft[i, j] = ft
                            plane_depth[i, j] = C(plane_depth_of(shapes, s, xa, pn, plane_offset[j]))
                        if (report_bits & REPORT_SUMS) != 0:
                            k = i * plane_turn.shape[1] + j
                            add_to_sums(
                                wall_sums, k, wp.vec3d(force), wp.vec3d(ft), wp.float64(fn), wp.vec3d(world_point)
                            )
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
# Pair bookkeeping at a broad-phase rebuild (no floating point: deterministic by construction)


@wp.func
def lower_bound(keys: wp.array(dtype=wp.int64), count: int, key: wp.int64):
    lo = int(0)
    hi = count
    while lo < hi:
        mid = (lo + hi) // 2
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.kernel(enable_backward=False)
def b_keys_kernel(
    # Model
    num_bodies: int,
    sentinel: wp.int64,
    # State in
    pair_a: wp.array(dtype=int),
    pair_b: wp.array(dtype=int),
    pair_count: wp.array(dtype=int),
    # Out
    keys_b: wp.array(dtype=wp.int64),
    pair_by_b: wp.array(dtype=int),
):
    """Keys ``b * N + a`` (sentinel past the count) with the pair index, to sort by the B body."""
    p = wp.tid()
    if p < pair_count[0]:
        keys_b[p] = wp.int64(pair_b[p]) * wp.int64(num_bodies) + wp.int64(pair_a[p])
    else:
        keys_b[p] = sentinel
    pair_by_b[p] = p


@wp.kernel(enable_backward=False)
def body_ranges_kernel(
    # Model
    num_bodies: int,
    # State in
    pair_key: wp.array(dtype=wp.int64),
    keys_b: wp.array(dtype=wp.int64),
    pair_count: wp.array(dtype=int),
    # Out
    body_pairs_a: wp.array(dtype=wp.vec2i),
    body_pairs_b: wp.array(dtype=wp.vec2i),
):
    """Each body's ranges in the pairs sorted by (a, b) and in those sorted by (b, a)."""
    i = wp.tid()
    count = pair_count[0]
    n = wp.int64(num_bodies)
    lo = wp.int64(i) * n
    hi = lo + n
    body_pairs_a[i] = wp.vec2i(lower_bound(pair_key, count, lo), lower_bound(pair_key, count, hi))
    body_pairs_b[i] = wp.vec2i(lower_bound(keys_b, count, lo), lower_bound(keys_b, count, hi))


@functools.cache
def make_remap_history_kernel(scalar):
    """The kernel that carries the pair history (in ``scalar``) over a rebuild."""
    vec3 = wp.types.vector(3, scalar)

    @wp.kernel(enable_backward=False, module="unique")
    def remap_history_kernel(
        # State in
        old_key: wp.array(dtype=wp.int64),
        old_count: wp.array(dtype=int),
        old_xi: wp.array(dtype=vec3),
        old_turn: wp.array(dtype=scalar),
        new_key: wp.array(dtype=wp.int64),
        new_count: wp.array(dtype=int),
        friction: int,
        # Out
        new_xi: wp.array(dtype=vec3),
        new_turn: wp.array(dtype=scalar),
    ):
        """Carries each pair's history (turning volume; friction spring, with ``friction``) over a
        rebuild, matched by the pair's key."""
        p = wp.tid()
        xi = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        turn = scalar(0.0)
        if p < new_count[0]:
            key = new_key[p]
            count = old_count[0]
            j = lower_bound(old_key, count, key)
            if j < count and old_key[j] == key:
                turn = old_turn[j]
                if friction != 0:
                    xi = old_xi[j]
        new_turn[p] = turn
        if friction != 0:
            new_xi[p] = xi

    return remap_history_kernel


@wp.kernel(enable_backward=False)
def remap_sums_kernel(
    # State in
    old_key: wp.array(dtype=wp.int64),
    old_count: wp.array(dtype=int),
    old_sums: ContactSums,
    new_key: wp.array(dtype=wp.int64),
    new_count: wp.array(dtype=int),
    # Out
    new_sums: ContactSums,
):
    """Carries each pair's sums of an averaging interval over a rebuild, matched by the pair's key
    (zero for a new pair and past the count)."""
    p = wp.tid()
    zero3 = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    force = zero3
    tangential = zero3
    normal = wp.float64(0.0)
    point = zero3
    steps = int(0)
    if p < new_count[0]:
        key = new_key[p]
        count = old_count[0]
        j = lower_bound(old_key, count, key)
        if j < count and old_key[j] == key:
            force = old_sums.force[j]
            tangential = old_sums.tangential[j]
            normal = old_sums.normal[j]
            point = old_sums.point[j]
            steps = old_sums.steps[j]
    new_sums.force[p] = force
    new_sums.tangential[p] = tangential
    new_sums.normal[p] = normal
    new_sums.point[p] = point
    new_sums.steps[p] = steps


@wp.kernel(enable_backward=False)
def retire_sums_kernel(
    # State in
    old_key: wp.array(dtype=wp.int64),
    old_count: wp.array(dtype=int),
    old_sums: ContactSums,
    new_key: wp.array(dtype=wp.int64),
    new_count: wp.array(dtype=int),
    # In/out
    retired_key: wp.array(dtype=wp.int64),
    retired: ContactSums,
    retired_count: wp.array(dtype=int),
    overflow: wp.array(dtype=int),
):
    """Appends the sums of each pair that a rebuild drops from the list after it was in contact in
    the interval, so that they count in the average. The slots are taken atomically: entries of
    different keys may come in any order, but those of one key are in the order of the rebuilds
    (one launch each); past the capacity, ``overflow`` is set (the chunk is redone with more room)."""
    p = wp.tid()
    if p >= old_count[0]:
        return
    if old_sums.steps[p] == 0:
        return
    key = old_key[p]
    count = new_count[0]
    j = lower_bound(new_key, count, key)
    if j < count and new_key[j] == key:
        return
    slot = wp.atomic_add(retired_count, 0, 1)
    if slot >= retired_key.shape[0]:
        wp.atomic_max(overflow, 0, 1)
        return
    retired_key[slot] = key
    retired.force[slot] = old_sums.force[p]
    retired.tangential[slot] = old_sums.tangential[p]
    retired.normal[slot] = old_sums.normal[p]
    retired.point[slot] = old_sums.point[p]
    retired.steps[slot] = old_sums.steps[p]
