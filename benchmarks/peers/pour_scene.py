"""The pour used to compare polydem with other DEM codes, exported for them, and polydem's own run of it.

The scene is the one of ``benchmarks/settle.py`` (its ``make_scene``, default options): N cubes of
1 cm edge (2500 kg/m^3) in columns of 10 with small gaps, uniformly random orientations, in an open
box of five fixed box bodies; hertz law sized for 1% overlap under 20 column weights, restitution
0.5, friction 0.5, polydem's recommended step. The cubes topple and settle into a pile.

Protocol, the same for every code: ``--warmup`` steps (default 1250 = 0.02 s, by when most cubes
touch), then ``--steps`` timed steps (default 500), all with polydem's recommended dt; then the
final poses are written so that :mod:`compare` can measure the overlaps of every code with the same
exact geometry (``polydem.overlap`` in float64).

    python benchmarks/peers/pour_scene.py export --grains 1000         # -> results/peers/pour_1000.json
    python benchmarks/peers/pour_scene.py run --grains 1000 --device cpu   # polydem's run of it

``export`` writes the scene for the other codes: per cube its world vertices (Yade builds each body
from them), its body-frame pose and the cube's body-frame vertices (Newton), the five walls as world
vertices and as centre + half extents, the material, the gravity and the step. ``run`` times
polydem on the same protocol and writes ``results/peers/polydem_pour_<device>_<N>.json`` in the
format that the peers' scripts write.
"""

import argparse
import json
import os
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
BENCH = os.path.dirname(HERE)
OUT_DIR = os.path.join(BENCH, "results", "peers")
sys.path.insert(0, BENCH)
from _meta import run_meta  # noqa: E402


def settle_options(layers=10):
    """benchmarks/settle.py's defaults for the scene."""
    import settle

    return settle.scene_options(layers=layers)


def build(n):
    """(scene, info) of the pour with n cubes."""
    import settle

    return settle.make_scene(n, settle_options())


def export(n, path, world_vertices=True):
    """Write the pour of ``n`` cubes as JSON; without ``world_vertices`` (the Yade scripts' and compare.py's
    input, 8 corners a cube: most of the file and of its time) the cubes are poses only, all Newton reads."""
    scene, info = build(n)
    ts = scene.time_step()  # the Model's dt and limit, on the host
    kinds = np.asarray(scene.body_kind)
    shapes = scene.shapes
    names = scene.shape_names
    body_shape = np.asarray(scene.body_shape)
    cube = shapes["cube"]
    free = np.flatnonzero(kinds == 0)
    walls = np.flatnonzero(kinds != 0)
    mat = scene.materials["grain"]
    data = {
        "grains": int(len(free)),
        "edge": 0.01,
        "density": mat.density,
        "gravity": list(scene.gravity),
        "dt": float(ts.dt),
        "dt_limit": float(ts.limit),
        "material": {"law": mat.law, "k": mat.k, "restitution": mat.restitution, "friction": mat.friction},
        "design": {
            "note": "k sized so that a face contact carrying 20 weights of a 10-cube column overlaps by 1% of a cube",
            "design_force_N": 20.0 * 10 * mat.density * 0.01**3 * 9.81,
            "design_overlap_volume_m3": 0.01 * 0.01**3,
        },
        "container_inner_m": info["container_inner_m"],
        "cube_body_vertices": np.asarray(cube.vertices).tolist(),
        "cube_faces": [[int(k) for k in f] for f in cube.faces],
        "cube_triangles": np.asarray(cube.to_trimesh().faces).tolist(),
        "cube_volume": float(cube.volume),
        "cube_inertia_body": (np.asarray(cube.inertia) * mat.density).tolist(),
        "cubes": {
            "position": np.asarray(scene.body_position)[free].tolist(),
            "orientation_xyzw": np.asarray(scene.body_orientation)[free].tolist(),
        },
        "walls": [],
    }
    if world_vertices:
        data["cubes"]["world_vertices"] = [scene.body_vertices(int(i)).tolist() for i in free]
    for i in walls:
        s = shapes[names[body_shape[i]]]
        v = np.asarray(s.vertices)
        data["walls"].append(
            {
                "center": np.asarray(scene.body_position[i]).tolist(),
                "orientation_xyzw": np.asarray(scene.body_orientation[i]).tolist(),
                "half_extents_body": (0.5 * (v.max(axis=0) - v.min(axis=0))).tolist(),
                "world_vertices": scene.body_vertices(int(i)).tolist(),
            }
        )
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "w") as f:
        json.dump(data, f)
    print(f"wrote {path}: {len(free)} cubes, {len(walls)} walls, dt {ts.dt:.4g} s", flush=True)
    return data


