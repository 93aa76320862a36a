"""Newton (``pip install newton``, Warp-based) on the peers' pour (see pour_scene.py): throughput and
the largest penetration at rest, or the time to a settled pile.

    python benchmarks/peers/pour_scene.py export --grains 10000
    python benchmarks/peers/newton_pour.py --grains 10000 --device cuda:0                 # XPBD, polydem's dt
    python benchmarks/peers/newton_pour.py --grains 10000 --device cuda:0 --substeps 1 --dt 1e-3   # its own dt
    python benchmarks/peers/newton_pour.py --grains 100 --device cpu --check              # construct + 10 steps
    python benchmarks/peers/newton_pour.py --grains 10000 --device cuda:0 --until-settled --dt 1e-3
    python benchmarks/peers/newton_pour.py --grains 10000 --device cuda:0 --dt-sweep 1e-3,5e-4,2.5e-4,1.25e-4

Newton is an optional benchmark dependency, never a runtime one. Its version must not move
warp-lang (newton 1.8.0 takes warp-lang>=1.17 and leaves polydem's 1.19 in place). On the lent GPU
machine it comes as a staged wheel: ``bash ../shared/gpu/stage.sh --extra newton`` (``.gpu3/``).

Scene: the exported pour (cubes and five fixed wall boxes of polydem's box container), each cube a
free body with one convex-hull shape (``add_shape_convex_hull`` of the cube's 8 vertices and 12
triangles; ``--shape box`` uses Newton's box primitive instead), density 2500 kg/m^3, friction
0.5, walls static box shapes. Newton does not have polydem's volume-energy contact: its collision
pipeline makes point contacts (GJK/EPA/SAT-style convex-convex, with contact reduction), and the
solver resolves them: ``--solver xpbd`` (default; position-based, ``--iterations``) or
``semi_implicit`` (penalty, ``ke`` = 1e4 N/m per contact point by default). Restitution is 0.5
where the solver supports it.

Protocol: ``--warmup`` steps, ``--steps`` timed steps (one CUDA graph of ``--substeps`` substeps
per launch on CUDA; ``dt`` is per substep, default polydem's recommended step), then, for the
"at rest" figure, stepping on to ``--settle-time`` simulated seconds (default 0.5 s) and reading
the contacts' signed distances (``newton.eval_rigid_contact_kinematics``; negative = penetration)
and the largest speed. Writes ``results/peers/newton_pour_<device>_<N>.json`` with the final poses,
so that compare.py can also measure the overlaps with polydem's exact geometry.

Time to settled (``--until-settled``, or ``--dt-sweep`` for one run per dt in one process): the
ModelBuilder is filled once (``builder_s``; by default one cube's builder replicated to every pose in one batched
pass, ``ModelBuilder.replicate``: 8.3 s at 1e5 and 70 s at 1e6 on the 2-core CPU machine, against 72 s at 1e5 for
``--builder loop``, a Python loop over the bodies; ``--check-builders`` finalizes both and compares every array
of their Models) and finalized into a fresh Model per dt; after one launch (``setup_wall_s``: finalize, collision
pipeline, solver, graph capture and that launch, kernels compiled), the run goes until polydem's
stopping rule holds (``polydem.SettleCheck`` of a ``polydem.SettleCriterion``, the code of
``Simulation.run_until_settled``: the free bodies' kinetic energy below ``--kinetic-fraction`` of
the gravitational energy released since that first launch, and the fastest point below
``--max-speed`` if given, held for ``--hold`` s) or for ``--max-time`` more simulated seconds.
The checks come every ``--check-every`` steps (default polydem's CHUNK_STEPS, 64) at absolute step
counts, outside the CUDA graph: one kernel over the bodies and two device sums, three numbers and
the contact count back to the host. Newton's body_qd is (linear velocity of the centre of mass,
angular velocity), both in world axes, and its body_inertia is about the centre of mass in body
axes: kinetic energy 1/2 m |v|^2 + 1/2 w_b . I w_b with w_b the angular velocity in body axes;
gravitational energy -m g . x_com (``--check`` compares these with numpy's, world-axes inertia,
on random velocities). ``wall_s`` times the loop, checks included, as polydem's
run_until_settled does. Afterwards: Newton's own largest penetration (its signed contact
distances), and with polydem's yardstick (``polydem.overlap`` in float64 on the run's device, on
every pair of bodies whose bounding spheres meet and every body near a wall) the largest depth
(x edge) and overlap volume (x cube volume) and, from the pairs that overlap, the packing fraction
and coordination number of the settled interior (``polydem.cli.diagnostics.settled_region`` on the
pour's polydem Scene, rebuilt by pour_scene.build and checked against the export, with Newton's
poses: the definition of time_to_settle.py). Writes
``results/peers/newton_settle_<device>_<N>.json``, one row per dt, with the final poses of a single
run (of every row with ``--save-poses``). ``--progress S`` prints the step's cost at a check every S wall
seconds, so that a run stopped by a deadline still shows it.

Newton's SAP broad phase counts its work (per shape, the shapes whose projections on one fixed direction start
inside its own) into an int32 prefix sum; past 2^31 - 1 the sum wraps and pairs are never tested (BENCHMARKS.md
26f: the 1e6 pour, 4.7e9 work items, the cubes fall through the floor). Each row records that work, summed
in int64 from Newton's own arrays after the first and the last launch, and what its scan held
(``sap_work_*``, ``sap_scan_*``, ``sap_scan_overflow``); ``--sap-estimate`` counts it for an export's initial
poses in numpy, without Newton, at any size.
"""

import argparse
import json
import math
import os
import sys
import time

import numpy as np
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
OUT_DIR = os.path.join(HERE, "..", "results", "peers")
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)
from _meta import run_meta  # noqa: E402

