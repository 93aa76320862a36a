"""Settling benchmark: throughput of the whole simulation step for a pile of cubes settling in a box.

Scene, the same for every N but for its footprint: cubes of 1 cm edge (density 2500 kg/m^3, hertz
law, restitution 0.5, friction 0.5, uniformly random orientations) stacked in columns of
``--layers`` (10) cubes on a square grid, in an open box container sized for the count. So the
pile height, the load per contact, the time step and the contacts per cube do not depend on N.
The columns are ``sqrt(3) edge (1 + margin)`` apart and jittered sideways by less than the margin
(bounding spheres of different columns never meet); in a column each cube sits a random gap
(``--gap``, in edges) above the axis-aligned box of the one below, the lowest one that gap above
the floor. Nothing overlaps at the start (checked: ``initial_contacts``) and grid neighbours are
candidate pairs from the first step. The pile then settles: it compacts from a packing fraction of
about 0.2 and the columns topple; 1000 cubes come to rest after about 0.2 s simulated.
``--shapes mixed`` pours equal numbers of cubes, regular tetrahedra, 20-vertex rocks and 2:1:1
boxes, each of the cube's volume, in random order, the columns spaced for the largest bounding
sphere and each body stacked by its own vertical extent (``--shapes cube``, the default, draws the
same numbers as before the option existed).

Stiffness (``--k-rule``): ``corner`` (the default) takes the hertz k that keeps every corner of the pile's
shapes at most ``--corner-depth`` (5%) of the edge deep under the weight of a full column of ``--layers``
cubes (``polydem.scene.depth.stiffness_for_depth``, the law alone: for the cube
``k = F / (3 (sqrt(3)/2)^1.5 d^3.5)``, 3.6e10 J/m^4.5). Corners are the soft contacts of the volume model
(their force grows as depth^3.5), so the corner depth, not the volume overlap, says how far the pile is from
the rigid limit: 8000 cubes (H100) packed to 0.650, 0.586 and 0.570 at 1, 16 and 64 times the former rule's
k, whose corners sink 17% of the edge under a column. ``volume``, the former rule, takes the k for which a
face contact carrying ``--load-factor`` (20) times the weight of a whole column overlaps by ``--overlap``
(1%) of the cube volume (4.9e8 J/m^4.5; the largest overlap in a pile of 1000 cubes at rest was 1.1% of a
cube's volume at a corner 23% of the edge deep). ``--k-factor`` multiplies either (a convergence study:
benchmarks/k_convergence.py). The time step is the simulator's "auto" one, which shrinks as k grows (as
1/sqrt(k) from the reference contact, as 1/k where the resting rule of ``Scene.time_step`` sets it: 1.6e-5 s
at the volume rule's k, 3.1e-7 s at the corner rule's). ``--shapes mixed`` takes the k of its sharpest
corners, the tetrahedra's (2.9e11 J/m^4.5 at 5%).

Walls: ``--walls box`` (default) uses ``Scene.add_box_container``: five fixed box bodies. They go
through the broad phase like any body, so every cube whose bounding sphere meets a wall's bounding
sphere is a candidate pair with it: in a wide container every cube with the floor and many with
the side walls (about 2.6 wall pairs per cube, most of them far from touching).
``--walls planes`` uses five infinite planes instead (tested per body in the gather kernel).

Per N: build (scene generation; ``Simulation()``: Model and first broad phase), warm-up (first
step: kernel compile and CUDA graph capture; then ``--warmup-time``, 0.1 s simulated (6300 steps at
the volume rule's k, 330 000 at the corner rule's: see Stiffness), of settling so that the timed window
sees a pile in contact: about 1.2 grain-grain contacts per cube (at the volume rule's k), against 2.7 at
rest and almost none in the first steps, which cost a tenth of a step in contact), then ``--steps``
timed steps through ``Simulation.step`` (the production path: one CUDA graph launch per step on CUDA,
the host loop on the CPU). Reported: body-steps per
second, time per step, candidate pairs (broad phase ``pair_count``) and contacts (pairs with
overlap volume > 0, from ``Simulation.contacts()``), broad-phase rebuilds in the window, device
bytes per body (every Warp array of the Simulation, Model, ShapeSet, State, Contacts and BroadPhase, views counted
once, plus an estimate of the BVH's own buffers; on CUDA also the growth of the mempool's used
memory).

Graph on/off (CUDA): ``use_graph`` of the same Simulation is switched off for ``--steps`` steps and
on again for another ``--steps``; the speed-up is against the mean of the two graph windows (the
pile moves on meanwhile). ``--fresh-no-graph`` times a new ``Simulation(use_graph=False)`` after
the same warm-up instead (the same state, twice the warm-up cost).

Stages: a separate measuring pass after the timed steps runs ``--stage-steps`` steps stage by
stage, with device synchronisation around each stage (wall_s: host clock, so a stage's time
includes its launch overhead; on CUDA also gpu_s, the sum of Warp's CUDA activity timing of its
kernels, copies and memsets): broad-phase check (the Verlet test, every step), broad-phase rebuild
(when the check asks; the device refit + query + sort on CUDA, a host build on the CPU; both also
timed on their own), pair contacts (narrow phase and wrench per candidate pair), gather (per body
sums plus the plane walls), integrate, and the rest (step counter, finiteness check). The launches
of ``Stepper.forces`` and ``Stepper.integrate`` are timed one by one by wrapping ``wp.launch`` for the
pass. These are not a breakdown of the timed steps; the broad phase per step is reported as the
check plus the rebuild cost times the rebuilds per timed step.

Tree (CUDA): the device broad phase refits the tree of its last host build, and the Simulation
rebuilds it between chunks when refitting has degraded it (``--tree-rebuild``: a ratio of the
summed node box areas to a fresh tree's, ``always`` after every chunk with a device rebuild, or
``never``; ``Simulation(tree_rebuild=)``). ``--tree-compare POLICY`` adds, after the stages, the
broad phase at the same poses on the tree as the run left it and on a freshly built one (the tree
walk alone, ``query_*``, and the device rebuild the graph runs, ``device_rebuild_*``), the cost of
the degradation check and of the tree rebuild, then ``--steps`` steps under POLICY. With
``--tree-rebuild never --warmup-time 0.3`` the tree has been refitted since the last host build
(the first, or the last redone chunk after the pair buffer grew: ``host_builds``) up to 0.3 s.

Order: ``--order`` lists the same cubes (same positions, orientations and spins) in memory in the
order they are generated (``grid``: layer by layer), shuffled at random, or along a Morton
(Z-order) curve of the cells of one edge holding their centres; the container walls come after
them in every order. The physics is that of the same pile; only memory locality differs.

    python benchmarks/settle.py --device cuda:0                      # 1e3, 1e4, 1e5, 1e6
    python benchmarks/settle.py --device cuda:0 --skin 0             # Verlet list off: rebuilt every step
    python benchmarks/settle.py --device cpu                         # 1e3, 1e4
    python benchmarks/settle.py --device cuda:0 --sizes 1e5 --warmup-time 0.3 --tree-rebuild never --tree-compare always
    python benchmarks/settle.py --device cuda:0 --sizes 1e5 --order morton   # body order in memory

Results: a table on stdout and JSON (``--out``, default ``benchmarks/results/settle_<device>.json``)
with the machine, Warp version and command line, rewritten after every phase of every size, so a
run cut short keeps what it measured.
"""

