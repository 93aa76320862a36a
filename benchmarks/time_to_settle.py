"""Time to a settled packing: wall time until a poured pile of cubes (or of mixed shapes) comes to rest.

The scene is the settling benchmark's (benchmarks/settle.py: 1 cm cubes in loose columns in an open box of fixed
slabs, hertz (or settle.py's ``--law power --exponent m``), e = 0.5, mu = 0.5, k by settle.py's ``--k-rule``: corners
at most ``--corner-depth`` (5%) of the edge deep under a column, or ``volume``, the former 1% overlap under 20 column
weights; dt "auto"). Each run goes until the pile is settled by the simulator's own stopping rule
(``Simulation.run_until_settled``: the free bodies' kinetic energy below ``--kinetic-fraction`` of the gravitational
energy released, held for ``--hold`` seconds) or ``--max-time`` simulated seconds. Reported per size: settled or not,
simulated time and steps to it, wall time (the first chunk, which compiles the kernels and captures the CUDA graph, is
timed apart), wall time per simulated second; at the end the largest penetration depth (shortest separating
translation, as a fraction of the edge) and the largest overlap volume (of a cube's volume), the packing fraction and
coordination number of the settled interior (``polydem.cli.diagnostics.settled_region``, the summary's definition).
``--order`` lists the cubes in memory in another order (settle.py's option: grid, shuffled, morton) and
``--tree-rebuild`` sets the Simulation's tree renewal policy.

``--shapes mixed``: settle.py's mixed set instead of cubes (cubes, regular tetrahedra, 20-vertex
rocks and 2:1:1 boxes of the cube's volume, in equal numbers, in the same columns spaced for the
largest bounding sphere); the depth and overlap of each contact are then fractions of its smaller
body's size (the cube root of its volume) and volume (``polydem.cli.diagnostics.relative_depths``,
``relative_overlaps``): ``max_depth_fraction_of_size`` instead of ``max_depth_fraction_of_edge``.

    python benchmarks/time_to_settle.py --device cpu                       # 200 cubes
    python benchmarks/time_to_settle.py --device cuda:0 --sizes 1e4,1e5,1e6
    python benchmarks/time_to_settle.py --device cuda:0 --sizes 1e4,1e5 --shapes mixed

Results: a table on stdout and JSON (``--out``, default
``benchmarks/results/time_to_settle_<device>.json``, ``..._<device>_mixed.json`` for the mixed
set), rewritten after every size.
"""

import argparse
import dataclasses
import json
import os
import sys
import time

import numpy as np
import warp as wp

from polydem import Simulation
from polydem import settle as polydem_settle
from polydem.cli.diagnostics import body_volumes, relative_depths, relative_overlaps, settled_region

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _meta import activity_ms_per_step, run_meta  # noqa: E402
from settle import SHAPE_SETS, add_pile_options, apply_stepper_options, kernel_options, make_scene, scene_options  # noqa: E402

EDGE = 0.01  # cube edge [m]


def default_pour(n, device, shapes="cube", use_graph=None):
    """A Simulation of this benchmark's pour of ``n`` grains at its defaults (mixed precision, the volume rule's k,
    4 x the recommended step), for the scripts that time or profile pieces of it (host_share.py, pair_stalls.py)."""
    options = scene_options(edge=EDGE, precision="mixed", k_rule="volume", shapes=shapes)
    scene, _ = make_scene(n, options, seed=0)
    scene.dt = 4.0 * scene.time_step().recommended
    return Simulation(scene, device=device, use_graph=use_graph)


def _largest(values):
    return float(np.max(values)) if len(values) else 0.0


def with_tangential_ratio(scene, ratio):
    """The scene with every material's tangential spring set to ``ratio`` x the derived one (the
    reference normal stiffness of :meth:`Scene.time_step`)."""
    if ratio is None:
        return scene
    kn = float(np.nanmax(scene.time_step().tangential_stiffness))
    for name, mat in scene.materials.items():
        # validated again by the run
        scene.material_table.by_name[name] = dataclasses.replace(mat, tangential_stiffness=ratio * kn)
    return scene


