"""The pair list after a broad-phase rebuild: what each pair carries, found again by its key, and
the order the gather walks.

A rebuild (:class:`polydem.contacts.Contacts`) replaces the candidate pairs. Each pair's history
(turning volume, friction spring) and, while an interval of contact forces is averaged, its sums
(:class:`~polydem.kernels.forces.ContactSums`) go with its key ``a * N + b``: a pair found again
keeps them, a new pair starts from zero, and the sums of a pair that left the list after it was in
contact are appended to a list of retired pairs. The gather (:mod:`polydem.kernels.forces`) then
needs each body's range in the pairs sorted by A (the keys) and by B (sorted here, stably on int32 keys
``b``: the slots are in increasing ``a * N + b``, so the pairs of one B stay in increasing A, the order the
gather sums them in).

No floating-point arithmetic: every kernel is deterministic by construction.
"""

import functools
from typing import Any, Protocol

import warp as wp
from polydem.kernels.forces import ContactSums
from polydem.kernels.structs import arrays, filled, make_struct


class PairHistoryArrays(Protocol):
    """A pair list's history by key (:class:`polydem.contacts.PairHistory`): ``key`` (C,) int64, increasing
    over the first ``count[0]`` entries; ``xi`` (C,) vec3 springs ((1,) without friction); ``turn`` (C,)."""

    key: wp.array
    count: wp.array
    xi: wp.array
    turn: wp.array


@wp.func
def lower_bound(keys: wp.array(dtype=Any), count: int, key: Any):
    # The first of the first count (increasing) keys that is not below key: int64 pair keys, int32 body keys.
    lo = int(0)
    hi = count
    while lo < hi:
        # Not (lo + hi) // 2: that overflows int32 past 2^30 pairs.
        mid = lo + (hi - lo) // 2
        if keys[mid] < key:
            lo = mid + 1
        else:
            hi = mid
    return lo


@wp.func
def find_key(keys: wp.array(dtype=wp.int64), count: int, key: wp.int64):
    # The index of key among the first count (increasing) keys, -1 where it is not there.
    j = lower_bound(keys, count, key)
    if j < count and keys[j] == key:
        return j
    return -1


@wp.func
def copy_sums(src: ContactSums, j: int, dst: ContactSums, k: int):
    # Contact j's sums of src into slot k of dst (a rebuild moves or retires them).
    dst.force[k] = src.force[j]
    dst.tangential[k] = src.tangential[j]
    dst.normal[k] = src.normal[j]
    dst.point[k] = src.point[j]
    dst.steps[k] = src.steps[j]


@wp.kernel(enable_backward=False)
def body_ranges_kernel(
    # Model
    num_bodies: int,
    # State in
    pair_key: wp.array(dtype=wp.int64),
    keys_b: wp.array(dtype=int),
    pair_count: wp.array(dtype=int),
    # Out
    body_pairs_a: wp.array(dtype=wp.vec2i),
    body_pairs_b: wp.array(dtype=wp.vec2i),
):
    """Each body's ranges in the pairs sorted by (a, b) and in those sorted by b (then by a)."""
    i = wp.tid()
    count = pair_count[0]
    n = wp.int64(num_bodies)
    lo = wp.int64(i) * n
    hi = lo + n
    body_pairs_a[i] = wp.vec2i(lower_bound(pair_key, count, lo), lower_bound(pair_key, count, hi))
    # i + 1 <= num_bodies < 2^31 (launch_body_ranges checks).
    body_pairs_b[i] = wp.vec2i(lower_bound(keys_b, count, i), lower_bound(keys_b, count, i + 1))


SortKeys = make_struct(
    "SortKeys",
    **arrays(pair_a=int, pair_b=int, count=int, body_shape=int, pair_class=int),
    by_class=int,
    num_shapes=int,
    sentinel=int,
)
"""What the pair slots are sorted by: body B (``by_class`` 0; ``body_shape`` and ``pair_class`` unread), or the
cost class of the pair's shapes, ``pair_class[shape_a * num_shapes + shape_b]``; past ``count[0]``, the
``sentinel`` (above every key)."""


@wp.kernel(enable_backward=False)
def sort_keys_kernel(src: SortKeys, keys: wp.array(dtype=int), order: wp.array(dtype=int)):
    """The key of each pair slot (:data:`SortKeys`) and the identity order (the values sorted with them)."""
    p = wp.tid()
    order[p] = p
    if p >= src.count[0]:
        keys[p] = src.sentinel
    elif src.by_class != 0:
        keys[p] = src.pair_class[src.body_shape[src.pair_a[p]] * src.num_shapes + src.body_shape[src.pair_b[p]]]
    else:
        keys[p] = src.pair_b[p]


