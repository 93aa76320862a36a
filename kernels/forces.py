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
  energy left when a contact opens are counted as dissipated (see :func:`respond`). The dashpots are
  explicit: where the dashpots of a body's contacts at the last step would, summed, change the velocity
  at its rim by more than DAMPING_SHARE of it in a step (its damping load, :func:`launch_damping_load`),
  each of its contacts' dashpots is scaled down to that share (kernels/response.py).

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
from polydem.kernels.response import DAMPING_SHARE, make_response
from polydem.kernels.structs import output_dtypes, outputs_struct, struct_types

# What the report variant of the step kernels (``report=True``) does besides the step, by bits of
# its ``report`` argument: write each contact's geometry and force into the diagnostics outputs (what
# Simulation.contacts() reads), and add each contact's force to the sums of an averaging interval.
REPORT_CONTACTS = wp.constant(1)
REPORT_SUMS = wp.constant(2)

# The default CUDA register cap of the pair kernel. Uncapped it takes about 200 registers, which
# leaves 12% of the warp slots active; at 128 twice as many warps hide the local-memory latency
# despite the spills (BENCHMARKS.md section 7c).
PAIR_MAX_REGISTERS = 128

SPREAD_LANES = 8
"""Lanes a spread pair takes (a power of two; :func:`make_contact_kernels`' ``spread``): one pair every 8 lanes, 4 to a
warp. A warp runs its lanes' paths through the clipping in lock step, so that 32 different pairs took 1.8x (cubes) to
5x (64-vertex hulls) one pair's time on an H200; 4 to a warp, 0.8x (cubes) and 0.6-0.8x (rocks) of 32 to a warp,
where the launch is one wave (BENCHMARKS.md 28b)."""

SPREAD_CAPACITY_WAVES = 4
"""The spread variant of the pair kernel runs while the pair buffers hold at most this many waves of pairs (or
:data:`SPREAD_MIN_CAPACITY`; :func:`spread_fits`): a list over two waves spreads nothing, and there the variant's idle
threads and its mapping of threads to pairs cost the long lists of large piles 1.2% (BENCHMARKS.md 29)."""
SPREAD_MIN_CAPACITY = 4096
"""Pair buffers this small never hold a list that is throughput-bound."""


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


@dataclass(frozen=True, eq=False)
class ContactKernels:
    """The contact kernels of one law, friction setting and polygon capacity (one object per variant:
    :func:`make_contact_kernels` is cached), with the functions they are made of."""

    law: str
    friction: bool
    diagnostics: bool
    precision: str
    report: bool
    compound: bool
    max_registers: int | None
    thread_order: bool
    phased: bool
    spread: bool
    shared_poly: bool
    geometry: Any  # polydem.kernels.geometry.Geometry
    body_geometry: Any  # polydem.kernels.compound.BodyGeometry
    respond: Any
    wall_contact: Any
    pair_contact_kernel: Any
    gather_kernel: Any
    damping_load_kernel: Any


# What the launch functions read, by name: a polydem Model, State and Contacts have these members
# (kernels/ does not import the host package; any object with them will do, as Stepper.report's).


class ShapeArgs(Protocol):
    """A shape set (:class:`polydem.shapeset.ShapeSet`): the geometry kernels' ``shapes`` struct."""

    def kernel_args(self) -> list[Any]: ...


class ContactModel(Protocol):
    """What the contact kernels read of a model (:class:`polydem.model.Model`): the shapes, and the
    structs (:mod:`polydem.kernels.structs`) of the bodies' static arrays (``bodies``), the material
    table (``materials``) and the plane walls (``planes``)."""

    num_bodies: int
    shapes: ShapeArgs
    bodies: Any  # body_model_struct(S)
    materials: Any  # materials_struct(C)
    planes: Any  # planes_struct(S)
    wall_material: wp.array  # (W,) int32


class BodyState(Protocol):
    """What a step's force stage reads and writes of a state (:class:`polydem.state.State`): the structs
    of the bodies' arrays (``bodies``) and of the wall contacts' history (``walls``), and the bodies'
    damping loads (``body_damping``, :func:`launch_damping_load`)."""

    bodies: Any  # bodies_struct(S)
    walls: Any  # wall_history_struct(C)
    body_damping: wp.array  # (N,) float32


@wp.func
def damping_scale(load_a: wp.float32, load_b: wp.float32):
    """What a contact's tangential dashpot is scaled by (float32): DAMPING_SHARE over the larger damping
    load of its two bodies where that exceeds DAMPING_SHARE, else 1 (a fixed body or a wall has load 0)."""
    load = wp.max(load_a, load_b)
    if load > wp.float32(DAMPING_SHARE):
        return wp.float32(DAMPING_SHARE) / load
    return wp.float32(1.0)


class PairArrays(Protocol):
    """The candidate pairs and their per-pair arrays (:class:`polydem.contacts.Contacts`), in the struct
    ``pairs`` (:func:`polydem.kernels.structs.pairs_struct`): ``capacity`` entries each (``xi``: 1 without
    friction), the first ``count[0]`` of them pairs."""

    capacity: int
    pairs: Any  # pairs_struct(C)


