"""DistributedSimulation: one scene stepped by several ranks, each owning the bodies of a slab.

Every rank loads the whole scene (its description: shapes, materials, walls, the bodies' initial
state). Each rank then steps a :class:`~polydem.Simulation` of its *local* bodies: those it owns
(the slab's, :mod:`polydem.distributed.partition`) and ghost copies of the bodies within the halo.
The local bodies keep the order of their global indices, so a rank's pair keys sort as the
undivided run's do and each body gathers its pair forces in the same order. A pair is computed by
every rank that holds both bodies, from the same inputs and so to the same bits; it belongs to
(is reported and booked by) the rank that owns its body A. After each step every rank sends the
new poses and velocities of its bodies that are ghosts elsewhere to the ranks that hold them, and
overwrites its own ghosts with what it receives: the ghosts stepped locally (with only part of their
contacts) are never used. When some body has moved more than half the halo's margin since the last
partition, the slabs are cut again (balanced by body count), bodies and their wall histories move to
their new owners and holders, and each pair's history (friction spring, turning volume) goes to
every rank that holds both its bodies.

What makes the result the undivided run's, bit for bit on one device type and precision: the
settings that depend on the bodies (time step, friction springs, mesh-wall thickness, the broad
phase's reference radius: :class:`~polydem.run_settings.RunSettings`) decided once from the whole
scene and given to every rank's Simulation, so that its size classes are the undivided run's and the
same body of a pair is A; pair histories carried by key; a pair that is a candidate but not in
contact contributes exact zeros, so the rank's own candidate lists and their rebuild times do not
matter. Sums over bodies (energies, the settle measures) are added per rank and then across ranks,
so they agree with the undivided run to rounding, not to the bit.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np
import warp as wp

from polydem.distributed import partition
from polydem.distributed.comm import SerialComm, world
from polydem.distributed.nccl import NcclExchange, auto_exchange, nccl_place
from polydem.kernels.ghosts import launch_largest_move, launch_pack_rows, launch_step_rows, launch_unpack_rows
from polydem.kernels.integrate import kinetic_energy
from polydem.run_settings import run_settings
from polydem.scene.bodies import BodyKind
from polydem.simulation import CHUNK_STEPS, Simulation, SimulationError, Snapshot

if TYPE_CHECKING:
    from polydem.distributed.comm import Comm
    from polydem.scene import Scene

CHUNK = 50
"""Steps between two agreements of the ranks (errors, overflows, moves): each costs a synchronisation and an
allreduce; a chunk that must be redone costs up to this many steps."""

EXCHANGES = ("host", "nccl")
"""How the ghosts' rows travel between ranks (:class:`DistributedSimulation`'s ``exchange``)."""

ROW = 14
"""What a ghost receives after every step, per body: pose (7), velocity (3), angular velocity (3) and damping
load (1: the scale of its contacts' dashpots at the next step depends on all its contacts, which only its owner
has); the rest of its state is only read by its owner."""


def simulation_time(start: float, done: int, n: int, dt: float) -> float:
    """The time of a :class:`~polydem.Simulation` at ``start`` [s] after ``done`` of the ``n`` steps of one
    ``step(n)`` call: it adds ``chunk * dt`` per chunk of its own (:meth:`Simulation.step`), whose rounding
    the checkpoints, frame times and summaries of a decomposed run must repeat to be the undivided run's
    (``steps_done * dt`` differs in the last bits). Between two of its chunk ends: the last end plus the
    steps since, times dt."""
    t, at = float(start), 0
    while at < n:
        chunk = min(CHUNK_STEPS, n - at)
        if chunk == n - at and chunk > 1:
            chunk -= 1  # as Simulation.step: the last step runs in a chunk of its own
        if at + chunk > done:
            return t + (done - at) * dt
        t += chunk * dt
        at += chunk
    return t


class DistributedError(SimulationError):
    """A rank of a decomposed run failed; every rank raises it (with the failing rank's message)."""


class DistributedSimulation:
    """Steps ``scene`` over the ranks of ``comm`` (every rank constructs it with the same scene).

    Args:
        scene: the whole scene, validated (:class:`~polydem.Scene`), the same on every rank.
        device: Warp device of this rank (one GPU per rank: ``cuda:<local rank>``).
        comm: an mpi4py communicator (default: ``MPI.COMM_WORLD`` under an MPI launcher, else one rank).
        margin: how far [m] a body may move between two partitions (default: the largest bounding
            radius); the halo is twice the largest bounding radius plus this.
        skin: Verlet skin of the ranks' broad phases [m] (default: the undivided run's).
        use_graph: CUDA graphs in the ranks' simulations (default: on CUDA devices).
        chunk: steps between two agreements of the ranks (see :meth:`step`).
        overlap: send the ghosts' rows while the step still runs (default: on a GPU, whose kernels run while the
            host exchanges; on the CPU they run in the calling thread, and a split step costs more): each rank's step
            is split (:meth:`polydem.Simulation.advance_split`), its first part computes the contacts and forces
            of the bodies it sends and their rows as the step will leave them, and the exchange runs while the
            second part computes the rest. The same bits as without; not with mesh walls (:attr:`split`).
        exchange: how the ghosts' rows travel: "host" through pinned host memory over MPI, the host waiting for
            each step's rows before it launches the next step; "nccl" from GPU to GPU with NCCL (nccl4py,
            :mod:`polydem.distributed.nccl`), enqueued on the GPU's streams and captured in the steps' graphs, so
            that the host never waits within a chunk (one GPU per rank); "auto" (default) "nccl" where every rank
            has a GPU of its own and nccl4py, else "host" (:func:`~polydem.distributed.nccl.auto_exchange`). The
            same bits either way.

    The methods that read the state (:meth:`state`, :meth:`contacts`, :meth:`energy`,
    :meth:`settle_measures`) and :meth:`step` are collective: every rank calls them in the same
    order. ``state`` and ``contacts`` return the whole scene's arrays on ``root`` and None elsewhere;
    ``energy`` and ``settle_measures`` return the totals on every rank.

    Attributes:
        rank, size: this rank and the number of ranks.
        num_bodies: bodies of the whole scene; dt: time step [s]; steps_done; time [s].
        settings: the whole scene's :class:`~polydem.run_settings.RunSettings`, which every rank's
            Simulation takes; skin: its Verlet skin [m]; r_max: its largest free bounding radius [m].
        margin, halo: the ``margin`` and the halo [m] (see Args).
        local_index: (n,) global indices of this rank's local bodies, ascending.
        owned: (n,) bool, which local bodies this rank owns.
        cuts: (size + 1,) slab boundaries along ``axis``; partitions: partitions made so far; redone:
            chunks stepped again (an overflow somewhere, or a body past the margin).
        exchange: "host" or "nccl", the exchange the ranks took (``exchange`` above; :meth:`set_exchange`).
        split: whether this rank's steps are split for the overlap (``overlap``, a Simulation with bodies to
            send, no mesh walls).
        timers: seconds spent per part of the step on this rank: ``compute`` (the local
            simulation's steps), ``exchange`` (packing, sending and unpacking ghosts), ``wait``
            (waiting for the other ranks at the step's agreement), ``partition``. On a GPU the launches
            are asynchronous: ``compute`` is the host's launch time and ``exchange`` includes waiting for
            the step's kernels, unless ``sync_timers`` is set (a synchronisation after each step's kernels).
    """

    scene: Scene
    device: wp.Device
    num_bodies: int
    dt: float
    steps_done: int
    time: float

    def __init__(
        self,
        scene: Scene,
        device: wp.DeviceLike = None,
        comm: Comm | None = None,
        *,
        margin: float | None = None,
        skin: float | None = None,
        use_graph: bool | None = None,
        root: int = 0,
        chunk: int = CHUNK,
        overlap: bool | None = None,
        exchange: str = "auto",
    ) -> None:
        self.split = False
        self.comm = comm if comm is not None else world()
        self.rank = int(self.comm.Get_rank())
        self.size = int(self.comm.Get_size())
        self.root = int(root)
        self.scene = scene
        self.device = wp.get_device(device)
        self.overlap = self.device.is_cuda if overlap is None else bool(overlap)
        self.exchange = "host"
        self._nccl: NcclExchange | None = None
        self._exchange_graphs: dict[bool, wp.Graph] = {}
        if exchange == "auto":  # collective: every rank takes the same
            exchange = auto_exchange(self.comm.allgather(nccl_place(self.device)))
        self.set_exchange(exchange)
        self.use_graph = use_graph
        self.num_bodies = n = scene.num_bodies
        # Decided once from the whole scene, and the same on every rank: each rank's Simulation takes them.
        self.settings = run_settings(scene, skin=skin)
        self.dt = self.settings.dt
        self.skin = self.settings.skin
        # Fixed and kinematic bodies (container slabs, drums) move as prescribed, the same on every rank,
        # and may be large: every rank holds them all and none is exchanged.
        self._free = np.asarray(scene.body_kind) == BodyKind.FREE
        self.r_max = self.settings.radius_max
        self.margin = self.r_max if margin is None else float(margin)
        if not self.margin > 0.0:
            raise ValueError(f"margin must be > 0 [m], got {margin!r}")
        self.halo = 2.0 * self.r_max + self.margin
        pos = np.asarray(scene.body_position, dtype=np.float64)
        self.axis = partition.longest_axis(pos.min(axis=0), pos.max(axis=0)) if n else 0
        self.steps_done = 0
        self.time = 0.0
        self.partitions = 0
        self.timers = {"compute": 0.0, "exchange": 0.0, "wait": 0.0, "partition": 0.0, "total": 0.0}
        self.chunk = int(chunk)
        if self.chunk < 1:
            raise ValueError(f"chunk must be >= 1 step, got {chunk!r}")
        self._good: Snapshot | None = None
        self.redone = 0
        self._repartition_due = False  # half the margin used by the last step() call's last chunk
        self.sync_timers = False
        self.sim: Simulation | None = None
        self._initial_partition(pos[:, self.axis])

    # -- the rank's simulation ------------------------------------------------------------------

    def _local_simulation(self, index: np.ndarray) -> Simulation:
        """A Simulation of the bodies ``index`` (global, ascending) with the whole scene's settings."""
        return Simulation(
            self.scene, self.device, use_graph=self.use_graph, validate=False, settings=self.settings, bodies=index
        )

    # -- partitions -----------------------------------------------------------------------------

    def _histogram(self, x: np.ndarray) -> np.ndarray:
        """Cuts balanced by body count from the coordinates ``x`` of this rank's bodies (collective)."""
        lo = self._allreduce(float(x.min()) if len(x) else np.inf, "min")
        hi = self._allreduce(float(x.max()) if len(x) else -np.inf, "max")
        if not hi > lo:
            hi = lo + 1.0
        counts = np.histogram(x, bins=partition.HISTOGRAM_BINS, range=(lo, hi))[0].astype(np.int64)
        counts = self._allreduce(counts, "sum")
        return partition.cuts_from_histogram(counts, lo, hi, self.size)

    def _initial_partition(self, x_all: np.ndarray) -> None:
        """At the start every rank has every body's position: the partition needs no messages
        beyond the histogram's sums (each rank histograms the bodies it would own by index)."""
        index, owner = self._partition_all(x_all)
        self._set_local(index, owner[index] == self.rank, owner[index], x_all[index])
        self.partitions += 1

    def _partition_all(self, x_all: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cut the slabs from every body's coordinate ``x_all`` (known to every rank; each histograms an
        equal share of the bodies, collective); returns this rank's local bodies (global, ascending) and
        every body's owner."""
        n = self.num_bodies
        share = np.array_split(np.arange(n), self.size)[self.rank]
        self.cuts = self._histogram(x_all[share])
        owner = partition.owner(x_all, self.cuts)
        index = np.flatnonzero(self._holders(x_all, np.arange(n))[:, self.rank])
        return index, owner

    def _set_local(
        self,
        index: np.ndarray,
        owned: np.ndarray,
        owner: np.ndarray,
        x: np.ndarray,
        rows: dict[str, np.ndarray] | None = None,
        history: dict[str, np.ndarray] | None = None,
        mesh_q: np.ndarray | None = None,
    ) -> None:
        """Make ``index`` (global, ascending) this rank's local bodies and plan the ghost exchange."""
        self.local_index = np.asarray(index, dtype=np.int64)
        self.owned = np.asarray(owned, dtype=bool)
        self._x_partition = np.asarray(x, dtype=np.float64)
        self._repartition_due = False
        self.sim = None
        self._good = None
        # A rank steps its ghosts too, even with no body of its own: its neighbours send to every rank
        # whose slab and halo hold their bodies, and a rank that holds none has no Simulation.
        if len(self.local_index):
            self.sim = self._local_simulation(self.local_index)
            if rows is not None:
                saved = dict(rows)
                st = self.sim.current_state
                if not self.sim.model.friction:
                    saved["wall_xi"] = st.wall_xi.numpy()
                if mesh_q is not None:
                    saved["mesh_q"] = mesh_q
                saved["step_count"] = np.array([self.steps_done], dtype=st.step_count.numpy().dtype)
                saved.update(self._local_history(history))
                self.sim.restore_from_arrays(saved, self.steps_done, self.time)
        # Ghost exchange: my owned bodies held by rank s go to s; my ghosts owned by s come from s.
        holders = self._holders(x, self.local_index)
        free = self._free[self.local_index]
        self._send, self._recv = {}, {}
        dev = self.device
        for s in range(self.size):
            if s == self.rank:
                continue
            send = np.flatnonzero(self.owned & holders[:, s] & free)
            recv = np.flatnonzero((~self.owned) & (owner == s) & free)
            if len(send):
                self._send[s] = self._buffers(send)
            if len(recv):
                self._recv[s] = self._buffers(recv)
        self._apply_overlap()
        self._exchange_graphs = {}
        if self.sim is not None:
            st = self.sim.current_state
            # The poses and velocities hold the model's body scalar (State.dtypes): viewed as rows of it.
            scalar = self.sim.model.scalar
            self._views = tuple(getattr(st, f).view(scalar) for f in ("body_q", "body_v", "body_w"))
            self._damping = st.body_damping
            mine = (self.owned & self._free[self.local_index]).astype(np.int32)
            self._mine = wp.array(mine, dtype=int, device=dev)
            self._x0 = wp.array(self._x_partition, dtype=wp.float64, device=dev)
            self._moved = wp.zeros(1, dtype=wp.float64, device=dev)

    def set_exchange(self, exchange: str) -> None:
        """How the ghosts' rows travel: "host" or "nccl" (the ``exchange`` argument; collective: the first switch to
        "nccl" makes the NCCL communicator)."""
        if exchange not in EXCHANGES:
            raise ValueError(f"exchange must be one of {EXCHANGES} (or 'auto' when constructed), got {exchange!r}")
        if exchange == "nccl" and not self.device.is_cuda:
            raise ValueError(
                f"exchange='nccl' moves the ghost rows between GPUs, but this rank runs on {self.device}: "
                "use exchange='host' (or a CUDA device per rank)"
            )
        if exchange == "nccl" and self._nccl is None and self.size > 1:
            self._nccl = NcclExchange(self.comm, self.device)
        self.exchange = exchange
        self._exchange_graphs = {}

    def set_overlap(self, overlap: bool) -> None:
        """Send the ghosts while the step runs, or after it (the ``overlap`` argument; the same bits either way)."""
        self.overlap = bool(overlap)
        self._apply_overlap()

    def _apply_overlap(self) -> None:
        sim = self.sim
        split = sim is not None and self.overlap and bool(self._send) and sim.stepper.mesh_kernels is None
        if split:
            first = np.zeros(len(self.local_index), dtype=bool)
            for index, _, _ in self._send.values():
                first[index.numpy()] = True
            sim.split_at(first)
        elif sim is not None and sim.stepper.body_first is not None:
            sim.split_at(None)
        self.split = split

    def _buffers(self, index: np.ndarray) -> tuple[wp.array, wp.array, wp.array]:
        """(device index, device rows, host rows) for the ghost rows of ``index`` (local) that go to or
        come from one rank; the host rows are pinned memory on a GPU, the device rows themselves on the CPU."""
        dev = self.device
        scalar = self.sim.model.scalar
        rows = wp.empty((len(index), ROW), dtype=scalar, device=dev)
        host = rows if dev.is_cpu else wp.empty((len(index), ROW), dtype=scalar, device="cpu", pinned=True)
        return wp.array(np.asarray(index, dtype=np.int32), dtype=int, device=dev), rows, host

    def _local_history(self, history: dict[str, np.ndarray] | None) -> dict[str, np.ndarray]:
        """Pair history with global keys (``key`` = a * N + b) as this rank's keys, for its pairs."""
        n_all = self.num_bodies
        n = len(self.local_index)
        key = history["pair_key"] if history else np.zeros(0, np.int64)
        a, b = np.divmod(key, n_all)
        ia = np.searchsorted(self.local_index, a)
        ib = np.searchsorted(self.local_index, b)
        ok = (ia < n) & (ib < n)
        ok[ok] &= (self.local_index[ia[ok]] == a[ok]) & (self.local_index[ib[ok]] == b[ok])
        order = np.argsort(ia[ok].astype(np.int64) * n + ib[ok], kind="stable")
        st = self.sim.current_state
        xi_dtype = st.wall_xi.numpy().dtype
        return {
            "pair_key": (ia[ok].astype(np.int64) * n + ib[ok])[order],
            "pair_xi": history["pair_xi"][ok][order]
            if history and len(history["pair_xi"])
            else np.zeros((0, 3), xi_dtype),
            "pair_turn": history["pair_turn"][ok][order] if history else np.zeros(0, xi_dtype),
        }

    def _repartition(self) -> None:
        """Cut the slabs again and move bodies, ghosts and pair histories to their new ranks (collective)."""
        sim = self.sim
        x_local = self._coordinates()
        owned = self.owned
        self.cuts = self._histogram(x_local[owned])
        outgoing = [dict() for _ in range(self.size)]
        if sim is not None:
            st = sim.current_state.numpy()
            holders = self._holders(x_local, self.local_index)
            st["body_damping"] = sim.current_state.body_damping.numpy()
            rows = {k: st[k] for k in ("body_q", "body_v", "body_w", "body_dissipated", "body_damping", "wall_turn")}
            if sim.model.friction:
                rows["wall_xi"] = st["wall_xi"]
            hist = sim.current_contacts.history_numpy()
            n = len(self.local_index)
            la, lb = np.divmod(hist["pair_key"], n)
            mine = owned[la] | owned[lb]
            for s in range(self.size):
                go = np.flatnonzero(owned & holders[:, s])
                pairs = np.flatnonzero(mine & holders[la, s] & holders[lb, s])
                msg = {"index": self.local_index[go], **{k: v[go] for k, v in rows.items()}}
                msg["pair_key"] = self.local_index[la[pairs]] * self.num_bodies + self.local_index[lb[pairs]]
                msg["pair_xi"] = hist["pair_xi"][pairs] if len(hist["pair_xi"]) else hist["pair_xi"]
                msg["pair_turn"] = hist["pair_turn"][pairs]
                outgoing[s] = msg
        mesh_q = sim.current_state.mesh_q.numpy() if sim is not None else None
        mesh_q = next((m for m in self.comm.allgather(mesh_q) if m is not None), None)
        incoming = [m for m in self.comm.alltoall(outgoing) if m and len(m["index"]) + len(m["pair_key"])]
        index = np.concatenate([m["index"] for m in incoming]) if incoming else np.zeros(0, np.int64)
        order = np.argsort(index, kind="stable")
        index = index[order]
        if len(np.unique(index)) != len(index):
            raise DistributedError(f"rank {self.rank}: a body arrived twice at a repartition (a bug)")
        rows = {}
        if incoming:
            for k in incoming[0]:
                if k in ("index", "pair_key", "pair_xi", "pair_turn"):
                    continue
                rows[k] = np.concatenate([m[k] for m in incoming])[order]
        history = None
        if incoming:
            key = np.concatenate([m["pair_key"] for m in incoming])
            key, first = np.unique(key, return_index=True)  # a pair between two ranks came from both
            xi = [m["pair_xi"] for m in incoming if len(m["pair_xi"])]
            history = {
                "pair_key": key,
                "pair_xi": np.concatenate(xi)[first] if xi else np.zeros((0, 3)),
                "pair_turn": np.concatenate([m["pair_turn"] for m in incoming])[first],
            }
        x = rows["body_q"][:, self.axis].astype(np.float64) if rows else np.zeros(0)
        owner = partition.owner(x, self.cuts)
        self._set_local(index, owner == self.rank, owner, x, rows=rows, history=history, mesh_q=mesh_q)
        self.partitions += 1

    def _holders(self, x: np.ndarray, index: np.ndarray) -> np.ndarray:
        """(n, size) bool: the ranks that hold the bodies ``index`` (global) at coordinates ``x``: every
        rank for a body that is not free, else the owner and the ranks within the halo."""
        held = partition.holders(x, self.cuts, self.halo)
        held[~self._free[index]] = True
        return held

    def restore_global(self, arrays: dict[str, np.ndarray] | None, steps_done: int, time: float) -> None:
        """Put the whole scene's state ``arrays`` (named as a checkpoint's, given on ``root``) into the ranks
        and partition afresh (collective): resuming a checkpoint, whoever wrote it."""
        arrays = self.comm.bcast(arrays if self.rank == self.root else None, root=self.root)
        self.steps_done, self.time = int(steps_done), float(time)
        n = self.num_bodies
        x_all = np.asarray(arrays["body_q"])[:, self.axis].astype(np.float64)
        index, owner = self._partition_all(x_all)
        fields = ["body_q", "body_v", "body_w", "body_dissipated", "wall_turn"]
        if np.asarray(arrays["wall_xi"]).shape[0] == n and np.asarray(arrays["wall_turn"]).shape[0] == n:
            fields.append("wall_xi")
        rows = {k: np.asarray(arrays[k])[index] for k in fields}
        history = {k: np.asarray(arrays[k]) for k in ("pair_key", "pair_xi", "pair_turn")}
        mesh_q = arrays.get("mesh_q")
        self._set_local(index, owner[index] == self.rank, owner[index], x_all[index], rows, history, mesh_q)
        # Each rank computed its bodies' damping loads from the history it holds: a ghost's, which counts contacts
        # this rank lacks, from its owner.
        self._exchange()
        self.partitions += 1

    def saved_arrays(self) -> dict[str, np.ndarray] | None:
        """The whole scene's state as a checkpoint keeps it (``State.SAVED`` and the pair history, global
        keys ``a * N + b``) on ``root``, None elsewhere (collective)."""
        mine = None
        if self.sim is not None:
            st = self.sim.current_state.numpy()
            own = self.owned
            mine = {k: st[k][own] for k in ("body_q", "body_v", "body_w", "body_dissipated", "wall_turn")}
            if self.sim.model.friction:
                mine["wall_xi"] = st["wall_xi"][own]
            mine["index"] = self.local_index[own]
            mine["mesh_q"] = st["mesh_q"]
            hist = self.sim.current_contacts.history_numpy()
            la, lb = np.divmod(hist["pair_key"], len(self.local_index))
            keep = self._pair_is_mine(la, lb)
            mine["pair_key"] = self.local_index[la[keep]] * self.num_bodies + self.local_index[lb[keep]]
            mine["pair_xi"] = hist["pair_xi"][keep] if len(hist["pair_xi"]) else hist["pair_xi"]
            mine["pair_turn"] = hist["pair_turn"][keep]
        parts = self.comm.gather(mine, root=self.root)
        if self.rank != self.root:
            return None
        parts = [p for p in parts if p is not None]
        n = self.num_bodies
        out = {}
        for k in ("body_q", "body_v", "body_w", "body_dissipated", "wall_turn", "wall_xi"):
            if k not in parts[0]:
                continue
            a = np.zeros((n, *parts[0][k].shape[1:]), dtype=parts[0][k].dtype)
            for p in parts:
                a[p["index"]] = p[k]
            out[k] = a
        if "wall_xi" not in out:
            out["wall_xi"] = self.sim.current_state.wall_xi.numpy() if self.sim is not None else np.zeros((1, 1, 3))
        out["mesh_q"] = parts[0]["mesh_q"]
        out["step_count"] = np.array([self.steps_done], dtype=np.int32)
        key = np.concatenate([p["pair_key"] for p in parts])
        order = np.argsort(key, kind="stable")
        out["pair_key"] = key[order]
        xi = [p["pair_xi"] for p in parts if len(p["pair_xi"])]
        out["pair_xi"] = np.concatenate(xi)[order] if xi else parts[0]["pair_xi"]
        out["pair_turn"] = np.concatenate([p["pair_turn"] for p in parts])[order]
        return out

    def _coordinates(self) -> np.ndarray:
        if self.sim is None:
            return np.zeros(0)
        return self.sim.current_state.body_q.numpy()[:, self.axis].astype(np.float64)

    # -- stepping -------------------------------------------------------------------------------

    def step(self, n: int = 1) -> None:
        """Advance every rank ``n`` steps (collective).

        The ranks step in chunks of at most ``chunk`` steps, exchanging ghosts after every step and
        agreeing once per chunk (one allreduce): on a clipped polygon or a pair list that did not fit
        on some rank, or a body that moved further than the halo allows, every rank goes back to the
        start of the chunk (the overflowing rank with more room, or all with a new partition) and
        steps it again; a non-finite state on some rank raises :class:`DistributedError` on all.
        """
        n = int(n)
        if n < 0:
            raise ValueError(f"step count must be >= 0, got {n}")
        done = 0
        chunk = self.chunk
        start_time = self.time
        if n and self._repartition_due:
            self._timed_repartition()
        while done < n:
            k = min(chunk, n - done)
            t0 = time.perf_counter()
            sim = self.sim
            if sim is not None:
                self._good = sim.snapshot(into=self._good)
            compute = exchange = 0.0
            error = ""
            # The timers' split needs each step's kernels done before the exchange: no overlap then.
            split = self.split and not self.sync_timers
            for _ in range(k):
                t1 = time.perf_counter()
                packed, ready = False, None
                if sim is not None and not error:
                    try:
                        if split:
                            ready = sim.advance_split(self._step_rows, key=("ghost rows", self.exchange))
                            packed = True
                        else:
                            sim.advance(1)
                    except Exception as exc:  # the others must hear of it at the agreement, not wait forever
                        error = f"rank {self.rank}: {type(exc).__name__}: {exc}"
                if self.sync_timers and sim is not None:
                    wp.synchronize_device(self.device)  # so that compute holds the step's kernels, not their launch
                t2 = time.perf_counter()
                if not self._exchange(packed, ready):
                    self._track_move()
                compute += t2 - t1
                exchange += time.perf_counter() - t2
            t3 = time.perf_counter()
            flags = self._chunk_flags() if not error else (0.0, 0.0, 1.0, 0.0)
            worst = self._allreduce(flags, "max_pair")
            self.timers["compute"] += compute
            self.timers["exchange"] += exchange
            self.timers["wait"] += time.perf_counter() - t3
            if worst[2]:
                messages = [m for m in self.comm.allgather(error or self._bad_message()) if m]
                raise DistributedError("; ".join(messages))
            redo_room, moved = worst[0] > 0 or worst[1] > 0, worst[3]
            if redo_room or moved > 0.5 * self.margin:
                self.redone += 1
                if sim is not None:
                    if flags[0]:
                        sim.stepper.grow_buffers()
                    sim.restore(self._good)
                # restore computed the damping loads from this rank's history: the ghosts' from their owners
                self._exchange()
                if moved > 0.5 * self.margin:
                    # The chunk went past the halo's margin: partition at its start and step it again,
                    # in shorter chunks (a body that fast reaches the margin sooner).
                    self._timed_repartition()
                    chunk = max(1, chunk // 2)
                continue
            if sim is not None and sim.stepper.device_rebuild:
                sim.current_contacts.broadphase.renew_tree(sim.tree_rebuild)
            done += k
            self.steps_done += k
            self.time = simulation_time(start_time, done, n, self.dt)
            if sim is not None:
                sim.steps_done, sim.time = self.steps_done, self.time
            if moved > 0.25 * self.margin:
                # Half the allowance used: partition before the next chunk, so that it has room. After
                # the call's last chunk that waits for the next call: a partition builds new local
                # simulations, which would lose the last step's inputs that contacts() reports from.
                if done < n:
                    self._timed_repartition()
                else:
                    self._repartition_due = True
            self.timers["total"] += time.perf_counter() - t0

    def _timed_repartition(self) -> None:
        t0 = time.perf_counter()
        self._repartition()
        self.timers["partition"] += time.perf_counter() - t0

    def _chunk_flags(self) -> tuple[float, float, float, float]:
        """(polygon or mesh candidate overflow, pair list overflow, non-finite state, largest move [m]) of this
        rank's chunk."""
        sim = self.sim
        if sim is None:
            return (0.0, 0.0, 0.0, 0.0)
        overflow = sim.stepper.buffers_overflowed()
        host_build = sim.stepper.device_rebuild and sim.current_contacts.host_build_needed()
        bad = sim.stepper.first_bad_step() is not None
        return (float(overflow), float(host_build), float(bad), float(self._moved.numpy()[0]))

    def _bad_message(self) -> str:
        sim = self.sim
        if sim is None or sim.stepper.first_bad_step() is None:
            return ""
        bad = sim.stepper.first_bad_step()
        st = sim.state()
        rows = ~np.isfinite(np.hstack([st[k] for k in ("body_position", "body_velocity", "body_angular_velocity")]))
        bodies = self.local_index[rows.any(axis=1)]
        return (
            f"rank {self.rank}: the state became non-finite at step {bad} (t = {bad * self.dt:.6g} s); bodies "
            f"{bodies[:20].tolist()}{' ...' if len(bodies) > 20 else ''}. Check the time step (dt = {self.dt:.3g} s), "
            "the stiffness and the initial overlaps."
        )

    def _step_rows(self) -> None:
        """Launch the rows of my bodies that are ghosts elsewhere as this step will leave them, and their copy to
        the host, or with NCCL the exchange itself (the first part of a split step, after the forces on them)."""
        sim = self.sim
        st, m = sim.current_state, sim.model
        for index, rows, host in self._send.values():
            launch_step_rows(model=m.bodies, gravity=m.gravity, dt=self.dt, bodies=st.bodies, damping=st.body_damping,
                             index=index, rows=rows)  # fmt: skip
            if host is not rows and self.exchange == "host":
                wp.copy(host, rows)
        if self.exchange == "nccl":
            self._post_nccl()

    def _post_nccl(self) -> None:
        """Enqueue the step's NCCL sends and receipts on the current stream (none with one rank)."""
        if self._nccl is None:
            return
        send = {s: rows for s, (_, rows, _) in self._send.items()}
        recv = {s: rows for s, (_, rows, _) in self._recv.items()}
        self._nccl.post(send, recv, wp.get_stream(self.device))

    def _device_exchange(self, packed: bool) -> None:
        """The exchange with NCCL, all of it enqueued on the device (captured once as a graph with the sim's graphs):
        the rows packed from the state unless ``packed`` (sent and received by the step), the ghosts unpacked, the
        largest move raised (:meth:`_track_move`)."""
        if not self.sim.use_graph:
            self._enqueue_device_exchange(packed)
            return
        graph = self._exchange_graphs.get(packed)
        if graph is None:
            with wp.ScopedCapture(device=self.device) as capture:
                self._enqueue_device_exchange(packed)
            graph = self._exchange_graphs[packed] = capture.graph
        wp.capture_launch(graph)

    def _enqueue_device_exchange(self, packed: bool) -> None:
        q, v, w = self._views
        if not packed:
            for index, rows, _ in self._send.values():
                launch_pack_rows(q=q, v=v, w=w, damping=self._damping, index=index, rows=rows)
            self._post_nccl()
        for index, rows, _ in self._recv.values():
            launch_unpack_rows(rows=rows, index=index, q=q, v=v, w=w, damping=self._damping)
        self._track_move()

    def _exchange(self, packed: bool = False, ready: wp.Event | None = None) -> bool:
        """Send the new poses, velocities and damping loads of my bodies that are ghosts elsewhere; take my
        ghosts' from their owners. ``packed``: the rows to send were launched by the step (:meth:`_step_rows`),
        done once ``ready`` is (None: once the device is); else packed here from the state after the step. Returns
        whether it also raised the largest move (:meth:`_track_move`: the NCCL exchange's graph does)."""
        comm = self.comm
        if isinstance(comm, SerialComm) or self.sim is None:
            return False
        if self.exchange == "nccl":
            self._device_exchange(packed)
            self.sim.forget_diagnostics()
            return True
        from mpi4py import MPI

        dev = self.device
        requests = []
        q, v, w = self._views
        if not packed:
            for index, rows, host in self._send.values():
                launch_pack_rows(q=q, v=v, w=w, damping=self._damping, index=index, rows=rows)
                if host is not rows:
                    wp.copy(host, rows)
        if ready is not None:
            wp.synchronize_event(ready)  # the rows only: the rest of the step may still run
        elif not dev.is_cpu:
            wp.synchronize_device(dev)
        for s, (_, _, host) in self._send.items():
            requests.append(comm.Isend(host.numpy(), dest=s, tag=11))
        for s, (_, _, host) in self._recv.items():
            requests.append(comm.Irecv(host.numpy(), source=s, tag=11))
        MPI.Request.Waitall(requests)
        for index, rows, host in self._recv.values():
            if host is not rows:
                wp.copy(rows, host)
            launch_unpack_rows(rows=rows, index=index, q=q, v=v, w=w, damping=self._damping)
        self.sim.forget_diagnostics()
        return False

    def _track_move(self) -> None:
        """Raise ``_moved`` (device) to the largest move along the axis of a free body of mine since the
        partition [m]; no host synchronisation."""
        if self.sim is None:
            return
        launch_largest_move(q=self._views[0], axis=self.axis, x0=self._x0, mine=self._mine, moved=self._moved)

    def _allreduce(self, value: float | np.ndarray | tuple[float, ...], how: str) -> Any:
        comm = self.comm
        if isinstance(comm, SerialComm):
            return value
        from mpi4py import MPI

        if how == "max_pair" or isinstance(value, np.ndarray):
            buf = np.ascontiguousarray(value, dtype=np.float64 if how == "max_pair" else value.dtype)
            out = np.empty_like(buf)
            comm.Allreduce(buf, out, op=MPI.MAX if how == "max_pair" else {"sum": MPI.SUM, "max": MPI.MAX}[how])
            return tuple(out.tolist()) if how == "max_pair" else out
        return comm.allreduce(value, op={"min": MPI.MIN, "max": MPI.MAX, "sum": MPI.SUM}[how])

    # -- reading the state (collective) -----------------------------------------------------------

    def _pair_is_mine(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Whether this rank books the contacts of local bodies ``a`` and ``b`` (``b < 0``: a wall): the owner
        of A does, or of B where A is a fixed or kinematic body (held by every rank, so the grain's owner
        has the pair, and the body's own owner may not)."""
        a = np.asarray(a)
        b = np.asarray(b)
        free = self._free[self.local_index]
        by_b = (b >= 0) & ~free[a]
        return np.where(by_b, self.owned[np.maximum(b, 0)], self.owned[a])

    def _owned_rows(self) -> dict[str, np.ndarray] | None:
        if self.sim is None:
            return None
        st = self.sim.state()
        return {"index": self.local_index[self.owned], **{k: v[self.owned] for k, v in st.items()}}

    def state(self) -> dict[str, np.ndarray] | None:
        """The whole scene's state on ``root`` (as :meth:`Simulation.state`, in global body order), None elsewhere."""
        parts = self.comm.gather(self._owned_rows(), root=self.root)
        if self.rank != self.root:
            return None
        parts = [p for p in parts if p is not None]
        n = self.num_bodies
        out = {}
        for k in ("body_position", "body_orientation", "body_velocity", "body_angular_velocity"):
            width = parts[0][k].shape[1]
            a = np.full((n, width), np.nan)
            for p in parts:
                a[p["index"]] = p[k]
            out[k] = a
        return out

    def contacts(self) -> dict[str, np.ndarray] | None:
        """The whole scene's contacts on ``root`` (as :meth:`Simulation.contacts`, body indices global:
        pairs in key order, then wall contacts by body and wall), None elsewhere. Each contact comes
        from the rank owning its body A (B where A is not free): none is missed or counted twice."""
        mine = None
        if self.sim is not None:
            c = self.sim.contacts()
            keep = self._pair_is_mine(c["body_a"], c["body_b"])
            g = {k: v[keep] for k, v in c.items()}
            b = g["body_b"]
            g["body_a"] = self.local_index[g["body_a"]]
            g["body_b"] = np.where(b >= 0, self.local_index[np.maximum(b, 0)], b)
            mine = g
        parts = [p for p in (self.comm.gather(mine, root=self.root) or []) if p is not None]
        if self.rank != self.root:
            return None
        out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        a, b = out["body_a"], out["body_b"]
        wall = b < 0
        # Pairs first, by key; then wall contacts by body and wall (Simulation.contacts' order).
        order = np.lexsort((np.where(wall, -1 - b, b), a, wall))
        return {k: v[order] for k, v in out.items()}

    def energy(self) -> dict[str, float]:
        """The energies of :meth:`Simulation.energy`, summed over the ranks (on every rank): each rank
        books its own bodies and the pairs it owns."""
        keys = ("kinetic", "contact", "gravity", "dissipated")
        parts = np.zeros(4)
        if self.sim is not None:
            bp = self.sim.current_contacts.broadphase
            count = len(self.sim.diagnostics()["pair_energy"])
            mine = self._pair_is_mine(bp.pair_a.numpy()[:count], bp.pair_b.numpy()[:count])
            e = self.sim.energy(bodies=self.owned, pairs=mine)
            parts = np.array([e[k] for k in keys])
        total = self._allreduce(parts, "sum").tolist()
        out = dict(zip(keys, total, strict=True))
        out["total"] = sum(total)
        return out

    def settle_measures(self) -> tuple[float, float, float]:
        """(kinetic energy [J], gravitational energy [J], largest speed [m/s]) of the free bodies, as
        :meth:`Simulation.settle_measures`, over all ranks (on every rank)."""
        kin = grav = speed = 0.0
        if self.sim is not None:
            sim, m = self.sim, self.sim.model
            st = sim.current_state
            lin, ang = kinetic_energy(
                m.body_inv_mass, m.body_inertia, m.body_flags, st.body_q, st.body_v, st.body_w, device=sim.device
            )
            free = self.owned & (m.body_flags_np == BodyKind.FREE)
            kin = float(np.sum(lin.numpy()[free], dtype=np.float64) + np.sum(ang.numpy()[free], dtype=np.float64))
            x = st.body_q.numpy()[:, :3].astype(np.float64)
            grav = -float(np.sum(m.body_mass[free].astype(np.float64) * (x[free] @ m.gravity)))
            v = np.linalg.norm(st.body_v.numpy()[free].astype(np.float64), axis=1)
            w = np.linalg.norm(st.body_w.numpy()[free].astype(np.float64), axis=1)
            r = m.body_radius.numpy()[free].astype(np.float64)
            speed = float(np.max(v + w * r, initial=0.0))
        kin, grav = self._allreduce(np.array([kin, grav]), "sum").tolist()
        speed = self._allreduce(speed, "max")
        return kin, grav, speed

    def balance(self) -> tuple[np.ndarray, np.ndarray]:
        """Owned and local (owned + ghost) body counts of every rank, on every rank: two (size,) arrays."""
        counts = self.comm.allgather((int(self.owned.sum()), len(self.local_index)))
        return np.array([c[0] for c in counts]), np.array([c[1] for c in counts])
