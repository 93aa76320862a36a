"""Broad phase: candidate body pairs from bounding spheres, with a Verlet skin.

A pair (a, b), a < b, is a candidate when at least one of the two bodies is free and

    |x_a - x_b| < r_a + r_b + skin

with x the body centre and r the radius of the bounding sphere about it. The list stays valid
(it holds every pair whose bounding spheres overlap) until some body has moved by more than
skin/2 since the build, see :meth:`BroadPhase.needs_rebuild`.

Design (mixed sizes, millions of bodies)
----------------------------------------
One Warp BVH over the sphere boxes ``x -+ (r + skin/2)``, built as a *grouped* BVH:

* every free body goes to a size class ``c = floor(log(r / r_min) / log(class_ratio))`` (r_min:
  the smallest free radius), clamped to ``MAX_CLASSES - 1``; each class is one group (subtree);
* all fixed and kinematic bodies share the group ``NONFREE_GROUP``.

Only free bodies query. A free body of class c runs one sphere query (centre x_i, radius
r_i + skin/2) from the root of each group c, c+1, ..., c_max and of the non-free group, so it never
walks over the bodies of the classes below its own. Each pair is emitted exactly once:

* free i, non-free j: only i queries (non-free bodies never query);
* free i, free j of a higher class: only i meets j (j does not look at lower classes);
* free i, free j of the same class: both meet, the lower index emits.

So a large body (a free boulder, a container wall) never walks over the thousands of small grains
around it, which would stall its warp: the grains find it. A uniform grid would need cells of the
largest diameter (or a hierarchy of grids) for the same. Query threads run in the Morton order of
the free bodies' centres (sorted at each host build and tree renewal check; the non-free bodies,
which do not query, after them), so that the threads of a warp walk the same part of the tree.

The class ratio 8, the Morton order and one atomic per pair were chosen by measurement:
BENCHMARKS.md, "Design measurements".

Threads append the int64 key ``a * num_bodies + b`` through one atomic counter. Past the capacity
nothing is written but the counter keeps counting, so the host build knows the true count, grows
the buffers and runs the query again: no pair is ever dropped silently. A radix sort of the keys
(only the bits that ``num_bodies**2`` needs) then gives the strictly increasing order, identical
on every run and every device for the same set of pairs; ``pair_a``/``pair_b`` are unpacked from
the sorted keys.

Two ways to drive it:

* host: :meth:`BroadPhase.build` (exact, grows on overflow; synchronises once to read the count;
  builds a fresh tree with new size classes) and :meth:`BroadPhase.update` (reads the rebuild
  flag, rebuilds when needed);
* device only, usable inside a CUDA graph capture: :meth:`BroadPhase.update_on_device` computes the
  rebuild flag and branches on it with ``wp.capture_if`` (Warp 1.19; a conditional graph node,
  CUDA 12.4+) into :meth:`BroadPhase.rebuild_on_device`. That one allocates nothing (a
  conditional graph body may not): it *refits* the tree of the last host build (same topology
  and size classes, new boxes; always exact, slower as the bodies drift away from the build
  layout), queries, and sorts the whole capacity with padded keys. It cannot grow the buffers:
  an overflow, or a change of body flags (which would need new groups), raises the sticky device
  flag ``host_build_needed``; the host checks it between graph launches
  (:meth:`BroadPhase.check_host_build_needed`), then calls :meth:`BroadPhase.build` and captures
  again. ``device_rebuilds`` counts the device rebuilds since the last host build.

Refitting keeps the tree of the last host build: as bodies move past one another (a pour) its boxes
grow and overlap and the queries slow down. Between graph launches the host may call
:meth:`BroadPhase.renew_tree`: after device rebuilds it measures the tree's degradation (the summed
node box areas of the refitted tree against a fresh one, :meth:`BroadPhase.tree_degradation`) and
past a ratio rebuilds the tree in place from the boxes of the last rebuild (Warp's LBVH rebuild
reuses its buffers, so a captured graph stays valid; it allocates scratch, so it stays out of the
graph). The tree only filters: the pairs, sorted by key, are the same with any tree.

Layout of this file: constants, ``@wp.func`` helpers, the kernels, then the plain numpy
reference :func:`all_pairs` and the host class :class:`BroadPhase`.
"""

import functools
import weakref
from typing import Any

import numpy as np
import warp as wp
from polydem.kernels.structs import arrays, filled, make_struct

FLAG_FREE = wp.constant(0)
FLAG_FIXED = wp.constant(1)
FLAG_KINEMATIC = wp.constant(2)

# Number of size classes of free bodies; the non-free bodies take the group after them.
MAX_CLASSES = wp.constant(16)
NONFREE_GROUP = wp.constant(16)
NUM_GROUPS = 17

# Relative padding of the BVH boxes and query spheres against float32 rounding: a box a few
# ulp too small could hide a pair that the exact test accepts. Extra candidates of the BVH are
# harmless, the exact sphere test below decides.
BOX_PAD = wp.constant(1.0e-5)

# Tree renewal (:meth:`BroadPhase.renew_tree`): the cost of a tree is measured on an implicit tree
# with this many children per node over the bodies in a Morton order.
TREE_BRANCHING = wp.constant(4)
# Default ratio of the cost of the refitted tree to a fresh one above which the tree is rebuilt;
# None: never. Off by default: in the settling pile the tree stayed as good as a fresh one (the host
# builds that grow the pair capacity renew it; a query on it cost 5% more than on a fresh tree) while
# each check costs a synchronisation and a sort (BENCHMARKS.md section 7e). Scenes that mix for a
# long time (drums, shaking) can turn it on with Simulation(tree_rebuild=1.2).
MAX_INDEX = 2**31 - 1
"""The largest index of a device array the kernels take (int32): the pair buffers hold twice the pair capacity."""

TREE_REBUILD_RATIO = None

# Default capacity in pairs per body (dense packings of equal spheres with a small skin have
# 6 to 8 candidate pairs per body).
DEFAULT_PAIRS_PER_BODY = 8
MIN_CAPACITY = 1024


# ---------------------------------------------------------------------------------------------
# What the kernels share, in structs (one instance each per BroadPhase, made with its arrays)

Boxes = make_struct("Boxes", **arrays(lower=wp.vec3, upper=wp.vec3))
"""Boxes (lower and upper corners) [m]: the BVH items', the bodies' in their own frames, a tree level's blocks."""