# Largest number of pairs per polydem.overlap call of the yardstick (its buffers scale with it).
YARDSTICK_CHUNK = 1 << 20


@wp.kernel(enable_backward=False)
def settle_measures_kernel(
    # Model
    body_mass: wp.array(dtype=float),
    body_inertia: wp.array(dtype=wp.mat33),
    body_com: wp.array(dtype=wp.vec3),
    body_radius: float,
    gravity: wp.vec3d,
    # State in
    body_q: wp.array(dtype=wp.transform),
    body_qd: wp.array(dtype=wp.spatial_vector),
    # Out
    body_kinetic: wp.array(dtype=wp.float64),
    body_gravity: wp.array(dtype=wp.float64),
    largest_speed: wp.array(dtype=wp.float64),
):
    """Per body: kinetic energy [J] and gravitational energy [J], float64, and the running maximum of
    ``|v| + |w| r`` [m/s]. Newton's body_qd: (v of the centre of mass, w), both in world axes; its
    body_inertia: about the centre of mass, body axes. Bodies without mass (none in the pour) count 0."""
    i = wp.tid()
    body_kinetic[i] = wp.float64(0.0)
    body_gravity[i] = wp.float64(0.0)
    m = body_mass[i]
    if m > 0.0:
        q = body_q[i]
        qd = body_qd[i]
        v = wp.spatial_top(qd)
        w = wp.spatial_bottom(qd)
        rot = wp.transform_get_rotation(q)
        w_body = wp.quat_rotate_inv(rot, w)
        e_lin = 0.5 * m * wp.dot(v, v)
        e_ang = 0.5 * wp.dot(w_body, body_inertia[i] * w_body)
        body_kinetic[i] = wp.float64(e_lin) + wp.float64(e_ang)
        x = wp.transform_point(q, body_com[i])
        h = wp.float64(x[0]) * gravity[0] + wp.float64(x[1]) * gravity[1] + wp.float64(x[2]) * gravity[2]
        body_gravity[i] = -wp.float64(m) * h
        speed = wp.float64(wp.length(v)) + wp.float64(wp.length(w)) * wp.float64(body_radius)
        wp.atomic_max(largest_speed, 0, speed)


def shape_config(newton, sc, args):
    """Newton shape settings from the exported material (friction, restitution) and the options."""
    cfg = newton.ModelBuilder.ShapeConfig()
    cfg.mu = sc["material"]["friction"]
    cfg.restitution = sc["material"]["restitution"]
    if args.ke is not None:
        cfg.ke = args.ke
    if args.kd is not None:
        cfg.kd = args.kd
    return cfg


def detection_gap(sc, args):
    """Newton's contact detection gap [m]: ``--gap``, else the export's skin (polydem's Verlet skin), else 0.2 of a
    cube's half diagonal."""
    return args.gap if args.gap is not None else sc.get("skin", 0.2 * 0.5 * np.sqrt(3.0) * sc["edge"])


def make_builder(sc, args):
    """Newton's ModelBuilder of the exported pour (a Model per ``finalize``)."""
    import newton

    builder = newton.ModelBuilder(gravity=tuple(float(g) for g in sc["gravity"]))
    # Newton's default detection gap is 0.1 m, ten cube edges: every cube would be paired with
    # hundreds of neighbours (and the contact buffer overflows). Use polydem's Verlet skin instead.
    builder.rigid_gap = detection_gap(sc, args)
    cfg = shape_config(newton, sc, args)
    cfg.density = sc["density"]
    verts = np.asarray(sc["cube_body_vertices"], dtype=np.float32)
    tris = np.asarray(sc["cube_triangles"], dtype=np.int32).reshape(-1)
    mesh = newton.Mesh(verts, tris)
    half = 0.5 * sc["edge"]
    pos = np.asarray(sc["cubes"]["position"], dtype=np.float64)
    quat = np.asarray(sc["cubes"]["orientation_xyzw"], dtype=np.float64)

    def add_shape(b, body):
        if args.shape == "box":
            # The exported cube's body frame may be turned against its edges (a cube's principal
            # axes are not unique): the box primitive is only right if the vertices are axis-aligned.
            b.add_shape_box(body, hx=half, hy=half, hz=half, cfg=cfg)
        else:
            b.add_shape_convex_hull(body, mesh=mesh, cfg=cfg)

    # Newton's mass properties of one cube, computed once: per shape they cost about 1.5 ms of Python,
    # half an hour for 1e6 cubes. Every body gets them with its inertia locked (the same model).
    probe = newton.ModelBuilder()
    add_shape(probe, probe.add_body())
    mass, com, inertia = probe.body_mass[0], probe.body_com[0], probe.body_inertia[0]
    if getattr(args, "builder", "replicate") == "loop":
        for p, q in zip(pos, quat, strict=True):
            xform = wp.transform(wp.vec3(*p), wp.quat(*q))
            add_shape(builder, builder.add_body(xform=xform, mass=mass, com=com, inertia=inertia, lock_inertia=True))
    else:
        # One cube's builder copied to every pose in one batched pass (ModelBuilder.replicate into this world,
        # where the copies collide): the same Model as the loop (--check-builders), without its Python work per
        # body and shape.
        template = newton.ModelBuilder(gravity=tuple(float(g) for g in sc["gravity"]))
        template.rigid_gap = builder.rigid_gap
        add_shape(template, template.add_body(mass=mass, com=com, inertia=inertia, lock_inertia=True))
        # Each pose as 7 plain floats (p, q xyzw), which replicate turns into a transform once: a wp.transform
        # given instead is unpacked element by element there, a third of the build's time.
        xforms = [tuple(row) for row in np.column_stack([pos, quat]).tolist()]
        builder.replicate(template, len(xforms), separate_worlds=False, xforms=xforms)
    wall_cfg = shape_config(newton, sc, args)
    for w in sc["walls"]:
        hx, hy, hz = w["half_extents_body"]
        builder.add_shape_box(
            body=-1,
            xform=wp.transform(wp.vec3(*w["center"]), wp.quat(*w["orientation_xyzw"])),
            hx=hx,
            hy=hy,
            hz=hz,
            cfg=wall_cfg,
        )
    return builder


