"""Stream simulation frames to a USD file (one PointInstancer, one Mesh prototype per shape).

Usage::

    from polydem.usd import UsdRecorder

    sim = polydem.Simulation(scene)
    with UsdRecorder("pour.usdc", scene, fps=30) as rec:
        for _ in range(300):
            rec.record_simulation(sim)           # or rec.record(sim.time, positions, orientations)
            sim.step(steps_per_frame)

Layout of the file (Z up and metres unless told otherwise)::

    /World                       Xform, the default prim
    /World/Bodies                PointInstancer: protoIndices = Scene.body_shape (constant),
                                 positions, orientations and orientationsf, velocities and
                                 angularVelocities, extent (time samples), polydem:time (time
                                 samples: the exact simulated time [s])
    /World/Bodies/Prototypes/S   Mesh per shape S, in its body frame (centroid, principal axes):
                                 the shape's polygon faces (counter-clockwise seen from outside),
                                 flat (face-varying) normals, subdivisionScheme "none", and a
                                 constant displayColor from :data:`PALETTE` (the shape's index)
    /World/Walls/plane_K         Mesh: plane wall K as one large quad facing the simulated side
    /World/Walls/mesh_K          Mesh: mesh wall K, its triangles in the wall's frame (origin at
                                 its pivot) with flat normals, posed by xformOp:translate and
                                 xformOp:orient (time samples from ``mesh_q`` when it moves)

Every body, whatever its kind, is an instance: fixed bodies stay put and kinematic ones move.

Metadata (the root layer's customLayerData, read by :func:`read_metadata`): ``polydem:version``,
``polydem:scene`` (its name), ``polydem:frame_dt`` and ``polydem:shapes_sha256``
(:func:`shapes_digest` of the scene), which ``polydem render`` compares with the scene it is given:
the poses of a file drawn with another scene's shapes would look right and be wrong.

Time. Stage ``timeCodesPerSecond`` and ``framesPerSecond`` are ``fps`` (playback rate) and a frame
recorded at simulated time ``t`` gets the time code ``round(t / frame_dt)``, where ``frame_dt`` is
the simulated time between consecutive time codes (default ``1 / fps``: playback in real time;
``frame_dt = 1e-3`` with ``fps = 25`` plays 1 ms of simulation per video frame, 40x slow motion).
Time codes must increase from record to record. ``startTimeCode`` is 0 and ``endTimeCode`` follows
the last recorded frame.

Orientations. polydem quaternions are ``[x, y, z, w]``; Gf quaternions are constructed as
``(w, x, y, z)`` (their memory holds x, y, z, w). The recorder writes them through numpy without any
per-body Python work. Where the installed usd-core has ``PointInstancer.orientationsf`` (``quatf[]``,
newer OpenUSD), they are written there in single precision (|q| within 1e-7 of 1), and also, in half
precision, to ``orientations`` (``quath[]``) for readers that predate ``orientationsf``: OpenUSD
prefers ``orientationsf`` where both are authored, older readers see ``orientations``. Half precision
alone (``orientation_precision="half"``, and the fallback on an older usd-core) rounds |q| by up to
about 4e-4 and the rotation by about 1e-3 rad. Each quaternion's sign is chosen to be nearest to the
previous frame's, so a viewer interpolating between frames turns the short way.

Velocities. Frames given velocities (:meth:`~UsdRecorder.record_simulation` always gives them) also
write ``velocities`` (file units per second) and ``angularVelocities`` (degrees per second, world
axes), which renderers use for motion blur and, per the PointInstancer schema, to move bodies between
time samples instead of interpolating. The schema's "second" is ``timeCodesPerSecond`` time codes of
playback, so both are scaled by ``frame_dt * fps`` (1 for real-time playback): with ``frame_dt =
1e-3`` and ``fps = 25``, a body at 1 m/s is written as 0.025 m/s. :func:`read_velocities` undoes the
scaling.

Streaming. Frames are not kept: the file is saved every ``save_every`` frames (if given), once the
unsaved frames reach ``max_unsaved_mb``, every ``save_interval`` seconds of wall time, and on
:meth:`~UsdRecorder.close`. ``.usdc`` and ``.usd`` (binary crate) saves append the new time samples
to the file, so memory stays bounded (BENCHMARKS.md gives the time and bytes per frame) and the file
on disk is a valid, complete recording of every frame up to the last save, should the run be
interrupted. Each save rewrites the (small) index, which grows with the number of frames: for
long runs of few bodies, save less often. ``.usda`` (text) keeps every frame in memory and rewrites
the whole file on each save: meant for small scenes and for reading by eye.

``pxr`` (the ``usd-core`` package) is imported only when a recorder is made or a file is read, so
``import polydem`` does not need it.
"""

from __future__ import annotations

import functools
import hashlib
import math
import os
import time as _time
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np

__all__ = [
    "PALETTE",
    "UsdRecorder",
    "read_frame",
    "read_metadata",
    "read_time_codes",
    "read_velocities",
    "shapes_digest",
]

EXTENSIONS = (".usda", ".usdc", ".usd")
"""File extensions the recorder writes: text (``.usda``) or binary crate (``.usdc``, ``.usd``)."""

