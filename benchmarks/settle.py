"""Settling benchmark: throughput of the whole simulation step for a pile of cubes in a container.

Scene (per N): cubes of 1 cm edge (density 2500 kg/m^3, hertz law, restitution 0.5, friction 0.5)
in columns of ``--layers`` cubes on a square grid, in an open box container sized for the count,
so every N has the same pile height, contacts per body and time step. Orientations are uniformly
random. The columns are ``sqrt(3) * edge * (1 + margin)`` apart and jittered sideways by less than
the margin, so bounding spheres of different columns never meet; within a column each cube sits
a small random gap (``--gap``, in edges) above the axis-aligned box of the one below, the lowest
one that gap above the floor. So nothing overlaps at the start, neighbours are already candidate
pairs, and the pile makes its contacts within the first few hundred steps as the gaps close and
the columns topple: a dense settling pile rather than a free fall. The stiffness k is chosen so
that a face contact carrying ``--load-factor`` times the weight of a whole column overlaps by
``--overlap`` (1%) of the cube volume; the time step is the simulator's "auto" one.

Walls: ``--walls box`` (default) uses ``Scene.add_box_container`` (fixed box bodies, so every cube
whose bounding sphere meets a wall's bounding sphere is a candidate pair with it: for a wide
container that is every cube with the floor and a good part of them with the side walls);
``--walls planes`` uses five infinite planes (handled per body in the gather kernel).

Per N: build (scene generation, Simulation: Model and first broad phase), warm-up (compile, CUDA
graph capture, and the first ``--warmup`` steps so that the pile is in contact), then ``--steps``
timed steps through ``Simulation.step`` (the production path: graph on CUDA, host loop on the
CPU). Reported: body-steps per second, time per step, candidate pairs and actual contacts (pairs
with overlap volume > 0), broad-phase rebuilds in the timed window, device bytes per body. Then a
separate *measuring pass* runs ``--stage-steps`` steps stage by stage, synchronising the device
around each stage (so a stage's time includes its launch overhead; on CUDA the GPU time of its
kernels, from Warp's activity timing, is reported too): broad-phase check (the Verlet test),
broad-phase rebuild (device refit+query+sort on CUDA, host build on the CPU; also timed on its
own), pair contacts (narrow phase + wrench per candidate), gather (per body sum plus walls),
integrate, and the rest (step counter, finiteness check). The stage times are not the timed
steps' breakdown (those are one graph launch): their sum against the step time shows the launch
and host overhead that the graph removes. On CUDA the same N is then run again with
``use_graph=False`` over the same warm-up and timed steps.

    python benchmarks/settle.py --device cuda:0                          # 1e3 .. 1e6
    python benchmarks/settle.py --device cpu --sizes 1000,10000 --steps 64

Results: a table on stdout and JSON (``--out``, default ``benchmarks/results/settle_<device>.json``),
rewritten after every phase of every size, so a run cut short keeps what it measured.
"""

import argparse
import datetime
import gc
import json
import math
import os
import platform
import subprocess
import sys
import time

import numpy as np
import warp as wp

from polydem import ConvexShape, Scene, Simulation

HERE = os.path.dirname(os.path.abspath(__file__))
SQRT3 = math.sqrt(3.0)
# Persistent device bytes per node of a Warp BVH (two packed 16-byte node halves, parent and
# count ints; leaf size 1 gives 2n - 1 nodes) and per item (primitive index).
BVH_NODE_BYTES = 40
BVH_ITEM_BYTES = 4
# Buffers that only the diagnostics (contacts(), energy()) allocate: not part of stepping.
SKIP_ATTRIBUTES = ("_diag",)


def log(*args):
    print(*args, flush=True)


# ---------------------------------------------------------------------------------------------
# Scene


