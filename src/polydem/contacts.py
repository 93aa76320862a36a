"""Contacts: the candidate pairs of the broad phase, and the history each pair carries.

A pair's history is its friction spring and the turning volume of the normal hysteresis
(kernels/forces.py). The pair list changes at every broad-phase rebuild; the history goes with the
pair's key ``a * N + b`` (kernels/pairlist.py ``launch_remap_history``), so a pair that persists
across a rebuild, a redone chunk or a checkpoint keeps it, and a new pair starts from zero.

The wall contacts' history is per (body, wall), has no list to follow, and lives in the
:class:`~polydem.state.State`.

While an interval of contact forces is averaged (:class:`ContactAverage`, from
``Simulation.start_contact_average``), each pair also carries its sums of the force, by key like its
history; a pair that a rebuild drops after it was in contact leaves its sums in a list of retired
pairs, so that a contact that ended still counts in the average.

The history is in the contact scalar of the model's precision (float32 in "float32" and "mixed",
float64 in "float64"). The broad phase runs in float32 in every precision: with float64 poses its kernels
cast the centres where they read them and grow the radii by the rounding of the cast
(``kernels/broadphase.py`` ``body_input``), so no candidate pair is missed; no float32 copy of the poses is
kept.

Memory: a pair slot costs 72 bytes in "float32" and "mixed". 36 hold the list from one step to the next: its
bodies (``pair_a``, ``pair_b``) and key, its history and its place in the order by B; 8 are the broad phase's
key-sort scratch; 28 are a scratch buffer (:attr:`Contacts.scratch_bytes`) that three sets of per-slot arrays
share, each needed only for a moment: the force stage's wrench and energy per pair (``pair_force``,
``pair_torque_a``, ``pair_dissipated``: written by the pair kernel, read by the gather and the motions' force
sums of the same step, dead once the step ends), the history of the list before a rebuild (``previous``: kept
at the start of the rebuild, read when the history is carried onto the new list, dead after it), and the keys
and values of the sort by B that ends the rebuild (after the carry). A rebuild runs between two force stages,
so the three never meet.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from polydem.kernels.broadphase import BroadPhase, byte_view
from polydem.kernels.forces import ContactSums
from polydem.kernels.pairlist import (
    launch_body_ranges,
    launch_carry_sums,
    launch_remap_history,
    launch_thread_order,
)
from polydem.kernels.precision import numpy_dtype
from polydem.kernels.structs import filled, pairs_struct

if TYPE_CHECKING:
    from polydem.model import Model

__all__ = ["ContactAverage", "Contacts", "PairHistory", "contact_sums"]


class PairHistory:
    """The history of a pair list, by key (device arrays): what a rebuild, a redo and a checkpoint carry.

    Attributes:
        key: (C,) int64 pair keys ``a * N + b`` (a < b), increasing over the first ``count[0]`` entries
            (C >= count: the capacity of a :class:`Contacts`, or the room of a snapshot's copy).
        xi: (C,) vec3 friction springs [m]; (1,) when the scene has no friction.
        turn: (C,) turning volumes [m^3].
        (``xi`` and ``turn`` in float32, or float64 in the "float64" precision.)
        count: (1,) int32 number of pairs.
    """

    FIELDS = ("key", "xi", "turn", "count")

    def __init__(self, key: wp.array, xi: wp.array, turn: wp.array, count: wp.array) -> None:
        self.key = key
        self.xi = xi
        self.turn = turn
        self.count = count

    @classmethod
    def zeros(cls, capacity: int, friction: bool, device: wp.DeviceLike, scalar: type = wp.float32) -> PairHistory:
        return cls(
            wp.zeros(capacity, dtype=wp.int64, device=device),
            wp.zeros(capacity if friction else 1, dtype=wp.types.vector(3, scalar), device=device),
            wp.zeros(capacity, dtype=scalar, device=device),
            wp.zeros(1, dtype=int, device=device),
        )

    @classmethod
    def from_numpy(
        cls,
        key: np.ndarray,
        xi: np.ndarray,
        turn: np.ndarray,
        friction: bool,
        device: wp.DeviceLike,
        scalar: type = wp.float32,
    ) -> PairHistory:
        """The history of ``len(key)`` pairs from host arrays (``xi`` is ignored without ``friction``),
        in ``scalar``."""
        count = len(key)
        cap = max(count, 1)
        k = np.zeros(cap, dtype=np.int64)
        k[:count] = key
        x = np.zeros((cap, 3), dtype=numpy_dtype(scalar))
        if friction and count:
            x[:count] = xi
        t = np.zeros(cap, dtype=numpy_dtype(scalar))
        t[:count] = turn
        return cls(
            wp.array(k, dtype=wp.int64, device=device),
            wp.array(x, dtype=wp.types.vector(3, scalar), device=device),
            wp.array(t, dtype=scalar, device=device),
            wp.array(np.array([count], dtype=np.int32), dtype=int, device=device),
        )

    def copy(self) -> PairHistory:
        return PairHistory(*(wp.clone(getattr(self, k)) for k in self.FIELDS))

    def assign(self, other: PairHistory) -> None:
        for k in self.FIELDS:
            wp.copy(getattr(self, k), getattr(other, k))

    def same_shapes(self, other: PairHistory) -> bool:
        return all(getattr(self, k).shape == getattr(other, k).shape for k in self.FIELDS)


THREAD_ORDERS = ("cost", "contact")
"""The ways :class:`Contacts` can group the pair kernel's threads (see its ``thread_order``)."""

THREAD_ORDER = "contact"
"""The grouping ``thread_order=True`` means (measured against "cost" in BENCHMARKS.md 20)."""


def pair_cost_classes(model) -> tuple[np.ndarray, int]:
    """(S, S) int32 cost class of each pair of the model's S shapes, and the number of classes: the products of
    the two shapes' face counts (a compound grain: its parts' faces together), ranked. The pair kernel clips
    each face of one shape by the other's planes, so its work grows with that product."""
    cost = pair_face_products(model)
    levels, rank = np.unique(cost, return_inverse=True)
    return rank.reshape(cost.shape).astype(np.int32), len(levels)


def pair_face_products(model) -> np.ndarray:
    """(S, S) int64: the products of the face counts of each pair of the model's S shapes (a compound grain: its
    parts' faces together), the cost of clipping them (:func:`pair_cost_classes` ranks them)."""
    from polydem.compound import convex_parts

    faces = np.array([sum(part.num_faces for part, _, _ in convex_parts(s)) for s in model.shapes.shapes], np.int64)
    return np.outer(faces, faces)


COSTLY_FACES = 64
"""A pair of shapes whose face counts multiply to more than this is costly: the pair kernel spreads such pairs over
more lanes of a warp (kernels/forces.py ``SPREAD_LANES``). A 20-vertex rock's pairs are (36 faces: 144 with a
tetrahedron), a cube's with a cube or a tetrahedron are not (36, 24): 32 different rock pairs took a warp 3.1x one
pair's time on an H200, cube pairs 1.8x (BENCHMARKS.md 28)."""


def costly_class_from(model) -> int:
    """The first cost class (:func:`pair_cost_classes`' rank) of the pairs of shapes above :data:`COSTLY_FACES`."""
    return int(np.searchsorted(np.unique(pair_face_products(model)), COSTLY_FACES, side="right"))


class Contacts:
    """The candidate pair list (a Verlet list with a skin) and its history, with the per-pair buffers of a step.

    Args:
        model: the :class:`~polydem.model.Model`.
        skin: Verlet skin [m].
        body_box: (lower, upper), two (N, 3) arrays: a box around each body's shape in its own frame [m]; or
            (lower, upper, box): B boxes and each body's index among them (see :class:`BroadPhase`).
        capacity: initial number of pairs there is room for (grows on overflow).
        radius_ref: the unit of the broad phase's size classes [m] (``RunSettings.radius_ref``; None:
            the smallest free radius of the model's bodies).
        thread_order: give the pair kernel's threads the pairs grouped (:attr:`pair_thread`): ``"cost"`` by the
            cost class of their shapes, where the model's shapes differ in cost (else nothing to group:
            :attr:`thread_order` stays False); ``"contact"`` by cost class from the costliest down and, within a
            class, the pairs that touched when the list was built (a carried turning volume) first;
            True: :data:`THREAD_ORDER`; False: slot order.

    Attributes (device arrays; C = :attr:`capacity`, N bodies):
        broadphase: the :class:`~polydem.kernels.broadphase.BroadPhase`, which owns the pair list
            ``pair_a``, ``pair_b`` (C,) int32, ``pair_key`` (C,) int64, ``pair_count`` (1,) int32.
        pair_xi: (C,) vec3 friction springs [m] ((1,) without friction).
        pair_turn: (C,) turning volumes [m^3].
        pair_force: (C,) vec3 contact force of the pair in the step's force stage [N] (kernels/forces.py).
        pair_torque_a: (C,) vec3 torque of the pair on body A about its centroid [N m].
        pair_dissipated: (C,) energy the pair dissipated in that stage [J].
        (These five in the model's contact scalar: float32 in "float32" and "mixed", float64 in
        "float64". The last three live in the scratch buffer (module docstring): valid from the pair
        kernel of a step to its end, overwritten by the next rebuild.)
        pair_by_b: (C,) int32 pair indices ordered by body B.
        pair_thread: (C,) int32 the pair each thread of the pair kernel takes, the pairs ordered by the cost
            class of their two shapes (the product of their face counts; with ``"contact"`` from the costliest
            down, then the pairs that touched at the rebuild first), stably; (1,) without thread_order.
        thread_order: host bool, whether the pair kernel reads :attr:`pair_thread`.
        thread_grouping: host str, how the threads are grouped: "slot" (not at all), "cost" or "contact".
        body_pairs_a, body_pairs_b: (N,) ``wp.vec2i`` each body's range in the pairs ordered by
            A (``pair_key``) and by B (``pair_by_b``).
        pairs: all of the above in the ``wp.struct`` the kernels take (:func:`polydem.kernels.structs.pairs_struct`),
            built again with the buffers.
        previous: :class:`PairHistory` of the list before a rebuild, during the rebuild (in the scratch
            buffer: overwritten by the next force stage; its ``count`` is its own).
        scratch_bytes: host int, the bytes of the scratch buffer.
        average: the :class:`ContactAverage` whose pair sums follow the list (None: no interval).
        capacity: host int.
        generation: host int, counts the times the per-pair buffers were replaced (a captured CUDA
            graph holds the old ones).
    """

    def __init__(
        self,
        model: Model,
        skin: float,
        body_box: tuple[np.ndarray, ...],
        capacity: int,
        radius_ref: float | None = None,
        thread_order: bool | str = False,
    ) -> None:
        if not isinstance(thread_order, str):
            thread_order = THREAD_ORDER if thread_order else False
        if thread_order not in (False, *THREAD_ORDERS):
            raise ValueError(f"thread_order must be True, False or one of {THREAD_ORDERS}, got {thread_order!r}")
        self.model = model
        self.device = model.device
        self.num_bodies = model.num_bodies
        self.friction = model.friction
        self.scalar = model.contact_scalar
        self.broadphase = BroadPhase(
            self.num_bodies,
            self.device,
            skin,
            capacity=capacity,
            rotation_term=False,
            body_box=body_box,
            radius_ref=radius_ref,
        )
        self.capacity = 0
        self.generation = 0
        self.average: ContactAverage | None = None
        self._pair_class, self._num_classes = pair_cost_classes(model) if thread_order else (None, 1)
        # by contact, even one cost class has two groups
        self._by_contact = thread_order == "contact"
        self.thread_order = self._num_classes > 1 or self._by_contact
        self.thread_grouping = thread_order if self.thread_order else "slot"
        if self.thread_order:
            self._pair_class_table = wp.array(self._pair_class.reshape(-1), dtype=int, device=self.device)
        self.body_first: wp.array | None = None
        self.pair_first_count = wp.zeros(1, dtype=int, device=self.device)
        # (1,) how many pairs, first in the thread order, are of costly shapes (COSTLY_FACES), at the last rebuild
        self.pair_costly = wp.zeros(1, dtype=int, device=self.device)
        self._costly_from = costly_class_from(model) if self._by_contact else 0

    def _inputs(self, body_q: wp.array) -> tuple[wp.array, wp.array]:
        """The poses and radii for the broad phase: as they are (float64 poses are cast in its kernels)."""
        return body_q, self.model.body_radius

    # -- the pair list (the broad phase replaces its arrays when it grows) ------------------------

    @property
    def pair_a(self) -> wp.array:
        return self.broadphase.pair_a

    @property
    def pair_b(self) -> wp.array:
        return self.broadphase.pair_b

    @property
    def pair_key(self) -> wp.array:
        return self.broadphase.pair_key

    @property
    def pair_count(self) -> wp.array:
        return self.broadphase.pair_count

    def count(self) -> int:
        """Number of candidate pairs (synchronises)."""
        return int(self.broadphase.pair_count.numpy()[0])

    # -- buffers -----------------------------------------------------------------------------

    def _allocate(self, capacity: int) -> None:
        dev = self.device
        self.capacity = capacity
        self.generation += 1
        springs = capacity if self.friction else 1
        scalar = self.scalar
        vec3 = wp.types.vector(3, scalar)
        self.pair_xi = wp.zeros(springs, dtype=vec3, device=dev)
        self.pair_turn = wp.zeros(capacity, dtype=scalar, device=dev)
        # One scratch buffer for three uses that never overlap in time (module docstring): the force stage's
        # outputs, the history before a rebuild, and the keys and values of the sort by B (radix sort: twice
        # the room; its values end up in pair_by_b).
        uses = (
            (("pair_force", vec3, capacity), ("pair_torque_a", vec3, capacity), ("pair_dissipated", scalar, capacity)),
            (("key", wp.int64, capacity), ("xi", vec3, springs), ("turn", scalar, capacity)),
            (("keys_b", wp.int32, 2 * capacity), ("by_b", wp.int32, 2 * capacity)),
        )
        layouts = [_layout(use) for use in uses]
        self.scratch_bytes = max(end for _, end in layouts)
        # int64 elements: 8-byte aligned for every view.
        self._scratch = wp.zeros(self.scratch_bytes // 8, dtype=wp.int64, device=dev)
        step, history, order = ({k: byte_view(self._scratch, *at) for k, at in views.items()} for views, _ in layouts)
        self.pair_force = step["pair_force"]
        self.pair_torque_a = step["pair_torque_a"]
        self.pair_dissipated = step["pair_dissipated"]
        self.previous = PairHistory(history["key"], history["xi"], history["turn"], wp.zeros(1, dtype=int, device=dev))
        self._keys_b, self._by_b = order["keys_b"], order["by_b"]
        self.pair_by_b = wp.zeros(capacity, dtype=int, device=dev)
        self.pair_thread = wp.zeros(capacity if self.thread_order else 1, dtype=int, device=dev)
        self.body_pairs_a = wp.zeros(self.num_bodies, dtype=wp.vec2i, device=dev)
        self.body_pairs_b = wp.zeros(self.num_bodies, dtype=wp.vec2i, device=dev)
        bp = self.broadphase
        self.pairs = filled(
            pairs_struct(scalar),
            a=bp.pair_a,
            b=bp.pair_b,
            count=bp.pair_count,
            xi=self.pair_xi,
            turn=self.pair_turn,
            force=self.pair_force,
            torque_a=self.pair_torque_a,
            dissipated=self.pair_dissipated,
            by_b=self.pair_by_b,
            thread=self.pair_thread,
            ranges_a=self.body_pairs_a,
            ranges_b=self.body_pairs_b,
        )
        if self.average is not None:
            self.average.resize(capacity)

    def _keep_previous(self) -> None:
        bp = self.broadphase
        prev = self.previous
        wp.copy(prev.key, bp.pair_key, count=self.capacity)
        wp.copy(prev.turn, self.pair_turn)
        if self.friction:
            wp.copy(prev.xi, self.pair_xi)
        wp.copy(prev.count, bp.pair_count)
        if self.average is not None:
            self.average.keep_previous()

    def carry_history(self, history: PairHistory, xi: wp.array, turn: wp.array) -> None:
        """Give each pair of the current list the history that ``history`` (a :class:`PairHistory`) holds
        under its key, into ``xi`` and ``turn`` (arrays shaped as :attr:`pair_xi` and :attr:`pair_turn`);
        zero for a new pair. A rebuild carries the previous list's into the live arrays so."""
        bp = self.broadphase
        launch_remap_history(
            old=history,
            new_key=bp.pair_key,
            new_count=bp.pair_count,
            friction=self.friction,
            new_xi=xi,
            new_turn=turn,
        )

    def _after_rebuild(self) -> None:
        """Turning volumes and friction springs carried over by pair key; per-body ranges for the gather."""
        bp = self.broadphase
        prev = self.previous
        self.carry_history(prev, self.pair_xi, self.pair_turn)
        if self.average is not None:
            self.average.after_rebuild(prev.key, prev.count, bp.pair_key, bp.pair_count)
        launch_body_ranges(
            num_bodies=self.num_bodies,
            pair_b=bp.pair_b,
            pair_key=bp.pair_key,
            pair_count=bp.pair_count,
            keys_b=self._keys_b,
            by_b=self._by_b,
            body_pairs_a=self.body_pairs_a,
            body_pairs_b=self.body_pairs_b,
            pair_by_b=self.pair_by_b,
        )
        if self.thread_order:  # the sort by B is done with the scratch: it holds nothing now
            self._thread_order()

    def _thread_order(self) -> None:
        bp = self.broadphase
        launch_thread_order(
            body_shape=self.model.body_shape,
            pair_class=self._pair_class_table,
            num_classes=self._num_classes,
            pair_a=bp.pair_a,
            pair_b=bp.pair_b,
            pair_count=bp.pair_count,
            keys=self._keys_b,
            order=self._by_b,
            pair_thread=self.pair_thread,
            pair_turn=self.pair_turn if self._by_contact else None,
            body_first=self.body_first,
            first_count=self.pair_first_count,
            costly_from=self._costly_from,
            costly_count=self.pair_costly if self._by_contact else None,
        )

    def split_at(self, body_first: wp.array | None) -> int | None:
        """Order the pair kernel's threads for a split step (:meth:`polydem.simulation.Stepper.split_at`): the pairs
        with a body flagged in ``body_first`` (N,) int32 first (:attr:`pair_first_count` of them), now and at each
        rebuild; None: not split. Returns how many there are now (None without :attr:`thread_order`, where the
        split step's kernels skip the other pairs instead)."""
        self.body_first = body_first
        if not self.thread_order:
            return None
        if self.capacity:
            self._thread_order()
        return int(self.pair_first_count.numpy()[0]) if body_first is not None else None

    # -- rebuilds (the broad phase of a step) -------------------------------------------------

    def build(self, body_q: wp.array, keep_history: bool = True) -> None:
        """Find the candidate pairs at the poses ``body_q`` on the host (grows the buffers as needed).

        With ``keep_history`` every pair that was already in the list keeps its history.
        """
        bp = self.broadphase
        m = self.model
        if keep_history and self.capacity:
            self._keep_previous()
        elif self.capacity:
            self.previous.count.zero_()
        bp.build(*self._inputs(body_q), m.body_flags)
        if bp.capacity != self.capacity:
            old = self.previous if self.capacity else None
            self._allocate(bp.capacity)
            if old is not None and keep_history:
                prev = self.previous
                n_old = min(len(old.key), bp.capacity)
                wp.copy(prev.key, old.key, count=n_old)
                if self.friction:
                    wp.copy(prev.xi, old.xi, count=n_old)
                wp.copy(prev.turn, old.turn, count=n_old)
                wp.copy(prev.count, old.count)
        self._after_rebuild()

    def rebuild_on_device(self, body_q: wp.array) -> None:
        """Rebuild without host synchronisation or allocation (a conditional node of a CUDA graph).

        When the pairs overflow the capacity, :meth:`host_build_needed` turns true: the steps since
        must be redone after a host :meth:`build` (``Simulation.step`` does).
        """
        self._keep_previous()
        m = self.model
        self.broadphase.rebuild_on_device(*self._inputs(body_q), m.body_flags)
        self._after_rebuild()

    def update(self, body_q: wp.array) -> None:
        """Host: :meth:`build` when some body may have left its skin since the last build."""
        m = self.model
        flag = self.broadphase.needs_rebuild(*self._inputs(body_q), m.body_flags)
        if int(flag.numpy()[0]):
            self.build(body_q)

    def update_on_device(self, body_q: wp.array) -> None:
        """:meth:`update` without host synchronisation: the test and a conditional :meth:`rebuild_on_device`."""
        bp = self.broadphase
        m = self.model
        bp.needs_rebuild(*self._inputs(body_q), m.body_flags)
        wp.capture_if(bp.rebuild_flag, on_true=self.rebuild_on_device, body_q=body_q)

    def host_build_needed(self) -> bool:
        """Host: True when a device rebuild overflowed or saw changed flags since the last host build."""
        return self.broadphase.check_host_build_needed()

    # -- history: redo, snapshots, checkpoints ------------------------------------------------

    def history(self, into: PairHistory | None = None) -> PairHistory:
        """A copy of the current pairs' history (synchronises, to read the count): the first ``count`` entries,
        in arrays with room for ``count + count // 8 + 64`` (at most the capacity), not the whole capacity;
        into ``into`` (a :class:`PairHistory`) when it has room for them."""
        bp = self.broadphase
        count = self.count()
        xi_len = (lambda n: n) if self.friction else (lambda n: 1)
        fits = into is not None and len(into.key) >= count and len(into.turn) >= count
        if fits:
            fits = len(into.xi) >= xi_len(count) and into.turn.dtype == self.pair_turn.dtype
        if not fits:
            room = min(count + count // 8 + 64, self.capacity)
            into = PairHistory.zeros(room, self.friction, self.device, self.scalar)
        wp.copy(into.count, bp.pair_count)
        if count:
            wp.copy(into.key, bp.pair_key, count=count)
            wp.copy(into.turn, self.pair_turn, count=count)
            wp.copy(into.xi, self.pair_xi, count=xi_len(count))
        return into

    def restore(self, history: PairHistory, body_q: wp.array, pair_sums: ContactSums | None = None) -> None:
        """Find the pairs at ``body_q`` afresh (host build) and give each pair of ``history`` its history back.

        ``pair_sums``: the sums of the averaging interval (:class:`ContactAverage`) of ``history``'s pairs
        (from :meth:`ContactAverage.snapshot`), given back to them likewise; None: they start from zero.
        """
        bp = self.broadphase
        m = self.model
        bp.build(*self._inputs(body_q), m.body_flags)
        if bp.capacity != self.capacity:
            self._allocate(bp.capacity)
        prev = self.previous
        n_old = min(int(history.count.numpy()[0]), len(history.key), self.capacity)
        if n_old:  # (a count of 0 would copy whole arrays)
            wp.copy(prev.key, history.key, count=n_old)
            wp.copy(prev.turn, history.turn, count=n_old)
            if self.friction:
                wp.copy(prev.xi, history.xi, count=n_old)
        prev.count.fill_(n_old)
        if self.average is not None:
            self.average.load_previous(pair_sums, n_old)
        self._after_rebuild()

    def history_numpy(self) -> dict[str, np.ndarray]:
        """Host copies of the current pairs' history: ``pair_key`` (C,) int64, ``pair_xi`` (C, 3) [m]
        ((0, 3) without friction), ``pair_turn`` (C,) [m^3]."""
        count = self.count()
        return {
            "pair_key": self.broadphase.pair_key.numpy()[:count],
            "pair_xi": self.pair_xi.numpy()[:count] if self.friction else np.zeros((0, 3), numpy_dtype(self.scalar)),
            "pair_turn": self.pair_turn.numpy()[:count],
        }


def _layout(parts: tuple[tuple[str, type, int], ...]) -> tuple[dict[str, tuple[int, type, int]], int]:
    """Byte offsets of (name, dtype, length) arrays laid one after the other, each at a multiple of 64 bytes:
    ({name: (offset, dtype, length)}, end)."""
    views, end = {}, 0
    for name, dtype, length in parts:
        views[name] = (end, dtype, length)
        end += -(-length * wp.types.type_size_in_bytes(dtype) // 64) * 64
    return views, end


def contact_sums(size: int, device: wp.DeviceLike) -> ContactSums:
    """A :class:`~polydem.kernels.forces.ContactSums` of ``size`` zero entries."""
    s = ContactSums()
    s.force = wp.zeros(size, dtype=wp.vec3d, device=device)
    s.tangential = wp.zeros(size, dtype=wp.vec3d, device=device)
    s.normal = wp.zeros(size, dtype=wp.float64, device=device)
    s.point = wp.zeros(size, dtype=wp.vec3d, device=device)
    s.steps = wp.zeros(size, dtype=int, device=device)
    return s


_SUM_FIELDS = ("force", "tangential", "normal", "point", "steps")


def _copy_sums(dst: ContactSums, src: ContactSums, count: int | None = None) -> None:
    for k in _SUM_FIELDS:
        if count is None:
            wp.copy(getattr(dst, k), getattr(src, k))
        elif count:
            wp.copy(getattr(dst, k), getattr(src, k), count=count)


def _zero_sums(s: ContactSums) -> None:
    for k in _SUM_FIELDS:
        getattr(s, k).zero_()


def _sums_numpy(s: ContactSums, count: int) -> dict[str, np.ndarray]:
    return {k: getattr(s, k).numpy()[:count] for k in _SUM_FIELDS}


class AverageSnapshot:
    """A copy of a :class:`ContactAverage` at one step (see :meth:`ContactAverage.snapshot`)."""

    def __init__(self, interval: int, pairs: ContactSums, walls: ContactSums, retired_count: wp.array) -> None:
        self.interval = interval
        self.pairs = pairs
        self.walls = walls
        self.retired_count = retired_count


class ContactAverage:
    """The device sums of the contact forces over an averaging interval (``Simulation.start_contact_average``).

    Each step of the interval adds every contact's force to its sums (the report variant of the
    step kernels, kernels/forces.py ``ContactSums``): no host synchronisation, so a captured CUDA
    graph of the step does it too. The pairs' sums follow the pair list by key (:class:`Contacts`
    calls :meth:`keep_previous`, :meth:`resize` and :meth:`after_rebuild`); a pair dropped by a rebuild
    after it was in contact is appended to the retired list; the wall contacts' sums are per
    (body, wall). :meth:`numpy` adds it all up on the host.

    Args:
        contacts: the :class:`Contacts` whose pairs are summed (this attaches itself to it).
        num_walls: the wall columns of the state (max(W, 1)).
        interval: a number that names the interval (a snapshot of another interval is not restored).
        start_step, start_time: where the interval begins.

    Attributes (device): ``pairs`` and ``previous`` (:class:`ContactSums` of the pair list and of
    the list before the last rebuild), ``walls`` (N * max(W, 1)), ``retired_key`` (R,) int64 and
    ``retired`` (R) with ``retired_count`` (1,), ``overflow`` (1,) set when R was too small.
    generation: host int, counts the times the arrays were replaced (a captured graph holds them).
    """

    def __init__(self, contacts: Contacts, num_walls: int, interval: int, start_step: int, start_time: float) -> None:
        self.device = contacts.device
        self.contacts = contacts
        self.num_bodies = contacts.num_bodies
        self.num_walls = max(int(num_walls), 1)
        self.generation = 0
        self.capacity = 0
        self.walls = contact_sums(self.num_bodies * self.num_walls, self.device)
        # The retired list starts as large as the pair list: more pairs than that must end within
        # one chunk of steps for it to overflow (then it doubles and the chunk is redone).
        self._allocate_retired(max(contacts.capacity, 64))
        self.retired_count = wp.zeros(1, dtype=int, device=self.device)
        self.overflow = wp.zeros(1, dtype=int, device=self.device)
        self.resize(contacts.capacity)
        self.reset(interval, start_step, start_time)
        contacts.average = self

    def _allocate_retired(self, size: int) -> None:
        self.retired_key = wp.zeros(size, dtype=wp.int64, device=self.device)
        self.retired = contact_sums(size, self.device)
        self.generation += 1

    def reset(self, interval: int, start_step: int, start_time: float) -> None:
        """Start the interval ``interval`` at ``start_step`` / ``start_time`` [s] with every sum zero."""
        self.interval = interval
        self.start_step = int(start_step)
        self.start_time = float(start_time)
        _zero_sums(self.pairs)
        _zero_sums(self.previous)
        _zero_sums(self.walls)
        self.retired_count.zero_()
        self.overflow.zero_()

    def detach(self) -> None:
        """Stop following the pair list."""
        if self.contacts.average is self:
            self.contacts.average = None

    # -- following the pair list (called by Contacts) ------------------------------------------

    def resize(self, capacity: int) -> None:
        """New pair arrays of ``capacity``; the previous list's sums are carried into the new ones."""
        old = self.previous if self.capacity else None
        self.pairs = contact_sums(capacity, self.device)
        self.previous = contact_sums(capacity, self.device)
        if old is not None:
            _copy_sums(self.previous, old, count=min(self.capacity, capacity))
        self.capacity = capacity
        self.generation += 1

    def keep_previous(self) -> None:
        _copy_sums(self.previous, self.pairs)

    def load_previous(self, pair_sums: ContactSums | None, count: int) -> None:
        """The previous list's sums from a snapshot's (``pair_sums``; None: zero), ``count`` pairs."""
        if pair_sums is None:
            _zero_sums(self.previous)
        else:
            _copy_sums(self.previous, pair_sums, count=min(count, len(pair_sums.steps), self.capacity))

    def after_rebuild(self, old_key: wp.array, old_count: wp.array, new_key: wp.array, new_count: wp.array) -> None:
        launch_carry_sums(
            old_key=old_key,
            old_count=old_count,
            old_sums=self.previous,
            new_key=new_key,
            new_count=new_count,
            new_sums=self.pairs,
            retired_key=self.retired_key,
            retired=self.retired,
            retired_count=self.retired_count,
            overflow=self.overflow,
        )

    # -- redo and snapshots ----------------------------------------------------------------------

    def overflowed(self) -> bool:
        """Host: whether the retired list ran out of room (the steps since must be redone after :meth:`grow`)."""
        return bool(int(self.overflow.numpy()[0]))

    def grow(self) -> None:
        """Double the retired list (keeping its entries); new arrays, so recapture a graph."""
        old_key, old = self.retired_key, self.retired
        self._allocate_retired(2 * len(old_key))
        wp.copy(self.retired_key, old_key, count=len(old_key))
        _copy_sums(self.retired, old, count=len(old_key))
        self.overflow.zero_()

    def snapshot(self, into: AverageSnapshot | None = None) -> AverageSnapshot:
        """An :class:`AverageSnapshot` (device copies of the pairs' and walls' sums and of the number
        of retired pairs: the retired entries before it stay as they are); reuses ``into`` where it fits."""
        if into is not None and len(into.pairs.steps) == self.capacity:
            _copy_sums(into.pairs, self.pairs)
            _copy_sums(into.walls, self.walls)
            wp.copy(into.retired_count, self.retired_count)
            into.interval = self.interval
            return into
        pairs = contact_sums(self.capacity, self.device)
        walls = contact_sums(len(self.walls.steps), self.device)
        _copy_sums(pairs, self.pairs)
        _copy_sums(walls, self.walls)
        return AverageSnapshot(self.interval, pairs, walls, wp.clone(self.retired_count))

    def restore(self, snap: AverageSnapshot) -> None:
        """The walls' sums and the retired count of ``snap`` (the pairs' go through :meth:`load_previous`)."""
        _copy_sums(self.walls, snap.walls)
        wp.copy(self.retired_count, snap.retired_count)
        self.overflow.zero_()

    # -- reading -----------------------------------------------------------------------------------

    def numpy(self, pair_key: wp.array, pair_count: wp.array) -> dict[str, np.ndarray]:
        """Host float64 sums per contact that was in contact in the interval: pairs (the current list's
        and the retired ones, added up by key in the order they were summed), then wall contacts.

        Returns ``key`` (K,) int64 pair keys ``a * N + b`` then ``-1 - (body * W + wall)`` for the walls,
        ``force``, ``tangential``, ``point`` (K, 3), ``normal`` (K,), ``steps`` (K,) int.
        """
        if self.overflowed():
            raise RuntimeError("the list of the contacts that ended in the averaging interval overflowed; step again")
        count = int(pair_count.numpy()[0])
        retired = min(int(self.retired_count.numpy()[0]), len(self.retired_key))
        keys = np.concatenate([self.retired_key.numpy()[:retired], pair_key.numpy()[:count]])
        r, live = _sums_numpy(self.retired, retired), _sums_numpy(self.pairs, count)
        cols = {k: np.concatenate([r[k], live[k]]) for k in _SUM_FIELDS}
        on = cols["steps"] > 0
        keys = keys[on]
        order = np.argsort(keys, kind="stable")  # stable: one key's entries in the order they were summed
        keys = keys[order]
        cols = {k: v[on][order] for k, v in cols.items()}
        out = {"key": np.unique(keys)}
        if len(keys):
            start = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
            for k, v in cols.items():
                out[k] = np.add.reduceat(v.astype(np.float64) if k != "steps" else v, start, axis=0)
        else:
            out.update({k: v for k, v in cols.items()})
        walls = _sums_numpy(self.walls, len(self.walls.steps))
        on = np.flatnonzero(walls["steps"] > 0)
        out["key"] = np.concatenate([out["key"], -1 - on.astype(np.int64)])
        for k in _SUM_FIELDS:
            out[k] = np.concatenate([out[k], walls[k][on]])
        return out
