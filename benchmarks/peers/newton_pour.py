"""Newton (``pip install newton``, Warp-based) on the peers' pour (see pour_scene.py): throughput and
the largest penetration at rest.

    python benchmarks/peers/pour_scene.py export --grains 10000
    python benchmarks/peers/newton_pour.py --grains 10000 --device cuda:0                 # XPBD, polydem's dt
    python benchmarks/peers/newton_pour.py --grains 10000 --device cuda:0 --substeps 1 --dt 1e-3   # its own dt
    python benchmarks/peers/newton_pour.py --grains 100 --device cpu --check              # construct + 10 steps

Newton is an optional benchmark dependency, never a runtime one. Its version must not move
warp-lang (newton 1.8.0 takes warp-lang>=1.17 and leaves polydem's 1.19 in place).

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
"""

import argparse
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
OUT_DIR = os.path.join(HERE, "..", "results", "peers")
sys.path.insert(0, os.path.dirname(HERE))
from _meta import run_meta  # noqa: E402


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


def build_model(sc, device, args):
    import newton
    import warp as wp

    builder = newton.ModelBuilder(gravity=tuple(float(g) for g in sc["gravity"]))
    # Newton's default detection gap is 0.1 m, ten cube edges: every cube would be paired with
    # hundreds of neighbours (and the contact buffer overflows). Use polydem's Verlet skin instead.
    builder.rigid_gap = args.gap if args.gap is not None else sc.get("skin", 0.2 * 0.5 * np.sqrt(3.0) * sc["edge"])
    cfg = shape_config(newton, sc, args)
    cfg.density = sc["density"]
    verts = np.asarray(sc["cube_body_vertices"], dtype=np.float32)
    tris = np.asarray(sc["cube_triangles"], dtype=np.int32).reshape(-1)
    mesh = newton.Mesh(verts, tris)
    half = 0.5 * sc["edge"]
    pos = np.asarray(sc["cubes"]["position"], dtype=np.float64)
    quat = np.asarray(sc["cubes"]["orientation_xyzw"], dtype=np.float64)
    for p, q in zip(pos, quat, strict=True):
        body = builder.add_body(xform=wp.transform(wp.vec3(*p), wp.quat(*q)))
        if args.shape == "box":
            # The exported cube's body frame may be turned against its edges (a cube's principal
            # axes are not unique): the box primitive is only right if the vertices are axis-aligned.
            builder.add_shape_box(body, hx=half, hy=half, hz=half, cfg=cfg)
        else:
            builder.add_shape_convex_hull(body, mesh=mesh, cfg=cfg)
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
    model = builder.finalize(device=device)
    return model


def axis_aligned(vertices):
    """True when a cube's body-frame vertices lie on the axes' planes (the box primitive fits)."""
    v = np.abs(np.asarray(vertices))
    return bool(np.allclose(v, v.max(), rtol=1e-6))


class Runner:
    def __init__(self, model, args, dt):
        import newton
        import newton.solvers
        import warp as wp

        self.wp = wp
        self.model = model
        self.dt = dt
        self.substeps = args.substeps
        self.pipeline = newton.CollisionPipeline(
            model, broad_phase=args.broad_phase, rigid_contact_max=args.contacts_per_body * model.body_count
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


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--grains", type=int, default=10000)
    ap.add_argument("--scene", default=None, help="exported pour (default results/peers/pour_<N>.json)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--solver", choices=("xpbd", "semi_implicit"), default="xpbd")
    ap.add_argument("--iterations", type=int, default=4, help="XPBD iterations per substep")
    ap.add_argument("--shape", choices=("hull", "box"), default="hull")
    ap.add_argument("--broad-phase", default="sap", choices=("sap", "nxn"))
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
    ap.add_argument("--out", default=None)
    args = ap.parse_args()

    import warp as wp

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    import newton

    wp.init()
    device = wp.get_device(args.device)
    path = args.scene or os.path.join(OUT_DIR, f"pour_{args.grains}.json")
    with open(path) as f:
        sc = json.load(f)
    if args.shape == "box" and not axis_aligned(sc["cube_body_vertices"]):
        sys.exit("--shape box needs axis-aligned body-frame cube vertices; use --shape hull")
    dt = args.dt or sc["dt"]
    n = sc["grains"]
    t0 = time.perf_counter()
    model = build_model(sc, device, args)
    runner = Runner(model, args, dt)
    t_build = time.perf_counter() - t0
    if args.check:
        runner.launch(10)
        wp.synchronize_device(device)
        q = runner.state_0.body_q.numpy()
        ok = bool(np.isfinite(q).all())
        pen, count = penetration(runner)
        print(
            f"newton {newton.__version__} on {device.name}: {n} cubes built in {t_build:.1f} s, 10 launches, "
            f"finite {ok}, {count} contacts, largest penetration {pen:.3g} m",
            flush=True,
        )
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