@functools.cache
def make_contact_bit_kernel(scalar):
    """The kernel that turns each listed pair's cost class c (of ``top + 1``) into the key ``2 (top - c)`` where
    the pair touches (a turning volume above zero, in ``scalar``), ``2 (top - c) + 1`` where it does not: the
    costliest work first."""

    @wp.kernel(enable_backward=False, module="unique")
    def contact_bit_kernel(
        # State in
        turn: wp.array(dtype=scalar),
        count: wp.array(dtype=int),
        top: int,
        sentinel: int,
        # Out
        keys: wp.array(dtype=int),
    ):
        p = wp.tid()
        if p >= count[0]:
            keys[p] = sentinel
        elif turn[p] > scalar(0.0):
            keys[p] = 2 * (top - keys[p])
        else:
            keys[p] = 2 * (top - keys[p]) + 1

    return contact_bit_kernel


@wp.kernel(enable_backward=False)
def first_keys_kernel(
    # In
    pair_a: wp.array(dtype=int),
    pair_b: wp.array(dtype=int),
    count: wp.array(dtype=int),
    body_first: wp.array(dtype=wp.int32),
    num_keys: int,
    # In/out: each pair's key, raised by num_keys unless it has a flagged body; out: (1,) the pairs that have one
    keys: wp.array(dtype=int),
    first_count: wp.array(dtype=int),
):
    """The pairs of a split step's first part (a body flagged in ``body_first``) before all the others."""
    p = wp.tid()
    if p >= count[0]:
        keys[p] = 2 * num_keys
    elif body_first[pair_a[p]] + body_first[pair_b[p]] > 0:
        wp.atomic_add(first_count, 0, 1)
    else:
        keys[p] = keys[p] + num_keys


@functools.cache
def make_remap_history_kernel(scalar):
    """The kernel that carries the pair history (in ``scalar``) over a rebuild."""
    vec3 = wp.types.vector(3, scalar)

    @wp.kernel(enable_backward=False, module="unique")
    def remap_history_kernel(
        # State in
        old_key: wp.array(dtype=wp.int64),
        old_count: wp.array(dtype=int),
        old_xi: wp.array(dtype=vec3),
        old_turn: wp.array(dtype=scalar),
        new_key: wp.array(dtype=wp.int64),
        new_count: wp.array(dtype=int),
        friction: int,
        # Out
        new_xi: wp.array(dtype=vec3),
        new_turn: wp.array(dtype=scalar),
    ):
        """Carries each pair's history (turning volume; friction spring, with ``friction``) over a
        rebuild, matched by the pair's key."""
        p = wp.tid()
        xi = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        turn = scalar(0.0)
        if p < new_count[0]:
            j = find_key(old_key, old_count[0], new_key[p])
            if j >= 0:
                turn = old_turn[j]
                if friction != 0:
                    xi = old_xi[j]
        new_turn[p] = turn
        if friction != 0:
            new_xi[p] = xi

    return remap_history_kernel


@wp.kernel(enable_backward=False)
def carry_sums_kernel(
    # State in: the list before the rebuild, with its sums, and the list after it
    old_key: wp.array(dtype=wp.int64),
    old_count: wp.array(dtype=int),
    old_sums: ContactSums,
    new_key: wp.array(dtype=wp.int64),
    new_count: wp.array(dtype=int),
    # Out: the sums of the list after the rebuild
    new_sums: ContactSums,
    # In/out: the retired pairs
    retired_key: wp.array(dtype=wp.int64),
    retired: ContactSums,
    retired_count: wp.array(dtype=int),
    overflow: wp.array(dtype=int),
):
    """Carries the pairs' sums of an averaging interval over a rebuild, one thread per slot p. The old
    list's pair p, if the rebuild drops it after it was in contact in the interval, is appended to the
    retired pairs, so that it counts in the average: the slots are taken atomically, so entries of
    different keys may come in any order, but those of one key are in the order of the rebuilds (one
    launch each); past the capacity, ``overflow`` is set (the chunk is redone with more room). The new
    list's pair p gets the sums of the old list's pair of its key (zero for a new pair and past the count)."""
    p = wp.tid()
    if p < old_count[0] and old_sums.steps[p] != 0:
        key = old_key[p]
        if find_key(new_key, new_count[0], key) < 0:
            slot = wp.atomic_add(retired_count, 0, 1)
            if slot >= retired_key.shape[0]:
                wp.atomic_max(overflow, 0, 1)
            else:
                retired_key[slot] = key
                copy_sums(old_sums, p, retired, slot)
    if p >= new_sums.steps.shape[0]:
        return
    if p < new_count[0]:
        j = find_key(old_key, old_count[0], new_key[p])
        if j >= 0:
            copy_sums(old_sums, j, new_sums, p)
            return
    zero3 = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    new_sums.force[p] = zero3
    new_sums.tangential[p] = zero3
    new_sums.normal[p] = wp.float64(0.0)
    new_sums.point[p] = zero3
    new_sums.steps[p] = 0