_BUILD = arrays(q_build=wp.transform, radius_build=float, flags_build=int, body_group=int, body_order=int)
_BUILD |= arrays(group_root=int, class_max=int, radius_min=float, box_lower=wp.vec3, box_upper=wp.vec3)
_BUILD |= arrays(body_box=int, body_box_lower=wp.vec3, body_box_upper=wp.vec3)
Build = make_struct("Build", **_BUILD)
"""The state of the last (re)build, as the :class:`BroadPhase` names its arrays (N,): the poses, radii and
flags of the build (the groups of the tree follow the flags of the last host build), each body's BVH group
(its size class, ``NONFREE_GROUP`` for the others) and the query order (a permutation); per group its
subtree's root (``group_root``, NUM_GROUPS, -1: empty); the largest size class of a free body (``class_max``,
(1,)) and the smallest positive free radius (``radius_min``, (1,)) [m]; the BVH items' boxes
(``box_lower``, ``box_upper``) and the boxes around the bodies' shapes in their own frames (body i's is
``body_box_lower[body_box[i]]``, ``body_box_upper[body_box[i]]``: each distinct box is stored once, so bodies of
one shape share theirs; a pair with a fixed or kinematic body must also have the free body's sphere, grown by
the skin, reach that box, so that a container wall, whose bounding sphere covers the whole pile, is a candidate
only of the grains near it)."""

PairList = make_struct("PairList", **arrays(pair_key=wp.int64, pair_a=int, pair_b=int, pair_count=int))
"""The pair list, as the :class:`BroadPhase` names its arrays: the keys, the bodies of each pair and their
count (see the :class:`BroadPhase`); made again with the arrays when the capacity grows."""

_COUNTS = arrays(pair_counter=int, pair_count=int, pair_count_peak=int, host_build_needed=int, device_rebuilds=int)
Counts = make_struct("Counts", **_COUNTS)

Spheres = make_struct("Spheres", **arrays(radius=float, flags=int))
"""The bodies' (N,) bounding-sphere radii about their centres [m] and flags (0 free, 1 fixed, 2 kinematic), as the
broad phase is given them at each call."""
"""The counters (1,) of a query, as the :class:`BroadPhase` names them: the pairs found (may exceed the
capacity), their count (at most the capacity), the largest found since the last host build, the sticky
``host_build_needed`` (a device rebuild overflowed or saw changed flags) and the device rebuilds since the
last host build."""


# ---------------------------------------------------------------------------------------------
# Helpers


@wp.func
def padded_extent(r: float, half_skin: float, x: wp.vec3):
    # Half extent of a body's box (and radius of its query sphere): r + skin/2, padded by a
    # relative amount and by the rounding of coordinates of the size of x.
    m = wp.max(wp.max(wp.abs(x[0]), wp.abs(x[1])), wp.abs(x[2]))
    return (r + half_skin) * (1.0 + BOX_PAD) + BOX_PAD * m


@wp.func
def make_pair_key(i: int, j: int, num_bodies: int):
    # int64 key a * num_bodies + b of the unordered pair {i, j}, a < b.
    a = wp.min(i, j)
    b = wp.max(i, j)
    return wp.int64(a) * wp.int64(num_bodies) + wp.int64(b)


@wp.func
def spread_bits(v: int):
    # The 10 low bits of v moved to every third bit (bits 0, 3, ..., 27).
    v = (v | (v << 16)) & 0x030000FF
    v = (v | (v << 8)) & 0x0300F00F
    v = (v | (v << 4)) & 0x030C30C3
    v = (v | (v << 2)) & 0x09249249
    return v


@wp.func
def rotation_angle(q: wp.quat, q0: wp.quat):
    # Angle [rad] in [0, pi] of the rotation taking q0 to q (not assumed normalised).
    r = q * wp.quat_inverse(q0)
    s = wp.length(wp.vec3(r[0], r[1], r[2]))
    return 2.0 * wp.atan2(s, wp.abs(r[3]))


@wp.func
def empty_box():
    # (lower, upper) of a box that holds nothing (lower above upper), to grow by wp.min and wp.max.
    return wp.vec3(3.0e38, 3.0e38, 3.0e38), wp.vec3(-3.0e38, -3.0e38, -3.0e38)


@wp.func
def box_area(lower: wp.vec3, upper: wp.vec3):
    # Surface area [m^2] of a box, 0 for an empty one (lower above upper).
    e = upper - lower
    if e[0] < 0.0:
        return 0.0
    return 2.0 * (e[0] * e[1] + e[1] * e[2] + e[2] * e[0])


@wp.func
def store_block(b: int, lo: wp.vec3, hi: wp.vec3, slot: int, blocks: Boxes, tree_cost: wp.array(dtype=wp.float64)):
    # Block b of a level of the implicit tree: its box, and its area added to the tree's cost.
    blocks.lower[b] = lo
    blocks.upper[b] = hi
    wp.atomic_add(tree_cost, slot, wp.float64(box_area(lo, hi)))


# Relative rounding of a float32 coordinate, 2^-24, and how many such roundings the radius of a
# body fed to the broad phase from float64 poses covers: its centre is rounded at the build and now
# (the skin test), its partner's too, each by up to sqrt(3) 2^-24 |x|_max; 8 leaves room for the
# arithmetic of the tests and for |x| growing by the skin between the two.
CAST_ROUNDINGS = 8.0


@wp.func
def body_input(body_q: wp.array(dtype=wp.transform), body_radius: wp.array(dtype=float), i: int):
    # Body i's pose and bounding radius [m] as the broad phase works with them: float32 poses as they are.
    return body_q[i], body_radius[i]


@wp.func
def body_input(body_q: wp.array(dtype=wp.transformd), body_radius: wp.array(dtype=float), i: int):  # noqa: F811 (overload)
    # From float64 poses: the pose cast to float32 and the radius grown by the rounding of the cast
    # (CAST_ROUNDINGS times 2^-24 of the largest coordinate and the radius), so that a pair whose float64
    # bounding spheres overlap is never missed; extra candidates are harmless.
    q = body_q[i]
    x = wp.transform_get_translation(q)
    r = wp.float64(body_radius[i])
    m = wp.max(wp.max(wp.abs(x[0]), wp.abs(x[1])), wp.abs(x[2]))
    pad = wp.float64(CAST_ROUNDINGS) * wp.float64(5.960464477539063e-08) * (m + r)
    return wp.transform(wp.vec3(x), wp.quat(wp.transform_get_rotation(q))), float(r + pad)


# ---------------------------------------------------------------------------------------------
# Kernels
#
# The kernels that read poses take ``body_q`` as (N,) ``wp.transform`` or ``wp.transformd`` (``Any``: one
# overload each) with float32 radii, through :func:`body_input`: float64 poses are cast where they are read,
# with no float32 copy of them in memory.


@wp.kernel(enable_backward=False)
def reset_classes_kernel(build: Build):
    build.radius_min[0] = 3.0e38
    build.class_max[0] = 0


@wp.kernel(enable_backward=False)
def radius_min_kernel(body_q: wp.array(dtype=Any), spheres: Spheres, build: Build):
    """Smallest positive radius [m] of the free bodies, into ``build.radius_min[0]``. Launch dim: bodies."""
    i = wp.tid()
    _q, r = body_input(body_q, spheres.radius, i)
    if spheres.flags[i] == FLAG_FREE and r > 0.0:
        wp.atomic_min(build.radius_min, 0, r)


