"""Build time of a large pile (issue 27): scene -> validated Scene -> Model -> Simulation ready to step, stage by stage.

The target is 1e8 cubes built in under 2 minutes on a GPU machine, so the host part of the build must cost a
small constant per body: no Python loop over bodies or pairs. This script times each stage at several N and
reports seconds and microseconds per body, so that a stage whose cost grows with N with a large constant shows.

Scenes (``--builder``):

* ``settle`` (default): the pile of ``benchmarks/settle.py`` (``make_scene`` with its default options): cubes of
  1 cm in columns of 10 on a square grid, random orientations, in an open box container of five fixed box bodies,
  added by one ``Scene.add_bodies`` call (the way a large run builds its piles).
* ``emit``: the scene of ``scenes/cubes_10k.toml`` scaled to N: one ``Scene.emit`` (``[[emitters]]``) of N cubes,
  random orientations, filling the bottom of a box container whose floor grows with N (same cell size, 15 layers).
* ``emit-plane``: the same emitter over a floor plane and four side planes (the plane-wall checks of the emitter and
  of the initial overlaps, instead of the container's box bodies).

Stages (seconds, host clock; every stage on the same scene, in this order):

* ``scene``: building the Scene (materials, shapes, bodies, container).
* ``validate``: ``Scene.validate()``, with its checks timed apart (``check.<name>``: the functions of
  ``polydem.scene.checks`` and ``polydem.scene.overlaps`` that ``validate`` calls, wrapped for the run).
* ``simulation``: ``Simulation(scene, device, validate=False)``, with its parts timed apart by wrapping them:
  ``run_settings``, ``model`` (``Model.__init__``, with ``model.shapeset``, ``model.motions``, ``model.pair_table``),
  ``state`` (``Model.state``), ``contacts_init`` (``Contacts.__init__``: the broad phase's buffers),
  ``contacts_build`` (the first broad phase, ``Contacts.build``), ``stepper`` (``Stepper.__init__``), and
  ``simulation.rest`` (the remainder: bounding boxes, speed limits, ...).

Kernel compilation is excluded: before the timed sizes the script builds (and validates) a small pile of the same
kind once (``compile_s``, reported apart), which loads or compiles every Warp module the build launches. The GPU
part of the build (array uploads, the device broad phase) is what ``--device cuda:0`` measures; on the CPU the
Warp kernels run on the CPU.

``--profile N`` also runs cProfile over the whole build of N bodies and writes the functions with the largest
cumulative and own times to ``<out>.profile.txt``.

    python benchmarks/build_time.py --sizes 1e4,1e5,1e6 --repeats 3 --device cpu
    python benchmarks/build_time.py --sizes 1e6 --builder emit --profile 1e6 --no-git
    PYTHONPATH=/old/copy/of/the/package python benchmarks/build_time.py ...   # before a change (BENCHMARKS.md 15)

Results: a table on stdout (seconds per stage, us/body) and JSON (``--out``, default
``benchmarks/results/build_time/<builder>_<device>.json``), rewritten after every size.
"""

import argparse
import contextlib
import cProfile
import functools
import gc
import io
import json
import math
import os
import platform
import pstats
import resource
import sys
import time
import warnings

import numpy as np
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
import settle  # noqa: E402
from _meta import run_meta  # noqa: E402
from polydem.kernels.broadphase import BroadPhase  # noqa: E402

from polydem import Scene, Simulation  # noqa: E402
from polydem import contacts as contacts_module  # noqa: E402
from polydem import model as model_module  # noqa: E402
from polydem import simulation as simulation_module  # noqa: E402
from polydem.scene import checks, overlaps  # noqa: E402

BUILDERS = ("settle", "emit", "emit-plane")


def log(*args):
    print(*args, flush=True)


# ---------------------------------------------------------------------------------------------
# Scenes


def settle_scene(n, seed=0):
    """The pile of benchmarks/settle.py, at its default options."""
    return settle.make_scene(n, settle.scene_options(), seed=seed)[0]


