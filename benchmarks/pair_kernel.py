"""Pair-kernel benchmark: pairs per second and error against the float64 reference.

For cube, tetrahedron, 20-vertex rock and 64-vertex hull pairs at overlap depths of 0.1%, 1% and
10% of the size, with half of the candidates not touching (separated along the line of centres
by up to 20% of the size, so that their bounding spheres still overlap as broad-phase candidates'
do), in float32 and float64; a depth ``flat`` gives flat contacts instead (every pair touching: a
face of one body 1e-7 to 1e-3 of the size deep in a face of the other). Prints a table and writes JSON, with a
SHA-256 of each case's outputs (two trees that agree there gave the same bits).

    python benchmarks/pair_kernel.py --device cuda:0            # GPU: 2^20 pairs per case
    python benchmarks/pair_kernel.py --device cpu --pairs 4096  # one CPU core

The other ways of holding the kernel's working set that BENCHMARKS.md section 7c compares live at
the git tag ``pair-variants-7c``, where this script takes ``--variants``; the clip layouts of issue 27
(BENCHMARKS.md section 14) at the tag ``clip-layouts-27``, where ``pair_layouts.py`` times them; the clipping
without a polygon buffer (``make_geometry(clip="edges")``, BENCHMARKS.md section 26) at the tag ``clip-edges-27``,
where ``--clips polygon,edges`` times both on the same pairs and prints each one's largest difference from the
first (over the size's power of each output). This tree has the polygon method only.
"""

import argparse
import hashlib
import json
import os
import sys
import time

import numpy as np
import warp as wp
from polydem.kernels.geometry import SHARED_POLY_BLOCK
from polydem.kernels.narrowphase import OVERLAP_OUTPUTS, make_narrowphase

from polydem import ConvexShape
from polydem.shapeset import ShapeSet

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "tests"))
sys.path.insert(0, HERE)
from _meta import run_meta  # noqa: E402


def shape_library():
    return {
        "cube": ConvexShape.box(1.0),
        "tetrahedron": ConvexShape.tetrahedron(1.0),
        "rock20": ConvexShape.rock(n_points=20, size=1.0, seed=1),
        "hull64": ConvexShape.rock(n_points=64, size=1.0, seed=2),
    }