def run_polydem(n, device, warmup, steps, out, settle_time=0.0):
    import warp as wp

    from polydem import Simulation

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    wp.init()
    dev = wp.get_device(device)
    scene, info = build(n)
    t0 = time.perf_counter()
    sim = Simulation(scene, device=dev)
    t_init = time.perf_counter() - t0
    print(f"polydem: {n} cubes, Simulation() {t_init:.2f} s; {warmup} warm-up steps", flush=True)
    sim.step(warmup)
    wp.synchronize_device(dev)
    print(f"polydem: warm-up done, timing {steps} steps", flush=True)
    t0 = time.perf_counter()
    sim.step(steps)
    wp.synchronize_device(dev)
    wall = time.perf_counter() - t0
    free = np.asarray(scene.body_kind) == 0
    c = sim.contacts()
    window = {
        "contacts": int(len(c["volume"])),
        "max_overlap_volume_fraction_own": float(c["volume"].max() / (0.01**3)) if len(c["volume"]) else 0.0,
    }
    at_rest = None
    if settle_time > sim.time:
        t0 = time.perf_counter()
        rest = int(round((settle_time - sim.time) / sim.dt))
        print(f"polydem: {1e3 * wall / steps:.3f} ms/step; {rest} more steps to {settle_time} s", flush=True)
        sim.step(rest)
        wp.synchronize_device(dev)
        c = sim.contacts()
        v = sim.state()["body_velocity"][free]
        at_rest = {
            "time_s": sim.time,
            "wall_s": time.perf_counter() - t0,
            "contacts": int(len(c["volume"])),
            "max_overlap_volume_fraction_own": float(c["volume"].max() / (0.01**3)) if len(c["volume"]) else 0.0,
            "max_speed_m_s": float(np.linalg.norm(v, axis=1).max()),
        }
    st = sim.state()
    result = {
        "code": "polydem",
        "version": __import__("polydem").__version__,
        "device": dev.name,
        "threads": 1 if not dev.is_cuda else None,
        "grains": int(free.sum()),
        "dt": sim.dt,
        "warmup_steps": warmup,
        "steps": steps,
        "init_s": t_init,
        "wall_s": wall,
        "step_s": wall / steps,
        "body_steps_per_s": int(free.sum()) * steps / wall,
        "contacts": window["contacts"],
        "max_overlap_volume_fraction_own": window["max_overlap_volume_fraction_own"],
        "at_rest": at_rest,
        "final": {
            "position": st["body_position"][free].tolist(),
            "orientation_xyzw": st["body_orientation"][free].tolist(),
        },
        "meta": run_meta(dev),
    }
    with open(out, "w") as f:
        json.dump(result, f)
    print(
        f"polydem on {dev.name}: {n} cubes, {steps} steps after {warmup}: {1e3 * wall / steps:.3f} ms/step, "
        f"{result['body_steps_per_s'] / 1e6:.3f} M body-steps/s, {result['contacts']} contacts"
        + (
            f"; at rest ({at_rest['time_s']:.2f} s): largest overlap "
            f"{100 * at_rest['max_overlap_volume_fraction_own']:.2f}% of a cube"
            if at_rest
            else ""
        )
        + f"; wrote {out}",
        flush=True,
    )
    return result


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("mode", choices=("export", "run"))
    ap.add_argument("--grains", type=int, default=1000)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--warmup", type=int, default=1250)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument(
        "--settle-time", type=float, default=None, help="go on to this simulated time for at-rest figures (GPU 0.5 s)"
    )
    ap.add_argument(
        "--no-world-vertices", action="store_true", help="export: poses only (enough for Newton; Yade needs them)"
    )
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    if args.mode == "export":
        path = args.out or os.path.join(OUT_DIR, f"pour_{args.grains}.json")
        export(args.grains, path, world_vertices=not args.no_world_vertices)
    else:
        os.makedirs(OUT_DIR, exist_ok=True)
        dev = args.device.replace(":", "")
        out = args.out or os.path.join(OUT_DIR, f"polydem_pour_{dev}_{args.grains}.json")
        settle = args.settle_time if args.settle_time is not None else (0.5 if "cuda" in args.device else 0.0)
        run_polydem(args.grains, args.device, args.warmup, args.steps, out, settle)


if __name__ == "__main__":
    main()