def emit_scene(n, planes=False, seed=0):
    """scenes/cubes_10k.toml scaled to n cubes: the same cube, material and cell (1.1 x the bounding diameter), 15
    layers of cells, the floor grown so that 15 layers hold n cubes; walls of box bodies or planes."""
    edge = 0.01
    cell = 1.1 * math.sqrt(3.0) * edge
    layers = 15
    side = math.ceil(math.sqrt(n / layers)) * cell + 1e-9  # room for ceil(n / layers) cells per layer
    height = (layers + 1) * cell
    scene = Scene(gravity=(0.0, 0.0, -9.81), dt="auto", name=f"build_emit_{n}")
    scene.add_material("stone", density=2500.0, law="hertz", k=5.0e8, restitution=0.4, friction=0.5)
    scene.add_shape("cube", settle.ConvexShape.box(edge, name="cube"))
    h = 0.5 * side
    if planes:
        scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "stone")
        for axis, sign in ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0)):
            point = [0.0, 0.0, 0.0]
            normal = [0.0, 0.0, 0.0]
            point[axis] = -sign * h
            normal[axis] = sign
            scene.add_plane(tuple(point), tuple(normal), "stone")
    else:
        scene.add_box_container((0.0, 0.0, 0.5 * height), (side, side, height), "stone", wall_thickness=0.02)
    region = {"min": (-h, -h, 0.0), "max": (h, h, height)}
    scene.emit("cube", "stone", n, region, orientation="random", seed=seed)
    return scene


def make_scene(builder, n):
    if builder == "settle":
        return settle_scene(n)
    if builder == "emit":
        return emit_scene(n)
    if builder == "emit-plane":
        return emit_scene(n, planes=True)
    raise ValueError(f"unknown builder {builder!r}")


# ---------------------------------------------------------------------------------------------
# Timing the parts of validate() and Simulation() by wrapping them for the run


class Timers:
    """Seconds per name, summed over the calls of the wrapped functions (nested calls count in both); on a CUDA
    device with a mempool also the pool's bytes in use and its high-water mark when each wrapped call returns."""

    def __init__(self):
        self.seconds = {}
        self.memory = {}
        self.device = None

    def wrap(self, name, fn):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                pool = mempool(self.device)  # synchronises first: the stage's device work is in its time
                self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0
                if pool is not None:
                    self.memory[name] = pool

        return timed

    def take(self):
        out, self.seconds = self.seconds, {}
        return out

    def take_memory(self):
        out, self.memory = self.memory, {}
        return out


def mempool(device):
    """(bytes in use, high-water mark) of a CUDA device's mempool, after a sync; None elsewhere."""
    if device is None or not device.is_cuda or not wp.is_mempool_enabled(device) or device.is_capturing:
        return None
    wp.synchronize_device(device)
    return {"current": int(wp.get_mempool_used_mem_current(device)), "high": int(wp.get_mempool_used_mem_high(device))}


@contextlib.contextmanager
def patched(timers):
    """Wrap the functions whose time the table reports apart; unwrap them on exit."""
    targets = [
        (checks, name, f"check.{name}")
        for name in (
            "check_body_arrays",
            "check_float32",
            "check_position_spacing",
            "time_step",
            "check_steps",
            "check_loads",
            "check_tunnelling",
            "check_motion_speeds",
        )
    ]
    targets.append((overlaps, "check_initial_overlaps", "check.check_initial_overlaps"))
    targets.append((simulation_module, "run_settings", "run_settings"))
    targets.append((wp.utils, "radix_sort_pairs", "contacts_build.radix_sort_pairs"))
    targets.append((simulation_module, "device_pair_overlaps", "overlap_check_device"))
    saved = []
    for module, name, label in targets:
        saved.append((module, name, getattr(module, name)))
        setattr(module, name, timers.wrap(label, getattr(module, name)))
    methods = [
        (model_module.Model, "__init__", "model"),
        (model_module.Model, "_motions", "model.motions"),
        (model_module.Model, "state", "state"),
        (model_module.ShapeSet, "__init__", "model.shapeset"),
        (contacts_module.Contacts, "__init__", "contacts_init"),
        (contacts_module.Contacts, "build", "contacts_build"),
        (simulation_module.Stepper, "__init__", "stepper"),
        # inside the first broad phase (contacts_build): where the device memory's high-water mark is set
        (contacts_module.Contacts, "_allocate", "contacts_build.contacts_allocate"),
        (BroadPhase, "_allocate", "contacts_build.broadphase_allocate"),
        (BroadPhase, "_spatial_order", "contacts_build.spatial_order"),
        (BroadPhase, "_query", "contacts_build.query"),
        (wp.Bvh, "__init__", "contacts_build.bvh_init"),
        (Scene, "finish_overlap_check", "overlap_check_finish"),  # the Simulation's: planes, the message
    ]
    for cls, name, label in methods:
        saved.append((cls, name, cls.__dict__[name]))
        setattr(cls, name, timers.wrap(label, cls.__dict__[name]))
    # Scene.pair_table is a method of the scene class: time it inside the model.
    saved.append((Scene, "pair_table", Scene.__dict__["pair_table"]))
    Scene.pair_table = timers.wrap("model.pair_table", Scene.__dict__["pair_table"])
    try:
        yield
    finally:
        for owner, name, value in reversed(saved):
            setattr(owner, name, value)