PALETTE = (
    (0.122, 0.467, 0.706),
    (1.000, 0.498, 0.055),
    (0.173, 0.627, 0.173),
    (0.839, 0.153, 0.157),
    (0.580, 0.404, 0.741),
    (0.549, 0.337, 0.294),
    (0.890, 0.467, 0.761),
    (0.498, 0.498, 0.498),
    (0.737, 0.741, 0.133),
    (0.090, 0.745, 0.812),
)
"""displayColor of shape ``k`` is ``PALETTE[k % len(PALETTE)]`` (RGB in [0, 1])."""

WALL_COLOR = (0.6, 0.6, 0.6)

BODIES_PATH = "/World/Bodies"
WALLS_PATH = "/World/Walls"
TIME_ATTR = "polydem:time"


def shapes_digest(scene) -> str:
    """sha256 (hex) of what a scene's bodies look like: each body's shape index and, shape by shape,
    the convex hulls it is drawn from (a compound grain's parts, placed in its body frame).

    A file records it (``polydem:shapes_sha256``, see :func:`read_metadata`) so that a reader
    can tell whether a scene is the one the file was written from: body counts and fixed bodies
    alike do not make the shapes alike. A convex hull is its vertex set, so the faces (and the
    order a hull algorithm lists the vertices in) are left out; the vertices are sorted and
    rounded to 1e-6 of the shape's size, so that the last bits of a shape rebuilt by another
    version of numpy or trimesh do not count.
    """
    scene = getattr(scene, "scene", scene)  # a Simulation (any front) -> its Scene
    h = hashlib.sha256(b"polydem shapes 1\n")
    h.update(np.ascontiguousarray(scene.body_shape, dtype="<i8").tobytes())
    for name in scene.shape_names:
        shape = scene.shapes[name]
        hulls = shape.part_vertices() if getattr(shape, "is_compound", False) else [shape.vertices]
        hulls = [np.asarray(v, dtype=np.float64).reshape(-1, 3) for v in hulls]
        size = max((float(np.abs(v).max()) for v in hulls if v.size), default=0.0) or 1.0
        h.update(f"shape {len(hulls)}\n".encode())
        for v in hulls:
            q = np.rint(v / (1e-6 * size)).astype("<i8")
            q = q[np.lexsort(q.T[::-1])]
            h.update(f"hull {len(q)}\n".encode())
            h.update(q.tobytes())
    return h.hexdigest()


def _check_path(path) -> Path:
    """The output path; its extension must be one of :data:`EXTENSIONS` (any letter case)."""
    p = Path(os.fspath(path))
    if p.suffix.lower() not in EXTENSIONS:
        raise ValueError(
            f"cannot write USD to {str(p)!r}: the extension must be .usda (text), .usdc or .usd (binary), "
            f"got {p.suffix or 'none'!r}"
        )
    return p


@functools.cache
def _real_last() -> bool:
    """Whether Gf quaternion arrays hold (x, y, z, w) in memory (True) or (w, x, y, z) (False)."""
    from pxr import Gf, Vt

    a = np.asarray(Vt.QuatfArray([Gf.Quatf(1.0, 2.0, 3.0, 4.0)]), dtype=np.float64).tolist()
    if a == [[2.0, 3.0, 4.0, 1.0]]:
        return True
    if a == [[1.0, 2.0, 3.0, 4.0]]:
        return False
    raise RuntimeError(f"unexpected memory layout of Gf.Quatf in this usd-core: {a}")


def _quats_to_vt(q_xyzw: np.ndarray, precision: str):
    """(N, 4) xyzw quaternions -> Vt.QuathArray / Vt.QuatfArray (no per-element Python work)."""
    from pxr import Vt

    q = q_xyzw if _real_last() else q_xyzw[:, [3, 0, 1, 2]]
    if precision == "half":
        return Vt.QuathArray.FromNumpy(np.ascontiguousarray(q, dtype=np.float16))
    return Vt.QuatfArray.FromNumpy(np.ascontiguousarray(q, dtype=np.float32))


def _vec3f_to_vt(array):
    """A device (N,) vec3f array -> Vt.Vec3fArray (its one host copy dropped once converted)."""
    from pxr import Vt

    return Vt.Vec3fArray.FromNumpy(array.numpy())


@dataclass
class _DeviceFrame:
    """The device arrays of one frame (:func:`polydem.kernels.export.launch_frame`), each (N,)."""

    previous: object  # vec4f: the previous frame's quaternions
    position: object  # vec3f, file units
    orientation: object  # vec4f, unit xyzw
    velocity: object  # vec3f, file units per second of playback
    angular_velocity: object  # vec3f, degrees per second of playback


def _quats_from_vt(values) -> np.ndarray:
    """Vt quaternion array -> (N, 4) float64 xyzw."""
    q = np.asarray(values, dtype=np.float64).reshape(-1, 4)
    return q if _real_last() else q[:, [1, 2, 3, 0]]


def _positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0.0):
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return v


