"""Convergence in k: the same pour of cubes at k, 4k and 16k, each run until it has settled, with dt "auto".

A pile is near the rigid limit when a stiffer k no longer changes it. The pour is settle.py's (1 cm cubes,
hertz, e = 0.5, mu = 0.5, columns of ``--layers`` in an open box of fixed slabs; ``--k-rule`` and
``--corner-depth`` choose the base k as there), run with k times each of ``--factors`` (dt = "auto" follows
k: as k^-1/2 from the reference contact, as 1/k where the resting rule of ``Scene.time_step`` sets it) until
settled (``Simulation.run_until_settled``: kinetic energy below ``--kinetic-fraction`` of the gravitational
energy released, for ``--hold`` s) or ``--max-time``. Reported per run: the packing fraction and coordination
number of the settled interior (``polydem.cli.diagnostics.settled_region``, the run summary's definition;
none for a bed narrower than about 4 cube diameters), and the depths of the corner contacts as fractions of
the edge, largest and median, next to the static corner depth under a column of ``--layers`` cubes that
``polydem.scene.depth`` predicts for the law alone and with the resolved toe of the run (``Model.toe_dt``). A
contact is a corner (or two crossing edges) where its overlap ``V < 0.42 |S| d`` (a cap ``V = c d^j`` has
``V = |S| d / j``: 1 face, 1/2 edge, 1/3 corner), from ``polydem.overlap`` of the contact's two bodies.

    python benchmarks/k_convergence.py --device cpu                               # 125 cubes, about 10 minutes
    python benchmarks/k_convergence.py --device cuda:0 --bodies 1000 --layers 10 --factors 1,4,16,64

Results: a table on stdout and JSON (``--out``, default ``benchmarks/results/k_convergence_<device>.json``),
rewritten after every run.
"""

import argparse
import json
import os
import sys
import time

import numpy as np
import warp as wp

import polydem
from polydem import Simulation, overlap
from polydem.cli.diagnostics import settled_region
from polydem.scene import depth

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _meta import run_meta  # noqa: E402
from settle import K_RULES, make_scene, scene_options  # noqa: E402

EDGE = 0.01  # cube edge [m]
CORNER_RATIO = 0.42  # V / (|S| d) below this: a corner (1/3) rather than an edge (1/2)


def contact_kinds(scene, state, contacts, device):
    """Per contact, V / (|S| d) of its two bodies' overlap (NaN for a wall plane or no depth)."""
    a, b = contacts["body_a"], contacts["body_b"]
    ratio = np.full(len(a), np.nan)
    names = scene.shape_names
    shape_of = np.asarray(scene.body_shape)
    poses = np.concatenate([state["body_position"], state["body_orientation"]], axis=1)
    body = b >= 0
    for sa, sb in {(int(shape_of[i]), int(shape_of[j])) for i, j in zip(a[body], b[body], strict=True)}:
        rows = np.flatnonzero(body & (shape_of[a] == sa) & (shape_of[np.maximum(b, 0)] == sb))
        res = overlap(
            scene.shapes[names[sa]], poses[a[rows]], scene.shapes[names[sb]], poses[b[rows]], frame="body",
            device=device, precision="float64",
        )  # fmt: skip
        with np.errstate(all="ignore"):
            ratio[rows] = res.volume / (np.linalg.norm(res.area_vector, axis=1) * res.depth)
    return ratio


def predicted_corner(scene, args, dt):
    """Static corner depth / edge under a column of ``args.layers`` cubes: (law alone, with the toe at dt)."""
    cube = scene.shapes["cube"]
    mat = scene.materials["grain"]
    mass = mat.density * cube.volume
    load = args.layers * mass * 9.81
    law = depth.resting_depth(cube, "hertz", mat.k, load)
    toe = depth.resting_depth(cube, "hertz", mat.k, load, toe=depth.Toe(mat.restitution, dt, 2.0 / mass))
    return law / EDGE, toe / EDGE


