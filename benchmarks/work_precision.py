"""Work-precision benchmark: error against cost for the time step, and for the pair kernel's precision.

Three parts (``--parts``, default all of them):

**impacts**: one free body thrown at a fixed target (an infinite plane or a fixed body), no
gravity, so that after the impact it flies freely and its velocities stay constant. Cases: a cube
of 1 cm edge face-first, edge-first (turned 30 degrees about an edge, so it also spins) and
corner-first (a body diagonal 8 degrees off the vertical) onto a plane; the same cube corner-first
onto a fixed slab (the pair kernel instead of the wall kernel); polyhedral spheres of 80 and 320
faces (``ConvexShape.sphere(1)``, ``(2)``, 5 mm circumscribed radius) onto a fixed copy of
themselves, off centre (impact parameter 0.3 of the sum of the radii); hertz law, restitution
e = 1 and e = 0.5, no friction; and one cube edge-first thrown obliquely onto a plane with
friction (e = 0.5, mu = 0.5). Density 2500 kg/m^3, impact speed 0.5 m/s, k = 4.69e8 J/m^4.5 (a
face-first impact then reaches 1% of the edge in depth; the same k as the settling benchmark to
within 5%). The body starts 1e-3 edge from first touch (found by bisection on the float64
``polydem.overlap``), placed so that its centre passes the world origin during the impact (float32
positions keep their finest resolution there).

For each case the step is swept from 0.5% to 50% of ``model.dt_recommended`` (``--fractions``).
The reference is the run at the smallest step in float64 (the swept runs in ``--precision``,
float32 by default), and its own error is estimated by the second smallest step's
difference from it (``ref_check``; for a first-order method the reference error is at most that
difference, for a second-order one a third of it). Every run covers the same simulated time: the
impact (its length measured once at 2% of the step, by polling the contacts) and half its length
again, after which no contact is left (checked; ``contact_at_end``; and the reference run is
carried on for one more impact length to make sure the body does not hit again, ``recontact``).
Reported per run: rebound velocity error ``|v - v_ref| / v0``, angular velocity error as a surface
speed ``|w - w_ref| r / v0`` (r the bounding radius), kinetic energy error
``|K - K_ref| / E_impact``, the energy balance ``(K + W + dissipated)_end - E_0`` over E_impact
(``Simulation.energy()``; for e = 1 this is the energy gained by the impact), for the face-first
cube the restitution actually obtained against the model's promise (rebound speed e v0), and the
cost: wall time per step and per impact (steps times time per step, from one ``Simulation.step``
call after a one-step warm-up). On the CPU a two-body step costs its launch overhead; on a GPU a
CUDA graph launch.

**settle**: the pile of cubes of ``benchmarks/settle.py`` (same scene builder: columns of 10 cubes
of 1 cm in an open box, hertz, e = 0.5, mu = 0.5) settling from rest for ``--settle-time``
simulated seconds, for steps of 0.25 to 4 times the recommended one (``--settle-fractions``). The
piles diverge (chaos), so runs are not compared with each other: each is checked against its own
energy balance, kinetic + contact + gravity + dissipated, which the exact dynamics keep constant.
Sampled ``--samples`` times per run (``Simulation.energy()``, outside the timed steps):
``balance_max`` = max |E_total(t) - E_total(0)| and ``balance_end`` = the signed value at the end,
both over the gravitational energy released by the end of the run (what flowed through the
contacts); the same for the first-order modified energy of symplectic Euler,
``H + dt/2 sum (v.F + w.tau)`` (``modified_*``; see tests/test_simulation.py), which takes out the
O(dt) swing of H inside contacts. Cost: wall time per step (the timed ``Simulation.step`` calls
only) and per simulated second.

**pair**: the pair kernel's float32 and float64 error against its cost, read from the pair-kernel
benchmark's JSON files (``--pair-json``; default ``benchmarks/results/pair_kernel_h200.json`` and
``pair_kernel.json``): largest error of V (x size^3) and of S_A (x size^2) against the float64
scipy reference, against nanoseconds per pair. Nothing is run for this part.

Output: tables on stdout, JSON ``benchmarks/results/work_precision_<device>.json`` (rewritten after
every run) and PNG plots beside it (``..._impacts.png``, ``..._settle.png``, ``..._pair.png``) when
matplotlib is installed (``pip install matplotlib``, the ``plot`` extra); ``--plot-only`` redraws them
from the JSON.

    python benchmarks/work_precision.py --device cpu --quick       # CPU, about 5 minutes
    python benchmarks/work_precision.py --device cpu               # CPU, all cases (about 15 minutes)
    python benchmarks/work_precision.py --device cuda:0            # GPU, settle with 10^4 cubes
"""