def run_size(n, args, device, dt_scale=1.0):
    """Pour ``n`` bodies and run to settled at ``dt_scale`` x the recommended step; returns the record."""
    import polydem

    options = scene_options(
        edge=EDGE, precision=args.precision, order=args.order, shapes=args.shapes, k_rule=args.k_rule,
        corner_depth=args.corner_depth, k_factor=args.k_factor, law=args.law, exponent=args.exponent,
    )  # fmt: skip
    scene, info = make_scene(n, options, seed=args.seed)
    scene = with_tangential_ratio(scene, args.tangential_ratio)
    ts = scene.time_step()
    scene.dt = dt_scale * ts.recommended
    t0 = time.perf_counter()
    sim = Simulation(scene, device=device, tree_rebuild=args.tree_rebuild, **kernel_options(args))
    sim = apply_stepper_options(sim, args)
    e0 = sim.energy()
    sim.step(1)  # kernels compiled, graph captured
    wp.synchronize_device(sim.device)
    setup = time.perf_counter() - t0
    criterion = polydem.SettleCriterion(
        kinetic_fraction=args.kinetic_fraction, speed_fraction=args.speed_fraction, hold=args.hold
    )
    t1 = time.perf_counter()
    result = sim.run_until_settled(args.max_time, criterion)
    wp.synchronize_device(sim.device)
    wall = time.perf_counter() - t1
    e1 = sim.energy()
    released = e0["gravity"] - e1["gravity"]
    profile = step_profile(sim, args.profile_steps) if args.profile_steps else None
    contacts = sim.contacts()
    state = sim.state()
    region = settled_region(scene, state, contacts)
    free = np.flatnonzero(scene.body_kind == 0)
    if args.shapes == "cube":
        sizes = {
            "max_depth_fraction_of_edge": _largest(contacts["depth"]) / EDGE,
            "max_overlap_volume_fraction": _largest(contacts["volume"]) / EDGE**3,
        }
    else:
        # Bodies of different shapes: each contact against its smaller body (the summary's measure).
        volumes = body_volumes(scene)
        sizes = {
            "max_depth_fraction_of_size": _largest(relative_depths(contacts, volumes)),
            "max_overlap_volume_fraction": _largest(relative_overlaps(contacts, volumes)),
        }
    return {
        "bodies": n,
        "shapes": args.shapes,
        "precision": args.precision,
        "order": args.order,
        "tree_rebuild": sim.tree_rebuild,
        "spread_pairs": sim.stepper.spread_pairs,
        "shared_poly": sim.stepper.kernels.shared_poly,
        "tree_rebuilds": sim.current_contacts.broadphase.num_tree_rebuilds,
        "dt": sim.dt,
        "dt_scale": dt_scale,
        "dt_recommended": ts.recommended,
        "dt_limit": ts.limit,
        "tangential_ratio": args.tangential_ratio,
        "energy_error_of_released": (e1["total"] - e0["total"]) / released if released > 0 else None,
        "released_j": released,
        "settled": bool(result.settled),
        "settle_time_s": float(result.time) if result.settled else None,
        "simulated_s": sim.time,
        "steps": sim.steps_done,
        "setup_wall_s": setup,
        "wall_s": wall,
        "wall_s_per_simulated_s": wall / max(sim.time, 1e-30),
        **sizes,
        "packing_fraction": region.get("packing_fraction"),
        "coordination_number": region.get("coordination_number"),
        "largest_speed_m_s": float(np.linalg.norm(state["body_velocity"][free], axis=1).max()),
        "scene": info,
        "profile": profile,
    }