import argparse
import gc
import json
import math
import os
import sys
import time
import traceback

import numpy as np
import warp as wp
from polydem.kernels.broadphase import TREE_REBUILD_RATIO

from polydem import ConvexShape, Scene, Simulation
from polydem.scene.depth import Law, stiffness_for_depth
from polydem.simulation import CHUNK_STEPS as CHUNK

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _meta import run_meta  # noqa: E402

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


def half_heights(q, edge):
    """Vertical half extent of cubes of edge ``edge`` turned by unit quaternions q (n, 4) xyzw.

    That is ``edge / 2 * sum_k |R_2k|``, with R_2k = e_z . (R e_k) the third row of R.
    """
    x, y, z, w = q.T
    r20 = 2.0 * (x * z - y * w)
    r21 = 2.0 * (y * z + x * w)
    r22 = 1.0 - 2.0 * (x * x + y * y)
    return 0.5 * edge * (np.abs(r20) + np.abs(r21) + np.abs(r22))


def hertz_k(edge, density, layers, overlap, load_factor, g=9.81, law="hertz", m=None):
    """k of the former rule (``--k-rule volume``; J/m^4.5 under hertz): a face contact (area edge^2) carrying
    load_factor times the weight of a column of ``layers`` cubes overlaps by ``overlap`` of the cube volume.

    W = 2/3 k V^1.5, so the force of a face contact of overlap volume V is k sqrt(V) edge^2; under ``law``
    "power" (W = k V^m / m) it is k V^(m-1) edge^2.
    """
    force = load_factor * layers * density * edge**3 * g
    volume = overlap * edge**3
    # (hertz through math.sqrt, as before the law was an option: the same k to the bit)
    slope = math.sqrt(volume) if law == "hertz" else Law(law, 1.0, m).derivative(volume)
    return force / (slope * edge**2)


K_RULES = ("corner", "volume")
"""``--k-rule``: an allowed corner depth under a column (the default), or the former volume overlap of a face."""


def corner_k(shapes, edge, density, layers, depth, g=9.81, law="hertz", m=None):
    """k of ``law`` (J/m^4.5 under hertz) that keeps every corner of ``shapes`` (each of volume edge^3) at most
    ``depth`` times ``edge`` deep under the weight of a column of ``layers`` of them (the law alone, no toe)."""
    load = layers * density * edge**3 * g
    return max(stiffness_for_depth(shape, law, depth * edge, load, "corner", m=m) for shape in shapes)


def pile_law(args):
    """(law, m) of the pile's material: ``--law`` (hertz, the default, or power with ``--exponent`` m)."""
    law = getattr(args, "law", "hertz")
    return law, (getattr(args, "exponent", 2.0) if law == "power" else None)


def pile_k(args, shapes):
    """The pile's k (J/m^4.5 under hertz) by ``args.k_rule`` times ``args.k_factor`` (see the module docstring). A
    namespace without ``k_rule`` (built by hand with the former rule's ``overlap`` and ``load_factor``) gets the
    volume rule."""
    rule = getattr(args, "k_rule", "volume")
    law, m = pile_law(args)
    if rule == "corner":
        k = corner_k(shapes, args.edge, args.density, args.layers, args.corner_depth, law=law, m=m)
    elif rule == "volume":
        k = hertz_k(args.edge, args.density, args.layers, args.overlap, args.load_factor, law=law, m=m)
    else:
        raise ValueError(f"k_rule must be one of {K_RULES}, got {rule!r}")
    return k * getattr(args, "k_factor", 1.0)


