"""The three precisions side by side: speed, energy balance and positions on one settling pile.

The scene is the settling benchmark's (benchmarks/settle.py: 1 cm cubes in columns in an open box
of fixed slabs, hertz law, friction, k for a 1% overlap under load, dt "auto"), ``--bodies`` cubes
(1000). The same scene runs in "float32", "mixed" and "float64" (``[simulation] precision``) for
``--steps`` steps (4000, 0.11 s simulated: the pile is in contact from about 0.05 s) after a first
step that compiles the kernels (and captures the CUDA graph).
Reported per precision:

* ms/step: the median over chunks of 64 steps through ``Simulation.step`` (the production path),
  synchronised at each chunk's end;
* energy error: the change of ``energy()["total"]`` (kinetic + contact + gravity + dissipated)
  over the run, relative to the energy the pile released (the fall of its gravitational energy);
* the final positions' largest and rms distance from the float64 run's, in metres and in edges,
  and the largest overlap volume (fraction of a cube's volume) at the end.

With ``--offset D`` the whole scene is moved by (D, D, D) metres, so that the modes are compared
far from the origin too (the positions are then compared relative to the offset).

    python benchmarks/precision.py --device cuda:0                       # 1000 cubes, 4000 steps
    python benchmarks/precision.py --device cpu --bodies 200 --steps 200 # a few minutes on a CPU
    python benchmarks/precision.py --device cuda:0 --offset 1000

Results: a table on stdout and JSON (``--out``, default
``benchmarks/results/precision_<device>.json``) with the machine, Warp version and command line.
"""

import argparse
import json
import os
import sys
import time

import numpy as np
import warp as wp

from polydem import Scene, Simulation
from polydem.simulation import CHUNK_STEPS as CHUNK

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _meta import run_meta  # noqa: E402
from settle import make_scene, scene_options  # noqa: E402

PRECISIONS = ("float32", "mixed", "float64")
EDGE = 0.01  # cube edge [m]


def shifted(scene, offset):
    """``scene`` with every body moved by ``offset`` (3,) [m] (the container is made of bodies)."""
    if not np.any(offset):
        return scene
    data = scene.to_dict()
    for body in data.get("bodies", []):
        body["position"] = (np.asarray(body["position"], dtype=np.float64) + offset).tolist()
    return Scene.from_dict(data)


def run_one(scene, precision, steps, device):
    scene.precision = precision
    t0 = time.perf_counter()
    sim = Simulation(scene, device=device)
    sim.step(1)  # compiles the kernels (and captures the graph on CUDA)
    wp.synchronize_device(sim.device)
    setup = time.perf_counter() - t0
    e0 = sim.energy()
    per_chunk = []
    done = 0
    while done < steps:
        n = min(CHUNK, steps - done)
        t = time.perf_counter()
        sim.step(n)
        wp.synchronize_device(sim.device)
        per_chunk.append((time.perf_counter() - t) / n)
        done += n
    e1 = sim.energy()
    released = e0["gravity"] - e1["gravity"]
    contacts = sim.contacts()
    return sim, {
        "precision": precision,
        "setup_s": setup,
        "ms_per_step_median": 1e3 * float(np.median(per_chunk)),
        "ms_per_step_min": 1e3 * float(np.min(per_chunk)),
        "energy_start": e0,
        "energy_end": e1,
        "released_energy_J": released,
        "energy_error_relative": (e1["total"] - e0["total"]) / released if released > 0.0 else float("nan"),
        "contacts": int(len(contacts["volume"])),
        "max_overlap_volume_fraction": float(contacts["volume"].max()) / EDGE**3 if len(contacts["volume"]) else 0.0,
        "max_depth_edges": float(contacts["depth"].max()) / EDGE if len(contacts["depth"]) else 0.0,
    }


IMPACTS = {
    # name: (orientation as a rotation vector [rad], restitution)
    "face_e1": ((0.0, 0.0, 0.0), 1.0),
    "face_e0.5": ((0.0, 0.0, 0.0), 0.5),
    "edge_e0.5": ((0.0, 0.7853981633974483, 0.0), 0.5),
    "corner_e0.5": ((0.6154797086703873, 0.7853981633974483, 0.0), 0.5),
}
IMPACT_SPEED = 1.0  # [m/s]


