"""At rest: force spread of a resting cube, creep on a slope, and the balance of a settled pile.

For every law and precision (and, for the hertz law the shipped scenes use, every restitution in
0.1, 0.3, 0.5, 0.9), at dt = "auto" (``--dt-scale S``: S times it, the price of a long step at rest):

* **cube**: scenes/cube_drop.toml's 0.1 m steel cube set down on the floor; after 0.1 s, the normal
  force reported in each of the next 400 steps, as a fraction of the weight (min, max), and the
  range of its height;
* **slope**: scenes/incline.toml's block (hertz k 1e9, mu 0.5) on a 20 degree slope; after 50 ms,
  how far it moves in the next 0.5 s (and the normal force over the weight at 20 samples);
* **pile** (``--pile N``): N 1 cm cubes (settle.py's pour: hertz, e 0.3, mu 0.5 between grains,
  frictionless walls: planes of a material with mu 0) run until settled by the default criterion,
  then over the next 40 steps the walls' push along gravity over the pile's weight (min, max), and
  the largest net force on a grain (contacts plus gravity) over its weight.

The script uses only the public API, so the same file measures an older checkout (put it first on
PYTHONPATH). Prints a table and writes JSON (``--out``).

    python benchmarks/at_rest.py --device cpu --quick
    python benchmarks/at_rest.py --device cuda:0 --pile 1000
    python benchmarks/at_rest.py --device cpu --quick --dt-scale 4
"""

import argparse
import json
import math
import os
import sys

import numpy as np
import warp as wp

import polydem
from polydem import ConvexShape, Scene, Simulation

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _meta import run_meta  # noqa: E402

G = 9.81
LAWS = [("hertz", None), ("power", 1.5), ("power", 2.0), ("linear", None)]
PRECISIONS = ("mixed", "float64", "float32")


def material(scene, law, m, k, e, mu, density):
    kw = dict(density=density, law=law, k=k, restitution=e, friction=mu)
    if m is not None:
        kw["m"] = m
    scene.add_material("m", **kw)


def scaled_step(scene, dt_scale):
    """``scene`` at ``dt_scale`` times its recommended step (1: dt = "auto" as built)."""
    if dt_scale != 1.0:
        scene.dt = dt_scale * scene.time_step().recommended
    return scene


def cube_case(device, law, m, e, precision, steps, dt_scale=1.0):
    k = {"hertz": 1e10, "power": 1e10, "linear": 1e6}[law] if law != "power" or m < 2 else 1e10
    if precision == "float32" and law == "hertz":
        k = 1e8  # float32 positions near 0.05 m round to 3.7e-9 m: rest 5.8e-7 m deep
    scene = Scene(gravity=(0, 0, -G), dt="auto", precision=precision)
    material(scene, law, m, k, e, 0.3, 7800.0)
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("cube", "m", position=(0.0, 0.0, 0.05))
    scene.add_plane((0, 0, 0), (0, 0, 1), "m")
    sim = Simulation(scaled_step(scene, dt_scale), device)
    sim.step(int(0.1 / sim.dt))
    weight = 7.8 * G
    f, z = [], []
    for _ in range(steps):
        sim.step(1)
        c = sim.contacts()
        f.append(float(np.sum(c["normal_force"])) / weight)
        z.append(float(sim.state()["body_position"][0, 2]))
    return {"dt": sim.dt, "force_min": min(f), "force_max": max(f), "height_range": float(np.ptp(z))}


def slope_case(device, law, m, e, precision, duration, dt_scale=1.0):
    th = math.radians(20.0)
    scene = Scene(gravity=(G * math.sin(th), 0, -G * math.cos(th)), dt="auto", precision=precision)
    material(scene, law, m, 1e9 if law != "linear" else 1e6, e, 0.5, 2700.0)
    scene.add_shape("block", ConvexShape.box(0.2, 0.1, 0.05))
    scene.add_body("block", "m", position=(0.0, 0.0, 0.025))
    scene.add_plane((0, 0, 0), (0, 0, 1), "m")
    sim = Simulation(scaled_step(scene, dt_scale), device)
    sim.step(int(0.05 / sim.dt))
    x0 = sim.state()["body_position"][0].copy()
    weight = 2700.0 * 1e-3 * G * math.cos(th)  # the block's normal load [N]
    fn = []
    for _ in range(20):
        sim.step(max(1, int(duration / 20 / sim.dt)))
        fn.append(float(np.sum(sim.contacts()["normal_force"])) / weight)
    moved = float(np.linalg.norm(sim.state()["body_position"][0] - x0))
    return {"dt": sim.dt, "moved": moved, "duration": duration, "normal_min": min(fn), "normal_max": max(fn)}