SHAPE_SETS = ("cube", "mixed")
"""``--shapes``: cubes only, or a mixed set of cubes, regular tetrahedra, 20-vertex rocks and 2:1:1 boxes,
each of the cube's volume, in equal numbers (see :func:`shape_set`)."""


def shape_set(edge, shapes="cube"):
    """The pile's shapes as a list of ConvexShape: the cube of edge ``edge``, or for "mixed" the cube,
    a regular tetrahedron, a 20-vertex rock (seed 1) and a 2:1:1 box, all of volume edge^3."""
    cube = ConvexShape.box(edge, name="cube")
    if shapes == "cube":
        return [cube]
    if shapes != "mixed":
        raise ValueError(f"shapes must be one of {SHAPE_SETS}, got {shapes!r}")
    volume = edge**3
    # A regular tetrahedron of edge t has volume t^3 / (6 sqrt 2).
    tetra = ConvexShape.tetrahedron((6.0 * math.sqrt(2.0) * volume) ** (1.0 / 3.0), name="tetrahedron")
    unit_rock = ConvexShape.rock(20, size=1.0, seed=1)
    rock = ConvexShape.rock(20, size=(volume / unit_rock.volume) ** (1.0 / 3.0), seed=1, name="rock20")
    b = (0.5 * volume) ** (1.0 / 3.0)
    long_box = ConvexShape.box(2.0 * b, b, b, name="box211")
    return [cube, tetra, rock, long_box]


def input_vertices(shape):
    """A shape's vertices in its input frame, whose origin and axes ``Scene.add_bodies`` places [m]."""
    return np.asarray(shape.vertices) @ np.asarray(shape.input_rotation).T + np.asarray(shape.input_translation)


def vertical_extents(q, vertices):
    """(below, above) (n,): how far the vertices of bodies turned by unit quaternions q (n, 4) xyzw
    reach below and above their origin, for input-frame ``vertices`` (m, 3)."""
    x, y, z, w = q.T
    row = np.column_stack([2.0 * (x * z - y * w), 2.0 * (y * z + x * w), 1.0 - 2.0 * (x * x + y * y)])
    heights = row @ np.asarray(vertices).T
    return -heights.min(axis=1), heights.max(axis=1)


def make_scene(n, args, seed=0):
    """The pile of ``n`` bodies (``args.shapes``: cubes, or the mixed set of :func:`shape_set`) and its
    container; returns (scene, info dict)."""
    a = args.edge
    layers = args.layers
    rng = np.random.default_rng(seed)
    shapes = shape_set(a, getattr(args, "shapes", "cube"))
    k = pile_k(args, shapes)
    scene = Scene(gravity=(0.0, 0.0, -9.81), dt="auto", name=f"settle_{n}")
    scene.precision = getattr(args, "precision", "float32")
    law, m = pile_law(args)
    extra = {} if m is None else {"m": m}
    scene.add_material(
        "grain", density=args.density, law=law, k=k, restitution=args.restitution, friction=args.friction, **extra
    )
    for shape in shapes:
        scene.add_shape(shape.name, shape)
    mixed = len(shapes) > 1

    # Columns on a square-ish grid; body i is in layer i // columns, column i % columns.
    columns = max(1, math.ceil(n / layers))
    # aspect: the footprint's x:y ratio (benchmarks/scaling.py: one square per rank, side by side along x)
    nx = max(1, math.ceil(math.sqrt(columns * getattr(args, "aspect", 1.0))))
    ny = max(1, math.ceil(columns / nx))
    nz = math.ceil(n / columns)
    # Bounding diameter: the cube's sqrt(3) a, or the largest of the set's.
    diameter = 2.0 * max(s.radius for s in shapes) if mixed else SQRT3 * a
    spacing = diameter * (1.0 + args.margin)
    jitter = 0.45 * (spacing - diameter)  # |dx|, |dy| < jitter: columns' spheres stay apart

    q = random_quaternions(rng, n)
    col = np.arange(n) % columns
    cx = (col % nx - 0.5 * (nx - 1)) * spacing
    cy = (col // nx - 0.5 * (ny - 1)) * spacing
    x = cx + rng.uniform(-jitter, jitter, n)
    y = cy + rng.uniform(-jitter, jitter, n)
    if mixed:
        # From a generator of its own, so that the cubes' draws above and below stay those of "cube".
        which = np.random.default_rng([seed, 1]).permutation(n) % len(shapes)
        below = np.zeros(n)
        above = np.zeros(n)
        for s, shape in enumerate(shapes):
            rows = which == s
            below[rows], above[rows] = vertical_extents(q[rows], input_vertices(shape))
    else:
        below = above = half_heights(q, a)
    # Stack each column: bottom of body k = top of body k-1 + gap (the floor is z = 0).
    lo = np.zeros((nz, columns))
    hi = np.zeros((nz, columns))
    lo.reshape(-1)[:n] = below
    hi.reshape(-1)[:n] = above
    gaps = rng.uniform(args.gap[0], args.gap[1], (nz, columns)) * a
    heights = lo + hi + gaps
    bottom = np.cumsum(heights, axis=0) - heights + gaps
    z = (bottom + lo).reshape(-1)[:n]
    top = float(np.max((bottom + (lo + hi)).reshape(-1)[:n]))
    del lo, hi, gaps, heights, bottom
    positions = np.column_stack([x, y, z])
    spin = None
    if args.spin > 0.0:
        spin = rng.normal(size=(n, 3))
        spin *= args.spin / np.linalg.norm(spin, axis=1, keepdims=True)
    # The same bodies listed in another order (the container walls stay after them).
    perm = listing_order(positions, getattr(args, "order", "grid"), a, seed)
    positions, q = positions[perm], q[perm]
    if spin is not None:
        spin = spin[perm]
    if mixed:
        which = which[perm]
        for s, shape in enumerate(shapes):
            rows = which == s
            w = None if spin is None else spin[rows]
            scene.add_bodies(shape.name, "grain", positions[rows], orientations=q[rows], angular_velocities=w)
    else:
        scene.add_bodies("cube", "grain", positions, orientations=q, angular_velocities=spin)
    del q, col, cx, cy, x, y, z, positions

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
        "law": law,
        "m": m,
        "k_rule": getattr(args, "k_rule", "volume"),
        "order": getattr(args, "order", "grid"),
    }
    if mixed:
        info["shapes"] = {shape.name: int(np.sum(which == s)) for s, shape in enumerate(shapes)}
    return scene, info


