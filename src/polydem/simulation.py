"""Simulation: a Model, its State and Contacts, and the Stepper that advances them.

Data flows one way::

    Scene --> Model (static) + State (bodies, wall contacts) + Contacts (pair list and its history)
    each step: state_in -> broad phase (Contacts) -> pair contacts -> gather per body (plus the
               walls) -> integrate -> finiteness check -> state_out

:class:`Stepper` is the step: ``step(state_in, state_out, contacts, dt)``. The broad phase is a
Verlet list: it is rebuilt only when some body moved far enough. :class:`Simulation` is the
front: it builds the three from a scene, steps them in place, and reads energies and contacts.
On a CUDA device the step is captured once as a CUDA graph, the broad-phase rebuild as a
conditional node inside it, and replayed; the CPU runs the same kernels.

The scene's ``precision`` ("float32", "mixed" or "float64"; :mod:`polydem.kernels.precision`) sets
the dtypes of the Model, State and Contacts arrays and the variant of every kernel; what
:meth:`Simulation.state`, :meth:`Simulation.contacts` and :meth:`Simulation.energy` return is float64
numpy in every precision.

Steps run in chunks between host checks. A chunk starts from a saved copy of the state and the
pair history; when something overflowed during the chunk (the candidate-pair buffer in a device
rebuild, or a clipped polygon) the copy is restored, the buffer grown, and the chunk run again, so
no contact is ever dropped. A non-finite value stops the run with an error naming the step and
the bodies; a body faster than a step or its contacts can stop before it has crossed the thinnest
body (:meth:`polydem.Scene.tunnelling_limits`) is warned about once (:class:`SimulationWarning`).
The last step of a :meth:`Simulation.step` call runs alone in its chunk: its saved copy is then what
its force stage read, which :meth:`Simulation.contacts` runs again to report the forces that step
applied. An average of the contact forces over an interval (:meth:`Simulation.start_contact_average`)
is summed on the device by the steps themselves (:class:`~polydem.contacts.ContactAverage`).
"""

from __future__ import annotations

import math
import time as _time
import warnings
from collections.abc import Callable, Hashable, Sequence
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any, Literal, NoReturn

import numpy as np
import warp as wp

from polydem.contacts import (
    THREAD_ORDERS,
    AverageSnapshot,
    ContactAverage,
    Contacts,
    PairHistory,
    contact_sums,
)
from polydem.kernels.broadphase import TREE_REBUILD_RATIO
from polydem.kernels.forces import (
    PAIR_MAX_REGISTERS,
    REPORT_CONTACTS,
    REPORT_SUMS,
    ContactKernels,
    ContactOutputs,
    ContactSums,
    PairArrays,
    launch_damping_load,
    launch_gather,
    launch_pair_contacts,
    make_contact_kernels,
    spread_fits,
    spread_room,
)
from polydem.kernels.geometry import shared_poly_fits
from polydem.kernels.integrate import (
    kinetic_energy,
    launch_check_state,
    launch_count_step,
    launch_integrate,
    launch_integrate_and_check,
    launch_settle_measures,
)
from polydem.kernels.meshwall import (
    MeshCandidates,
    MeshKernels,
    MeshWallState,
    launch_advance_meshes,
    launch_mesh_contacts,
    make_mesh_kernels,
)
from polydem.kernels.motion import LANES, launch_drive_bodies, launch_drive_walls, launch_measure_motions
from polydem.kernels.precision import numpy_dtype, scalars
from polydem.kernels.structs import (
    bodies_struct,
    filled,
    mesh_walls_struct,
    pairs_struct,
    planes_struct,
    wall_history_struct,
)
from polydem.model import Model
from polydem.overlap_check import device_check_applies, device_pair_overlaps
from polydem.run_settings import RunSettings, run_settings
from polydem.scene import SceneError
from polydem.scene.bodies import BodyKind
from polydem.settle import SettleCheck, SettleCriterion, SettleResult
from polydem.state import State

if TYPE_CHECKING:
    from polydem.scene import Scene

__all__ = ["Simulation", "SimulationError", "SimulationWarning", "Snapshot", "StepInputs", "Stepper"]

CHUNK_STEPS = 64
NO_STEP = 2**31 - 1


class SimulationError(RuntimeError):
    """The run cannot go on (a non-finite state); the message names the step and the bodies."""


class SimulationWarning(UserWarning):
    """Something in the run is suspect but it goes on (a body fast enough to tunnel)."""