@dataclass
class ContactOutputs:
    """What the diagnostics and report variants write per contact: ``pair_*`` per candidate pair,
    ``wall_*`` per (body, wall column). The contact points are in the state's scalar (world
    positions), the rest in the contact scalar; ``wall_normal`` is written for the mesh walls only
    (a plane's normal is the plane's). The step variant takes them and writes none. ``pairs`` and
    ``walls`` hold the ``pair_*`` and ``wall_*`` arrays as the kernels take them (:func:`outputs_struct`)."""

    pair_volume: wp.array
    pair_energy: wp.array
    pair_normal: wp.array
    pair_point: wp.array
    pair_fn: wp.array
    pair_ft: wp.array
    pair_depth: wp.array
    wall_volume: wp.array
    wall_energy: wp.array
    wall_point: wp.array
    wall_fn: wp.array
    wall_ft: wp.array
    wall_depth: wp.array
    wall_normal: wp.array

    @classmethod
    def zeros(cls, pairs: int, bodies: int, walls: int, precision: str, device: Any) -> Self:
        """Zero arrays for ``pairs`` candidate pairs and ``bodies`` x ``walls`` wall columns."""
        dtypes = output_dtypes(*scalars(precision))
        arrays = {}
        for f in fields(cls):
            prefix, quantity = f.name.split("_", 1)
            shape = pairs if prefix == "pair" else (bodies, walls)
            arrays[f.name] = wp.zeros(shape, dtype=dtypes[quantity], device=device)
        return cls(**arrays)

    def __post_init__(self):
        # The state scalar from the points' vectors, the contact scalar from the volumes.
        S = wp.float64 if wp.types.types_equal(self.wall_point.dtype, wp.vec3d) else wp.float32
        C = self.wall_volume.dtype
        for prefix, walls in (("pair", False), ("wall", True)):
            columns = outputs_struct(S, C, walls)()
            for quantity in output_dtypes(S, C):
                setattr(columns, quantity, getattr(self, f"{prefix}_{quantity}"))
            setattr(self, f"{prefix}s", columns)

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
    T = struct_types(precision)
    resp = make_response(C, law, friction, diagnostics)
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
        damping: C,
        # Model
        materials: T.Materials,
        dt: C,
        # State in/out
        walls: T.WallHistory,
        # Out (diagnostics; no normal)
        out: T.WallOutputs,
        # Report (the report variant only)
        report_bits: int,
        wall_sums: ContactSums,
        # The body's sums so far
        f: vec3s,
        t: vec3s,
        lost: S,
    ):
        # Returns the body's sums with this contact and the contact's normal (zero when open). ``damping``: the
        # dashpot's scale (damping_scale of the body's load).
        if vol <= C(0.0):
            kept = resp.kept_energy(
                walls.turn[i, j], materials.k[mat], materials.law_m, materials.e[mat], materials.toe_dt, face_area,
                radius, inv_mass,
            )  # fmt: skip
            if wp.static(diagnostics):
                out.volume[i, j] = C(0.0)
                out.energy[i, j] = kept
                out.fn[i, j] = C(0.0)
                out.ft[i, j] = zero3
                out.depth[i, j] = C(0.0)
            else:
                lost += S(kept)
                walls.turn[i, j] = C(0.0)
                if wp.static(friction):
                    xi = walls.xi[i, j]
                    lost += S(C(0.5) * materials.kt[mat] * wp.dot(xi, xi))
                    walls.xi[i, j] = zero3
                if wp.static(report):
                    if (report_bits & REPORT_CONTACTS) != 0:
                        out.volume[i, j] = C(0.0)
            return f, t, lost, zero3
        xi_in = zero3
        if wp.static(friction):
            xi_in = walls.xi[i, j]
        force, torque, xi, turn, energy, dl, n, point, fn, ft = resp.respond(
            vol, first_moment, s_a, m_a, fb_a, r_ab, v_a, w_a, v_b, w_b,
            materials.k[mat], materials.law_m, materials.e[mat], materials.mu[mat], materials.kt[mat], xi_in,
            walls.turn[i, j], dt, materials.toe_dt, radius, face_area, inv_mass, damping,
        )  # fmt: skip
        if wp.static(diagnostics):
            out.volume[i, j] = vol
            out.energy[i, j] = energy
            out.fn[i, j] = fn
            out.point[i, j] = vec3s(point) + origin
            out.ft[i, j] = ft
            out.depth[i, j] = depth
        else:
            if wp.static(friction):
                walls.xi[i, j] = xi
            walls.turn[i, j] = turn
            f += vec3s(force)
            t += vec3s(torque)
            lost += S(dl)
            if wp.static(report):
                world_point = vec3s(point) + origin
                if (report_bits & REPORT_CONTACTS) != 0:
                    out.volume[i, j] = vol
                    out.fn[i, j] = fn
                    out.point[i, j] = world_point
                    out.ft[i, j] = ft
                    out.depth[i, j] = depth
                if (report_bits & REPORT_SUMS) != 0:
                    k = i * walls.turn.shape[1] + j
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
    thread_order: bool = False,
    phased: bool = False,
    spread: bool = False,
    shared_poly: bool = False,
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
    (:mod:`polydem.kernels.compound`: the geometry loops over their parts). ``thread_order``: thread t of the
    pair kernel takes pair ``pairs.thread[t]`` (pairs grouped by cost, and by contact at the last rebuild:
    :func:`polydem.kernels.pairlist.launch_thread_order`) instead of pair t; the same results, bit for bit.
    ``phased``: the pair and gather kernels can run a step's force stage in two launches each (their ``phase``
    argument, with ``body_first`` (N,) int32): phase 1 takes the pairs with a body flagged in ``body_first``
    and gathers the flagged bodies, phase 2 the rest, phase 0 everything; every pair and body is computed as in
    one launch, so the same bits. A decomposed run (:mod:`polydem.distributed`) flags the bodies it sends, so
    that their new state is known, and on its way, before the rest of the step has run. Without ``phased`` the
    kernels take the two arguments and never read them.
    ``spread`` (with ``thread_order`` grouped by contact, costliest first; not ``phased``): the first pairs of the
    thread order take :data:`SPREAD_LANES` lanes each, one computing and the others idle, and the rest one lane
    each, so that a warp runs 4 pairs' paths in lock step, not 32: as many as fit a launch of ``spread_threads``
    threads (the pair kernel's arguments; a wave: below about 1e4 grains the step waits for its slowest warps), or
    more, where the list is at most two such waves, the pairs of costly shapes (``costly[0]``,
    :func:`polydem.kernels.pairlist.launch_thread_order`), whose paths differ the most; at most ``spread_pairs``.
    The same results, bit for bit.
    ``shared_poly``: the pair kernel's polygon buffer in the block's shared memory on a GPU
    (:func:`polydem.kernels.geometry.make_geometry`'s; float32 clipping, at most 63 vertices); the wall kernels keep
    theirs per thread. The same results, bit for bit.
    """
    if spread and not (thread_order and not phased):
        raise ValueError("spread needs thread_order and not phased")
    S, C = scalars(precision)
    vec3s = wp.types.vector(3, S)
    vec3c = wp.types.vector(3, C)
    T = struct_types(precision)
    resp = make_response(C, law, friction, diagnostics)
    wall_contact = make_wall_contact(law, friction, diagnostics, precision, report)
    geom = make_geometry(C, max_poly, max_faces, pose_scalar=S)
    body_geom = make_body_geometry(geom, compound)
    # The pair kernel's own clipping: the shared buffer is laid out for the blocks it is launched with, not the
    # mesh walk's.
    pair_geom = body_geom
    if shared_poly:
        pair_geom = make_body_geometry(make_geometry(C, max_poly, max_faces, pose_scalar=S, shared_poly=True), compound)
    zero3 = wp.constant(vec3c(C(0.0), C(0.0), C(0.0)))

    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=max_registers)
    def pair_contact_kernel(
        # Model
        shapes: geom.shapes,
        model: T.BodyModel,
        materials: T.Materials,
        dt: C,
        # State in: the bodies and their damping loads; in/out: the pairs' history; out (step): their wrench and
        # energy lost
        bodies: T.Bodies,
        body_damping: wp.array(dtype=wp.float32),
        pairs: T.Pairs,
        overflow: wp.array(dtype=int),
        # Out (diagnostics)
        out: T.PairOutputs,
        # Report (the report variant only)
        report_bits: int,
        pair_sums: ContactSums,
        # Phases (the phased variant only): (N,) 1 for the bodies of phase 1; 0 all pairs, 1 or 2 one phase's;
        # with thread_order, (1,) the number of phase 1's pairs, which the thread order puts first
        body_first: wp.array(dtype=wp.int32),
        phase: int,
        first_count: wp.array(dtype=int),
        # Spread (the spread variant only): at most spread_pairs of the first pairs of the thread order take
        # SPREAD_LANES lanes: as many as spread_threads threads leave room for, or the costly pairs ((1,) costly)
        spread_pairs: int,
        spread_threads: int,
        costly: wp.array(dtype=int),
    ):
        """The step variant writes the wrench on A, the spring and the energy dissipated; the
        diagnostics variant (run on request only) writes what energy() reports, at the current
        state, and changes nothing; the report variant steps and reports (see the factory)."""
        p = wp.tid()
        if wp.static(phased and thread_order):
            # Phase 1's pairs come first in the thread order (Contacts.split_at): each phase takes its own range.
            if phase == 1:
                if p >= first_count[0]:
                    return
            elif phase == 2:
                p = p + first_count[0]
        if wp.static(spread):
            # Threads [0, s L) hold the first s pairs, one every SPREAD_LANES lanes; the rest one pair each.
            listed = pairs.count[0]
            room = wp.max(spread_threads - listed, 0) / wp.static(SPREAD_LANES - 1)
            # The costly pairs where the list is at most two waves: measured there (a mixed pile of 1e4 grains,
            # 1.25 waves: -36%); a longer list is bound by the GPU's throughput, which the idle lanes would take.
            costly_here = int(0)
            if listed <= 2 * spread_threads:
                costly_here = costly[0]
            s = wp.min(wp.min(listed, spread_pairs), wp.max(room, costly_here))
            if p < s * wp.static(SPREAD_LANES):
                if (p & wp.static(SPREAD_LANES - 1)) != 0:
                    return
                p = p >> wp.static(SPREAD_LANES.bit_length() - 1)
            else:
                p = p - s * wp.static(SPREAD_LANES - 1)
        if p >= pairs.count[0]:
            return
        if wp.static(thread_order):
            p = pairs.thread[p]
        a = pairs.a[p]
        b = pairs.b[p]
        if wp.static(phased and not thread_order):
            first = body_first[a] + body_first[b] > 0
            if (phase == 1 and not first) or (phase == 2 and first):
                return
        xa = bodies.q[a]
        xb = bodies.q[b]
        vol, first_moment, s_a, m_a, s_b, m_b, fb_a, of = pair_geom.pair_geometry(
            shapes, model.shape[a], model.shape[b], xa, xb
        )
        if of != 0:
            wp.atomic_max(overflow, 0, 1)
        mat = model.material[a] * materials.count + model.material[b]
        r_min = wp.min(shapes.shape_radius[model.shape[a]], shapes.shape_radius[model.shape[b]])
        area = wp.min(shapes.shape_face_area[model.shape[a]], shapes.shape_face_area[model.shape[b]])
        inv_mass = C(model.inv_mass[a] + model.inv_mass[b])
        if vol <= C(0.0):
            # Until the step books what an opening contact kept, it is still part of its energy.
            kept = resp.kept_energy(
                pairs.turn[p], materials.k[mat], materials.law_m, materials.e[mat], materials.toe_dt, area, r_min,
                inv_mass,
            )  # fmt: skip
            if wp.static(diagnostics):
                out.volume[p] = C(0.0)
                out.energy[p] = kept
                out.fn[p] = C(0.0)
                out.ft[p] = zero3
                out.depth[p] = C(0.0)
            else:
                lost = kept
                pairs.turn[p] = C(0.0)
                if wp.static(friction):
                    xi = pairs.xi[p]
                    lost += C(0.5) * materials.kt[mat] * wp.dot(xi, xi)  # the spring lets go
                    pairs.xi[p] = zero3
                pairs.force[p] = zero3
                pairs.torque_a[p] = zero3
                pairs.dissipated[p] = lost
                if wp.static(report):
                    if (report_bits & REPORT_CONTACTS) != 0:
                        out.volume[p] = C(0.0)
            return
        r_ab = vec3c(wp.transform_get_translation(xb) - wp.transform_get_translation(xa))
        xi_in = zero3
        if wp.static(friction):
            xi_in = pairs.xi[p]
        force, torque, xi, turn, energy, lost, n, point, fn, ft = resp.respond(
            vol, first_moment, s_a, m_a, fb_a, r_ab,
            vec3c(bodies.v[a]), vec3c(bodies.w[a]), vec3c(bodies.v[b]), vec3c(bodies.w[b]),
            materials.k[mat], materials.law_m, materials.e[mat], materials.mu[mat], materials.kt[mat], xi_in,
            pairs.turn[p], dt, materials.toe_dt, r_min, area, inv_mass,
            C(damping_scale(body_damping[a], body_damping[b])),
        )  # fmt: skip
        if wp.static(diagnostics):
            out.volume[p] = vol
            out.energy[p] = energy
            out.normal[p] = n
            out.point[p] = vec3s(point) + wp.transform_get_translation(xa)
            out.fn[p] = fn
            out.ft[p] = ft
            out.depth[p] = C(body_geom.pair_depth(shapes, model.shape[a], model.shape[b], xa, xb))
        else:
            if wp.static(friction):
                pairs.xi[p] = xi
            pairs.turn[p] = turn
            pairs.force[p] = force
            pairs.torque_a[p] = torque
            pairs.dissipated[p] = lost
            if wp.static(report):
                world_point = vec3s(point) + wp.transform_get_translation(xa)
                if (report_bits & REPORT_CONTACTS) != 0:
                    out.volume[p] = vol
                    out.normal[p] = n
                    out.point[p] = world_point
                    out.fn[p] = fn
                    out.ft[p] = ft
                    out.depth[p] = C(body_geom.pair_depth(shapes, model.shape[a], model.shape[b], xa, xb))
                if (report_bits & REPORT_SUMS) != 0:
                    add_to_sums(pair_sums, p, wp.vec3d(force), wp.vec3d(ft), wp.float64(fn), wp.vec3d(world_point))

    @wp.func
    def dashpot_inputs(model: T.BodyModel, materials: T.Materials, a: int, b: int):
        # What the dashpot of pair (a, b) is made of: friction, tangential stiffness, the restitution's damping
        # factor (the table's: no logarithm a contact), inverse mass
        mat = model.material[a] * materials.count + model.material[b]
        return (materials.mu[mat], materials.kt[mat], materials.damping[mat], C(model.inv_mass[a] + model.inv_mass[b]))

    @wp.func
    def dashpot_of(mu: C, kt: C, factor: C, inv_mass: C):
        # The dashpot as the pair kernel takes it, the same bits (0 without friction: no tangential force)
        ct = C(0.0)
        if mu > C(0.0):
            ct = resp.dashpot_factored(factor, kt, inv_mass)
        return ct

    @wp.func
    def friction_dashpot(model: T.BodyModel, materials: T.Materials, a: int, b: int):
        # The dashpot of pair (a, b) as the pair kernel takes it
        mu, kt, factor, inv_mass = dashpot_inputs(model, materials, a, b)
        return dashpot_of(mu, kt, factor, inv_mass)

    @wp.func
    def add_loss_and_load(
        lost: S, load_total: C, want_load: bool, dissipated: C, flags_other: int, turn: C, mu: C, kt: C, factor: C,
        inv_mass: C,
    ):  # fmt: skip
        # A pair's energy lost, half to each body (all of it where the partner is fixed or kinematic: it books
        # none), and its dashpot in the body's damping load while in contact
        share = S(0.5)
        if flags_other != 0:
            share = S(1.0)
        lost += share * S(dissipated)
        if want_load and turn > C(0.0):
            load_total += dashpot_of(mu, kt, factor, inv_mass)
        return lost, load_total

    @wp.func
    def add_pair_a(
        f: vec3s, t: vec3s, lost: S, load_total: C, want_load: bool,
        force: vec3c, torque: vec3c, dissipated: C, flags_b: int, turn: C, mu: C, kt: C, factor: C, inv_mass: C,
    ):  # fmt: skip
        # A pair's terms on its body A, from what the gather read of it
        f += vec3s(force)
        t += vec3s(torque)
        lost, load_total = add_loss_and_load(
            lost, load_total, want_load, dissipated, flags_b, turn, mu, kt, factor, inv_mass
        )
        return f, t, lost, load_total

    @wp.func
    def add_pair_b(
        f: vec3s, t: vec3s, lost: S, load_total: C, want_load: bool, xi_pos: vec3s, xa_pos: vec3s,
        force: vec3c, torque: vec3c, dissipated: C, flags_a: int, turn: C, mu: C, kt: C, factor: C, inv_mass: C,
    ):  # fmt: skip
        # A pair's terms on its body B (the reaction, and the torque about B's centre)
        fa = vec3s(force)
        r_ab = xi_pos - xa_pos
        f -= fa
        t += wp.cross(r_ab, fa) - vec3s(torque)
        lost, load_total = add_loss_and_load(
            lost, load_total, want_load, dissipated, flags_a, turn, mu, kt, factor, inv_mass
        )
        return f, t, lost, load_total

    @wp.func
    def wall_dashpot(model: T.BodyModel, materials: T.Materials, i: int, wall_mat: int):
        # The dashpot of body i's contact with a wall of material wall_mat (0 without friction)
        mat = model.material[i] * materials.count + wall_mat
        ct = C(0.0)
        if materials.mu[mat] > C(0.0):
            ct = resp.dashpot_factored(materials.damping[mat], materials.kt[mat], C(model.inv_mass[i]))
        return ct

    @wp.func
    def damping_load(model: T.BodyModel, i: int, dt: C, total: C):
        # Free body i's damping load from the sum of its contacts' dashpots (see damping_load_kernel).
        inertia = model.inertia[i]
        i_min = C(wp.min(inertia[0], wp.min(inertia[1], inertia[2])))
        reach = C(model.inv_mass[i])
        if i_min > C(0.0):
            r = C(model.radius[i])
            reach += C(1.25) * r * r / i_min
        return wp.float32(dt * reach * total)

    @wp.kernel(enable_backward=False, module="unique")
    def gather_kernel(
        # Model
        shapes: geom.shapes,
        model: T.BodyModel,
        materials: T.Materials,
        dt: C,
        planes: T.Planes,
        # State in/out: the bodies (out (step): force, torque, energy lost), the wall contacts' history; in: the
        # damping loads
        bodies: T.Bodies,
        walls: T.WallHistory,
        body_damping: wp.array(dtype=wp.float32),
        # In: the pairs' wrenches and energy lost, and the per-body ranges
        pairs: T.Pairs,
        # Out: (N,) the damping loads for the next step, or 0 entries where damping_load_kernel writes them
        # (it may be body_damping: a thread reads only its own body's load, before it writes it)
        damping_out: wp.array(dtype=wp.float32),
        # Out (diagnostics)
        wall_out: T.WallOutputs,
        # Report (the report variant only)
        report_bits: int,
        wall_sums: ContactSums,
        # Phases (the phased variant only): (N,) 1 for the bodies of phase 1, and their indices (phase 1 takes
        # thread t to body first_index[t]); 0 all bodies, 1 or 2 one phase's
        body_first: wp.array(dtype=wp.int32),
        first_index: wp.array(dtype=int),
        phase: int,
    ):
        """Sums each body's pair wrenches in key order and adds its wall contacts (step variant);
        the diagnostics variant only reports the wall contacts; the report variant steps and reports
        its wall contacts (see the factory). Where ``damping_out`` has entries (a scene without mesh walls,
        with friction), also each body's damping load as damping_load_kernel computes it: the same sums in
        the same order, so the same bits, without a launch of its own."""
        i = wp.tid()
        if wp.static(phased):
            # Phase 1 launches a thread per flagged body: a pass over all of them would cost this kernel's launch.
            if phase == 1:
                i = first_index[i]
            elif phase == 2 and body_first[i] != 0:
                return
        f = vec3s(S(0.0), S(0.0), S(0.0))
        t = vec3s(S(0.0), S(0.0), S(0.0))
        lost = S(0.0)
        want_load = wp.static(friction and not diagnostics) and damping_out.shape[0] > 0
        load_total = C(0.0)
        xi_pos = wp.transform_get_translation(bodies.q[i])
        # A fixed or kinematic body needs no force, and a container wall may touch a whole pile:
        # it skips its pairs (one thread would walk them all), and its free partners book the
        # energy lost in full.
        if wp.static(not diagnostics) and model.flags[i] == 0:
            # Two pairs an iteration, both read before either is summed: each pair's reads wait on global memory
            # (its partner's flags and material behind its index), and the second pair's overlap the first's.
            # The same sums in the same order: the same bits as one pair an iteration.
            ra = pairs.ranges_a[i]
            p = ra[0]
            while p < ra[1]:
                q = wp.min(p + 1, ra[1] - 1)
                b_p = pairs.b[p]
                b_q = pairs.b[q]
                mu_p, kt_p, e_p, im_p = dashpot_inputs(model, materials, i, b_p)
                mu_q, kt_q, e_q, im_q = dashpot_inputs(model, materials, i, b_q)
                force_p = pairs.force[p]
                force_q = pairs.force[q]
                torque_p = pairs.torque_a[p]
                torque_q = pairs.torque_a[q]
                lost_p = pairs.dissipated[p]
                lost_q = pairs.dissipated[q]
                turn_p = pairs.turn[p]
                turn_q = pairs.turn[q]
                flags_p = model.flags[b_p]
                flags_q = model.flags[b_q]
                f, t, lost, load_total = add_pair_a(
                    f, t, lost, load_total, want_load, force_p, torque_p, lost_p, flags_p, turn_p, mu_p, kt_p, e_p,
                    im_p,
                )  # fmt: skip
                if q > p:
                    f, t, lost, load_total = add_pair_a(
                        f, t, lost, load_total, want_load, force_q, torque_q, lost_q, flags_q, turn_q, mu_q, kt_q,
                        e_q, im_q,
                    )  # fmt: skip
                p += 2
            rb = pairs.ranges_b[i]
            k = rb[0]
            while k < rb[1]:
                pb_1 = pairs.by_b[k]
                pb_2 = pairs.by_b[wp.min(k + 1, rb[1] - 1)]
                a_1 = pairs.a[pb_1]
                a_2 = pairs.a[pb_2]
                mu_1, kt_1, e_1, im_1 = dashpot_inputs(model, materials, a_1, i)
                mu_2, kt_2, e_2, im_2 = dashpot_inputs(model, materials, a_2, i)
                xa_1 = wp.transform_get_translation(bodies.q[a_1])
                xa_2 = wp.transform_get_translation(bodies.q[a_2])
                force_1 = pairs.force[pb_1]
                force_2 = pairs.force[pb_2]
                torque_1 = pairs.torque_a[pb_1]
                torque_2 = pairs.torque_a[pb_2]
                lost_1 = pairs.dissipated[pb_1]
                lost_2 = pairs.dissipated[pb_2]
                turn_1 = pairs.turn[pb_1]
                turn_2 = pairs.turn[pb_2]
                flags_1 = model.flags[a_1]
                flags_2 = model.flags[a_2]
                f, t, lost, load_total = add_pair_b(
                    f, t, lost, load_total, want_load, xi_pos, xa_1, force_1, torque_1, lost_1, flags_1, turn_1,
                    mu_1, kt_1, e_1, im_1,
                )  # fmt: skip
                if k + 1 < rb[1]:
                    f, t, lost, load_total = add_pair_b(
                        f, t, lost, load_total, want_load, xi_pos, xa_2, force_2, torque_2, lost_2, flags_2, turn_2,
                        mu_2, kt_2, e_2, im_2,
                    )  # fmt: skip
                k += 2
        if model.flags[i] == 0:
            xa = bodies.q[i]
            s = model.shape[i]
            scale = C(damping_scale(body_damping[i], wp.float32(0.0)))
            # The depth only for the diagnostics and a report of the contacts (not for the sums).
            want_depth = wp.static(diagnostics)
            if wp.static(report):
                want_depth = (report_bits & REPORT_CONTACTS) != 0
            for j in range(planes.normal.shape[0]):
                pn = planes.normal[j]
                vol, first_moment, s_a, m_a, fb_a = body_geom.plane_geometry(shapes, s, xa, pn, planes.offset[j])
                mat = model.material[i] * materials.count + planes.material[j]
                depth = C(0.0)
                if wp.static(diagnostics or report):
                    if want_depth and vol > C(0.0):
                        depth = C(body_geom.plane_depth(shapes, s, xa, pn, planes.offset[j]))
                f, t, lost, _ = wall_contact(
                    i, j, mat, vol, first_moment, s_a, m_a, fb_a, depth,
                    -vec3c(pn), vec3c(bodies.v[i]), vec3c(bodies.w[i]), vec3c(planes.v[j]), zero3, xi_pos,
                    shapes.shape_radius[s], shapes.shape_face_area[s], C(model.inv_mass[i]), scale,
                    materials, dt, walls, wall_out, report_bits, wall_sums, f, t, lost,
                )  # fmt: skip
                if want_load and walls.turn[i, j] > C(0.0):
                    load_total += wall_dashpot(model, materials, i, planes.material[j])
        if wp.static(not diagnostics):
            bodies.f[i] = f
            bodies.t[i] = t
            bodies.dissipated[i] = bodies.dissipated[i] + lost
        if want_load:
            load = wp.float32(0.0)
            if model.flags[i] == 0:
                load = damping_load(model, i, dt, load_total)
            damping_out[i] = load

    @wp.kernel(enable_backward=False, module="unique")
    def damping_load_kernel(
        # Model
        model: T.BodyModel,
        materials: T.Materials,
        wall_material: wp.array(dtype=int),
        dt: C,
        # In: the contacts' history as this step left it, the per-body ranges
        pairs: T.Pairs,
        walls: T.WallHistory,
        # Out: (N,) the bodies' damping loads for the next step
        body_damping: wp.array(dtype=wp.float32),
    ):
        """Each free body's damping load: dt times the inverse mass at its farthest point (1/m + 1.25 r^2 / I_min:
        a bound on the velocity a tangential force meets there, with the rocking damping made of the same
        dashpot, at most a quarter of it) times the sum of the tangential dashpots of its contacts with
        friction (those with a turning volume: in contact at this step; the dashpot is 0 for e = 1; one
        without friction applies none), as the step took them unscaled. The next step scales each contact's
        dashpot by damping_scale of its bodies' loads, so that the dashpots of the contacts a body had at
        this step change the velocity at its rim by at most DAMPING_SHARE of it in a step. Summed in the
        gather's order (pairs by key, then walls)."""
        i = wp.tid()
        load = wp.float32(0.0)
        if model.flags[i] == 0:
            total = C(0.0)
            ra = pairs.ranges_a[i]
            for p in range(ra[0], ra[1]):
                if pairs.turn[p] > C(0.0):
                    total += friction_dashpot(model, materials, i, pairs.b[p])
            rb = pairs.ranges_b[i]
            for k in range(rb[0], rb[1]):
                p = pairs.by_b[k]
                if pairs.turn[p] > C(0.0):
                    total += friction_dashpot(model, materials, pairs.a[p], i)
            for j in range(wall_material.shape[0]):
                if walls.turn[i, j] > C(0.0):
                    total += wall_dashpot(model, materials, i, wall_material[j])
            load = damping_load(model, i, dt, total)
        body_damping[i] = load

    return ContactKernels(
        law=law,
        friction=friction,
        diagnostics=diagnostics,
        precision=precision,
        report=report,
        compound=compound,
        max_registers=max_registers,
        thread_order=thread_order,
        phased=phased,
        spread=spread,
        shared_poly=shared_poly,
        geometry=geom,
        body_geometry=body_geom,
        respond=resp.respond,
        wall_contact=wall_contact,
        pair_contact_kernel=pair_contact_kernel,
        gather_kernel=gather_kernel,
        damping_load_kernel=damping_load_kernel,
    )


# ---------------------------------------------------------------------------------------------
# Launch functions
# ---------------------------------------------------------------------------------------------


def spread_room(device: wp.DeviceLike, max_registers: int | None = PAIR_MAX_REGISTERS) -> tuple[int, int]:
    """(at most how many pairs, threads of a wave) the pair kernel's spread takes on ``device`` (the kernel's
    ``spread_pairs`` and ``spread_threads``): a wave is the threads that its register cap of R leaves resident
    (65536 / R an SM); at most as many pairs as half a wave can idle for. (0, 0) on the CPU, whose kernels run one
    thread after another."""
    dev = wp.get_device(device)
    if not dev.is_cuda:
        return 0, 0
    wave = dev.sm_count * (65536 // max(int(max_registers or 255), 32))
    return wave // 2 // (SPREAD_LANES - 1), wave


def spread_fits(capacity: int, spread_threads: int) -> bool:
    """Whether the pair kernel's spread variant is worth launching over pair buffers of ``capacity`` pairs with
    ``spread_threads`` threads a wave (:func:`spread_room`): whether they could hold a list short enough to spread
    anything (:data:`SPREAD_CAPACITY_WAVES`). The same bits either way."""
    return int(capacity) <= max(SPREAD_CAPACITY_WAVES * int(spread_threads), SPREAD_MIN_CAPACITY)


@wp.kernel(enable_backward=False)
def room_kernel(count: wp.array(dtype=int), room: int, overflow: wp.array(dtype=int)):
    """Flag ``overflow`` where ``count`` is above ``room``."""
    if count[0] > room:
        overflow[0] = 1


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
    body_first: wp.array,
    phase: int = 0,
    first_count: wp.array | None = None,
    first_room: int | None = None,
    first_overflow: wp.array | None = None,
    spread_pairs: int = 0,
    spread_threads: int = 0,
    costly: wp.array | None = None,
) -> None:
    """The pair kernel of ``kernels``, one thread per candidate pair: each pair's wrench on A, spring,
    turning volume and energy dissipated into ``pairs`` (the step and report variants), its contact
    into ``out`` (the diagnostics variant; the report variant by ``report_bits``), its force into
    ``pair_sums`` (the report variant, ``REPORT_SUMS``). A clipped polygon that did not fit sets
    ``overflow``. ``out`` and ``pair_sums`` may be placeholders of one entry where nothing is written
    to them. ``body_first`` (N,) int32 and ``phase``: which pairs (phased kernels: 1, those with a body
    flagged in ``body_first``; 2, the others; 0, all; kernels not phased take all and never read
    ``body_first``, which may then be a placeholder of one entry). With the threads ordered (``thread_order``),
    ``first_count`` (1,) int32 holds how many pairs phase 1 has, first in the order (Contacts.split_at); phase 1
    then launches ``first_room`` threads and sets ``first_overflow`` (1,) int32 where they were too few (the
    step must be redone with more). ``spread_pairs``, ``spread_threads``, ``costly`` (1,) int32: with the ``spread``
    kernels, at most how many of the first pairs of the thread order take :data:`SPREAD_LANES` lanes each (0: none),
    the threads that leave room for, and how many pairs of costly shapes come first (``pairs.pair_costly``)."""
    m = model
    ordered = kernels.phased and kernels.thread_order and phase != 0
    first_count = body_first if first_count is None else first_count
    dim = pairs.capacity
    if kernels.spread:
        spread_pairs = min(int(spread_pairs), pairs.capacity)
        dim += spread_pairs * (SPREAD_LANES - 1)
    else:
        spread_pairs = 0
    if ordered and phase == 1:
        dim = min(int(first_room), pairs.capacity)
        wp.launch(room_kernel, dim=1, inputs=[first_count, dim], outputs=[first_overflow], device=body_first.device)
    wp.launch(
        kernels.pair_contact_kernel,
        dim=dim,
        inputs=[
            *m.shapes.kernel_args(),
            m.bodies,
            m.materials,
            dt,
            state.bodies,
            state.body_damping,
            pairs.pairs,
            overflow,
        ],
        outputs=[
            out.pairs,
            int(report_bits),
            pair_sums,
            body_first,
            int(phase),
            first_count,
            spread_pairs,
            int(spread_threads),
            body_first if costly is None else costly,
        ],  # fmt: skip
        device=state.bodies.q.device,
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
    planes: Any = None,
    damping_out: wp.array,
    body_first: wp.array,
    phase: int = 0,
    first_index: wp.array | None = None,
) -> None:
    """The gather kernel of ``kernels``, one thread per body, after :func:`launch_pair_contacts`: each
    body's pair wrenches in key order plus its plane-wall contacts into ``state.body_f`` and
    ``body_t`` (the step and report variants), its wall contacts into ``out`` and ``wall_sums`` as
    the pair kernel does. ``planes``: the plane walls where they are now (default the model's, at rest).
    ``damping_out``: (N,) float32, where the gather also writes the damping loads that
    :func:`launch_damping_load` would (only where the plane walls are all the walls: a mesh wall's contacts
    come after the gather; may be ``state.body_damping``), or an array of no entries: not written (nor
    without friction). ``body_first`` and ``phase``: which bodies, as :func:`launch_pair_contacts` takes pairs
    (phase 1: the flagged bodies, one thread each from ``first_index`` (their indices, int32); 2: the others)."""
    m = model
    planes = m.planes if planes is None else planes
    first_index = body_first if first_index is None else first_index
    dim = m.num_bodies
    if kernels.phased and phase == 1:
        dim = first_index.shape[0]
    wp.launch(
        kernels.gather_kernel,
        dim=dim,
        inputs=[
            *m.shapes.kernel_args(),
            m.bodies,
            m.materials,
            dt,
            planes,
            state.bodies,
            state.walls,
            state.body_damping,
            pairs.pairs,
        ],
        outputs=[damping_out, out.walls, int(report_bits), wall_sums, body_first, first_index, int(phase)],
        device=state.bodies.q.device,
    )


def launch_damping_load(
    kernels: ContactKernels, *, model: ContactModel, state: BodyState, pairs: PairArrays, dt: float
) -> None:
    """The damping load kernel of ``kernels``, one thread per body, after a step's force stage (pair, gather and
    mesh-wall kernels): each body's damping load for the next step into ``state.body_damping`` (0 without
    friction: there is no dashpot). ``model.wall_material``: (W,) int32, the material of each wall column
    (the planes, then the mesh walls)."""
    if not kernels.friction:
        return  # the loads stay 0
    m = model
    wp.launch(
        kernels.damping_load_kernel,
        dim=m.num_bodies,
        inputs=[m.bodies, m.materials, m.wall_material, dt, pairs.pairs, state.walls],
        outputs=[state.body_damping],
        device=state.bodies.q.device,
    )