def builders_agree(sc, device, args):
    """Whether the replicating builder and the loop give the same Model: every Warp array of both, compared
    as numbers (labels and other Python lists are not compared). Prints each builder's time and any difference."""
    models, times = {}, {}
    for kind in ("loop", "replicate"):
        t0 = time.perf_counter()
        builder = make_builder(sc, argparse.Namespace(**{**vars(args), "builder": kind}))
        times[kind] = time.perf_counter() - t0
        models[kind] = builder.finalize(device=device)
    print(f"builder: loop {times['loop']:.2f} s, replicate {times['replicate']:.2f} s ({sc['grains']} cubes)")
    same, compared = True, 0
    for name, value in vars(models["loop"]).items():
        other = getattr(models["replicate"], name, None)
        if not isinstance(value, wp.array):
            continue
        if not isinstance(other, wp.array):
            print(f"  {name}: an array in the loop's Model only")
            same = False
            continue
        if name == "shape_color":
            continue  # the viewer's colour of each shape: the loop's vary, the copies take the template's
        a, b = value.numpy(), other.numpy()
        compared += 1
        if name.endswith("_ptr"):
            # Device addresses of the meshes each Model uploaded: the same sharing (which shapes use which
            # mesh), not the same numbers.
            a, b = np.unique(a, return_inverse=True)[1], np.unique(b, return_inverse=True)[1]
        if a.shape != b.shape or not np.array_equal(a, b, equal_nan=a.dtype.kind == "f"):
            diff = "shapes differ" if a.shape != b.shape else f"largest difference {np.abs(a - b).max():.3g}"
            print(f"  {name}: {a.shape} {a.dtype}: {diff}")
            same = False
    print(f"{compared} arrays compared: {'the same' if same else 'DIFFERENT'}")
    return same


def build_model(sc, device, args):
    return make_builder(sc, args).finalize(device=device)


def axis_aligned(vertices):
    """True when a cube's body-frame vertices lie on the axes' planes (the box primitive fits)."""
    v = np.abs(np.asarray(vertices))
    return bool(np.allclose(v, v.max(), rtol=1e-6))


class Runner:
    def __init__(self, model, args, dt):
        import newton
        import newton.solvers

        self.wp = wp
        self.model = model
        self.dt = dt
        self.substeps = args.substeps
        self.steps_done = 0  # substeps taken, kept by the settle loop
        # The broad phase's candidate-pair buffer is sized by default for every shape pair
        # (N (N - 1) / 2: 5e9 entries at 1e5 cubes, past a Warp array's int32 limit); a pour needs a
        # few per shape. The count written is checked against it after the run (pair_overflow).
        self.shape_pairs_max = args.pairs_per_shape * model.shape_count
        self.pipeline = newton.CollisionPipeline(
            model,
            broad_phase=args.broad_phase,
            rigid_contact_max=args.contacts_per_body * model.body_count,
            shape_pairs_max=self.shape_pairs_max,
        )
        self.contacts = self.pipeline.contacts()
        if args.solver == "xpbd":
            self.solver = newton.solvers.SolverXPBD(model, iterations=args.iterations, enable_restitution=True)
        else:
            self.solver = newton.solvers.SolverSemiImplicit(model)
        self.state_0 = model.state()
        self.state_1 = model.state()
        self.control = model.control()
        newton.eval_fk(model, model.joint_q, model.joint_qd, self.state_0)
        self.graph = None
        if model.device.is_cuda and not args.no_graph:
            with wp.ScopedCapture(device=model.device) as cap:
                self._substeps()
            self.graph = cap.graph

    def _substeps(self):
        for k in range(self.substeps):
            self.state_0.clear_forces()
            self.pipeline.collide(self.state_0, self.contacts)
            self.solver.step(self.state_0, self.state_1, self.control, self.contacts, self.dt)
            if self.substeps % 2 == 1 and k == self.substeps - 1:
                self.state_0.assign(self.state_1)
            else:
                self.state_0, self.state_1 = self.state_1, self.state_0

    def launch(self, n):
        """n launches of ``substeps`` substeps."""
        for _ in range(n):
            if self.graph is not None:
                self.wp.capture_launch(self.graph)
            else:
                self._substeps()


INT32_MAX = 2**31 - 1
# Newton 1.8's SAP projects every AABB on this fixed direction (broad_phase_sap.py: "random fixed direction").
NEWTON_SAP_DIRECTION = np.array([0.5935, 0.7790, 0.1235])


def sap_work(runner):
    """Newton's SAP work of its last launch: (the exact total of its per-shape ranges, summed here in int64; the
    total its int32 scan holds, from which its pair kernel takes its work), or None for another broad phase. Past
    2^31 - 1 the scan wraps and the broad phase misses pairs (the 1e6 pour: the cubes fall through the floor)."""
    bp = runner.pipeline.broad_phase
    if not hasattr(bp, "sap_range"):
        return None
    ranges = bp.sap_range.numpy().astype(np.int64)
    return int(ranges.sum()), int(bp.sap_cumulative_sum.numpy()[-1])