ORDERS = ("grid", "shuffled", "morton")


def _spread_bits_21(v):
    # The 21 low bits of v moved to every third bit of a uint64.
    v = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    v = (v | (v << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    return (v | (v << np.uint64(2))) & np.uint64(0x1249249249249249)


def listing_order(positions, order, cell, seed):
    """Permutation of the cubes for ``--order``: "grid" (as generated: layer by layer, column by
    column), "shuffled" (random), "morton" (Z-order of the cells of edge ``cell`` holding the centres)."""
    n = len(positions)
    if order == "grid":
        return np.arange(n)
    if order == "shuffled":
        return np.random.default_rng([seed, 1]).permutation(n)
    if order == "morton":
        c = np.floor((positions - positions.min(axis=0)) / cell).astype(np.int64)
        code = _spread_bits_21(c[:, 0]) | (_spread_bits_21(c[:, 1]) << np.uint64(1))
        code |= _spread_bits_21(c[:, 2]) << np.uint64(2)
        return np.argsort(code, kind="stable")
    raise ValueError(f"unknown order {order!r}, expected one of {ORDERS}")


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
    """Bytes of the Warp arrays owned by the Simulation, its Model, ShapeSet, State, Contacts and BroadPhase.

    Views (e.g. ``pair_key`` into the sort buffer) are counted once: the address ranges are merged.
    The BVH's own buffers are estimated from its node count. Returns a dict.
    """
    owners = {
        "simulation": sim,
        "model": sim.model,
        "shapes": sim.model.shapes,
        "state": sim.current_state,
        "contacts": sim.current_contacts,
        "pair_history": sim.current_contacts.previous,
        "stepper": sim.stepper,
        "broadphase": sim.current_contacts.broadphase,
    }
    if sim.last_good is not None:  # the copy a chunk starts from, for a redo
        owners["snapshot_state"] = sim.last_good.state
        owners["snapshot_pairs"] = sim.last_good.pairs
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
    bp = sim.current_contacts.broadphase
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

    ``wp.launch`` is wrapped for the duration, so that the launches of ``Stepper.forces`` and
    ``Stepper.integrate`` are timed one by one and sorted into stages by kernel name. Returns a dict.
    """
    clock = StageClock(sim.device)
    state, contacts, stepper = sim.current_state, sim.current_contacts, sim.stepper
    bp = contacts.broadphase
    m = sim.model
    device_rebuild = sim.use_graph

    def host_build():
        contacts.build(state.body_q)

    def device_rebuild_once():
        contacts.rebuild_on_device(state.body_q)

    original = wp.launch

    def timed_launch(kernel, *args, **kwargs):
        return clock.run(_launch_stage(kernel), lambda: original(kernel, *args, **kwargs))

    rebuilds = 0
    for _ in range(steps):
        # The broad phase takes the poses as they are (float64 ones are cast inside its kernels).
        clock.run("broadphase_check", lambda: bp.needs_rebuild(*contacts._inputs(state.body_q), m.body_flags))
        if int(bp.rebuild_flag.numpy()[0]):
            rebuilds += 1
            clock.run("broadphase_rebuild", device_rebuild_once if device_rebuild else host_build)
            if device_rebuild and contacts.host_build_needed():
                host_build()
        wp.launch = timed_launch
        try:
            stepper.forces(state, contacts, sim.dt)
            stepper.integrate(state, sim.dt)
        finally:
            wp.launch = original
    # Rebuild costs on their own (the window above may hold none): a host build always; on CUDA
    # also the device rebuild that the graph runs (refit, query, sort of the whole capacity).
    for _ in range(rebuild_reps):
        clock.run("host_build", host_build)
        if device_rebuild:
            clock.run("device_rebuild", device_rebuild_once)
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
    bp = sim.current_contacts.broadphase
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
    bp = sim.current_contacts.broadphase
    count = int(bp.pair_count.numpy()[0])
    b = bp.pair_b.numpy()[:count]
    c = sim.contacts()
    cb = c["body_b"]
    plane = cb < 0
    wall = cb >= grains
    vmax = float(c["volume"].max()) if len(c["volume"]) else 0.0
    worst = int(np.argmax(c["volume"])) if len(c["volume"]) else -1
    worst_pair = [int(c["body_a"][worst]), int(c["body_b"][worst])] if worst >= 0 else []
    return {
        "max_overlap_pair": worst_pair,
        "max_overlap_position": sim.state()["body_position"][worst_pair[0]].tolist() if worst_pair else [],
        "candidate_pairs": count,
        "candidate_pairs_grain_grain": int(np.count_nonzero(b < grains)),
        "pair_capacity": int(bp.capacity),
        "contacts": int(np.count_nonzero(~plane)),
        "contacts_grain_grain": int(np.count_nonzero(~plane & ~wall)),
        "contacts_grain_wall": int(np.count_nonzero(wall)),
        "plane_contacts": int(np.count_nonzero(plane)),
        "max_overlap_volume_fraction": vmax / sim.model.shapes.shapes[0].volume,
        "candidate_pairs_per_grain": count / grains,
        # Mean contacts per cube: a grain-grain contact counts for both cubes.
        "coordination": (2 * int(np.count_nonzero(~plane & ~wall)) + int(np.count_nonzero(plane | wall))) / grains,
    }


# ---------------------------------------------------------------------------------------------
# Driver


def warm_up(sim, steps, record):
    """First step (kernel compile, CUDA graph capture), then the rest in a few blocks with progress."""
    dev = sim.device
    t0 = time.perf_counter()
    sim.step(1)
    wp.synchronize_device(dev)
    first = time.perf_counter() - t0
    log(f"  warm-up: first step (compile, capture) {first:.2f} s")
    rest = steps - 1
    block = max(CHUNK, -(-rest // 8 // CHUNK) * CHUNK)
    done = 0
    t1 = time.perf_counter()
    while done < rest:
        k = min(block, rest - done)
        sim.step(k)
        done += k
        log(
            f"    {1 + done}/{steps} steps, t = {1e3 * sim.time:.1f} ms, {time.perf_counter() - t1:.1f} s, "
            f"{int(sim.current_contacts.broadphase.pair_count.numpy()[0])} candidate pairs"
        )
    wp.synchronize_device(dev)
    record.update({"first_step_s": first, "warmup_steps": steps, "warmup_s": time.perf_counter() - t1})


def run_size(n, args, device, record, save):
    """Benchmark one size; fills ``record`` (a dict) and calls ``save()`` after every phase."""
    gc.collect()
    pool0 = mempool_used(device)
    t0 = time.perf_counter()
    scene, info = make_scene(n, args, seed=args.seed)
    t1 = time.perf_counter()
    skin = None
    if args.skin is not None:
        # In units of the cube's bounding radius; 0 turns the Verlet list off (rebuild every step).
        skin = args.skin * scene.shapes["cube"].radius
    sim = Simulation(scene, device=device, skin=skin, tree_rebuild=args.tree_rebuild, **kernel_options(args))
    apply_stepper_options(sim, args)
    wp.synchronize_device(device)
    t2 = time.perf_counter()
    warmup = args.warmup if args.warmup is not None else max(CHUNK, math.ceil(args.warmup_time / sim.dt))
    initial = sim.contacts()
    sim.stepper.release_diagnostics()  # the buffers of contacts(): not part of stepping
    record.update(info)
    record.update(
        {
            "status": "built",
            "pair_max_registers": sim.stepper.pair_max_registers,
            "order_pair_threads": sim.stepper.thread_order,
            "pair_thread_grouping": sim.current_contacts.thread_grouping,
            "spread_pairs": sim.stepper.spread_pairs,
            "shared_poly": sim.stepper.kernels.shared_poly,
            "dt": sim.dt,
            "skin": sim.skin,
            "use_graph": sim.use_graph,
            "tree_rebuild": sim.tree_rebuild,
            "scene_s": t1 - t0,
            "simulation_init_s": t2 - t1,
            "first_pairs": int(sim.current_contacts.broadphase.num_pairs),
            "initial_contacts": len(initial["volume"]),
            "initial_max_overlap_volume_fraction": float(initial["volume"].max() / sim.model.shapes.shapes[0].volume)
            if len(initial["volume"])
            else 0.0,
        }
    )
    del initial
    log(
        f"N={n}: scene {t1 - t0:.2f} s, Simulation() {t2 - t1:.2f} s, dt {sim.dt:.3g} s, grid {info['grid']}, "
        f"{sim.current_contacts.broadphase.num_pairs} candidate pairs, {record['initial_contacts']} initial contacts; "
        f"{warmup} warm-up steps"
    )
    save()

    warm_up(sim, warmup, record)
    record["status"] = "warm"
    record["warmup_tree_rebuilds"] = sim.current_contacts.broadphase.num_tree_rebuilds
    save()

    trees0 = sim.current_contacts.broadphase.num_tree_rebuilds
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
            "tree_rebuilds": sim.current_contacts.broadphase.num_tree_rebuilds - trees0,
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
        try:
            record["memory"]["mempool_high_water_bytes"] = int(wp.get_mempool_used_mem_high(device))
        except Exception:
            pass
    log(
        f"  timed: {args.steps} steps {seconds:.3f} s = {1e3 * seconds / args.steps:.3f} ms/step, "
        f"{n * args.steps / seconds / 1e6:.3f} M body-steps/s; {record['candidate_pairs']} candidate pairs "
        f"({record['candidate_pairs_grain_grain']} grain-grain), contacts {record['contacts_grain_grain']} "
        f"grain-grain + {record['contacts_grain_wall'] + record['plane_contacts']} wall, max overlap "
        f"{100 * record['max_overlap_volume_fraction']:.2f}% of a cube; rebuilds host {host_builds} device "
        f"{dev_rebuilds} tree {record['tree_rebuilds']}; {mem['total'] / n:.0f} B/body"
    )
    save()

    if sim.use_graph and not args.no_graph_compare:
        graph_off(sim, scene, args, record, warmup)
        save()

    if args.stage_steps > 0:
        stages = measure_stages(sim, args.stage_steps, args.rebuild_reps)
        rebuilds = host_builds + dev_rebuilds
        rebuild_cost = stages["wall_s"].get("device_rebuild" if sim.use_graph else "host_build", 0.0)
        stages["broadphase_per_step_s"] = stages["wall_s"]["broadphase_check"] + rebuild_cost * rebuilds / args.steps
        stages["note"] = (
            "measuring pass after the timed steps, separate from them: each stage run alone with device "
            "synchronisation around it (wall_s includes launch overhead; gpu_s: Warp CUDA activity timing); "
            "broadphase_per_step_s = check + rebuild cost x rebuilds per timed step"
        )
        record["stages"] = stages
        log(
            "  stages (measuring pass, each synchronised) ms: "
            + ", ".join(f"{k} {1e3 * v:.3f}" for k, v in stages["wall_s"].items())
            + (
                "; GPU ms: " + ", ".join(f"{k} {1e3 * v:.3f}" for k, v in stages["gpu_s"].items())
                if stages["gpu_s"]
                else ""
            )
        )
    if args.tree_compare is not None and sim.use_graph:
        record["tree_compare"] = compare_trees(sim, args)
        save()
    record["status"] = "complete"
    save()
    del sim
    gc.collect()


def compare_trees(sim, args):
    """The device broad phase on its tree as it is and on a fresh one, at the same poses; then
    ``--steps`` steps under the ``--tree-compare`` policy (see the module docstring). Returns a dict."""
    clock = StageClock(sim.device)
    state, contacts = sim.current_state, sim.current_contacts
    bp = contacts.broadphase
    reps = max(args.rebuild_reps, 1)
    q, radius = contacts._inputs(state.body_q)
    contacts.rebuild_on_device(state.body_q)  # the pairs of these poses (history carried over)
    refits = int(bp.device_rebuilds.numpy()[0])

    def query():
        bp._query(q, radius)  # the tree walk alone; the list is restored below

    def device_rebuild():
        contacts.rebuild_on_device(state.body_q)  # what the graph runs: refit, query, sort, history

    for tree in ("as_is", "fresh"):
        if tree == "fresh":
            ratio = clock.run("tree_check", bp.tree_degradation)
            clock.run("tree_rebuild", bp.rebuild_tree)
        for _ in range(reps):
            clock.run(f"query_{tree}", query)
            clock.run(f"device_rebuild_{tree}", device_rebuild)
    out = {
        "tree_ratio": ratio,
        "device_rebuilds_since_host_build": refits,
        "wall_s": {k: v / clock.calls[k] for k, v in clock.wall.items()},
        "gpu_s": {k: v / clock.calls[k] for k, v in clock.gpu.items()} if clock.gpu_ok else None,
    }
    policy = sim.tree_rebuild
    sim.tree_rebuild = args.tree_compare
    trees0 = bp.num_tree_rebuilds
    try:
        seconds, host_builds, dev_rebuilds = timed_steps(sim, args.steps)
    finally:
        sim.tree_rebuild = policy
    out.update(
        {
            "policy": args.tree_compare,
            "steps": args.steps,
            "step_s": seconds / args.steps,
            "body_steps_per_s": sim.num_bodies * args.steps / seconds,
            "host_builds": host_builds,
            "device_rebuilds": dev_rebuilds,
            "tree_rebuilds": bp.num_tree_rebuilds - trees0,
        }
    )
    w = out["wall_s"]
    log(
        f"  tree: degradation {ratio:.2f} after {refits} refits; query {1e3 * w['query_as_is']:.3f} ms as is, "
        f"{1e3 * w['query_fresh']:.3f} ms fresh; device rebuild {1e3 * w['device_rebuild_as_is']:.3f} / "
        f"{1e3 * w['device_rebuild_fresh']:.3f} ms; check {1e3 * w['tree_check']:.3f} ms, tree rebuild "
        f"{1e3 * w['tree_rebuild']:.3f} ms; then tree_rebuild={args.tree_compare}: "
        f"{1e3 * out['step_s']:.3f} ms/step ({out['tree_rebuilds']} tree rebuilds)"
    )
    return out


def graph_off(sim, scene, args, record, warmup):
    """Time the same steps with ``use_graph=False``.

    Default: the same Simulation with ``use_graph`` switched off for ``--steps`` steps, then on
    again for another ``--steps`` (the state moves on meanwhile: the speed-up is against the mean of
    the graph windows before and after). ``--fresh-no-graph``: a new ``Simulation(use_graph=False)``
    from the same scene, with the same warm-up, timed from the very same state.
    """
    n = record["grains"]
    if args.fresh_no_graph:
        other = Simulation(scene, device=sim.device, use_graph=False, **kernel_options(args))
        other = apply_stepper_options(other, args)
        other.step(warmup)
        seconds, host_builds, _ = timed_steps(other, args.steps)
        del other
        gc.collect()
        graph_seconds = record["seconds"]
        mode = "fresh Simulation(use_graph=False), same warm-up"
    else:
        sim.use_graph = False
        try:
            seconds, host_builds, _ = timed_steps(sim, args.steps)
        finally:
            sim.use_graph = True
        again, _, _ = timed_steps(sim, args.steps)
        record["step_s_graph_after"] = again / args.steps
        graph_seconds = 0.5 * (record["seconds"] + again)
        mode = "same Simulation, use_graph switched off for the window between two graph windows"
    record["no_graph"] = {
        "mode": mode,
        "seconds": seconds,
        "step_s": seconds / args.steps,
        "body_steps_per_s": n * args.steps / seconds,
        "host_builds": host_builds,
        "graph_speedup": seconds / graph_seconds,
    }
    log(
        f"  use_graph=False: {1e3 * seconds / args.steps:.3f} ms/step ({host_builds} host builds); graph "
        f"{1e3 * graph_seconds / args.steps:.3f} ms/step: speed-up x{seconds / graph_seconds:.2f}"
    )


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
        ("coord", 5, lambda r: f"{r['coordination']:.2f}"),
        ("rebuilds", 8, lambda r: f"{r['host_builds'] + r['device_rebuilds']}"),
        ("B/body", 7, lambda r: f"{r['memory']['bytes_per_body']:.0f}"),
        ("nograph", 9, lambda r: f"{1e3 * r['no_graph']['step_s']:.3f}" if "no_graph" in r else "-"),
        ("regs", 5, lambda r: str(r.get("pair_max_registers") or "none")),
    ]
    log("")
    log(
        "ms per step; stage columns from the separate synchronised measuring pass (bp = check + amortised "
        "rebuild); cand = candidate pairs, contacts = pairs and walls with overlap > 0, coord = contacts per cube"
    )
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


def make_parser():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    ap.add_argument("--sizes", default=None, help="comma-separated cube counts (default 1e3..1e6 GPU, 1e3,1e4 CPU)")
    ap.add_argument("--steps", type=int, default=None, help="timed steps (default 200 GPU, 64 CPU)")
    ap.add_argument("--warmup-time", type=float, default=0.1, help="simulated time [s] before the timing")
    ap.add_argument("--warmup", type=int, default=None, help="warm-up steps (overrides --warmup-time)")
    ap.add_argument("--stage-steps", type=int, default=None, help="steps of the measuring pass (default 20 GPU, 8 CPU)")
    ap.add_argument("--rebuild-reps", type=int, default=2, help="lone broad-phase rebuilds timed in that pass")
    ap.add_argument("--out", default=None, help="JSON file (default benchmarks/results/settle_<device>.json)")
    ap.add_argument("--no-graph-compare", action="store_true", help="skip the use_graph=False timing on CUDA")
    ap.add_argument(
        "--fresh-no-graph", action="store_true", help="time use_graph=False on a new Simulation (repeats the warm-up)"
    )
    ap.add_argument(
        "--skin",
        type=float,
        default=None,
        help="Verlet skin in cube bounding radii (default: the simulator's, 0.2); 0 = no skin, rebuilt every step",
    )
    ap.add_argument("--verbose", action="store_true", help="Warp's module load messages")
    ap.add_argument("--walls", choices=("box", "planes"), default="box", help="container of fixed boxes or planes")
    ap.add_argument("--layers", type=int, default=10, help="cubes per column")
    ap.add_argument("--edge", type=float, default=0.01, help="cube edge [m]")
    ap.add_argument("--density", type=float, default=2500.0, help="[kg/m^3]")
    ap.add_argument("--restitution", type=float, default=0.5)
    ap.add_argument("--friction", type=float, default=0.5)
    ap.add_argument("--overlap", type=float, default=0.01, help="k rule volume: face overlap volume / cube volume")
    ap.add_argument("--load-factor", type=float, default=20.0, help="k rule volume: design load / a column's weight")
    ap.add_argument(
        "--shapes", choices=SHAPE_SETS, default="cube", help="cubes, or cubes, tetrahedra, rocks and 2:1:1 boxes"
    )
    ap.add_argument("--margin", type=float, default=0.03, help="column spacing = bounding diameter (1 + margin)")
    ap.add_argument("--gap", default="0.002,0.02", help="min,max gap between stacked cubes [edges]")
    ap.add_argument("--spin", type=float, default=0.0, help="initial angular speed [rad/s], random axes")
    ap.add_argument("--seed", type=int, default=0)
    add_pile_options(ap)
    ap.add_argument(
        "--tree-compare",
        type=tree_policy,
        default=None,
        help="after the run: the broad phase on its tree and on a fresh one, then --steps steps with this policy",
    )
    ap.add_argument("--precision", choices=("float32", "mixed", "float64"), default="float32", help="precision")
    return ap


def add_kernel_options(ap):
    """``--max-registers``: the register cap of the step's pair kernel; ``--pair-thread-order``: its threads take
    the pairs grouped by cost and contact (the default), by cost alone, or in slot order (see
    :func:`kernel_options`)."""
    ap.add_argument(
        "--max-registers",
        type=int,
        default=None,
        help="CUDA register cap of the step's pair kernel (default: kernels/forces.py PAIR_MAX_REGISTERS; 0: no cap)",
    )
    ap.add_argument(
        "--pair-thread-order",
        choices=("default", "cost", "contact", "slot"),
        default="default",
        help="default: Simulation's default (order_pair_threads=True, which is contact); cost: the pair kernel's "
        "threads take the pairs grouped by the cost of their shapes where the shapes differ in cost (--shapes "
        "mixed); contact: by cost, the costliest first, and then by whether the pair touched at the last rebuild "
        "(any pile); slot: in slot order, order_pair_threads=False (the same results every way)",
    )
    ap.add_argument(
        "--spread-pairs",
        default="default",
        help="how many of the costliest pairs the pair kernel spreads over 8 lanes each (Stepper.set_spread): "
        "default (spread_room: half a wave's worth on a GPU, none on the CPU), or a count (0: none)",
    )
    ap.add_argument(
        "--shared-poly", action=argparse.BooleanOptionalAction, default=None,
        help="the pair kernel's polygon buffer in the block's shared memory where it fits (Stepper.set_shared_poly; "
        "default: the library's, on); --no-shared-poly: the per-thread buffer",
    )  # fmt: skip
    # the flag of the runs before the default changed (BENCHMARKS.md 17)
    ap.add_argument(
        "--order-pair-threads", dest="pair_thread_order", action="store_const", const="cost", help=argparse.SUPPRESS
    )


def apply_stepper_options(sim, args):
    """``--spread-pairs`` and ``--[no-]shared-poly`` on a built Simulation (before its first step: its graphs are
    captured afterwards)."""
    value = getattr(args, "spread_pairs", "default")
    if value != "default" and sim.stepper.thread_order:
        sim.stepper.set_spread(int(value))
    shared = getattr(args, "shared_poly", None)
    if shared is not None and shared != sim.stepper.shared_poly:
        sim.stepper.set_shared_poly(shared)
    return sim


def kernel_options(args):
    """The ``Simulation`` keyword arguments of ``--max-registers`` and ``--pair-thread-order`` (none at their
    defaults)."""
    out = {}
    if args.max_registers is not None:
        out["pair_max_registers"] = args.max_registers or None
    order = getattr(args, "pair_thread_order", "default")
    if order != "default":
        out["order_pair_threads"] = False if order == "slot" else order
    return out


def add_pile_options(ap):
    """The options this benchmark shares with time_to_settle.py: register cap, k rule, listing order, tree policy."""
    add_kernel_options(ap)
    ap.add_argument(
        "--k-rule", choices=K_RULES, default="corner", help="k from a corner depth, or the former volume overlap"
    )
    ap.add_argument(
        "--corner-depth", type=float, default=0.05, help="k rule corner: largest corner depth / edge under a column"
    )
    ap.add_argument("--k-factor", type=float, default=1.0, help="k = this x the rule's")
    ap.add_argument("--law", choices=("hertz", "power"), default="hertz", help="the grains' contact law")
    ap.add_argument("--exponent", type=float, default=2.0, help="m of --law power (W = k V^m / m)")
    ap.add_argument("--order", choices=ORDERS, default="grid", help="listing order of the cubes in memory")
    ap.add_argument(
        "--tree-rebuild",
        type=tree_policy,
        default=TREE_REBUILD_RATIO,
        help="Simulation(tree_rebuild=): a ratio, 'always' (0) or 'never' (default: TREE_REBUILD_RATIO)",
    )


def tree_policy(text):
    """``--tree-rebuild`` value: "never" (None), "always" (0) or a ratio."""
    if text == "never":
        return None
    if text == "always":
        return 0.0
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'never', 'always' or a ratio, got {text!r}") from None
    if not value >= 0.0:
        raise argparse.ArgumentTypeError(f"the ratio must be >= 0, got {text!r}")
    return value


def parse_args(ap, argv=None):
    args = ap.parse_args(argv)
    args.gap = tuple(float(v) for v in args.gap.split(","))
    if len(args.gap) != 2 or not 0.0 <= args.gap[0] <= args.gap[1]:
        ap.error("--gap needs two numbers 0 <= min <= max")
    return args


def scene_options(**overrides):
    """This benchmark's scene options at their defaults (for the scripts that build the same pile)."""
    args = parse_args(make_parser(), [])
    for key, value in overrides.items():
        setattr(args, key, value)
    return args


def main():
    args = parse_args(make_parser())

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    cuda = device.is_cuda
    sizes = args.sizes or ("1000,10000,100000,1000000" if cuda else "1000,10000")
    sizes = [int(float(s)) for s in sizes.split(",") if s.strip()]
    if args.steps is None:
        args.steps = 200 if cuda else 64
    if args.stage_steps is None:
        args.stage_steps = 20 if cuda else 8
    if args.warmup is not None:
        args.warmup = max(args.warmup, 1)
    if not args.verbose:
        wp.config.log_level = wp.LOG_WARNING
    out = args.out or os.path.join(HERE, "results", f"settle_{device.alias.replace(':', '')}.json")
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)

    meta = run_meta(device)
    config = {k: v for k, v in vars(args).items() if k != "out"}
    config["sizes"] = sizes
    records = []

    def save():
        tmp = out + ".tmp"
        with open(tmp, "w") as f:
            json.dump({"meta": meta, "config": config, "results": records}, f, indent=1)
        os.replace(tmp, out)

    log(f"settle benchmark on {device.name} ({device.alias}), Warp {wp.config.version}; sizes {sizes}, ")
    warm = f"{args.warmup} warm-up steps" if args.warmup else f"{args.warmup_time} s simulated warm-up"
    log(f"  {args.steps} timed steps after {warm}; walls {args.walls}; JSON -> {out}")
    for n in sizes:
        record = {"grains": n, "status": "started"}
        records.append(record)
        try:
            run_size(n, args, device, record, save)
        except Exception as err:  # keep what was measured, go on with the next size
            record["status"] = "error"
            record["error"] = f"{type(err).__name__}: {err}"
            record["traceback"] = traceback.format_exc()
            log(f"  N={n}: {record['traceback']}")
            save()
            if isinstance(err, MemoryError):
                break
    print_table(records)
    save()


if __name__ == "__main__":
    main()