import argparse
import json
import math
import os
import sys
import time

import numpy as np
import warp as wp
from _meta import run_meta

import polydem
from polydem import ConvexShape, Scene, Simulation
from polydem.model import Model
from polydem.scene import quat_from_axis_angle

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.join(HERE, "results")

EDGE = 0.01  # cube edge [m]
DENSITY = 2500.0  # [kg/m^3]
SPEED = 0.5  # impact speed [m/s]
FACE_DEPTH = 0.01  # depth of a face-first cube impact, as a fraction of the edge
START_GAP = 1e-3  # distance to first touch at the start, as a fraction of the edge
FRACTIONS = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.35, 0.5)
QUICK_FRACTIONS = (0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5)
PROBE_FRACTION = 0.02
SETTLE_FRACTIONS = (0.25, 0.5, 1.0, 2.0, 4.0)
QUICK_SETTLE_FRACTIONS = (0.5, 1.0, 2.0, 4.0)


def log(*args):
    print(*args, flush=True)


def hertz_k_for_face_impact(edge=EDGE, density=DENSITY, speed=SPEED, depth=FACE_DEPTH):
    """k such that a cube landing flat at ``speed`` stores its kinetic energy at ``depth`` (x edge).

    W = 2/3 k V^1.5 with V = edge^2 d: k = (3/4) m v^2 / (edge^2 d)^1.5.
    """
    mass = density * edge**3
    return 0.75 * mass * speed**2 / (edge**2 * depth * edge) ** 1.5


# ---------------------------------------------------------------------------------------------
# Impact cases