def run_factor(factor, args, device):
    options = scene_options(
        edge=EDGE, layers=args.layers, k_rule=args.k_rule, corner_depth=args.corner_depth, k_factor=factor
    )
    scene, info = make_scene(args.bodies, options, seed=args.seed)
    t0 = time.perf_counter()
    sim = Simulation(scene, device=device)
    criterion = polydem.SettleCriterion(kinetic_fraction=args.kinetic_fraction, hold=args.hold)
    result = sim.run_until_settled(args.max_time, criterion)
    wp.synchronize_device(sim.device)
    wall = time.perf_counter() - t0
    state = sim.state()
    contacts = sim.contacts()
    region = settled_region(scene, state, contacts)
    ratio = contact_kinds(scene, state, contacts, device)
    corner = ratio < CORNER_RATIO
    rel = contacts["depth"] / EDGE
    law, toe = predicted_corner(scene, args, sim.model.toe_dt)
    return {
        "factor": factor,
        "k_hertz": info["k_hertz"],
        "dt": sim.dt,
        "settled": bool(result.settled),
        "settle_time_s": float(result.time) if result.settled else None,
        "simulated_s": sim.time,
        "steps": sim.steps_done,
        "wall_s": wall,
        "packing_fraction": region.get("packing_fraction"),
        "coordination_number": region.get("coordination_number"),
        "region_bodies": region.get("bodies"),
        "contacts": len(rel),
        "corner_contacts": int(corner.sum()),
        "max_corner_depth": float(rel[corner].max()) if corner.any() else None,
        "median_corner_depth": float(np.median(rel[corner])) if corner.any() else None,
        "max_depth": float(rel.max()) if len(rel) else None,
        "max_overlap_volume_fraction": float(contacts["volume"].max() / EDGE**3) if len(rel) else None,
        "predicted_corner_depth_law": law,
        "predicted_corner_depth_toe": toe,
        "scene": info,
    }


def fmt(x, spec):
    return "-" if x is None else format(x, spec)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    ap.add_argument("--bodies", type=int, default=125, help="cubes in the pour")
    ap.add_argument("--layers", type=int, default=3, help="cubes per column (the column load of the k rule)")
    ap.add_argument("--factors", default="1,4,16", help="comma-separated multiples of the base k")
    ap.add_argument("--k-rule", choices=K_RULES, default="volume", help="base k: settle.py's rules")
    ap.add_argument("--corner-depth", type=float, default=0.05, help="k rule corner: corner depth / edge")
    ap.add_argument("--max-time", type=float, default=0.6, help="simulated seconds at most per run")
    ap.add_argument("--kinetic-fraction", type=float, default=1e-4, help="settled: kinetic < this x released")
    ap.add_argument("--hold", type=float, default=0.02, help="settled for this long [s]")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="JSON (default benchmarks/results/k_convergence_<device>.json)")
    args = ap.parse_args()

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    device = wp.get_device(args.device)
    tag = str(device).replace(":", "")
    out = args.out or os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", f"k_convergence_{tag}.json")
    record = {"meta": run_meta(device), "args": vars(args), "runs": []}
    head = ("k x", "k", "dt", "settled", "t", "steps", "wall s", "phi", "Z", "corners", "max c%", "med c%")
    head += ("max d%", "pred%", "toe%")
    print(" ".join(f"{h:>8s}" for h in head), flush=True)
    for factor in (float(x) for x in args.factors.split(",")):
        r = run_factor(factor, args, device)
        record["runs"].append(r)
        os.makedirs(os.path.dirname(out), exist_ok=True)
        with open(out, "w") as f:
            json.dump(record, f, indent=1)
        pct = [None if r[k] is None else 100.0 * r[k] for k in ("max_corner_depth", "median_corner_depth")]
        pct += [None if r[k] is None else 100.0 * r[k] for k in ("max_depth", "predicted_corner_depth_law")]
        pct.append(100.0 * r["predicted_corner_depth_toe"])
        print(
            f"{factor:>8.3g} {r['k_hertz']:>8.2e} {r['dt']:>8.2e} {str(r['settled']):>8s} "
            f"{fmt(r['settle_time_s'], '.3f'):>8s} {r['steps']:>8d} {r['wall_s']:>8.1f} "
            f"{fmt(r['packing_fraction'], '.3f'):>8s} {fmt(r['coordination_number'], '.2f'):>8s} "
            f"{r['corner_contacts']:>8d} " + " ".join(f"{fmt(p, '.2f'):>8s}" for p in pct),
            flush=True,
        )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