def sap_work_estimate(sc, gap):
    """Newton 1.8's SAP work for the export's initial poses, from numpy alone (no Newton, any size): each shape's
    AABB (a turned box: a cube or a wall) widened by ``gap`` on each side as Newton's pipeline does, projected on
    NEWTON_SAP_DIRECTION, sorted by lower end; a shape's work is the number of shapes after it whose lower end is
    below its upper end. Returns the int64 total."""
    from polydem.quaternions import quat_to_matrix

    walls = sc["walls"]
    n = len(sc["cubes"]["position"])
    centre = np.vstack([np.asarray(sc["cubes"]["position"], dtype=np.float64).reshape(n, 3)]
                       + [np.asarray(w["center"], dtype=np.float64)[None] for w in walls])  # fmt: skip
    quat = np.vstack([np.asarray(sc["cubes"]["orientation_xyzw"], dtype=np.float64).reshape(n, 4)]
                     + [np.asarray(w["orientation_xyzw"], dtype=np.float64)[None] for w in walls])  # fmt: skip
    half = np.vstack([np.full((n, 3), 0.5 * sc["edge"])] + [np.asarray(w["half_extents_body"])[None] for w in walls])
    # A turned box's AABB half-widths: |R| times its half extents.
    reach = np.einsum("nij,nj->ni", np.abs(quat_to_matrix(quat)), half) + gap
    d = NEWTON_SAP_DIRECTION / np.linalg.norm(NEWTON_SAP_DIRECTION)
    mid, radius = centre @ d, reach @ np.abs(d)
    lo, hi = mid - radius, mid + radius
    order = np.argsort(lo, kind="stable")
    limit = np.searchsorted(lo[order], hi[order], side="left")
    return int(np.maximum(limit - np.arange(len(order)) - 1, 0).sum(dtype=np.int64))


def model_gap(runner):
    gap = getattr(runner.model, "shape_gap", None)
    return float(gap.numpy().max()) if gap is not None else None


def penetration(runner):
    """(largest penetration [m], contact count) from Newton's own contacts at the current state."""
    import newton

    wp = runner.wp
    c = runner.contacts
    runner.pipeline.collide(runner.state_0, c)
    count = int(c.rigid_contact_count.numpy()[0])
    # Newton drops the contacts beyond its capacity (with a warning): such a run is not valid.
    runner.overflow = max(getattr(runner, "overflow", 0), count - c.rigid_contact_max)
    count = min(count, c.rigid_contact_max)
    if count == 0:
        return 0.0, 0
    dist = wp.zeros(c.rigid_contact_max, dtype=float, device=runner.model.device)
    newton.eval_rigid_contact_kinematics(runner.model, runner.state_0, c, out_distance=dist)
    d = dist.numpy()[:count]
    return float(max(0.0, -d.min())), count


class SettleMeter:
    """The measurements of a polydem SettleCriterion on Newton's state: kinetic energy [J],
    gravitational energy [J] and largest ``|v| + |w| r`` [m/s] of the bodies, float64 sums on the
    device, three numbers to the host; also the contact count of the last collide (capacity check)."""

    def __init__(self, runner, sc):
        model = runner.model
        dev = model.device
        n = model.body_count
        com = model.body_com.numpy().astype(np.float64)
        verts = np.asarray(sc["cube_body_vertices"], dtype=np.float64)
        # The bounding radius about the centre of mass (Newton's, from the hull, ~0 for the cube).
        self.radius = float(np.linalg.norm(verts[None, :, :] - com[:, None, :], axis=2).max()) if n else 0.0
        self.gravity = wp.vec3d(*(float(g) for g in sc["gravity"]))
        self.kinetic = wp.empty(n, dtype=wp.float64, device=dev)
        self.potential = wp.empty(n, dtype=wp.float64, device=dev)
        self.out = wp.zeros(3, dtype=wp.float64, device=dev)
        self.runner = runner
        self.most_contacts = 0
        self.most_pairs = 0

    def measure(self):
        r = self.runner
        m = r.model
        self.out.zero_()
        wp.launch(
            settle_measures_kernel,
            dim=m.body_count,
            inputs=[
                m.body_mass,
                m.body_inertia,
                m.body_com,
                self.radius,
                self.gravity,
                r.state_0.body_q,
                r.state_0.body_qd,
            ],
            outputs=[self.kinetic, self.potential, self.out[2:3]],
            device=m.device,
        )
        wp.utils.array_sum(self.kinetic, out=self.out[0:1])
        wp.utils.array_sum(self.potential, out=self.out[1:2])
        kinetic, gravity, speed = self.out.numpy().tolist()
        self.most_contacts = max(self.most_contacts, int(r.contacts.rigid_contact_count.numpy()[0]))
        pairs = getattr(r.pipeline, "broad_phase_pair_count", None)
        if pairs is not None:
            self.most_pairs = max(self.most_pairs, int(pairs.numpy()[0]))
        return kinetic, gravity, speed


def settle_measures_numpy(runner, sc):
    """SettleMeter's numbers the slow way, on host copies: kinetic energy with the inertia turned to
    world axes (R I R^T), gravitational energy, largest speed (for the --check comparison)."""
    from scipy.spatial.transform import Rotation

    m = runner.model
    q = runner.state_0.body_q.numpy().astype(np.float64)
    qd = runner.state_0.body_qd.numpy().astype(np.float64)
    mass = m.body_mass.numpy().astype(np.float64)
    inertia = m.body_inertia.numpy().astype(np.float64)
    com = m.body_com.numpy().astype(np.float64)
    rot = Rotation.from_quat(q[:, 3:7]).as_matrix()
    v, w = qd[:, :3], qd[:, 3:]
    world_inertia = rot @ inertia @ np.transpose(rot, (0, 2, 1))
    kinetic = 0.5 * mass * np.einsum("ni,ni->n", v, v) + 0.5 * np.einsum("ni,nij,nj->n", w, world_inertia, w)
    x_com = q[:, :3] + np.einsum("nij,nj->ni", rot, com)
    gravity = -mass * (x_com @ np.asarray(sc["gravity"], dtype=np.float64))
    verts = np.asarray(sc["cube_body_vertices"], dtype=np.float64)
    radius = np.linalg.norm(verts[None, :, :] - com[:, None, :], axis=2).max()
    speed = np.linalg.norm(v, axis=1) + np.linalg.norm(w, axis=1) * radius
    return float(kinetic.sum()), float(gravity.sum()), float(speed.max())