def rotation_between(a, b):
    """Unit quaternion (xyzw) turning unit vector a onto unit vector b (not antiparallel)."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.array([0.0, 0.0, 0.0, 1.0])
    return quat_from_axis_angle(axis / s, math.atan2(s, float(a @ b)))


def quat_mul(a, b):
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ]
    )


def impact_cases():
    """name -> dict(shape, target, orientation, direction, e, mu, offset, note)."""
    identity = np.array([0.0, 0.0, 0.0, 1.0])
    edge_down = quat_from_axis_angle((1.0, 0.0, 0.0), math.radians(30.0))
    corner_down = quat_mul(
        quat_from_axis_angle((1.0, 0.0, 0.0), math.radians(8.0)), rotation_between((1.0, 1.0, 1.0), (0.0, 0.0, -1.0))
    )
    down = (0.0, 0.0, -1.0)
    cases = {}
    for e in (1.0, 0.5):
        tag = "e1" if e == 1.0 else "e05"
        cases[f"cube_face_{tag}"] = dict(shape="cube", target="plane", orientation=identity, direction=down, e=e)
        cases[f"cube_edge_{tag}"] = dict(shape="cube", target="plane", orientation=edge_down, direction=down, e=e)
        cases[f"cube_corner_{tag}"] = dict(shape="cube", target="plane", orientation=corner_down, direction=down, e=e)
        cases[f"cube_corner_slab_{tag}"] = dict(
            shape="cube", target="slab", orientation=corner_down, direction=down, e=e
        )
        for s in ("sphere80", "sphere320"):
            cases[f"{s}_{tag}"] = dict(shape=s, target="same", orientation=identity, direction=down, e=e, offset=0.3)
    oblique = np.array([0.0, 0.6, -0.8])
    cases["cube_edge_friction_e05"] = dict(
        shape="cube", target="plane", orientation=edge_down, direction=oblique, e=0.5, mu=0.5
    )
    for c in cases.values():
        c.setdefault("mu", 0.0)
        c.setdefault("offset", 0.0)
    return cases


QUICK_CASES = (
    "cube_face_e1",
    "cube_face_e05",
    "cube_edge_e1",
    "cube_corner_e1",
    "cube_corner_e05",
    "sphere80_e1",
    "sphere320_e05",
    "cube_edge_friction_e05",
)


def make_shape(name):
    if name == "cube":
        return ConvexShape.box(EDGE, name="cube")
    if name == "sphere80":
        return ConvexShape.sphere(1, radius=0.5 * EDGE, name="sphere80")
    if name == "sphere320":
        return ConvexShape.sphere(2, radius=0.5 * EDGE, name="sphere320")
    raise ValueError(name)


def body_frame_quat(shape, orientation):
    """Orientation of the body (principal) frame of ``shape`` placed with input ``orientation``."""
    sc = Scene(gravity=(0.0, 0.0, 0.0))
    sc.add_material("m", density=DENSITY, law="hertz", k=1.0, restitution=1.0, friction=0.0)
    sc.add_shape("s", shape)
    sc.add_body("s", "m", orientation=orientation)
    return np.array(sc.body_orientation[0], dtype=np.float64), np.array(sc.body_position[0], dtype=np.float64)


def touch_distance(shape_a, q_a, shape_b, q_b, lateral, direction):
    """Largest h such that A at the origin and B at ``lateral - h * direction`` overlap (V > 0).

    Bisection on the float64 ``polydem.overlap`` (body-frame poses); ``lateral`` is B's offset
    across the line of approach.
    """
    qa_body, ca = body_frame_quat(shape_a, q_a)
    qb_body, cb = body_frame_quat(shape_b, q_b)
    lo, hi = 0.0, 2.0 * (shape_a.radius + shape_b.radius) + float(np.linalg.norm(lateral))
    pose_a = np.concatenate([ca, qa_body])
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        pose_b = np.concatenate([lateral - mid * direction + cb, qb_body])
        res = polydem.overlap(shape_a, pose_a, shape_b, pose_b, frame="body", precision="float64")  # default device
        if res.volume[0] > 0.0:
            lo = mid
        else:
            hi = mid
    return hi


def build_impact_scene(case, dt, k):
    """The scene of one impact case with time step ``dt`` (seconds or "auto")."""
    shape = make_shape(case["shape"])
    direction = np.asarray(case["direction"], dtype=np.float64)
    direction /= np.linalg.norm(direction)
    sc = Scene(gravity=(0.0, 0.0, 0.0), dt=dt, name="impact")
    sc.add_material("m", density=DENSITY, law="hertz", k=k, restitution=case["e"], friction=case["mu"])
    sc.add_shape(shape.name, shape)
    gap = START_GAP * EDGE
    q = case["orientation"]
    if case["target"] == "plane":
        # The plane lies `gap` below the lowest vertex of the body, which starts at the origin.
        sc.add_body(shape.name, "m", position=(0.0, 0.0, 0.0), orientation=q)
        lowest = float(sc.body_vertices(0)[:, 2].min())
        plane_z = lowest - gap
        sc = Scene(gravity=(0.0, 0.0, 0.0), dt=dt, name="impact")
        sc.add_material("m", density=DENSITY, law="hertz", k=k, restitution=case["e"], friction=case["mu"])
        sc.add_shape(shape.name, shape)
        sc.add_body(shape.name, "m", position=(0.0, 0.0, 0.0), orientation=q, velocity=SPEED * direction)
        sc.add_plane((0.0, 0.0, plane_z), (0.0, 0.0, 1.0), "m")
    else:
        if case["target"] == "slab":
            target = ConvexShape.box(4.0 * EDGE, 4.0 * EDGE, EDGE, name="slab")
        else:
            target = shape
        # B's lateral offset: a fraction of the sum of the radii across the line of approach.
        side = np.cross(direction, (0.0, 1.0, 0.0))
        if np.linalg.norm(side) < 1e-9:
            side = np.cross(direction, (1.0, 0.0, 0.0))
        side /= np.linalg.norm(side)
        lateral = case["offset"] * (shape.radius + target.radius) * side
        identity = np.array([0.0, 0.0, 0.0, 1.0])
        h = touch_distance(shape, q, target, identity, lateral, -direction)
        # touch_distance moves B along -(-direction) = +direction: B sits ahead of A on its path.
        if target.name != shape.name:
            sc.add_shape(target.name, target)
        sc.add_body(shape.name, "m", position=(0.0, 0.0, 0.0), orientation=q, velocity=SPEED * direction)
        sc.add_body(target.name, "m", position=lateral + (h + gap) * direction, kind="fixed")
    return sc


def run_probe(case, k, device):
    """Run the impact at PROBE_FRACTION of the recommended step, polling the contacts.

    Returns (dt_recommended, impact start, impact end, largest overlap volume).
    """
    dt_rec = Model(build_impact_scene(case, "auto", k), device).dt_recommended
    dt = PROBE_FRACTION * dt_rec
    sim = Simulation(build_impact_scene(case, dt, k), device=device)
    chunk = max(1, round(0.25 * dt_rec / dt))
    t_first = t_last = None
    vmax = 0.0
    limit = int(20.0 * EDGE / SPEED / dt)  # 20 edges of travel: surely past
    steps = 0
    while steps < limit:
        sim.step(chunk)
        steps += chunk
        vol = float(np.sum(sim.contacts()["volume"]))
        if vol > 0.0:
            vmax = max(vmax, vol)
            if t_first is None:
                t_first = sim.time
            t_last = sim.time
        elif t_first is not None and sim.time - t_last > max(t_last - t_first, 4.0 * dt_rec):
            break
    if t_first is None:
        raise RuntimeError("the probe never touched the target")
    return dt_rec, t_first - chunk * dt, t_last + chunk * dt, vmax


def measure_run(case, k, dt, t_end, device, extra=0.0, precision="float32"):
    """One timed run to ``t_end`` in ``precision``; returns a dict of the end state, energies and timing."""
    scene = build_impact_scene(case, dt, k)
    scene.precision = precision
    sim = Simulation(scene, device=device)
    e0 = sim.energy()
    n = max(2, int(math.ceil(t_end / dt)))
    sim.step(1)  # kernels loaded, CUDA graph captured
    wp.synchronize_device(sim.device)
    t0 = time.perf_counter()
    sim.step(n - 1)
    wp.synchronize_device(sim.device)
    wall = time.perf_counter() - t0
    st = sim.state()
    en = sim.energy()
    contact_end = float(np.sum(sim.contacts()["volume"]))
    out = {
        "steps": n,
        "wall_s": wall,
        "step_s": wall / (n - 1),
        "impact_wall_s": wall / (n - 1) * n,
        "simulated_s": n * dt,
        "velocity": st["body_velocity"][0].tolist(),
        "angular_velocity": st["body_angular_velocity"][0].tolist(),
        "energy_start": e0,
        "energy_end": en,
        "contact_at_end": contact_end,
        # Worst case of float32 rounding piling up over the steps, relative: steps * 2^-24.
        "roundoff_bound": n * 2.0**-24,
    }
    if extra > 0.0:
        # Carry on and look for a second contact (a spinning body hitting again).
        recontact = 0.0
        chunk = max(1, int(extra / dt / 20))
        for _ in range(20):
            sim.step(chunk)
            recontact = max(recontact, float(np.sum(sim.contacts()["volume"])))
        out["recontact"] = recontact
    return out


def impact_errors(row, ref, case, shape, e_impact):
    v = np.array(row["velocity"])
    w = np.array(row["angular_velocity"])
    vr = np.array(ref["velocity"])
    wr = np.array(ref["angular_velocity"])
    k_end = row["energy_end"]["kinetic"]
    out = {
        "err_velocity": float(np.linalg.norm(v - vr) / SPEED),
        "err_angular": float(np.linalg.norm(w - wr) * shape.radius / SPEED),
        "err_kinetic": float(abs(k_end - ref["energy_end"]["kinetic"]) / e_impact),
        "energy_balance": float((row["energy_end"]["total"] - row["energy_start"]["total"]) / e_impact),
        "kinetic_ratio": float(k_end / e_impact),
    }
    if case["target"] == "plane" and case["mu"] == 0.0 and "face" in row["case"]:
        out["restitution_error"] = float(v[2] / (case["e"] * SPEED) - 1.0)
    return out


def run_impacts(args, device, record, save):
    k = hertz_k_for_face_impact()
    cases = impact_cases()
    names = args.cases.split(",") if args.cases else (QUICK_CASES if args.quick else tuple(cases))
    fractions = sorted(float(f) for f in args.fractions.split(",")) if args.fractions else None
    fractions = fractions or list(QUICK_FRACTIONS if args.quick else FRACTIONS)
    part = record.setdefault("impacts", {"k_hertz": k, "speed": SPEED, "edge": EDGE, "density": DENSITY})
    part["fractions"] = fractions
    part["cases"] = {}
    log(f"\n== impacts: {len(names)} cases, dt = {', '.join(f'{f:g}' for f in fractions)} x dt_recommended")
    log(
        f"{'case':<24}{'dt/rec':>7}{'steps':>8}{'us/step':>9}{'ms/impact':>10}{'err v':>10}{'err w':>10}"
        f"{'err K':>10}{'balance':>10}{'K/E0':>8}"
    )
    for name in names:
        case = cases[name]
        shape = make_shape(case["shape"])
        t_probe = time.perf_counter()
        dt_rec, t_start, t_stop, vmax = run_probe(case, k, device)
        duration = t_stop - t_start
        t_end = t_stop + 0.5 * duration
        crec = {
            "shape": case["shape"],
            "faces": shape.num_faces,
            "target": case["target"],
            "restitution": case["e"],
            "friction": case["mu"],
            "dt_recommended": dt_rec,
            "impact_duration_s": duration,
            "impact_duration_dt_rec": duration / dt_rec,
            "max_overlap_volume_fraction": vmax / shape.volume,
            "t_end_s": t_end,
            "probe_s": time.perf_counter() - t_probe,
            "runs": [],
        }
        part["cases"][name] = crec
        ref = None
        for f in fractions:
            dt = f * dt_rec
            extra = duration if ref is None else 0.0
            # The reference (the smallest step) runs in float64, the sweep in --precision.
            prec = "float64" if ref is None else args.precision
            row = {"case": name, "fraction": f, "dt": dt, "precision": prec}
            row.update(measure_run(case, k, dt, t_end, device, extra=extra, precision=prec))
            if ref is None:
                ref = row
            e_impact = row["energy_start"]["total"]
            row.update(impact_errors(row, ref, case, shape, e_impact))
            crec["runs"].append(row)
            save()
            log(
                f"{name:<24}{f:>7.3f}{row['steps']:>8}{1e6 * row['step_s']:>9.1f}{1e3 * row['impact_wall_s']:>10.2f}"
                f"{row['err_velocity']:>10.2e}{row['err_angular']:>10.2e}{row['err_kinetic']:>10.2e}"
                f"{row['energy_balance']:>+10.2e}{row['kinetic_ratio']:>8.4f}"
                + (f"  restitution {row['restitution_error']:+.2e}" if "restitution_error" in row else "")
                + (f"  CONTACT AT END {row['contact_at_end']:.2e}" if row["contact_at_end"] > 0 else "")
            )
        if len(crec["runs"]) > 1:
            second = crec["runs"][1]
            crec["ref_check"] = {key: second[key] for key in ("fraction", "err_velocity", "err_angular", "err_kinetic")}
        crec["recontact"] = crec["runs"][0].get("recontact", 0.0)
        check = crec.get("ref_check", {})
        log(
            f"  {name}: impact {duration / dt_rec:.1f} dt_rec long, max overlap "
            f"{100 * vmax / shape.volume:.3f}% of the body; reference check (dt {check.get('fraction', '-')} vs "
            f"{fractions[0]}): "
            + (", ".join(f"{k_} {v:.1e}" for k_, v in check.items() if k_ != "fraction") or "-")
            + (f"; RECONTACT after the window ({crec['recontact']:.2e} m^3)" if crec["recontact"] > 0 else "")
        )
        save()


# ---------------------------------------------------------------------------------------------
# Settling


def load_settle_module():
    sys.path.insert(0, HERE)
    import settle  # benchmarks/settle.py: the same pile

    return settle


def settle_args():
    """The defaults of benchmarks/settle.py's scene options."""
    return load_settle_module().scene_options()