def plane_quad(point, normal, center, half: float) -> np.ndarray:
    """(4, 3) corners of a square of half-size ``half`` in the plane, counter-clockwise seen from
    the side the normal points to, centred on ``center``'s projection onto the plane."""
    n = np.asarray(normal, dtype=np.float64)
    p = np.asarray(point, dtype=np.float64)
    c = center - np.dot(center - p, n) * n
    a = np.zeros(3)
    a[int(np.argmin(np.abs(n)))] = 1.0
    u = np.cross(a, n)
    u /= np.linalg.norm(u)
    v = np.cross(n, u)  # (u, v, n) right-handed
    corners = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]]) * half
    return c + corners[:, :1] * u + corners[:, 1:] * v


class UsdRecorder:
    """Write the frames of a run to a USD file as they come (see the module docstring).

    Args:
        path: output file; ``.usda`` (text), ``.usdc`` or ``.usd`` (binary crate). Overwritten if it
            exists; missing parent folders are made. A file that this process still has open (a
            ``Usd.Stage`` or ``Sdf.Layer`` on it) cannot be recorded to.
        scene: the :class:`~polydem.Scene`, or a :class:`~polydem.Simulation` (its scene is used).
        fps: playback rate, stage ``timeCodesPerSecond`` and ``framesPerSecond`` [1/s].
        frame_dt: simulated time per time code [s]; default ``1 / fps`` (real-time playback).
        up_axis: ``"Z"`` or ``"Y"``, stage metadata only: the data is written in the simulation's
            axes unchanged, so give the axis that points against gravity.
        meters_per_unit: length unit of the file [m]; lengths are written in this unit (e.g. 0.01
            writes centimetres). :func:`read_frame` converts back to metres.
        orientation_precision: ``"auto"`` (the default: ``"float"`` where this usd-core has
            ``orientationsf``, else ``"half"``), ``"float"`` (``orientationsf``, quatf, plus
            ``orientations`` in half precision for older readers) or ``"half"`` (``orientations``,
            quath, only).
        save_every: save after this many frames (default: no frame count limit).
        max_unsaved_mb: save once the unsaved frames reach this size [MB] (binary files only; a
            text file keeps every frame in memory anyway).
        save_interval: save when this much wall time [s] has passed since the last save.
        wall_size: side length of the wall quads [m]; default twice the diagonal of the bounding
            box of the bodies' initial bounding spheres (1 m when there are no bodies).
    """

    def __init__(
        self,
        path: str | PathLike,
        scene,
        *,
        fps: float = 24.0,
        frame_dt: float | None = None,
        up_axis: str = "Z",
        meters_per_unit: float = 1.0,
        orientation_precision: str = "auto",
        save_every: int | None = None,
        max_unsaved_mb: float = 128.0,
        save_interval: float = 30.0,
        wall_size: float | None = None,
    ):
        self.path = _check_path(path)
        scene = getattr(scene, "scene", scene)  # a Simulation (any front) -> its Scene
        self.fps = _positive("fps", fps)
        self.frame_dt = 1.0 / self.fps if frame_dt is None else _positive("frame_dt", frame_dt)
        axis = str(up_axis).upper()
        if axis not in ("Y", "Z"):
            raise ValueError(f"up_axis must be 'Y' or 'Z', got {up_axis!r}")
        self.up_axis = axis
        self.meters_per_unit = _positive("meters_per_unit", meters_per_unit)
        self._scale = 1.0 / self.meters_per_unit
        if orientation_precision not in ("auto", "half", "float"):
            raise ValueError(f"orientation_precision must be 'auto', 'half' or 'float', got {orientation_precision!r}")
        if save_every is not None and (not isinstance(save_every, int | np.integer) or save_every < 1):
            raise ValueError(f"save_every must be a positive integer or None, got {save_every!r}")
        self.save_every = None if save_every is None else int(save_every)
        self.max_unsaved_mb = _positive("max_unsaved_mb", max_unsaved_mb)
        self.save_interval = _positive("save_interval", save_interval)
        wall_size = None if wall_size is None else _positive("wall_size", wall_size)

        from pxr import Gf, Sdf, Tf, Usd, UsdGeom, Vt

        has_float = hasattr(UsdGeom.PointInstancer, "CreateOrientationsfAttr")
        if orientation_precision == "auto":
            orientation_precision = "float" if has_float else "half"
        if orientation_precision == "float" and not has_float:
            raise ValueError(
                f"this usd-core ({'.'.join(map(str, Usd.GetVersion()))}) has no PointInstancer.orientationsf; "
                "use orientation_precision='half' (or 'auto')"
            )
        self.orientation_precision = orientation_precision
        # The schema's velocities are per second of playback: timeCodesPerSecond = fps time codes,
        # each frame_dt of simulated time.
        self._vel_scale = self._scale * self.frame_dt * self.fps
        self._ang_scale = math.degrees(1.0) * self.frame_dt * self.fps
        self._with_velocities = None  # decided by the first frame

        self.num_bodies = n = int(scene.num_bodies)
        self.body_shape = np.array(scene.body_shape, dtype=np.int32)
        shapes = scene.shapes
        names = scene.shape_names
        self._binary = self.path.suffix.lower() != ".usda"
        self._frame_bytes = n * (12 + 8 + (16 if orientation_precision == "float" else 0) + 24) + 64
        radius = np.array([shapes[s].radius for s in names], dtype=np.float64)
        self._max_radius = float(radius.max()) if len(radius) else 0.0

        # -- the layer
        ident = str(self.path.resolve())
        if Sdf.Layer.Find(ident):
            raise RuntimeError(
                f"{ident} is open in this process (a Usd.Stage or Sdf.Layer still refers to it); "
                "release it before recording to this file"
            )
        self.path.parent.mkdir(parents=True, exist_ok=True)
        args = {"format": "usdc"} if self.path.suffix.lower() == ".usd" else {}
        layer = Sdf.Layer.CreateNew(ident, args)
        if not layer:
            raise RuntimeError(f"cannot create the USD file {ident}")
        self._layer = layer
        stage = self._stage = Usd.Stage.Open(layer)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if axis == "Z" else UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, self.meters_per_unit)
        stage.SetTimeCodesPerSecond(self.fps)
        stage.SetFramesPerSecond(self.fps)
        stage.SetStartTimeCode(0.0)
        stage.SetEndTimeCode(0.0)
        from polydem import __version__

        layer.customLayerData = {
            "polydem:version": __version__,
            "polydem:scene": str(getattr(scene, "name", "")),
            "polydem:frame_dt": self.frame_dt,
            "polydem:shapes_sha256": shapes_digest(scene),
        }
        world = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(world.GetPrim())

        # -- bodies: one PointInstancer, one Mesh prototype per shape
        inst = self._instancer = UsdGeom.PointInstancer.Define(stage, BODIES_PATH)
        protos = UsdGeom.Scope.Define(stage, f"{BODIES_PATH}/Prototypes")
        rel = inst.CreatePrototypesRel()
        used = set()
        for k, name in enumerate(names):
            prim_name = base = Tf.MakeValidIdentifier(name)
            i = 1
            while prim_name in used:
                i += 1
                prim_name = f"{base}_{i}"
            used.add(prim_name)
            mesh = UsdGeom.Mesh.Define(stage, protos.GetPath().AppendChild(prim_name))
            self._author_mesh(mesh, shapes[name].vertices, shapes[name].faces, shapes[name].face_normals)
            mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set([PALETTE[k % len(PALETTE)]])
            mesh.GetPrim().SetCustomDataByKey("polydem:shape", name)
            if hasattr(mesh.GetPrim(), "SetDisplayName"):
                mesh.GetPrim().SetDisplayName(name)
            rel.AddTarget(mesh.GetPath())

        inst.CreateProtoIndicesAttr(Vt.IntArray.FromNumpy(self.body_shape))
        self._pos_attr = inst.CreatePositionsAttr()
        self._ori_attr = inst.CreateOrientationsAttr()
        self._orif_attr = inst.CreateOrientationsfAttr() if orientation_precision == "float" else None
        self._vel_attr = self._angvel_attr = None  # made by the first frame with velocities
        self._extent_attr = inst.CreateExtentAttr()
        self._time_attr = inst.GetPrim().CreateAttribute(TIME_ATTR, Sdf.ValueTypeNames.Double, custom=True)
        # Defaults (shown before the first frame, and where no time sample exists): the scene's poses.
        p0 = np.asarray(scene.body_position, dtype=np.float64).reshape(n, 3)
        q0 = np.asarray(scene.body_orientation, dtype=np.float64).reshape(n, 4)
        self._prev_q = None  # the last frame's orientations (float32), for the sign choice
        self._prev_on_device = False  # whether they are in self._frame.previous instead (record_simulation)
        self._frame = None  # the device arrays record_simulation makes a frame in
        pos, ori, orif, ext = self._convert(p0, q0)
        self._prev_q = None  # the defaults do not count as a frame
        self._pos_attr.Set(pos)
        self._ori_attr.Set(ori)
        if orif is not None:
            self._orif_attr.Set(orif)
        self._extent_attr.Set(ext)

        # -- walls
        if scene.planes:
            if n:
                lo = (p0 - radius[self.body_shape][:, None]).min(axis=0)
                hi = (p0 + radius[self.body_shape][:, None]).max(axis=0)
            else:
                lo = hi = np.zeros(3)
            center = 0.5 * (lo + hi)
            size = wall_size or 2.0 * float(np.linalg.norm(hi - lo)) or 1.0
            UsdGeom.Scope.Define(stage, WALLS_PATH)
            for k, plane in enumerate(scene.planes):
                quad = plane_quad(plane.point, plane.normal, center, 0.5 * size)
                mesh = UsdGeom.Mesh.Define(stage, f"{WALLS_PATH}/plane_{k}")
                self._author_mesh(mesh, quad, [np.arange(4)], np.asarray(plane.normal, dtype=np.float64)[None])
                mesh.CreateDoubleSidedAttr(False)  # seen from outside the box, walls let the view through
                mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set([WALL_COLOR])
                prim = mesh.GetPrim()
                prim.SetCustomDataByKey("polydem:point", Gf.Vec3d(*(np.asarray(plane.point) * self._scale)))
                prim.SetCustomDataByKey("polydem:normal", Gf.Vec3d(*plane.normal))
                prim.SetCustomDataByKey("polydem:material", plane.material)

        # -- mesh walls: the vertices in the wall's frame (origin at its pivot), posed by an Xform op
        # pair; a moving wall gets a time sample per frame from the simulation's mesh_q.
        self._mesh_ops = []
        self._mesh_moving = []
        if scene.mesh_walls:
            UsdGeom.Scope.Define(stage, WALLS_PATH)
        for k, wall in enumerate(scene.mesh_walls):
            v = np.asarray(wall.vertices, dtype=np.float64)
            tri = np.asarray(wall.triangles, dtype=np.int64)
            pivot = np.asarray(wall.pivot, dtype=np.float64)
            normals = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
            normals /= np.maximum(np.linalg.norm(normals, axis=1), 1e-300)[:, None]
            mesh = UsdGeom.Mesh.Define(stage, f"{WALLS_PATH}/mesh_{k}")
            self._author_mesh(mesh, v - pivot, list(tri), normals)
            mesh.CreateDoubleSidedAttr(False)  # the far side of a closed drum shows, the near side lets the view in
            mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set([WALL_COLOR])
            translate = mesh.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble)
            orient = mesh.AddOrientOp(UsdGeom.XformOp.PrecisionDouble)
            translate.Set(Gf.Vec3d(*(pivot * self._scale)))
            orient.Set(Gf.Quatd(1.0, 0.0, 0.0, 0.0))
            self._mesh_ops.append((translate, orient))
            self._mesh_moving.append(bool(wall.moving))
            prim = mesh.GetPrim()
            prim.SetCustomDataByKey("polydem:material", wall.material)
            prim.SetCustomDataByKey("polydem:pivot", Gf.Vec3d(*(pivot * self._scale)))
            prim.SetCustomDataByKey("polydem:velocity", Gf.Vec3d(*(np.asarray(wall.velocity) * self._scale)))
            prim.SetCustomDataByKey("polydem:angular_velocity", Gf.Vec3d(*wall.angular_velocity))
            prim.SetCustomDataByKey("polydem:moving", bool(wall.moving))
            prim.SetCustomDataByKey("polydem:source", str(wall.source))

        self.frames = 0
        self.last_time_code = None
        self._unsaved = 0
        self._closed = False
        self.save()

    # ------------------------------------------------------------------ helpers

    def _author_mesh(self, mesh, vertices, faces, face_normals):
        from pxr import UsdGeom, Vt

        pts = np.asarray(vertices, dtype=np.float64) * self._scale
        counts = np.array([len(f) for f in faces], dtype=np.int32)
        mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(pts, dtype=np.float32)))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(counts))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.concatenate(faces).astype(np.int32)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        normals = np.repeat(np.asarray(face_normals, dtype=np.float32), counts, axis=0)
        mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normals)))
        mesh.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying)
        ext = np.array([pts.min(axis=0), pts.max(axis=0)], dtype=np.float32)
        mesh.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(ext))

    def _convert(self, positions, orientations):
        """Checked numpy poses -> (Vt positions, Vt quath orientations, Vt quatf orientations or None,
        Vt extent) in file units."""

        n = self.num_bodies
        p = np.asarray(positions)
        q = np.asarray(orientations)
        if p.shape != (n, 3):
            raise ValueError(f"positions must have shape ({n}, 3) (one row per body), got {p.shape}")
        if q.shape != (n, 4):
            raise ValueError(f"orientations must have shape ({n}, 4) (quaternions x y z w), got {q.shape}")
        p = p.astype(np.float64, copy=False)
        if self._scale != 1.0:
            p = p * self._scale
        q = q.astype(np.float32)
        norm = np.sqrt(np.einsum("ij,ij->i", q, q))
        q /= np.where(norm > 0.0, norm, 1.0)[:, None]
        if self._prev_q is not None:  # nearest sign to the previous frame: interpolation turns the short way
            q[np.einsum("ij,ij->i", q, self._prev_q) < 0.0] *= -1.0
        self._prev_q = q
        pos, ext = self._positions_to_vt(np.ascontiguousarray(p, dtype=np.float32))
        orif = _quats_to_vt(q, "float") if self.orientation_precision == "float" else None
        return pos, _quats_to_vt(q, "half"), orif, ext

    def _convert_velocities(self, velocities, angular_velocities):
        """Checked (N, 3) velocities [m/s] and angular velocities [rad/s] -> Vt arrays as the schema has them."""
        from pxr import Vt

        n = self.num_bodies
        out = []
        for name, value, scale in (
            ("velocities", velocities, self._vel_scale),
            ("angular_velocities", angular_velocities, self._ang_scale),
        ):
            a = np.asarray(value)
            if a.shape != (n, 3):
                raise ValueError(f"{name} must have shape ({n}, 3) (one row per body), got {a.shape}")
            out.append(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(a * scale, dtype=np.float32)))
        return out

    # ------------------------------------------------------------------ recording

    def time_code(self, time_s: float) -> int:
        """The time code of a frame at simulated time ``time_s`` [s]: ``round(time_s / frame_dt)``."""
        return int(round(float(time_s) / self.frame_dt))

    def record(
        self, time_s: float, positions, orientations, velocities=None, angular_velocities=None, mesh_poses=None
    ) -> int:
        """Write one frame; returns its time code.

        Args:
            time_s: simulated time [s] (>= 0); the time code is ``round(time_s / frame_dt)`` and must
                be larger than the previous frame's.
            positions: (N, 3) centres of mass [m] (``Simulation.state()["body_position"]``).
            orientations: (N, 4) unit quaternions x y z w of the body frames
                (``Simulation.state()["body_orientation"]``).
            velocities, angular_velocities: (N, 3) [m/s] and world-axes [rad/s]
                (``Simulation.state()["body_velocity"]``, ``["body_angular_velocity"]``), both or
                neither; the first frame decides for the whole file.
            mesh_poses: (M, 7) poses of the mesh walls' frames, position [m] and quaternion xyzw
                (``Simulation.current_state.mesh_q``); moving walls get a time sample. Without it a
                wall keeps its initial pose.
        """
        t, code, mesh = self._check_frame(time_s, velocities is not None, angular_velocities is not None, mesh_poses)
        self._pull_previous()
        prev_q = self._prev_q
        try:
            pos, ori, orif, ext = self._convert(positions, orientations)
            vel = self._convert_velocities(velocities, angular_velocities) if velocities is not None else None
        except Exception:
            self._prev_q = prev_q
            raise
        return self._write(t, code, pos, ori, orif, ext, vel, mesh)

    def _check_frame(self, time_s, has_velocities: bool, has_angular: bool, mesh_poses):
        """The checks of a frame before anything of it is converted: (time [s], time code, mesh poses or None)."""
        if self._closed:
            raise RuntimeError(f"the recorder of {self.path} is closed")
        t = float(time_s)
        if not (math.isfinite(t) and t >= 0.0):
            raise ValueError(f"time_s must be a finite time >= 0 s, got {time_s!r}")
        code = self.time_code(t)
        if self.last_time_code is not None and code <= self.last_time_code:
            raise ValueError(
                f"frame at t = {t:.9g} s has time code {code} (round(t / frame_dt), frame_dt = {self.frame_dt:.6g} s), "
                f"not after the previous frame's {self.last_time_code}; record frames at least frame_dt apart "
                "or make frame_dt smaller"
            )
        given = (has_velocities, has_angular)
        if given[0] != given[1]:
            raise ValueError("give both velocities and angular_velocities, or neither")
        if self._with_velocities is not None and given[0] != self._with_velocities:
            raise ValueError(
                "the first frame of this file was recorded "
                + ("with" if self._with_velocities else "without")
                + " velocities: give velocities and angular_velocities to every frame or to none"
            )
        moving = [k for k, m in enumerate(self._mesh_moving) if m]
        mesh = None
        if mesh_poses is not None and moving:
            mesh = np.asarray(mesh_poses, dtype=np.float64)
            if mesh.ndim != 2 or mesh.shape[1] != 7 or len(mesh) < len(self._mesh_moving):
                raise ValueError(
                    f"mesh_poses must have shape ({len(self._mesh_moving)}, 7) (position and quaternion xyzw "
                    f"per mesh wall), got {mesh.shape}"
                )
        return t, code, mesh

    def _write(self, t, code, pos, ori, orif, ext, vel, mesh) -> int:
        """Set one frame's Vt arrays at ``code``, save when due; returns the time code."""
        if vel is not None and self._vel_attr is None:
            self._vel_attr = self._instancer.CreateVelocitiesAttr()
            self._angvel_attr = self._instancer.CreateAngularVelocitiesAttr()
        self._with_velocities = vel is not None
        self._pos_attr.Set(pos, code)
        self._ori_attr.Set(ori, code)
        if orif is not None:
            self._orif_attr.Set(orif, code)
        if vel is not None:
            self._vel_attr.Set(vel[0], code)
            self._angvel_attr.Set(vel[1], code)
        self._extent_attr.Set(ext, code)
        self._time_attr.Set(t, code)
        if mesh is not None:
            from pxr import Gf

            for k in (k for k, m in enumerate(self._mesh_moving) if m):
                p, q = mesh[k, :3] * self._scale, mesh[k, 3:] / np.linalg.norm(mesh[k, 3:])
                self._mesh_ops[k][0].Set(Gf.Vec3d(*p), code)
                self._mesh_ops[k][1].Set(Gf.Quatd(float(q[3]), float(q[0]), float(q[1]), float(q[2])), code)
        self._stage.SetEndTimeCode(float(code))
        self.last_time_code = code
        self.frames += 1
        self._unsaved += 1
        if (
            (self.save_every is not None and self._unsaved >= self.save_every)
            or (self._binary and self._unsaved * self._frame_bytes >= self.max_unsaved_mb * 1e6)
            or _time.monotonic() - self._last_save >= self.save_interval
        ):
            self.save()
        return code

    def record_simulation(self, sim) -> int:
        """Record a :class:`~polydem.Simulation`'s current state (poses and velocities) at ``sim.time``;
        returns the time code.

        The frame is made on the simulation's device in the file's own types (:mod:`polydem.kernels.export`)
        and brought to the host one array at a time, each turned into its USD array at once: the host holds
        the frame once (as the file's arrays) and, briefly, one of its arrays twice, where ``record`` from
        :meth:`Simulation.state` holds it several times over in float64 (what a frame of 1e8 bodies needs).
        Same values as ``record`` given :meth:`Simulation.state`'s four arrays, up to the last bit of the
        quaternions' float32 norm. It keeps 68 bytes a body of device memory for the frame until :meth:`close`."""
        import warp as wp

        from polydem.kernels.export import launch_frame

        if not isinstance(getattr(sim.current_state, "body_q", None), wp.array):
            # A state already on the host (a run over several processes gathers its ranks' on the first).
            st = sim.state()
            return self.record(sim.time, st["body_position"], st["body_orientation"], st["body_velocity"],
                               st["body_angular_velocity"], mesh_poses=self._mesh_poses(sim))  # fmt: skip
        if sim.num_bodies != self.num_bodies:
            raise ValueError(f"the simulation has {sim.num_bodies} bodies, this file {self.num_bodies}")
        t, code, mesh = self._check_frame(sim.time, True, True, self._mesh_poses(sim))
        frame = self._device_frame(sim)
        align = self._prev_q is not None or self._prev_on_device
        if self._prev_q is not None:  # the previous frame came through record(): its signs go to the device
            wp.copy(frame.previous, wp.array(self._prev_q, dtype=wp.vec4f, device=frame.previous.device))
            self._prev_q, self._prev_on_device = None, True
        launch_frame(sim.current_state, sim.model.scalar, frame, scale=self._scale, velocity_scale=self._vel_scale,
                     angular_scale=self._ang_scale, with_velocities=True, align=align)  # fmt: skip
        pos, ext = self._positions_to_vt(frame.position.numpy())
        ori, orif = self._orientations_to_vt(frame.orientation)
        vel = [_vec3f_to_vt(frame.velocity), _vec3f_to_vt(frame.angular_velocity)]
        code = self._write(t, code, pos, ori, orif, ext, vel, mesh)
        wp.copy(frame.previous, frame.orientation)  # only a frame written sets the signs the next one follows
        self._prev_on_device = True
        return code

    def _mesh_poses(self, sim):
        return sim.current_state.mesh_q.numpy()[: sim.model.num_mesh_walls] if sim.model.num_mesh_walls else None

    def _device_frame(self, sim):
        """The device arrays a frame is made in (kept between frames: a frame allocates nothing)."""
        import warp as wp

        device = sim.current_state.body_q.device
        frame = self._frame
        if frame is None or frame.position.device != device:
            self._pull_previous()  # the signs so far stay on the host until the new arrays take them
            n = self.num_bodies
            frame = self._frame = _DeviceFrame(
                previous=wp.zeros(n, dtype=wp.vec4f, device=device),
                position=wp.empty(n, dtype=wp.vec3f, device=device),
                orientation=wp.empty(n, dtype=wp.vec4f, device=device),
                velocity=wp.empty(n, dtype=wp.vec3f, device=device),
                angular_velocity=wp.empty(n, dtype=wp.vec3f, device=device),
            )
        return frame

    def _pull_previous(self) -> None:
        """Before a frame from the host: the previous frame's signs, where record_simulation left them."""
        if self._prev_on_device:
            self._prev_q = self._frame.previous.numpy().copy()
            self._prev_on_device = False

    def _positions_to_vt(self, p: np.ndarray):
        """(N, 3) float32 positions in file units -> (Vt positions, Vt extent)."""
        from pxr import Vt

        ext = np.zeros((2, 3), dtype=np.float32)
        if len(p):
            r = self._max_radius * self._scale
            for k in range(3):  # per column: much faster than min(axis=0) on an (N, 3) array
                ext[0, k], ext[1, k] = p[:, k].min() - r, p[:, k].max() + r
        return Vt.Vec3fArray.FromNumpy(p), Vt.Vec3fArray.FromNumpy(ext)

    def _orientations_to_vt(self, orientation):
        """Device (N,) vec4f unit quaternions xyzw -> (Vt quath, Vt quatf or None), one host copy at a time."""
        q = orientation.numpy()
        orif = _quats_to_vt(q, "float") if self.orientation_precision == "float" else None
        return _quats_to_vt(q, "half"), orif

    def save(self) -> None:
        """Write what has been recorded so far to the file (done automatically; see the class)."""
        if self._closed:
            return
        if not self._layer.Save():
            raise RuntimeError(f"could not save {self.path}")
        self._unsaved = 0
        self._last_save = _time.monotonic()

    def close(self) -> None:
        """Save and release the file; the recorder cannot record afterwards. Calling it again does nothing."""
        if self._closed:
            return
        self.save()
        self._closed = True
        self._instancer = self._pos_attr = self._ori_attr = self._orif_attr = self._extent_attr = None
        self._vel_attr = self._angvel_attr = self._time_attr = None
        self._stage = None
        self._layer = None
        self._prev_q = None
        self._frame, self._prev_on_device = None, False  # the device frame's memory goes back

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> UsdRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()  # also on an exception: the frames recorded so far are kept

    def set_metadata(self, **entries) -> None:
        """Add ``polydem:KEY`` entries to the file's customLayerData (saved with the next save), e.g.
        ``scene_file`` (the scene file's absolute path) or ``default_scene=True``; read them back
        with :func:`read_metadata`."""
        if self._closed:
            raise RuntimeError("the recorder is closed")
        data = dict(self._layer.customLayerData)
        data.update({f"polydem:{key}": value for key, value in entries.items()})
        self._layer.customLayerData = data

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"UsdRecorder({str(self.path)!r}, bodies={self.num_bodies}, frames={self.frames}, {state})"