@wp.kernel(enable_backward=False)
def classes_kernel(inv_log_class_ratio: float, body_q: wp.array(dtype=Any), spheres: Spheres, build: Build):
    """BVH group of every body into ``build.body_group`` (its size class, ``NONFREE_GROUP`` for the others;
    the largest class into ``class_max``, atomic max); remembers the flags (0 free, 1 fixed, 2 kinematic) of the
    build. Launch dim: bodies. ``inv_log_class_ratio`` is 1 / ln(class_ratio); ``build.radius_min`` holds the
    smallest positive free radius; the radii [m] are those ``body_input`` makes of ``body_q`` and the
    ``spheres`` (grown by the cast of float64 poses)."""
    i = wp.tid()
    _q, r = body_input(body_q, spheres.radius, i)
    f = spheres.flags[i]
    build.flags_build[i] = f
    if f == FLAG_FREE:
        c = int(0)
        r0 = build.radius_min[0]
        if r > r0:
            c = wp.min(int(wp.floor(wp.log(r / r0) * inv_log_class_ratio)), MAX_CLASSES - 1)
            c = wp.max(c, 0)
        build.body_group[i] = c
        wp.atomic_max(build.class_max, 0, c)
    else:
        build.body_group[i] = NONFREE_GROUP


@wp.kernel(enable_backward=False)
def bounds_kernel(half_skin: float, body_q: wp.array(dtype=Any), spheres: Spheres, build: Build, counts: Counts):
    """Boxes of the BVH items; remembers the poses and radii of the build. Launch dim: bodies.

    Args:
        half_skin: skin / 2 [m].
        body_q: (N,) body poses, position [m] and unit quaternion xyzw.
        spheres: :data:`Spheres`, the bodies' radii and flags now.
        build: :data:`Build`: out, ``box_lower``, ``box_upper`` (the sphere boxes inflated by skin/2 [m]),
            ``q_build`` and ``radius_build`` (copies of the inputs, float32: :func:`body_input`); in, ``flags_build``.
        counts: :data:`Counts`: ``host_build_needed`` set to 1 (sticky) when a flag differs from the build's.
    """
    i = wp.tid()
    q, r = body_input(body_q, spheres.radius, i)
    x = wp.transform_get_translation(q)
    e = padded_extent(r, half_skin, x)
    ev = wp.vec3(e, e, e)
    build.box_lower[i] = x - ev
    build.box_upper[i] = x + ev
    build.q_build[i] = q
    build.radius_build[i] = r
    if spheres.flags[i] != build.flags_build[i]:
        wp.atomic_max(counts.host_build_needed, 0, 1)


@wp.kernel(enable_backward=False)
def float32_input_kernel(
    # Model
    body_radius: wp.array(dtype=float),
    # State in
    body_q: wp.array(dtype=wp.transformd),
    # Out
    body_q32: wp.array(dtype=wp.transform),
    body_radius32: wp.array(dtype=float),
):
    """Float32 poses and radii from float64 poses, as the broad phase's kernels see them
    (:func:`body_input`; they cast where they read, so the broad phase needs no copy). Launch dim: bodies.

    The radii grow by the rounding of the cast (``CAST_ROUNDINGS`` times 2^-24 of the largest
    coordinate and the radius), so that a pair whose float64 bounding spheres overlap is never
    missed; extra candidates are harmless.
    """
    i = wp.tid()
    q, r = body_input(body_q, body_radius, i)
    body_q32[i] = q
    body_radius32[i] = r


@wp.kernel(enable_backward=False)
def reset_extent_kernel(
    # Out
    scene_lower: wp.array(dtype=float),
    scene_upper: wp.array(dtype=float),
):
    for k in range(3):
        scene_lower[k] = 3.0e38
        scene_upper[k] = -3.0e38


@wp.kernel(enable_backward=False)
def extent_kernel(build: Build, scene_lower: wp.array(dtype=float), scene_upper: wp.array(dtype=float)):
    """Box (3,) + (3,) [m] around all body centres of the build (atomic min / max). Launch dim: bodies."""
    x = wp.transform_get_translation(build.q_build[wp.tid()])
    for k in range(3):
        wp.atomic_min(scene_lower, k, x[k])
        wp.atomic_max(scene_upper, k, x[k])


@wp.kernel(enable_backward=False)
def morton_kernel(
    build: Build,
    scene_lower: wp.array(dtype=float),
    scene_upper: wp.array(dtype=float),
    morton: wp.array(dtype=int),
    order: wp.array(dtype=int),
):
    """30-bit Morton code of each free body's centre in the scene box at the build (2^30 for the others,
    which so sort after the free bodies: they do not query), and the identity order into ``order`` (the
    values the codes are sorted with). Launch dim: bodies.
    """
    i = wp.tid()
    x = wp.transform_get_translation(build.q_build[i])
    code = int(1 << 30)
    if build.flags_build[i] == FLAG_FREE:
        code = int(0)
        for k in range(3):
            lo = scene_lower[k]
            w = wp.max(scene_upper[k] - lo, 1.0e-30)
            c = wp.clamp(int((x[k] - lo) / w * 1024.0), 0, 1023)
            code = code | (spread_bits(c) << k)
    morton[i] = code
    order[i] = i


@wp.kernel(enable_backward=False)
def group_root_kernel(bvh_id: wp.uint64, build: Build):
    """Root node of each group's subtree, -1 for an empty group. Launch dim: ``NUM_GROUPS``."""
    g = wp.tid()
    build.group_root[g] = wp.bvh_get_group_root(bvh_id, g)


@wp.kernel(enable_backward=False)
def query_pairs_kernel(
    bvh_id: wp.uint64,
    num_bodies: int,
    capacity: int,
    half_skin: float,
    skin: float,
    body_q: wp.array(dtype=Any),
    body_radius: wp.array(dtype=float),
    build: Build,
    counts: Counts,
    pairs: PairList,
):
    """Appends the key of every candidate pair, each exactly once (see the module docstring).

    Launch dim: bodies; thread t handles body ``build.body_order[t]`` (a spatial order, so that the
    threads of a warp walk the same part of the tree).

    Args:
        num_bodies: N.
        capacity: length of ``pair_key`` that may be written.
        half_skin, skin: skin / 2 and skin [m].
        body_q, body_radius: (N,) the poses and radii now.
        build: :data:`Build`: the query order, the groups, their roots and the largest size class, the flags
            of the last host build, the bodies' boxes in their own frames.
        counts: :data:`Counts`: ``pair_counter``, in/out, the number of pairs found (may exceed ``capacity``).
        pairs: :data:`PairList`: out, ``pair_key`` (capacity,), the keys ``a * N + b`` in arbitrary order.
    """
    i = build.body_order[wp.tid()]
    if build.flags_build[i] != FLAG_FREE:
        return
    qi, ri = body_input(body_q, body_radius, i)
    xi = wp.transform_get_translation(qi)
    ci = build.body_group[i]
    query_radius = padded_extent(ri, half_skin, xi)
    last = build.class_max[0] + 1
    for k in range(ci, last + 1):
        g = k
        if k == last:
            g = NONFREE_GROUP
        root = build.group_root[g]
        if root >= 0:
            query = wp.bvh_query_sphere(bvh_id, xi, query_radius, root)
            j = int(0)
            while wp.bvh_query_next(query, j):
                # Within the own class both bodies meet each other: the lower index emits.
                if g == ci and j <= i:
                    continue
                qj, rj = body_input(body_q, body_radius, j)
                d = wp.transform_get_translation(qj) - xi
                cut = ri + rj + skin
                near = wp.dot(d, d) < cut * cut
                if near and build.flags_build[j] != FLAG_FREE:
                    local = wp.quat_rotate_inv(wp.transform_get_rotation(qj), -d)
                    kb = build.body_box[j]
                    gap = local - wp.min(wp.max(local, build.body_box_lower[kb]), build.body_box_upper[kb])
                    near = wp.dot(gap, gap) < (ri + skin) * (ri + skin)
                if near:
                    # One atomic per pair: no slower than batching a thread's keys in local memory,
                    # since the tree walk dominates (BENCHMARKS.md, "Design measurements").
                    slot = wp.atomic_add(counts.pair_counter, 0, 1)
                    if slot < capacity:
                        pairs.pair_key[slot] = make_pair_key(i, j, num_bodies)


