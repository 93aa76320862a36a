"""The Scene class: simulation settings, the shape registry, validate and describe.

Every other concern is a group of methods in the module of that concern, which also sets up and
owns the state it keeps (in its ``__init__``): bodies and their arrays (:mod:`.bodies`), materials
(:mod:`.materials`), plane walls, box containers and drums (:mod:`.walls`), emitters
(:mod:`.emitters`), and the checks of :meth:`Scene.validate` (:mod:`.checks`, :mod:`.overlaps`).
Scene files are read and written by :mod:`.loader` through the public methods only. The groups
reach each other only through public methods (:meth:`Scene.error`, :meth:`Scene.material_index`,
:meth:`Scene.append_bodies`, ...): a private name is used only in the module that defines it.
"""

from __future__ import annotations

import math
import re
import warnings
from os import PathLike

import numpy as np

from polydem.compound import CompoundShape
from polydem.quaternions import quat_from_matrix
from polydem.scene import loader
from polydem.scene.bodies import BodyMethods
from polydem.scene.checks import CheckMethods
from polydem.scene.emitters import EmitterMethods
from polydem.scene.errors import SceneError, SceneWarning, did_you_mean, unknown_name
from polydem.scene.materials import LAW_UNITS, MaterialMethods
from polydem.scene.output import Output
from polydem.scene.overlaps import OverlapMethods
from polydem.scene.values import read_choice, read_integer, read_number, read_string, read_vector, typename
from polydem.scene.walls import WallMethods
from polydem.settle import SPEED_FRACTION, SettleCriterion
from polydem.shapes import ConvexShape

PRECISIONS = ("float32", "mixed", "float64")
"""Values of ``[simulation] precision`` (:mod:`polydem.kernels.precision`): everything in float32;
"mixed" (the default), float64 positions, velocities and force sums with float32 contact geometry in
a frame local to each contact; everything in float64."""