# ---------------------------------------------------------------------------------------------
# Launch functions
# ---------------------------------------------------------------------------------------------


def launch_remap_history(
    *,
    old: PairHistoryArrays,
    new_key: wp.array,
    new_count: wp.array,
    friction: bool,
    new_xi: wp.array,
    new_turn: wp.array,
) -> None:
    """Give each pair of the list ``new_key`` (its first ``new_count[0]`` entries) the history of
    ``old`` under the same key, into ``new_xi`` (with ``friction``) and ``new_turn``; zero for a new
    pair and past the count. The kernel is in the scalar of ``new_turn``."""
    wp.launch(
        make_remap_history_kernel(new_turn.dtype),
        dim=new_turn.shape[0],
        inputs=[old.key, old.count, old.xi, old.turn, new_key, new_count, int(friction)],
        outputs=[new_xi, new_turn],
        device=new_turn.device,
    )


def launch_carry_sums(
    *,
    old_key: wp.array,
    old_count: wp.array,
    old_sums: ContactSums,
    new_key: wp.array,
    new_count: wp.array,
    new_sums: ContactSums,
    retired_key: wp.array,
    retired: ContactSums,
    retired_count: wp.array,
    overflow: wp.array,
) -> None:
    """Give each pair of ``new_key`` the sums of ``old_sums`` under the same key (zero for a new pair), and
    append to ``retired`` the sums of each pair of ``old_key`` that is not in ``new_key`` and was in contact
    in the interval (``overflow`` set where ``retired_key`` has no room left)."""
    wp.launch(
        carry_sums_kernel,
        dim=max(old_sums.steps.shape[0], new_sums.steps.shape[0]),
        inputs=[old_key, old_count, old_sums, new_key, new_count],
        outputs=[new_sums, retired_key, retired, retired_count, overflow],
        device=new_key.device,
    )


def launch_body_ranges(
    *,
    num_bodies: int,
    pair_b: wp.array,
    pair_key: wp.array,
    pair_count: wp.array,
    keys_b: wp.array,
    by_b: wp.array,
    body_pairs_a: wp.array,
    body_pairs_b: wp.array,
    pair_by_b: wp.array | None = None,
) -> None:
    """Order the pairs (C of ``pair_b``'s length) by their B body and find each body's ranges.

    ``keys_b``, ``by_b``: (2C,) int32 each, the radix sort's keys and values (the upper halves are its
    scratch); ``by_b[:C]`` ends as the pair indices ordered by B, and within one B in increasing slot, so
    by A as the keys ``a * N + b`` of ``pair_key`` are increasing. ``keys_b`` holds nothing between calls.
    ``body_pairs_a``, ``body_pairs_b``: (N,) vec2i, each body's range in the pairs by A (``pair_key``) and
    by B. ``pair_by_b``: (C,) int32, where given, gets a copy of ``by_b[:C]`` (then ``by_b`` holds nothing
    between calls either: both may be scratch shared with other uses)."""
    capacity = pair_b.shape[0]
    device = pair_b.device
    # The sentinel N must exceed every body index and fit an int32 key.
    if num_bodies > 2**31 - 1:
        raise ValueError(f"{num_bodies} bodies: the pair list takes at most 2^31 - 1")
    if keys_b.dtype != wp.int32 or keys_b.size < 2 * capacity or by_b.size < 2 * capacity:
        raise ValueError(f"keys_b and by_b must be int32 arrays of at least {2 * capacity} entries")
    src = filled(
        SortKeys, pair_a=pair_b, pair_b=pair_b, count=pair_count, body_shape=pair_b, pair_class=pair_b, by_class=0,
        num_shapes=0, sentinel=int(num_bodies),
    )  # fmt: skip
    wp.launch(sort_keys_kernel, dim=capacity, inputs=[src], outputs=[keys_b, by_b], device=device)
    # Stable (Warp's radix sort: LSD counting passes on the CPU, CUB on CUDA): equal keys b keep the
    # increasing slot order the values start in. Bits up to the sentinel only.
    wp.utils.radix_sort_pairs(keys_b, by_b, capacity, 0, max(1, int(num_bodies).bit_length()))
    wp.launch(
        body_ranges_kernel,
        dim=num_bodies,
        inputs=[num_bodies, pair_key, keys_b, pair_count],
        outputs=[body_pairs_a, body_pairs_b],
        device=device,
    )
    if pair_by_b is not None:
        wp.copy(pair_by_b, by_b, count=capacity)


