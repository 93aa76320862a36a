"""Angle of repose of heaps poured from a funnel (scenes/heap.toml), over seeds and grain shapes.

The fixed-funnel test: ``--grains`` grains of ``--shape`` (cube: 1 cm edge; tetrahedron: 2.04 cm
edge, the cube's volume; elbow: a non-convex L of three 6.93 mm cells, the cube's volume; or any
shape of the scene file) fill the funnel of scenes/heap.toml (the 7 cm orifice of the hopper mesh,
0.15 m above the floor) with its orifice shut, then run out and pile up until the heap is at rest.
The pour has two phases, so that the heap is built by the funnel's flow and not by the fall from the
emitter's column (for large bounding spheres, the tetrahedron's, that column is metres tall, and
grains dropped from it straight through the orifice hit the floor at 5 m/s and scatter into a flat
ring): (1) a gate, a plane at the orifice, holds the grains until they rest in the funnel (at most
``--fill-time``); (2) the same scene without the gate starts from that state (positions,
orientations, velocities and the grains' own friction history) and runs until it settles (the
run's settle check, at most ``--max-time``). The angle of repose is measured from
the final surface with ``polydem.analysis.angle_of_repose``: the highest grain centre in rings
around the heap's axis, a straight line through them over the flank (25% to 75% of the foot
radius). Each seed changes the grains' initial orientations and places; the table gives every
seed's angle and their mean and standard deviation per shape.

    python benchmarks/repose.py --device cpu --grains 300 --seeds 2
    python benchmarks/repose.py --device cuda:0 --grains 3000 --seeds 4 --shapes cube,tetrahedron,elbow

Writes JSON to ``--out`` (final positions included, so the angle can be measured again).
"""

import argparse
import json
import time
import tomllib
from pathlib import Path

import numpy as np
import warp as wp

from polydem import Scene, Simulation
from polydem.analysis import angle_of_repose
from polydem.scene.shape_specs import build_shape
from polydem.settle import SettleCriterion

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "heap.toml"


def heap_scene(shape, grains, seed, precision, gate=False):
    data = tomllib.loads(SCENE.read_text())
    em = data["emitters"][0]
    em["shape"] = shape
    em["count"] = grains
    em["seed"] = seed
    # A column over the bin tall enough for the grains.
    r = build_shape(shape, data["shapes"][shape], f"shapes.{shape}", SCENE, SCENE.parent)[0].radius
    cell = 2.0 * r * 1.1  # the emitter's grid: 1.1 bounding diameters
    per_layer = int(0.16 / cell) ** 2
    layers = int(np.ceil(grains / per_layer)) + 2
    em["region"] = {"min": [-0.08, -0.08, 0.31], "max": [0.08, 0.08, 0.31 + cell * layers]}
    data["simulation"]["precision"] = precision
    data["simulation"].pop("until_settled", None)
    data.pop("output", None)
    if gate:  # the last wall, so the other walls keep their indices
        z = data["walls"][0]["position"][2]
        data["walls"].append({"type": "plane", "point": [0.0, 0.0, z], "normal": [0.0, 0.0, 1.0], "material": "steel"})
    return Scene.from_dict(data, file=SCENE, base_dir=SCENE.parent)


def run_one(shape, grains, seed, args):
    t0 = time.perf_counter()
    filled = Simulation(heap_scene(shape, grains, seed, args.precision, gate=True), device=args.device)
    fill = filled.run_until_settled(args.fill_time, SettleCriterion())
    scene = heap_scene(shape, grains, seed, args.precision)
    sim = Simulation(scene, device=args.device)
    if sim.model.num_bodies != filled.model.num_bodies:
        raise RuntimeError("the gated and the open scene emitted different grains")
    # The grains' state and their pair history carry over; the wall springs start afresh (one wall less).
    snap = filled.snapshot()
    saved = {k: getattr(snap.state, k).numpy() for k in ("body_q", "body_v", "body_w", "body_dissipated", "step_count")}
    saved.update({k: getattr(sim.current_state, k).numpy() for k in ("wall_xi", "wall_turn")})
    count = int(snap.pairs.count.numpy()[0])
    saved.update(
        pair_key=snap.pairs.key.numpy()[:count],
        pair_xi=snap.pairs.xi.numpy()[:count],
        pair_turn=snap.pairs.turn.numpy()[:count],
    )
    sim.restore_from_arrays(saved, filled.steps_done, filled.time)
    result = sim.run_until_settled(args.max_time, SettleCriterion())
    wall = time.perf_counter() - t0
    pos = sim.state()["body_position"]
    size = 0.01 if shape == "cube" else float(scene.shapes[shape].volume) ** (1.0 / 3.0)
    # Grains still in the funnel (above its orifice) are not part of the heap.
    heap = pos[pos[:, 2] < 0.14]
    angle = angle_of_repose(heap, grain_size=size)
    return {
        "shape": shape,
        "grains": grains,
        "seed": seed,
        "filled": bool(fill.settled),
        "fill_time_s": filled.time,
        "settled": bool(result.settled),
        "time_s": sim.time,
        "steps": sim.steps_done,
        "wall_s": wall,
        "in_funnel": int(len(pos) - len(heap)),
        "angle": angle.to_dict(),
        "positions": heap.round(6).tolist(),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--grains", type=int, default=300)
    ap.add_argument("--shapes", default="cube")
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--fill-time", type=float, default=2.0, help="most time for the gated fill [s]")
    ap.add_argument("--max-time", type=float, default=4.0, help="most time for the discharge [s]")
    ap.add_argument("--precision", default="mixed")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    wp.config.quiet = True
    runs, summary = [], []
    for shape in args.shapes.split(","):
        angles = []
        for seed in range(args.first_seed, args.first_seed + args.seeds):
            r = run_one(shape, args.grains, seed, args)
            runs.append(r)
            write(args, runs, summary)  # each run as it ends: a long series cut short keeps its runs
            a = r["angle"]
            angles.append(a["angle_deg"])
            print(
                f"{shape:>12} seed {seed}: {a['angle_deg']:.1f} +- {a['stderr_deg']:.1f} deg (heap height "
                f"{a['height']:.3f} m, foot radius {a['foot_radius']:.3f} m, {r['in_funnel']} left in the funnel, "
                f"{'settled' if r['settled'] else 'NOT settled'} at {r['time_s']:.2f} s, {r['wall_s']:.0f} s wall)"
            )
        mean, sd = float(np.mean(angles)), float(np.std(angles, ddof=1)) if len(angles) > 1 else 0.0
        summary.append({"shape": shape, "mean_deg": mean, "sd_deg": sd, "seeds": len(angles)})
        print(f"{shape:>12}: {mean:.1f} deg, standard deviation {sd:.1f} deg over {len(angles)} seeds")
    print(f"wrote {write(args, runs, summary)}")


def write(args, runs, summary):
    tag = args.device.replace(":", "")
    out = Path(args.out or ROOT / f"benchmarks/results/issue13/repose_{tag}_{args.grains}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(vars(args), warp=wp.__version__)
    out.write_text(json.dumps({"meta": meta, "summary": summary, "runs": runs}))
    return out


if __name__ == "__main__":
    main()
