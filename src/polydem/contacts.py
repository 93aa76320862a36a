"""Contacts: the candidate pairs of the broad phase, and the history each pair carries.

A pair's history is its friction spring and the turning volume of the normal hysteresis
(kernels/forces.py). The pair list changes at every broad-phase rebuild; the history goes with the
pair's key ``a * N + b`` (kernels/forces.py ``remap_history_kernel``), so a pair that persists
across a rebuild, a redone chunk or a checkpoint keeps it, and a new pair starts from zero.

The wall contacts' history is per (body, wall), has no list to follow, and lives in the
:class:`~polydem.state.State`.

The history is in the contact scalar of the model's precision (float32 in "float32" and "mixed",
float64 in "float64"). The broad phase runs in float32 in every precision: with float64 poses it
gets float32 copies of the centres and radii grown by the rounding of the cast
(``kernels/broadphase.py`` ``float32_input_kernel``), so no candidate pair is missed.
"""

import numpy as np
import warp as wp

from polydem.kernels.broadphase import BroadPhase, float32_input_kernel
from polydem.kernels.forces import b_keys_kernel, body_ranges_kernel, make_remap_history_kernel
from polydem.kernels.precision import numpy_dtype

__all__ = ["Contacts", "PairHistory"]


class PairHistory:
    """The history of a pair list, by key (device arrays): what a rebuild, a redo and a checkpoint carry.

    Attributes:
        key: (C,) int64 pair keys ``a * N + b`` (a < b), increasing over the first ``count[0]`` entries.
        xi: (C,) vec3 friction springs [m]; (1,) when the scene has no friction.
        turn: (C,) turning volumes [m^3].
        (``xi`` and ``turn`` in float32, or float64 in the "float64" precision.)
        count: (1,) int32 number of pairs.
    """

    FIELDS = ("key", "xi", "turn", "count")

    def __init__(self, key, xi, turn, count):
        self.key = key
        self.xi = xi
        self.turn = turn
        self.count = count

    @classmethod
    def zeros(cls, capacity, friction, device, scalar=wp.float32):
        return cls(
            wp.zeros(capacity, dtype=wp.int64, device=device),
            wp.zeros(capacity if friction else 1, dtype=wp.types.vector(3, scalar), device=device),
            wp.zeros(capacity, dtype=scalar, device=device),
            wp.zeros(1, dtype=int, device=device),
        )

    @classmethod
    def from_numpy(cls, key, xi, turn, friction, device, scalar=wp.float32):
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

    def copy(self):
        return PairHistory(*(wp.clone(getattr(self, k)) for k in self.FIELDS))

    def assign(self, other):
        for k in self.FIELDS:
            wp.copy(getattr(self, k), getattr(other, k))

    def same_shapes(self, other):
        return all(getattr(self, k).shape == getattr(other, k).shape for k in self.FIELDS)


