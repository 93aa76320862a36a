"""The Scene class: a description record of a simulation, with thin methods for its public API.

A Scene holds its settings (read as :mod:`.settings` declares them), its shape registry and a registry per
concern as plain attributes: :attr:`Scene.body_table` (:class:`.bodies.BodyTable`, the body arrays),
:attr:`Scene.material_table` (:class:`.materials.MaterialTable`), :attr:`Scene.wall_table`
(:class:`.walls.WallTable`: planes, mesh walls, drums), :attr:`Scene.emitters` and
:attr:`Scene.scaled_shapes`. The work is done by functions that take the scene, in the module of each
concern: :mod:`.bodies`, :mod:`.materials`, :mod:`.walls`, :mod:`.emitters`, and the checks of
:meth:`Scene.validate` in :mod:`.checks` and :mod:`.overlaps`; the Scene's methods of the same names call
them. Scene files are read and written by :mod:`.loader` through the public methods only. A module reads
another's registry only through the scene's public attributes and methods: a private name is used only in
the module that defines it.
"""

from __future__ import annotations

import math
import warnings
from os import PathLike

import numpy as np

from polydem.compound import CompoundShape
from polydem.quaternions import quat_from_matrix
from polydem.scene import bodies as scene_bodies
from polydem.scene import checks, loader, overlaps
from polydem.scene import emitters as scene_emitters
from polydem.scene import materials as scene_materials
from polydem.scene import walls as scene_walls
from polydem.scene.bodies import BODY, Body, BodyKind, BodyTable
from polydem.scene.emitters import EMITTER
from polydem.scene.errors import SceneError, SceneWarning, unknown_name
from polydem.scene.materials import LAW_UNITS, Material, MaterialTable, PairMaterial
from polydem.scene.motions import MOTION, Motion
from polydem.scene.output import Output
from polydem.scene.settings import SETTING_NAMES, SIMULATION, read_settings
from polydem.scene.values import distinct_codes, typename
from polydem.scene.walls import BOX, DRUM, MESH, PLANE, Drum, MeshWall, PlaneWall, WallTable
from polydem.shapes import ConvexShape