class Stepper:
    """One time step of a :class:`~polydem.model.Model`: ``step(state_in, state_out, contacts, dt)``.

    Stages: :meth:`collide` (the broad phase: rebuild the pair list when needed), :meth:`forces`
    (pair contacts, then the gather per body with the walls, then each body's damping load for the next
    step), :meth:`integrate` (and the finiteness check). The kernels update their arrays in place; ``state_out`` may be
    ``state_in`` (the :class:`Simulation` steps in place, so one captured graph serves every step).

    Args:
        model: the model.
        device_rebuild: rebuild the pair list on the device, without host synchronisation (for
            CUDA graph capture); an overflow is then reported by ``contacts.host_build_needed()``.
        pair_max_registers: CUDA register cap per thread of the pair kernels (None: the compiler's
            choice); the results do not depend on it (benchmarks/settle.py --max-registers).
        thread_order: the pair kernel's thread t takes pair ``contacts.pairs.thread[t]`` (the contacts must
            have been made with ``thread_order``); the results do not depend on it.
        mesh_candidates: as for :class:`Simulation` (None: on CUDA).
        spread: the thread order is grouped by contact, the costliest first (the contacts' default): the pair
            kernel spreads its first pairs over more lanes (:meth:`set_spread`; on a GPU only by default).

    Attributes:
        poly_capacity: room for the vertices of a clipped polygon (grows with :meth:`grow_buffers`).
        mesh_candidates: the :class:`~polydem.kernels.meshwall.MeshCandidates` of the mesh-wall contacts (grow
            with :meth:`grow_buffers`), or None (no mesh walls, or the walk).
        poly_overflow: (1,) int32, set when a clipped polygon did not fit (the step must be redone).
        bad_step: (1,) int32, the first step whose state was not finite (``NO_STEP``: none yet).
        body_speed_limit: (N,) float32 speed of a body's fastest point above which it may tunnel
            [m/s] (:meth:`polydem.Scene.tunnelling_limits`; inf until the Simulation sets it).
        body_peak_speed: (N,) float32 largest speed of each body's fastest point so far [m/s].
        too_fast: (1,) int32, set when a body went above its speed limit.
        keep_inputs: a :class:`StepInputs` that the next steps copy their force stage's inputs into
            (for :meth:`report`), or None.
        average: a :class:`~polydem.contacts.ContactAverage` that the next steps add each contact's
            force to, or None.
        body_first: (N,) int32, the bodies whose contacts and new state :meth:`step_part` 1 computes (None:
            the step is not split; :meth:`split_at`).
        shared_poly: the pair kernel clips with its polygon buffer in shared memory where it fits (the default;
            :meth:`set_shared_poly`; ``kernels.shared_poly`` says whether it does now).
    """

    def __init__(
        self,
        model: Model,
        device_rebuild: bool = False,
        pair_max_registers: int | None = PAIR_MAX_REGISTERS,
        thread_order: bool = False,
        mesh_candidates: bool | None = None,
        spread: bool = False,
    ) -> None:
        self.model = model
        self.thread_order = bool(thread_order)
        self.device = model.device
        self.device_rebuild = bool(device_rebuild)
        self.poly_capacity = model.shapes.default_poly_capacity
        self.poly_overflow = wp.zeros(1, dtype=int, device=self.device)
        # The diagnostics pass has its own flag: it must not leave one set for the next chunk.
        self._diag_overflow = wp.zeros(1, dtype=int, device=self.device)
        self.bad_step = wp.full(1, NO_STEP, dtype=int, device=self.device)
        n = model.num_bodies
        self.body_speed_limit = wp.full(n, float("inf"), dtype=float, device=self.device)
        self.body_peak_speed = wp.zeros(n, dtype=float, device=self.device)
        self.too_fast = wp.zeros(1, dtype=int, device=self.device)
        self.pair_max_registers = pair_max_registers
        # The partial force sums of the ramps' and servos' bodies (kernels/motion.py), made before any capture.
        rows = len(model.measured_rows) if model.has_measured_motions else 0
        self._motion_parts = wp.zeros((max(rows, 1), LANES), dtype=wp.vec3d, device=self.device)
        self._wall_arrays()
        if mesh_candidates is None:
            mesh_candidates = wp.get_device(self.device).is_cuda
        self.mesh_candidates: MeshCandidates | None = None
        self._steps_overflowed = False  # the candidates of a step overflowed, seen (and grown) by a later pass
        if model.num_mesh_walls and mesh_candidates:
            # Room for a quarter of the bodies' worth to start with: it grows to what a step lists.
            self.mesh_candidates = MeshCandidates(n, max(1024, n // 4), model.precision, self.device)
        self.body_first: wp.array | None = None
        self.body_first_index: wp.array | None = None
        # With the pair threads ordered, a split step's first part launches this many (grown when too few).
        self.first_room = 1024
        self.first_overflow = wp.zeros(1, dtype=int, device=self.device)
        # The costliest pairs of the thread order spread over more warps (kernels/forces.py SPREAD_LANES): where
        # the launch is a wave or less, and the costly shapes' pairs.
        self._spread_allowed = bool(spread) and self.thread_order
        # set_shared_poly: on by default, measured faster on an H200 (BENCHMARKS.md section 31)
        self.shared_poly = True
        self.spread_pairs, self.spread_threads = (0, 0)
        if self._spread_allowed:
            self.spread_pairs, self.spread_threads = spread_room(self.device, pair_max_registers)
        self._kernels()
        self._diag: ContactOutputs | None = None
        self._diag_generation: int | None = None
        # What the kernels take where they write nothing: made here, not on the first (captured) step.
        self._no_outputs = ContactOutputs.zeros(1, 1, 1, model.precision, self.device)
        self._no_sums = contact_sums(1, self.device)
        self._no_loads = wp.zeros(0, dtype=wp.float32, device=self.device)
        self._no_first = wp.zeros(1, dtype=wp.int32, device=self.device)
        self.keep_inputs: StepInputs | None = None
        self.average: ContactAverage | None = None
        self._report: tuple[ContactOutputs, dict[str, wp.array]] | None = None  # the outputs and scratch arrays
        self._report_generation: int | None = None
        self._history_on: tuple[int, wp.array, wp.array] | None = None  # the pair history of history_on()

    def _wall_arrays(self) -> None:
        """The plane and mesh walls the contact kernels take: the model's, or where walls follow motions, copies
        with the Stepper's own offsets and velocities, set from the step counter before each force stage
        (``drive_walls``) and so never carried by a snapshot or checkpoint."""
        m = self.model
        self.planes, self.meshes = m.planes, m.meshes
        self._mesh_v = None
        if not m.has_wall_motions:
            return
        self.planes = filled(
            planes_struct(m.scalar),
            normal=m.plane_normal,
            offset=wp.clone(m.plane_offset),
            material=m.plane_material,
            v=wp.clone(m.plane_v),
        )
        if m.meshes is None:
            self._mesh_v = wp.zeros(1, dtype=wp.types.vector(3, m.scalar), device=self.device)
            return
        self._mesh_v = wp.clone(m.mesh_v)
        self.meshes = filled(
            mesh_walls_struct(m.scalar),
            **{k: getattr(m.meshes, k) for k in ("bvh", "cell_start", "material", "w", "cell_shape", "cell_center")},
            cell_front=m.meshes.cell_front,
            first_column=m.meshes.first_column,
            v=self._mesh_v,
        )

    def drive_walls(self, state: State, dt: float, step_offset: int = 0) -> None:
        """The driven plane and mesh walls where their motions put them at the end of step
        ``state.step_count[0] + step_offset``."""
        m = self.model
        if m.has_wall_motions:
            launch_drive_walls(
                m.motions, state.step_count, step_offset, dt, self.planes, state.mesh_q, self._mesh_v, self.device
            )

    def _kernels(self) -> None:
        self.kernels = self._contact_kernels()
        self.mesh_kernels = self._mesh_kernels(False)

    def _contact_kernels(self, diagnostics: bool = False, report: bool = False, spread: bool = True) -> ContactKernels:
        """The pair and gather kernels of the model at the current polygon capacity: the step's, the
        diagnostics variant or the report variant; ``spread`` False: never the spread variant."""
        m = self.model
        spread = spread and self.body_first is None and self.spread_pairs > 0
        return make_contact_kernels(
            m.law,
            m.friction,
            self.poly_capacity,
            m.shapes.max_faces,
            diagnostics=diagnostics,
            precision=m.precision,
            max_registers=self.pair_max_registers,
            compound=m.shapes.compound,
            report=report,
            thread_order=self.thread_order,
            phased=self.body_first is not None and not diagnostics,
            spread=spread,
            shared_poly=self.shared_poly and shared_poly_fits(scalars(m.precision)[1], self.poly_capacity),
        )

    def _mesh_kernels(self, diagnostics: bool, report: bool = False) -> MeshKernels | None:
        if not self.model.num_mesh_walls:
            return None
        return make_mesh_kernels(self._contact_kernels(diagnostics, report))

    def _report_kernels(self) -> tuple[ContactKernels, MeshKernels | None]:
        """The report variant of the step's kernels (built on first use: a run that never asks for
        its contacts or an average never compiles it): (contact kernels, mesh kernels or None)."""
        return self._contact_kernels(report=True), self._mesh_kernels(False, report=True)

    def split_at(self, body_first: np.ndarray | None) -> None:
        """Split each step in two parts (:meth:`step_part`): the first computes the contacts of the bodies
        flagged in ``body_first`` ((N,) bool) and the forces on them, so that their new state can be computed
        (:func:`polydem.kernels.ghosts.launch_step_rows`) before the second has run; None: one part. The same
        bits either way. Not with mesh walls (their contacts come after the gather of every body). With the pair
        threads ordered, the contacts must be ordered for it too (:meth:`Simulation.split_at` does both)."""
        self.first_overflow.zero_()
        if body_first is None:
            self.body_first = None
            self.body_first_index = None
        else:
            if self.mesh_kernels is not None:
                raise ValueError("a step with mesh walls cannot be split in two parts (their contacts come last)")
            flags = np.asarray(body_first, dtype=bool)
            if flags.shape != (self.model.num_bodies,):
                raise ValueError(f"body_first must have one flag per body ({self.model.num_bodies}), got {flags.shape}")
            self.body_first = wp.array(flags.astype(np.int32), dtype=wp.int32, device=self.device)
            self.body_first_index = wp.array(np.flatnonzero(flags).astype(np.int32), dtype=int, device=self.device)
        self._kernels()

    def grow_buffers(self) -> None:
        """After :meth:`buffers_overflowed`: double the room for clipped polygons (new kernels), grow the
        mesh-wall candidate list (new arrays) or double a split step's first part (:attr:`first_room`),
        whichever overflowed; recapture a graph."""
        if int(self.first_overflow.numpy()[0]):
            self.first_overflow.zero_()
            self.first_room *= 2
        if int(self.poly_overflow.numpy()[0]):
            self.poly_overflow.zero_()
            self.poly_capacity = min(2 * self.poly_capacity, self.model.shapes.max_poly_bound)
            self._kernels()
        if self.mesh_candidates is not None and self.mesh_candidates.overflowed():
            self.mesh_candidates.grow()
        self._steps_overflowed = False

    def clear_checks(self) -> None:
        """Forget the non-finite steps and the speeds recorded so far (their states were discarded by a restore)."""
        self.bad_step.fill_(NO_STEP)
        self.body_peak_speed.zero_()
        self.too_fast.zero_()

    def went_too_fast(self) -> bool:
        """Host: whether a body went above its ``body_speed_limit`` since :meth:`clear_checks`."""
        return bool(int(self.too_fast.numpy()[0]))

    def buffers_overflowed(self) -> bool:
        """Host: whether a clipped polygon or the mesh-wall candidates did not fit since :meth:`grow_buffers`."""
        if self._steps_overflowed or (self.mesh_candidates is not None and self.mesh_candidates.overflowed()):
            return True
        if self.body_first is not None and int(self.first_overflow.numpy()[0]):
            return True
        return bool(int(self.poly_overflow.numpy()[0]))

    @property
    def buffer_generation(self) -> tuple[int, int, int, int, int]:
        """What a captured step depends on besides the pair list: the polygon room, the candidate list's arrays, the
        split's first room and the spread pairs."""
        mesh = 0 if self.mesh_candidates is None else self.mesh_candidates.generation
        return self.poly_capacity, mesh, self.first_room, self.spread_pairs, self.spread_threads

    def set_spread(self, pairs: int, threads: int | None = None) -> None:
        """Spread at most ``pairs`` of the first pairs of the thread order over
        :data:`~polydem.kernels.forces.SPREAD_LANES` lanes each: as many as a launch of ``threads`` threads leaves
        room for (None: the device's wave, :func:`~polydem.kernels.forces.spread_room`), or, where the list holds
        at most twice ``threads`` pairs, the pairs of costly shapes (0 pairs: none). The spread pair's other lanes
        idle: sharing its faces among them was slower for cubes, rocks and 64-vertex hulls on an H200 (each lane
        repeats the pair's set-up; BENCHMARKS.md sections 30 and 31; that variant is at git tag ``pair-lanes-30``).
        The same bits either way. Needs the pair threads grouped by contact (the default)."""
        pairs = int(pairs)
        if pairs < 0:
            raise ValueError(f"spread pairs must be >= 0, got {pairs}")
        if pairs and not self._spread_allowed:
            raise ValueError(
                "spreading the pairs needs the pair threads grouped by contact, the costliest first (Simulation's "
                "default, order_pair_threads=True)"
            )
        self.spread_pairs = pairs
        self.spread_threads = spread_room(self.device, self.pair_max_registers)[1] if threads is None else int(threads)
        self._kernels()

    def set_shared_poly(self, on: bool) -> None:
        """Clip in the pair kernel with its polygon buffer in the block's shared memory (make_geometry's
        ``shared_poly``; the default; benchmarks/settle.py --no-shared-poly turns it off) wherever it fits: float32
        clipping (precision "float32" or "mixed"), at most 63 vertices a polygon (else the per-thread buffer in
        local memory). On the CPU, whose kernels run one thread after another, one static buffer. The same bits
        either way; on an H200 the shared buffer is 2-5% faster in mixed and cube piles of 1e4 and 1e5 grains and
        gives the pair kernel 5% more pairs a second (BENCHMARKS.md sections 30 and 31)."""
        self.shared_poly = bool(on)
        self._kernels()

    def first_bad_step(self) -> int | None:
        """Host: the first step whose state was not finite, or None."""
        bad = int(self.bad_step.numpy()[0])
        return None if bad == NO_STEP else bad

    # -- one step ------------------------------------------------------------------------------

    def step(self, state_in: State, state_out: State, contacts: Contacts, dt: float) -> None:
        """Advance ``state_in`` by ``dt`` into ``state_out`` (which may be ``state_in``); updates ``contacts``.

        With :attr:`keep_inputs` set, the step copies what its force stage reads into it; with
        :attr:`average` set, the force stage adds each contact's force to its sums.
        """
        if state_out is not state_in:
            state_out.assign(state_in)
        self.collide(state_out, contacts)
        if self.keep_inputs is not None:
            self.keep_inputs.save(state_out, contacts)
        self.forces(state_out, contacts, dt)
        if self.model.has_measured_motions:
            # The ramps' and servos' force from this force stage, and where they go at the end of the step.
            launch_measure_motions(self.model, contacts, self._motion_parts, state_out.step_count, 1, dt,
                                   state_out.motion_travel, device=self.device)  # fmt: skip
        self.integrate(state_out, dt)

    SPLIT_PARTS = ("collide", "first", "pairs", "rest")
    """The parts of a split step, in the order :meth:`step_part` takes them: "first" and "pairs" write disjoint
    arrays (each pair's slot once; the flagged bodies' forces, loads and wall histories) and may run at once."""

    def step_part(self, state: State, contacts: Contacts, dt: float, part: str) -> None:
        """One part of a split step (:meth:`split_at`), in place: "collide" the broad phase, "first" the force
        stage of the flagged bodies (their pairs, their gather), "pairs" the other pairs, "rest" the other
        bodies' gather and the integration. The parts in :data:`SPLIT_PARTS`' order are :meth:`step` with
        ``state_out`` = ``state_in``, to the bit, and so are they with "first" and "pairs" run concurrently."""
        if self.body_first is None:
            raise RuntimeError("the step is not split: call split_at() first")
        if self.thread_order and getattr(contacts, "body_first", None) is not self.body_first:
            # The ordered kernels take each part's pairs from the contacts' order: it must be the split's.
            raise RuntimeError("the contacts' thread order is not this split's: call Simulation.split_at()")
        if part == "collide":
            self.collide(state, contacts)
            if self.keep_inputs is not None:
                self.keep_inputs.save(state, contacts)
            return
        if part == "first":
            self.forces(state, contacts, dt, phase=1)
            return
        if part == "pairs":
            self.forces(state, contacts, dt, phase=2, stage="pairs")
            return
        if part != "rest":
            raise ValueError(f"part must be one of {self.SPLIT_PARTS}, got {part!r}")
        self.forces(state, contacts, dt, phase=2, stage="gather")
        if self.model.has_measured_motions:
            launch_measure_motions(self.model, contacts, self._motion_parts, state.step_count, 1, dt,
                                   state.motion_travel, device=self.device)  # fmt: skip
        self.integrate(state, dt)

    def collide(self, state: State, contacts: Contacts) -> None:
        """The broad phase: rebuild the pair list when some body may have left its skin."""
        if self.device_rebuild:
            contacts.update_on_device(state.body_q)
        else:
            contacts.update(state.body_q)

    def forces(self, state: State, contacts: Contacts, dt: float, phase: int = 0, stage: str = "all") -> None:
        """Contact forces and torques of the pairs and walls into ``state.body_f``, ``state.body_t``, and the
        damping loads the next step scales the dashpots by into ``state.body_damping``; with :attr:`average`
        set, each contact's force is also added to its sums (the report variant of the kernels). ``phase``: 0
        every body, 1 or 2 the part of a split step (:meth:`step_part`); ``stage``: "all", or the pair kernel
        ("pairs") or what follows it ("gather") alone."""
        average = self.average
        in_gather = self.loads_in_gather
        loads = state.body_damping if in_gather else None
        if average is None:
            self._force_stage(
                self.kernels,
                self.mesh_kernels,
                state=state,
                pairs=contacts,
                dt=dt,
                overflow=self.poly_overflow,
                damping_out=loads,
                phase=phase,
                stage=stage,
            )
        else:
            kernels, mesh = self._report_kernels()
            self._force_stage(
                kernels,
                mesh,
                state=state,
                pairs=contacts,
                dt=dt,
                overflow=self.poly_overflow,
                report_bits=REPORT_SUMS,
                pair_sums=average.pairs,
                wall_sums=average.walls,
                damping_out=loads,
                phase=phase,
                stage=stage,
            )
        if not in_gather and phase != 1 and stage != "pairs":
            self.damping_load(state, contacts, dt)

    @property
    def loads_in_gather(self) -> bool:
        """Whether the gather kernel writes the damping loads (the same bits as the load kernel, one launch
        fewer): with friction and no mesh walls, whose contacts come after the gather."""
        return self.kernels.friction and self.mesh_kernels is None

    def damping_load(self, state: State, contacts: PairArrays, dt: float) -> None:
        """Each body's damping load for the next step (``state.body_damping``) from the contact history as it is
        now (kernels/forces.py ``launch_damping_load``): after each step's force stage where the gather does not
        write them (:attr:`loads_in_gather`), and where a state is set from arrays without one (a checkpoint)."""
        launch_damping_load(self.kernels, model=self.model, state=state, pairs=contacts, dt=dt)

    def integrate(self, state: State, dt: float) -> None:
        """Move the bodies by ``dt`` under their forces and gravity; count the step; check it is finite."""
        m = self.model
        checks = {
            "step_count": state.step_count,
            "body_speed_limit": self.body_speed_limit,
            "bad_step": self.bad_step,
            "body_peak_speed": self.body_peak_speed,
            "too_fast": self.too_fast,
        }
        if not m.has_motions:
            # Nothing moves a body between the integration and the check: one launch for both (a launch less a
            # step, which a small pile's step waits on; BENCHMARKS.md section 31).
            launch_integrate_and_check(model=m, state=state, dt=dt, **checks)
        else:
            launch_integrate(model=m, state=state, dt=dt)
        if self.mesh_kernels is not None and m.mesh_moves:
            launch_advance_meshes(self.mesh_kernels.advance, meshes=m.meshes, dt=dt, mesh_q=state.mesh_q)
        launch_count_step(state.step_count)
        if m.has_motions:
            # The driven containers' poses at the end of this step, from the counter just advanced.
            travel = state.motion_travel if m.has_measured_motions else None
            launch_drive_bodies(
                m.motions, state.step_count, 0, dt, state.body_q, state.body_v, self.device, travel=travel
            )
        # The walls' poses at the end of this step too, for what reads the state between steps (pictures, USD).
        self.drive_walls(state, dt, 0)
        if m.has_motions:
            launch_check_state(model=m, state=state, **checks)

    def _force_stage(
        self,
        kernels: ContactKernels,
        mesh_kernels: MeshKernels | None,
        *,
        state: MeshWallState,
        pairs: PairArrays,
        dt: float,
        overflow: wp.array,
        out: ContactOutputs | None = None,
        report_bits: int = 0,
        pair_sums: ContactSums | None = None,
        wall_sums: ContactSums | None = None,
        damping_out: wp.array | None = None,
        phase: int = 0,
        stage: str = "all",
    ) -> None:
        """The pair, gather and mesh-wall kernels (``kernels``; ``mesh_kernels``, None without mesh walls):
        the step variant, or the diagnostics one into ``out``, or the report variant (``report_bits``,
        into ``out`` and the sums); a clipped polygon that did not fit sets ``overflow``. ``damping_out``:
        where the gather writes the damping loads (only without mesh walls; None: not written). ``phase``: the
        part of a split step (:meth:`step_part`; 0: the whole force stage); ``stage``: "all", "pairs" (the pair
        kernel alone) or "gather" (the rest)."""
        m = self.model
        out = self._no_outputs if out is None else out
        first = self._no_first if self.body_first is None or phase == 0 else self.body_first
        if phase != 2:
            self.drive_walls(state, dt, 0)
        if stage != "gather":
            self._pairs_stage(kernels, state, pairs, dt, overflow, out, report_bits, pair_sums, first, phase)
        if stage == "pairs":
            return
        wall_sums = self._no_sums if wall_sums is None else wall_sums
        launch_gather(
            kernels, model=m, state=state, pairs=pairs, dt=dt, out=out, report_bits=report_bits, wall_sums=wall_sums,
            planes=self.planes, damping_out=self._no_loads if damping_out is None else damping_out,
            body_first=first, phase=phase, first_index=self.body_first_index if phase == 1 else None,
        )  # fmt: skip
        if mesh_kernels is not None:
            launch_mesh_contacts(
                mesh_kernels,
                model=m,
                state=state,
                dt=dt,
                overflow=overflow,
                out=out,
                report_bits=report_bits,
                wall_sums=wall_sums,
                meshes=self.meshes,
                candidates=self.mesh_candidates,
            )

    def _pairs_stage(self, kernels, state, pairs, dt, overflow, out, report_bits, pair_sums, first, phase) -> None:
        # The pair kernel of _force_stage; with the threads ordered for a split step, the part's own range of them.
        if kernels.spread and not spread_fits(pairs.capacity, self.spread_threads):
            # Buffers this long never spread a pair: the plain variant (cached), whose launch has no idle threads.
            kernels = self._contact_kernels(kernels.diagnostics, kernels.report, spread=False)
        launch_pair_contacts(
            kernels,
            model=self.model,
            state=state,
            pairs=pairs,
            dt=dt,
            overflow=overflow,
            out=out,
            report_bits=report_bits,
            pair_sums=self._no_sums if pair_sums is None else pair_sums,
            body_first=first,
            phase=phase,
            first_count=getattr(pairs, "pair_first_count", None),
            first_room=self.first_room,
            first_overflow=self.first_overflow,
            spread_pairs=self.spread_pairs,
            spread_threads=self.spread_threads,
            costly=getattr(pairs, "pair_costly", None),
        )

    def _diag_arrays(self, pairs: int) -> ContactOutputs:
        # The outputs of the diagnostics and report variants for ``pairs`` candidate pairs.
        m = self.model
        return ContactOutputs.zeros(pairs, m.num_bodies, max(m.num_walls, 1), m.precision, self.device)

    def _until_polygons_fit(self, run_pass: Callable[[], None]) -> None:
        """Run ``run_pass`` (a diagnostics or report pass, with the current kernels) until no clipped polygon
        overflowed and the mesh-wall candidates fitted: an overflowed contact is wrong, so the room grows (for
        the steps too from now on: their kernels and graph are rebuilt) and the pass runs again. The candidate
        list's flag is shared with the steps: one the steps left set is kept for :meth:`buffers_overflowed`."""
        bound = self.model.shapes.max_poly_bound
        candidates = self.mesh_candidates
        if candidates is not None and candidates.overflowed():
            self._steps_overflowed = True  # the caller's check (after Simulation.advance) must still see it
            candidates.grow()
        while True:
            self._diag_overflow.zero_()
            run_pass()
            if candidates is not None and candidates.overflowed():
                candidates.grow()  # not all mesh-wall candidates were listed
                continue
            if not int(self._diag_overflow.numpy()[0]) or self.poly_capacity >= bound:
                return
            self.poly_capacity = min(2 * self.poly_capacity, bound)
            self._kernels()

    def diagnose(self, state: State, contacts: Contacts, dt: float) -> dict[str, np.ndarray]:
        """Runs the diagnostics variant of the contact kernels at ``state``; returns its host arrays.

        Per pair (the first ``count`` candidates): ``pair_volume`` [m^3], ``pair_energy`` [J],
        ``pair_normal``, ``pair_point`` [m], ``pair_fn`` [N], ``pair_ft`` [N], ``pair_depth`` [m]; per
        (body, wall): ``wall_volume``, ``wall_energy``, ``wall_fn``, ``wall_point``, ``wall_ft``,
        ``wall_depth``.
        """
        if self._diag is None or self._diag_generation != contacts.generation:
            self._diag_generation = contacts.generation
            self._diag = self._diag_arrays(contacts.capacity)

        def run_pass() -> None:
            kernels = self._contact_kernels(diagnostics=True)
            mesh = self._mesh_kernels(True)
            self._force_stage(
                kernels, mesh, state=state, pairs=contacts, dt=dt, overflow=self._diag_overflow, out=self._diag
            )

        self._until_polygons_fit(run_pass)
        count = contacts.count()
        out = {k: v.numpy() for k, v in self._diag.arrays().items()}
        for k in ("pair_volume", "pair_energy", "pair_normal", "pair_point", "pair_fn", "pair_ft", "pair_depth"):
            out[k] = out[k][:count]
        return out

    def release_diagnostics(self) -> None:
        """Let the buffers of :meth:`diagnose` and :meth:`report` go (they are allocated again when needed)."""
        self._diag = None
        self._report = None
        self._history_on = None

    def history_on(self, history: PairHistory, contacts: Contacts) -> tuple[wp.array, wp.array]:
        """(xi, turn): the pair history ``history`` (a :class:`~polydem.contacts.PairHistory`, by key)
        carried onto the current pair list of ``contacts``, in arrays of :meth:`report`'s."""
        r = self._history_on
        if r is None or r[0] != contacts.generation:
            r = self._history_on = (
                contacts.generation,
                wp.zeros_like(contacts.pair_xi),
                wp.zeros_like(contacts.pair_turn),
            )
        contacts.carry_history(history, r[1], r[2])
        return r[1], r[2]

    def report(self, inputs: dict[str, wp.array], contacts: Contacts, dt: float) -> dict[str, np.ndarray]:
        """Runs the force stage of a step again on ``inputs`` (device arrays by name, as
        :class:`StepInputs`' ``arrays``: what the force stage of a step read, after its broad phase,
        the pair history on the current pair list), with the report variant of the kernels, into
        arrays of its own; returns host arrays as :meth:`diagnose` does, without the energies.

        The same kernel code on the same inputs: the contacts and forces the step computed, the ones
        its integration applied (``state.body_f`` is their sum). The state, the pair history and
        ``inputs`` are left as they are. The geometry (volume, normal, point, depth) is that of the
        poses the step started from.
        """
        m = self.model
        cap = contacts.capacity
        n = m.num_bodies
        if self._report is None or self._report_generation != contacts.generation:
            self._report_generation = contacts.generation
            out = self._diag_arrays(cap)
            # What the step writes besides the report: scratch arrays, so that nothing of the run changes.
            scratch = {k: wp.empty_like(inputs[k]) for k in ("wall_xi", "wall_turn", "pair_xi", "pair_turn")}
            scratch["body_f"] = wp.zeros_like(inputs["body_v"])
            scratch["body_t"] = wp.zeros_like(inputs["body_v"])
            scratch["body_dissipated"] = wp.zeros(n, dtype=m.scalar, device=self.device)
            for name in ("pair_force", "pair_torque_a", "pair_dissipated"):
                scratch[name] = wp.zeros_like(getattr(contacts, name))
            self._report = (out, scratch)
        out, scratch = self._report
        a = inputs
        # The force stage's structs of these arrays (kernels/structs.py): the inputs and the scratch.
        bodies = {k: a[f"body_{k}"] for k in ("q", "v", "w")} | {k: scratch[f"body_{k}"] for k in ("f", "t")}
        bodies = filled(bodies_struct(m.scalar), **bodies, dissipated=scratch["body_dissipated"])
        walls = filled(wall_history_struct(m.contact_scalar), xi=scratch["wall_xi"], turn=scratch["wall_turn"])
        Pairs = pairs_struct(m.contact_scalar)
        live = {k: getattr(contacts.pairs, k) for k in Pairs.vars}
        damping = a.get("body_damping")
        if damping is None:
            # Inputs from a snapshot, which holds no damping loads: those the step read, from the history it read.
            if "body_damping" not in scratch:
                scratch["body_damping"] = wp.zeros(n, dtype=wp.float32, device=self.device)
            damping = scratch["body_damping"]
            read = SimpleNamespace(
                bodies=bodies,
                walls=filled(wall_history_struct(m.contact_scalar), xi=a["wall_xi"], turn=a["wall_turn"]),
                body_damping=damping,
            )
            history = filled(Pairs, **(live | {"xi": a["pair_xi"], "turn": a["pair_turn"]}))
            self.damping_load(read, SimpleNamespace(capacity=cap, pairs=history), dt)
        state = SimpleNamespace(
            bodies=bodies, walls=walls, body_damping=damping, mesh_q=a["mesh_q"], step_count=a["step_count"]
        )
        steps = {k: scratch[f"pair_{k}"] for k in ("xi", "turn", "force", "torque_a", "dissipated")}
        pairs = SimpleNamespace(capacity=cap, pairs=filled(Pairs, **(live | steps)))

        def run_pass() -> None:
            for name in ("wall_xi", "wall_turn", "pair_xi", "pair_turn"):
                wp.copy(scratch[name], a[name])
            kernels, mesh = self._report_kernels()
            overflow = self._diag_overflow
            self._force_stage(
                kernels, mesh, state=state, pairs=pairs, dt=dt, overflow=overflow, out=out, report_bits=REPORT_CONTACTS
            )

        self._until_polygons_fit(run_pass)
        count = contacts.count()
        host = {k: v.numpy() for k, v in out.arrays().items() if not k.endswith("_energy")}
        for k in ("pair_volume", "pair_normal", "pair_point", "pair_fn", "pair_ft", "pair_depth"):
            host[k] = host[k][:count]
        host["body_f"] = scratch["body_f"].numpy()
        host["body_t"] = scratch["body_t"].numpy()
        return host

    def kinetic_energies(self, state: State) -> tuple[wp.array, wp.array]:
        """Device (translational, rotational) kinetic energy of each body [J] (0 for those not free)."""
        m = self.model
        return kinetic_energy(
            body_inv_mass=m.body_inv_mass,
            body_inertia=m.body_inertia,
            body_flags=m.body_flags,
            body_q=state.body_q,
            body_v=state.body_v,
            body_w=state.body_w,
            device=self.device,
        )

    def kinetic_energy(self, state: State) -> tuple[float, float]:
        """Host float64 (translational, rotational) kinetic energy of the free bodies [J]."""
        lin, ang = self.kinetic_energies(state)
        return np.sum(lin.numpy(), dtype=np.float64), np.sum(ang.numpy(), dtype=np.float64)


class StepInputs:
    """Copies of what the force stage of a step read, taken after its broad phase: the poses and
    velocities, the mesh walls' poses, the wall contacts' and the pairs' history (the pair list
    itself stays in the :class:`~polydem.contacts.Contacts` until the next step's broad phase).
    :meth:`Stepper.report` runs the force stage again on them. :meth:`Simulation.advance` keeps them
    of its last step (:meth:`Simulation.step` needs none: its copy for a redo serves).

    Attributes:
        arrays: device arrays by name: ``body_q``, ``body_v``, ``body_w``, ``body_damping``, ``mesh_q``, ``wall_xi``,
            ``wall_turn``, ``step_count`` (as the :class:`~polydem.state.State`'s), ``pair_xi``, ``pair_turn`` (as the
            :class:`~polydem.contacts.Contacts`').
    """

    # The step counter too: the walls that follow motions are put where they were at that step.
    STATE = ("body_q", "body_v", "body_w", "body_damping", "mesh_q", "wall_xi", "wall_turn", "step_count")
    PAIRS = ("pair_xi", "pair_turn")

    def __init__(self) -> None:
        self.arrays: dict[str, wp.array] = {}

    def _sources(self, state: State, contacts: Contacts) -> list[tuple[str, wp.array]]:
        return [(k, getattr(state, k)) for k in self.STATE] + [(k, getattr(contacts, k)) for k in self.PAIRS]

    def ensure(self, state: State, contacts: Contacts) -> None:
        """Arrays of the shapes of ``state`` and ``contacts`` (before a graph capture: none is made in it)."""
        for name, src in self._sources(state, contacts):
            dst = self.arrays.get(name)
            if dst is None or dst.shape != src.shape or dst.dtype != src.dtype:
                self.arrays[name] = wp.empty_like(src)

    def save(self, state: State, contacts: Contacts) -> None:
        """Copy what the force stage will read from ``state`` and ``contacts``."""
        self.ensure(state, contacts)
        for name, src in self._sources(state, contacts):
            wp.copy(self.arrays[name], src)


class Snapshot:
    """A copy of a simulation at one step: :class:`~polydem.state.State`, pair history, step count and time,
    and the sums of the contact-force average then running (``average``, None without one).

    From :meth:`Simulation.snapshot`; give it to :meth:`Simulation.restore` to go back to that step. The
    state is copied without ``body_f`` and ``body_t`` (``State.TRANSIENT``: the next step writes them before
    it reads them) and the damping loads (the restore computes them from the pair history), and the pair
    history holds the pairs of the list then (``count``) with some room, not the whole capacity of the live
    list (:meth:`~polydem.contacts.Contacts.history`).
    """

    def __init__(
        self, state: State, pairs: PairHistory, steps_done: int, time: float, average: AverageSnapshot | None = None
    ) -> None:
        self.state = state
        self.pairs = pairs
        self.steps_done = int(steps_done)
        self.time = float(time)
        self.average = average


class Simulation:
    """Steps a :class:`~polydem.Scene` on a Warp device.

    Args:
        scene: the scene (validated here).
        device: Warp device, default Warp's default device ("cuda:0" when there is one).
        skin: Verlet skin [m]; default a fifth of the smallest free body's bounding radius
            (:func:`~polydem.run_settings.run_settings`; give it there where ``settings`` is given).
        use_graph: capture the step as a CUDA graph (default: on CUDA devices).
        validate: validate the scene first (off only for a scene validated already, such as the whole
            scene of a decomposed run, :mod:`polydem.distributed`).
        tree_rebuild: when the broad phase rebuilds on the device (the CUDA graph), it refits the tree of
            the last host build; after each chunk of steps the tree is rebuilt when refitting has made it
            this many times as costly as a fresh one (:meth:`~polydem.kernels.broadphase.BroadPhase.renew_tree`);
            0: after every chunk with a device rebuild; None (default): never. The pairs, and so the
            results, do not depend on it. Without the graph every rebuild builds a fresh tree.
        pair_max_registers: as for :class:`Stepper`.
        settings: the :class:`~polydem.run_settings.RunSettings` of the run (default: the scene's).
        bodies: indices of the scene's bodies to step, ascending (default: all): with the whole scene's
            ``settings``, the bodies step as in the whole scene's run where their contacts are all
            among them (a rank of a decomposed run); body indices of the results are then positions
            in ``bodies``.
        order_pair_threads: hand the pair kernel's threads the candidate pairs grouped, so that a warp's threads
            do alike work and none waits for a costlier neighbour: True (default) or ``"contact"``: by the cost of
            their shapes (the product of their face counts) from the costliest down, and in each cost class the
            pairs that touched at the last rebuild (they clip their faces) before those that did not (they stop
            at a separating plane), in a pile of one shape too (BENCHMARKS.md 20: a step of 1e5 cubes 31% and of
            1e5 mixed grains 39% shorter on an H200); ``"cost"``: by cost class alone, ascending (off by itself
            where every pair costs alike; BENCHMARKS.md 17); False: slot order. The same results bit for bit
            (each pair's arithmetic is its own); one sort of the pair list a rebuild and 4 bytes a pair slot.
        overlap_check: where the validation tests body pairs for initial overlaps: "host" (the scene's own
            check, a k-d tree search), "device" (the same test over the first broad phase's candidate pairs, on
            this device: :mod:`polydem.overlap_check`; convex grains, the whole scene), "auto" (default: the
            device on CUDA from :data:`~polydem.overlap_check.DEVICE_CHECK_MIN_BODIES` bodies on). The same
            warning or error either way. A scene validated before with ``Scene.validate(pair_overlaps=False)``
            (``polydem run`` where the device check applies) is finished here: on the device where it applies,
            else on the host.
        mesh_candidates: the mesh-wall contacts through a list of (body, cell) candidates, a thread each to
            clip (True), or a thread per body walking its cells (False); None (default): the list on CUDA, the
            walk on the CPU. The same motion bit for bit either way (:mod:`polydem.kernels.meshwall`; on CUDA the
            energy-lost book may differ in its last bits).
        join_flat_cells: the mesh walls' cells of coplanar triangles joined into one where they are convex
            together (True, default: fewer cells to clip, the same contacts to rounding), or one cell per
            triangle (False); see :mod:`polydem.meshmerge`.

    Attributes:
        scene: the :class:`~polydem.Scene` it was built from (the whole scene, where ``bodies`` is given).
        settings: the :class:`~polydem.run_settings.RunSettings`.
        model: the :class:`~polydem.model.Model` (static).
        current_state: the :class:`~polydem.state.State` after the last step (stepped in place).
        current_contacts: the :class:`~polydem.contacts.Contacts` (pair list and its history).
        stepper: the :class:`Stepper`.
        steps_done: steps taken; time: ``steps_done * dt`` [s]; dt: time step [s].
    """

    scene: Scene
    settings: RunSettings
    model: Model
    device: wp.Device
    dt: float
    num_bodies: int
    current_state: State
    current_contacts: Contacts
    stepper: Stepper
    steps_done: int
    time: float

    def __init__(
        self,
        scene: Scene,
        device: wp.DeviceLike = None,
        skin: float | None = None,
        use_graph: bool | None = None,
        tree_rebuild: float | None = TREE_REBUILD_RATIO,
        *,
        validate: bool = True,
        pair_max_registers: int | None = PAIR_MAX_REGISTERS,
        settings: RunSettings | None = None,
        bodies: np.ndarray | None = None,
        order_pair_threads: bool | str = True,
        overlap_check: str = "auto",
        mesh_candidates: bool | None = None,
        join_flat_cells: bool = True,
    ) -> None:
        if tree_rebuild is not None and not float(tree_rebuild) >= 0.0:
            raise ValueError(f"tree_rebuild must be >= 0 or None, got {tree_rebuild}")
        if not isinstance(order_pair_threads, str):
            order_pair_threads = bool(order_pair_threads)
        if order_pair_threads not in (True, False, *THREAD_ORDERS):
            raise ValueError(
                f"order_pair_threads must be True, False or one of {THREAD_ORDERS}, got {order_pair_threads!r}"
            )
        self.tree_rebuild = None if tree_rebuild is None else float(tree_rebuild)
        on_device = device_check_applies(scene, device, bodies, overlap_check)
        if validate:
            scene.validate(pair_overlaps=not on_device)
        if settings is None:
            settings = run_settings(scene, skin=skin)
        elif skin is not None:
            raise ValueError("give the skin to run_settings(scene, skin=...), which made the settings given")
        self.scene = scene
        self.settings = settings
        self.model = model = Model(
            scene, device, validate=False, settings=settings, bodies=bodies, join_flat_cells=join_flat_cells
        )
        self.device = dev = model.device
        self.dt = model.dt
        n = model.num_bodies
        self.num_bodies = n
        self.use_graph = dev.is_cuda if use_graph is None else (bool(use_graph) and dev.is_cuda)
        self.current_state = model.state()
        self.steps_done = 0
        self.time = 0.0

        self.skin = settings.skin
        # Bounding spheres about the centre do not change as a body turns: no rotation term.
        shape_list = [scene.shapes[name] for name in scene.shape_names]
        lower = np.array([s.vertices.min(axis=0) for s in shape_list])
        upper = np.array([s.vertices.max(axis=0) for s in shape_list])
        # Settled packings of convex grains have 3-4 candidate pairs per body at this skin: start
        # with room for 5 (an overflow grows the buffers and redoes the step).
        self.current_contacts = Contacts(
            model,
            self.skin,
            body_box=(lower, upper, model.body_shape_np),  # a box per shape
            capacity=max(1024, 5 * n),
            radius_ref=settings.radius_ref,
            thread_order=order_pair_threads,
        )
        self.stepper = Stepper(
            model,
            device_rebuild=self.use_graph,
            pair_max_registers=pair_max_registers,
            thread_order=self.current_contacts.thread_order,
            mesh_candidates=mesh_candidates,
            spread=self.current_contacts.thread_grouping == "contact",
        )
        self._speed_limit = settings.tunnel.body_speed_limit[model.body_index]
        self.stepper.body_speed_limit.assign(self._speed_limit.astype(np.float32))
        # Warned once a run: already by the scene's validation where the initial speeds are too high.
        self._tunnel_warned = settings.starts_too_fast
        self._graphs: dict[Any, wp.Graph] = {}
        self._graph_key: tuple | None = None
        self._side_stream: wp.Stream | None = None
        self._split_events: list[wp.Event] = []
        self._last_good: Snapshot | None = None
        self._diag_cache: dict[str, np.ndarray] | None = None
        # contacts() runs the last step's force stage again on what it read: where that is kept
        # (_last_step: "snapshot", the copy step() takes before its last step, which runs alone in its
        # chunk; "inputs", the copies advance() keeps of its last step; None: no step since the state
        # was set), and the host arrays of its report.
        self._last_step: Literal["snapshot", "inputs"] | None = None
        self._inputs: StepInputs | None = None
        self._report_cache: dict[str, np.ndarray] | None = None
        # The contact-force average (start_contact_average): its device sums, and the intervals begun.
        self._average: ContactAverage | None = None
        self._intervals = 0
        self.current_contacts.build(self.current_state.body_q, keep_history=False)
        if scene.pair_overlaps_pending:  # validated here or before without the body pairs' overlaps
            try:
                found = (
                    device_pair_overlaps(scene, model, self.current_contacts, self.current_state) if on_device else None
                )
                scene.finish_overlap_check(found)
            except SceneError:
                # an overlap too deep: nothing of the run is kept (the traceback would hold the device arrays)
                self.__dict__.clear()
                del model
                raise

    # -- snapshots -----------------------------------------------------------------------------

    def snapshot(self, into: Snapshot | None = None) -> Snapshot:
        """A :class:`Snapshot` (device copies) of the current step; reuses the arrays of ``into`` where they fit.
        Synchronises once (to read the pair count: the copy of the pair history is sized to the list)."""
        st = self.current_state
        if into is not None and into.state.same_shapes(st):
            into.state.assign(st)
            state = into.state
        else:
            state = st.copy(transient=False)  # no body_f, body_t, body_damping (State.TRANSIENT)
        pairs = self.current_contacts.history(into.pairs if into is not None else None)
        average = None
        if self._average is not None:
            average = self._average.snapshot(getattr(into, "average", None))
        if into is None:
            return Snapshot(state, pairs, self.steps_done, self.time, average)
        into.state, into.pairs, into.steps_done, into.time = state, pairs, self.steps_done, self.time
        into.average = average
        return into

    def restore(self, snapshot: Snapshot) -> None:
        """Go back to the step of ``snapshot`` (from :meth:`snapshot`, or a checkpoint's).

        The candidate pairs are found afresh at the restored poses; each pair gets its history back by key.
        A contact-force average (:meth:`start_contact_average`) goes on: with the sums of ``snapshot``
        where it was taken during the same interval, else started afresh at the restored step.
        ``current_state.body_f`` and ``body_t`` are zero afterwards, as before the first step and after a
        checkpoint is loaded (no step has run since the state was set; a snapshot does not copy them), until
        the next step writes them; :meth:`contacts` reports the forces that step will apply. The damping loads
        (``body_damping``) are the snapshot's where it holds them, else computed from the restored history.
        """
        self._diag_cache = None
        self._report_cache = None
        self._last_step = None  # the last step is not the one that led to the restored state
        # A non-finite step recorded after the snapshot belongs to the states that are discarded now.
        self.stepper.clear_checks()
        avg = self._average
        while True:
            self.current_state.assign(snapshot.state)
            pair_sums = None
            if avg is not None:
                saved = getattr(snapshot, "average", None)
                if saved is not None and saved.interval == avg.interval:
                    avg.restore(saved)
                    pair_sums = saved.pairs
                else:
                    avg.reset(avg.interval, snapshot.steps_done, snapshot.time)
            self.current_contacts.restore(snapshot.pairs, self.current_state.body_q, pair_sums=pair_sums)
            # The pairs of the snapshot that the fresh list has not are retired: room for them.
            if avg is None or not avg.overflowed():
                break
            avg.grow()
        if "body_damping" not in snapshot.state.__dict__:
            # A snapshot does not copy the damping loads: derived from the pair history, computed again.
            self.stepper.damping_load(self.current_state, self.current_contacts, self.dt)
        self.steps_done = snapshot.steps_done
        self.time = snapshot.time

    def restore_from_arrays(self, arrays: dict[str, np.ndarray], steps_done: int, time: float) -> None:
        """:meth:`restore` from host arrays named as a checkpoint's: ``State.SAVED``, ``pair_key``, ``pair_xi``,
        ``pair_turn``."""
        m = self.model
        saved = {k: arrays[k] for k in State.SAVED if k in arrays}
        # The damping loads where the arrays carry them (a decomposed run's rows, whose ghosts' loads come from
        # their owners); else computed again from the restored history below.
        if "body_damping" in arrays:
            saved["body_damping"] = arrays["body_damping"]
        if "mesh_q" not in saved:
            saved["mesh_q"] = self.current_state.mesh_q.numpy()
        # The ramps' and servos' travel, kept apart from State.SAVED (a decomposed run gathers those).
        travel = arrays.get("motion_travel")
        saved["motion_travel"] = self.current_state.motion_travel.numpy() if travel is None else travel
        state = State.from_numpy(saved, self.device, m.precision)
        pairs = PairHistory.from_numpy(
            arrays["pair_key"], arrays["pair_xi"], arrays["pair_turn"], m.friction, self.device, m.contact_scalar
        )
        self.restore(Snapshot(state, pairs, steps_done, time))
        if "body_damping" not in arrays:
            self.stepper.damping_load(self.current_state, self.current_contacts, self.dt)

    @property
    def last_good(self) -> Snapshot | None:
        """The :class:`Snapshot` taken at the start of the last chunk of :meth:`step` (None before the first)."""
        return self._last_good

    def is_consistent(self) -> bool:
        """Whether the device state is that of step ``steps_done`` and finite (synchronises)."""
        st = self.current_state
        return int(st.step_count.numpy()[0]) == self.steps_done and bool(np.all(np.isfinite(st.body_q.numpy())))

    def restore_last_good(self) -> bool:
        """Bring the simulation back to step ``steps_done`` after an exception inside :meth:`step`.

        A step interrupted part-way through a chunk (Ctrl-C) has moved the state beyond
        ``steps_done``, and a :class:`SimulationError` leaves a non-finite one: the copy saved at
        the start of that chunk is restored. Returns whether the state now is that of ``steps_done``.
        """
        if self.is_consistent():
            return True
        last = self._last_good
        if last is None or int(last.state.step_count.numpy()[0]) != self.steps_done:
            return False
        self.restore(last)
        return self.is_consistent()

    # -- stepping ------------------------------------------------------------------------------

    def _graph_cache(self) -> dict[Any, wp.Graph]:
        """The captured steps for the current pair list, buffers, polygon room, split and average."""
        contacts, avg, stepper = self.current_contacts, self._average, self.stepper
        key = (contacts.generation, stepper.buffer_generation, id(stepper.kernels),
               None if avg is None else (id(avg), avg.generation))  # fmt: skip
        if self._graph_key != key:
            self._graphs = {}
            self._graph_key = key
        return self._graphs

    def _graph(self, keep_inputs: bool) -> wp.Graph:
        """The captured step (``keep_inputs``: the one that also keeps its inputs, for advance()), for
        the current buffers, polygon room and average."""
        state, contacts = self.current_state, self.current_contacts
        graph = self._graph_cache().get(keep_inputs)
        if graph is None:
            self.stepper.keep_inputs = self._inputs if keep_inputs else None
            try:
                with wp.ScopedCapture(device=self.device) as capture:
                    self.stepper.step(state, state, contacts, self.dt)
            finally:
                self.stepper.keep_inputs = None
            graph = self._graphs[keep_inputs] = capture.graph
        return graph

    def _split_graph(self, part: str, between: Callable[[], None], key: Hashable, stream: wp.Stream) -> wp.Graph:
        """Part ``part`` of a split step that keeps its inputs (:meth:`advance_split`), captured on ``stream``;
        the "first" part with ``between``."""
        graphs = self._graph_cache()
        graph = graphs.get(("split", part, key))
        if graph is None:
            self.stepper.keep_inputs = self._inputs if part == "collide" else None
            try:
                # The capture records the stream it is given; the launches go to the current stream: the same one.
                with wp.ScopedStream(stream, sync_enter=False), wp.ScopedCapture(stream=stream) as capture:
                    self._split_part(part, between)
            finally:
                self.stepper.keep_inputs = None
            graph = graphs["split", part, key] = capture.graph
        return graph

    def _split_part(self, part: str, between: Callable[[], None]) -> None:
        self.stepper.step_part(self.current_state, self.current_contacts, self.dt, part)
        if part == "first":
            between()

    def _run_chunk(self, steps: int, keep_inputs: bool = False) -> None:
        """``steps`` steps; ``keep_inputs``: the last one keeps what its force stage read (StepInputs)."""
        if steps <= 0:
            return
        self._diag_cache = None
        self._report_cache = None
        self._last_step = None
        state, contacts = self.current_state, self.current_contacts
        self.stepper.average = self._average
        if keep_inputs:
            if self._inputs is None:
                self._inputs = StepInputs()
            self._inputs.ensure(state, contacts)
        if self.use_graph:
            plain = steps - 1 if keep_inputs else steps
            if plain:
                graph = self._graph(False)
                for _ in range(plain):
                    wp.capture_launch(graph)
            if keep_inputs:
                wp.capture_launch(self._graph(True))
        else:
            try:
                for k in range(steps):
                    self.stepper.keep_inputs = self._inputs if keep_inputs and k == steps - 1 else None
                    self.stepper.step(state, state, contacts, self.dt)
            finally:
                self.stepper.keep_inputs = None
        if keep_inputs:
            self._last_step = "inputs"

    def step(self, n: int = 1) -> None:
        """Advance ``n`` steps of length ``dt``."""
        n = int(n)
        if n < 0:
            raise ValueError(f"step count must be >= 0, got {n}")
        done = 0
        while done < n:
            chunk = min(CHUNK_STEPS, n - done)
            if chunk == n - done and chunk > 1:
                # The last step runs alone in its chunk: the copy taken before it (for a redo) is then
                # what its force stage read, which contacts() runs again. No copy of its own.
                chunk -= 1
            self._last_good = self.snapshot(into=self._last_good)
            self._run_chunk(chunk)
            redo = False
            if self.stepper.buffers_overflowed():
                self.stepper.grow_buffers()
                redo = True
            if self.stepper.device_rebuild and self.current_contacts.host_build_needed():
                redo = True
            if self._average is not None and self._average.overflowed():
                self._average.grow()  # more contacts ended in the chunk than the retired list holds
                redo = True
            if redo:
                self.restore(self._last_good)
                continue
            bad = self.stepper.first_bad_step()
            if bad is not None:
                self._report_nonfinite(bad)
            if not self._tunnel_warned and self.stepper.went_too_fast():
                self._warn_too_fast(chunk)
            if self.stepper.device_rebuild:
                self.current_contacts.broadphase.renew_tree(self.tree_rebuild)
            done += chunk
            self.steps_done += chunk
            self.time += chunk * self.dt
            if done == n:
                self._last_step = "snapshot"

    def _warn_too_fast(self, chunk: int) -> None:
        # Once a run: the body the furthest above its limit, at its largest speed so far.
        self._tunnel_warned = True
        peak = self.stepper.body_peak_speed.numpy().astype(np.float64)
        i = int(np.argmax(peak / self._speed_limit))
        body = int(self.model.body_index[i])
        warnings.warn(
            f"{self.scene.body_label(body)} reached {self.settings.tunnel.describe(body, float(peak[i]), self.dt)} "
            f"(in steps {self.steps_done + 1} to {self.steps_done + chunk})",
            SimulationWarning,
            stacklevel=3,
        )

    def advance(self, steps: int) -> None:
        """Run ``steps`` steps with no host check or redo (one CUDA graph launch each on a GPU).

        For callers that check for themselves what :meth:`step` checks after each chunk (the overflow
        flags of ``stepper`` and ``current_contacts``, the first non-finite step) and keep their own
        copy to go back to: a decomposed run (:mod:`polydem.distributed`) does, once per chunk of all
        its ranks. Does not count the steps (``steps_done``, ``time``): the caller sets them. The last
        step keeps a copy of what its force stage read (:class:`StepInputs`), for :meth:`contacts`.
        """
        self._run_chunk(int(steps), keep_inputs=True)

    def split_at(self, body_first: np.ndarray | None) -> None:
        """Split each step in two parts (:meth:`advance_split`): the first computes the contacts of the bodies
        flagged in ``body_first`` ((N,) bool), the forces on them and whatever ``advance_split``'s ``between``
        launches, the second the rest; None: one part. The same bits either way (:meth:`Stepper.split_at`). With
        the pair threads ordered, the flagged bodies' pairs come first in the order, and the first part launches
        only threads for them (about twice as many as now; more where they grow)."""
        stepper, contacts = self.stepper, self.current_contacts
        stepper.split_at(body_first)
        first = contacts.split_at(stepper.body_first)
        if first is not None:
            stepper.first_room = max(1024, 2 * first)

    def advance_split(
        self, between: Callable[[], None], key: Hashable = None, marks: Sequence[wp.Event] | None = None
    ) -> wp.Event | None:
        """One step as :meth:`advance` takes it, split (:meth:`split_at`, which must have been called) so that the
        flagged bodies' contacts and forces, then ``between`` (which launches work on this device that reads
        them: on a GPU it is captured once with them, per ``key``), come first, and on a GPU run on a stream of
        their own alongside the other pairs' contacts (:data:`Stepper.SPLIT_PARTS`).

        Returns, on a GPU, an event recorded once that part and ``between`` are done, while the rest of the step
        may still run; on the CPU None (everything has run). The same bits as ``advance(1)``.

        ``marks``: on a GPU, one event per part of :data:`Stepper.SPLIT_PARTS`, each recorded on its part's stream
        as the part ends (made with ``enable_timing=True``, they time the parts: ``benchmarks/split_step.py``).
        """
        if marks is not None and len(marks) != len(Stepper.SPLIT_PARTS):
            raise ValueError(f"marks: one event per part of {Stepper.SPLIT_PARTS}, got {len(marks)}")
        self._diag_cache = None
        self._report_cache = None
        self._last_step = None
        state, contacts = self.current_state, self.current_contacts
        self.stepper.average = self._average
        if self._inputs is None:
            self._inputs = StepInputs()
        self._inputs.ensure(state, contacts)
        if not self.device.is_cuda:
            self.stepper.keep_inputs = self._inputs
            try:
                self._split_part("collide", between)
            finally:
                self.stepper.keep_inputs = None
            for part in ("first", "pairs", "rest"):
                self._split_part(part, between)
            self._last_step = "inputs"
            return None
        main = wp.get_stream(self.device)
        if self._side_stream is None:
            # High priority: its blocks go ahead of the other pairs' as SMs free up, so that its rows are ready
            # early (at the default priority they waited behind the whole pair kernel).
            self._side_stream = wp.Stream(self.device, priority=-1)
            self._split_events = [wp.Event(self.device) for _ in range(2)]
        side, (collided, first_done) = self._side_stream, self._split_events
        # collide on the main stream; then the first part on the side stream and the other pairs on the main one,
        # at once; the rest once both are done.
        for part, stream in (("collide", main), ("first", side), ("pairs", main), ("rest", main)):
            if part == "first":
                side.wait_event(main.record_event(collided))
            if part == "rest":
                main.wait_event(first_done)
            if self.use_graph:
                wp.capture_launch(self._split_graph(part, between, key, stream), stream=stream)
            else:
                self.stepper.keep_inputs = self._inputs if part == "collide" else None
                try:
                    with wp.ScopedStream(stream, sync_enter=False):
                        self._split_part(part, between)
                finally:
                    self.stepper.keep_inputs = None
            if part == "first":
                side.record_event(first_done)
            if marks is not None:
                stream.record_event(marks[Stepper.SPLIT_PARTS.index(part)])
        self._last_step = "inputs"
        return first_done

    def forget_diagnostics(self) -> None:
        """Drop the contact diagnostics computed at this step (after the state was changed from outside).

        :meth:`contacts` still reports the last step as it ran (from copies of what it read); before
        any step or after :meth:`restore`, it is computed again at the changed state.
        """
        self._diag_cache = None
        if self._last_step is None:
            self._report_cache = None

    def diagnostics(self) -> dict[str, np.ndarray]:
        """The per-pair and per-wall diagnostics of the current step (what :meth:`energy` and
        :meth:`contacts` read): host arrays by name, ``pair_*`` (candidate pairs, in pair-list order)
        and ``wall_*`` (bodies x walls)."""
        return self._diagnostics()

    def _report_nonfinite(self, bad: int) -> NoReturn:
        st = self.state()
        rows = ~np.isfinite(
            np.hstack([st["body_position"], st["body_orientation"], st["body_velocity"], st["body_angular_velocity"]])
        ).all(axis=1)
        bodies = np.flatnonzero(rows)
        raise SimulationError(
            f"the state became non-finite at step {bad} (t = {bad * self.dt:.6g} s); bodies {bodies[:20].tolist()}"
            f"{' ...' if len(bodies) > 20 else ''}. Check the time step (dt = {self.dt:.3g} s, recommended "
            f"{self.model.dt_recommended:.3g} s), the stiffness and the initial overlaps."
        )

    # -- running until settled -----------------------------------------------------------------

    def settle_measures(self) -> tuple[float, float, float]:
        """Host float64 (kinetic energy [J], gravitational energy [J], largest speed [m/s]) of the free
        bodies at the current step: the measurements of a :class:`~polydem.settle.SettleCriterion`.

        The speed is that of a body's fastest point, ``|v| + |w| r`` (r its bounding radius), at this
        step (not the peak since the last check: a resumed run then measures as the unbroken one).
        No contact pass: one kernel over the bodies and two sums on the device (deterministic, so a
        resumed run decides as the unbroken one); three numbers come back to the host.
        """
        m = self.model
        n = self.num_bodies
        dev = self.device
        if getattr(self, "_settle_arrays", None) is None:
            self._settle_arrays = (
                wp.empty(n, dtype=wp.float64, device=dev),
                wp.empty(n, dtype=wp.float64, device=dev),
                wp.zeros(3, dtype=wp.float64, device=dev),
            )
        kin, grav, out = self._settle_arrays
        out.zero_()
        launch_settle_measures(
            model=m, state=self.current_state, body_kinetic=kin, body_gravity=grav, largest_speed=out[2:3]
        )
        wp.utils.array_sum(kin, out=out[0:1])
        wp.utils.array_sum(grav, out=out[1:2])
        kinetic, gravity, speed = out.numpy().tolist()
        return kinetic, gravity, speed

    def settle_check(self, criterion: SettleCriterion | None = None, check: SettleCheck | None = None) -> SettleCheck:
        """A :class:`~polydem.settle.SettleCheck` of ``criterion`` (default :class:`SettleCriterion()`)
        from the current step, with the criterion's speed limit in this scene (``speed_fraction`` of
        ``sqrt(|g| r_min)``, or ``max_speed``); ``check``: one to continue instead. Raises ValueError
        when the criterion cannot be met in this scene (no free body; the kinetic part or the scaled
        speed limit without gravity)."""
        if check is not None:
            return check
        criterion = SettleCriterion() if criterion is None else criterion
        if not isinstance(criterion, SettleCriterion):
            raise TypeError(f"criterion must be a polydem.SettleCriterion, got {type(criterion).__name__}")
        if not np.any(self.model.body_flags_np == BodyKind.FREE):
            raise ValueError("the scene has no free bodies: there is nothing to settle")
        criterion.check_gravity(self.model.gravity)
        limit = criterion.speed_limit_of(self.scene, self.settings)
        return SettleCheck(criterion, self.settle_measures()[1], speed_limit=limit)

    def run_until_settled(
        self, max_time: float, criterion: SettleCriterion | None = None, *, check: SettleCheck | None = None
    ) -> SettleResult:
        """Step until the free bodies have settled (``criterion``, default :class:`SettleCriterion()`:
        the kinetic energy below 1e-4 of the gravitational energy released and no free body's fastest
        point at 1e-3 sqrt(|g| r_min) or faster, for 0.02 s), for at most ``max_time`` more simulated
        seconds.

        The criterion is checked every ``CHUNK_STEPS`` steps (at step counts that are multiples of it;
        the last step is measured for the result); the energy released counts from the current step
        (or from the start of ``check``, a :class:`~polydem.settle.SettleCheck` to continue). Returns
        a :class:`~polydem.settle.SettleResult`.

        Raises:
            ValueError: ``max_time`` not > 0; no free body; the kinetic part in a scene without gravity.
        """
        max_time = float(max_time)
        if not (math.isfinite(max_time) and max_time > 0.0):
            raise ValueError(f"max_time must be a simulated time > 0 [s], got {max_time!r}")
        check = self.settle_check(criterion, check)
        t0 = _time.perf_counter()
        start = self.steps_done
        end = start + max(1, math.ceil(max_time / self.dt - 1e-9))
        settled = False
        while self.steps_done < end and not settled:
            stop = min(end, (self.steps_done // CHUNK_STEPS + 1) * CHUNK_STEPS)
            self.step(stop - self.steps_done)
            if self.steps_done % CHUNK_STEPS:
                # The last step, off the cadence: measured for the result; the hold goes on from the last
                # check, so that a later call continuing ``check`` holds as one unbroken call would.
                check.holds(*self.settle_measures())
            else:
                settled = check.update(self.steps_done, self.dt, *self.settle_measures())
        return SettleResult(
            settled=settled,
            time=self.time,
            held_from=None if check.held_since is None else check.held_since * self.dt,
            steps=self.steps_done - start,
            steps_done=self.steps_done,
            wall=_time.perf_counter() - t0,
            kinetic=check.kinetic,
            released=check.released,
            largest_speed=check.largest_speed,
            speed_limit=check.speed_limit,
        )

    # -- reading the current step --------------------------------------------------------------

    def _diagnostics(self) -> dict[str, np.ndarray]:
        # energy() and contacts() at the same step share one run (dropped by a step and a restore).
        if self._diag_cache is None:
            self._diag_cache = self.stepper.diagnose(self.current_state, self.current_contacts, self.dt)
        return self._diag_cache

    def current_planes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each plane wall as (a point [m], its unit normal) where it is now: moved by its motion, if any."""
        planes = self.scene.planes
        if not planes:
            return []
        self.stepper.drive_walls(self.current_state, self.dt)  # a report pass may have put them at its step
        normal = np.array([p.normal for p in planes], dtype=np.float64)
        point = np.array([p.point for p in planes], dtype=np.float64)
        rest = np.einsum("ij,ij->i", normal, point)
        shift = self.stepper.planes.offset.numpy().astype(np.float64) - rest
        if not self.model.has_wall_motions:
            shift[:] = 0.0  # the model's float32 offsets would move them by their rounding
        return [(x + d * n, n) for x, n, d in zip(point, normal, shift, strict=True)]

    def state(self) -> dict[str, np.ndarray]:
        """Current state as numpy arrays (world frame, body frame = centroid and principal axes).

        Returns a dict: ``body_position`` (N,3) [m], ``body_orientation`` (N,4) quaternion xyzw,
        ``body_velocity`` (N,3) [m/s], ``body_angular_velocity`` (N,3) world axes [rad/s].
        """
        st = self.current_state
        q = st.body_q.numpy()
        return {
            "body_position": q[:, :3].astype(np.float64),
            "body_orientation": q[:, 3:].astype(np.float64),
            "body_velocity": st.body_v.numpy().astype(np.float64),
            "body_angular_velocity": st.body_w.numpy().astype(np.float64),
        }

    def energy(self, bodies: np.ndarray | None = None, pairs: np.ndarray | None = None) -> dict[str, float]:
        """Energies [J]: ``kinetic``, ``contact`` (W(V) summed over contacts, plus the friction
        springs), ``gravity`` (-sum m g.x over free bodies), ``dissipated`` (by damping and friction
        so far), and ``total`` (their sum, constant up to the integrator's error).

        ``bodies`` ((N,) bool) counts only those bodies (their kinetic, gravitational and dissipated
        energy and their wall contacts) and ``pairs`` ((C,) bool over the candidate pairs, in pair-list
        order) only those pairs' contacts: a rank of a decomposed run books its own share so.
        """
        m = self.model
        st = self.current_state
        d = self._diagnostics()
        keep = np.ones(self.num_bodies, dtype=bool) if bodies is None else np.asarray(bodies, dtype=bool)
        pair_energy = d["pair_energy"] if pairs is None else d["pair_energy"][np.asarray(pairs, dtype=bool)]
        contact = float(np.sum(pair_energy, dtype=np.float64))
        if m.num_walls:
            contact += float(np.sum(d["wall_energy"][keep], dtype=np.float64))
        free = (m.body_flags_np == BodyKind.FREE) & keep
        x = st.body_q.numpy()[:, :3].astype(np.float64)
        grav = -float(np.sum(m.body_mass[free].astype(np.float64) * (x[free] @ m.gravity)))
        if bodies is None:
            lin, ang = self.stepper.kinetic_energy(st)
            kin = float(lin + ang)
        else:
            lin, ang = self.stepper.kinetic_energies(st)
            kin = float(np.sum(lin.numpy()[keep], dtype=np.float64) + np.sum(ang.numpy()[keep], dtype=np.float64))
        diss = float(np.sum(st.body_dissipated.numpy()[keep], dtype=np.float64))
        return {
            "kinetic": kin,
            "contact": contact,
            "gravity": grav,
            "dissipated": diss,
            "total": kin + contact + grav + diss,
        }

    def _reported(self) -> dict[str, np.ndarray]:
        # The host arrays of contacts(): the last step's force stage run again (Stepper.report) on
        # its kept inputs, or, with no step since the state was set (the start, a restore), on the
        # current state: the forces the next step will apply. Kept until a step or a restore.
        if self._report_cache is None:
            self._report_cache = self.stepper.report(self._last_step_inputs(), self.current_contacts, self.dt)
        return self._report_cache

    def _last_step_inputs(self) -> dict[str, wp.array]:
        """What the force stage of the last step read, by name (as :class:`StepInputs`' arrays), or
        the current state and pair history where no step ran since the state was set."""
        contacts = self.current_contacts
        if self._last_step == "inputs":
            return self._inputs.arrays
        if self._last_step == "snapshot":
            snap = self._last_good
            st, history = snap.state, snap.pairs
            # The snapshot's pair history is by key, from before the step's broad phase: carried onto
            # the pair list that phase made (the current one), as the step's rebuild carried it.
            xi, turn = self.stepper.history_on(history, contacts)
            # (a snapshot holds no damping loads: the report computes them from this history)
            arrays = {k: getattr(st, k) for k in StepInputs.STATE if k in vars(st)}
            arrays.update(pair_xi=xi, pair_turn=turn)
            return arrays
        st = self.current_state
        arrays = {k: getattr(st, k) for k in StepInputs.STATE}
        arrays.update(pair_xi=contacts.pair_xi, pair_turn=contacts.pair_turn)
        return arrays

    def contacts(self) -> dict[str, np.ndarray]:
        """The contacts of the last step and the forces it applied, as numpy arrays, one row per contact.

        ``body_a``, ``body_b`` (int; ``body_b = -1 - p`` for wall p: the planes, then the mesh
        walls), ``normal`` (N,3) from A into B, ``point`` (N,3) [m], ``normal_force`` (N,) [N],
        ``tangential_force`` (N,3) on A [N], ``volume`` (N,) [m^3], ``depth`` (N,) [m]: the
        penetration depth, the shortest translation along a face normal of either body that separates
        the pair (for a wall, how far the body's lowest vertex lies beyond it).

        The forces are those the last step computed and integrated: for each free body, the sum of
        ``-normal_force * normal + tangential_force`` over its rows (negated where it is B) plus m g
        is m (v - v_before) / dt of that step, to rounding. The geometry (volume, normal, point,
        depth) is that of the poses the step started from, where its forces were evaluated (one
        step before :meth:`state`). Before the first step, and after :meth:`restore`: the contacts at
        the current state with the forces the next step will apply. The report runs the step's force
        stage again (the same kernels, in a variant that also writes the contacts) on what it read:
        :meth:`step` runs its last step alone in a chunk, so the copy it takes before each chunk, for
        a redo, holds it (:meth:`advance` keeps a copy of its own). Stepping costs nothing more and
        holds no more memory. See :meth:`start_contact_average` for forces averaged over an interval.
        """
        bp = self.current_contacts.broadphase
        d = self._reported()
        count = len(d["pair_volume"])
        vol = d["pair_volume"]
        on = vol > 0.0
        out = {
            "body_a": bp.pair_a.numpy()[:count][on].astype(np.int64),
            "body_b": bp.pair_b.numpy()[:count][on].astype(np.int64),
            "normal": d["pair_normal"][on].astype(np.float64),
            "point": d["pair_point"][on].astype(np.float64),
            "normal_force": d["pair_fn"][on].astype(np.float64),
            "tangential_force": d["pair_ft"][on].astype(np.float64),
            "volume": vol[on].astype(np.float64),
            "depth": d["pair_depth"][on].astype(np.float64),
        }
        if self.model.num_walls:
            pv = d["wall_volume"]
            body, wall = np.nonzero(pv > 0.0)
            normals = -self.model.plane_normal.numpy().astype(np.float64).reshape(-1, 3)
            mesh_normals = d["wall_normal"][body, wall].astype(np.float64)
            is_plane = wall < self.model.num_planes
            normal = mesh_normals.copy()
            normal[is_plane] = normals[wall[is_plane]]
            out["body_a"] = np.concatenate([out["body_a"], body])
            out["body_b"] = np.concatenate([out["body_b"], -1 - wall])
            out["normal"] = np.concatenate([out["normal"], normal])
            out["point"] = np.concatenate([out["point"], d["wall_point"][body, wall].astype(np.float64)])
            out["normal_force"] = np.concatenate([out["normal_force"], d["wall_fn"][body, wall].astype(np.float64)])
            out["tangential_force"] = np.concatenate(
                [out["tangential_force"], d["wall_ft"][body, wall].astype(np.float64)]
            )
            out["volume"] = np.concatenate([out["volume"], pv[body, wall].astype(np.float64)])
            out["depth"] = np.concatenate([out["depth"], d["wall_depth"][body, wall].astype(np.float64)])
        return out

    # -- contact forces averaged over an interval ------------------------------------------------

    def start_contact_average(self) -> None:
        """Start (or start again) averaging the contact forces over the steps from now on.

        Every later :meth:`step` adds each contact's force, as the step applied it, to sums on the
        device (no host synchronisation; a captured CUDA graph does it too), until
        :meth:`stop_contact_average`; :meth:`contact_average` reads the average so far. While it runs
        the steps use the report variant of the contact kernels (a few more stores per contact); the
        plain step pays nothing. A :meth:`restore` keeps the interval going (with the sums of the
        snapshot where it was taken in this interval, else from zero at the restored step); a
        checkpoint does not hold the sums. Not in a decomposed run (:mod:`polydem.distributed`).
        """
        self._intervals += 1
        if self._average is None:
            self._average = ContactAverage(
                self.current_contacts, self.model.num_walls, self._intervals, self.steps_done, self.time
            )
        else:
            self._average.reset(self._intervals, self.steps_done, self.time)

    @property
    def contact_average_steps(self) -> int | None:
        """Steps in the running contact-force average so far (None: none is running)."""
        return None if self._average is None else self.steps_done - self._average.start_step

    def contact_average(self) -> dict[str, np.ndarray | float | int]:
        """The contact forces averaged over the interval from :meth:`start_contact_average` to now.

        One row per contact that had an overlap in some step of the interval (pairs by key, then
        wall contacts by body and wall, as :meth:`contacts`), with its impulse over the interval
        divided by the interval's length: a contact that lasted part of the interval (an impact)
        counts over the whole of it, so that for each free body the sum of its rows' ``force``
        (negated where it is B) plus m g is m (v_end - v_start) / (end_time - start_time), to rounding.

        Returns a dict: ``body_a``, ``body_b`` (as :meth:`contacts`), ``force`` (M,3) mean force on
        A [N], ``normal_force`` (M,) mean magnitude of the normal force [N], ``tangential_force``
        (M,3) mean tangential force on A [N], ``normal`` (M,3) unit direction of the mean normal
        force on A, negated (from A into B; zero where it vanishes), ``point`` (M,3) mean contact
        point over the steps in contact [m], ``contact_time`` (M,) time in contact [s]; and
        ``start_time``, ``end_time`` [s] and ``steps`` (int) of the interval.

        Raises:
            RuntimeError: no average is running (call :meth:`start_contact_average` first).
            ValueError: the interval has no step yet.
        """
        avg = self._average
        if avg is None:
            raise RuntimeError("no contact-force average is running: call start_contact_average() first")
        steps = self.steps_done - avg.start_step
        if steps <= 0:
            raise ValueError(
                f"the contact-force average started at step {avg.start_step} has no step yet: step the simulation "
                "before asking for it"
            )
        contacts = self.current_contacts
        sums = avg.numpy(contacts.pair_key, contacts.pair_count)
        key = sums["key"]
        n = self.num_bodies
        walls = avg.num_walls
        pair = key >= 0
        wall_index = -1 - key[~pair]
        body_a = np.where(pair, key // n, 0)
        body_a[~pair] = wall_index // walls
        body_b = np.where(pair, key % n, 0)
        body_b[~pair] = -1 - wall_index % walls
        force = sums["force"] / steps
        tangential = sums["tangential"] / steps
        normal_vec = -(force - tangential)
        size = np.linalg.norm(normal_vec, axis=1, keepdims=True)
        in_contact = np.maximum(sums["steps"], 1)[:, None]
        return {
            "body_a": body_a.astype(np.int64),
            "body_b": body_b.astype(np.int64),
            "force": force,
            "normal_force": sums["normal"] / steps,
            "tangential_force": tangential,
            "normal": np.divide(normal_vec, size, out=np.zeros_like(normal_vec), where=size > 0.0),
            "point": sums["point"] / in_contact,
            "contact_time": sums["steps"].astype(np.float64) * self.dt,
            "start_time": avg.start_time,
            "end_time": self.time,
            "steps": steps,
        }

    def stop_contact_average(self) -> dict[str, np.ndarray | float | int] | None:
        """Stop the contact-force average (the steps go back to the plain kernels); returns its
        :meth:`contact_average`, or None where it had no step (or none was running)."""
        avg = self._average
        if avg is None:
            return None
        result = self.contact_average() if self.steps_done > avg.start_step else None
        avg.detach()
        self._average = None
        return result

    # -- changing the friction during a run ------------------------------------------------------

    def material_friction(self) -> dict[str, float]:
        """The friction coefficient of each material now, by name (the scene's, or :meth:`set_friction`'s)."""
        current = getattr(self, "_friction", None)
        return dict(current) if current is not None else {n: m.friction for n, m in self.scene.materials.items()}

    def set_friction(self, mu: float, material: str | None = None) -> None:
        """Give ``material`` (default: every material) the friction coefficient ``mu`` from the next step on.

        The pairs mix as the scene's do (:meth:`polydem.Scene.pair_table`: the smaller coefficient of the
        two). Only the coefficient changes: the friction springs keep their stiffness and state (a
        stretched spring is capped at the new Coulomb limit by the next step). The step reads the
        coefficients from the device, so a captured CUDA graph runs on with the new ones. The scene is
        not changed: a checkpoint records its friction, and a run resumed from it starts with that.

        Raises:
            ValueError: ``mu`` is not a number >= 0; an unknown material; ``mu`` > 0 where the scene was
                built without friction (every material's friction 0: its kernels have no friction springs).
        """
        from dataclasses import replace

        from polydem.scene.materials import pair_material

        mu = float(mu)
        if not (math.isfinite(mu) and mu >= 0.0):
            raise ValueError(f"friction must be a number >= 0, got {mu!r}")
        current = self.material_friction()
        if material is not None and material not in current:
            raise ValueError(f"unknown material {material!r}; the scene's materials are {', '.join(current)}")
        for name in current if material is None else [material]:
            current[name] = mu
        mats = [replace(self.scene.materials[name], friction=current[name]) for name in self.scene.material_names]
        table = np.array([[pair_material(a, b).friction for b in mats] for a in mats], dtype=np.float64)
        m = self.model
        if (table > 0.0).any() and not m.friction:
            raise ValueError(
                f"friction {mu:g} cannot be set: this simulation was built without friction (every material of the "
                "scene has friction 0), so its contact kernels have no friction springs. Build it with the friction "
                "the run needs at its end (e.g. friction = 0.5 in the material), then set_friction(0) for the part "
                "without"
            )
        m.material_mu.assign(table.ravel().astype(numpy_dtype(m.contact_scalar)))
        self._friction = current