class Contacts:
    """The candidate pair list (a Verlet list with a skin) and its history, with the per-pair buffers of a step.

    Args:
        model: the :class:`~polydem.model.Model`.
        skin: Verlet skin [m].
        body_box: (lower, upper), two (N, 3) arrays: a box around each body's shape in its own frame [m].
        capacity: initial number of pairs there is room for (grows on overflow).

    Attributes (device arrays; C = :attr:`capacity`, N bodies):
        broadphase: the :class:`~polydem.kernels.broadphase.BroadPhase`, which owns the pair list
            ``pair_a``, ``pair_b`` (C,) int32, ``pair_key`` (C,) int64, ``pair_count`` (1,) int32.
        pair_xi: (C,) vec3 friction springs [m] ((1,) without friction).
        pair_turn: (C,) turning volumes [m^3].
        pair_force: (C,) vec3 contact force of the pair in the last step [N] (kernels/forces.py).
        pair_torque_a: (C,) vec3 torque of the pair on body A about its centroid [N m].
        pair_dissipated: (C,) energy the pair dissipated in the last step [J].
        (These five in the model's contact scalar: float32 in "float32" and "mixed", float64 in
        "float64".)
        pair_by_b: (C,) int32 pair indices ordered by body B.
        body_pairs_a, body_pairs_b: (N,) ``wp.vec2i`` each body's range in the pairs ordered by
            A (``pair_key``) and by B (``pair_by_b``).
        previous: :class:`PairHistory` of the list before the last rebuild.
        capacity: host int.
        generation: host int, counts the times the per-pair buffers were replaced (a captured CUDA
            graph holds the old ones).
    """

    def __init__(self, model, skin, body_box, capacity):
        self.model = model
        self.device = model.device
        self.num_bodies = model.num_bodies
        self.friction = model.friction
        self.scalar = model.contact_scalar
        self.broadphase = BroadPhase(
            self.num_bodies, self.device, skin, capacity=capacity, rotation_term=False, body_box=body_box
        )
        self.capacity = 0
        self.generation = 0
        self._remap = make_remap_history_kernel(self.scalar)
        # Float64 poses reach the broad phase through float32 copies (module docstring).
        self._cast = model.scalar != wp.float32
        if self._cast:
            self._q32 = wp.zeros(self.num_bodies, dtype=wp.transform, device=self.device)
            self._radius32 = wp.zeros(self.num_bodies, dtype=float, device=self.device)

    def _inputs(self, body_q):
        """The poses and radii for the broad phase: float32 copies when the poses are float64."""
        m = self.model
        if not self._cast:
            return body_q, m.body_radius
        wp.launch(
            float32_input_kernel,
            dim=self.num_bodies,
            inputs=[m.body_radius, body_q],
            outputs=[self._q32, self._radius32],
            device=self.device,
        )
        return self._q32, self._radius32

    # -- the pair list (the broad phase replaces its arrays when it grows) ------------------------

    @property
    def pair_a(self):
        return self.broadphase.pair_a

    @property
    def pair_b(self):
        return self.broadphase.pair_b

    @property
    def pair_key(self):
        return self.broadphase.pair_key

    @property
    def pair_count(self):
        return self.broadphase.pair_count

    def count(self):
        """Number of candidate pairs (synchronises)."""
        return int(self.broadphase.pair_count.numpy()[0])

    # -- buffers -----------------------------------------------------------------------------

    def _allocate(self, capacity):
        dev = self.device
        self.capacity = capacity
        self.generation += 1
        springs = capacity if self.friction else 1
        scalar = self.scalar
        vec3 = wp.types.vector(3, scalar)
        self.pair_xi = wp.zeros(springs, dtype=vec3, device=dev)
        self.pair_turn = wp.zeros(capacity, dtype=scalar, device=dev)
        self.pair_force = wp.zeros(capacity, dtype=vec3, device=dev)
        self.pair_torque_a = wp.zeros(capacity, dtype=vec3, device=dev)
        self.pair_dissipated = wp.zeros(capacity, dtype=scalar, device=dev)
        self.previous = PairHistory.zeros(capacity, self.friction, dev, scalar)
        # Pairs ordered by their B body (radix sort needs twice the room).
        self._keys_b = wp.zeros(2 * capacity, dtype=wp.int64, device=dev)
        self._by_b = wp.zeros(2 * capacity, dtype=int, device=dev)
        self.pair_by_b = self._by_b[:capacity]
        self.body_pairs_a = wp.zeros(self.num_bodies, dtype=wp.vec2i, device=dev)
        self.body_pairs_b = wp.zeros(self.num_bodies, dtype=wp.vec2i, device=dev)

    def _keep_previous(self):
        bp = self.broadphase
        prev = self.previous
        wp.copy(prev.key, bp.pair_key, count=self.capacity)
        wp.copy(prev.turn, self.pair_turn)
        if self.friction:
            wp.copy(prev.xi, self.pair_xi)
        wp.copy(prev.count, bp.pair_count)

    def _after_rebuild(self):
        """Turning volumes and friction springs carried over by pair key; per-body ranges for the gather."""
        bp = self.broadphase
        dev = self.device
        cap = self.capacity
        prev = self.previous
        wp.launch(
            self._remap,
            dim=cap,
            inputs=[prev.key, prev.count, prev.xi, prev.turn, bp.pair_key, bp.pair_count, int(self.friction)],
            outputs=[self.pair_xi, self.pair_turn],
            device=dev,
        )
        wp.launch(
            b_keys_kernel,
            dim=cap,
            inputs=[self.num_bodies, bp.sentinel, bp.pair_a, bp.pair_b, bp.pair_count],
            outputs=[self._keys_b, self._by_b],
            device=dev,
        )
        wp.utils.radix_sort_pairs(self._keys_b, self._by_b, cap, 0, bp.key_bits)
        wp.launch(
            body_ranges_kernel,
            dim=self.num_bodies,
            inputs=[self.num_bodies, bp.pair_key, self._keys_b, bp.pair_count],
            outputs=[self.body_pairs_a, self.body_pairs_b],
            device=dev,
        )

    # -- rebuilds (the broad phase of a step) -------------------------------------------------

    def build(self, body_q, keep_history=True):
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

    def rebuild_on_device(self, body_q):
        """Rebuild without host synchronisation or allocation (a conditional node of a CUDA graph).

        When the pairs overflow the capacity, :meth:`host_build_needed` turns true: the steps since
        must be redone after a host :meth:`build` (``Simulation.step`` does).
        """
        self._keep_previous()
        m = self.model
        self.broadphase.rebuild_on_device(*self._inputs(body_q), m.body_flags)
        self._after_rebuild()

    def update(self, body_q):
        """Host: :meth:`build` when some body may have left its skin since the last build."""
        m = self.model
        flag = self.broadphase.needs_rebuild(*self._inputs(body_q), m.body_flags)
        if int(flag.numpy()[0]):
            self.build(body_q)

    def update_on_device(self, body_q):
        """:meth:`update` without host synchronisation: the test and a conditional :meth:`rebuild_on_device`."""
        bp = self.broadphase
        m = self.model
        bp.needs_rebuild(*self._inputs(body_q), m.body_flags)
        wp.capture_if(bp.rebuild_flag, on_true=self.rebuild_on_device, body_q=body_q)

    def host_build_needed(self):
        """Host: True when a device rebuild overflowed or saw changed flags since the last host build."""
        return self.broadphase.check_host_build_needed()

    # -- history: redo, snapshots, checkpoints ------------------------------------------------

    def history(self, into=None):
        """A copy of the current pairs' history; into ``into`` (a :class:`PairHistory`) when its shapes fit."""
        bp = self.broadphase
        live = PairHistory(bp.pair_key, self.pair_xi, self.pair_turn, bp.pair_count)
        if into is None or not into.same_shapes(live):
            return live.copy()
        into.assign(live)
        return into

    def restore(self, history, body_q):
        """Find the pairs at ``body_q`` afresh (host build) and give each pair of ``history`` its history back."""
        bp = self.broadphase
        m = self.model
        bp.build(*self._inputs(body_q), m.body_flags)
        if bp.capacity != self.capacity:
            self._allocate(bp.capacity)
        prev = self.previous
        n_old = min(int(history.count.numpy()[0]), len(history.key), self.capacity)
        wp.copy(prev.key, history.key, count=n_old)
        wp.copy(prev.turn, history.turn, count=n_old)
        if self.friction:
            wp.copy(prev.xi, history.xi, count=n_old)
        prev.count.fill_(n_old)
        self._after_rebuild()

    def history_numpy(self):
        """Host copies of the current pairs' history: ``pair_key`` (C,) int64, ``pair_xi`` (C, 3) [m]
        ((0, 3) without friction), ``pair_turn`` (C,) [m^3]."""
        count = self.count()
        return {
            "pair_key": self.broadphase.pair_key.numpy()[:count],
            "pair_xi": self.pair_xi.numpy()[:count] if self.friction else np.zeros((0, 3), numpy_dtype(self.scalar)),
            "pair_turn": self.pair_turn.numpy()[:count],
        }