class Scene:
    """Validated, host-only description of a simulation (see :mod:`polydem.scene` for the frames).

    Bodies are stored as per-body numpy arrays (read-only views; scenes reach 10^6 bodies):
    :attr:`body_shape`, :attr:`body_material` (int32 indices into :attr:`shapes` and
    :attr:`materials` in insertion order), :attr:`body_position` (N, 3) centre of mass [m],
    :attr:`body_orientation` (N, 4) xyzw of the body (principal) frame, :attr:`body_velocity`
    (N, 3) [m/s], :attr:`body_angular_velocity` (N, 3) world axes [rad/s] and :attr:`body_kind`
    (int32, 0 free, 1 fixed, 2 kinematic). :meth:`body` returns one body as a :class:`Body`.

    Args:
        gravity: (3,) gravitational acceleration [m/s^2].
        dt: time step [s], > 0, or ``"auto"`` to let the simulator choose from the stiffest contact.
        name: label.
        steps: number of steps to run (optional), > 0.
        duration: simulated time to run [s] (optional), > 0; not together with ``steps``.
        description: free text.
        file: scene file the scene came from (used in error messages), or None.
        device: Warp device to run on (``"cpu"``, ``"cuda"``, ``"cuda:N"``), or None for the default;
            a command-line ``--device`` overrides it.
        precision: ``"mixed"`` (the default: float64 positions, velocities and force sums; float32
            contact geometry in a frame local to each contact, so a grain far from the origin moves
            as one at the origin), ``"float32"`` (everything in float32: less memory and a little
            faster, but positions resolve only the float32 spacing of their coordinates) or
            ``"float64"`` (everything in float64).
        output: what a run writes (:class:`Output`); default ``Output()`` (a summary only).
        settle: run until the pile has settled (:class:`polydem.SettleCriterion`; ``steps`` or
            ``duration`` is then the maximum): a criterion, True for the default one, a dict of its
            fields, or None (the default) to run the whole duration.

    Other attributes: :attr:`drums` (the :class:`Drum` records of :meth:`add_drum`) and :attr:`warnings` (the
    :class:`SceneWarning` messages of the last :meth:`validate`). The registries, which the functions of the
    scene's modules fill and read: :attr:`body_table` (:class:`.bodies.BodyTable`), :attr:`material_table`
    (:class:`.materials.MaterialTable`), :attr:`wall_table` (:class:`.walls.WallTable`), :attr:`emitters` (one
    dict per :meth:`emit` call: key, count, first and last body index) and :attr:`scaled_shapes` (the shapes
    emitters scaled: (shape index, factor) -> index of the scaled shape).
    """

    def __init__(
        self,
        gravity=SIMULATION.defaults["gravity"],
        dt=SIMULATION.defaults["dt"],
        name: str = SIMULATION.defaults["name"],
        *,
        steps: int | None = SIMULATION.defaults["steps"],
        duration: float | None = SIMULATION.defaults["duration"],
        description: str = SIMULATION.defaults["description"],
        file=None,
        device: str | None = SIMULATION.defaults["device"],
        precision: str = SIMULATION.defaults["precision"],
        output: Output | None = None,
        settle=SIMULATION.defaults["settle"],
    ):
        # The arguments named as [simulation] keys are read as SIMULATION declares them.
        given = {attr: value for attr, value in locals().items() if attr in SETTING_NAMES}
        self.file = file
        for attr, value in read_settings(given, file).items():
            setattr(self, attr, value)
        self.output = self._check_output(output)
        self._shapes: dict[str, ConvexShape] = {}
        self._shape_index: dict[str, int] = {}
        self._shape_specs: dict[str, dict] = {}
        self._shape_frames: list[tuple[np.ndarray, np.ndarray]] = []  # (q(R_in), t_in) per shape
        self.warnings: list[str] = []  # of the last validate()
        self._warned: list[str] = []
        # the initial-overlap messages of the last check, and where they stand among the warnings
        self._overlap_messages: list[str] = []
        self._overlap_at = 0
        # validated without the body pairs' overlaps (validate(pair_overlaps=False)) and not finished since
        self.pair_overlaps_pending = False
        self.body_table = BodyTable()
        self.material_table = MaterialTable()
        self.wall_table = WallTable()
        self.motions: dict[str, Motion] = {}  # name -> Motion ([motions.NAME])
        self.body_motion: dict[int, str] = {}  # driven body index -> the name of its motion
        self.emitters: list[dict] = []
        self.scaled_shapes: dict[tuple[int, float], int] = {}

    def _check_output(self, output):
        if output is None:
            return Output()
        if not isinstance(output, Output):
            raise SceneError(
                f"expected a polydem.scene.Output, got {typename(output)}; build one with Output(usd=...)",
                "output",
                self.file,
            )
        return output

    def _check_settle_gravity(self):
        if self.settle is not None:
            try:
                self.settle.check_gravity(self.gravity)
            except ValueError as exc:
                raise SceneError(
                    f"{exc}; in a scene file: settle = {{kinetic_fraction = false, max_speed = V}}",
                    "simulation.settle",
                    self.file,
                ) from None

    def error(self, message: str, key: str) -> SceneError:
        """A :class:`SceneError` about ``key`` of this scene's file, for the functions of its modules to raise."""
        return SceneError(message, key, self.file)

    # ------------------------------------------------------------------ shapes

    @property
    def shapes(self) -> dict[str, ConvexShape]:
        """Registered shapes, name -> :class:`ConvexShape`, in insertion (= index) order (a copy)."""
        return dict(self._shapes)

    @property
    def shape_names(self) -> list[str]:
        return list(self._shapes)

    def shape_index(self, name: str) -> int:
        """Index of a shape in :attr:`shapes` (the value stored in :attr:`body_shape`)."""
        return self._lookup_shape(name, "shape")

    def _lookup_shape(self, name, key) -> int:
        if not isinstance(name, str):
            raise self.error(f"expected a shape name, got {typename(name)}", key)
        if name not in self._shape_index:
            raise self.error(
                unknown_name(name, self._shapes, "shape", "define one with [shapes.NAME] or Scene.add_shape()"), key
            )
        return self._shape_index[name]

    def add_shape(self, name: str, shape: ConvexShape, *, spec: dict | None = None) -> ConvexShape:
        """Register ``shape`` under ``name`` (bodies refer to it by name); returns the shape.

        Registering the same object again under the same name is a no-op. ``spec`` is where the shape
        came from, for :meth:`shape_spec` and :meth:`describe`: the ``[shapes.NAME]`` table it was built
        from, or None.
        """
        key = f"shapes.{name}"
        if not isinstance(name, str) or not name:
            raise self.error(f"shape name must be a non-empty string, got {typename(name)}", "shapes")
        if not isinstance(shape, ConvexShape | CompoundShape):
            raise self.error(
                f"expected a polydem.ConvexShape or CompoundShape, got {typename(shape)}; build one with e.g. "
                "ConvexShape.box(0.1)",
                key,
            )
        if name in self._shapes:
            if self._shapes[name] is shape:
                return shape
            raise self.error(f"a different shape is already registered as {name!r}; choose another name", key)
        self._shape_index[name] = len(self._shapes)
        self._shapes[name] = shape
        if spec is not None:
            self._shape_specs[name] = spec
        self._shape_frames.append((quat_from_matrix(shape.input_rotation), np.array(shape.input_translation)))
        return shape

    def resolve_shape(self, shape, key: str) -> int:
        """Index of ``shape``, a registered name or a :class:`ConvexShape` (registered if new); errors name ``key``."""
        if isinstance(shape, ConvexShape | CompoundShape):
            for name, s in self._shapes.items():
                if s is shape:
                    return self._shape_index[name]
            self.add_shape(shape.name, shape)
            return self._shape_index[shape.name]
        return self._lookup_shape(shape, key)

    def shape_input_frames(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """``(q(R_in), t_in)`` of every shape, in index order: its input frame in its body frame."""
        return self._shape_frames

    def shape_spec(self, name: str) -> dict | None:
        """The ``[shapes.NAME]`` table shape ``name`` was built from (a copy), or None for a shape given as
        a :class:`ConvexShape` (scaled shapes of emitters have the spec of theirs scaled, where it has one)."""
        self._lookup_shape(name, "shape")
        spec = self._shape_specs.get(name)
        return None if spec is None else dict(spec)

    def validate(self, pair_overlaps: bool = True) -> Scene:
        """Check the whole scene; raise :class:`SceneError` on the first problem, else return self.

        ``pair_overlaps=False`` leaves the initial overlaps (plane walls and body pairs) to
        :meth:`finish_overlap_check`, which a :class:`~polydem.Simulation` calls with the pairs found on
        its device.

        Checks: simulation settings; all materials share one contact law; at least one body; every
        body's shape and material index exists; all numbers finite; unit quaternions; valid kinds;
        fixed bodies at rest; free bodies have a shape with positive volume and inertia; planes use
        registered materials and have unit normals; only kinematic bodies have pivots; precision is
        float32; the device name and the output settings are valid. Then what a run needs:

        * float32: shape sizes, masses, inertias, stiffnesses and the power law's V^m within
          [F32_LOW, F32_HIGH] (float32's normal range, 10^6 from both ends);
        * positions near enough the origin that their float64 spacing resolves a contact
          (:func:`.checks.check_position_spacing`);
        * the time step (:meth:`time_step`): finite, a given dt within the stable limit, and the
          steps of the run (``duration / dt``) at most MAX_STEPS;
        * contacts stiff enough for the bodies' weight and initial speeds (see :func:`.checks.check_loads`);
        * a given dt above TOE_STEP_WARNING recommended steps under a law with the resolved toe: a warning
          (:func:`.checks.check_toe_step`);
        * a power law without the toe (m >= 2) with a restitution below RINGING_RESTITUTION under gravity: a
          warning, such contacts ring at rest (:func:`.checks.check_resting_ringing`);
        * tunnelling: a warning where a body starts faster than a step or its contacts can stop it
          before it is through the thinnest body (:meth:`tunnelling_limits`);
        * initial overlaps: a free body deep behind a plane wall or deep inside another body
          (by more than INITIAL_OVERLAP_ERROR of its thickness) is an error; overlaps above
          INITIAL_OVERLAP_WARNING are warnings.

        Warnings are issued as :class:`SceneWarning` (:func:`warnings.warn`; not again by a
        repeated call that finds the same) and kept in :attr:`warnings` (a list of strings).
        """
        self.warnings = []
        self._check_settings()
        scene_materials.check_laws(self)
        if self.num_bodies == 0:
            raise self.error(
                "the scene has no bodies; add at least one with a [[bodies]] table in the scene file or "
                "Scene.add_body() / add_bodies() in Python",
                "bodies",
            )
        a = self.body_arrays()
        checks.check_body_arrays(self, a)
        for j, plane in enumerate(self.planes):
            self.material_index(plane.material, key=f"planes[{j}].material")
            nrm = np.asarray(plane.normal)
            if not (np.all(np.isfinite(nrm)) and abs(np.linalg.norm(nrm) - 1.0) < 1e-9):
                raise self.error(f"normal {list(plane.normal)} is not a unit vector", f"planes[{j}].normal")
        checks.check_float32(self, a)
        checks.check_position_spacing(self, a)
        ts = checks.time_step(self)
        checks.check_steps(self, ts)
        found = checks.check_loads(self, a, ts)
        found += checks.check_toe_step(self, ts)
        found += checks.check_resting_ringing(self)
        if pair_overlaps:
            self._overlap_messages = overlaps.check_initial_overlaps(self, a)
        self.pair_overlaps_pending = not pair_overlaps
        self._overlap_at = len(found)
        # Checked apart (pair_overlaps=False), the overlaps stand here as last found until finish_overlap_check.
        found += self._overlap_messages
        found += checks.check_tunnelling(self, a, ts.dt)
        found += checks.check_motion_speeds(self, a, ts.dt)
        found += self._check_compound_parts(a)
        # A run validates twice (loading the file, building the Model): say each thing once.
        if found != self._warned:
            for message in found if pair_overlaps else self._without_overlaps(found):
                warnings.warn(f"{self.file}: {message}" if self.file else message, SceneWarning, stacklevel=2)
        self._warned = found
        self.warnings = found if pair_overlaps else self._without_overlaps(found)
        return self

    def _without_overlaps(self, found: list[str]) -> list[str]:
        at = self._overlap_at
        return found[:at] + found[at + len(self._overlap_messages) :]

    def finish_overlap_check(self, pair_overlaps=None) -> Scene:
        """The initial-overlap check of a scene validated with ``pair_overlaps=False``: plane walls here, the body
        pairs' records (:class:`~polydem.scene.overlaps.OverlapRecords`) as found on a device, or searched here
        (None); a :class:`SceneError` for an overlap too deep, else its warning issued (once, as :meth:`validate`
        issues its) and put in :attr:`warnings` where validate puts it."""
        found = overlaps.check_initial_overlaps(self, self.body_arrays(), pair_overlaps)
        self.pair_overlaps_pending = False
        at = self._overlap_at
        warned = self._without_overlaps(self._warned)
        warned = warned[:at] + found + warned[at:]
        if warned != self._warned:
            for message in found:
                warnings.warn(f"{self.file}: {message}" if self.file else message, SceneWarning, stacklevel=2)
        self._warned = warned
        self._overlap_messages = found
        self.warnings = warned
        return self

    # ------------------------------------------------------------------ bodies (see bodies.py)

    def body_arrays(self) -> dict[str, np.ndarray]:
        """The stored body arrays by field name (see BODY_FIELDS), trimmed to the bodies: not copies, for reading."""
        return self.body_table.trimmed()

    @property
    def num_bodies(self) -> int:
        return self.body_table.n

    @property
    def body_shape(self) -> np.ndarray:
        """(N,) int32 shape index (into :attr:`shapes`)."""
        return self.body_table.view("shape")

    @property
    def body_material(self) -> np.ndarray:
        """(N,) int32 material index (into :attr:`materials`)."""
        return self.body_table.view("material")

    @property
    def body_position(self) -> np.ndarray:
        """(N, 3) world position of each body's centre of mass [m]."""
        return self.body_table.view("position")

    @property
    def body_orientation(self) -> np.ndarray:
        """(N, 4) unit xyzw quaternion of each body's principal (body) frame, body -> world."""
        return self.body_table.view("orientation")

    @property
    def body_velocity(self) -> np.ndarray:
        """(N, 3) velocity of the centre of mass [m/s]."""
        return self.body_table.view("velocity")

    @property
    def body_angular_velocity(self) -> np.ndarray:
        """(N, 3) angular velocity in world axes [rad/s]."""
        return self.body_table.view("angular_velocity")

    @property
    def body_kind(self) -> np.ndarray:
        """(N,) int32 kind code: a :class:`~polydem.scene.bodies.BodyKind` (0 free, 1 fixed, 2 kinematic)."""
        return self.body_table.view("kind")

    @property
    def body_pivot(self) -> np.ndarray:
        """(N, 3) fixed point each kinematic body turns about [m]; NaN rows for bodies without one.

        A body with a pivot p and angular velocity w moves rigidly about p: after a time t its
        centroid is ``p + Rot(w t) (x0 - p)`` and its velocity ``w x (x - p)``. The parts of a
        :meth:`add_drum` drum have the drum centre as their pivot.
        """
        return self.body_table.view("pivot")

    def add_body(
        self,
        shape,
        material,
        position=(0.0, 0.0, 0.0),
        orientation=BODY.defaults["orientation"],
        velocity=BODY.defaults["velocity"],
        angular_velocity=BODY.defaults["angular_velocity"],
        kind: str = BODY.defaults["kind"],
        *,
        pivot=BODY.defaults["pivot"],
        motion: str | None = BODY.defaults["motion"],
        key: str | None = None,
    ) -> int:
        """Add one body; returns its index.

        Args:
            shape: name of a registered shape, or a :class:`ConvexShape` (registered under its
                ``name`` if it is not yet).
            material: name of a registered material.
            position: (3,) world position of the shape's input-frame origin [m].
            orientation: (4,) unit quaternion xyzw of the shape's input axes.
            velocity: (3,) velocity of the centre of mass [m/s].
            angular_velocity: (3,) world axes [rad/s].
            kind: ``"free"``, ``"fixed"`` (velocities must be zero) or ``"kinematic"``.
            pivot: (3,) for a kinematic body only: a fixed point [m] the body turns about at
                ``angular_velocity``; its velocity is then derived, ``angular_velocity x (centroid -
                pivot)``, so leave ``velocity`` at zero.
            motion: for a kinematic body only: the name of a registered motion (:meth:`add_motion`) it
                follows from its position at t = 0 (:meth:`drive`).
            key: where the value came from, for error messages (default ``bodies[N]``).
        """
        key = key or f"bodies[{self.num_bodies}]"
        if motion is not None:
            self.motion_named(motion, f"{key}.motion")
            if kind != "kinematic":
                raise self.error(f"only a kinematic body follows a motion, this one is {kind!r}: give kind = "
                                 "'kinematic' or leave motion out", f"{key}.motion")  # fmt: skip
        index = scene_bodies.add_body(
            self, shape, material, position, orientation, velocity, angular_velocity, kind, pivot=pivot, key=key
        )
        if motion is not None:
            self.drive([index], motion, key=f"{key}.motion")
        return index

    def add_bodies(
        self,
        shape,
        material,
        positions,
        orientations=None,
        velocities=None,
        angular_velocities=None,
        kind: str = "free",
        *,
        pivots=None,
    ) -> np.ndarray:
        """Add N bodies of one shape and material at once; returns their indices (int64, (N,)).

        Args:
            positions: (N, 3) world positions of the input-frame origins [m].
            orientations: (N, 4) or (4,) unit xyzw quaternions; default identity.
            velocities: (N, 3) or (3,) [m/s]; default zero.
            angular_velocities: (N, 3) or (3,) world axes [rad/s]; default zero.
            kind: one kind for all of them.
            pivots: (N, 3) or (3,) fixed points the (kinematic) bodies turn about [m], or None; see
                :meth:`add_body`.
        """
        return scene_bodies.add_bodies(
            self, shape, material, positions, orientations, velocities, angular_velocities, kind, pivots=pivots
        )

    def body_label(self, i: int) -> str:
        """``body 12 (shape 'cube', free, from emitters[0])``: how messages name a body."""
        return scene_bodies.body_label(self, i)

    def body(self, i: int) -> Body:
        """Body ``i`` as a :class:`Body` (input-frame pose as given, plus its centroid and body frame)."""
        return scene_bodies.body(self, i)

    def input_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) positions [m] and (N, 4) xyzw orientations of the bodies' input frames: the poses as
        given to :meth:`add_body` (see the module docstring of :mod:`polydem.scene` for the frames)."""
        return scene_bodies.input_poses(self)

    def body_vertices(self, i: int) -> np.ndarray:
        """(nv, 3) world coordinates of body ``i``'s vertices [m]."""
        return scene_bodies.body_vertices(self, i)

    def body_mass(self) -> np.ndarray:
        """(N,) mass of each body [kg] (density times volume, whatever the kind)."""
        return scene_bodies.body_mass(self)

    def body_inertia(self) -> np.ndarray:
        """(N, 3) principal moments of inertia of each body [kg m^2], about its body-frame axes."""
        return scene_bodies.body_inertia(self)

    # ------------------------------------------------------------------ materials (see materials.py)

    @property
    def materials(self) -> dict[str, Material]:
        """Registered materials, name -> :class:`Material`, in insertion (= index) order (a copy)."""
        return dict(self.material_table.by_name)

    @property
    def material_names(self) -> list[str]:
        return list(self.material_table.by_name)

    def material_index(self, name: str, *, key: str = "material") -> int:
        """Index of a material in :attr:`materials` (the value stored in :attr:`body_material`).

        ``name`` may also be a registered :class:`Material`; ``key`` is where the name came from, for
        error messages.
        """
        return scene_materials.material_index(self, name, key=key)

    def add_material(self, name: str, **props) -> Material:
        """Register a material; ``props`` are the :class:`Material` fields (density, law, k,
        restitution, friction, and m / tangential_stiffness where needed)."""
        return scene_materials.add_material(self, name, **props)

    def pair_material(self, a, b) -> PairMaterial:
        """Contact properties between two materials (names or :class:`Material`); see :func:`pair_material`."""
        return scene_materials.scene_pair_material(self, a, b)

    def pair_table(self) -> dict:
        """Mixed contact properties of every material pair, as (M, M) float64 arrays indexed like
        :attr:`materials`: ``k``, ``restitution``, ``friction``, ``tangential_stiffness`` (NaN where
        the simulator derives it); plus ``law`` (str) and ``exponent`` (float) shared by all."""
        return scene_materials.pair_table(self)

    # ------------------------------------------------------------------ walls (see walls.py)

    @property
    def planes(self) -> list[PlaneWall]:
        """Plane walls (a copy of the list)."""
        return list(self.wall_table.planes)

    @property
    def plane_keys(self) -> list[str]:
        """Where each plane wall came from, e.g. ``walls[0]`` of a scene file or ``planes[1]`` (for messages)."""
        return list(self.wall_table.plane_keys)

    @property
    def mesh_walls(self) -> list[MeshWall]:
        """Triangle-mesh walls (a copy of the list)."""
        return list(self.wall_table.mesh_walls)

    @property
    def mesh_wall_keys(self) -> list[str]:
        """Where each mesh wall came from, e.g. ``walls[2]`` (for messages)."""
        return list(self.wall_table.mesh_wall_keys)

    @property
    def drums(self) -> list[Drum]:
        """The :class:`Drum` records of :meth:`add_drum`."""
        return self.wall_table.drums

    def add_plane(
        self, point, normal, material, *, motion: str | None = PLANE.defaults["motion"], key: str | None = None
    ) -> PlaneWall:
        """Add an infinite plane through ``point`` [m] facing ``normal`` (normalised; non-zero).

        ``motion``: the name of a registered cycle or ramp motion (:meth:`add_motion`) that moves the plane from
        where it is at t = 0 (a shaken floor, a piston at a set speed); default fixed. ``key`` is where the
        value came from, for error messages (default ``planes[N]``).
        """
        return scene_walls.add_plane(self, point, normal, material, motion=motion, key=key)

    def add_mesh_wall(
        self,
        mesh,
        material,
        *,
        scale=MESH.defaults["scale"],
        orientation=MESH.defaults["orientation"],
        position=MESH.defaults["position"],
        velocity=MESH.defaults["velocity"],
        angular_velocity=MESH.defaults["angular_velocity"],
        pivot=MESH.defaults["pivot"],
        thickness=MESH.defaults["thickness"],
        flip_normals: bool = MESH.defaults["flip_normals"],
        motion: str | None = MESH.defaults["motion"],
        key: str | None = None,
        base_dir=None,
    ) -> MeshWall:
        """Add a wall made of a triangle mesh: open or closed, convex or not (see :mod:`polydem.meshwall`).

        The wall is solid behind its triangles (against their normals, i.e. the bodies are on the
        side a counter-clockwise triangle faces), ``thickness`` [m] deep (default: the largest
        bounding diameter of the free bodies); ``flip_normals`` reverses every triangle. Keep the
        thickness below half the thinnest part of a closed wall, or the cells behind one side
        reach out of the other (:meth:`validate` warns where they do), and within a factor of
        10^6 of the triangles' sizes (validation refuses others: the cells are built to 10^-9 of
        their size). Validation also refuses free bodies that start deep in the solid (as for
        plane walls) and warns of a wall moving faster than the bodies it hits can take.

        Args:
            mesh: a mesh file (STL, OBJ, PLY; relative paths from ``base_dir``), a trimesh.Trimesh,
                or ``(vertices, triangles)`` arrays.
            material: a material name registered in the scene.
            scale: a factor or (sx, sy, sz) applied to the file's coordinates first.
            orientation: unit quaternion xyzw applied after the scale (default: none).
            position: translation applied last [m].
            velocity: (3,) [m/s]; angular_velocity: (3,) [rad/s] about ``pivot`` (default
                ``position``): a kinematic wall, e.g. a turning mixer.
            motion: the name of a registered cycle or ramp motion (:meth:`add_motion`) that moves the whole wall
                from where it is at t = 0, e.g. a tapped mesh container (then no velocity or angular_velocity).
            key: where the values came from, for messages (default ``mesh_walls[N]``).
        """
        return scene_walls.add_mesh_wall(
            self,
            mesh,
            material,
            scale=scale,
            orientation=orientation,
            position=position,
            velocity=velocity,
            angular_velocity=angular_velocity,
            pivot=pivot,
            thickness=thickness,
            flip_normals=flip_normals,
            motion=motion,
            key=key,
            base_dir=base_dir,
        )

    def mesh_wall_thickness(self, wall: MeshWall) -> float:
        """The depth [m] of a mesh wall's solid: its ``thickness``, or by default the largest bounding
        diameter of the free bodies' shapes (of all shapes where no body is free), as the Model takes it."""
        return scene_walls.mesh_wall_thickness(self, wall)

    def mesh_wall_cells(self, wall: MeshWall, thickness: float):
        """The :class:`~polydem.meshwall.MeshCells` of ``wall`` at ``thickness`` [m], in the wall's own frame
        (world axes at t = 0, origin at its pivot: what the Model steps), kept for the next call (the checks
        run at every validation and the Model reuses them; the cells only change with the thickness)."""
        return scene_walls.mesh_wall_cells(self, wall, thickness)

    def add_motion(self, name: str, frequency=None, **props) -> Motion:
        """Register a prescribed motion (vibration, taps, a ramp or a servo: :class:`~polydem.scene.motions.Motion`)
        that box containers (``add_box_container(..., motion=name)``) and kinematic bodies (:meth:`drive`) follow;
        ``frequency`` and ``props`` are its fields (kind, amplitude or gamma, axis, start, period, count, ...)."""
        if name in self.motions:
            raise self.error(f"motion {name!r} is already defined; give each motion its own name", f"motions.{name}")
        try:
            motion = Motion(name=name, frequency=frequency, **props)
        except TypeError as exc:
            raise self.error(f"{exc}; a motion takes {', '.join(MOTION.names)}", f"motions.{name}") from None
        motion.amplitude_in(self.gravity)  # gamma needs gravity: refuse it now, not at the run
        self.motions[name] = motion
        return motion

    def motion_named(self, name, key: str) -> Motion:
        """The registered motion ``name``; a SceneError about ``key`` where there is none."""
        if not isinstance(name, str) or name not in self.motions:
            how = "define one with [motions.NAME] or Scene.add_motion()"
            raise self.error(unknown_name(str(name), self.motions, "motion", how), key)
        return self.motions[name]

    def drive(self, bodies, motion: str, *, key: str | None = None) -> None:
        """Move the kinematic ``bodies`` (indices) by the registered ``motion`` from their positions at t = 0."""
        key = key or "motion"
        self.motion_named(motion, key)
        kind = np.asarray(self.body_kind)
        index = np.atleast_1d(np.asarray(bodies, dtype=np.int64)).reshape(-1)
        inside = (index >= 0) & (index < self.num_bodies)
        bad = ~inside
        bad[inside] = kind[index[inside]] != BodyKind.KINEMATIC
        first = int(np.argmax(bad)) if bad.any() else len(index)
        # The bodies before the first refused one follow it, as one by one.
        self.body_motion.update(dict.fromkeys(index[:first].tolist(), motion))
        if first < len(index):
            raise self.error(f"body {int(index[first])} is not a kinematic body of this scene: only kinematic bodies "
                             "follow a motion (kind = 'kinematic')", key)  # fmt: skip

    def add_box_container(
        self,
        center,
        inner_size,
        material,
        wall_thickness=BOX.defaults["wall_thickness"],
        open_top: bool = BOX.defaults["open_top"],
        *,
        motion: str | None = None,
        key: str | None = None,
    ) -> list[int]:
        """Add an axis-aligned box container made of fixed box-shaped bodies; returns their indices.

        The cavity is ``inner_size`` = (lx, ly, lz) [m] centred on ``center`` [m], z up. The walls,
        ``wall_thickness`` [m] thick (default 10% of the smallest inner size), are: a floor plate
        covering the whole outer footprint, two x walls spanning the outer y extent, two y walls
        between them, and a lid like the floor unless ``open_top``. Walls touch but do not overlap.
        The needed box shapes are registered as ``"wall_box_{sx}x{sy}x{sz}"``. ``key`` is where the
        value came from, for error messages (default ``box_container``).
        """
        return scene_walls.add_box_container(
            self, center, inner_size, material, wall_thickness, open_top, motion=motion, key=key
        )

    def add_drum(
        self,
        center,
        axis,
        radius,
        length,
        material,
        *,
        omega=DRUM.defaults["omega"],
        rpm=DRUM.defaults["rpm"],
        sides=DRUM.defaults["sides"],
        thickness=DRUM.defaults["thickness"],
        caps=DRUM.defaults["caps"],
        key: str | None = None,
    ) -> Drum:
        """Add a rotating polygonal drum made of kinematic bodies; returns its :class:`Drum` record.

        A hollow drum is not convex, so it is built from ``sides`` box slabs, ``thickness`` thick
        and ``length`` long, whose inner faces are the sides of a regular polygon of inradius
        ``radius`` around the axis (adjacent slabs meet along the polygon's corners and open up
        outwards, so the inside is closed). With ``caps`` two polygonal plates (prisms centred on
        the axis, covering the slabs' outer corners) close the ends at ``+-length / 2``.

        Every part is a kinematic body with angular velocity ``omega * axis`` and the drum centre
        as its pivot (:attr:`body_pivot`); a slab's velocity is ``omega x r``, r from the axis to
        the slab's centre, and the caps only spin. The registered shapes are
        ``"wall_box_{w}x{length}x{thickness}"`` (w = 2 radius tan(pi / sides)) and
        ``"drum_cap_{sides}_{r}x{thickness}"``.

        Args:
            center: (3,) middle of the drum on its axis [m].
            axis: (3,) direction of the axis (any non-zero length) [-]; the drum turns by the
                right-hand rule about it.
            radius: inradius of the inner polygon [m], > 0.
            length: inner length along the axis [m], > 0.
            material: material name.
            omega: angular speed [rad/s] (negative turns the other way); or give ``rpm``.
            rpm: revolutions per minute (2 pi / 60 rad/s each); or give ``omega``.
            sides: number of slabs, >= 3 (default 24).
            thickness: slab and cap thickness [m], default a tenth of ``radius``.
            caps: close the ends with rotating plates (default True).
            key: where the value came from, for error messages (default ``drums[N]``).
        """
        return scene_walls.add_drum(
            self,
            center,
            axis,
            radius,
            length,
            material,
            omega=omega,
            rpm=rpm,
            sides=sides,
            thickness=thickness,
            caps=caps,
            key=key,
        )

    # ------------------------------------------------------------------ emitters (see emitters.py)

    def emit(
        self,
        shape,
        material,
        count,
        region,
        *,
        weights=EMITTER.defaults["weights"],
        orientation=EMITTER.defaults["orientation"],
        seed=EMITTER.defaults["seed"],
        velocity=EMITTER.defaults["velocity"],
        velocity_jitter=EMITTER.defaults["velocity_jitter"],
        scale=EMITTER.defaults["scale"],
        scale_range=EMITTER.defaults["scale_range"],
        scale_lognormal=EMITTER.defaults["scale_lognormal"],
        scale_bins=EMITTER.defaults["scale_bins"],
        kind=EMITTER.defaults["kind"],
        spacing=EMITTER.defaults["spacing"],
        jitter=EMITTER.defaults["jitter"],
        fill=EMITTER.defaults["fill"],
        key: str | None = None,
    ) -> np.ndarray:
        """Place ``count`` bodies in a box region without overlaps; returns their indices.

        This is the ``[[emitters]]`` table of a scene file (same argument names).

        Placement. Each body gets a cell of a cubic grid filling the region (centred in it); the
        cell side is ``spacing`` times the largest bounding diameter among the emitted bodies, and
        each body's centre of mass is moved from its cell centre by up to ``jitter`` times its free
        room (half the cell minus its bounding radius) along each axis, uniformly at random. So
        every bounding sphere stays inside its own cell: no two emitted bodies overlap and none
        crosses the region's faces. Cells that would cross a plane wall, any body already in the
        scene (a container's slabs, a drum's slabs, earlier bodies and emitters; tested against
        the body's face planes) or that lie beside a drum (within its axial span) without being
        wholly inside it are left out.
        ``fill = "bottom"`` takes the lowest cells first (layers against gravity; within the last
        layer at random), ``fill = "random"`` cells anywhere in the region. Bodies are stored in
        the grid order of their cells. If the region cannot hold ``count`` bodies, SceneError
        (key ``.count``, or ``.region`` when not even one cell fits) says how many fit.

        Everything is deterministic for a given ``seed`` (independent random streams for the
        shape mix, the sizes, the cells, the jitter, the orientations and the velocities) and
        vectorised: 10^6 bodies take a few seconds.

        Args:
            shape: a shape name (or :class:`ConvexShape`), a list of names (a mix; ``weights``
                gives their proportions, equal by default), or a dict name -> weight. The counts
                follow the weights exactly (largest remainders), in random order.
            material: material name.
            count: number of bodies, >= 1.
            region: the box to fill, ``{"min": (x0, y0, z0), "max": (x1, y1, z1)}`` or a pair
                ``(min, max)`` [m].
            weights: proportions of a list of shapes (non-negative, not all zero).
            orientation: ``"random"`` (uniform) or ``"aligned"`` (input axes along world axes).
            seed: integer >= 0.
            velocity: (3,) initial velocity of every body [m/s].
            velocity_jitter: each velocity component gets a uniform random addition in
                ``[-velocity_jitter, velocity_jitter]`` [m/s].
            scale: one size factor for all bodies (default 1), or
            scale_range: ``(lo, hi)``, factors uniform in [lo, hi], or
            scale_lognormal: ``{"mean": m, "sigma": s}``: ln(factor) normal with standard deviation
                s, its mean chosen so that the factors average m; truncated at 3 s either side.
            scale_bins: a distribution is quantised into this many equal bins (in log for the
                lognormal), each body taking its bin's centre, so at most ``scale_bins`` new shapes
                per base shape are registered (``ConvexShape.scaled``, named ``"{name}_x{factor}"``).
                Factors scale about each shape's input origin (its centroid but for rocks).
            kind: ``"free"`` (default), ``"fixed"`` or ``"kinematic"``.
            spacing: cell side over the largest bounding diameter, >= 1 (default 1.1).
            jitter: fraction of each body's free room used for its random offset, in [0, 1].
            fill: ``"bottom"`` (default) or ``"random"``.
            key: where the value came from, for error messages (default ``emitters[N]``).
        """
        args = {k: v for k, v in locals().items() if k not in ("self", "shape", "material", "count", "region")}
        return scene_emitters.emit(self, shape, material, count, region, **args)

    # ------------------------------------------------------------------ checks (see checks.py)

    def time_step(self) -> checks.TimeStep:
        """The time step of a run and its bounds (:func:`.checks.time_step`; host-only: ``polydem validate`` needs
        no Warp)."""
        return checks.time_step(self)

    def tunnelling_limits(self, a, dt: float) -> checks.TunnelLimits:
        """Per body, the speed of its fastest point above which it may tunnel at time step ``dt`` [s] (``a``: the
        body arrays; :func:`.checks.tunnelling_limits`)."""
        return checks.tunnelling_limits(self, a, dt)

    def check_tunnelling(self, a, dt: float, limits: checks.TunnelLimits | None = None) -> list[str]:
        """A warning when a body starts faster than its :meth:`tunnelling_limits` (``limits``, where they are at
        hand; :func:`.checks.check_tunnelling`)."""
        return checks.check_tunnelling(self, a, dt, limits)

    def check_run_span(self, dt: float, steps: int, source: str, default: bool = False) -> list[str]:
        """Warnings about the simulated time a run of ``steps`` steps of ``dt`` [s] covers
        (:func:`.checks.check_run_span`)."""
        return checks.check_run_span(self, dt, steps, source, default)

    def check_initial_overlaps(self, a) -> list[str]:
        """Warnings of free bodies that start behind a plane wall or inside another body (``a``: the body arrays);
        a SceneError for one deeper than INITIAL_OVERLAP_ERROR (:func:`.overlaps.check_initial_overlaps`)."""
        return overlaps.check_initial_overlaps(self, a)

    def _check_compound_parts(self, a) -> list[str]:
        """A warning per compound shape in use whose parts overlap each other: their contacts count the shared
        region twice."""
        found = []
        used = set(distinct_codes(a["shape"], len(self.shapes)).tolist())
        for index, (name, shape) in enumerate(self.shapes.items()):
            if index in used and getattr(shape, "overlapping", False):
                found.append(
                    f"shapes.{name}: parts of this compound grain overlap each other, so a contact that reaches "
                    "their shared region counts it twice (V and the force up to 2x there); parts that only "
                    "touch are exact (README.md, 'Non-convex grains')"
                )
        return found

    def _check_settings(self):
        """The simulation settings again: they are attributes a user may have changed since __init__."""
        for attr, value in read_settings({a: getattr(self, a) for a in SETTING_NAMES}, self.file).items():
            setattr(self, attr, value)
        self.output = self._check_output(self.output)
        self._check_settle_gravity()

    # ------------------------------------------------------------------ scene files (see loader.py)

    @classmethod
    def from_toml(cls, path: str | PathLike, *, validate: bool = True) -> Scene:
        """Load a scene file (TOML; see ``scenes/*.toml`` for examples) and validate it.

        Relative mesh paths are taken from the folder of the scene file. Every problem raises
        :class:`SceneError` naming the file and the key.
        """
        return loader.load_toml(cls, path, validate)

    @classmethod
    def from_dict(cls, data: dict, *, file=None, base_dir=None, validate: bool = True) -> Scene:
        """A scene from the nested dict of a scene file (as ``tomllib`` reads one, or :meth:`to_dict` gives);
        errors name ``file``, and relative mesh paths are taken from ``base_dir`` (default: the working folder)."""
        return loader.load_dict(cls, data, file, base_dir, validate)

    def to_dict(self) -> dict:
        """The scene as the nested dict of a scene file, which :meth:`from_dict` reads back to the same scene."""
        return loader.scene_dict(self)

    def describe(self) -> str:
        """A human-readable summary."""
        g = ", ".join(f"{x:g}" for x in self.gravity)
        dt = self.dt if self.dt == "auto" else f"{self.dt:g} s"
        run = f", {self.steps} steps" if self.steps is not None else ""
        run += f", duration {self.duration:g} s" if self.duration is not None else ""
        run += f", {self.precision}" + (f", device {self.device}" if self.device else "")
        if self.settle is not None:
            run += f"; until settled ({self.settle.describe(self)})"
        lines = [
            f"Scene {self.name!r}" + (f" from {self.file}" if self.file else ""),
            f"  gravity [{g}] m/s^2, dt {dt}{run}",
        ]
        if self.description:
            lines.append(f"  {self.description}")
        lines.append(f"  materials ({len(self.material_names)}):")
        for m in self.materials.values():
            extra = f", m={m.m:g}" if m.m is not None else ""
            extra += f", kt={m.tangential_stiffness:g} N/m" if m.tangential_stiffness is not None else ""
            lines.append(
                f"    {m.name}: density {m.density:g} kg/m^3, {m.law} k={m.k:g} {LAW_UNITS[m.law]}{extra}, "
                f"e={m.restitution:g}, mu={m.friction:g}"
            )
        lines.append(f"  shapes ({len(self._shapes)}):")
        counts = (
            np.bincount(self.body_shape, minlength=len(self._shapes)) if self.num_bodies else [0] * len(self._shapes)
        )
        for (name, s), c in zip(self._shapes.items(), counts, strict=True):
            kind = self._shape_specs.get(name, {}).get("type", "custom")
            lines.append(
                f"    {name}: {kind}, {s.num_vertices} vertices, {s.num_faces} faces, volume {s.volume:.4g} "
                f"m^3, radius {s.radius:.4g} m; {int(c)} bodies"
            )
        kinds = np.bincount(self.body_kind, minlength=3) if self.num_bodies else [0, 0, 0]
        lines.append(f"  bodies: {self.num_bodies} ({kinds[0]} free, {kinds[1]} fixed, {kinds[2]} kinematic)")
        lines.append(f"  planes ({len(self.planes)}):")
        for p in self.planes:
            lines.append(
                f"    point [{', '.join(f'{x:g}' for x in p.point)}], normal "
                f"[{', '.join(f'{x:.4g}' for x in p.normal)}], material {p.material}"
                + (f", follows motion {p.motion}" if p.motion is not None else "")
            )
        for w, key in zip(self.mesh_walls, self.mesh_wall_keys, strict=True):
            lo, hi = w.vertices.min(axis=0), w.vertices.max(axis=0)
            moving = ""
            if w.moving:
                moving = (
                    f", velocity [{', '.join(f'{x:g}' for x in w.velocity)}] m/s, angular velocity "
                    f"[{', '.join(f'{x:g}' for x in w.angular_velocity)}] rad/s about "
                    f"[{', '.join(f'{x:g}' for x in w.pivot)}]"
                )
            if w.motion is not None:
                moving = f", follows motion {w.motion}"
            lines.append(
                f"  mesh wall {key} ({w.source}): {len(w.triangles)} triangles, bounds "
                f"[{', '.join(f'{x:.4g}' for x in lo)}] to [{', '.join(f'{x:.4g}' for x in hi)}] m, "
                f"material {w.material}{moving}"
            )
        for d in self.drums:
            centre = ", ".join(f"{x:g}" for x in d.center)
            axis = ", ".join(f"{x:.4g}" for x in d.axis)
            lines.append(
                f"  drum: centre [{centre}], axis [{axis}],"
                f" radius {d.radius:g} m, length {d.length:g} m, {d.sides} slabs{' and 2 caps' if d.caps else ''}, "
                f"omega {d.omega:.4g} rad/s ({d.omega * 60.0 / (2.0 * math.pi):.4g} rpm)"
            )
        for e in self.emitters:
            lines.append(f"  {e['key']}: {e['count']} bodies (indices {e['first']} to {e['last']})")
        o = self.output
        out = [f"summary {o.summary}" if o.summary else "no summary"]
        if o.usd:
            out.append(f"USD {o.usd} at {o.fps:g} fps")
        if o.pictures:
            out.append(f"pictures {o.pictures if isinstance(o.pictures, str) else list(o.pictures)}")
        if o.checkpoint_steps is not None:
            out.append(f"checkpoint every {o.checkpoint_steps} steps")
        if o.checkpoint_seconds is not None:
            out.append(f"checkpoint every {o.checkpoint_seconds:g} s")
        if o.vtk:
            out.append("VTK files in vtk/")
        lines.append("  output: " + ", ".join(out))
        return "\n".join(lines)

    def __repr__(self) -> str:
        return (
            f"Scene(name={self.name!r}, bodies={self.num_bodies}, shapes={len(self._shapes)}, "
            f"materials={len(self.material_names)}, planes={len(self.planes)})"
        )