def build(builder, n, device, timers, steps=0, overlap_check="host"):
    """One build of n bodies, then ``steps`` steps: (stage seconds, the Scene, the Simulation). On a CUDA device
    ``timers.memory`` holds the mempool at the end of each stage (``start``: before the Simulation)."""
    stages = {}
    timers.device = device
    timers.take_memory()
    gc.collect()
    t0 = time.perf_counter()
    scene = make_scene(builder, n)
    stages["scene"] = time.perf_counter() - t0
    timers.take()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        t0 = time.perf_counter()
        scene.validate(pair_overlaps=overlap_check == "host")
        stages["validate"] = time.perf_counter() - t0
        stages.update(timers.take())
        start = mempool(device)
        t0 = time.perf_counter()
        # validated above; with overlap_check "device" the Simulation finishes the check (the pairs on the device)
        sim = Simulation(scene, device, validate=False, overlap_check=overlap_check)
        wp.synchronize_device(device)
        stages["simulation"] = time.perf_counter() - t0
        if start is not None:
            timers.memory["start"] = start
            timers.memory["simulation"] = mempool(device)
        parts = timers.take()
        if steps:
            memory = timers.take_memory()
            timers.device = None  # no synchronisation inside the timed steps
            t0 = time.perf_counter()
            sim.step(steps)
            wp.synchronize_device(device)
            stages["steps"] = time.perf_counter() - t0
            timers.take()  # the steps' own broad phases are not the build's
            timers.memory = memory
            timers.device = device
            if start is not None:
                timers.memory["steps"] = mempool(device)
    stages.update(parts)
    top = ("run_settings", "model", "state", "contacts_init", "contacts_build", "stepper")
    top += ("overlap_check_device", "overlap_check_finish")
    stages["simulation.rest"] = stages["simulation"] - sum(parts.get(k, 0.0) for k in top)
    stages["total"] = stages["scene"] + stages["validate"] + stages["simulation"]
    return stages, scene, sim