# ---------------------------------------------------------------------- reading


def _open_instancer(path):
    from pxr import Usd, UsdGeom

    p = Path(os.fspath(path))
    if not p.exists():
        raise FileNotFoundError(f"no such USD file: {p}")
    stage = Usd.Stage.Open(str(p.resolve()))
    if stage is None:
        raise ValueError(f"cannot open {p} as a USD stage")
    inst = UsdGeom.PointInstancer.Get(stage, BODIES_PATH)
    if not inst:
        raise ValueError(f"{p} has no PointInstancer at {BODIES_PATH}; was it written by polydem.usd.UsdRecorder?")
    return stage, inst


def read_frame(path: str | PathLike, time_code: float) -> tuple[np.ndarray, np.ndarray]:
    """Body poses of a file written by :class:`UsdRecorder` at ``time_code``.

    Returns ``(positions, orientations)``: (N, 3) float64 centres of mass in metres (converted with the
    stage's metersPerUnit) and (N, 4) float64 unit quaternions x y z w. At a recorded time code these
    are the recorded frame (to float32, or half for ``orientations``); between time codes USD's
    interpolation applies. Reads ``orientationsf`` where authored (and known to this usd-core), else
    ``orientations``: files of every polydem version read alike.
    """
    from pxr import Usd, UsdGeom

    stage, inst = _open_instancer(path)
    t = Usd.TimeCode(float(time_code))
    pos = np.asarray(inst.GetPositionsAttr().Get(t), dtype=np.float64).reshape(-1, 3)
    attr = inst.GetOrientationsfAttr() if hasattr(inst, "GetOrientationsfAttr") else None
    if attr is None or not attr.HasAuthoredValue():
        attr = inst.GetOrientationsAttr()
    q = _quats_from_vt(attr.Get(t))
    return pos * UsdGeom.GetStageMetersPerUnit(stage), q


