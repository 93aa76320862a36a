"""Simulation: owns the Model, the State and the contact buffers, and steps them.

Each step: broad phase (Verlet skin; rebuilt only when some body moved far enough) -> pair
contacts (narrow phase and wrench per candidate pair) -> gather per body (plus the walls) ->
integrate -> finiteness check. On a CUDA device the step is captured once as a CUDA graph, the
broad-phase rebuild as a conditional node inside it, and replayed; the CPU runs the same kernels.

Steps run in chunks between host checks. A chunk starts from a saved copy of the state; when
something overflowed during the chunk (the candidate-pair buffer in a device rebuild, or a
clipped polygon) the state is restored, the buffer grown, and the chunk run again, so no contact
is ever dropped. A non-finite value stops the run with an error naming the step and the bodies.
"""

import numpy as np
import warp as wp

from polydem.kernels.broadphase import BroadPhase
from polydem.kernels.forces import (
    b_keys_kernel,
    body_ranges_kernel,
    make_contact_kernels,
    remap_history_kernel,
)
from polydem.kernels.integrate import integrate_bodies, kinetic_energy
from polydem.kernels.narrowphase import NARROWPHASE_BLOCK_DIM
from polydem.model import Model

__all__ = ["Simulation", "SimulationError"]

CHUNK_STEPS = 64


class SimulationError(RuntimeError):
    """The run cannot go on (a non-finite state); the message names the step and the bodies."""


@wp.kernel(enable_backward=False)
def check_state_kernel(
    # Model
    body_flags: wp.array(dtype=int),
    # State in
    step: wp.array(dtype=int),
    body_q: wp.array(dtype=wp.transform),
    body_v: wp.array(dtype=wp.vec3),
    body_w: wp.array(dtype=wp.vec3),
    # Out
    bad_step: wp.array(dtype=int),
):
    """Records (atomic min) the first step at which a body's state is not finite."""
    i = wp.tid()
    q = body_q[i]
    p = wp.transform_get_translation(q)
    r = wp.transform_get_rotation(q)
    v = body_v[i]
    w = body_w[i]
    total = p[0] + p[1] + p[2] + r[0] + r[1] + r[2] + r[3] + v[0] + v[1] + v[2] + w[0] + w[1] + w[2]
    if not wp.isfinite(total):
        wp.atomic_min(bad_step, 0, step[0])


@wp.kernel(enable_backward=False)
def advance_step_kernel(step: wp.array(dtype=int)):
    step[0] = step[0] + 1