@wp.kernel(enable_backward=False)
def finish_count_kernel(capacity: int, counts: Counts):
    """``pair_count = min(pair_counter, capacity)`` (:data:`Counts`); an overflow sets the sticky
    ``host_build_needed``.

    Also counts the builds in ``device_rebuilds`` and keeps the largest true count in ``pair_count_peak``.
    Launch dim: 1.
    """
    n = counts.pair_counter[0]
    counts.pair_count_peak[0] = wp.max(counts.pair_count_peak[0], n)
    if n > capacity:
        counts.host_build_needed[0] = 1
        n = capacity
    counts.pair_count[0] = n
    counts.device_rebuilds[0] = counts.device_rebuilds[0] + 1


@wp.kernel(enable_backward=False)
def pad_keys_kernel(sentinel: wp.int64, pairs: PairList):
    """Unused slots get a key above every real key so a sort over the capacity leaves them last.

    Launch dim: capacity.
    """
    k = wp.tid()
    if k >= pairs.pair_count[0]:
        pairs.pair_key[k] = sentinel


@wp.kernel(enable_backward=False)
def unpack_pairs_kernel(num_bodies: int, pairs: PairList):
    """Body indices (``pair_a``, ``pair_b``) from the sorted keys; -1 past the count. Launch dim: count or
    capacity."""
    k = wp.tid()
    if k < pairs.pair_count[0]:
        key = pairs.pair_key[k]
        n = wp.int64(num_bodies)
        a = key / n
        pairs.pair_a[k] = int(a)
        pairs.pair_b[k] = int(key - a * n)
    else:
        pairs.pair_a[k] = -1
        pairs.pair_b[k] = -1


@wp.kernel(enable_backward=False)
def needs_rebuild_kernel(
    # Now
    body_q: wp.array(dtype=Any),
    spheres: Spheres,
    # At the build, and how far a body may move from it: skin / 2 [m], with or without its turn (0 or 1)
    build: Build,
    half_skin: float,
    rotation_term: int,
    # Out
    rebuild_flag: wp.array(dtype=int),
):
    """Raises ``rebuild_flag[0]`` (atomic max) when a body may have left its skin since the ``build``.
    Launch dim: bodies.

    A body's motion since the build is ``|x - x_0| + r * angle(q q_0^-1) + max(r - r_0, 0)`` [m]; past
    skin / 2 a pair could be missed. A change of flags also asks for a rebuild.
    """
    i = wp.tid()
    q, r = body_input(body_q, spheres.radius, i)
    q0 = build.q_build[i]
    move = wp.length(wp.transform_get_translation(q) - wp.transform_get_translation(q0))
    move += wp.max(r - build.radius_build[i], 0.0)
    # A fixed or kinematic body is tested by its box, which turns with it.
    if rotation_term != 0 or spheres.flags[i] != FLAG_FREE:
        move += r * rotation_angle(wp.transform_get_rotation(q), wp.transform_get_rotation(q0))
    if move > half_skin or spheres.flags[i] != build.flags_build[i]:
        wp.atomic_max(rebuild_flag, 0, 1)


@wp.kernel(enable_backward=False)
def leaf_blocks_kernel(
    num_bodies: int,
    slot: int,
    order: wp.array(dtype=int),
    build: Build,
    blocks: Boxes,
    tree_cost: wp.array(dtype=wp.float64),
):
    """Box around the free bodies ``order[4 b .. 4 b + 3]`` (their BVH items' boxes at the build; empty:
    lower above upper) into ``blocks``, its surface area added to ``tree_cost[slot]`` [m^2]. Launch dim:
    ceil(N / 4)."""
    b = wp.tid()
    lo, hi = empty_box()
    for k in range(TREE_BRANCHING):
        t = TREE_BRANCHING * b + k
        if t < num_bodies:
            i = order[t]
            if build.flags_build[i] == FLAG_FREE:
                lo = wp.min(lo, build.box_lower[i])
                hi = wp.max(hi, build.box_upper[i])
    store_block(b, lo, hi, slot, blocks, tree_cost)


@wp.kernel(enable_backward=False)
def merge_blocks_kernel(
    num_children: int, slot: int, children: Boxes, blocks: Boxes, tree_cost: wp.array(dtype=wp.float64)
):
    """One level up: box of the ``children`` blocks ``4 b .. 4 b + 3`` into ``blocks``, its area added to
    ``tree_cost[slot]``.

    Launch dim: ceil(num_children / 4).
    """
    b = wp.tid()
    lo, hi = empty_box()
    for k in range(TREE_BRANCHING):
        c = TREE_BRANCHING * b + k
        if c < num_children:
            lo = wp.min(lo, children.lower[c])
            hi = wp.max(hi, children.upper[c])
    store_block(b, lo, hi, slot, blocks, tree_cost)


# ---------------------------------------------------------------------------------------------
# Launch functions (the BroadPhase below launches its own kernels)


def launch_float32_inputs(
    *, body_radius: wp.array, body_q: wp.array, body_q32: wp.array, body_radius32: wp.array
) -> None:
    """Float32 copies ``body_q32`` and ``body_radius32`` of float64 poses ``body_q`` and of the radii
    grown by the cast's rounding (:func:`float32_input_kernel`), for the broad phase."""
    wp.launch(
        float32_input_kernel,
        dim=body_q.shape[0],
        inputs=[body_radius, body_q],
        outputs=[body_q32, body_radius32],
        device=body_q.device,
    )


def for_poses(kernel: wp.Kernel, body_q: wp.array) -> wp.Kernel:
    """The overload of ``kernel`` (one of this module's kernels generic over ``body_q``) for the poses ``body_q``,
    to launch as it is: a generic kernel would infer its argument types at every launch (20 us on the CPU)."""
    return _overload(kernel, body_q.dtype)