def random_rotations(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def rotate(q, v):
    """Rotate vectors v (n,3) by quaternions q (n,4) xyzw."""
    u = q[:, :3]
    w = q[:, 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def support(shape, q, direction):
    """max over the shape's vertices of direction . (R v), per row."""
    local = rotate(q * np.array([-1, -1, -1, 1]), direction)  # direction in the body frame
    return (local @ np.asarray(shape.vertices).T).max(axis=1)


def make_pairs(shape, n, depth, rng, device):
    """Poses of n pairs of `shape` along random lines of centres: the first half pushed `depth` of
    the size past first touch, the second half separated along the line by 2-20% of the size.

    First touch is found by bisection on the float64 kernel (V > 0), as projections along the line
    overlapping does not mean the bodies do."""
    size = 2.0 * shape.radius
    qa = random_rotations(rng, n)
    qb = random_rotations(rng, n)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pa = np.hstack([np.zeros((n, 3)), qa])
    lo = np.zeros(n)
    hi = support(shape, qa, u) + support(shape, qb, -u)  # projections apart: surely not overlapping
    shapes64 = ShapeSet([shape], device=device, precision="float64")
    for _ in range(32):
        mid = 0.5 * (lo + hi)
        _, outs = time_kernel(shapes64, pa, np.hstack([u * mid[:, None], qb]), 0)
        touching = outs[0] > 0.0
        lo = np.where(touching, mid, lo)
        hi = np.where(touching, hi, mid)
    gap = np.where(np.arange(n) < n // 2, -depth * size, rng.uniform(0.02, 0.2, n) * size)
    return pa, np.hstack([u * (hi + gap)[:, None], qb])


def flat_pairs(shape, n, rng):
    """Poses of n pairs of `shape` with a face of B lying in a face of A, 1e-7 to 1e-3 of the size deep
    (log-uniform), turned about the normal and shifted along the face by up to a tenth of the size."""
    verts = np.asarray(shape.vertices, dtype=np.float64)
    normals = np.asarray(shape.face_normals, dtype=np.float64)
    offsets = np.array([normals[f] @ verts[loop[0]] for f, loop in enumerate(shape.faces)])
    centroids = np.array([verts[loop].mean(axis=0) for loop in shape.faces])
    size = 2.0 * shape.radius
    qa = random_rotations(rng, n)
    fa = rng.integers(0, len(shape.faces), n)
    gb = rng.integers(0, len(shape.faces), n)
    n_world = rotate(qa, normals[fa])
    qb = np.empty((n, 4))
    for i in range(n):
        # B's face normal m onto -n, then a turn about n
        m, t = normals[gb[i]], -n_world[i]
        axis = np.cross(m, t)
        s, c = np.linalg.norm(axis), float(m @ t)
        if s < 1e-12:
            axis, s = (np.array([1.0, 0.0, 0.0]) if abs(m[0]) < 0.9 else np.array([0.0, 1.0, 0.0])), 0.0
            axis = np.cross(m, axis)
            axis /= np.linalg.norm(axis)
            q1 = np.array([*axis, 0.0]) if c < 0 else np.array([0.0, 0.0, 0.0, 1.0])
        else:
            half = 0.5 * np.arctan2(s, c)
            q1 = np.array([*(axis / s * np.sin(half)), np.cos(half)])
        spin = rng.uniform(0, 2 * np.pi)
        q2 = np.array([*(t * np.sin(spin / 2)), np.cos(spin / 2)])
        # q2 * q1 (xyzw)
        v1, w1, v2, w2 = q1[:3], q1[3], q2[:3], q2[3]
        qb[i] = [*(w2 * v1 + w1 * v2 + np.cross(v2, v1)), w2 * w1 - v2 @ v1]
    depth = size * 10.0 ** rng.uniform(-7, -3, n)
    shift = rng.normal(size=(n, 3)) * 0.1 * size
    shift -= (shift * n_world).sum(axis=1, keepdims=True) * n_world
    p = rotate(qa, centroids[fa]) - rotate(qb, centroids[gb]) + shift
    # n . p = d_f - depth + e_g: B's face plane `depth` inside A's
    along = offsets[fa] - depth + offsets[gb]
    p += (along - (p * n_world).sum(axis=1))[:, None] * n_world
    return np.hstack([np.zeros((n, 3)), qa]), np.hstack([p, qb])


def pair_inputs(kernel, arrays):
    """The pairs' arguments of an overlap kernel: one ``pairs`` struct (since issue 25) or, in older trees, the
    four arrays shape_a, shape_b, pose_a, pose_b themselves."""
    if "pairs" not in [arg.label for arg in kernel.adj.args]:
        return arrays
    from polydem.kernels.narrowphase import BatchPairs

    return [BatchPairs(*arrays).struct()]


def time_kernel(
    shapes, poses_a, poses_b, repeats, max_registers=128, block_dim=64, pose_scalar=None, clip="polygon",
    events=False, count_work=False, setup_only=False, shared_poly=False,
):  # fmt: skip
    """Median seconds of a launch of the engine's overlap kernel over the pairs, and the outputs.
    ``pose_scalar``: the poses' precision (default the shapes'; float64 with float32 shapes is the mixed mode).
    ``clip``: make_geometry's clipping method (only "polygon" exists in trees before it). ``events``: on a GPU,
    time each launch alone with CUDA events (not the host's clock around a launch and synchronisation).
    ``count_work``: the measuring variant (make_geometry's ``count_work``); the outputs then end with each pair's
    path word. ``setup_only``: the measuring variant of the pairs' set-up alone (make_geometry's). ``shared_poly``: the
    polygon buffer in the block's shared memory (make_geometry's; blocks of NARROWPHASE_BLOCK_DIM threads)."""
    dev = shapes.device
    n = len(poses_a)
    scalar = shapes.scalar
    pose_scalar = pose_scalar or scalar
    np_pose = np.float32 if pose_scalar == wp.float32 else np.float64
    vec3 = wp.types.vector(3, scalar)
    tf = wp.types.transformation(pose_scalar)
    cap, faces = shapes.default_poly_capacity, shapes.max_faces
    extra = {} if clip == "polygon" else {"clip": clip}
    if count_work:
        extra["count_work"] = True
    if setup_only:
        extra["setup_only"] = True
    if shared_poly:
        extra["shared_poly"] = True
        if block_dim != SHARED_POLY_BLOCK:
            raise ValueError(f"the shared polygon buffer needs blocks of {SHARED_POLY_BLOCK} threads, not {block_dim}")
    kernel = make_narrowphase(
        scalar, cap, faces, max_registers=max_registers, pose_scalar=pose_scalar, **extra
    ).overlap_kernel
    pair_arrays = [
        wp.zeros(n, dtype=int, device=dev),
        wp.zeros(n, dtype=int, device=dev),
        wp.array(poses_a.astype(np_pose), dtype=tf, device=dev),
        wp.array(poses_b.astype(np_pose), dtype=tf, device=dev),
    ]
    args = [*shapes.kernel_args(), *pair_inputs(kernel, pair_arrays)]
    outs = [wp.zeros(n, dtype=scalar, device=dev)]
    outs += [wp.zeros(n, dtype=vec3, device=dev) for _ in OVERLAP_OUTPUTS[1:]]
    overflow = wp.zeros(1 + n if count_work else 1, dtype=int, device=dev)
    launch = {"dim": n, "inputs": args, "outputs": [*outs, overflow], "device": dev, "block_dim": block_dim}
    wp.launch(kernel, **launch)  # compile, warm
    wp.synchronize_device(dev)
    times = []
    if events and dev.is_cuda:
        start, end = wp.Event(dev, enable_timing=True), wp.Event(dev, enable_timing=True)
        for _ in range(repeats):
            wp.record_event(start)
            wp.launch(kernel, **launch)
            wp.record_event(end)
            times.append(1e-3 * wp.get_event_elapsed_time(start, end))
    else:
        for _ in range(repeats):
            t0 = time.perf_counter()
            wp.launch(kernel, **launch)
            wp.synchronize_device(dev)
            times.append(time.perf_counter() - t0)
    if int(overflow.numpy()[0]):
        raise RuntimeError("polygon buffer overflow in the benchmark; raise the capacity")
    work = [overflow.numpy()[1:]] if count_work else []
    return (float(np.median(times)) if times else 0.0), [o.numpy() for o in outs] + work


def reference_errors(shape, poses_a, poses_b, outs, sample):
    """Largest errors of V [size^3] and S_A [size^2] against the float64 reference on a sample."""
    from reference_geometry import reference_overlap

    def world(p):
        return rotate(np.repeat(p[None, 3:], len(shape.vertices), axis=0), np.asarray(shape.vertices)) + p[:3]

    size = 2.0 * shape.radius
    err_v = err_s = 0.0
    n = len(poses_a)
    rows = np.unique(
        np.concatenate([np.arange(min(sample // 2, n // 2)), n // 2 + np.arange(min(sample // 2, n // 2))])
    )
    for i in rows:
        ref = reference_overlap(world(poses_a[i]), world(poses_b[i]))
        err_v = max(err_v, abs(float(outs[0][i]) - ref["volume"]) / size**3)
        err_s = max(err_s, float(np.abs(outs[2][i] - ref["area_vector"]).max()) / size**2)
    return err_v, err_s


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    ap.add_argument("--pairs", type=int, default=None, help="pairs per case (default 2^21 GPU, 4096 CPU)")
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--sample", type=int, default=64, help="pairs per case checked against the reference")
    ap.add_argument("--precisions", default="float32,float64")
    ap.add_argument("--shapes", default="cube,tetrahedron,rock20,hull64")
    ap.add_argument("--depths", default="0.001,0.01,0.1", help="depths of the touching half; 'flat': flat contacts")
    ap.add_argument(
        "--clips", default="polygon",
        help="comma-separated clipping methods: polygon, shared (its buffer in the block's shared memory, float32 "
        "clipping only), or an older tree's make_geometry clip (edges)",
    )  # fmt: skip
    ap.add_argument("--out", default=os.path.join(HERE, "results", "pair_kernel.json"))
    args = ap.parse_args()

    wp.config.quiet = True
    wp.init()
    dev = wp.get_device(args.device)
    n = args.pairs or (1 << 20 if dev.is_cuda else 4096)
    repeats = args.repeats or (20 if dev.is_cuda else 5)
    lib = shape_library()
    rows = []
    cases = {}  # poses per (shape, depth), shared by both precisions
    print(f"device {dev.name} ({dev.alias}), {n} pairs per case, half touching, median of {repeats}")
    print(
        f"{'shape':<12}{'faces':>6}{'depth':>8}{'prec':>9}{'clip':>9}{'touch':>7}{'Mpairs/s':>11}{'ns/pair':>10}"
        f"{'err V':>10}{'err S':>10}{'vs first':>10}"
    )
    for prec in args.precisions.split(","):
        for name in args.shapes.split(","):
            shape = lib[name]
            shapes = ShapeSet([shape], device=dev, precision=prec)
            for depth in (d if d == "flat" else float(d) for d in args.depths.split(",")):
                if (name, depth) not in cases and depth == "flat":
                    cases[name, depth] = flat_pairs(shape, n, np.random.default_rng(6789))
                elif (name, depth) not in cases:
                    cases[name, depth] = make_pairs(shape, n, depth, np.random.default_rng(12345), dev)
                pa, pb = cases[name, depth]
                first = None
                for clip in args.clips.split(","):
                    if clip == "shared" and prec == "float64":
                        continue  # float32 clipping only
                    shared = clip == "shared"
                    method = "polygon" if shared else clip
                    t, outs = time_kernel(shapes, pa, pb, repeats, clip=method, shared_poly=shared)
                    # The largest difference from the first method's outputs, over the size's power of each.
                    size = 2.0 * shape.radius
                    diff = 0.0
                    if first is None:
                        first = outs
                    else:
                        for o, f0, power in zip(outs, first, (3, 4, 2, 3, 2, 3, 2), strict=True):
                            d = np.abs(o.astype(np.float64) - f0.astype(np.float64)).max() if len(o) else 0.0
                            diff = max(diff, float(d) / size**power)
                    rows.append(case_row(args, shape, name, depth, prec, clip, n, t, outs, pa, pb, diff))
                    write(args.out, dev, rows)
    print(f"wrote {args.out}")


def case_row(args, shape, name, depth, prec, clip, n, t, outs, pa, pb, diff):
    """One case's row (printed as a table line)."""
    ev, es = reference_errors(shape, pa, pb, outs, args.sample)
    touching = int((outs[0][: n // 2] > 0).sum())
    row = {
        "shape": name,
        "faces": shape.num_faces,
        "vertices": shape.num_vertices,
        "depth": depth,
        "precision": prec,
        "clip": clip,
        "pairs": n,
        "touching": touching,
        "seconds": t,
        "pairs_per_second": n / t,
        "error_volume": ev,
        "error_area_vector": es,
        "difference_from_first_clip": diff,
        # SHA-256 of all outputs: two trees that agree here gave the same bits.
        "outputs_sha256": hashlib.sha256(b"".join(o.tobytes() for o in outs)).hexdigest(),
    }
    label = depth if depth == "flat" else f"{depth:.3g}"
    print(
        f"{name:<12}{shape.num_faces:>6}{label:>8}{prec:>9}{clip:>9}{touching / (n // 2):>7.0%}"
        f"{n / t / 1e6:>11.1f}{t / n * 1e9:>10.1f}{ev:>10.1e}{es:>10.1e}{diff:>10.1e}",
        flush=True,
    )
    return row


def write(path, dev, rows):
    os.makedirs(os.path.dirname(path), exist_ok=True)
    meta = run_meta(dev)
    with open(path, "w") as f:
        json.dump({"meta": meta, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
