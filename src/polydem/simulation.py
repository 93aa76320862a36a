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
"""

import functools
import math
import time as _time
import warnings

import numpy as np
import warp as wp

from polydem.contacts import Contacts, PairHistory
from polydem.kernels import geometry as _geometry
from polydem.kernels.broadphase import TREE_REBUILD_RATIO
from polydem.kernels.forces import make_contact_kernels
from polydem.kernels.integrate import integrate_bodies, kinetic_energy, make_integrator
from polydem.kernels.meshwall import make_mesh_kernels
from polydem.kernels.narrowphase import NARROWPHASE_BLOCK_DIM
from polydem.model import Model
from polydem.settle import SettleCheck, SettleCriterion, SettleResult
from polydem.state import State

__all__ = ["Simulation", "SimulationError", "SimulationWarning", "Snapshot", "Stepper"]

CHUNK_STEPS = 64
NO_STEP = 2**31 - 1


class SimulationError(RuntimeError):
    """The run cannot go on (a non-finite state); the message names the step and the bodies."""


class SimulationWarning(UserWarning):
    """Something in the run is suspect but it goes on (a body fast enough to tunnel)."""


@functools.cache
def make_check_state_kernel(scalar):
    """The check of a state in ``scalar``: finiteness, and each body's peak speed against its limit."""
    vec3 = wp.types.vector(3, scalar)

    @wp.kernel(enable_backward=False, module="unique")
    def check_state_kernel(
        # Model
        body_flags: wp.array(dtype=int),
        body_radius: wp.array(dtype=float),
        body_speed_limit: wp.array(dtype=float),
        # State in
        step: wp.array(dtype=int),
        body_q: wp.array(dtype=wp.types.transformation(scalar)),
        body_v: wp.array(dtype=vec3),
        body_w: wp.array(dtype=vec3),
        # Out
        bad_step: wp.array(dtype=int),
        body_peak_speed: wp.array(dtype=float),
        too_fast: wp.array(dtype=int),
    ):
        """Records (atomic min) the first step at which a body's state is not finite, each body's
        largest speed of its fastest point (|v| + |w| r), and whether one went above its speed limit."""
        i = wp.tid()
        speed = float(wp.length(body_v[i]) + wp.length(body_w[i]) * scalar(body_radius[i]))
        # One thread per body: a plain running maximum, no atomics.
        if speed > body_peak_speed[i]:
            body_peak_speed[i] = speed
        if speed > body_speed_limit[i]:
            wp.atomic_max(too_fast, 0, 1)
        q = body_q[i]
        p = wp.transform_get_translation(q)
        r = wp.transform_get_rotation(q)
        v = body_v[i]
        w = body_w[i]
        total = p[0] + p[1] + p[2] + r[0] + r[1] + r[2] + r[3] + v[0] + v[1] + v[2] + w[0] + w[1] + w[2]
        if not wp.isfinite(total):
            wp.atomic_min(bad_step, 0, step[0])

    return check_state_kernel


@functools.cache
def make_settle_measures_kernel(scalar):
    """Per free body, in float64: kinetic and gravitational energy; the largest speed of a fastest point."""
    vec3 = wp.types.vector(3, scalar)
    body_kinetic_energy = make_integrator(scalar).body_kinetic_energy

    @wp.kernel(enable_backward=False, module="unique")
    def settle_measures_kernel(
        # Model
        body_flags: wp.array(dtype=int),
        body_inv_mass: wp.array(dtype=scalar),
        body_inertia: wp.array(dtype=vec3),
        body_radius: wp.array(dtype=float),
        gravity: wp.vec3d,
        # State in
        body_q: wp.array(dtype=wp.types.transformation(scalar)),
        body_v: wp.array(dtype=vec3),
        body_w: wp.array(dtype=vec3),
        # Out
        body_kinetic: wp.array(dtype=wp.float64),
        body_gravity: wp.array(dtype=wp.float64),
        largest_speed: wp.array(dtype=wp.float64),
    ):
        """Zero for fixed, kinematic and infinite-mass bodies (driven from outside the pile); the
        speeds go into one running maximum (atomic: a maximum does not depend on the order)."""
        i = wp.tid()
        inv_mass = body_inv_mass[i]
        body_kinetic[i] = wp.float64(0.0)
        body_gravity[i] = wp.float64(0.0)
        if body_flags[i] == 0 and inv_mass > scalar(0.0):
            v = body_v[i]
            w = body_w[i]
            q = body_q[i]
            e_lin, e_ang = body_kinetic_energy(inv_mass, body_inertia[i], q, v, w)
            body_kinetic[i] = wp.float64(e_lin + e_ang)
            x = wp.transform_get_translation(q)
            mass = wp.float64(1.0) / wp.float64(inv_mass)
            h = wp.float64(x[0]) * gravity[0] + wp.float64(x[1]) * gravity[1] + wp.float64(x[2]) * gravity[2]
            body_gravity[i] = -mass * h
            speed = wp.float64(wp.length(v)) + wp.float64(wp.length(w)) * wp.float64(body_radius[i])
            wp.atomic_max(largest_speed, 0, speed)

    return settle_measures_kernel


