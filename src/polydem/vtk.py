"""Write simulation frames as VTK files for ParaView: ``.pvd`` time series of ``.vtu`` frames.

Usage::

    from polydem.vtk import VtkWriter

    sim = polydem.Simulation(scene)
    with VtkWriter("out/vtk", scene) as vtk:
        for _ in range(100):
            vtk.record_simulation(sim)
            sim.step(steps_per_frame)

then open ``out/vtk/particles.pvd`` (and ``centres.pvd``, ``contacts.pvd``) in ParaView. Layout of
the folder (frame ``k`` is the ``k``-th recorded frame, or the index given to :meth:`VtkWriter.record`)::

    particles.pvd                    collection: one entry per frame, with its simulated time
    particles/particles_<k>.vtu      the bodies as their polyhedra, in world coordinates
    centres.pvd, centres/...         one point per body
    contacts.pvd, contacts/...       one line per contact: the force network
    walls.vtu                        the wall planes as quads and the fixed mesh walls' triangles
                                     (written once: they do not move)
    moving_walls.pvd, moving_walls/  the moving mesh walls' triangles at each frame's pose (only
                                     when the scene has moving mesh walls)

``particles``: an unstructured grid of polygon cells (triangles, quads, polygons), one per face of
each body, vertices in world coordinates [m]. Cell data (the face's body): ``body_id``,
``shape_id`` (index in ``Scene.shape_names``), ``kind`` (0 free, 1 fixed, 2 kinematic),
``velocity`` [m/s] and ``angular_velocity`` [rad/s, world axes]. Colour by ``body_id`` or ``velocity``;
Threshold on ``kind`` hides a drum's slabs.

``centres``: one point (and one vertex cell) per body at its centre of mass, with point data
``body_id``, ``shape_id``, ``kind``, ``orientation`` (unit quaternion x, y, z, w of the body's
principal frame), ``velocity`` [m/s], ``angular_velocity`` [rad/s], ``radius`` (the shape's bounding
sphere [m]) and ``equivalent_radius`` (radius of the sphere of the body's volume [m]; for Glyph
spheres of the body's size).

``contacts``: one line cell per contact (``Simulation.contacts()``: the contacts of the frame's
last step, with the forces that step applied), from the centre of body A to the centre of body B, or
to the contact point for a wall contact; each line has two points of its own. Cell data:
``body_a``, ``body_b`` (-1 for a wall), ``wall`` (the plane's index, -1 between bodies), ``normal``
(unit, from A into B or the wall), ``normal_force`` (vector on A [N]: ``-fn * normal``),
``normal_force_magnitude`` (``fn`` [N]), ``tangential_force`` (friction force on A [N]),
``tangential_force_magnitude``, ``force`` (their sum) and ``force_magnitude``, ``overlap_volume``
[m^3], ``contact_point`` [m], and with ``VtkWriter(..., contact_types=True)`` ``contact_type``
(below). Point data ``normal_force_magnitude`` repeats the cell's value at both ends, so that
ParaView's Tube filter can scale the tubes by it (it varies the radius by point scalars): the force
chains. A frame without contacts has one vertex cell instead of lines (meshio cannot read a grid
without cells): a point at body 0's centre with ``body_a``, ``body_b``, ``wall`` and ``contact_type`` -1 and every force
zero, which draws nothing outside the body and no tube.

``contact_type`` (int32; only where the writer was made with ``contact_types=True``, or
``"features"`` or ``"overlap"``): the kind of each contact, by
:func:`polydem.measures.classify_contacts` from the frame's contacts at the frame's poses (``True``
is its default ``method="features"``: what each body presents to the other within 10 degrees of the
contact normal; ``"overlap"``: the overlap's shape; see :mod:`polydem.measures`). The codes
(:data:`CONTACT_TYPES`) are the index into :data:`polydem.measures.KINDS`: 0 face-face,
1 edge-face, 2 vertex-face, 3 edge-edge, and -1 not classified (a vertex against a vertex or an
edge; with ``"overlap"`` also a contact without overlap at the frame's poses, one that opened in the
last step). Wall contacts are classified too, the wall counting as a face: 0, 1 or 2 (the grain's
face, edge or corner on it). A mesh wall counts as the plane of the contact's normal at its depth,
so contacts given without ``normal`` and ``depth`` leave their mesh-wall contacts at -1; a line
that only the average has (``current`` 0: a contact that ended before the frame) is -1 as well.
Threshold on ``contact_type`` shows the force chains of one kind. meshio writes no field data into
``.vtu`` files, so the names are only here. The classification is off by default because of its
host time: for a pile of 1000 cubes with about 2900 contacts, on a 2-core CPU (Warp on ``cpu``), a
frame of all the series takes about 30 ms to write and 90-110 ms with ``contact_types=True``; most
of the difference is the float64 overlap and depth of each pair, computed again on the writer's
Warp device (``device``; for a :class:`~polydem.Simulation`, its device).

With the forces averaged over the time before the frame (``Simulation.contact_average()``, given
as ``average``; ``polydem run`` averages over each interval between frames), the frame also has a
line for each contact that ended in that interval, and the cell data ``current`` (1: a contact of
the frame's last step, 0: one that only the average has; its instantaneous fields are zero and a
wall contact's line ends at its mean point), ``mean_force`` (vector on A [N]: the impulse over the
interval divided by its length) and ``mean_force_magnitude``, ``mean_normal_force`` (vector on A
[N]), ``mean_normal_force_magnitude`` (the mean of ``fn`` [N]), ``mean_tangential_force`` [N] and
``contact_time`` (time in contact in the interval [s]); point data ``mean_normal_force_magnitude``
as above, for tubes of the averaged force chains.

The ``.pvd`` files are rewritten (atomically) after every frame, so an interrupted run leaves a
valid series of the frames so far. ``meshio`` writes the ``.vtu`` files (binary, zlib-compressed;
empty ones uncompressed); it is imported only when a writer is made. BENCHMARKS.md gives the time
and bytes per frame.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from os import PathLike
from pathlib import Path

import numpy as np

from polydem.measures import KINDS, Grains, classify_contacts

__all__ = ["CONTACT_TYPES", "SERIES", "VtkWriter", "read_pvd"]

SERIES = ("particles", "centres", "contacts")
"""The time series a :class:`VtkWriter` writes, each as ``<name>.pvd`` and ``<name>/<name>_<k>.vtu``."""

WALLS_FILE = "walls.vtu"

CONTACT_TYPES = {-1: "unclassified", **dict(enumerate(KINDS))}
"""The codes of the contacts' ``contact_type`` cell data and their names: -1 "unclassified", then
the index into :data:`polydem.measures.KINDS` (0 "face-face", 1 "edge-face", 2 "vertex-face",
3 "edge-edge")."""

_METHODS = ("features", "overlap")

_MESHIO_TYPES = {3: "triangle", 4: "quad"}  # other face sizes are "polygon"


def read_pvd(path: str | PathLike) -> list[tuple[float, Path]]:
    """The ``(time, file)`` entries of a ``.pvd`` collection, files as absolute paths, in file order."""
    p = Path(os.fspath(path))
    root = ET.parse(p).getroot()
    if root.tag != "VTKFile" or root.get("type") != "Collection":
        raise ValueError(f"{p} is not a VTK collection (.pvd) file")
    return [(float(d.get("timestep")), p.parent / d.get("file")) for d in root.iter("DataSet")]


def _write_pvd(path: Path, entries) -> None:
    """ParaView collection of ``(time, relative file)`` entries, written to a temporary file and
    moved into place: a reader never sees half a file."""
    root = ET.Element("VTKFile", type="Collection", version="0.1", byte_order="LittleEndian")
    coll = ET.SubElement(root, "Collection")
    for t, name in entries:
        ET.SubElement(coll, "DataSet", timestep=repr(float(t)), group="", part="0", file=name)
    ET.indent(root)
    tmp = path.with_name(path.name + ".tmp")
    try:
        ET.ElementTree(root).write(tmp, encoding="utf-8", xml_declaration=True)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _index_type(count: int):
    """Connectivity in int32 where it fits: half the bytes to compress and write."""
    return np.int32 if count < 2**31 else np.int64


def _write_vtu(meshio, path: Path, points, cells, point_data=None, cell_data=None) -> None:
    cells = [(kind, np.asarray(c, dtype=_index_type(len(points)))) for kind, c in cells]
    mesh = meshio.Mesh(points, cells, point_data=point_data or {}, cell_data=cell_data or {})
    empty = len(points) == 0 or sum(len(c[1]) for c in cells) == 0
    # Empty arrays stay uncompressed: the plain form of an empty array, not a zlib header of zero blocks.
    tmp = path.with_name(path.name + ".tmp")
    try:
        meshio.write(tmp, mesh, file_format="vtu", compression=None if empty else "zlib")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


class VtkWriter:
    """Write the frames of a run as ``.vtu`` files with ``.pvd`` series (see the module docstring).

    Args:
        folder: output folder (made if missing); files of an earlier run in it are overwritten.
        scene: the :class:`~polydem.Scene`, or a :class:`~polydem.Simulation` (its scene is used).
        resume: continue the series already in ``folder`` (a resumed run): the entries of its
            ``.pvd`` files before the first frame recorded now are kept (where their files exist).
            Otherwise the series start empty.
        wall_size: side length of the wall quads [m]; default as :class:`polydem.usd.UsdRecorder`
            (twice the diagonal of the bounding box of the bodies' initial bounding spheres).
        contact_types: write the contacts' ``contact_type`` cell data (module docstring): True or
            "features" classifies by the features the bodies present, "overlap" by the overlap's
            shape (:func:`polydem.measures.classify_contacts`'s ``method``). False (the default)
            leaves the array out: the classification takes two to three times as long as writing
            the frame.
        device: Warp device of the classification's pair geometry; default the simulation's where
            ``scene`` is a :class:`~polydem.Simulation` (and at :meth:`record_simulation`), else
            Warp's default device.
    """

    def __init__(
        self,
        folder: str | PathLike,
        scene,
        *,
        resume: bool = False,
        wall_size: float | None = None,
        contact_types: bool | str = False,
        device=None,
    ):
        import meshio  # noqa: F401  (fail here, before any frame, if it is missing)

        if contact_types is True:
            contact_types = "features"
        if contact_types not in (False, None, *_METHODS):
            raise ValueError(f"contact_types must be True, False, 'features' or 'overlap', got {contact_types!r}")
        self.contact_types = contact_types or None
        """How the contacts' ``contact_type`` is classified ("features" or "overlap"), None: not written."""
        model = getattr(scene, "model", None)
        self._device = device if device is not None else getattr(model, "device", None)
        scene = getattr(scene, "scene", scene)  # a Simulation (any front) -> its Scene
        self._mesh_walls = list(getattr(scene, "mesh_walls", ()))
        self._num_planes = len(scene.planes)
        self._moving = [k for k, w in enumerate(self._mesh_walls) if w.moving]
        self._series = SERIES + (("moving_walls",) if self._moving else ())
        self.folder = Path(os.fspath(folder))
        if self.folder.exists() and not self.folder.is_dir():
            raise ValueError(f"cannot write VTK files to {self.folder}: it is a file, not a folder")
        self.num_bodies = n = int(scene.num_bodies)
        self.body_shape = np.array(scene.body_shape, dtype=np.int32).reshape(n)
        self.body_kind = np.array(scene.body_kind, dtype=np.int32).reshape(n)
        names = scene.shape_names
        shapes = [scene.shapes[s] for s in names]
        self._shapes = shapes
        radius = np.array([s.radius for s in shapes], dtype=np.float64)
        eq_radius = np.array([(3.0 * s.volume / (4.0 * math.pi)) ** (1.0 / 3.0) for s in shapes], dtype=np.float64)
        self._radius = radius[self.body_shape] if n else np.zeros(0)
        self._eq_radius = eq_radius[self.body_shape] if n else np.zeros(0)
        # The planes as polydem.measures.Grains takes them, for the wall contacts' types.
        self._plane_normal = np.array([pl.normal for pl in scene.planes], dtype=np.float64).reshape(-1, 3)
        self._plane_offset = np.array([np.dot(pl.normal, pl.point) for pl in scene.planes], dtype=np.float64)
        # Per shape: the bodies of that shape and its faces grouped by size, so that a frame is a few
        # numpy operations per (shape, face size) whatever the number of bodies.
        self._groups = []
        for k, shape in enumerate(shapes):
            bodies = np.flatnonzero(self.body_shape == k)
            if not len(bodies):
                continue
            by_size: dict[int, list] = {}
            for f in shape.faces:
                by_size.setdefault(len(f), []).append(np.asarray(f, dtype=np.int64))
            faces = {size: np.array(fs) for size, fs in sorted(by_size.items())}
            self._groups.append((bodies, np.asarray(shape.vertices, dtype=np.float64), faces))
        self.paths = {name: self.folder / f"{name}.pvd" for name in self._series}
        self._entries: dict[str, list] = {name: [] for name in self._series}
        self._resume = bool(resume)
        self.frames = 0
        self.last_index = None
        self.last_time = None
        self._closed = False
        self.folder.mkdir(parents=True, exist_ok=True)
        for name in self._series:
            (self.folder / name).mkdir(exist_ok=True)
            if not self._resume:  # no series of an earlier run in this folder stays listed
                _write_pvd(self.paths[name], [])
        self.walls_path = None
        if scene.planes or len(self._moving) < len(self._mesh_walls):
            self.walls_path = self.folder / WALLS_FILE
            self._write_walls(scene, radius, wall_size)

    # ------------------------------------------------------------------ files

    def _write_walls(self, scene, radius, wall_size) -> None:
        import meshio

        from polydem.usd import plane_quad

        n = self.num_bodies
        p0 = np.asarray(scene.body_position, dtype=np.float64).reshape(n, 3)
        if n:
            r = radius[self.body_shape][:, None]
            lo, hi = (p0 - r).min(axis=0), (p0 + r).max(axis=0)
        else:
            lo = hi = np.zeros(3)
        size = wall_size or 2.0 * float(np.linalg.norm(hi - lo)) or 1.0
        quads = [plane_quad(p.point, p.normal, 0.5 * (lo + hi), 0.5 * size) for p in scene.planes]
        k = len(quads)
        points = [np.concatenate(quads)] if k else []
        cells, walls, normals = [], [], []
        if k:
            cells.append(("quad", np.arange(4 * k, dtype=np.int64).reshape(k, 4)))
            walls.append(np.arange(k, dtype=np.int32))
            normals.append(np.array([p.normal for p in scene.planes], dtype=np.float32))
        fixed = [w for w in range(len(self._mesh_walls)) if w not in self._moving]
        if fixed:
            pts, tri, wall, normal = self._mesh_triangles(fixed, None)
            points.append(pts)
            cells.append(("triangle", tri + 4 * k))
            walls.append(wall)
            normals.append(normal)
        _write_vtu(
            meshio,
            self.walls_path,
            np.concatenate(points).astype(np.float32),
            cells,
            cell_data={"wall": walls, "normal": normals},
        )

    def _mesh_triangles(self, walls, mesh_poses):
        """(points, triangles, wall index, unit normal) of the mesh walls ``walls`` at ``mesh_poses``
        ((M, 7) pivot positions and quaternions xyzw; None: their t = 0 pose). The wall index counts
        after the planes (mesh wall w is ``P + w``)."""
        from polydem.quaternions import quat_to_matrix

        points, tris, index, normals = [], [], [], []
        base = 0
        for w in walls:
            wall = self._mesh_walls[w]
            v = np.asarray(wall.vertices, dtype=np.float64)
            if mesh_poses is not None and wall.moving:
                pose = np.asarray(mesh_poses[w], dtype=np.float64)
                rot = quat_to_matrix(pose[3:] / np.linalg.norm(pose[3:]))
                v = (v - np.asarray(wall.pivot, dtype=np.float64)) @ rot.T + pose[:3]
            t = np.asarray(wall.triangles, dtype=np.int64)
            n = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
            n /= np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
            points.append(v)
            tris.append(t + base)
            index.append(np.full(len(t), self._num_planes + w, dtype=np.int32))
            normals.append(n.astype(np.float32))
            base += len(v)
        return (np.concatenate(points), np.concatenate(tris), np.concatenate(index), np.concatenate(normals))

    def _previous_entries(self, name: str, time_s: float) -> list:
        """Entries of an existing ``.pvd`` before ``time_s`` whose files exist (for ``resume``)."""
        path = self.paths[name]
        if not path.is_file():
            return []
        try:
            entries = read_pvd(path)
        except (ET.ParseError, ValueError, TypeError):
            return []  # not a collection we can continue: the series starts again
        keep = []
        for t, file in entries:
            if t < time_s and file.is_file():
                keep.append((t, file.relative_to(self.folder).as_posix()))
        return keep

    # ------------------------------------------------------------------ recording

    def record(
        self, time_s: float, state: dict, contacts: dict, index: int | None = None, mesh_poses=None, average=None
    ) -> int:
        """Write one frame of every series; returns its index.

        Args:
            time_s: simulated time [s], the frame's time in the ``.pvd`` files.
            state: ``Simulation.state()``: ``body_position``, ``body_orientation``, ``body_velocity``,
                ``body_angular_velocity``.
            contacts: ``Simulation.contacts()`` at the same state.
            index: the frame's number in the file names (``particles_<index>.vtu``); default the
                previous frame's plus one (0 for the first). Must increase from frame to frame.
            mesh_poses: (M, 7) poses of the mesh walls' frames (pivot position [m], quaternion xyzw;
                ``Simulation.current_state.mesh_q``) for the moving walls' series; None: their
                initial pose.
            average: ``Simulation.contact_average()`` over the time before the frame: the contacts file
                gets the averaged fields (module docstring); an empty dict: an interval without a step
                (the fields, all zero). None: no averaged fields.
        """
        import meshio

        if self._closed:
            raise RuntimeError(f"the VTK writer of {self.folder} is closed")
        t = float(time_s)
        if not math.isfinite(t):
            raise ValueError(f"time_s must be a finite time, got {time_s!r}")
        k = (0 if self.last_index is None else self.last_index + 1) if index is None else int(index)
        if k < 0 or (self.last_index is not None and k <= self.last_index):
            raise ValueError(f"frame index {k} must be >= 0 and larger than the previous frame's ({self.last_index})")
        n = self.num_bodies
        x = np.asarray(state["body_position"], dtype=np.float64).reshape(n, 3)
        q = np.asarray(state["body_orientation"], dtype=np.float64).reshape(n, 4)
        v = np.asarray(state["body_velocity"], dtype=np.float64).reshape(n, 3)
        w = np.asarray(state["body_angular_velocity"], dtype=np.float64).reshape(n, 3)
        norm = np.linalg.norm(q, axis=1, keepdims=True)
        q = q / np.where(norm > 0.0, norm, 1.0)
        if self.frames == 0 and self._resume:
            for name in self._series:
                self._entries[name] = self._previous_entries(name, t)
        files = {name: f"{name}/{name}_{k:06d}.vtu" for name in self._series}
        self._write_particles(meshio, self.folder / files["particles"], x, q, v, w)
        self._write_centres(meshio, self.folder / files["centres"], x, q, v, w)
        self._write_contacts(meshio, self.folder / files["contacts"], x, q, contacts, average)
        if self._moving:
            if mesh_poses is not None:
                mesh_poses = np.asarray(mesh_poses, dtype=np.float64)
                if mesh_poses.ndim != 2 or mesh_poses.shape[1] != 7 or len(mesh_poses) < len(self._mesh_walls):
                    raise ValueError(
                        f"mesh_poses must have shape ({len(self._mesh_walls)}, 7) (position and quaternion xyzw "
                        f"per mesh wall), got {mesh_poses.shape}"
                    )
            pts, tri, wall, normal = self._mesh_triangles(self._moving, mesh_poses)
            _write_vtu(
                meshio,
                self.folder / files["moving_walls"],
                pts.astype(np.float32),
                [("triangle", tri)],
                cell_data={"wall": [wall], "normal": [normal]},
            )
        for name in self._series:
            self._entries[name].append((t, files[name]))
            _write_pvd(self.paths[name], self._entries[name])
        self.frames += 1
        self.last_index = k
        self.last_time = t
        return k

    def record_simulation(self, sim, index: int | None = None) -> int:
        """Record a :class:`~polydem.Simulation`'s current state and contacts at ``sim.time``, with its
        contact-force average where one is running (``sim.start_contact_average()``; start it again
        after each frame for an average over each interval between frames)."""
        m = sim.model.num_mesh_walls
        mesh = sim.current_state.mesh_q.numpy()[:m] if m else None
        self._device = getattr(sim.model, "device", self._device)
        steps = sim.contact_average_steps
        average = None if steps is None else sim.contact_average() if steps > 0 else {}
        return self.record(sim.time, sim.state(), sim.contacts(), index, mesh_poses=mesh, average=average)

    def _write_particles(self, meshio, path, x, q, v, w) -> None:
        from polydem.quaternions import quat_to_matrix

        rot = quat_to_matrix(q) if len(q) else np.zeros((0, 3, 3))
        points, cells, data = (
            [],
            [],
            {"body_id": [], "shape_id": [], "kind": [], "velocity": [], "angular_velocity": []},
        )
        start = 0
        for bodies, verts, faces in self._groups:
            nv = len(verts)
            world = np.einsum("bij,vj->bvi", rot[bodies], verts) + x[bodies, None, :]  # (m, nv, 3)
            points.append(world.reshape(-1, 3))
            base = start + nv * np.arange(len(bodies), dtype=np.int64)
            for size, f in faces.items():
                conn = (base[:, None, None] + f[None, :, :]).reshape(-1, size)  # body-major: body b's faces in a row
                owner = np.repeat(bodies, len(f))
                cells.append((_MESHIO_TYPES.get(size, "polygon"), conn))
                data["body_id"].append(owner.astype(np.int32))
                data["shape_id"].append(self.body_shape[owner])
                data["kind"].append(self.body_kind[owner])
                data["velocity"].append(v[owner].astype(np.float32))
                data["angular_velocity"].append(w[owner].astype(np.float32))
            start += nv * len(bodies)
        pts = np.concatenate(points).astype(np.float32) if points else np.zeros((0, 3), np.float32)
        if not cells:
            cells = [("polygon", np.zeros((0, 3), dtype=np.int64))]
            data = {key: [np.zeros((0, 3) if "velocity" in key else 0, np.float32)] for key in data}
        _write_vtu(meshio, path, pts, cells, cell_data=data)

    def _write_centres(self, meshio, path, x, q, v, w) -> None:
        n = self.num_bodies
        _write_vtu(
            meshio,
            path,
            x.astype(np.float32),
            [("vertex", np.arange(n, dtype=np.int64).reshape(n, 1))],
            point_data={
                "body_id": np.arange(n, dtype=np.int32),
                "shape_id": self.body_shape,
                "kind": self.body_kind,
                "orientation": q.astype(np.float32),
                "velocity": v.astype(np.float32),
                "angular_velocity": w.astype(np.float32),
                "radius": self._radius.astype(np.float32),
                "equivalent_radius": self._eq_radius.astype(np.float32),
            },
        )

    def _contact_kinds(self, x, q, contacts, a, b) -> np.ndarray:
        """(C,) int32 ``contact_type`` of the contacts ``a``, ``b`` at the poses ``x``, ``q`` (-1 where
        not classified; module docstring)."""
        kind = np.full(len(a), -1, dtype=np.int32)
        # A mesh wall's contact needs its normal and depth (the wall counts as that plane at that depth).
        mesh_ok = "depth" in contacts and "normal" in contacts
        rows = np.arange(len(a)) if mesh_ok else np.flatnonzero(b >= -self._num_planes)
        if not len(rows) or not self.num_bodies:
            return kind
        grains = Grains(
            self._shapes,
            self.body_shape,
            x,
            q,
            plane_normal=self._plane_normal,
            plane_offset=self._plane_offset,
        )
        sub = {"body_a": a[rows], "body_b": b[rows]}
        for key, width in (("normal", 3), ("depth", 1)):
            if key in contacts:
                values = np.asarray(contacts[key], dtype=np.float64).reshape(len(a), width)[rows]
                sub[key] = values if width == 3 else values[:, 0]
        types = classify_contacts(grains, sub, method=self.contact_types, device=self._device)
        kind[rows] = types.kind
        return kind

    def _write_contacts(self, meshio, path, x, q, contacts, average=None) -> None:
        a = np.asarray(contacts["body_a"], dtype=np.int64)
        b = np.asarray(contacts["body_b"], dtype=np.int64)
        m = len(a)
        kind = None if self.contact_types is None else self._contact_kinds(x, q, contacts, a, b)
        normal = np.asarray(contacts["normal"], dtype=np.float64).reshape(m, 3)
        point = np.asarray(contacts["point"], dtype=np.float64).reshape(m, 3)
        fn = np.asarray(contacts["normal_force"], dtype=np.float64).reshape(m)
        ft = np.asarray(contacts["tangential_force"], dtype=np.float64).reshape(m, 3)
        volume = np.asarray(contacts["volume"], dtype=np.float64).reshape(m)
        mean = None
        if average is not None:
            # The union of the frame's contacts and the averaged ones: the frame's first, in their
            # order, then those that ended in the interval; each row gets both kinds of field.
            avg_a = np.asarray(average.get("body_a", np.zeros(0)), dtype=np.int64)
            avg_b = np.asarray(average.get("body_b", np.zeros(0)), dtype=np.int64)
            k = len(avg_a)

            def column(name, width):
                return np.asarray(average.get(name, np.zeros((0, width))), dtype=np.float64).reshape(k, width)

            row = {(int(i), int(j)): r for r, (i, j) in enumerate(zip(a.tolist(), b.tolist(), strict=True))}
            where = np.array([row.get((int(i), int(j)), -1) for i, j in zip(avg_a, avg_b, strict=True)], dtype=np.int64)
            extra = np.flatnonzero(where < 0)
            where[extra] = m + np.arange(len(extra))
            total = m + len(extra)
            a = np.concatenate([a, avg_a[extra]])
            b = np.concatenate([b, avg_b[extra]])
            mean_point = column("point", 3)
            point = np.concatenate([point, mean_point[extra]])
            normal = np.concatenate([normal, np.zeros((len(extra), 3))])
            fn = np.concatenate([fn, np.zeros(len(extra))])
            ft = np.concatenate([ft, np.zeros((len(extra), 3))])
            volume = np.concatenate([volume, np.zeros(len(extra))])
            if kind is not None:  # an ended contact: not classified
                kind = np.concatenate([kind, np.full(len(extra), -1, dtype=np.int32)])
            mean = {"current": (np.arange(total) < m).astype(np.int32)}
            for name, src, width in (
                ("mean_force", "force", 3),
                ("mean_tangential_force", "tangential_force", 3),
                ("mean_normal_force_magnitude", "normal_force", 1),
                ("contact_time", "contact_time", 1),
            ):
                values = np.zeros((total, width))
                values[where] = column(src, width)
                mean[name] = values if width == 3 else values[:, 0]
            mean["mean_normal_force"] = mean["mean_force"] - mean["mean_tangential_force"]
            m = total
        wall = b < 0
        end = np.where(wall[:, None], point, x[np.maximum(b, 0)])
        ends = np.stack([x[a], end], axis=1).reshape(-1, 3)
        f_n = -fn[:, None] * normal  # on A: the overlap pushes A away from B (normal points from A into B)
        force = f_n + ft

        def f32(values):
            return np.asarray(values, dtype=np.float32)

        point_data = {"normal_force_magnitude": f32(np.repeat(fn, 2))}
        extra_cells = {}
        if mean is not None:
            point_data["mean_normal_force_magnitude"] = f32(np.repeat(mean["mean_normal_force_magnitude"], 2))
            extra_cells = {
                "current": [mean["current"]],
                "mean_force": [f32(mean["mean_force"])],
                "mean_force_magnitude": [f32(np.linalg.norm(mean["mean_force"], axis=1))],
                "mean_normal_force": [f32(mean["mean_normal_force"])],
                "mean_normal_force_magnitude": [f32(mean["mean_normal_force_magnitude"])],
                "mean_tangential_force": [f32(mean["mean_tangential_force"])],
                "contact_time": [f32(mean["contact_time"])],
            }
        points = f32(ends)
        cells = [("line", np.arange(2 * m, dtype=np.int64).reshape(m, 2))]
        cell_data = {
            "body_a": [a.astype(np.int32)],
            "body_b": [np.where(wall, -1, b).astype(np.int32)],
            "wall": [np.where(wall, -1 - b, -1).astype(np.int32)],
            "normal": [f32(normal)],
            "normal_force": [f32(f_n)],
            "normal_force_magnitude": [f32(fn)],
            "tangential_force": [f32(ft)],
            "tangential_force_magnitude": [f32(np.linalg.norm(ft, axis=1))],
            "force": [f32(force)],
            "force_magnitude": [f32(np.linalg.norm(force, axis=1))],
            "overlap_volume": [f32(volume)],
            "contact_point": [f32(point)],
            **extra_cells,
        }
        if kind is not None:
            cell_data["contact_type"] = [kind.astype(np.int32)]
        if m == 0:
            # meshio cannot read a grid without cells back (its reader looks up the first cell's type),
            # so a frame without contacts holds one vertex cell instead: at body 0's centre, hidden
            # inside it, with body_a = body_b = wall = -1 and zero forces; the contacts are the lines.
            points = f32(x[:1]) if len(x) else np.zeros((1, 3), dtype=np.float32)
            cells = [("vertex", np.zeros((1, 1), dtype=np.int64))]
            cell_data = {key: [np.zeros((1, *v[0].shape[1:]), dtype=v[0].dtype)] for key, v in cell_data.items()}
            for key in ("body_a", "body_b", "wall", "contact_type"):
                if key in cell_data:
                    cell_data[key][0][:] = -1
            point_data = {key: np.zeros(1, dtype=np.float32) for key in point_data}
        _write_vtu(meshio, path, points, cells, point_data=point_data, cell_data=cell_data)

    # ------------------------------------------------------------------ the end

    @property
    def files(self) -> list[Path]:
        """The files to open: the ``.pvd`` series, and ``walls.vtu`` when the scene has walls."""
        out = [self.paths[name] for name in self._series]
        if self.walls_path is not None:
            out.append(self.walls_path)
        return out

    def close(self) -> None:
        """Nothing is pending (every frame rewrites the ``.pvd`` files); no frames can follow."""
        self._closed = True

    @property
    def closed(self) -> bool:
        return self._closed

    def __enter__(self) -> VtkWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        state = "closed" if self._closed else "open"
        return f"VtkWriter({str(self.folder)!r}, bodies={self.num_bodies}, frames={self.frames}, {state})"
