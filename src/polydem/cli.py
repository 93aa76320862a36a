"""The ``polydem`` command: run a scene, check the installation.

polydem run                 # the built-in default scene
polydem run scene.toml --device cpu --duration 0.2 --out results/
polydem info
"""

import argparse
import json
import os
import sys
import time

import numpy as np

from polydem.scene import SceneError


def _load_scene(path):
    from polydem.scene import Scene

    if path is None:
        from polydem.default_scene import default_scene

        return default_scene()
    return Scene.from_toml(path)


def _summary(sim, wall, steps):
    e = sim.energy()
    c = sim.contacts()
    vol = np.array([s.volume for s in sim.model.scene.shapes.values()])[sim.model.scene.body_shape]
    rel = 0.0
    if len(c["volume"]):
        rel = float(np.max(c["volume"] / vol[c["body_a"]]))
    return {
        "scene": sim.model.scene.name,
        "bodies": sim.num_bodies,
        "steps": steps,
        "dt": sim.dt,
        "simulated_time": sim.time,
        "wall_time": wall,
        "body_steps_per_second": sim.num_bodies * steps / wall if wall > 0 else None,
        "contacts": int(len(c["volume"])),
        "largest_overlap_relative": rel,
        "energy": e,
        "device": str(sim.device),
    }


def cmd_run(args):
    import warp as wp

    from polydem.simulation import Simulation

    wp.config.quiet = True
    scene = _load_scene(args.scene)
    sim = Simulation(scene, device=args.device)
    if args.steps is not None:
        steps = args.steps
    else:
        duration = args.duration if args.duration is not None else (scene.duration or None)
        steps = int(np.ceil(duration / sim.dt)) if duration else (scene.steps or 1000)
    print(f"{scene.name}: {sim.num_bodies} bodies on {sim.device}, dt {sim.dt:.3g} s, {steps} steps", flush=True)
    t0 = time.perf_counter()
    done = 0
    report = max(1, steps // 20)
    try:
        while done < steps:
            n = min(report, steps - done)
            sim.step(n)
            done += n
            wall = time.perf_counter() - t0
            e = sim.energy()
            print(
                f"  t = {sim.time:8.4f} s  {done / wall:9.1f} steps/s  {len(sim.contacts()['volume']):7d} contacts  "
                f"kinetic {e['kinetic']:.4g} J",
                flush=True,
            )
    except KeyboardInterrupt:
        print("interrupted: writing the summary of the steps so far", file=sys.stderr)
    summary = _summary(sim, time.perf_counter() - t0, done)
    os.makedirs(args.out, exist_ok=True)
    path = os.path.join(args.out, "summary.json")
    with open(path, "w") as f:
        json.dump(summary, f, indent=1)
    print(
        f"done: {done} steps in {summary['wall_time']:.2f} s, {summary['contacts']} contacts, largest overlap "
        f"{summary['largest_overlap_relative']:.2%} of a body's volume; summary in {path}"
    )
    return 0


def cmd_info(args):
    import warp as wp

    import polydem

    wp.init()
    print(f"polydem {polydem.__version__}, Warp {wp.config.version}")
    for d in wp.get_devices():
        print(f"  {d.alias}: {d.name}")
    return 0


def main(argv=None):
    parser = argparse.ArgumentParser(prog="polydem", description="Discrete element simulation of convex polyhedra.")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run a scene (the built-in default when none is given)")
    run.add_argument("scene", nargs="?", default=None, help="scene file (TOML); default: the built-in default scene")
    run.add_argument("--device", default=None, help='Warp device, e.g. "cpu" or "cuda:0" (default: the GPU if any)')
    group = run.add_mutually_exclusive_group()
    group.add_argument("--steps", type=int, default=None, help="number of steps")
    group.add_argument("--duration", type=float, default=None, help="simulated time [s]")
    run.add_argument("--out", default="polydem_out", help="output folder (default: polydem_out)")
    run.set_defaults(func=cmd_run)
    info = sub.add_parser("info", help="print the Warp version and devices")
    info.set_defaults(func=cmd_info)
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except SceneError as err:
        print(f"polydem: error: {err}", file=sys.stderr)
        return 2
    except FileNotFoundError as err:
        print(f"polydem: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