@functools.cache
def _overload(kernel: wp.Kernel, pose_dtype: type) -> wp.Kernel:
    types = [wp.array(dtype=pose_dtype) if name == "body_q" else t for name, t in kernel.adj.arg_types.items()]
    return kernel.add_overload(types)


def pose_overloads(kernel: wp.Kernel) -> None:
    """Both overloads of a kernel generic over ``body_q`` (float32 and float64 poses), made before its module's
    first load: no overload is then added (and the module loaded again) later, in a CUDA graph capture say."""
    for pose in (wp.transform, wp.transformd):
        _overload(kernel, pose)


for _kernel in (radius_min_kernel, classes_kernel, bounds_kernel, query_pairs_kernel, needs_rebuild_kernel):
    pose_overloads(_kernel)
del _kernel


def byte_view(base: wp.array, offset: int, dtype, length: int) -> wp.array:
    """A (length,) array of ``dtype`` over the bytes of the contiguous array ``base`` from ``offset`` [bytes]
    on: the same memory seen as another type (scratch shared by uses that never overlap in time). The view
    keeps ``base`` alive."""
    size = wp.types.type_size_in_bytes(dtype)
    if offset % 8 or offset < 0 or offset + length * size > base.capacity:
        raise ValueError(f"a view of {length} x {size} bytes at {offset} does not fit {base.capacity} bytes")
    view = wp.array(ptr=base.ptr + offset, dtype=dtype, shape=(length,), capacity=length * size, device=base.device)
    # A finalizer holds its arguments until the view is collected: base lives as long as the view.
    weakref.finalize(view, _keep, base).atexit = False
    return view


def _keep(base: wp.array) -> None:
    pass


# ---------------------------------------------------------------------------------------------
# Reference and host code


def all_pairs(positions, radii, flags, skin):
    """Every candidate pair by brute force in float64 (O(N^2)); the reference of the tests.

    Args:
        positions: (N, 3) body centres [m].
        radii: (N,) bounding-sphere radii [m].
        flags: (N,) 0 free, 1 fixed, 2 kinematic.
        skin: Verlet skin [m].

    Returns:
        (a, b): int64 arrays of the pairs with a < b, at least one free and
        ``|x_a - x_b| < r_a + r_b + skin``, sorted by (a, b).
    """
    x = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    free = np.asarray(flags).reshape(-1) == 0
    out_a, out_b = [], []
    for a in range(len(x) - 1):
        d = np.linalg.norm(x[a + 1 :] - x[a], axis=1)
        ok = d < r[a] + r[a + 1 :] + skin
        ok &= free[a] | free[a + 1 :]
        b = np.nonzero(ok)[0] + a + 1
        out_a.append(np.full(len(b), a, dtype=np.int64))
        out_b.append(b.astype(np.int64))
    if not out_a:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    return np.concatenate(out_a), np.concatenate(out_b)