@wp.kernel(enable_backward=False)
def advance_step_kernel(step: wp.array(dtype=int)):
    step[0] = step[0] + 1


class Stepper:
    """One time step of a :class:`~polydem.model.Model`: ``step(state_in, state_out, contacts, dt)``.

    Stages: :meth:`collide` (the broad phase: rebuild the pair list when needed), :meth:`forces`
    (pair contacts, then the gather per body with the walls), :meth:`integrate` (and the
    finiteness check). The kernels update their arrays in place; ``state_out`` may be
    ``state_in`` (the :class:`Simulation` steps in place, so one captured graph serves every step).

    Args:
        model: the model.
        device_rebuild: rebuild the pair list on the device, without host synchronisation (for
            CUDA graph capture); an overflow is then reported by ``contacts.host_build_needed()``.

    Attributes:
        poly_capacity: room for the vertices of a clipped polygon (grows with :meth:`grow_polygons`).
        poly_overflow: (1,) int32, set when a clipped polygon did not fit (the step must be redone).
        bad_step: (1,) int32, the first step whose state was not finite (``NO_STEP``: none yet).
        body_speed_limit: (N,) float32 speed of a body's fastest point above which it may tunnel
            [m/s] (:meth:`polydem.Scene.tunnelling_limits`; inf until the Simulation sets it).
        body_peak_speed: (N,) float32 largest speed of each body's fastest point so far [m/s].
        too_fast: (1,) int32, set when a body went above its speed limit.
    """

    def __init__(self, model, device_rebuild=False):
        self.model = model
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
        # How the pair kernel holds its working set (same results; benchmarks/settle.py --variants).
        self.pair_variant = _geometry.DEFAULT_PAIR_VARIANT
        self._kernels()
        self._diag = None
        self._diag_generation = None
        self._empty = None

    def _kernels(self):
        m = self.model
        self.kernels = make_contact_kernels(
            m.law,
            m.friction,
            self.poly_capacity,
            m.shapes.max_faces,
            precision=m.precision,
            variant=self.pair_variant,
            compound=m.shapes.compound,
        )
        self.mesh_kernels = self._mesh_kernels(False)

    def _mesh_kernels(self, diagnostics):
        m = self.model
        if not m.num_mesh_walls:
            return None
        return make_mesh_kernels(
            m.law,
            m.friction,
            self.poly_capacity,
            m.shapes.max_faces,
            diagnostics=diagnostics,
            precision=m.precision,
            variant=self.pair_variant,
            compound=m.shapes.compound,
        )

    def grow_polygons(self):
        """Double the room for clipped polygons (after an overflow); new kernels, so recapture a graph."""
        self.poly_overflow.zero_()
        self.poly_capacity = min(2 * self.poly_capacity, self.model.shapes.max_poly_bound)
        self._kernels()

    def clear_checks(self):
        """Forget the non-finite steps and the speeds recorded so far (their states were discarded by a restore)."""
        self.bad_step.fill_(NO_STEP)
        self.body_peak_speed.zero_()
        self.too_fast.zero_()

    def went_too_fast(self):
        """Host: whether a body went above its ``body_speed_limit`` since :meth:`clear_checks`."""
        return bool(int(self.too_fast.numpy()[0]))

    def polygons_overflowed(self):
        """Host: whether a clipped polygon did not fit since :meth:`grow_polygons`."""
        return bool(int(self.poly_overflow.numpy()[0]))

    def first_bad_step(self):
        """Host: the first step whose state was not finite, or None."""
        bad = int(self.bad_step.numpy()[0])
        return None if bad == NO_STEP else bad

    # -- one step ------------------------------------------------------------------------------

    def step(self, state_in, state_out, contacts, dt):
        """Advance ``state_in`` by ``dt`` into ``state_out`` (which may be ``state_in``); updates ``contacts``."""
        if state_out is not state_in:
            state_out.assign(state_in)
        self.collide(state_out, contacts)
        self.forces(state_out, contacts, dt)
        self.integrate(state_out, dt)

    def collide(self, state, contacts):
        """The broad phase: rebuild the pair list when some body may have left its skin."""
        if self.device_rebuild:
            contacts.update_on_device(state.body_q)
        else:
            contacts.update(state.body_q)

    def forces(self, state, contacts, dt):
        """Contact forces and torques of the pairs and walls into ``state.body_f``, ``state.body_t``."""
        self._launch_contacts(self.kernels, None, state, contacts, dt, self.poly_overflow)
        if self.mesh_kernels is not None:
            self._launch_meshes(self.mesh_kernels[0], None, state, dt, self.poly_overflow)

    def integrate(self, state, dt):
        """Move the bodies by ``dt`` under their forces and gravity; count the step; check it is finite."""
        m = self.model
        dev = self.device
        integrate_bodies(
            m.body_inv_mass,
            m.body_inertia,
            m.body_flags,
            m.gravity,
            state.body_q,
            state.body_v,
            state.body_w,
            state.body_f,
            state.body_t,
            dt,
            device=dev,
            body_pivot=m.body_pivot,
        )
        if self.mesh_kernels is not None and m.mesh_moves:
            wp.launch(
                self.mesh_kernels[1],
                dim=m.num_mesh_walls,
                inputs=[m.mesh_v, m.mesh_w, m.scalar(dt), state.mesh_q],
                device=dev,
            )
        wp.launch(advance_step_kernel, dim=1, inputs=[state.step_count], device=dev)
        wp.launch(
            make_check_state_kernel(m.scalar),
            dim=m.num_bodies,
            inputs=[
                m.body_flags,
                m.body_radius,
                self.body_speed_limit,
                state.step_count,
                state.body_q,
                state.body_v,
                state.body_w,
            ],
            outputs=[self.bad_step, self.body_peak_speed, self.too_fast],
            device=dev,
        )

    def _launch_contacts(self, kernels, diag, state, contacts, dt, overflow):
        """The pair and gather kernels: the step variant, or the diagnostics one into ``diag``;
        a clipped polygon that did not fit sets ``overflow``."""
        m = self.model
        s = m.shapes
        bp = contacts.broadphase
        dev = self.device
        materials = [m.num_materials, m.material_k, m.material_e, m.material_mu, m.material_kt, m.law_m, dt]
        d = diag if diag is not None else self._placeholders()
        wp.launch(
            kernels.pair_contact_kernel,
            dim=contacts.capacity,
            inputs=[
                *s.kernel_args(),
                m.body_shape,
                m.body_material,
                m.body_inv_mass,
                *materials,
                state.body_q,
                state.body_v,
                state.body_w,
                bp.pair_a,
                bp.pair_b,
                bp.pair_count,
                contacts.pair_xi,
                contacts.pair_turn,
            ],
            outputs=[
                contacts.pair_force,
                contacts.pair_torque_a,
                contacts.pair_dissipated,
                overflow,
                d["pair_volume"],
                d["pair_energy"],
                d["pair_normal"],
                d["pair_point"],
                d["pair_fn"],
                d["pair_ft"],
                d["pair_depth"],
            ],
            device=dev,
            block_dim=NARROWPHASE_BLOCK_DIM,
        )
        wp.launch(
            kernels.gather_kernel,
            dim=m.num_bodies,
            inputs=[
                *s.kernel_args(),
                m.body_shape,
                m.body_material,
                m.body_flags,
                m.body_inv_mass,
                *materials,
                m.plane_normal,
                m.plane_offset,
                m.plane_material,
                state.body_q,
                state.body_v,
                state.body_w,
                bp.pair_a,
                bp.pair_b,
                contacts.body_pairs_a,
                contacts.body_pairs_b,
                contacts.pair_by_b,
                contacts.pair_force,
                contacts.pair_torque_a,
                contacts.pair_dissipated,
                state.plane_xi,
                state.plane_turn,
                state.body_dissipated,
            ],
            outputs=[
                state.body_f,
                state.body_t,
                d["plane_volume"],
                d["plane_energy"],
                d["plane_fn"],
                d["plane_point"],
                d["plane_ft"],
                d["plane_depth"],
            ],
            device=dev,
        )

    def _launch_meshes(self, kernel, diag, state, dt, overflow):
        """The mesh-wall contacts of every body, added to ``state.body_f`` and ``body_t`` after the
        gather (step), or reported into ``diag``'s wall columns (diagnostics)."""
        m = self.model
        d = diag if diag is not None else self._placeholders()
        wp.launch(
            kernel,
            dim=m.num_bodies,
            inputs=[
                *m.shapes.kernel_args(),
                m.body_shape,
                m.body_material,
                m.body_flags,
                m.body_inv_mass,
                m.body_radius,
                m.num_materials,
                m.material_k,
                m.material_e,
                m.material_mu,
                m.material_kt,
                m.law_m,
                dt,
                m.mesh_bvh,
                m.mesh_cell_start,
                m.mesh_material,
                m.mesh_v,
                m.mesh_w,
                m.cell_shape,
                m.cell_center,
                m.cell_front,
                m.num_planes,
                state.body_q,
                state.body_v,
                state.body_w,
                state.mesh_q,
                state.plane_xi,
                state.plane_turn,
                state.body_dissipated,
                state.body_f,
                state.body_t,
                overflow,
            ],
            outputs=[
                d["plane_volume"],
                d["plane_energy"],
                d["plane_fn"],
                d["plane_point"],
                d["plane_ft"],
                d["plane_depth"],
                d["plane_normal"],
            ],
            device=self.device,
        )

    def _diag_arrays(self, pairs, bodies, planes):
        # The outputs of the diagnostics variant: contact points in the state's scalar (they are
        # world positions), the rest in the contact scalar.
        dev = self.device
        m = self.model
        c = m.contact_scalar
        vec3c = wp.types.vector(3, c)
        vec3s = wp.types.vector(3, m.scalar)
        out = {}
        for prefix, shape in (("pair", pairs), ("plane", (bodies, planes))):
            out[f"{prefix}_volume"] = wp.zeros(shape, dtype=c, device=dev)
            out[f"{prefix}_energy"] = wp.zeros(shape, dtype=c, device=dev)
            if prefix == "pair":
                out["pair_normal"] = wp.zeros(shape, dtype=vec3c, device=dev)
            out[f"{prefix}_point"] = wp.zeros(shape, dtype=vec3s, device=dev)
            out[f"{prefix}_fn"] = wp.zeros(shape, dtype=c, device=dev)
            out[f"{prefix}_ft"] = wp.zeros(shape, dtype=vec3c, device=dev)
            out[f"{prefix}_depth"] = wp.zeros(shape, dtype=c, device=dev)
        # The normals of the mesh-wall contacts (a plane's is the plane's).
        out["plane_normal"] = wp.zeros((bodies, planes), dtype=vec3c, device=dev)
        return out

    def _placeholders(self):
        if getattr(self, "_empty", None) is None:
            self._empty = self._diag_arrays(1, 1, 1)
        return self._empty

    def diagnose(self, state, contacts, dt):
        """Runs the diagnostics variant of the contact kernels at ``state``; returns its host arrays.

        Per pair (the first ``count`` candidates): ``pair_volume`` [m^3], ``pair_energy`` [J],
        ``pair_normal``, ``pair_point`` [m], ``pair_fn`` [N], ``pair_ft`` [N], ``pair_depth`` [m]; per
        (body, wall): ``plane_volume``, ``plane_energy``, ``plane_fn``, ``plane_point``, ``plane_ft``,
        ``plane_depth``.
        """
        cap = contacts.capacity
        n = self.model.num_bodies
        p = max(self.model.num_walls, 1)
        if self._diag is None or self._diag_generation != contacts.generation:
            self._diag_generation = contacts.generation
            self._diag = self._diag_arrays(cap, n, p)
        m = self.model
        while True:
            self._diag_overflow.zero_()
            kernels = make_contact_kernels(
                m.law,
                m.friction,
                self.poly_capacity,
                m.shapes.max_faces,
                diagnostics=True,
                precision=m.precision,
                variant=self.pair_variant,
                compound=m.shapes.compound,
            )
            self._launch_contacts(kernels, self._diag, state, contacts, dt, self._diag_overflow)
            if m.num_mesh_walls:
                self._launch_meshes(self._mesh_kernels(True)[0], self._diag, state, dt, self._diag_overflow)
            if not int(self._diag_overflow.numpy()[0]) or self.poly_capacity >= m.shapes.max_poly_bound:
                break
            # A clipped polygon did not fit: its contact is wrong. Grow the room (the steps use it
            # too from now on: their kernels and graph are rebuilt) and run the pass again.
            self.poly_capacity = min(2 * self.poly_capacity, m.shapes.max_poly_bound)
            self._kernels()
        count = contacts.count()
        out = {k: v.numpy() for k, v in self._diag.items()}
        for k in ("pair_volume", "pair_energy", "pair_normal", "pair_point", "pair_fn", "pair_ft", "pair_depth"):
            out[k] = out[k][:count]
        return out

    def release_diagnostics(self):
        """Let the buffers of :meth:`diagnose` go (they are allocated again when needed)."""
        self._diag = None

    def kinetic_energy(self, state):
        """Host float64 (translational, rotational) kinetic energy of the free bodies [J]."""
        m = self.model
        lin, ang = kinetic_energy(
            m.body_inv_mass, m.body_inertia, m.body_flags, state.body_q, state.body_v, state.body_w, device=self.device
        )
        return np.sum(lin.numpy(), dtype=np.float64), np.sum(ang.numpy(), dtype=np.float64)


