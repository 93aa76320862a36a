"""Model: the static device arrays of a simulation, built once from a validated Scene.

What changes during a run is not here: see :class:`~polydem.state.State` (bodies, wall contacts) and
:class:`~polydem.contacts.Contacts` (the pair list and its history).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from polydem.kernels.motion import Motions
from polydem.kernels.precision import Precision, numpy_dtype, scalars
from polydem.kernels.response import fill_damping_factors
from polydem.kernels.structs import (
    body_model_struct,
    filled,
    materials_struct,
    mesh_walls_struct,
    planes_struct,
)
from polydem.meshmerge import join_flat_cells
from polydem.quaternions import quat_to_matrix
from polydem.run_settings import RunSettings, run_settings
from polydem.scene import (  # noqa: F401  (re-exported: the time step is computed host-side in polydem.scene)
    MAX_DT_FRACTION,
    REFERENCE_DEPTH,
    STEPS_PER_CONTACT_PERIOD,
    SceneError,
    reference_stiffness,
)
from polydem.scene.bodies import BodyKind
from polydem.scene.motions import KINDS
from polydem.scene.walls import mesh_wall_memo
from polydem.shapeset import ShapeSet
from polydem.state import State

if TYPE_CHECKING:
    from polydem.scene import Scene
    from polydem.shapes import ConvexShape


class Model:
    """Static device arrays of a simulation, from a :class:`~polydem.Scene`.

    The scene's ``precision`` (:mod:`polydem.kernels.precision`) sets two scalars: S, that of the
    bodies (inverse mass, inertia, pivot) and walls (normal, offset), and C, that of the shapes and
    the material table. "float32": S = C = float32; "mixed": S = float64, C = float32;
    "float64": S = C = float64. The bounding radii feed the broad phase and stay float32.

    A model of some of the scene's bodies (``bodies``, their indices) holds their rows alone, with the
    settings of the whole scene's run (``settings``): a rank of a decomposed run steps its bodies so.

    Args:
        scene: the :class:`~polydem.Scene`; the model keeps none of it but the cells of its mesh walls.
        device: Warp device.
        validate: run ``scene.validate()`` first.
        settings: the :class:`~polydem.run_settings.RunSettings` of the run (default: the scene's,
            :func:`~polydem.run_settings.run_settings`).
        bodies: (N,) indices of the scene's bodies to hold, in the order to hold them (default: all).

    Attributes:
        settings: the :class:`~polydem.run_settings.RunSettings` (time step, friction springs, skin, ...).
        body_index: (N,) int64 index in the scene of each body of the model.
        precision: the :class:`~polydem.kernels.precision.Precision`; scalar, contact_scalar: the Warp
            scalars S, C.
        shapes: :class:`~polydem.shapeset.ShapeSet` of the scene's shapes (``shape_*``, ``face_*``).
        body_shape: (N,) int32 shape index.
        body_material: (N,) int32 material index.
        body_flags: (N,) int32 :class:`~polydem.scene.bodies.BodyKind` (0 free, 1 fixed, 2 kinematic);
            body_flags_np, body_shape_np: the flags and shape indices on the host.
        body_mass: (N,) mass [kg] (numpy, host; float32 in "float32", else float64).
        body_inv_mass: (N,) S inverse mass [1/kg], 0 for fixed and kinematic bodies.
        body_inertia: (N,) S vec3 principal moments of inertia [kg m^2].
        body_radius: (N,) float32 bounding radius about the centre [m].
        body_pivot: (N,) S vec3 point a kinematic body turns about [m] (NaN: none), or None when no
            body has one.
        material_k, material_e, material_mu, material_kt: (M*M,) C mixed pair properties,
            row-major by (material of A, material of B): stiffness (units of the law),
            restitution, friction coefficient, tangential stiffness [N/m].
        material_damping: (M*M,) C the tangential dashpot's factor of each pair's restitution (twice its damping
            ratio, kernels/response.py ``make_damping``), computed on the device [1].
        law: "linear", "hertz" or "power"; law_m: its exponent m (W = k V^m / m).
        plane_normal: (P,) S vec3 outward unit normals of the walls; plane_offset: (P,) S [m]
            (the wall is n.x <= offset); plane_material: (P,) int32.
        num_mesh_walls: M, the triangle-mesh walls (:mod:`polydem.meshwall`); num_walls: P + M, the
            columns of the wall-contact arrays of the state (planes first).
        mesh_cells: M :class:`~polydem.meshwall.MeshCells`, each wall's surface and cells in its frame (those of
            flat patches joined where they are convex together, :func:`~polydem.meshmerge.join_flat_cells`,
            unless ``join_flat_cells`` is False: one cell per triangle).
        mesh_bvh: (M,) uint64 ids of a ``wp.Bvh`` per wall over its cells' bounds (in ``mesh_bvhs``).
        mesh_cell_start: (M+1,) int32 first cell of each wall; cell_shape: (C,) int32 the cell's
            shape in ``shapes`` (after the scene's shapes); cell_center: (C,) S vec3 the cell's
            frame origin in its wall's frame [m]; cell_front: (C,) S vec4 the plane (normal,
            offset [m]) of the triangle a cell lies behind, zero for the cells of concave edges
            and corners (for the reported depth).
        wall_material: (P + M,) int32 material of each wall column (planes first).
        mesh_material: (M,) int32; mesh_v: (M,) S vec3 velocity of the wall's origin [m/s];
            mesh_w: (M,) S vec3 angular velocity [rad/s]; mesh_q0: (M, 7) initial poses (pivot and
            identity rotation).
        grain_shapes: the ShapeSet of the scene's shapes alone (``shapes`` without the cells).
        bodies, materials, planes, meshes: the ``body_*`` arrays (with ``has_pivot``), the material table
            (with ``num_materials`` and ``law_m``), the ``plane_*`` arrays and the mesh walls' arrays (with
            ``num_planes``, the first mesh column; None without mesh walls) in the ``wp.struct`` the kernels
            take (:mod:`polydem.kernels.structs`), built once here.
        gravity: (3,) [m/s^2]; dt: time step [s]; dt_recommended, dt_limit: the recommended and the
            largest accurate step [s] (from ``settings``); toe_dt: the step whose resolved toe the hertz and
            power (m < 2) laws take [s] (:func:`polydem.scene.checks.toe_step`).
    """

    def __init__(
        self,
        scene: Scene,
        device: wp.DeviceLike = None,
        validate: bool = True,
        *,
        settings: RunSettings | None = None,
        bodies: np.ndarray | None = None,
        join_flat_cells: bool = True,
    ) -> None:
        if not isinstance(join_flat_cells, bool):
            raise TypeError(f"join_flat_cells must be True or False, got {join_flat_cells!r}")
        if validate:
            scene.validate()
        self.settings = run_settings(scene) if settings is None else settings
        self.device = wp.get_device(device)
        dev = self.device
        names = scene.shape_names
        shape_list = [scene.shapes[n] for n in names]
        self.precision = Precision(scene.precision)
        self.scalar, self.contact_scalar = scalars(self.precision)
        s_np, c_np = numpy_dtype(self.scalar), numpy_dtype(self.contact_scalar)
        vec3s = wp.types.vector(3, self.scalar)
        rows = {name: v.view() for name, v in scene.body_arrays().items()}
        if bodies is None:
            self.body_index = np.arange(scene.num_bodies, dtype=np.int64)
        else:
            self.body_index = np.asarray(bodies, dtype=np.int64)
            index = self.body_index
            if index.ndim != 1 or not np.all((index >= 0) & (index < scene.num_bodies)):
                raise ValueError(f"bodies must be a 1-D array of the scene's body indices, 0 to {scene.num_bodies - 1}")
            # Copies of these bodies' rows alone: a rank's model costs the host what its own bodies do.
            rows = {name: np.ascontiguousarray(v[index]) for name, v in rows.items()}
        for v in rows.values():
            v.setflags(write=False)  # the scene's own arrays where the model has every body
        self.num_bodies = n = len(self.body_index)
        self._mesh_walls(scene, shape_list, dev, s_np, join_flat_cells)
        # Every wall column's material, the planes then the mesh walls (the damping loads, kernels/forces.py).
        mat_of = {name: i for i, name in enumerate(scene.material_names)}
        wall_mats = [mat_of[p.material] for p in scene.planes] + [mat_of[w.material] for w in scene.mesh_walls]
        self.wall_material = wp.array(np.array(wall_mats, dtype=np.int32), dtype=int, device=dev)
        self.shapes = ShapeSet(shape_list, device=dev, precision=np.dtype(c_np).name, packed=self.mesh_cells)
        self.grain_shapes = (
            ShapeSet(shape_list, device=dev, precision=np.dtype(c_np).name) if self.mesh_cells else self.shapes
        )
        self.num_materials = len(scene.material_names)

        body_shape = np.asarray(rows["shape"], dtype=np.int32)
        body_material = np.asarray(rows["material"], dtype=np.int32)
        kind = np.asarray(rows["kind"], dtype=np.int32)
        # Scene.body_mass() and body_inertia() over these bodies alone (the same products, so the same bits).
        volume = np.array([s.volume for s in scene.shapes.values()])
        density = np.array([m.density for m in scene.materials.values()])
        shape_inertia = np.array([s.inertia for s in scene.shapes.values()]).reshape(-1, 3)
        mass = np.asarray(density[body_material] * volume[body_shape], dtype=np.float64)
        inertia = np.asarray(density[body_material][:, None] * shape_inertia[body_shape], dtype=np.float64)
        radius = np.array([s.radius for s in shape_list])[body_shape]
        free = kind == BodyKind.FREE
        self.body_mass = mass.astype(s_np)
        self.body_flags_np = kind
        self.body_shape_np = body_shape
        inv_mass = np.where(free, 1.0 / np.maximum(mass, 1e-300), 0.0)

        table = scene.pair_table()
        self.law = table["law"]
        self.law_m = float(table["exponent"])
        k = np.asarray(table["k"], dtype=np.float64)

        kt = self.settings.tangential_stiffness
        self.dt_recommended = self.settings.dt_recommended
        self.toe_dt = self.settings.dt_toe
        self.dt_limit = self.settings.dt_limit
        self.dt = self.settings.dt
        self.gravity = np.asarray(scene.gravity, dtype=np.float64)
        self.friction = bool(np.any(np.asarray(table["friction"]) > 0.0))

        def arr(a: np.ndarray, dtype: type) -> wp.array:
            return wp.array(a, dtype=dtype, device=dev)

        self.body_shape = arr(body_shape, int)
        self.body_material = arr(body_material, int)
        self.body_flags = arr(kind, int)
        self.body_inv_mass = arr(inv_mass.astype(s_np), self.scalar)
        self.body_inertia = arr(inertia.astype(s_np), vec3s)
        self.body_radius = arr(radius.astype(np.float32), float)
        pivot = np.asarray(rows["pivot"], dtype=np.float64)
        # Only kinematic bodies turning about a pivot (drum parts) need the array.
        self.body_pivot = arr(pivot.astype(s_np), vec3s) if np.isfinite(pivot).any() else None
        c = self.contact_scalar
        self.material_k = arr(k.astype(c_np).ravel(), c)
        self.material_e = arr(np.asarray(table["restitution"], dtype=c_np).ravel(), c)
        self.material_mu = arr(np.asarray(table["friction"], dtype=c_np).ravel(), c)
        self.material_kt = arr(kt.astype(c_np).ravel(), c)
        # The dashpot's factor of each pair's restitution, on the device by the kernels' own expression.
        self.material_damping = wp.empty_like(self.material_e)
        fill_damping_factors(self.material_e, self.material_damping)
        self.materials = filled(
            materials_struct(c),
            count=self.num_materials,
            law_m=self.law_m,
            toe_dt=self.toe_dt,
            k=self.material_k,
            e=self.material_e,
            mu=self.material_mu,
            kt=self.material_kt,
            damping=self.material_damping,
        )
        self.bodies = filled(
            body_model_struct(self.scalar),
            shape=self.body_shape,
            material=self.body_material,
            flags=self.body_flags,
            inv_mass=self.body_inv_mass,
            inertia=self.body_inertia,
            radius=self.body_radius,
            pivot=self.body_pivot,
            has_pivot=int(self.body_pivot is not None),
        )

        planes = scene.planes
        mat_index = {name: i for i, name in enumerate(scene.material_names)}
        normals = np.array([p.normal for p in planes], dtype=np.float64).reshape(-1, 3)
        offsets = np.array([np.dot(p.normal, p.point) for p in planes], dtype=np.float64)
        self.num_planes = len(planes)
        self.plane_normal = arr(normals.astype(s_np), vec3s)
        self.plane_offset = arr(offsets.astype(s_np), self.scalar)
        self.plane_material = arr(np.array([mat_index[p.material] for p in planes], dtype=np.int32), int)
        self.plane_v = wp.zeros(len(planes), dtype=vec3s, device=dev)
        plane_arrays = {"normal": self.plane_normal, "offset": self.plane_offset, "material": self.plane_material}
        self.planes = filled(planes_struct(self.scalar), **plane_arrays, v=self.plane_v)
        # The initial state's rows (state()): views of the scene's arrays, or the copies of the slice.
        self._initial = {k: rows[k] for k in ("position", "orientation", "velocity", "angular_velocity")}
        self._motions(scene, dev)
        self.bytes = sum(
            a.capacity
            for a in (
                self.body_shape,
                self.body_material,
                self.body_flags,
                self.body_inv_mass,
                self.body_inertia,
                self.body_radius,
            )
        )
        if n == 0:
            raise SceneError("the scene has no bodies", key="bodies")

    def _mesh_walls(
        self, scene: Scene, shape_list: list[ConvexShape], dev: wp.Device, s_np: type, join_flat: bool
    ) -> None:
        walls = scene.mesh_walls
        self.num_mesh_walls = len(walls)
        self.num_walls = len(scene.planes) + len(walls)
        self.mesh_cells = []
        vec3s = wp.types.vector(3, self.scalar)
        self.mesh_moves = False
        self.meshes = None
        if not walls:
            self.mesh_bvhs = []
            return
        mat_index = {name: i for i, name in enumerate(scene.material_names)}
        starts, centers, fronts, lowers, uppers = [0], [], [], [], []
        for wall, thickness in zip(walls, self.settings.mesh_wall_thickness, strict=True):
            # The scene's cells (its checks built them at validation, at this thickness): one build.
            mc = scene.mesh_wall_cells(wall, thickness)
            if join_flat:
                memo = mesh_wall_memo(scene, wall, thickness)
                if "joined" not in memo:
                    memo["joined"] = join_flat_cells(mc)
                mc = memo["joined"]
            self.mesh_cells.append(mc)
            starts.append(starts[-1] + mc.num_cells)
            centers.append(mc.cell_center)
            fronts.append(mc.cell_front)
            # float32 bounds, grown by their rounding, so that the query never misses a cell.
            size = np.abs(mc.lower).max() + np.abs(mc.upper).max()
            lowers.append(mc.lower - 1e-6 * size)
            uppers.append(mc.upper + 1e-6 * size)

        def arr(a: np.ndarray, dtype: type) -> wp.array:
            return wp.array(a, dtype=dtype, device=dev)

        self.mesh_bvhs = [
            wp.Bvh(arr(lo.astype(np.float32), wp.vec3), arr(hi.astype(np.float32), wp.vec3))
            for lo, hi in zip(lowers, uppers, strict=True)
        ]
        self.mesh_bvh = arr(np.array([b.id for b in self.mesh_bvhs], dtype=np.uint64), wp.uint64)
        self.mesh_cell_start = arr(np.array(starts, dtype=np.int32), int)
        self.cell_shape = arr(len(shape_list) + np.arange(starts[-1], dtype=np.int32), int)
        self.cell_center = arr(np.concatenate(centers).astype(s_np), vec3s)
        self.cell_front = arr(np.concatenate(fronts).astype(s_np), wp.types.vector(4, self.scalar))
        self.mesh_material = arr(np.array([mat_index[w.material] for w in walls], dtype=np.int32), int)
        self.mesh_v = arr(np.array([w.velocity for w in walls], dtype=s_np), vec3s)
        self.mesh_w = arr(np.array([w.angular_velocity for w in walls], dtype=s_np), vec3s)
        self.mesh_moves = any(w.moving for w in walls)
        self.meshes = filled(
            mesh_walls_struct(self.scalar),
            bvh=self.mesh_bvh,
            cell_start=self.mesh_cell_start,
            material=self.mesh_material,
            v=self.mesh_v,
            w=self.mesh_w,
            cell_shape=self.cell_shape,
            cell_center=self.cell_center,
            cell_front=self.cell_front,
            first_column=len(scene.planes),
        )
        self.mesh_q0 = np.array([[*w.pivot, 0.0, 0.0, 0.0, 1.0] for w in walls], dtype=np.float64)

    def _motions(self, scene: Scene, dev: wp.Device) -> None:
        """The container motions (:mod:`polydem.scene.motions`, kernels/motion.py), in ``motions`` (a
        :data:`~polydem.kernels.motion.Motions`, None without motions): per motion its axis, amplitude [m],
        angular frequency [rad/s], start [s], period [s] and count; per body of the model the index of the
        motion it follows (-1: none, also in ``body_motion``) and its position at rest [m], as the state's poses
        hold it (``body_rest``); the same for the plane walls (offset at rest) and mesh walls (translation at
        rest). ``has_motions``: some body follows a motion; ``has_wall_motions``: some plane or mesh wall does."""
        names = list(scene.motions)
        self.motions = None
        which = {name: k for k, name in enumerate(names)}
        motion = _body_motions(scene.body_motion, which, self.body_index)
        self.has_motions = bool((motion >= 0).any())
        plane_motion = np.array([which.get(p.motion, -1) for p in scene.planes], dtype=np.int32)
        mesh_motion = np.array([which.get(w.motion, -1) for w in scene.mesh_walls], dtype=np.int32)
        self.has_wall_motions = bool((plane_motion >= 0).any() or (mesh_motion >= 0).any())
        self.motion_names = names
        self.has_measured_motions = False
        # The motions the driven bodies follow, each once, in the order of their first body.
        servo = any(scene.motions[name].kind == "servo" for name in dict.fromkeys(scene.body_motion.values()))
        if servo and len(self.body_index) != scene.num_bodies:
            # Refused by every rank alike, whether it holds the servo's wall or not.
            raise SceneError(
                "a servo motion needs the force of every grain on its wall in one process: run the scene undivided "
                "(a decomposed run holds each rank's share of the grains)",
                "motions",
            )
        if not (self.has_motions or self.has_wall_motions):
            return
        ms = [scene.motions[name] for name in names]

        def f64(values: list[float]) -> wp.array:
            return wp.array(np.array(values, dtype=np.float64), dtype=wp.float64, device=dev)

        self.body_motion = wp.array(motion, dtype=int, device=dev)
        rest = np.asarray(self._initial["position"], dtype=np.float64)
        self.body_rest = wp.array(rest, dtype=wp.vec3d, device=dev)
        self.motions = filled(
            Motions,
            axis=wp.array(np.array([m.axis for m in ms], dtype=np.float64), dtype=wp.vec3d, device=dev),
            amplitude=f64([m.amplitude_in(scene.gravity) for m in ms]),
            omega=f64([m.omega for m in ms]),
            start=f64([m.start for m in ms]),
            period=f64([m.cycle_period() for m in ms]),
            count=wp.array(np.array([m.count for m in ms], dtype=np.int32), dtype=int, device=dev),
            kind=wp.array(np.array([KINDS.index(m.kind) for m in ms], dtype=np.int32), dtype=int, device=dev),
            speed=f64([m.speed if m.kind == "ramp" else (m.max_speed if m.kind == "servo" else 0.0) for m in ms]),
            duration=f64([m.ramp_duration() for m in ms]),
            body_motion=self.body_motion,
            body_rest=self.body_rest,
            plane_motion=wp.array(plane_motion, dtype=int, device=dev),
            plane_rest=wp.array(np.array([np.dot(p.normal, p.point) for p in scene.planes]), dtype=wp.float64,
                                device=dev),
            mesh_motion=wp.array(mesh_motion, dtype=int, device=dev),
            mesh_rest=wp.array(np.array([w.pivot for w in scene.mesh_walls]).reshape(-1, 3), dtype=wp.vec3d,
                               device=dev),
        )  # fmt: skip
        self._measured_motions(scene, ms, motion, dev)

    def _measured_motions(self, scene: Scene, ms: list, motion: np.ndarray, dev: wp.Device) -> None:
        """The ramps and servos (kernels/motion.py, ``launch_measure_motions``), in ``motions``: per motion its
        target force [N] and gain [m/(N s)]; the
        driven bodies of each (``rows``, also in ``measured_rows``), in ``row_start`` ranges; ``motion_area``
        (K,) host [m^2] each motion's bodies' area across its axis (what a servo's stress acts on, where it
        gives none)."""
        kinds = np.array([KINDS.index(m.kind) for m in ms], dtype=np.int32)
        measured = np.flatnonzero(kinds[np.maximum(motion, 0)] * (motion >= 0))
        self.motion_kind_np = kinds
        self.has_measured_motions = bool(len(measured))
        if not self.has_measured_motions:
            return
        # Rows ordered by motion, then body: the force sums run in this fixed order.
        order = measured[np.lexsort((measured, motion[measured]))]
        starts = np.searchsorted(motion[order], np.arange(len(ms) + 1)).astype(np.int32)
        orientation = np.asarray(self._initial["orientation"], dtype=np.float64)
        shapes = [scene.shapes[name] for name in scene.shape_names]
        area = np.zeros(len(ms))
        for k, m in enumerate(ms):
            for i in order[starts[k] : starts[k + 1]]:
                area[k] += _area_across(shapes[self.body_shape_np[i]], orientation[i], np.asarray(m.axis))
        self.motion_area = area
        target = [m.target_force(area[k]) if m.kind == "servo" else 0.0 for k, m in enumerate(ms)]

        def f64(values: list[float]) -> wp.array:
            return wp.array(np.array(values, dtype=np.float64), dtype=wp.float64, device=dev)

        self.measured_rows = wp.array(order.astype(np.int32), dtype=int, device=dev)
        measured = {
            "target": f64(target),
            "gain": f64([m.gain or 0.0 for m in ms]),
            "rows": self.measured_rows,
            "row_start": wp.array(starts, dtype=int, device=dev),
        }
        for name, value in measured.items():
            setattr(self.motions, name, value)

    def state(self) -> State:
        """The initial :class:`~polydem.state.State` of the model's bodies: their poses and velocities in the
        scene, no contact history."""
        initial = self._initial
        state = State(
            self.num_bodies, self.num_walls, self.friction, self.device, self.precision, num_meshes=self.num_mesh_walls
        )
        if self.has_measured_motions:
            state.motion_travel = wp.zeros(len(self.motion_names), dtype=wp.vec3d, device=self.device)
        s_np = numpy_dtype(self.scalar)
        state.body_q.assign(np.hstack([initial["position"], initial["orientation"]]).astype(s_np))
        state.body_v.assign(np.asarray(initial["velocity"], dtype=s_np))
        state.body_w.assign(np.asarray(initial["angular_velocity"], dtype=s_np))
        if self.num_mesh_walls:
            state.mesh_q.assign(self.mesh_q0.astype(s_np))
        return state


def _body_motions(body_motion: dict, which: dict, body_index: np.ndarray) -> np.ndarray:
    """(N,) int32 index in ``which`` (motion name -> index) of the motion each body of ``body_index`` follows
    (``body_motion``: scene body index -> motion name, the driven bodies alone), -1 where none: a lookup of
    the driven bodies among the model's, without a pass in Python over the model's bodies."""
    motion = np.full(len(body_index), -1, dtype=np.int32)
    if not body_motion:
        return motion
    driven = np.fromiter(body_motion.keys(), dtype=np.int64, count=len(body_motion))
    code = np.fromiter((which.get(name, -1) for name in body_motion.values()), dtype=np.int32, count=len(body_motion))
    order = np.argsort(driven, kind="stable")
    driven, code = driven[order], code[order]
    at = np.minimum(np.searchsorted(driven, body_index), len(driven) - 1)
    hit = driven[at] == body_index
    motion[hit] = code[at[hit]]
    return motion


def _area_across(shape: ConvexShape, orientation: np.ndarray, axis: np.ndarray) -> float:
    """The area [m^2] of a convex body's shadow along the unit ``axis`` (world), at ``orientation`` (xyzw, of
    its principal frame): half the sum of |n . axis| A over its faces (0 for a shape without faces)."""
    normals = getattr(shape, "face_normals", None)
    if normals is None:
        return 0.0
    # R^T axis: the axis in the body frame, where the face normals are.
    local = quat_to_matrix(orientation).T @ axis
    return 0.5 * float(np.sum(np.abs(np.asarray(normals) @ local) * np.asarray(shape.face_areas)))