def random_quaternions(rng, n):
    """Uniformly random unit quaternions (n, 4), xyzw."""
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def abs_rotation_rowsums(q):
    """For unit quaternions q (n, 4) xyzw, sum_k |R_jk| per world axis j: (n, 3).

    A cube of edge a rotated by R has the axis-aligned half extent (a / 2) * sum_k |R_jk|.
    """
    x, y, z, w = q.T
    r = np.empty((len(q), 3, 3))
    r[:, 0, 0] = 1 - 2 * (y * y + z * z)
    r[:, 0, 1] = 2 * (x * y - z * w)
    r[:, 0, 2] = 2 * (x * z + y * w)
    r[:, 1, 0] = 2 * (x * y + z * w)
    r[:, 1, 1] = 1 - 2 * (x * x + z * z)
    r[:, 1, 2] = 2 * (y * z - x * w)
    r[:, 2, 0] = 2 * (x * z - y * w)
    r[:, 2, 1] = 2 * (y * z + x * w)
    r[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return np.abs(r).sum(axis=2)


def hertz_k(edge, density, layers, overlap, load_factor, g=9.81):
    """Hertz k [J/m^4.5] such that a face contact (area edge^2) carrying load_factor times the
    weight of a column of ``layers`` cubes overlaps by ``overlap`` of the cube volume.

    W = 2/3 k V^1.5, so the force of a face contact of overlap volume V is k sqrt(V) edge^2.
    """
    force = load_factor * layers * density * edge**3 * g
    volume = overlap * edge**3
    return force / (math.sqrt(volume) * edge**2)


def make_scene(n, args, seed=0):
    """The pile of ``n`` cubes and its container; returns (scene, info dict)."""
    a = args.edge
    layers = args.layers
    rng = np.random.default_rng(seed)
    k = hertz_k(a, args.density, layers, args.overlap, args.load_factor)
    scene = Scene(gravity=(0.0, 0.0, -9.81), dt="auto", name=f"settle_{n}")
    scene.add_material(
        "grain", density=args.density, law="hertz", k=k, restitution=args.restitution, friction=args.friction
    )
    scene.add_shape("cube", ConvexShape.box(a, name="cube"))

    # Columns on a square-ish grid; body i is in layer i // columns, column i % columns.
    columns = max(1, math.ceil(n / layers))
    nx = max(1, math.ceil(math.sqrt(columns)))
    ny = max(1, math.ceil(columns / nx))
    nz = math.ceil(n / columns)
    spacing = SQRT3 * a * (1.0 + args.margin)
    jitter = 0.45 * (spacing - SQRT3 * a)  # |dx|, |dy| < jitter: columns' spheres stay apart

    q = random_quaternions(rng, n)
    half = 0.5 * a * abs_rotation_rowsums(q)  # (n, 3) axis-aligned half extents
    col = np.arange(n) % columns
    lay = np.arange(n) // columns
    cx = (col % nx - 0.5 * (nx - 1)) * spacing
    cy = (col // nx - 0.5 * (ny - 1)) * spacing
    x = cx + rng.uniform(-jitter, jitter, n)
    y = cy + rng.uniform(-jitter, jitter, n)
    # Stack each column: bottom of cube k = top of cube k-1 + gap (the floor is z = 0).
    hz = np.zeros((nz, columns))
    hz.reshape(-1)[:n] = half[:, 2]
    gaps = rng.uniform(args.gap[0], args.gap[1], (nz, columns)) * a
    heights = 2.0 * hz + gaps
    bottom = np.cumsum(heights, axis=0) - heights + gaps
    z = (bottom + hz).reshape(-1)[:n]
    top = float(np.max((bottom + 2.0 * hz).reshape(-1)[:n]))
    del hz, gaps, heights, bottom
    positions = np.column_stack([x, y, z])
    scene.add_bodies("cube", "grain", positions, orientations=q)
    del q, half, col, lay, cx, cy, x, y, z, positions

    lx = nx * spacing + 0.1 * a
    ly = ny * spacing + 0.1 * a
    lz = top + 2.0 * a
    if args.walls == "box":
        scene.add_box_container((0.0, 0.0, 0.5 * lz), (lx, ly, lz), "grain", open_top=True)
    else:
        scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "grain")
        scene.add_plane((-0.5 * lx, 0.0, 0.0), (1.0, 0.0, 0.0), "grain")
        scene.add_plane((0.5 * lx, 0.0, 0.0), (-1.0, 0.0, 0.0), "grain")
        scene.add_plane((0.0, -0.5 * ly, 0.0), (0.0, 1.0, 0.0), "grain")
        scene.add_plane((0.0, 0.5 * ly, 0.0), (0.0, -1.0, 0.0), "grain")
    info = {
        "grains": n,
        "bodies": scene.num_bodies,
        "grid": [nx, ny, nz],
        "container_inner_m": [lx, ly, lz],
        "walls": args.walls,
        "k_hertz": k,
    }
    return scene, info


# ---------------------------------------------------------------------------------------------
# Memory


def _arrays_of(obj):
    out = []

    def visit(v, depth=0):
        if isinstance(v, wp.array):
            out.append(v)
        elif depth < 2 and isinstance(v, dict):
            for x in v.values():
                visit(x, depth + 1)
        elif depth < 2 and isinstance(v, list | tuple):
            for x in v:
                visit(x, depth + 1)

    for name, v in vars(obj).items():
        if name not in SKIP_ATTRIBUTES:
            visit(v)
    return out


def device_bytes(sim):
    """Bytes of the Warp arrays owned by the Simulation, its Model, ShapeSet and BroadPhase.

    Views (e.g. ``pair_key`` into the sort buffer) are counted once: the address ranges are merged.
    The BVH's own buffers are estimated from its node count. Returns a dict.
    """
    owners = {
        "simulation": sim,
        "model": sim.model,
        "shapes": sim.model.shapes,
        "broadphase": sim.broadphase,
    }
    ranges = []
    per_owner = {}
    for name, obj in owners.items():
        rs = []
        for arr in _arrays_of(obj):
            if arr.ptr is None or not arr.capacity:
                continue
            rs.append((int(arr.ptr), int(arr.ptr) + int(arr.capacity)))
        per_owner[name] = _merged_size(rs)
        ranges += rs
    total = _merged_size(ranges)
    bvh = 0
    bp = sim.broadphase
    if getattr(bp, "bvh", None) is not None:
        items = len(bp.box_lower)
        bvh = (2 * items - 1) * BVH_NODE_BYTES + items * BVH_ITEM_BYTES
    return {"arrays": total, "by_owner": per_owner, "bvh_estimate": bvh, "total": total + bvh}


def _merged_size(ranges):
    size = 0
    end = -1
    for lo, hi in sorted(ranges):
        if lo >= end:
            size += hi - lo
            end = hi
        elif hi > end:
            size += hi - end
            end = hi
    return size


def mempool_used(device):
    if not device.is_cuda:
        return None
    try:
        return int(wp.get_mempool_used_mem_current(device))
    except Exception:
        return None


# ---------------------------------------------------------------------------------------------
# Timing


class StageClock:
    """Times callables with device synchronisation; on CUDA also sums Warp's GPU activity timing."""

    def __init__(self, device):
        self.device = device
        self.wall = {}
        self.gpu = {}
        self.calls = {}
        self.gpu_ok = device.is_cuda

    def run(self, stage, fn):
        dev = self.device
        wp.synchronize_device(dev)
        timing = False
        if self.gpu_ok:
            try:
                wp.timing_begin(cuda_filter=wp.TIMING_ALL, synchronize=False)
                timing = True
            except Exception:
                self.gpu_ok = False
        t0 = time.perf_counter()
        try:
            result = fn()
        finally:
            wp.synchronize_device(dev)
            t1 = time.perf_counter()
            if timing:
                try:
                    ms = sum(r.elapsed for r in wp.timing_end(synchronize=False))
                    self.gpu[stage] = self.gpu.get(stage, 0.0) + 1e-3 * ms
                except Exception:
                    self.gpu_ok = False
        self.wall[stage] = self.wall.get(stage, 0.0) + (t1 - t0)
        self.calls[stage] = self.calls.get(stage, 0) + 1
        return result


def _launch_stage(kernel):
    key = getattr(kernel, "key", str(kernel))
    if "pair_contact" in key:
        return "pair_contacts"
    if "gather" in key:
        return "gather"
    if "integrate" in key:
        return "integrate"
    return "other"


def measure_stages(sim, steps, rebuild_reps):
    """Run ``steps`` steps stage by stage (see the module docstring); seconds per call of each stage.

    ``wp.launch`` is wrapped for the duration, so that the launches of ``_contacts_and_integrate``
    are timed one by one and sorted into stages by kernel name. Returns a dict.
    """
    clock = StageClock(sim.device)
    bp = sim.broadphase
    m = sim.model
    device_rebuild = sim.use_graph
    original = wp.launch

    def timed_launch(kernel, *args, **kwargs):
        return clock.run(_launch_stage(kernel), lambda: original(kernel, *args, **kwargs))

    rebuilds = 0
    for _ in range(steps):
        clock.run("broadphase_check", lambda: bp.needs_rebuild(sim.body_q, m.body_radius, m.body_flags))
        if int(bp.rebuild_flag.numpy()[0]):
            rebuilds += 1
            clock.run("broadphase_rebuild", sim._device_rebuild if device_rebuild else sim._host_build)
            if device_rebuild and bp.check_host_build_needed():
                sim._host_build()
        wp.launch = timed_launch
        try:
            sim._contacts_and_integrate()
        finally:
            wp.launch = original
    # Rebuild costs on their own (the window above may hold none): a host build always; on CUDA
    # also the device rebuild that the graph runs (refit, query, sort of the whole capacity).
    for _ in range(rebuild_reps):
        clock.run("host_build", sim._host_build)
        if device_rebuild:
            clock.run("device_rebuild", sim._device_rebuild)
    out = {"steps": steps, "rebuilds_in_pass": rebuilds, "wall_s": {}, "gpu_s": {}}
    for stage, total in clock.wall.items():
        per = steps if stage in ("broadphase_check", "pair_contacts", "gather", "integrate", "other") else None
        calls = clock.calls[stage]
        out["wall_s"][stage] = total / (per or calls)
        if stage in clock.gpu:
            out["gpu_s"][stage] = clock.gpu[stage] / (per or calls)
    if not clock.gpu_ok:
        out["gpu_s"] = None
    return out


def timed_steps(sim, steps):
    """Seconds for ``sim.step(steps)`` and what the broad phase did meanwhile."""
    bp = sim.broadphase
    builds0 = bp.num_builds
    dev0 = int(bp.device_rebuilds.numpy()[0])
    wp.synchronize_device(sim.device)
    t0 = time.perf_counter()
    sim.step(steps)
    wp.synchronize_device(sim.device)
    seconds = time.perf_counter() - t0
    host_builds = bp.num_builds - builds0
    dev1 = int(bp.device_rebuilds.numpy()[0])
    # build() resets the device counter: after a host build only the later device rebuilds are known.
    device_rebuilds = dev1 - dev0 if host_builds == 0 else dev1
    return seconds, host_builds, device_rebuilds if sim.use_graph else 0


def contact_stats(sim, grains):
    """Candidate pairs (broad phase) and contacts (overlap volume > 0, from ``Simulation.contacts``)."""
    bp = sim.broadphase
    count = int(bp.pair_count.numpy()[0])
    b = bp.pair_b.numpy()[:count]
    c = sim.contacts()
    cb = c["body_b"]
    plane = cb < 0
    wall = cb >= grains
    vmax = float(c["volume"].max()) if len(c["volume"]) else 0.0
    return {
        "candidate_pairs": count,
        "candidate_pairs_grain_grain": int(np.count_nonzero(b < grains)),
        "pair_capacity": int(bp.capacity),
        "contacts": int(np.count_nonzero(~plane)),
        "contacts_grain_grain": int(np.count_nonzero(~plane & ~wall)),
        "contacts_grain_wall": int(np.count_nonzero(wall)),
        "plane_contacts": int(np.count_nonzero(plane)),
        "max_overlap_volume_fraction": vmax / sim.model.shapes.shapes[0].volume,
    }


# ---------------------------------------------------------------------------------------------
# Driver


def run_size(n, args, device, record, save):
    """Benchmark one size; fills ``record`` (a dict) and calls ``save()`` after every phase."""
    gc.collect()
    pool0 = mempool_used(device)
    t0 = time.perf_counter()
    scene, info = make_scene(n, args, seed=args.seed)
    t1 = time.perf_counter()
    sim = Simulation(scene, device=device)
    wp.synchronize_device(device)
    t2 = time.perf_counter()
    record.update(info)
    record.update(
        {
            "status": "built",
            "dt": sim.dt,
            "skin": sim.skin,
            "use_graph": sim.use_graph,
            "scene_s": t1 - t0,
            "simulation_init_s": t2 - t1,
            "first_pairs": int(sim.broadphase.num_pairs),
        }
    )
    log(
        f"  N={n}: scene {t1 - t0:.2f} s, Simulation() {t2 - t1:.2f} s, dt {sim.dt:.3g} s, grid {info['grid']}, "
        f"{sim.broadphase.num_pairs} candidate pairs"
    )
    save()

    # Warm-up: compile and capture in the first step, then settle into contact.
    t0 = time.perf_counter()
    sim.step(1)
    wp.synchronize_device(device)
    t1 = time.perf_counter()
    if args.warmup > 1:
        sim.step(args.warmup - 1)
    wp.synchronize_device(device)
    t2 = time.perf_counter()
    record.update({"first_step_s": t1 - t0, "warmup_steps": args.warmup, "warmup_s": t2 - t1})
    log(f"  warm-up: first step (compile, capture) {t1 - t0:.2f} s, {args.warmup - 1} more {t2 - t1:.2f} s")

    seconds, host_builds, dev_rebuilds = timed_steps(sim, args.steps)
    record.update(
        {
            "status": "timed",
            "steps": args.steps,
            "seconds": seconds,
            "step_s": seconds / args.steps,
            "body_steps_per_s": n * args.steps / seconds,
            "host_builds": host_builds,
            "device_rebuilds": dev_rebuilds,
            "simulated_time_s": sim.time,
        }
    )
    mem = device_bytes(sim)
    pool1 = mempool_used(device)
    record.update(contact_stats(sim, n))
    record["memory"] = {
        "bytes": mem["total"],
        "bytes_per_body": mem["total"] / n,
        "arrays_bytes": mem["arrays"],
        "bvh_estimate_bytes": mem["bvh_estimate"],
        "by_owner": mem["by_owner"],
        "mempool_used_delta_bytes": None if pool0 is None or pool1 is None else pool1 - pool0,
    }
    if record["memory"]["mempool_used_delta_bytes"] is not None:
        record["memory"]["mempool_bytes_per_body"] = record["memory"]["mempool_used_delta_bytes"] / n
    log(
        f"  timed: {args.steps} steps {seconds:.3f} s = {1e3 * seconds / args.steps:.3f} ms/step, "
        f"{n * args.steps / seconds / 1e6:.3f} M body-steps/s; {record['candidate_pairs']} candidates, "
        f"{record['contacts']} contacts (+{record['plane_contacts']} plane), rebuilds host {host_builds} "
        f"device {dev_rebuilds}, {mem['total'] / n:.0f} B/body"
    )
    save()

    if args.stage_steps > 0:
        stages = measure_stages(sim, args.stage_steps, args.rebuild_reps)
        rebuilds = host_builds + dev_rebuilds
        rebuild_cost = stages["wall_s"].get("device_rebuild" if sim.use_graph else "host_build", 0.0)
        stages["broadphase_per_step_s"] = stages["wall_s"]["broadphase_check"] + rebuild_cost * rebuilds / args.steps
        stages["note"] = (
            "measuring pass, separate from the timed steps: each stage run alone with device "
            "synchronisation around it (wall_s includes launch overhead; gpu_s: Warp CUDA activity timing); "
            "broadphase_per_step_s = check + rebuild cost x rebuilds per timed step"
        )
        record["stages"] = stages
        w = stages["wall_s"]
        log(
            "  stages (measuring pass, each synchronised) ms: "
            + ", ".join(f"{k} {1e3 * v:.3f}" for k, v in w.items())
            + (
                "; GPU ms: " + ", ".join(f"{k} {1e3 * v:.3f}" for k, v in stages["gpu_s"].items())
                if stages["gpu_s"]
                else ""
            )
        )
        save()

    del sim
    gc.collect()

    if device.is_cuda and not args.no_graph_compare:
        sim = Simulation(scene, device=device, use_graph=False)
        sim.step(args.warmup)
        seconds_ng, host_builds_ng, _ = timed_steps(sim, args.steps)
        record["no_graph"] = {
            "seconds": seconds_ng,
            "step_s": seconds_ng / args.steps,
            "body_steps_per_s": n * args.steps / seconds_ng,
            "host_builds": host_builds_ng,
            "graph_speedup": seconds_ng / record["seconds"],
        }
        log(
            f"  use_graph=False: {1e3 * seconds_ng / args.steps:.3f} ms/step, host builds {host_builds_ng}; "
            f"graph speed-up x{seconds_ng / record['seconds']:.2f}"
        )
        del sim
        gc.collect()
    record["status"] = "complete"
    save()


def print_table(records):
    cols = [
        ("N", 8, lambda r: f"{r['grains']}"),
        ("ms/step", 9, lambda r: f"{1e3 * r['step_s']:.3f}"),
        ("Mbody-st/s", 10, lambda r: f"{r['body_steps_per_s'] / 1e6:.3f}"),
        ("bp", 7, lambda r: _stage(r, "broadphase_per_step_s")),
        ("pairs", 7, lambda r: _stage(r, "pair_contacts")),
        ("gather", 7, lambda r: _stage(r, "gather")),
        ("integ", 7, lambda r: _stage(r, "integrate")),
        ("other", 7, lambda r: _stage(r, "other")),
        ("cand", 9, lambda r: f"{r['candidate_pairs']}"),
        ("contacts", 9, lambda r: f"{r['contacts'] + r['plane_contacts']}"),
        ("rebuilds", 8, lambda r: f"{r['host_builds'] + r['device_rebuilds']}"),
        ("B/body", 7, lambda r: f"{r['memory']['bytes_per_body']:.0f}"),
        ("nograph", 9, lambda r: f"{1e3 * r['no_graph']['step_s']:.3f}" if "no_graph" in r else "-"),
    ]
    log("")
    log("stage columns: ms per step from the separate synchronised measuring pass (bp = check + amortised rebuild)")
    log(" ".join(f"{name:>{w}}" for name, w, _ in cols))
    for r in records:
        if "step_s" not in r:
            continue
        log(" ".join(f"{fmt(r):>{w}}" for _, w, fmt in cols))


def _stage(r, key):
    st = r.get("stages")
    if not st:
        return "-"
    v = st.get(key) if key == "broadphase_per_step_s" else st["wall_s"].get(key)
    return "-" if v is None else f"{1e3 * v:.3f}"


def machine_meta(device):
    meta = {
        "device": device.name,
        "alias": device.alias,
        "is_cuda": device.is_cuda,
        "warp": wp.config.version,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "machine": platform.platform(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
        "command": " ".join([sys.executable, *sys.argv]),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    if device.is_cuda:
        meta["memory_bytes"] = getattr(device, "total_memory", None)
        meta["arch"] = getattr(device, "arch", None)
        meta["mempool_enabled"] = bool(wp.is_mempool_enabled(device))
        try:
            meta["cuda_driver"] = wp.context.runtime.driver_version
            meta["cuda_toolkit"] = wp.context.runtime.toolkit_version
        except Exception:
            pass
    try:
        meta["git_commit"] = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=HERE, capture_output=True, text=True, timeout=10
        ).stdout.strip()
        meta["git_dirty"] = bool(
            subprocess.run(
                ["git", "status", "--porcelain", "--", "src", "kernels"],
                cwd=HERE,
                capture_output=True,
                text=True,
                timeout=10,
            ).stdout.strip()
        )
    except Exception:
        pass
    return meta


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    ap.add_argument("--sizes", default=None, help="comma-separated cube counts (default 1e3..1e6 GPU, 1e3,1e4 CPU)")
    ap.add_argument("--steps", type=int, default=None, help="timed steps (default 200 GPU, 64 CPU)")
    ap.add_argument("--warmup", type=int, default=None, help="untimed steps first (default 256 GPU, 128 CPU)")
    ap.add_argument("--stage-steps", type=int, default=None, help="steps of the measuring pass (default 20 GPU, 8 CPU)")
    ap.add_argument("--rebuild-reps", type=int, default=2, help="lone broad-phase rebuilds timed in that pass")
    ap.add_argument("--out", default=None, help="JSON file (default benchmarks/results/settle_<device>.json)")
    ap.add_argument("--no-graph-compare", action="store_true", help="skip the use_graph=False run on CUDA")
    ap.add_argument("--walls", choices=("box", "planes"), default="box", help="container of fixed boxes or planes")
    ap.add_argument("--layers", type=int, default=10, help="cubes per column")
    ap.add_argument("--edge", type=float, default=0.01, help="cube edge [m]")
    ap.add_argument("--density", type=float, default=2500.0, help="[kg/m^3]")
    ap.add_argument("--restitution", type=float, default=0.5)
    ap.add_argument("--friction", type=float, default=0.5)
    ap.add_argument("--overlap", type=float, default=0.01, help="target overlap volume / cube volume")
    ap.add_argument("--load-factor", type=float, default=2.0, help="design load / weight of a full column")
    ap.add_argument("--margin", type=float, default=0.03, help="column spacing = sqrt(3) edge (1 + margin)")
    ap.add_argument("--gap", default="0.002,0.02", help="min,max gap between stacked cubes [edges]")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    args.gap = tuple(float(v) for v in args.gap.split(","))
    if len(args.gap) != 2 or not 0.0 <= args.gap[0] <= args.gap[1]:
        ap.error("--gap needs two numbers 0 <= min <= max")

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    cuda = device.is_cuda
    sizes = args.sizes or ("1000,10000,100000,1000000" if cuda else "1000,10000")
    sizes = [int(float(s)) for s in sizes.split(",") if s.strip()]
    if args.steps is None:
        args.steps = 200 if cuda else 64
    if args.warmup is None:
        args.warmup = 256 if cuda else 128
    if args.stage_steps is None:
        args.stage_steps = 20 if cuda else 8
    args.warmup = max(args.warmup, 1)
    out = args.out or os.path.join(HERE, "results", f"settle_{device.alias.replace(':', '')}.json")
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)

    meta = machine_meta(device)
    config = {k: v for k, v in vars(args).items() if k != "out"}
    config["sizes"] = sizes
    records = []

    def save():
        tmp = out + ".tmp"
        with open(tmp, "w") as f:
            json.dump({"meta": meta, "config": config, "results": records}, f, indent=1)
        os.replace(tmp, out)

    log(f"settle benchmark on {device.name} ({device.alias}), Warp {wp.config.version}; sizes {sizes}, ")
    log(f"  {args.steps} timed steps after {args.warmup} warm-up steps; walls {args.walls}; JSON -> {out}")
    for n in sizes:
        record = {"grains": n, "status": "started"}
        records.append(record)
        try:
            run_size(n, args, device, record, save)
        except Exception as err:  # keep what was measured, go on with the next size
            record["status"] = "error"
            record["error"] = f"{type(err).__name__}: {err}"
            log(f"  N={n}: {record['error']}")
            save()
            if isinstance(err, MemoryError):
                break
    print_table(records)
    save()


if __name__ == "__main__":
    main()