def read_time_codes(path: str | PathLike) -> np.ndarray:
    """The time codes of the frames in a file written by :class:`UsdRecorder` (float64, increasing)."""
    _, inst = _open_instancer(path)
    return np.array(inst.GetPositionsAttr().GetTimeSamples(), dtype=np.float64)


def read_velocities(path: str | PathLike, time_code: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Body velocities of a file written by :class:`UsdRecorder` at a recorded ``time_code``.

    Returns ``(velocities, angular_velocities)``: (N, 3) float64 in m/s and rad/s (world axes) of
    simulated time, undoing the file's scaling (see the module docstring); None when the file has no
    velocities (frames recorded without them, or a file of an older polydem).
    """
    from pxr import Usd, UsdGeom

    stage, inst = _open_instancer(path)
    vel_attr, ang_attr = inst.GetVelocitiesAttr(), inst.GetAngularVelocitiesAttr()
    if not (vel_attr.HasAuthoredValue() and ang_attr.HasAuthoredValue()):
        return None
    frame_dt = float(stage.GetRootLayer().customLayerData.get("polydem:frame_dt", 0.0))
    if not frame_dt > 0.0:
        raise ValueError(f"{path} has no polydem:frame_dt in its layer metadata; was it written by UsdRecorder?")
    per_second = frame_dt * stage.GetTimeCodesPerSecond()
    t = Usd.TimeCode(float(time_code))
    v = np.asarray(vel_attr.Get(t), dtype=np.float64).reshape(-1, 3)
    w = np.asarray(ang_attr.Get(t), dtype=np.float64).reshape(-1, 3)
    return v * UsdGeom.GetStageMetersPerUnit(stage) / per_second, np.radians(w) / per_second


def read_metadata(path: str | PathLike) -> dict:
    """The ``polydem:`` entries of a file's customLayerData, without the prefix: ``version``,
    ``scene`` (its name), ``frame_dt``, ``shapes_sha256`` (:func:`shapes_digest` of its scene; not in
    files of polydem before it) and those of :meth:`UsdRecorder.set_metadata`."""
    stage, _ = _open_instancer(path)
    data = stage.GetRootLayer().customLayerData
    return {key[len("polydem:") :]: value for key, value in data.items() if key.startswith("polydem:")}