class Scene(BodyMethods, MaterialMethods, WallMethods, EmitterMethods, CheckMethods, OverlapMethods):
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

    Other attributes: :attr:`drums` (the :class:`Drum` records of :meth:`add_drum`),
    :attr:`emitters` (one dict per :meth:`emit` call: key, count, first and last body index) and
    :attr:`warnings` (the :class:`SceneWarning` messages of the last :meth:`validate`).
    """

    def __init__(
        self,
        gravity=(0.0, 0.0, -9.81),
        dt="auto",
        name: str = "scene",
        *,
        steps: int | None = None,
        duration: float | None = None,
        description: str = "",
        file=None,
        device: str | None = None,
        precision: str = "mixed",
        output: Output | None = None,
        settle=None,
    ):
        self.file = file
        self.name = read_string(name, "simulation.name", file)
        self.description = read_string(description, "simulation.description", file)
        self.gravity = tuple(read_vector(gravity, 3, "simulation.gravity", file).tolist())
        self.dt = self._check_dt(dt)
        if steps is not None and duration is not None:
            raise SceneError(
                f"give either steps or duration, not both (got steps = {steps}, duration = {duration})",
                "simulation.duration",
                file,
            )
        self.steps = None if steps is None else read_integer(steps, "simulation.steps", file, minimum=1)
        self.duration = (
            None
            if duration is None
            else read_number(duration, "simulation.duration", file, positive=True, hint=" (simulated time in s)")
        )
        self.device = self._check_device(device)
        self.precision = self._check_precision(precision)
        self.output = self._check_output(output)
        self.settle = self._check_settle(settle)
        self._shapes: dict[str, ConvexShape] = {}
        self._shape_index: dict[str, int] = {}
        self._shape_specs: dict[str, dict] = {}
        self._shape_frames: list[tuple[np.ndarray, np.ndarray]] = []  # (q(R_in), t_in) per shape
        self.warnings: list[str] = []  # of the last validate()
        self._warned: list[str] = []
        # Each concern keeps its own state, set up by the __init__ of its method group.
        super().__init__()

    def _check_dt(self, dt):
        if isinstance(dt, str):
            if dt != "auto":
                raise SceneError(
                    f'expected a time step in seconds or "auto", got string {dt!r}', "simulation.dt", self.file
                )
            return "auto"
        return read_number(dt, "simulation.dt", self.file, positive=True, hint=' (time step in s, or "auto")')

    def _check_device(self, device):
        if device is None:
            return None
        device = read_string(device, "simulation.device", self.file, what='a device name such as "cpu" or "cuda:0"')
        if not re.fullmatch(r"cpu|cuda(:\d+)?", device):
            raise SceneError(
                f'unknown device {device!r}{did_you_mean(device, ("cpu", "cuda", "cuda:0")) or "."} Give "cpu", '
                '"cuda" (the default GPU) or "cuda:N" (GPU number N), or leave device out to use the GPU when '
                "there is one",
                "simulation.device",
                self.file,
            )
        return device

    def _check_precision(self, precision):
        return read_choice(precision, PRECISIONS, "simulation.precision", self.file, what="precision")

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

    def _check_settle(self, settle):
        key = "simulation.settle"
        if settle is None or settle is False or isinstance(settle, SettleCriterion):
            return settle or None
        if settle is True:
            return SettleCriterion()
        if not isinstance(settle, dict):
            raise SceneError(
                "expected a table {kinetic_fraction = 1e-4, speed_fraction = 3e-4, max_speed = ..., hold = 0.02}, got "
                f"{typename(settle)}",
                key,
                self.file,
            )
        fields = ("kinetic_fraction", "speed_fraction", "max_speed", "hold")
        unknown = [k for k in settle if k not in fields]
        if unknown:
            k = unknown[0]
            raise SceneError(
                f"unknown key {k!r}{did_you_mean(k, fields) or '.'} Valid keys: {', '.join(fields)}",
                f"{key}.{k}",
                self.file,
            )
        values = {}
        kf = settle.get("kinetic_fraction", 1e-4)
        if kf is False or kf is None:
            values["kinetic_fraction"] = None
        else:
            hint = " (a fraction of the gravitational energy released, e.g. 1e-4; false to check max_speed alone)"
            values["kinetic_fraction"] = read_number(kf, f"{key}.kinetic_fraction", self.file, positive=True, hint=hint)
            if values["kinetic_fraction"] >= 1.0:
                raise SceneError(f"must be < 1, got {kf:g}{hint}", f"{key}.kinetic_fraction", self.file)
        sf = settle.get("speed_fraction", SPEED_FRACTION)
        if sf is False or sf is None:
            values["speed_fraction"] = None
        else:
            hint = f" (the speed limit as a fraction of sqrt(g r_min), e.g. {SPEED_FRACTION:g}; false for none)"
            values["speed_fraction"] = read_number(sf, f"{key}.speed_fraction", self.file, positive=True, hint=hint)
        if settle.get("max_speed") is not None:
            values["max_speed"] = read_number(
                settle["max_speed"], f"{key}.max_speed", self.file, positive=True, hint=" (largest speed in m/s)"
            )
        if "hold" in settle:
            values["hold"] = read_number(
                settle["hold"], f"{key}.hold", self.file, nonneg=True, hint=" (how long it must hold, in s)"
            )
        if values["kinetic_fraction"] is None and values["speed_fraction"] is None and "max_speed" not in values:
            raise SceneError(
                "with kinetic_fraction = false and speed_fraction = false give max_speed (in m/s): with none of them "
                "nothing is checked",
                f"{key}.max_speed",
                self.file,
            )
        return SettleCriterion(**values)

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
        """A :class:`SceneError` about ``key`` of this scene's file, for its method groups to raise."""
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

    def validate(self) -> Scene:
        """Check the whole scene; raise :class:`SceneError` on the first problem, else return self.

        Checks: simulation settings; all materials share one contact law; at least one body; every
        body's shape and material index exists; all numbers finite; unit quaternions; valid kinds;
        fixed bodies at rest; free bodies have a shape with positive volume and inertia; planes use
        registered materials and have unit normals; only kinematic bodies have pivots; precision is
        float32; the device name and the output settings are valid. Then what a run needs:

        * float32: shape sizes, masses, inertias, stiffnesses and the power law's V^m within
          [F32_LOW, F32_HIGH] (float32's normal range, 10^6 from both ends);
        * positions near enough the origin that their float64 spacing resolves a contact
          (:meth:`check_position_spacing`);
        * the time step (:meth:`time_step`): finite, a given dt within the stable limit, and the
          steps of the run (``duration / dt``) at most MAX_STEPS;
        * contacts stiff enough for the bodies' weight and initial speeds (see :meth:`check_loads`);
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
        self.check_laws()
        if self.num_bodies == 0:
            raise self.error(
                "the scene has no bodies; add at least one with a [[bodies]] table in the scene file or "
                "Scene.add_body() / add_bodies() in Python",
                "bodies",
            )
        a = self.body_arrays()
        self.check_body_arrays(a)
        for j, plane in enumerate(self.planes):
            self.material_index(plane.material, key=f"planes[{j}].material")
            nrm = np.asarray(plane.normal)
            if not (np.all(np.isfinite(nrm)) and abs(np.linalg.norm(nrm) - 1.0) < 1e-9):
                raise self.error(f"normal {list(plane.normal)} is not a unit vector", f"planes[{j}].normal")
        self.check_float32(a)
        self.check_position_spacing(a)
        ts = self.time_step()
        self.check_steps(ts)
        found = self.check_loads(a, ts)
        found += self.check_initial_overlaps(a)
        found += self.check_tunnelling(a, ts.dt)
        found += self._check_compound_parts(a)
        # A run validates twice (loading the file, building the Model): say each thing once.
        if found != self._warned:
            for message in found:
                warnings.warn(f"{self.file}: {message}" if self.file else message, SceneWarning, stacklevel=2)
        self._warned = found
        self.warnings = found
        return self

    def _check_compound_parts(self, a) -> list[str]:
        """A warning per compound shape in use whose parts overlap each other: their contacts count the shared
        region twice."""
        found = []
        used = set(np.unique(a["shape"]).tolist())
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
        f = self.file
        self.gravity = tuple(read_vector(list(self.gravity), 3, "simulation.gravity", f).tolist())
        self.dt = self._check_dt(self.dt)
        self.device = self._check_device(self.device)
        self.precision = self._check_precision(self.precision)
        self.output = self._check_output(self.output)
        self.settle = self._check_settle(self.settle)
        self._check_settle_gravity()
        if self.steps is not None and self.duration is not None:
            raise self.error("give either steps or duration, not both", "simulation.duration")
        if self.steps is not None:
            self.steps = read_integer(self.steps, "simulation.steps", f, minimum=1)
        if self.duration is not None:
            self.duration = read_number(self.duration, "simulation.duration", f, positive=True)

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
        """Settings from an ``[output]`` table (errors name ``output.KEY`` and ``file``)."""
        return loader.load_dict(cls, data, file, base_dir, validate)

    def to_dict(self) -> dict:
        """The ``[materials.NAME]`` table of a scene file (without the name)."""
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