class Snapshot:
    """A copy of a simulation at one step: :class:`~polydem.state.State`, pair history, step count and time.

    From :meth:`Simulation.snapshot`; give it to :meth:`Simulation.restore` to go back to that step.
    """

    def __init__(self, state, pairs, steps_done, time):
        self.state = state
        self.pairs = pairs
        self.steps_done = int(steps_done)
        self.time = float(time)


class Simulation:
    """Steps a :class:`~polydem.Scene` on a Warp device.

    Args:
        scene: the scene (validated here).
        device: Warp device, default Warp's default device ("cuda:0" when there is one).
        skin: Verlet skin [m]; default a fifth of the smallest free body's bounding radius.
        use_graph: capture the step as a CUDA graph (default: on CUDA devices).
        validate: validate the scene first (off only for scenes built from a validated one, such as the
            parts of a decomposed run, :mod:`polydem.distributed`).
        tree_rebuild: when the broad phase rebuilds on the device (the CUDA graph), it refits the tree of
            the last host build; after each chunk of steps the tree is rebuilt when refitting has made it
            this many times as costly as a fresh one (:meth:`~polydem.kernels.broadphase.BroadPhase.renew_tree`);
            0: after every chunk with a device rebuild; None (default): never. The pairs, and so the
            results, do not depend on it. Without the graph every rebuild builds a fresh tree.

    Attributes:
        model: the :class:`~polydem.model.Model` (static).
        current_state: the :class:`~polydem.state.State` after the last step (stepped in place).
        current_contacts: the :class:`~polydem.contacts.Contacts` (pair list and its history).
        stepper: the :class:`Stepper`.
        steps_done: steps taken; time: ``steps_done * dt`` [s]; dt: time step [s].
    """

    def __init__(
        self, scene, device=None, skin=None, use_graph=None, tree_rebuild=TREE_REBUILD_RATIO, *, validate=True
    ):
        if tree_rebuild is not None and not float(tree_rebuild) >= 0.0:
            raise ValueError(f"tree_rebuild must be >= 0 or None, got {tree_rebuild}")
        self.tree_rebuild = None if tree_rebuild is None else float(tree_rebuild)
        self.model = model = Model(scene, device, validate=validate)
        self.device = dev = model.device
        self.dt = model.dt
        n = model.num_bodies
        self.num_bodies = n
        self.use_graph = dev.is_cuda if use_graph is None else (bool(use_graph) and dev.is_cuda)
        self.current_state = model.state()
        self.steps_done = 0
        self.time = 0.0

        radius = model.body_radius.numpy()
        free = model.body_flags_np == 0
        r_min = float(radius[free].min()) if free.any() else float(radius.min())
        self.skin = 0.2 * r_min if skin is None else float(skin)
        # Bounding spheres about the centre do not change as a body turns: no rotation term.
        shape_list = [scene.shapes[name] for name in scene.shape_names]
        lower = np.array([s.vertices.min(axis=0) for s in shape_list])[scene.body_shape]
        upper = np.array([s.vertices.max(axis=0) for s in shape_list])[scene.body_shape]
        # Settled packings of convex grains have 3-4 candidate pairs per body at this skin: start
        # with room for 5 (an overflow grows the buffers and redoes the step).
        self.current_contacts = Contacts(model, self.skin, body_box=(lower, upper), capacity=max(1024, 5 * n))
        self.stepper = Stepper(model, device_rebuild=self.use_graph)
        arrays = scene.body_arrays()
        self._tunnel = scene.tunnelling_limits(arrays, self.dt)
        self.stepper.body_speed_limit.assign(self._tunnel.body_speed_limit.astype(np.float32))
        # Warned once a run: already by the scene's validation where the initial speeds are too high.
        self._tunnel_warned = bool(scene.check_tunnelling(arrays, self.dt))
        self._graph = None
        self._graph_key = None
        self._last_good = None
        self._diag_cache = None
        self.current_contacts.build(self.current_state.body_q, keep_history=False)

    # -- the arrays of the current state, by their former names --------------------------------

    @property
    def body_q(self):
        """``current_state.body_q``."""
        return self.current_state.body_q

    @property
    def body_v(self):
        """``current_state.body_v``."""
        return self.current_state.body_v

    @property
    def body_w(self):
        """``current_state.body_w``."""
        return self.current_state.body_w

    @property
    def body_f(self):
        """``current_state.body_f``."""
        return self.current_state.body_f

    @property
    def body_t(self):
        """``current_state.body_t``."""
        return self.current_state.body_t

    @property
    def step_count(self):
        """``current_state.step_count``."""
        return self.current_state.step_count

    @property
    def broadphase(self):
        """``current_contacts.broadphase``."""
        return self.current_contacts.broadphase

    # -- snapshots -----------------------------------------------------------------------------

    def snapshot(self, into=None):
        """A :class:`Snapshot` (device copies) of the current step; reuses the arrays of ``into`` where they fit."""
        st = self.current_state
        if into is not None and into.state.same_shapes(st):
            into.state.assign(st)
            state = into.state
        else:
            state = st.copy()
        pairs = self.current_contacts.history(into.pairs if into is not None else None)
        if into is None:
            return Snapshot(state, pairs, self.steps_done, self.time)
        into.state, into.pairs, into.steps_done, into.time = state, pairs, self.steps_done, self.time
        return into

    def restore(self, snapshot):
        """Go back to the step of ``snapshot`` (from :meth:`snapshot`, or a checkpoint's).

        The candidate pairs are found afresh at the restored poses; each pair gets its history back by key.
        """
        self._diag_cache = None
        # A non-finite step recorded after the snapshot belongs to the states that are discarded now.
        self.stepper.clear_checks()
        self.current_state.assign(snapshot.state)
        self.current_contacts.restore(snapshot.pairs, self.current_state.body_q)
        self.steps_done = snapshot.steps_done
        self.time = snapshot.time

    def restore_from_arrays(self, arrays, steps_done, time):
        """:meth:`restore` from host arrays named as a checkpoint's: ``State.SAVED``, ``pair_key``, ``pair_xi``,
        ``pair_turn``."""
        m = self.model
        saved = {k: arrays[k] for k in State.SAVED if k in arrays}
        if "mesh_q" not in saved:
            saved["mesh_q"] = self.current_state.mesh_q.numpy()
        state = State.from_numpy(saved, self.device, m.precision)
        pairs = PairHistory.from_numpy(
            arrays["pair_key"], arrays["pair_xi"], arrays["pair_turn"], m.friction, self.device, m.contact_scalar
        )
        self.restore(Snapshot(state, pairs, steps_done, time))

    @property
    def last_good(self):
        """The :class:`Snapshot` taken at the start of the last chunk of :meth:`step` (None before the first)."""
        return self._last_good

    def is_consistent(self):
        """Whether the device state is that of step ``steps_done`` and finite (synchronises)."""
        st = self.current_state
        return int(st.step_count.numpy()[0]) == self.steps_done and bool(np.all(np.isfinite(st.body_q.numpy())))

    def restore_last_good(self):
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

    def _run_chunk(self, steps):
        self._diag_cache = None
        state, contacts = self.current_state, self.current_contacts
        if self.use_graph:
            key = (contacts.generation, self.stepper.poly_capacity)
            if self._graph is None or self._graph_key != key:
                with wp.ScopedCapture(device=self.device) as capture:
                    self.stepper.step(state, state, contacts, self.dt)
                self._graph = capture.graph
                self._graph_key = key
            for _ in range(steps):
                wp.capture_launch(self._graph)
        else:
            for _ in range(steps):
                self.stepper.step(state, state, contacts, self.dt)

    def step(self, n=1):
        """Advance ``n`` steps of length ``dt``."""
        n = int(n)
        if n < 0:
            raise ValueError(f"step count must be >= 0, got {n}")
        done = 0
        while done < n:
            chunk = min(CHUNK_STEPS, n - done)
            self._last_good = self.snapshot(into=self._last_good)
            self._run_chunk(chunk)
            redo = False
            if self.stepper.polygons_overflowed():
                self.stepper.grow_polygons()
                redo = True
            if self.stepper.device_rebuild and self.current_contacts.host_build_needed():
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

    def _warn_too_fast(self, chunk):
        # Once a run: the body the furthest above its limit, at its largest speed so far.
        self._tunnel_warned = True
        peak = self.stepper.body_peak_speed.numpy().astype(np.float64)
        i = int(np.argmax(peak / self._tunnel.body_speed_limit))
        scene = self.model.scene
        warnings.warn(
            f"{scene.body_label(i)} reached {self._tunnel.describe(i, float(peak[i]), self.dt)} "
            f"(in steps {self.steps_done + 1} to {self.steps_done + chunk})",
            SimulationWarning,
            stacklevel=3,
        )

    def advance(self, steps):
        """Run ``steps`` steps with no host check, copy or redo (one CUDA graph launch each on a GPU).

        For callers that check for themselves what :meth:`step` checks after each chunk (the overflow
        flags of ``stepper`` and ``current_contacts``, the first non-finite step) and keep their own
        copy to go back to: a decomposed run (:mod:`polydem.distributed`) does, once per chunk of all
        its ranks. Does not count the steps (``steps_done``, ``time``): the caller sets them.
        """
        self._run_chunk(int(steps))

    def forget_diagnostics(self):
        """Drop the contact diagnostics computed at this step (after the state was changed from outside)."""
        self._diag_cache = None

    def diagnostics(self):
        """The per-pair and per-wall diagnostics of the current step (what :meth:`energy` and
        :meth:`contacts` read): host arrays by name, ``pair_*`` (candidate pairs, in pair-list order)
        and ``plane_*`` (bodies x walls)."""
        return self._diagnostics()

    def _report_nonfinite(self, bad):
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

    def settle_measures(self):
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
        st = self.current_state
        wp.launch(
            make_settle_measures_kernel(m.scalar),
            dim=n,
            inputs=[
                m.body_flags,
                m.body_inv_mass,
                m.body_inertia,
                m.body_radius,
                wp.vec3d(*m.gravity.tolist()),
                st.body_q,
                st.body_v,
                st.body_w,
            ],
            outputs=[kin, grav, out[2:3]],
            device=dev,
        )
        wp.utils.array_sum(kin, out=out[0:1])
        wp.utils.array_sum(grav, out=out[1:2])
        kinetic, gravity, speed = out.numpy().tolist()
        return kinetic, gravity, speed

    def settle_check(self, criterion=None, check=None):
        """A :class:`~polydem.settle.SettleCheck` of ``criterion`` (default :class:`SettleCriterion()`)
        from the current step; ``check``: one to continue instead. Raises ValueError when the criterion
        cannot be met in this scene (no free body; the kinetic part without gravity)."""
        if check is not None:
            return check
        criterion = SettleCriterion() if criterion is None else criterion
        if not isinstance(criterion, SettleCriterion):
            raise TypeError(f"criterion must be a polydem.SettleCriterion, got {type(criterion).__name__}")
        if not np.any(self.model.body_flags_np == 0):
            raise ValueError("the scene has no free bodies: there is nothing to settle")
        criterion.check_gravity(self.model.gravity)
        return SettleCheck(criterion, self.settle_measures()[1])

    def run_until_settled(self, max_time, criterion=None, *, check=None):
        """Step until the free bodies have settled (``criterion``, default :class:`SettleCriterion()`),
        for at most ``max_time`` more simulated seconds.

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
        )

    # -- reading the current step --------------------------------------------------------------

    def _diagnostics(self):
        # energy() and contacts() at the same step share one run (dropped by a step and a restore).
        if self._diag_cache is None:
            self._diag_cache = self.stepper.diagnose(self.current_state, self.current_contacts, self.dt)
        return self._diag_cache

    def state(self):
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

    def energy(self, bodies=None, pairs=None):
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
            contact += float(np.sum(d["plane_energy"][keep], dtype=np.float64))
        free = (m.body_flags_np == 0) & keep
        x = st.body_q.numpy()[:, :3].astype(np.float64)
        grav = -float(np.sum(m.body_mass[free].astype(np.float64) * (x[free] @ m.gravity)))
        if bodies is None:
            lin, ang = self.stepper.kinetic_energy(st)
            kin = float(lin + ang)
        else:
            lin, ang = kinetic_energy(
                m.body_inv_mass, m.body_inertia, m.body_flags, st.body_q, st.body_v, st.body_w, device=self.device
            )
            kin = float(np.sum(lin.numpy()[keep], dtype=np.float64) + np.sum(ang.numpy()[keep], dtype=np.float64))
        diss = float(np.sum(st.body_dissipated.numpy()[keep], dtype=np.float64))
        return {
            "kinetic": kin,
            "contact": contact,
            "gravity": grav,
            "dissipated": diss,
            "total": kin + contact + grav + diss,
        }

    def contacts(self):
        """Current contacts (overlap volume > 0) as numpy arrays, one row per contact.

        ``body_a``, ``body_b`` (int; ``body_b = -1 - p`` for wall p: the planes, then the mesh
        walls), ``normal`` (N,3) from A
        into B, ``point`` (N,3) [m], ``normal_force`` (N,) [N], ``tangential_force`` (N,3) on A [N],
        ``volume`` (N,) [m^3], ``depth`` (N,) [m]: the penetration depth, the shortest translation along
        a face normal of either body that separates the pair (for a wall, how far the body's lowest
        vertex lies beyond it). Computed at the current state (after the last step).
        """
        bp = self.current_contacts.broadphase
        d = self._diagnostics()
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
            pv = d["plane_volume"]
            body, plane = np.nonzero(pv > 0.0)
            normals = -self.model.plane_normal.numpy().astype(np.float64).reshape(-1, 3)
            mesh_normals = d["plane_normal"][body, plane].astype(np.float64)
            is_plane = plane < self.model.num_planes
            normal = mesh_normals.copy()
            normal[is_plane] = normals[plane[is_plane]]
            out["body_a"] = np.concatenate([out["body_a"], body])
            out["body_b"] = np.concatenate([out["body_b"], -1 - plane])
            out["normal"] = np.concatenate([out["normal"], normal])
            out["point"] = np.concatenate([out["point"], d["plane_point"][body, plane].astype(np.float64)])
            out["normal_force"] = np.concatenate([out["normal_force"], d["plane_fn"][body, plane].astype(np.float64)])
            out["tangential_force"] = np.concatenate(
                [out["tangential_force"], d["plane_ft"][body, plane].astype(np.float64)]
            )
            out["volume"] = np.concatenate([out["volume"], pv[body, plane].astype(np.float64)])
            out["depth"] = np.concatenate([out["depth"], d["plane_depth"][body, plane].astype(np.float64)])
        return out