class Simulation:
    """Steps a :class:`~polydem.Scene` on a Warp device.

    Args:
        scene: the scene (validated here).
        device: Warp device, default Warp's default device ("cuda:0" when there is one).
        skin: Verlet skin [m]; default a fifth of the smallest free body's bounding radius.
        use_graph: capture the step as a CUDA graph (default: on CUDA devices).
    """

    def __init__(self, scene, device=None, skin=None, use_graph=None):
        self.model = model = Model(scene, device)
        self.device = dev = model.device
        self.dt = model.dt
        n = model.num_bodies
        self.num_bodies = n
        self.use_graph = dev.is_cuda if use_graph is None else (bool(use_graph) and dev.is_cuda)

        # State
        self.body_q = wp.array(
            np.hstack([scene.body_position, scene.body_orientation]).astype(np.float32), dtype=wp.transform, device=dev
        )
        self.body_v = wp.array(np.asarray(scene.body_velocity, dtype=np.float32), dtype=wp.vec3, device=dev)
        self.body_w = wp.array(np.asarray(scene.body_angular_velocity, dtype=np.float32), dtype=wp.vec3, device=dev)
        self.body_f = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.body_t = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.body_dissipated = wp.zeros(n, dtype=float, device=dev)
        # Friction springs of the wall contacts (a placeholder when the scene has no friction).
        shape = (n, max(model.num_planes, 1)) if model.friction else (1, 1)
        self.plane_xi = wp.zeros(shape, dtype=wp.vec3, device=dev)
        # Turning volumes of the wall contacts (the normal hysteresis, kernels/forces.py).
        self.plane_turn = wp.zeros((n, max(model.num_planes, 1)), dtype=float, device=dev)
        self._diag = None
        self.step_count = wp.zeros(1, dtype=int, device=dev)
        self.bad_step = wp.full(1, 2**31 - 1, dtype=int, device=dev)
        self.poly_overflow = wp.zeros(1, dtype=int, device=dev)
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
        self.broadphase = BroadPhase(
            n, dev, self.skin, capacity=max(1024, 5 * n), rotation_term=False, body_box=(lower, upper)
        )
        self.poly_capacity = model.shapes.default_poly_capacity
        self._kernels()
        self._graph = None
        self._capacity = 0
        self._host_build(history=False)

    # -- buffers --------------------------------------------------------------------------------

    def _kernels(self):
        shapes = self.model.shapes
        self.kernels = make_contact_kernels(self.model.law, self.model.friction, self.poly_capacity, shapes.max_faces)

    def _allocate_pairs(self, capacity):
        dev = self.device
        self._capacity = capacity
        springs = capacity if self.model.friction else 1
        self.pair_xi = wp.zeros(springs, dtype=wp.vec3, device=dev)
        self.pair_turn = wp.zeros(capacity, dtype=float, device=dev)
        self.pair_force = wp.zeros(capacity, dtype=wp.vec3, device=dev)
        self.pair_torque_a = wp.zeros(capacity, dtype=wp.vec3, device=dev)
        self.pair_dissipated = wp.zeros(capacity, dtype=float, device=dev)
        # History of the previous pair list, for the turning volumes and springs across a rebuild.
        self.old_key = wp.zeros(capacity, dtype=wp.int64, device=dev)
        self.old_xi = wp.zeros(springs, dtype=wp.vec3, device=dev)
        self.old_turn = wp.zeros(capacity, dtype=float, device=dev)
        self.old_count = wp.zeros(1, dtype=int, device=dev)
        # Pairs ordered by their B body (radix sort needs twice the room).
        self._keys_b = wp.zeros(2 * capacity, dtype=wp.int64, device=dev)
        self._by_b = wp.zeros(2 * capacity, dtype=int, device=dev)
        self.pair_by_b = self._by_b[:capacity]
        self.body_pairs_a = wp.zeros(self.num_bodies, dtype=wp.vec2i, device=dev)
        self.body_pairs_b = wp.zeros(self.num_bodies, dtype=wp.vec2i, device=dev)
        self._diag = None
        self._graph = None

    def _save_history(self):
        bp = self.broadphase
        wp.copy(self.old_key, bp.pair_key, count=self._capacity)
        wp.copy(self.old_turn, self.pair_turn)
        if self.model.friction:
            wp.copy(self.old_xi, self.pair_xi)
        wp.copy(self.old_count, bp.pair_count)

    def _after_rebuild(self):
        """Turning volumes and friction springs carried over by pair key; per-body ranges for the gather."""
        bp = self.broadphase
        dev = self.device
        cap = self._capacity
        wp.launch(
            remap_history_kernel,
            dim=cap,
            inputs=[
                self.old_key,
                self.old_count,
                self.old_xi,
                self.old_turn,
                bp.pair_key,
                bp.pair_count,
                int(self.model.friction),
            ],
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

    def _host_build(self, history=True):
        bp = self.broadphase
        m = self.model
        if history and self._capacity:
            self._save_history()
        elif self._capacity:
            self.old_count.zero_()
        bp.build(self.body_q, m.body_radius, m.body_flags)
        if bp.capacity != self._capacity:
            old = (self.old_key, self.old_xi, self.old_turn, self.old_count) if self._capacity else None
            self._allocate_pairs(bp.capacity)
            if old is not None and history:
                n_old = min(len(old[0]), bp.capacity)
                wp.copy(self.old_key, old[0], count=n_old)
                if self.model.friction:
                    wp.copy(self.old_xi, old[1], count=n_old)
                wp.copy(self.old_turn, old[2], count=n_old)
                wp.copy(self.old_count, old[3])
        self._after_rebuild()

    def _device_rebuild(self):
        self._save_history()
        m = self.model
        self.broadphase.rebuild_on_device(self.body_q, m.body_radius, m.body_flags)
        self._after_rebuild()

    # -- one step ------------------------------------------------------------------------------

    def _launch_contacts(self, kernels, diag):
        """The pair and gather kernels: the step variant, or the diagnostics one into ``diag``."""
        m = self.model
        s = m.shapes
        bp = self.broadphase
        dev = self.device
        materials = [m.num_materials, m.material_k, m.material_e, m.material_mu, m.material_kt, m.law_m, self.dt]
        d = diag if diag is not None else self._placeholders()
        wp.launch(
            kernels.pair_contact_kernel,
            dim=self._capacity,
            inputs=[
                *s.kernel_args(),
                m.body_shape,
                m.body_material,
                m.body_inv_mass,
                *materials,
                self.body_q,
                self.body_v,
                self.body_w,
                bp.pair_a,
                bp.pair_b,
                bp.pair_count,
                self.pair_xi,
                self.pair_turn,
            ],
            outputs=[
                self.pair_force,
                self.pair_torque_a,
                self.pair_dissipated,
                self.poly_overflow,
                d["pair_volume"],
                d["pair_energy"],
                d["pair_normal"],
                d["pair_point"],
                d["pair_fn"],
                d["pair_ft"],
            ],
            device=dev,
            block_dim=NARROWPHASE_BLOCK_DIM,
        )
        wp.launch(
            kernels.gather_kernel,
            dim=self.num_bodies,
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
                self.body_q,
                self.body_v,
                self.body_w,
                bp.pair_a,
                bp.pair_b,
                self.body_pairs_a,
                self.body_pairs_b,
                self.pair_by_b,
                self.pair_force,
                self.pair_torque_a,
                self.pair_dissipated,
                self.plane_xi,
                self.plane_turn,
                self.body_dissipated,
            ],
            outputs=[
                self.body_f,
                self.body_t,
                d["plane_volume"],
                d["plane_energy"],
                d["plane_fn"],
                d["plane_point"],
                d["plane_ft"],
            ],
            device=dev,
        )

    def _placeholders(self):
        if getattr(self, "_empty", None) is None:
            dev = self.device
            self._empty = {
                "pair_volume": wp.zeros(1, dtype=float, device=dev),
                "pair_energy": wp.zeros(1, dtype=float, device=dev),
                "pair_normal": wp.zeros(1, dtype=wp.vec3, device=dev),
                "pair_point": wp.zeros(1, dtype=wp.vec3, device=dev),
                "pair_fn": wp.zeros(1, dtype=float, device=dev),
                "pair_ft": wp.zeros(1, dtype=wp.vec3, device=dev),
                "plane_volume": wp.zeros((1, 1), dtype=float, device=dev),
                "plane_energy": wp.zeros((1, 1), dtype=float, device=dev),
                "plane_fn": wp.zeros((1, 1), dtype=float, device=dev),
                "plane_point": wp.zeros((1, 1), dtype=wp.vec3, device=dev),
                "plane_ft": wp.zeros((1, 1), dtype=wp.vec3, device=dev),
            }
        return self._empty

    def _diagnostics(self):
        """Runs the diagnostics variant at the current state; returns its host arrays.

        energy() and contacts() at the same state share one run (the cache is dropped whenever
        the state changes: a step, a restore)."""
        if getattr(self, "_diag_cache", None) is not None:
            return self._diag_cache
        dev = self.device
        cap = self._capacity
        n = self.num_bodies
        p = max(self.model.num_planes, 1)
        if self._diag is None:
            self._diag = {
                "pair_volume": wp.zeros(cap, dtype=float, device=dev),
                "pair_energy": wp.zeros(cap, dtype=float, device=dev),
                "pair_normal": wp.zeros(cap, dtype=wp.vec3, device=dev),
                "pair_point": wp.zeros(cap, dtype=wp.vec3, device=dev),
                "pair_fn": wp.zeros(cap, dtype=float, device=dev),
                "pair_ft": wp.zeros(cap, dtype=wp.vec3, device=dev),
                "plane_volume": wp.zeros((n, p), dtype=float, device=dev),
                "plane_energy": wp.zeros((n, p), dtype=float, device=dev),
                "plane_fn": wp.zeros((n, p), dtype=float, device=dev),
                "plane_point": wp.zeros((n, p), dtype=wp.vec3, device=dev),
                "plane_ft": wp.zeros((n, p), dtype=wp.vec3, device=dev),
            }
        m = self.model
        kernels = make_contact_kernels(m.law, m.friction, self.poly_capacity, m.shapes.max_faces, diagnostics=True)
        self._launch_contacts(kernels, self._diag)
        count = int(self.broadphase.pair_count.numpy()[0])
        out = {k: v.numpy() for k, v in self._diag.items()}
        for k in ("pair_volume", "pair_energy", "pair_normal", "pair_point", "pair_fn", "pair_ft"):
            out[k] = out[k][:count]
        self._diag_cache = out
        return out

    def _contacts_and_integrate(self):
        m = self.model
        dev = self.device
        self._launch_contacts(self.kernels, None)
        integrate_bodies(
            m.body_inv_mass,
            m.body_inertia,
            m.body_flags,
            m.gravity,
            self.body_q,
            self.body_v,
            self.body_w,
            self.body_f,
            self.body_t,
            self.dt,
            device=dev,
            body_pivot=m.body_pivot,
        )
        wp.launch(advance_step_kernel, dim=1, inputs=[self.step_count], device=dev)
        wp.launch(
            check_state_kernel,
            dim=self.num_bodies,
            inputs=[m.body_flags, self.step_count, self.body_q, self.body_v, self.body_w],
            outputs=[self.bad_step],
            device=dev,
        )

    def _step_device(self):
        m = self.model
        bp = self.broadphase
        bp.needs_rebuild(self.body_q, m.body_radius, m.body_flags)
        wp.capture_if(bp.rebuild_flag, on_true=self._device_rebuild)
        self._contacts_and_integrate()

    def _step_host(self):
        m = self.model
        flag = self.broadphase.needs_rebuild(self.body_q, m.body_radius, m.body_flags)
        if int(flag.numpy()[0]):
            self._host_build()
        self._contacts_and_integrate()

    # -- public --------------------------------------------------------------------------------

    def _backup(self):
        """Copies the state at the start of a chunk into buffers kept between chunks."""
        bp = self.broadphase
        live = {
            "q": self.body_q,
            "v": self.body_v,
            "w": self.body_w,
            "diss": self.body_dissipated,
            "plane_xi": self.plane_xi,
            "plane_turn": self.plane_turn,
            "xi": self.pair_xi,
            "turn": self.pair_turn,
            "key": bp.pair_key,
            "count": bp.pair_count,
            "step": self.step_count,
        }
        saved = getattr(self, "_saved", None)
        if saved is None or any(saved[k].shape != a.shape for k, a in live.items()):
            self._saved = {k: wp.clone(a) for k, a in live.items()}
            return
        for k, a in live.items():
            wp.copy(saved[k], a)

    def _restore(self):
        self._diag_cache = None
        s = self._saved
        wp.copy(self.body_q, s["q"])
        wp.copy(self.body_v, s["v"])
        wp.copy(self.body_w, s["w"])
        wp.copy(self.body_dissipated, s["diss"])
        wp.copy(self.plane_xi, s["plane_xi"])
        wp.copy(self.plane_turn, s["plane_turn"])
        wp.copy(self.step_count, s["step"])
        # A fresh host build from the restored poses; the pair histories come back through their keys.
        bp = self.broadphase
        bp.build(self.body_q, self.model.body_radius, self.model.body_flags)
        if bp.capacity != self._capacity:
            self._allocate_pairs(bp.capacity)
        n_old = min(int(s["count"].numpy()[0]), len(s["key"]), self._capacity)
        wp.copy(self.old_key, s["key"], count=n_old)
        wp.copy(self.old_turn, s["turn"], count=n_old)
        if self.model.friction:
            wp.copy(self.old_xi, s["xi"], count=n_old)
        self.old_count.fill_(n_old)
        self._after_rebuild()

    def _run_chunk(self, steps):
        self._diag_cache = None
        if self.use_graph:
            if self._graph is None:
                with wp.ScopedCapture(device=self.device) as capture:
                    self._step_device()
                self._graph = capture.graph
            for _ in range(steps):
                wp.capture_launch(self._graph)
        else:
            for _ in range(steps):
                self._step_host()

    def step(self, n=1):
        """Advance ``n`` steps of length ``dt``."""
        n = int(n)
        if n < 0:
            raise ValueError(f"step count must be >= 0, got {n}")
        done = 0
        while done < n:
            chunk = min(CHUNK_STEPS, n - done)
            self._backup()
            self._run_chunk(chunk)
            redo = False
            if int(self.poly_overflow.numpy()[0]):
                self.poly_overflow.zero_()
                self.poly_capacity = min(2 * self.poly_capacity, self.model.shapes.max_poly_bound)
                self._kernels()
                self._graph = None
                redo = True
            if self.use_graph and self.broadphase.check_host_build_needed():
                redo = True
            if redo:
                self._restore()
                continue
            bad = int(self.bad_step.numpy()[0])
            if bad != 2**31 - 1:
                self._report_nonfinite(bad)
            done += chunk
            self.steps_done += chunk
            self.time += chunk * self.dt

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

    def state(self):
        """Current state as numpy arrays (world frame, body frame = centroid and principal axes).

        Returns a dict: ``body_position`` (N,3) [m], ``body_orientation`` (N,4) quaternion xyzw,
        ``body_velocity`` (N,3) [m/s], ``body_angular_velocity`` (N,3) world axes [rad/s].
        """
        q = self.body_q.numpy()
        return {
            "body_position": q[:, :3].astype(np.float64),
            "body_orientation": q[:, 3:].astype(np.float64),
            "body_velocity": self.body_v.numpy().astype(np.float64),
            "body_angular_velocity": self.body_w.numpy().astype(np.float64),
        }

    def energy(self):
        """Energies [J]: ``kinetic``, ``contact`` (W(V) summed over contacts, plus the friction
        springs), ``gravity`` (-sum m g.x over free bodies), ``dissipated`` (by damping and friction
        so far), and ``total`` (their sum, constant up to the integrator's error)."""
        m = self.model
        lin, ang = kinetic_energy(
            m.body_inv_mass, m.body_inertia, m.body_flags, self.body_q, self.body_v, self.body_w, device=self.device
        )
        d = self._diagnostics()
        contact = float(np.sum(d["pair_energy"], dtype=np.float64))
        if m.num_planes:
            contact += float(np.sum(d["plane_energy"], dtype=np.float64))
        free = m.body_flags_np == 0
        x = self.body_q.numpy()[:, :3].astype(np.float64)
        grav = -float(np.sum(m.body_mass[free].astype(np.float64) * (x[free] @ m.gravity)))
        kin = float(np.sum(lin.numpy(), dtype=np.float64) + np.sum(ang.numpy(), dtype=np.float64))
        diss = float(np.sum(self.body_dissipated.numpy(), dtype=np.float64))
        return {
            "kinetic": kin,
            "contact": contact,
            "gravity": grav,
            "dissipated": diss,
            "total": kin + contact + grav + diss,
        }

    def contacts(self):
        """Current contacts (overlap volume > 0) as numpy arrays, one row per contact.

        ``body_a``, ``body_b`` (int; ``body_b = -1 - p`` for wall plane p), ``normal`` (N,3) from A
        into B, ``point`` (N,3) [m], ``normal_force`` (N,) [N], ``tangential_force`` (N,3) on A [N],
        ``volume`` (N,) [m^3]. Computed at the current state (after the last step).
        """
        bp = self.broadphase
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
        }
        if self.model.num_planes:
            pv = d["plane_volume"]
            body, plane = np.nonzero(pv > 0.0)
            normals = self.model.plane_normal.numpy()
            out["body_a"] = np.concatenate([out["body_a"], body])
            out["body_b"] = np.concatenate([out["body_b"], -1 - plane])
            out["normal"] = np.concatenate([out["normal"], -normals[plane].astype(np.float64)])
            out["point"] = np.concatenate([out["point"], d["plane_point"][body, plane].astype(np.float64)])
            out["normal_force"] = np.concatenate([out["normal_force"], d["plane_fn"][body, plane].astype(np.float64)])
            out["tangential_force"] = np.concatenate(
                [out["tangential_force"], d["plane_ft"][body, plane].astype(np.float64)]
            )
            out["volume"] = np.concatenate([out["volume"], pv[body, plane].astype(np.float64)])
        return out