def criterion_of(args):
    from polydem import SettleCriterion

    kf = None if args.kinetic_fraction <= 0.0 else args.kinetic_fraction
    return SettleCriterion(
        kinetic_fraction=kf, max_speed=args.max_speed, hold=args.hold, speed_fraction=args.speed_fraction
    )


def run_until_settled(runner, meter, criterion, max_time, every, speed_limit=None, progress=0.0):
    """polydem's ``Simulation.run_until_settled`` loop on a Newton runner: checks every ``every`` steps
    (substeps) at absolute step counts, from step ``runner.steps_done``; ``speed_limit`` [m/s]: the
    criterion's for the pour's scene (``SettleCriterion.speed_limit_of``); ``progress`` [s]: a line at a check
    at most this often in wall time (0: none), so that a run cut off by a deadline still shows its step's cost;
    returns (settled, check)."""
    from polydem.settle import SettleCheck

    dt, sub = runner.dt, runner.substeps
    check = SettleCheck(criterion, meter.measure()[1], speed_limit=speed_limit)
    start = runner.steps_done
    end = start + sub * math.ceil(max(1, math.ceil(max_time / dt - 1e-9)) / sub)
    settled = False
    t0 = last = time.perf_counter()
    while runner.steps_done < end and not settled:
        stop = min(end, (runner.steps_done // every + 1) * every)
        runner.launch((stop - runner.steps_done) // sub)
        runner.steps_done = stop
        if stop % every:
            check.holds(*meter.measure())
        else:
            settled = check.update(stop, dt, *meter.measure())
        now = time.perf_counter()
        if progress > 0 and now - last >= progress:
            last = now
            print(
                f"  t {stop * dt:.3f} s, step {stop}, wall {now - t0:.1f} s ({1e3 * (now - t0) / (stop - start):.3f} "
                f"ms/step), kinetic fraction {check.kinetic_fraction:.3g}, largest speed {check.largest_speed:.3g} m/s",
                flush=True,
            )
    return settled, check


def pour_scene_of(sc):
    """polydem's Scene of the exported pour (pour_scene.build), checked against the export."""
    import pour_scene

    scene, _ = pour_scene.build(sc["grains"])
    n = sc["grains"]
    same = np.allclose(np.asarray(scene.body_position)[:n], np.asarray(sc["cubes"]["position"]), rtol=0, atol=1e-12)
    if not (same and np.all(np.asarray(scene.body_kind)[:n] == 0) and scene.num_bodies == n + len(sc["walls"])):
        sys.exit("the exported pour is not pour_scene.build's: export it again with this tree")
    return scene


def yardstick_contacts(scene, position, orientation, device):
    """Every overlapping pair by polydem's float64 geometry at the given body poses ((B, 3), (B, 4)
    xyzw, all bodies of ``scene``): dict of body_a, body_b (int64), volume [m^3], depth [m]."""
    from scipy.spatial import cKDTree

    import polydem

    kind = np.asarray(scene.body_kind)
    body_shape = np.asarray(scene.body_shape)
    shapes = [scene.shapes[name] for name in scene.shape_names]
    radius = np.array([s.radius for s in shapes])[body_shape]
    free = np.flatnonzero(kind == 0)
    fixed = np.flatnonzero(kind != 0)
    pos = np.asarray(position, dtype=np.float64)
    quat = np.asarray(orientation, dtype=np.float64)
    quat = quat / np.linalg.norm(quat, axis=1, keepdims=True)
    pairs = free[cKDTree(pos[free]).query_pairs(2.0 * radius[free].max(), output_type="ndarray")].reshape(-1, 2)
    gap = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1)
    pairs = [pairs[gap <= radius[pairs[:, 0]] + radius[pairs[:, 1]]]]
    for w in fixed:
        # A body near a fixed one: its centre within its radius of the fixed body's bounding box.
        v = scene.body_vertices(int(w))
        out = np.maximum(np.maximum(v.min(axis=0) - pos[free], pos[free] - v.max(axis=0)), 0.0)
        near = free[np.linalg.norm(out, axis=1) <= radius[free]]
        pairs.append(np.column_stack([near, np.full(len(near), w)]))
    pairs = np.concatenate(pairs).astype(np.int64)
    poses = np.hstack([pos, quat])
    volume = np.zeros(len(pairs))
    depth = np.zeros(len(pairs))
    for sa in np.unique(body_shape[pairs[:, 0]]):
        for sb in np.unique(body_shape[pairs[:, 1]]):
            rows = np.flatnonzero((body_shape[pairs[:, 0]] == sa) & (body_shape[pairs[:, 1]] == sb))
            for k in range(0, len(rows), YARDSTICK_CHUNK):
                r = rows[k : k + YARDSTICK_CHUNK]
                a, b = poses[pairs[r, 0]], poses[pairs[r, 1]]
                res = polydem.overlap(shapes[sa], a, shapes[sb], b, frame="body", device=device, precision="float64")
                volume[r] = res.volume
                depth[r] = res.depth
    hit = volume > 0.0
    return {"body_a": pairs[hit, 0], "body_b": pairs[hit, 1], "volume": volume[hit], "depth": depth[hit]}


def settled_figures(sc, scene, position, orientation, device):
    """polydem's yardstick and settled-interior figures of Newton's final cube poses."""
    from polydem.cli.diagnostics import settled_region

    n = sc["grains"]
    pos = np.array(scene.body_position, dtype=np.float64)
    quat = np.array(scene.body_orientation, dtype=np.float64)
    pos[:n] = position
    quat[:n] = orientation
    contacts = yardstick_contacts(scene, pos, quat, device)
    region = settled_region(scene, {"body_position": pos, "body_orientation": quat}, contacts)
    a = sc["edge"]
    return {
        "max_depth_fraction_of_edge": float(contacts["depth"].max()) / a if len(contacts["depth"]) else 0.0,
        "max_overlap_volume_fraction": float(contacts["volume"].max()) / a**3 if len(contacts["volume"]) else 0.0,
        "overlapping_pairs": int(len(contacts["volume"])),
        "packing_fraction": region.get("packing_fraction"),
        "coordination_number": region.get("coordination_number"),
        "coordination_number_free": region.get("coordination_number_free"),
        "region_bodies": region.get("bodies"),
    }


def settle_run(sc, scene, builder, device, args, dt, save_poses):
    """A Model from ``builder``, run to settled at ``dt``, measured; returns the row."""
    import newton

    n = sc["grains"]
    criterion = criterion_of(args)
    every = args.check_every
    t0 = time.perf_counter()
    model = builder.finalize(device=device)
    runner = Runner(model, args, dt)
    meter = SettleMeter(runner, sc)
    runner.launch(1)  # kernels compiled (graph captured in Runner)
    runner.steps_done = args.substeps
    wp.synchronize_device(device)
    setup = time.perf_counter() - t0
    work_start = sap_work(runner)
    if work_start and work_start[0] > INT32_MAX:
        print(
            f"  Newton's SAP work {work_start[0]:,} > 2^31 - 1: its int32 scan holds {work_start[1]:,}, pairs missed",
            flush=True,
        )
    t1 = time.perf_counter()
    limit = criterion.speed_limit_of(scene)
    settled, check = run_until_settled(runner, meter, criterion, args.max_time, every, limit, args.progress)
    wp.synchronize_device(device)
    wall = time.perf_counter() - t1
    sim_time = runner.steps_done * dt
    work_end = sap_work(runner)
    runner.overflow = meter.most_contacts - runner.contacts.rigid_contact_max
    pen, count = penetration(runner)
    q = runner.state_0.body_q.numpy().astype(np.float64)
    t2 = time.perf_counter()
    figures = settled_figures(sc, scene, q[:n, :3], q[:n, 3:7], device)
    row = {
        "dt": dt,
        "substeps": args.substeps,
        "iterations": args.iterations if args.solver == "xpbd" else None,
        "settled": bool(settled),
        "settle_time_s": sim_time if settled else None,
        "held_from_s": None if check.held_since is None else check.held_since * dt,
        "simulated_s": sim_time,
        "steps": runner.steps_done,
        "setup_wall_s": setup,
        "wall_s": wall,
        "wall_s_per_simulated_s": wall / max(sim_time, 1e-30),
        "kinetic_J": check.kinetic,
        "released_J": check.released,
        "kinetic_fraction": check.kinetic_fraction,
        "largest_speed_m_s": check.largest_speed,
        "newton_contacts": count,
        "newton_max_penetration_m": pen,
        "newton_max_penetration_edges": pen / sc["edge"],
        "rigid_contact_max": int(runner.contacts.rigid_contact_max),
        "contact_overflow": int(max(runner.overflow, 0)),
        "shape_pairs_max": int(runner.shape_pairs_max),
        "most_broad_phase_pairs": int(meter.most_pairs),
        "pair_overflow": int(max(meter.most_pairs - runner.shape_pairs_max, 0)),
        # Newton's SAP work (exact, int64) and what its int32 scan held, after the first and the last launch
        "sap_work_start": None if work_start is None else work_start[0],
        "sap_scan_start": None if work_start is None else work_start[1],
        "sap_work_end": None if work_end is None else work_end[0],
        "sap_scan_end": None if work_end is None else work_end[1],
        "sap_scan_overflow": any(w is not None and w[0] > INT32_MAX for w in (work_start, work_end)),
        **figures,
        "yardstick_wall_s": time.perf_counter() - t2,
        "graph": runner.graph is not None,
        "version": newton.__version__,
    }
    if save_poses:
        row["final"] = {"position": q[:n, :3].tolist(), "orientation_xyzw": q[:n, 3:7].tolist()}
    return row


def settle_main(sc, device, args):
    """--until-settled and --dt-sweep: one row per dt, rewritten after each."""
    import newton

    n = sc["grains"]
    sweep = args.dt_sweep is not None
    try:
        criterion_of(args)
        dts = [float(v) for v in args.dt_sweep.split(",")] if sweep else [args.dt or sc["dt"]]
    except ValueError as err:
        sys.exit(f"newton_pour.py: {err}")
    if args.check_every < 1 or args.check_every % args.substeps:
        sys.exit(f"newton_pour.py: --check-every ({args.check_every}) must be a multiple of --substeps {args.substeps}")
    scene = pour_scene_of(sc)
    t0 = time.perf_counter()
    # The Python loop over the bodies (about 0.5 ms a body) once; a fresh Model per dt.
    builder = make_builder(sc, args)
    builder_s = time.perf_counter() - t0
    record = {
        "code": "newton",
        "version": newton.__version__,
        "warp": wp.config.version,
        "device": device.name,
        "grains": n,
        "solver": args.solver,
        "shape": args.shape,
        "broad_phase": args.broad_phase,
        "criterion": criterion_of(args).to_dict(),
        "check_every_steps": args.check_every,
        "max_time_s": args.max_time,
        "builder_s": builder_s,
        "builder": args.builder,
        "rows": [],
        "meta": run_meta(device),
    }
    os.makedirs(OUT_DIR, exist_ok=True)
    tag = "" if (args.solver, args.shape) == ("xpbd", "hull") else f"_{args.solver}_{args.shape}"
    out = args.out or os.path.join(OUT_DIR, f"newton_settle_{device.alias.replace(':', '')}_{n}{tag}.json")
    head = ("dt", "settled", "t_settle", "steps", "setup s", "wall s", "wall/sim", "pen", "depth", "max V", "phi", "Z")
    # Written before the first run too: a run cut off by a deadline (1e6 cubes) still leaves the build's figures.
    with open(out, "w") as f:
        json.dump(record, f)
    print(
        f"newton {newton.__version__} {args.solver} ({args.shape}) on {device.name}: {n} cubes, builder "
        f"({args.builder}) {builder_s:.1f} s",
        flush=True,
    )
    print(" ".join(f"{h:>9s}" for h in head), flush=True)
    for dt in dts:
        r = settle_run(sc, scene, builder, device, args, dt, args.save_poses or not sweep)
        record["rows"].append(r)
        with open(out, "w") as f:
            json.dump(record, f)
        t = r["settle_time_s"]
        print(
            f"{dt:>9.3g} {str(r['settled']):>9s} {(format(t, '.3f') if t is not None else '-'):>9s} {r['steps']:>9d} "
            f"{r['setup_wall_s']:>9.2f} {r['wall_s']:>9.2f} {r['wall_s_per_simulated_s']:>9.2f} "
            f"{100 * r['newton_max_penetration_edges']:>8.1f}% {100 * r['max_depth_fraction_of_edge']:>8.1f}% "
            f"{100 * r['max_overlap_volume_fraction']:>8.2f}% {r['packing_fraction'] or float('nan'):>9.3f} "
            f"{r['coordination_number'] or float('nan'):>9.2f}"
            + (f"  (contact overflow {r['contact_overflow']})" if r["contact_overflow"] else ""),
            flush=True,
        )
    print(f"wrote {out}", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--grains", type=int, default=10000)
    ap.add_argument("--scene", default=None, help="exported pour (default results/peers/pour_<N>.json)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--solver", choices=("xpbd", "semi_implicit"), default="xpbd")
    ap.add_argument("--iterations", type=int, default=4, help="XPBD iterations per substep")
    ap.add_argument("--shape", choices=("hull", "box"), default="hull")
    ap.add_argument("--broad-phase", default="sap", choices=("sap", "nxn"))
    ap.add_argument(
        "--pairs-per-shape", type=int, default=32, help="broad-phase candidate pairs room per shape (default 32)"
    )
    ap.add_argument("--ke", type=float, default=None, help="contact stiffness (semi_implicit) [N/m]")
    ap.add_argument("--kd", type=float, default=None, help="contact damping (semi_implicit)")
    ap.add_argument("--dt", type=float, default=None, help="substep [s] (default polydem's recommended step)")
    ap.add_argument("--substeps", type=int, default=1, help="substeps per launch (one CUDA graph)")
    ap.add_argument("--warmup", type=int, default=1250, help="warm-up launches")
    ap.add_argument("--steps", type=int, default=500, help="timed launches")
    ap.add_argument("--settle-time", type=float, default=0.5, help="simulated time for the at-rest figures [s]")
    ap.add_argument("--gap", type=float, default=None, help="contact detection gap [m] (default polydem's skin)")
    ap.add_argument("--contacts-per-body", type=int, default=32, help="rigid contact capacity per body")
    ap.add_argument("--no-graph", action="store_true")
    ap.add_argument("--check", action="store_true", help="construct and run 10 launches only (CPU smoke test)")
    ap.add_argument("--until-settled", action="store_true", help="run to settled (polydem's rule) at --dt")
    ap.add_argument("--dt-sweep", default=None, help="comma-separated dts [s]: one run to settled per dt")
    ap.add_argument("--max-time", type=float, default=1.0, help="settle runs: simulated seconds at most")
    ap.add_argument(
        "--kinetic-fraction", type=float, default=1e-4, help="settled: kinetic < this x released (0: unchecked)"
    )
    ap.add_argument("--max-speed", type=float, default=None, help="settled: also |v| + |w| r < this [m/s]")
    ap.add_argument("--hold", type=float, default=0.02, help="settled for this long [s]")
    ap.add_argument(
        "--speed-fraction",
        type=lambda v: None if v == "off" else float(v),
        default=None,
        help="settled: also every grain's fastest point below this x sqrt(g r_min), as polydem's default rule "
        "(default off: the kinetic part alone, section 7's rule, unless --max-speed)",
    )
    ap.add_argument("--check-every", type=int, default=None, help="steps between checks (default polydem's, 64)")
    ap.add_argument("--progress", type=float, default=0.0, help="settle runs: a line every this many wall s (0: none)")
    ap.add_argument("--save-poses", action="store_true", help="--dt-sweep: keep every row's final poses")
    ap.add_argument(
        "--builder",
        choices=("replicate", "loop"),
        default="replicate",
        help="fill the ModelBuilder by replicating one cube (default) or by a Python loop over the bodies",
    )
    ap.add_argument(
        "--check-builders", action="store_true", help="finalize both builders and compare every Model array"
    )
    ap.add_argument(
        "--sap-estimate",
        action="store_true",
        help="print Newton's SAP work for the export's initial poses (numpy, no Newton) and exit",
    )
    ap.add_argument("--out", default=None)
    args = ap.parse_args()

    path = args.scene or os.path.join(OUT_DIR, f"pour_{args.grains}.json")
    if args.sap_estimate:
        with open(path) as f:
            sc = json.load(f)
        work = sap_work_estimate(sc, detection_gap(sc, args))
        print(
            f"{sc['grains']} cubes: Newton's SAP work at the start {work:,} ({work / INT32_MAX:.2f} x 2^31 - 1: "
            f"{'its int32 scan wraps' if work > INT32_MAX else 'fits'})"
        )
        return
    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    import newton

    wp.init()
    device = wp.get_device(args.device)
    with open(path) as f:
        sc = json.load(f)
    if args.shape == "box" and not axis_aligned(sc["cube_body_vertices"]):
        sys.exit("--shape box needs axis-aligned body-frame cube vertices; use --shape hull")
    if args.check_builders:
        sys.exit(0 if builders_agree(sc, device, args) else 1)
    if args.until_settled or args.dt_sweep is not None:
        if args.check_every is None:
            from polydem.simulation import CHUNK_STEPS

            args.check_every = CHUNK_STEPS
        settle_main(sc, device, args)
        return
    dt = args.dt or sc["dt"]
    n = sc["grains"]
    t0 = time.perf_counter()
    model = build_model(sc, device, args)
    runner = Runner(model, args, dt)
    t_build = time.perf_counter() - t0
    if args.check:
        runner.launch(1)
        wp.synchronize_device(device)
        work = sap_work(runner)
        if work is not None:
            estimate = sap_work_estimate(sc, model_gap(runner))
            print(f"Newton's SAP work at the first launch {work[0]:,} (its scan {work[1]:,}), numpy's {estimate:,}")
        runner.launch(9)
        wp.synchronize_device(device)
        q = runner.state_0.body_q.numpy()
        ok = bool(np.isfinite(q).all())
        pen, count = penetration(runner)
        # Random linear and angular velocities, so that both halves of body_qd count in the comparison.
        qd = np.random.default_rng(0).normal(size=(model.body_count, 6)).astype(np.float32)
        runner.state_0.body_qd.assign(qd)
        kinetic, gravity, speed = SettleMeter(runner, sc).measure()
        ref = settle_measures_numpy(runner, sc)
        print(
            f"newton {newton.__version__} on {device.name}: {n} cubes built in {t_build:.1f} s, 10 launches, "
            f"finite {ok}, {count} contacts, largest penetration {pen:.3g} m; settle measures (kinetic, "
            f"gravitational [J], largest speed [m/s]) on the device {kinetic:.9g}, {gravity:.9g}, {speed:.6g}, "
            f"in numpy {ref[0]:.9g}, {ref[1]:.9g}, {ref[2]:.6g}",
            flush=True,
        )
        if not np.allclose([kinetic, gravity, speed], ref, rtol=1e-5, atol=0.0):
            sys.exit("the device's settle measures differ from numpy's")
        return

    runner.launch(args.warmup)
    wp.synchronize_device(device)
    t0 = time.perf_counter()
    runner.launch(args.steps)
    wp.synchronize_device(device)
    wall = time.perf_counter() - t0
    per_launch = wall / args.steps
    done = args.warmup + args.steps
    pen_window, count_window = penetration(runner)
    rest = max(0, int(round(args.settle_time / (dt * args.substeps))) - done)
    t0 = time.perf_counter()
    runner.launch(rest)
    wp.synchronize_device(device)
    t_rest = time.perf_counter() - t0
    pen_rest, count_rest = penetration(runner)
    q = runner.state_0.body_q.numpy().astype(np.float64)
    qd = runner.state_0.body_qd.numpy().astype(np.float64)
    speed = float(np.linalg.norm(qd[:, :3], axis=1).max()) if len(qd) else 0.0
    sim_time = (done + rest) * dt * args.substeps
    result = {
        "code": "newton",
        "version": newton.__version__,
        "warp": wp.config.version,
        "device": device.name,
        "grains": n,
        "solver": args.solver,
        "iterations": args.iterations if args.solver == "xpbd" else None,
        "shape": args.shape,
        "broad_phase": args.broad_phase,
        "dt": dt,
        "substeps": args.substeps,
        "graph": runner.graph is not None,
        "warmup_steps": args.warmup * args.substeps,
        "steps": args.steps * args.substeps,
        "build_s": t_build,
        "wall_s": wall,
        "step_s": per_launch / args.substeps,
        "body_steps_per_s": n * args.steps * args.substeps / wall,
        "simulated_s_per_wall_s": args.steps * args.substeps * dt / wall,
        "gap_m": model_gap(runner),
        "rigid_contact_max": int(runner.contacts.rigid_contact_max),
        "contact_overflow": int(max(getattr(runner, "overflow", 0), 0)),
        "contacts_after_window": count_window,
        "max_penetration_after_window_m": pen_window,
        "settle_time_s": sim_time,
        "settle_wall_s": t_rest,
        "contacts_at_rest": count_rest,
        "max_penetration_at_rest_m": pen_rest,
        "max_penetration_at_rest_edges": pen_rest / sc["edge"],
        "max_speed_at_rest_m_s": speed,
        "final": {"position": q[:n, :3].tolist(), "orientation_xyzw": q[:n, 3:7].tolist()},
        "meta": run_meta(device),
    }
    os.makedirs(OUT_DIR, exist_ok=True)
    tag = "" if (args.solver, args.shape) == ("xpbd", "hull") else f"_{args.solver}_{args.shape}"
    out = args.out or os.path.join(OUT_DIR, f"newton_pour_{device.alias.replace(':', '')}_{n}{tag}.json")
    with open(out, "w") as f:
        json.dump(result, f)
    print(
        f"newton {newton.__version__} {args.solver} ({args.shape}) on {device.name}: {n} cubes, dt {dt:.3g} s x "
        f"{args.substeps}: {1e3 * result['step_s']:.3f} ms/step, "
        f"{result['body_steps_per_s'] / 1e6:.2f} M body-steps/s; "
        f"at rest ({sim_time:.2f} s): {count_rest} contacts, largest penetration {1e3 * pen_rest:.3f} mm "
        f"({100 * pen_rest / sc['edge']:.2f}% of the edge), max speed {speed:.3g} m/s; wrote {out}",
        flush=True,
    )


if __name__ == "__main__":
    main()