def modified_energy(sim, en):
    """H + dt/2 sum over free bodies of (v.F + w.tau), F with gravity (first-order modified energy)."""
    m = sim.model
    free = m.body_flags_np == 0
    mass = m.body_mass[free].astype(np.float64)
    st = sim.current_state
    v = st.body_v.numpy()[free].astype(np.float64)
    w = st.body_w.numpy()[free].astype(np.float64)
    f = st.body_f.numpy()[free].astype(np.float64) + mass[:, None] * m.gravity[None, :]
    tau = st.body_t.numpy()[free].astype(np.float64)
    return en["total"] + 0.5 * sim.dt * (float(np.sum(f * v)) + float(np.sum(tau * w)))


def run_settle(args, device, record, save):
    settle = load_settle_module()
    sargs = settle_args()
    sizes = [int(float(s)) for s in (args.sizes or ("10000" if device.is_cuda else "1000")).split(",")]
    fractions = sorted(float(f) for f in args.settle_fractions.split(",")) if args.settle_fractions else None
    fractions = fractions or list(QUICK_SETTLE_FRACTIONS if args.quick else SETTLE_FRACTIONS)
    t_sim = args.settle_time or (0.05 if args.quick else 0.1)
    part = record.setdefault("settle", {})
    part.update({"sizes": sizes, "fractions": fractions, "simulated_s": t_sim, "samples": args.samples, "runs": []})
    log(f"\n== settle: {sizes} cubes, {t_sim} s simulated, dt = {', '.join(f'{f:g}' for f in fractions)} x dt_rec")
    log(
        f"{'N':>7}{'dt/rec':>7}{'steps':>7}{'ms/step':>9}{'s/sim s':>9}{'bal max':>10}{'bal end':>10}"
        f"{'mod max':>10}{'mod end':>10}{'released J':>11}{'contacts':>9}"
    )
    for n in sizes:
        scene, info = settle.make_scene(n, sargs, seed=sargs.seed)
        dt_rec = Model(scene, device).dt_recommended
        for f in fractions:
            dt = f * dt_rec
            scene.dt = float(dt)
            scene.precision = args.precision
            sim = Simulation(scene, device=device)
            steps = int(math.ceil(t_sim / dt))
            every = max(1, steps // args.samples)
            e0 = sim.energy()
            h0 = modified_energy(sim, e0)
            g0 = e0["gravity"]
            sim.step(1)  # kernels, graph
            done = 1
            wall = 0.0
            bal = []
            mod = []
            while done < steps:
                chunk = min(every, steps - done)
                wp.synchronize_device(sim.device)
                t0 = time.perf_counter()
                sim.step(chunk)
                wp.synchronize_device(sim.device)
                wall += time.perf_counter() - t0
                done += chunk
                en = sim.energy()
                bal.append(en["total"] - e0["total"])
                mod.append(modified_energy(sim, en) - h0)
            released = g0 - en["gravity"]
            contacts = int(np.sum(sim.contacts()["volume"] > 0.0))
            row = {
                "grains": n,
                "bodies": info["bodies"],
                "k_hertz": info["k_hertz"],
                "fraction": f,
                "dt": dt,
                "dt_recommended": dt_rec,
                "steps": steps,
                "timed_steps": steps - 1,
                "wall_s": wall,
                "step_s": wall / (steps - 1),
                "wall_per_simulated_s": wall / ((steps - 1) * dt),
                "body_steps_per_s": n * (steps - 1) / wall,
                "released_J": released,
                "dissipated_J": en["dissipated"],
                "kinetic_end_J": en["kinetic"],
                "balance_max": float(np.max(np.abs(bal)) / released),
                "balance_end": float(bal[-1] / released),
                "modified_max": float(np.max(np.abs(mod)) / released),
                "modified_end": float(mod[-1] / released),
                "contacts_end": contacts,
                "energy_start": e0,
                "energy_end": en,
            }
            part["runs"].append(row)
            save()
            log(
                f"{n:>7}{f:>7.2f}{steps:>7}{1e3 * row['step_s']:>9.3f}{row['wall_per_simulated_s']:>9.1f}"
                f"{row['balance_max']:>10.2e}{row['balance_end']:>+10.2e}{row['modified_max']:>10.2e}"
                f"{row['modified_end']:>+10.2e}{released:>11.3e}{contacts:>9}"
            )
            del sim


# ---------------------------------------------------------------------------------------------
# Pair kernel (from the pair-kernel benchmark's JSON)


def run_pair(args, record):
    paths = (
        args.pair_json.split(",")
        if args.pair_json
        else [
            os.path.join(RESULTS, "pair_kernel_h200.json"),
            os.path.join(RESULTS, "pair_kernel.json"),
        ]
    )
    part = record.setdefault("pair", {"sources": []})
    part["sources"] = []
    log("\n== pair kernel: error against cost (from the pair-kernel benchmark's JSON)")
    log(f"{'device':<14}{'shape':<12}{'depth':>7}{'prec':>9}{'ns/pair':>9}{'err V':>10}{'err S':>10}")
    for path in paths:
        if not os.path.exists(path):
            log(f"  {path}: missing, skipped")
            continue
        with open(path) as fh:
            data = json.load(fh)
        rows = []
        for r in data["rows"]:
            rows.append(
                {
                    "shape": r["shape"],
                    "faces": r["faces"],
                    "depth": r["depth"],
                    "precision": r["precision"],
                    "ns_per_pair": 1e9 / r["pairs_per_second"],
                    "pairs_per_second": r["pairs_per_second"],
                    "error_volume": r["error_volume"],
                    "error_area_vector": r["error_area_vector"],
                }
            )
            log(
                f"{data['meta']['device'][:13]:<14}{r['shape']:<12}{r['depth']:>7.3g}{r['precision']:>9}"
                f"{1e9 / r['pairs_per_second']:>9.2f}{r['error_volume']:>10.1e}{r['error_area_vector']:>10.1e}"
            )
        # float64 cost over float32 cost, per shape and depth, where both were measured.
        ratios = []
        by_key = {(r["shape"], r["depth"], r["precision"]): r for r in rows}
        for (shape, depth, prec), r in by_key.items():
            if prec == "float32" and (shape, depth, "float64") in by_key:
                r64 = by_key[shape, depth, "float64"]
                ratios.append(
                    {
                        "shape": shape,
                        "depth": depth,
                        "cost_ratio_64_over_32": r64["ns_per_pair"] / r["ns_per_pair"],
                        "error_area_vector_32": r["error_area_vector"],
                        "error_area_vector_64": r64["error_area_vector"],
                    }
                )
        rel = os.path.relpath(path, os.path.join(HERE, ".."))
        part["sources"].append({"file": rel, "meta": data["meta"], "rows": rows, "ratios": ratios})
        for q in ratios:
            log(
                f"  {q['shape']} depth {q['depth']:g}: float64 costs x{q['cost_ratio_64_over_32']:.2f}, error of S_A "
                f"{q['error_area_vector_32']:.1e} -> {q['error_area_vector_64']:.1e}"
            )


# ---------------------------------------------------------------------------------------------
# Plots


def plots(record, prefix):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        log("matplotlib is not installed: no plots (pip install matplotlib, or the 'plot' extra)")
        return []
    written = []

    def save(fig, part):
        fig.tight_layout()
        path = f"{prefix}_{part}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)

    dev = record["meta"]["device"]
    imp = record.get("impacts", {}).get("cases")
    if imp:
        fig, axes = plt.subplots(2, 2, figsize=(12, 9))
        keys = [
            ("err_velocity", "rebound velocity error |v - v_ref| / v0"),
            ("err_angular", "angular velocity error |w - w_ref| r / v0"),
            ("err_kinetic", "kinetic energy error |K - K_ref| / E_impact"),
            ("energy_balance", "energy balance error |E_end - E_0| / E_impact"),
        ]
        cmap = plt.get_cmap("tab20")
        for ax, (key, title) in zip(axes.ravel(), keys, strict=True):
            for i, (name, c) in enumerate(imp.items()):
                runs = c["runs"] if key == "energy_balance" else c["runs"][1:]
                xs = [r["impact_wall_s"] for r in runs]
                ys = [max(abs(r[key]), 1e-12) for r in runs]
                if xs:
                    ax.loglog(xs, ys, "o-", ms=3, color=cmap(i % 20), label=name)
            ax.set_title(title, fontsize=10)
            ax.set_xlabel("wall time per impact [s] (steps x time per step)")
            ax.grid(True, which="both", alpha=0.3)
        axes[0, 0].legend(fontsize=7, ncol=2)
        fig.suptitle(
            f"Impacts: error against cost, dt from {record['impacts']['fractions'][0]:g} to "
            f"{record['impacts']['fractions'][-1]:g} x dt_recommended ({dev}); reference = smallest dt",
            fontsize=11,
        )
        save(fig, "impacts")
    st = record.get("settle", {}).get("runs")
    if st:
        fig, ax = plt.subplots(1, 2, figsize=(12, 4.8))
        for n in sorted({r["grains"] for r in st}):
            rows = [r for r in st if r["grains"] == n]
            x = [r["wall_per_simulated_s"] for r in rows]
            ax[0].loglog(x, [r["balance_max"] for r in rows], "o-", label=f"{n} cubes: total energy")
            ax[0].loglog(x, [r["modified_max"] for r in rows], "s--", label=f"{n} cubes: modified energy")
            for r in rows:
                ax[0].annotate(f"{r['fraction']:g}", (r["wall_per_simulated_s"], r["balance_max"]), fontsize=7)
            ax[1].plot([r["fraction"] for r in rows], [1e3 * r["step_s"] for r in rows], "o-", label=f"{n} cubes")
        ax[0].set_xlabel("wall time per simulated second [s]")
        ax[0].set_ylabel("max |E(t) - E(0)| / gravitational energy released")
        ax[0].set_title("Settling: energy balance error against cost (labels: dt / dt_rec)", fontsize=10)
        ax[0].grid(True, which="both", alpha=0.3)
        ax[0].legend(fontsize=8)
        ax[1].set_xlabel("dt / dt_recommended")
        ax[1].set_ylabel("wall time per step [ms]")
        ax[1].set_xscale("log")
        ax[1].set_title("time per step", fontsize=10)
        ax[1].grid(True, which="both", alpha=0.3)
        ax[1].legend(fontsize=8)
        fig.suptitle(f"Settling pile of cubes ({dev})", fontsize=11)
        save(fig, "settle")
    pair = record.get("pair", {}).get("sources")
    if pair:
        fig, ax = plt.subplots(1, 2, figsize=(12, 4.8))
        markers = {"cube": "s", "tetrahedron": "^", "rock20": "o", "hull64": "D"}
        for src in pair:
            label_dev = src["meta"]["device"]
            for prec, color in (("float32", "tab:blue"), ("float64", "tab:red")):
                for shape, mk in markers.items():
                    rows = [r for r in src["rows"] if r["shape"] == shape and r["precision"] == prec]
                    if not rows:
                        continue
                    hollow = "none" if "CPU" in label_dev else color
                    x = [r["ns_per_pair"] for r in rows]
                    ax[0].loglog(
                        x, [r["error_area_vector"] for r in rows], mk, color=color, mfc=hollow,
                        label=f"{shape} {prec} ({label_dev})",
                    )  # fmt: skip
                    ax[1].loglog(x, [r["error_volume"] for r in rows], mk, color=color, mfc=hollow)
        ax[0].set_ylabel("largest error of S_A [x size^2]")
        ax[1].set_ylabel("largest error of V [x size^3]")
        for a in ax:
            a.set_xlabel("nanoseconds per candidate pair (half touching)")
            a.grid(True, which="both", alpha=0.3)
        ax[0].legend(fontsize=7, ncol=2)
        fig.suptitle("Pair kernel: float32 (blue) and float64 (red), error against cost", fontsize=11)
        save(fig, "pair")
    for p in written:
        log(f"wrote {p}")
    return written


# ---------------------------------------------------------------------------------------------


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    ap.add_argument("--parts", default="impacts,settle,pair", help="comma-separated: impacts, settle, pair")
    ap.add_argument("--quick", action="store_true", help="fewer impact cases and steps, a shorter settling window")
    ap.add_argument(
        "--precision",
        choices=("float32", "mixed", "float64"),
        default="float32",
        help="precision of the swept runs (the reference at the smallest step is float64)",
    )
    ap.add_argument("--cases", default=None, help="impact cases (default all; --quick: a subset)")
    ap.add_argument("--fractions", default=None, help="impact steps as fractions of dt_recommended")
    ap.add_argument("--sizes", default=None, help="settling cube counts (default 10000 on CUDA, 1000 on the CPU)")
    ap.add_argument("--settle-fractions", default=None, help="settling steps as multiples of dt_recommended")
    ap.add_argument("--settle-time", type=float, default=None, help="simulated settling time [s] (0.1; --quick 0.05)")
    ap.add_argument("--samples", type=int, default=20, help="energy samples per settling run")
    ap.add_argument("--pair-json", default=None, help="pair-kernel JSON files (comma-separated)")
    ap.add_argument("--out", default=None, help="JSON (default benchmarks/results/work_precision_<device>.json)")
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument("--plot-only", action="store_true", help="redraw the plots from --out and exit")
    args = ap.parse_args()

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    if args.plot_only:
        if not args.out:
            ap.error("--plot-only needs --out")
        with open(args.out) as fh:
            record = json.load(fh)
        plots(record, os.path.splitext(args.out)[0])
        return
    wp.init()
    device = wp.get_device(args.device)
    out = args.out or os.path.join(RESULTS, f"work_precision_{device.alias.replace(':', '')}.json")
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    record = {"meta": run_meta(device), "config": {k: v for k, v in vars(args).items() if k != "out"}}

    def save():
        tmp = out + ".tmp"
        with open(tmp, "w") as fh:
            json.dump(record, fh, indent=1)
        os.replace(tmp, out)

    log(f"work-precision benchmark on {device.name} ({device.alias}), Warp {wp.config.version}; JSON -> {out}")
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    t0 = time.perf_counter()
    if "pair" in parts:
        run_pair(args, record)
        save()
    if "impacts" in parts:
        run_impacts(args, device, record, save)
    if "settle" in parts:
        run_settle(args, device, record, save)
    record["meta"]["total_s"] = time.perf_counter() - t0
    save()
    log(f"\nwrote {out} ({record['meta']['total_s']:.0f} s)")
    if not args.no_plots:
        plots(record, os.path.splitext(out)[0])


if __name__ == "__main__":
    main()