def impact(name, precision, device, offset):
    """A 1 cm cube falling at IMPACT_SPEED (no gravity, no friction) on a plane wall, face, edge or
    corner first: rebound speed against e v0, energy balance over the impact, largest depth."""
    from scipy.spatial.transform import Rotation

    rotvec, e = IMPACTS[name]
    k = 1.4e9  # hertz: a face impact at 1 m/s reaches about 1% of the edge in depth
    scene = Scene(gravity=(0.0, 0.0, 0.0), dt="auto", name=f"impact_{name}")
    scene.precision = precision
    scene.add_material("m", density=2500.0, law="hertz", k=k, restitution=e, friction=0.0)
    from polydem import ConvexShape

    scene.add_shape("cube", ConvexShape.box(EDGE, EDGE, EDGE))
    q = Rotation.from_rotvec(rotvec).as_quat()
    lowest = float((Rotation.from_quat(q).apply(np.array(ConvexShape.box(EDGE, EDGE, EDGE).vertices))[:, 2]).min())
    gap = 1e-4 * EDGE
    scene.add_body(
        "cube", "m", position=offset + (0.0, 0.0, -lowest + gap), orientation=q, velocity=(0, 0, -IMPACT_SPEED)
    )
    scene.add_plane(offset, (0.0, 0.0, 1.0), "m")
    sim = Simulation(scene, device=device)
    e0 = sim.energy()
    depth = 0.0
    touched = False
    per_chunk = []
    steps = 0
    limit = int(0.2 * EDGE / (IMPACT_SPEED * sim.dt)) + 10000
    while steps < limit:
        t = time.perf_counter()
        sim.step(8)
        wp.synchronize_device(sim.device)
        per_chunk.append((time.perf_counter() - t) / 8)
        steps += 8
        c = sim.contacts()
        if len(c["depth"]):
            touched = True
            depth = max(depth, float(c["depth"].max()))
        elif touched:
            break
    e1 = sim.energy()
    v = sim.state()["body_velocity"][0]
    return {
        "impact": name,
        "precision": precision,
        "restitution": e,
        "dt": sim.dt,
        "steps": steps,
        "ms_per_step_median": 1e3 * float(np.median(per_chunk)),
        "rebound_error": float(v[2] / (e * IMPACT_SPEED) - 1.0),
        "energy_error_relative": float((e1["total"] - e0["total"]) / e0["total"]),
        "max_depth_edges": depth / EDGE,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu", help="Warp device (default cpu)")
    ap.add_argument("--bodies", type=int, default=1000, help="cubes in the pile")
    ap.add_argument("--steps", type=int, default=4000, help="steps after the first (4000: 0.11 s, the pile in contact)")
    ap.add_argument("--offset", type=float, default=0.0, help="move the scene by (D, D, D) metres")
    ap.add_argument("--precisions", default=",".join(PRECISIONS), help="comma-separated subset")
    ap.add_argument("--out", default=None, help="JSON file (default benchmarks/results/precision_<device>.json)")
    ap.add_argument("--no-impacts", action="store_true", help="skip the single-cube impacts")
    args = ap.parse_args()

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    options = scene_options(edge=EDGE)
    offset = np.full(3, args.offset)
    precisions = [p.strip() for p in args.precisions.split(",") if p.strip()]
    out = args.out or os.path.join(
        os.path.dirname(os.path.abspath(__file__)), "results", f"precision_{str(device).replace(':', '')}.json"
    )
    record = {"meta": run_meta(device), "bodies": args.bodies, "steps": args.steps, "offset_m": args.offset}
    rows, finals = [], {}
    for precision in precisions:
        scene, info = make_scene(args.bodies, options)
        record["scene"] = info
        sim, row = run_one(shifted(scene, offset), precision, args.steps, device)
        finals[precision] = sim.state()["body_position"][: args.bodies] - offset
        row["dt"] = sim.dt
        rows.append(row)
        del sim
    if "float64" in finals:
        ref = finals["float64"]
        for row in rows:
            d = np.linalg.norm(finals[row["precision"]] - ref, axis=1)
            row["position_diff_max_m"] = float(d.max())
            row["position_diff_rms_m"] = float(np.sqrt(np.mean(d * d)))
            row["position_diff_max_edges"] = float(d.max()) / EDGE
    record["rows"] = rows
    impacts = []
    if not args.no_impacts:
        for name in IMPACTS:
            for precision in precisions:
                impacts.append(impact(name, precision, device, offset))
    record["impacts"] = impacts

    print(f"{args.bodies} cubes, {args.steps} steps on {device}, offset {args.offset:g} m")
    head = ("precision", "ms/step", "energy err", "dx max [m]", "dx rms [m]", "max V/Vc", "depth/edge")
    print(f"{head[0]:10s} {head[1]:>9s} {head[2]:>11s} {head[3]:>11s} {head[4]:>11s} {head[5]:>9s} {head[6]:>10s}")
    for r in rows:
        print(
            f"{r['precision']:10s} {r['ms_per_step_median']:9.3f} {r['energy_error_relative']:11.3e} "
            f"{r.get('position_diff_max_m', float('nan')):11.3e} {r.get('position_diff_rms_m', float('nan')):11.3e} "
            f"{r['max_overlap_volume_fraction']:9.4f} {r['max_depth_edges']:10.4f}"
        )
    if impacts:
        print("impacts: 1 cm cube at 1 m/s on a plane (rebound error = v_out / (e v_in) - 1)")
        head = ("impact", "precision", "ms/step", "rebound err", "energy err", "depth/edge")
        print(f"{head[0]:12s} {head[1]:10s} {head[2]:>9s} {head[3]:>12s} {head[4]:>11s} {head[5]:>10s}")
        for r in impacts:
            print(
                f"{r['impact']:12s} {r['precision']:10s} {r['ms_per_step_median']:9.3f} {r['rebound_error']:12.3e} "
                f"{r['energy_error_relative']:11.3e} {r['max_depth_edges']:10.4f}"
            )
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as f:
        json.dump(record, f, indent=1)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