def profile_build(builder, n, device, path, top=40):
    """cProfile of one whole build of n bodies (scene, validate, Simulation), written to ``path``."""
    gc.collect()
    prof = cProfile.Profile()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prof.enable()
        scene = make_scene(builder, n)
        scene.validate()
        sim = Simulation(scene, device, validate=False)
        wp.synchronize_device(device)
        prof.disable()
    del sim, scene
    text = io.StringIO()
    stats = pstats.Stats(prof, stream=text)
    text.write(f"cProfile of the build of {n} bodies ({builder}) on {device}\n\n== by cumulative time ==\n")
    stats.sort_stats("cumulative").print_stats(top)
    text.write("\n== by own time ==\n")
    stats.sort_stats("tottime").print_stats(top)
    with open(path, "w") as fh:
        fh.write(text.getvalue())
    log(f"wrote {path}")


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="1e4,1e5,1e6", help="comma-separated body counts (default 1e4,1e5,1e6)")
    ap.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    ap.add_argument("--builder", choices=BUILDERS, default="settle", help="how the pile is built (see above)")
    ap.add_argument("--repeats", type=int, default=1, help="builds per size; the table shows the fastest total")
    ap.add_argument("--profile", default=None, help="also cProfile one build of this many bodies")
    ap.add_argument("--out", default=None, help="JSON (default benchmarks/results/build_time/<builder>_<device>.json)")
    ap.add_argument("--steps", type=int, default=0, help="steps after each build (their time and device memory)")
    ap.add_argument(
        "--overlap-check",
        choices=("host", "device"),
        default="host",
        help="initial overlaps of body pairs: the scene's k-d tree check, or the test over the first broad phase's "
        "pairs on the device (polydem.overlap_check)",
    )
    ap.add_argument("--no-git", action="store_true", help="leave the git commit out of the record")
    args = ap.parse_args()

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    sizes = [int(float(s)) for s in args.sizes.split(",") if s.strip()]
    name = f"{args.builder}_{device.alias.replace(':', '')}.json"
    out = args.out or os.path.join(HERE, "results", "build_time", name)
    if args.no_git:
        meta = {
            "python": platform.python_version(),
            "machine": platform.platform(),
            "cpu_count": os.cpu_count(),
            "command": " ".join([os.path.basename(sys.executable), *sys.argv]),
            "device": device.name,
            "warp": wp.config.version,
            "numpy": np.__version__,
        }
    else:
        meta = run_meta(device)
    record = {"meta": meta, "builder": args.builder, "overlap_check": args.overlap_check, "results": []}

    timers = Timers()
    with patched(timers):
        t0 = time.perf_counter()
        build(args.builder, 1000, device, timers, overlap_check=args.overlap_check)
        record["compile_s"] = time.perf_counter() - t0
        log(f"compile (a first build of 1000 bodies, modules loaded or compiled): {record['compile_s']:.2f} s")
        for n in sizes:
            runs = []
            for _ in range(args.repeats):
                stages, scene, sim = build(
                    args.builder, n, device, timers, steps=args.steps, overlap_check=args.overlap_check
                )
                bodies = scene.num_bodies
                memory = timers.take_memory()
                del scene, sim
                gc.collect()
                runs.append(stages)
            best = min(runs, key=lambda s: s["total"])
            row = {
                "n": n,
                "bodies": bodies,
                "stages_s": best,
                "us_per_body": {k: 1e6 * v / bodies for k, v in best.items()},
            }
            if memory:
                # the pool at the end of each stage over the pool before the Simulation, in bytes per body; the
                # high-water mark is the process's (never reset), so it grows only where this build set a new one
                base = memory["start"]["current"]
                row["mempool"] = memory
                row["mempool_bytes_per_body"] = {
                    k: {"current": (m["current"] - base) / bodies, "high": (m["high"] - base) / bodies}
                    for k, m in memory.items()
                }
                log("  device memory (mempool over its use before the Simulation, B/body, current / high-water):")
                for k, m in row["mempool_bytes_per_body"].items():
                    log(f"    {k:<38} {m['current']:>9.1f} {m['high']:>9.1f}")
            # the process's peak resident host memory so far (Linux reports KiB): a 1e8 build must fit the host too
            row["host_peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
            log(f"  host peak resident memory so far: {row['host_peak_rss_bytes'] / 2**30:.1f} GiB")
            if args.repeats > 1:
                row["runs"] = runs
            record["results"].append(row)
            log(f"\n{n} cubes ({bodies} bodies), {args.builder}, {device}:")
            log(f"  {'stage':<40} {'s':>9} {'us/body':>9}")
            for k, v in best.items():
                log(f"  {k:<40} {v:>9.3f} {1e6 * v / bodies:>9.2f}")
            os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
            with open(out, "w") as fh:
                json.dump(record, fh, indent=1)
    if args.profile:
        profile_build(args.builder, int(float(args.profile)), device, os.path.splitext(out)[0] + ".profile.txt")
    log(f"wrote {out}")


if __name__ == "__main__":
    main()