def pile_case(device, n, precision, max_time, dt_scale=1.0):
    """N cubes of 1 cm dropped from a loose grid into a 'frictionless' box; balance after settling."""
    edge = 0.01
    side = max(2, int(round(n ** (1.0 / 3.0))))
    layers = math.ceil(n / side**2)
    scene = Scene(gravity=(0, 0, -G), dt="auto", precision=precision)
    scene.add_material("grain", density=2500.0, law="hertz", k=4.9e8, restitution=0.3, friction=0.5)
    scene.add_material("wall", density=2500.0, law="hertz", k=4.9e8, restitution=0.3, friction=0.0)
    scene.add_shape("cube", ConvexShape.box(edge))
    pitch = 1.3 * edge
    half = 0.5 * side * pitch + 0.2 * edge
    rng = np.random.default_rng(0)
    count = 0
    for k in range(layers):
        for i in range(side):
            for j in range(side):
                if count == n:
                    break
                p = (-half + 0.2 * edge + (i + 0.5) * pitch, -half + 0.2 * edge + (j + 0.5) * pitch,
                     0.6 * edge + k * pitch)  # fmt: skip
                q = rng.normal(size=4)
                scene.add_body("cube", "grain", position=p, orientation=tuple(q / np.linalg.norm(q)))
                count += 1
    scene.add_plane((0, 0, 0), (0, 0, 1), "wall")
    for axis in range(2):
        for sign in (-1.0, 1.0):
            pt = [0.0, 0.0, 0.0]
            nr = [0.0, 0.0, 0.0]
            pt[axis] = sign * half
            nr[axis] = -sign
            scene.add_plane(tuple(pt), tuple(nr), "wall")
    sim = Simulation(scaled_step(scene, dt_scale), device)
    res = sim.run_until_settled(max_time)
    mass = 2500.0 * edge**3
    weight = n * mass * G
    push, worst = [], []
    for _ in range(40):
        sim.step(1)
        c = sim.contacts()
        f = -c["normal_force"][:, None] * c["normal"] + c["tangential_force"]  # on body A
        on_wall = c["body_b"] < 0
        push.append(float(f[on_wall, 2].sum()) / weight)
        net = np.zeros((n, 3))
        net[:, 2] -= mass * G
        np.add.at(net, c["body_a"], f)
        pair = ~on_wall
        np.add.at(net, c["body_b"][pair], -f[pair])
        worst.append(float(np.linalg.norm(net, axis=1).max()) / (mass * G))
    return {
        "bodies": n,
        "dt": sim.dt,
        "settled": bool(res.settled),
        "settle_time": res.time,
        "settle_wall_s": res.wall,
        "push_min": min(push),
        "push_max": max(push),
        "largest_net_force": max(worst),
        "largest_speed": float(res.largest_speed),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true", help="hertz in mixed only, fewer steps (a CPU check)")
    ap.add_argument("--pile", type=int, default=0, help="cubes in the settled pile (0: no pile)")
    ap.add_argument("--pile-max-time", type=float, default=2.0)
    ap.add_argument("--dt-scale", type=float, default=1.0, help='the step, x dt = "auto"')
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    wp.config.quiet = True
    wp.init()
    rows = []
    cases = []
    for law, m in LAWS[:1] if args.quick else LAWS:
        for precision in ("mixed",) if args.quick else PRECISIONS:
            es = (0.1, 0.3, 0.5, 0.9) if (law == "hertz" and precision == "mixed") else (0.3,)
            for e in es:
                cases.append((law, m, e, precision))
    for law, m, e, precision in cases:
        name = law if m is None else f"{law} m={m:g}"
        row = {"law": law, "m": m, "e": e, "precision": precision}
        try:
            row["cube"] = cube_case(args.device, law, m, e, precision, 100 if args.quick else 400, args.dt_scale)
            row["slope"] = slope_case(args.device, law, m, e, precision, 0.1 if args.quick else 0.5, args.dt_scale)
        except Exception as exc:  # a case that cannot run (e.g. validate refuses it) is reported, not fatal
            row["error"] = f"{type(exc).__name__}: {exc}"
        rows.append(row)
        if "error" in row:
            print(f"{name:12s} e {e:.1f} {precision:8s} | {row['error'][:100]}", flush=True)
            continue
        c, s = row["cube"], row["slope"]
        print(
            f"{name:12s} e {e:.1f} {precision:8s} | cube F/W {c['force_min']:.4f}..{c['force_max']:.4f} "
            f"height range {c['height_range']:.2g} m | slope moved {s['moved']:.2g} m in {s['duration']:g} s, "
            f"Fn/W {s['normal_min']:.4f}..{s['normal_max']:.4f}",
            flush=True,
        )
    out = {"meta": run_meta(wp.get_device(args.device)), "polydem": os.path.dirname(polydem.__file__)}
    out |= {"dt_scale": args.dt_scale, "cases": rows}
    if args.pile:
        pile = pile_case(args.device, args.pile, "mixed", args.pile_max_time, args.dt_scale)
        out["pile"] = pile
        print(
            f"pile of {pile['bodies']}: settled {pile['settled']} at {pile['settle_time']:.3f} s "
            f"({pile['settle_wall_s']:.1f} s wall); walls' push / weight "
            f"{pile['push_min']:.4f}..{pile['push_max']:.4f}; "
            f"largest net force on a grain {pile['largest_net_force']:.3g} of its weight",
            flush=True,
        )
    path = args.out or os.path.join(
        os.path.dirname(__file__), "results", f"at_rest_{args.device.replace(':', '')}.json"
    )
    with open(path, "w") as fh:
        json.dump(out, fh, indent=1)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