def _distinct_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``rows`` (N, K) uint32 and each row's index among them. One 64-bit hash a row and a
    sort of N numbers (a sort of the rows themselves, ``np.unique(axis=0)``, took 1.9 s at 1e6 bodies); a hash
    that joined two different rows is caught by the check and falls back to that sort."""
    if not len(rows):
        return rows, np.zeros(0, dtype=np.int64)
    h = np.zeros(len(rows), dtype=np.uint64)
    with np.errstate(over="ignore"):
        for k in range(rows.shape[1]):
            h = (h ^ rows[:, k].astype(np.uint64)) * np.uint64(0x9E3779B97F4A7C15)
            h ^= h >> np.uint64(29)
    _, first, index = np.unique(h, return_index=True, return_inverse=True)
    distinct = rows[first]
    if np.array_equal(distinct[index], rows):
        return distinct, index
    distinct, index = np.unique(rows, axis=0, return_inverse=True)
    return distinct, index.reshape(-1)


class BroadPhase:
    """Candidate pairs of bounding spheres with a Verlet skin (see the module docstring).

    Attributes (device arrays; the pair arrays are replaced by new ones when the capacity grows):
        pair_a, pair_b: (capacity,) int32 body indices, a < b, of the first ``pair_count[0]``
            entries; -1 after them (the two halves of one buffer, which a rebuild's key sort takes for its
            values: unspecified during a rebuild, until the keys are unpacked).
        pair_key: (capacity,) int64 keys ``a * num_bodies + b``, strictly increasing over the first
            ``pair_count[0]`` entries (a view of the sort buffer; entries past the count are
            unspecified; the upper half of that buffer is the sort's scratch, and the Morton sort's).
        pair_count: (1,) int32 number of pairs.
        rebuild_flag: (1,) int32, written by :meth:`needs_rebuild`.
        host_build_needed: (1,) int32, sticky: 1 once a device rebuild overflowed or saw changed
            flags; cleared by :meth:`build`.
        device_rebuilds: (1,) int32, device rebuilds since the last host build.
        q_build, radius_build, flags_build: (N,) poses, radii [m] and flags at the last build.
        num_pairs: host int, the count of the last host :meth:`build`.
        capacity: host int.
        num_builds: host int, number of host :meth:`build` calls so far.
    """

    def __init__(
        self,
        num_bodies: int,
        device=None,
        skin: float = 0.0,
        capacity: int | None = None,
        class_ratio: float = 8.0,
        rotation_term: bool = True,
        body_box=None,
        radius_ref: float | None = None,
    ):
        """
        Args:
            num_bodies: N, fixed for the life of the object.
            device: Warp device of every array.
            skin: Verlet skin [m], >= 0.
            capacity: initial pair capacity (default ``max(1024, 8 N)``); grows on overflow.
            class_ratio: radius ratio of one size class (> 1); ``float("inf")`` puts every free
                body in one class (a plain BVH query, every free pair met from both sides).
            rotation_term: count ``radius * rotation angle`` in the motion of a body. Bounding
                spheres about the centre do not move under rotation, so the candidate set never
                needs it; it makes the rebuild test conservative for later uses of the list.
                Non-free bodies always count it (they are tested by their boxes).
            body_box: optional pair of (N, 3) arrays, the lower and upper corners of a box around
                each body's shape in its own frame [m], used to test pairs with non-free bodies; or a triple
                (lower (B, 3), upper (B, 3), box (N,) int): B boxes and each body's index among them (a box per
                shape and the bodies' shapes: no array of N boxes to make and sort out).
            radius_ref: the unit of the size classes [m] (default None: the smallest positive radius
                of the free bodies, found at each build).
        """
        if num_bodies < 0:
            raise ValueError("num_bodies must be >= 0")
        if skin < 0.0:
            raise ValueError("skin must be >= 0")
        if not class_ratio > 1.0:
            raise ValueError("class_ratio must be > 1")
        self.num_bodies = int(num_bodies)
        self.device = wp.get_device(device)
        self.skin = float(skin)
        self.class_ratio = float(class_ratio)
        self.rotation_term = bool(rotation_term)
        n = max(self.num_bodies, 1)
        # Keys up to N*N (the padding sentinel) fit in this many bits.
        self.sentinel = self.num_bodies * self.num_bodies
        self.key_bits = max(1, int(self.sentinel).bit_length())

        dev = self.device
        if body_box is None or not self.num_bodies:
            far = np.full((n, 3), 1.0e30, dtype=np.float32)
            body_box = (-far, far)
        lo, hi = (np.asarray(b, dtype=np.float32).reshape(-1, 3) for b in body_box[:2])
        if len(body_box) == 3 and self.num_bodies:
            box_of = np.asarray(body_box[2]).reshape(-1)
            if box_of.shape != (self.num_bodies,) or lo.shape != hi.shape:
                raise ValueError(
                    f"body_box (lower, upper, box) needs {self.num_bodies} box indices and two (B, 3) arrays, got "
                    f"{box_of.shape[0]} indices and {lo.shape}, {hi.shape}"
                )
            if box_of.size and not (0 <= box_of.min() and box_of.max() < len(lo)):
                raise ValueError(
                    f"body_box: box indices must lie in [0, {len(lo)}), got {box_of.min()}..{box_of.max()}"
                )
            boxes = np.hstack([lo, hi])
        else:
            if lo.shape != (self.num_bodies, 3) and self.num_bodies:
                raise ValueError(f"body_box arrays must have shape ({self.num_bodies}, 3), got {lo.shape}")
            # Each distinct box once (by its bits; the bodies of one shape share theirs) and each body's row of it:
            # 4 bytes a body instead of 24.
            rows = np.ascontiguousarray(np.hstack([lo, hi])).view(np.uint32)
            boxes, box_of = _distinct_rows(rows)
            boxes = np.ascontiguousarray(boxes).view(np.float32)
        self.body_box_lower = wp.array(boxes[:, :3], dtype=wp.vec3, device=dev)
        self.body_box_upper = wp.array(boxes[:, 3:], dtype=wp.vec3, device=dev)
        self.body_box = wp.array(np.asarray(box_of, dtype=np.int32).reshape(-1), dtype=int, device=dev)
        self.box_lower = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.box_upper = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.body_group = wp.zeros(n, dtype=int, device=dev)
        self.q_build = wp.zeros(n, dtype=wp.transform, device=dev)
        self.radius_build = wp.zeros(n, dtype=float, device=dev)
        self.flags_build = wp.zeros(n, dtype=int, device=dev)
        self.group_root = wp.full(NUM_GROUPS, -1, dtype=int, device=dev)
        self.radius_min = wp.zeros(1, dtype=float, device=dev)
        # A fixed reference radius for the size classes, instead of the smallest free radius of these
        # bodies: a rank of a decomposed run gives the whole scene's, so that its classes, and with
        # them which body of a pair is A, are those of the undivided run (polydem.distributed).
        self.radius_ref = None if radius_ref is None else float(radius_ref)
        self.class_max = wp.zeros(1, dtype=int, device=dev)
        self.pair_counter = wp.zeros(1, dtype=int, device=dev)
        self.pair_count = wp.zeros(1, dtype=int, device=dev)
        self.rebuild_flag = wp.ones(1, dtype=int, device=dev)
        self.host_build_needed = wp.zeros(1, dtype=int, device=dev)
        self.device_rebuilds = wp.zeros(1, dtype=int, device=dev)
        # Largest true pair count since the last host build (a device rebuild may overflow with
        # more pairs than the host build that follows finds at the restored poses).
        self.pair_count_peak = wp.zeros(1, dtype=int, device=dev)
        # Spatial order of the query threads (sorted in scratch: _order_scratch).
        self.body_order = wp.array(np.arange(n, dtype=np.int32), dtype=int, device=dev)
        self._own_order_scratch = None
        self.scene_lower = wp.zeros(3, dtype=float, device=dev)
        self.scene_upper = wp.zeros(3, dtype=float, device=dev)
        self.bvh = None
        self.built = False
        self.num_pairs = 0
        self.num_builds = 0
        # Tree renewal (renew_tree): buffers allocated at the first check.
        self._tree_order = None
        self._refits_checked = 0
        self.num_tree_rebuilds = 0
        self.tree_ratio = None
        # The structs the kernels take, of the arrays above (never replaced; the pair arrays, which are, go alone).
        self._build = filled(Build, **{name: getattr(self, name) for name in Build.vars})
        self._counts = filled(Counts, **{name: getattr(self, name) for name in Counts.vars})
        if capacity is None:
            capacity = max(MIN_CAPACITY, DEFAULT_PAIRS_PER_BODY * self.num_bodies)
        self._allocate(int(capacity))

    # -- buffers -----------------------------------------------------------------------------

    def _allocate(self, capacity: int):
        capacity = max(int(capacity), 1)
        if 2 * capacity > MAX_INDEX:
            raise RuntimeError(
                f"the broad phase needs room for {capacity:,} candidate pairs, more than its int32 indices reach "
                f"({MAX_INDEX // 2:,}): step fewer bodies on one device (a decomposed run), or take a smaller skin"
            )
        dev = self.device
        self.capacity = capacity
        # radix_sort_pairs needs 2 * count of keys and values (the upper half is scratch).
        self._key_buffer = wp.zeros(2 * capacity, dtype=wp.int64, device=dev)
        self.pair_key = self._key_buffer[:capacity]
        # The sort's values are never read: it sorts them in pair_a and pair_b (2C int32, one buffer), which
        # nothing reads during a rebuild before the unpack writes them from the sorted keys (8 bytes a pair
        # slot less than values of their own).
        self._pair_ab = wp.full(2 * capacity, -1, dtype=int, device=dev)
        self.pair_a = self._pair_ab[:capacity]
        self.pair_b = self._pair_ab[capacity:]
        self._pairs = filled(PairList, **{name: getattr(self, name) for name in PairList.vars})

    def _check_inputs(self, body_q, body_radius, body_flags=None):
        for name, arr in (("body_q", body_q), ("body_radius", body_radius), ("body_flags", body_flags)):
            if arr is None:
                continue
            if len(arr) != self.num_bodies:
                raise ValueError(f"{name} has {len(arr)} entries, expected {self.num_bodies}")
            if arr.device != self.device:
                raise ValueError(f"{name} lives on {arr.device}, expected {self.device}")

    # -- stages ------------------------------------------------------------------------------

    def _classes(self, body_q, body_radius, body_flags):
        n = self.num_bodies
        spheres = filled(Spheres, radius=body_radius, flags=body_flags)
        dev = self.device
        inv_log = 0.0 if np.isinf(self.class_ratio) else 1.0 / float(np.log(self.class_ratio))
        wp.launch(reset_classes_kernel, dim=1, inputs=[self._build], device=dev)
        if self.radius_ref is None:
            kernel = for_poses(radius_min_kernel, body_q)
            wp.launch(kernel, dim=n, inputs=[body_q, spheres, self._build], device=dev)
        else:
            self.radius_min.fill_(float(self.radius_ref))
        kernel = for_poses(classes_kernel, body_q)
        wp.launch(kernel, dim=n, inputs=[inv_log, body_q, spheres, self._build], device=dev)

    def _spatial_order(self):
        # Query order (body_order): the Morton order of the free bodies at the last (re)build
        # (q_build, flags_build), the others after them.
        n = self.num_bodies
        dev = self.device
        scene = [self.scene_lower, self.scene_upper]
        wp.launch(reset_extent_kernel, dim=1, outputs=scene, device=dev)
        wp.launch(extent_kernel, dim=n, inputs=[self._build], outputs=scene, device=dev)
        morton, order = self._order_scratch()
        wp.launch(morton_kernel, dim=n, inputs=[self._build, *scene], outputs=[morton, order], device=dev)
        wp.utils.radix_sort_pairs(morton, order, n, 0, 31)
        wp.copy(self.body_order, order, count=n)

    def _order_scratch(self):
        # The keys and values (2N int32 each) of the Morton sort: in the upper half of the key buffer, the
        # pair sort's scratch (free from one rebuild's sort to the next one's query, and the Morton order is
        # sorted outside that: at a host build before its query, between steps for the tree), where it has
        # room (capacity >= 2N); else in buffers of their own.
        n = self.num_bodies
        if 2 * n <= self.capacity:
            self._own_order_scratch = None
            half = 8 * self.capacity
            return (
                byte_view(self._key_buffer, half, wp.int32, 2 * n),
                byte_view(self._key_buffer, half + 8 * n, wp.int32, 2 * n),
            )
        if self._own_order_scratch is None:
            dev = self.device
            self._own_order_scratch = (wp.zeros(2 * n, dtype=int, device=dev), wp.zeros(2 * n, dtype=int, device=dev))
        return self._own_order_scratch

    def _bounds(self, body_q, body_radius, body_flags):
        wp.launch(
            for_poses(bounds_kernel, body_q),
            dim=self.num_bodies,
            inputs=[0.5 * self.skin, body_q, filled(Spheres, radius=body_radius, flags=body_flags)],
            outputs=[self._build, self._counts],
            device=self.device,
        )

    def _query(self, body_q, body_radius):
        # Who queries and which group a body sits in follow the flags of the last host build.
        self.pair_counter.zero_()
        wp.launch(
            for_poses(query_pairs_kernel, body_q),
            dim=self.num_bodies,
            inputs=[
                self.bvh.id,
                self.num_bodies,
                self.capacity,
                0.5 * self.skin,
                self.skin,
                body_q,
                body_radius,
                self._build,
            ],
            outputs=[self._counts, self._pairs],
            device=self.device,
        )

    def _group_roots(self):
        wp.launch(group_root_kernel, dim=NUM_GROUPS, inputs=[self.bvh.id, self._build], device=self.device)

    def _finish_count(self):
        wp.launch(finish_count_kernel, dim=1, inputs=[self.capacity], outputs=[self._counts], device=self.device)

    def _unpack(self):
        wp.launch(unpack_pairs_kernel, dim=self.capacity, inputs=[self.num_bodies, self._pairs], device=self.device)

    # -- build -------------------------------------------------------------------------------

    def build(self, body_q, body_radius, body_flags):
        """Find every candidate pair; grow the buffers and query again until all fit.

        Builds a fresh tree with size classes from the current radii and flags. Synchronises with
        the device once per query pass (to read the pair count).

        Args:
            body_q: (N,) wp.transform body poses: position [m], unit quaternion xyzw; or wp.transformd
                (float64: cast in the kernels, the radii grown by the cast's rounding, :func:`body_input`;
                the same poses and radii as :func:`launch_float32_inputs` gives). Every call takes the same
                dtype.
            body_radius: (N,) float32 bounding-sphere radii about the body centres [m].
            body_flags: (N,) int32 flags: 0 free, 1 fixed, 2 kinematic.

        Returns:
            The number of pairs (also in ``num_pairs`` and ``pair_count``).
        """
        self._check_inputs(body_q, body_radius, body_flags)
        self.num_builds += 1
        # Room for what an overflowed device rebuild saw: the host build usually runs from the
        # poses at the start of a redone chunk, where fewer pairs may fit than the chunk will need
        # (without this the redo would overflow again, for ever).
        peak = int(self.pair_count_peak.numpy()[0])
        if peak > self.capacity:
            self._allocate(peak + peak // 4 + 64)
        self.pair_count_peak.zero_()
        self.host_build_needed.zero_()
        self.rebuild_flag.zero_()
        self.device_rebuilds.zero_()
        if self.num_bodies == 0:
            self.pair_count.zero_()
            self.num_pairs = 0
            self.built = True
            return 0
        self._classes(body_q, body_radius, body_flags)
        self._bounds(body_q, body_radius, body_flags)
        self._spatial_order()
        self._refits_checked = 0
        if self._tree_order is not None:
            wp.copy(self._tree_order, self.body_order)
        if self.bvh is None:
            self.bvh = wp.Bvh(self.box_lower, self.box_upper, groups=self.body_group)
        else:
            self.bvh.rebuild()
        self._group_roots()
        while True:
            self._query(body_q, body_radius)
            count = int(self.pair_counter.numpy()[0])
            if count <= self.capacity:
                break
            # The true count is known: grow with some headroom and query again.
            self._allocate(count + count // 4 + 64)
        self._finish_count()
        self.device_rebuilds.zero_()
        if count > 0:
            wp.utils.radix_sort_pairs(self._key_buffer, self._pair_ab, count, 0, self.key_bits)
        self._unpack()
        self.num_pairs = count
        self.built = True
        return count

    def rebuild_on_device(self, body_q, body_radius, body_flags):
        """Rebuild without host synchronisation or allocation (usable in a conditional graph node).

        Needs a previous :meth:`build`, whose tree topology, size classes, flags, query order and
        capacity it keeps: it refits the tree to the new boxes, queries and sorts the whole
        capacity with padded keys. The pairs are exact (for the flags of the last host build). When they exceed
        the capacity, ``pair_count`` is clamped, the kept pairs are an arbitrary subset, and the
        sticky ``host_build_needed`` flag is raised; changed flags raise it too.
        """
        if not self.built:
            raise RuntimeError("rebuild_on_device needs a previous host build()")
        if self.num_bodies == 0:
            return
        self._bounds(body_q, body_radius, body_flags)
        self.bvh.refit()
        self._query(body_q, body_radius)
        self._finish_count()
        wp.launch(pad_keys_kernel, dim=self.capacity, inputs=[self.sentinel, self._pairs], device=self.device)
        wp.utils.radix_sort_pairs(self._key_buffer, self._pair_ab, self.capacity, 0, self.key_bits)
        self._unpack()

    # -- tree renewal (host, between steps) -----------------------------------------------------

    def _tree_buffers(self):
        if self._tree_order is not None:
            return
        dev = self.device
        leaves = -(-max(self.num_bodies, 1) // TREE_BRANCHING)
        parents = -(-leaves // TREE_BRANCHING)
        self._tree_order = wp.clone(self.body_order)
        self._tree_blocks = tuple(
            filled(Boxes, lower=wp.empty(m, dtype=wp.vec3, device=dev), upper=wp.empty(m, dtype=wp.vec3, device=dev))
            for m in (leaves, parents)
        )
        self._tree_cost = wp.zeros(2, dtype=wp.float64, device=dev)

    def _order_cost(self, order, slot):
        # Sum of the box areas of every node of the implicit tree over ``order`` into tree_cost[slot].
        n = self.num_bodies
        dev = self.device
        m = -(-n // TREE_BRANCHING)
        src, dst = self._tree_blocks
        wp.launch(leaf_blocks_kernel, dim=m, inputs=[n, slot, order, self._build, src, self._tree_cost], device=dev)
        while m > 1:
            parents = -(-m // TREE_BRANCHING)
            wp.launch(merge_blocks_kernel, dim=parents, inputs=[m, slot, src, dst, self._tree_cost], device=dev)
            src, dst = dst, src
            m = parents

    def tree_degradation(self):
        """How much refitting has degraded the tree: its cost over that of a fresh tree (synchronises).

        A BVH's query cost grows with the surface areas of its nodes' boxes. The tree stands for an
        implicit one over the free bodies in the Morton order of the last tree build (``TREE_BRANCHING``
        children per node, leaves the bodies' current boxes); the cost is the sum of the node box
        areas, and the ratio is against the same sum over the Morton order of the current boxes. About
        1 right after a build; it grows as bodies move past one another. Also sets the query order
        (``body_order``) to the current Morton order. Returns a host float (1.0 before a build).
        """
        if not self.built or self.bvh is None or self.num_bodies == 0:
            return 1.0
        self._tree_buffers()
        self._tree_cost.zero_()
        self._order_cost(self._tree_order, 0)
        self._spatial_order()
        self._order_cost(self.body_order, 1)
        old, fresh = (float(v) for v in self._tree_cost.numpy())
        return old / fresh if fresh > 0.0 else 1.0

    def _rebuild_tree(self):
        # From the boxes of the last (re)build, in place: a captured graph that refits and queries
        # this tree stays valid (Warp's LBVH rebuild reuses its buffers); the group roots move.
        self.bvh.rebuild()
        self._group_roots()
        wp.copy(self._tree_order, self.body_order)
        self.num_tree_rebuilds += 1

    def rebuild_tree(self):
        """Host: build the tree afresh over the boxes of the last (re)build, keeping the pair list.

        Not for a graph capture (Warp's tree build allocates scratch memory). The pair list, its
        order and the Verlet test are unchanged; the next device rebuild refits the new tree.
        """
        if not self.built or self.bvh is None or self.num_bodies == 0:
            return
        self._tree_buffers()
        self._spatial_order()
        self._rebuild_tree()

    def renew_tree(self, ratio=TREE_REBUILD_RATIO):
        """Host, between steps: rebuild the tree when device rebuilds since the last check degraded it.

        Args:
            ratio: rebuild when :meth:`tree_degradation` exceeds this; 0 rebuilds at every check after a
                device rebuild; None never (the tree of the last host build is refitted for ever).

        Returns:
            True when the tree was rebuilt. The last ratio measured is in ``tree_ratio``. Synchronises
            (reads the device rebuild counter); measures only when a device rebuild happened since the
            last check.
        """
        if ratio is None or not self.built or self.bvh is None or self.num_bodies == 0:
            return False
        refits = int(self.device_rebuilds.numpy()[0])
        if refits == self._refits_checked:
            return False
        self._refits_checked = refits
        self.tree_ratio = self.tree_degradation()
        if not self.tree_ratio > ratio:
            return False
        self._rebuild_tree()
        return True

    # -- Verlet test -------------------------------------------------------------------------

    def needs_rebuild(self, body_q, body_radius, body_flags=None):
        """Device flag (1,) int32: 1 when some body may have left its skin since the last build.

        A body counts as moved by ``|x - x_build| + r * angle + max(r - r_build, 0)`` [m] (the
        angle of the rotation since the build, when ``rotation_term``); the flag is raised when
        that exceeds skin / 2 for any body, or when ``body_flags`` (optional) differ from the
        build's. Before the first build the flag is 1. No host synchronisation.
        """
        if not self.built:
            self.rebuild_flag.fill_(1)
            return self.rebuild_flag
        self._check_inputs(body_q, body_radius, body_flags)
        self.rebuild_flag.zero_()
        if self.num_bodies == 0:
            return self.rebuild_flag
        flags = self.flags_build if body_flags is None else body_flags
        wp.launch(
            for_poses(needs_rebuild_kernel, body_q),
            dim=self.num_bodies,
            inputs=[
                body_q,
                filled(Spheres, radius=body_radius, flags=flags),
                self._build,
                0.5 * self.skin,
                int(self.rotation_term),
            ],
            outputs=[self.rebuild_flag],
            device=self.device,
        )
        return self.rebuild_flag

    def update(self, body_q, body_radius, body_flags):
        """Host convenience: :meth:`build` only when needed; returns True when it rebuilt."""
        if self.built:
            flag = self.needs_rebuild(body_q, body_radius, body_flags)
            if int(flag.numpy()[0]) == 0:
                return False
        self.build(body_q, body_radius, body_flags)
        return True

    def update_on_device(self, body_q, body_radius, body_flags):
        """Rebuild test and conditional :meth:`rebuild_on_device`, all on the device.

        Branches on the device flag with ``wp.capture_if``, so it can be recorded inside
        ``wp.ScopedCapture`` (a conditional graph node; CUDA 12.4+). Outside a capture Warp reads
        the flag on the host and runs the branch directly. Needs a previous :meth:`build`; check
        :meth:`check_host_build_needed` now and then outside the graph.
        """
        if not self.built:
            raise RuntimeError("update_on_device needs a previous host build()")
        self.needs_rebuild(body_q, body_radius, body_flags)
        wp.capture_if(
            self.rebuild_flag,
            on_true=self.rebuild_on_device,
            body_q=body_q,
            body_radius=body_radius,
            body_flags=body_flags,
        )

    def check_host_build_needed(self):
        """Host: True when a device rebuild overflowed or saw changed flags (then :meth:`build`)."""
        return bool(int(self.host_build_needed.numpy()[0]))

    # -- host views --------------------------------------------------------------------------

    def pairs_numpy(self):
        """(a, b, key) numpy copies of the current pairs (synchronises)."""
        n = int(self.pair_count.numpy()[0])
        return self.pair_a.numpy()[:n], self.pair_b.numpy()[:n], self.pair_key.numpy()[:n]