def step_profile(sim, steps):
    """The settled pile's step, ``steps`` more of them: the wall time per step as run_until_settled takes them
    (graph chunks), each captured graph's GPU time per step, and (graphs off) each kernel's and copy's."""
    wp.synchronize_device(sim.device)
    t0 = time.perf_counter()
    sim.step(steps)
    wp.synchronize_device(sim.device)
    record = {"steps": steps, "wall_ms_per_step": 1e3 * (time.perf_counter() - t0) / steps}
    if not sim.device.is_cuda:
        return record
    graphs = sim.use_graph
    for use_graph, filt in ((True, wp.TIMING_GRAPH), (False, wp.TIMING_KERNEL | wp.TIMING_MEMCPY)):
        sim.use_graph = use_graph
        sim.step(3)
        sums = activity_ms_per_step(lambda: sim.step(steps), steps, filt)
        record["graphs_ms_per_step" if use_graph else "kernels_ms_per_step"] = sums
    sim.use_graph = graphs
    return record


def make_parser():
    """The command line's options (converged_pile.py runs with them too)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    ap.add_argument("--sizes", default=None, help="comma-separated cube counts (default 200 on the CPU, 1e4 on a GPU)")
    ap.add_argument("--max-time", type=float, default=1.0, help="simulated seconds at most")
    ap.add_argument("--kinetic-fraction", type=float, default=1e-4, help="settled: kinetic < this x released")
    ap.add_argument("--hold", type=float, default=0.02, help="settled for this long [s]")
    ap.add_argument(
        "--speed-fraction",
        type=lambda v: None if v == "off" else float(v),
        default=polydem_settle.SettleCriterion().speed_fraction,
        help="settled: every grain's fastest point below this x sqrt(g r_min) ('off': the kinetic part "
        "alone, the rule before issue 22; default: the simulator's)",
    )
    ap.add_argument("--precision", default="mixed", choices=("float32", "mixed", "float64"))
    ap.add_argument("--shapes", default="cube", choices=SHAPE_SETS, help="cubes, or settle.py's mixed set")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--profile-steps", type=int, default=0, help="after settling, profile this many more steps")
    ap.add_argument(
        "--dt-scales", default="1", help="comma-separated steps, as multiples of the recommended dt (dt = 'auto')"
    )
    ap.add_argument(
        "--tangential-ratio",
        type=float,
        default=None,
        help="tangential spring stiffness / the derived one (the reference normal stiffness; default: derived)",
    )
    add_pile_options(ap)
    ap.add_argument("--out", default=None, help="JSON (default benchmarks/results/time_to_settle_<device>.json)")
    return ap


def main():
    args = make_parser().parse_args()

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    default = "200" if device.is_cpu else "1e4"
    sizes = [int(float(s)) for s in (args.sizes or default).split(",")]
    tag = str(device).replace(":", "") + ("" if args.shapes == "cube" else f"_{args.shapes}")
    out = args.out or os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", f"time_to_settle_{tag}.json")
    record = {"meta": run_meta(device), "args": vars(args), "runs": []}
    head = ("cubes" if args.shapes == "cube" else "bodies", "dt x rec", "settled", "t_settle", "steps", "wall s")
    head += ("wall/sim", "depth", "max V", "phi", "Z", "E error")
    print(" ".join(f"{h:>9s}" for h in head))
    scales = [float(x) for x in args.dt_scales.split(",")]
    for n, scale in ((n, scale) for n in sizes for scale in scales):
        r = run_size(n, args, device, scale)
        record["runs"].append(r)
        os.makedirs(os.path.dirname(out), exist_ok=True)
        with open(out, "w") as f:
            json.dump(record, f, indent=1)
        t = r["settle_time_s"]
        depth = r.get("max_depth_fraction_of_edge", r.get("max_depth_fraction_of_size"))
        print(
            f"{n:>9d} {scale:>9.3g} {str(r['settled']):>9s} {(format(t, '.3f') if t is not None else '-'):>9s} "
            f"{r['steps']:>9d} {r['wall_s']:>9.2f} {r['wall_s_per_simulated_s']:>9.2f} {100 * depth:>8.1f}% "
            f"{100 * r['max_overlap_volume_fraction']:>8.2f}% {r['packing_fraction'] or float('nan'):>9.3f} "
            f"{r['coordination_number'] or float('nan'):>9.2f} {r['energy_error_of_released'] or float('nan'):>+9.2e}"
        )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