@wp.kernel(enable_backward=False)
def costly_count_kernel(keys: wp.array(dtype=int), num_keys: int, below: int, costly: wp.array(dtype=int)):
    """How many of the sorted ``keys`` (the first ``num_keys``) are below ``below``: one thread."""
    costly[0] = lower_bound(keys, num_keys, below)


def launch_thread_order(
    *,
    body_shape: wp.array,
    pair_class: wp.array,
    num_classes: int,
    pair_a: wp.array,
    pair_b: wp.array,
    pair_count: wp.array,
    keys: wp.array,
    order: wp.array,
    pair_thread: wp.array,
    pair_turn: wp.array | None = None,
    body_first: wp.array | None = None,
    first_count: wp.array | None = None,
    costly_from: int | None = None,
    costly_count: wp.array | None = None,
) -> None:
    """Which pair each thread of the pair kernel takes: the pairs by cost class, so that the threads of a warp
    clip shapes of like face counts (a warp waits for its slowest thread), and within a class in slot order.
    With ``pair_turn`` (C,) (the turning volumes the rebuild carried over) each class is split in two, and the
    costliest work comes first: the classes from the costliest down, in each the pairs that touch (they clip
    their faces) before those that do not (they stop at their first separating plane). A warp of both kinds
    waits for the clipping; and blocks handed out costliest first leave the cheap ones to fill the last wave of
    the launch, where the other way round its slowest blocks ran last, alone on the GPU.

    ``pair_class``: (S * S,) int32, the class of a pair of shapes (A's shape * S + B's), 0 to ``num_classes`` - 1.
    ``keys``, ``order``: (2C,) int32 each, the radix sort's keys and values (scratch). ``pair_thread``: (C,)
    int32, gets the pair of each thread: the first ``pair_count`` threads take the listed pairs, the rest the
    empty slots. Each pair's arithmetic is its own, so the results do not depend on this order.
    With ``body_first`` (N,) int32 (a split step, :meth:`polydem.simulation.Stepper.split_at`): the pairs with a
    flagged body first, each part so grouped, and their number into ``first_count`` (1,) int32: the first part
    of the step takes threads 0 to ``first_count`` - 1, the second the rest.
    With ``pair_turn``, no ``body_first`` and ``costly_count`` (1,) int32: how many pairs of the classes from
    ``costly_from`` up (which the order puts first) into ``costly_count``: the pairs the pair kernel spreads over
    more lanes (:func:`polydem.kernels.forces.make_contact_kernels`' ``spread``)."""
    capacity = pair_a.shape[0]
    if keys.dtype != wp.int32 or keys.size < 2 * capacity or order.size < 2 * capacity:
        raise ValueError(f"keys and order must be int32 arrays of at least {2 * capacity} entries")
    src = filled(
        SortKeys, pair_a=pair_a, pair_b=pair_b, count=pair_count, body_shape=body_shape, pair_class=pair_class,
        by_class=1, num_shapes=int(round(pair_class.shape[0] ** 0.5)), sentinel=int(num_classes),
    )  # fmt: skip
    wp.launch(sort_keys_kernel, dim=capacity, inputs=[src], outputs=[keys, order], device=pair_a.device)
    num_keys = int(num_classes)
    if pair_turn is not None:
        num_keys *= 2
        wp.launch(
            make_contact_bit_kernel(pair_turn.dtype),
            dim=capacity,
            inputs=[pair_turn, pair_count, int(num_classes) - 1, num_keys],
            outputs=[keys],
            device=pair_a.device,
        )
    if body_first is not None:
        first_count.zero_()
        wp.launch(
            first_keys_kernel,
            dim=capacity,
            inputs=[pair_a, pair_b, pair_count, body_first, num_keys],
            outputs=[keys, first_count],
            device=pair_a.device,
        )
        num_keys *= 2
    # Stable: the pairs of one key keep their slot order, and the empty slots (the sentinel) come last.
    wp.utils.radix_sort_pairs(keys, order, capacity, 0, max(1, num_keys.bit_length()))
    wp.copy(pair_thread, order, count=capacity)
    if costly_count is not None and pair_turn is not None and body_first is None:
        # Class c's keys are 2 (top - c) and 2 (top - c) + 1: those of the classes from costly_from up lie below
        # 2 (top - costly_from) + 2 (none where costly_from is num_classes).
        below = 2 * (int(num_classes) - 1 - int(costly_from)) + 2
        wp.launch(costly_count_kernel, dim=1, inputs=[keys, capacity, below], outputs=[costly_count],
                  device=pair_a.device)  # fmt: skip
