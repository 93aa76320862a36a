"""Pictures of a state: a Warp ray caster for instanced convex polyhedra, and a small PNG writer.

``render`` casts one ray per pixel from a pinhole camera (see :class:`Camera`) on the CPU or a
GPU: a BVH over the bodies' bounding spheres culls, then the ray is clipped exactly by each
candidate's face planes (kernels in :mod:`polydem.kernels.raycast`); the nearest hit wins.
Bodies are coloured by shape index from :data:`PALETTE` and lit by one directional light
(Lambert, ambient, optional shadow rays); the scene's walls are drawn as infinite planes with a
light checker, seen from their simulated side only. ``save_png`` writes the image with the
standard library (zlib), so no imaging package is needed; ``render_simulation`` does both for a
:class:`~polydem.Simulation`::

    sim = polydem.Simulation(scene, device="cpu")
    sim.step(2000)
    render_simulation(sim, "frame.png", width=800, height=600)
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from os import PathLike
from pathlib import Path

import numpy as np
import warp as wp

from polydem.compound import expand_bodies
from polydem.kernels.raycast import launch_raycast
from polydem.picture_memory import PictureSizeError, check_picture_size
from polydem.quaternions import quat_to_matrix
from polydem.scene.bodies import BodyKind
from polydem.shapeset import ShapeSet

__all__ = [
    "Camera",
    "FIXED_COLOR",
    "PALETTE",
    "PictureSizeError",
    "check_picture",
    "render",
    "render_layers",
    "render_simulation",
    "save_png",
]

PALETTE = np.array(
    [
        (0.894, 0.455, 0.196),  # orange
        (0.259, 0.522, 0.776),  # blue
        (0.376, 0.690, 0.376),  # green
        (0.847, 0.306, 0.365),  # rose
        (0.580, 0.455, 0.773),  # violet
        (0.925, 0.769, 0.275),  # yellow
        (0.302, 0.725, 0.722),  # teal
        (0.871, 0.529, 0.706),  # pink
        (0.608, 0.475, 0.353),  # brown
        (0.553, 0.600, 0.655),  # slate
    ]
)
"""RGB in [0, 1] of shape index ``s``: ``PALETTE[s % len(PALETTE)]``."""

FIXED_COLOR = (0.74, 0.74, 0.72)
"""RGB of fixed and kinematic bodies (containers, drums) in :func:`render_simulation`."""

CUTAWAY_PIXELS = 240
"""Longer side [pixels] of the small pictures in which :func:`render_simulation` looks for the
container bodies that hide free bodies."""


def _unit(v, what="vector") -> np.ndarray:
    v = np.asarray(v, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n == 0.0:
        raise ValueError(f"{what} must be a finite non-zero 3-vector, got {v.tolist()}")
    return v / n


def _perpendicular_basis(up) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors e1, e2 with (e1, e2, up) right-handed; e1 = x, e2 = y for up = z."""
    up = _unit(up, "up")
    axis = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = _unit(axis - up * np.dot(axis, up))
    return e1, np.cross(up, e1)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera looking from ``position`` at ``target`` [m].

    ``up`` fixes the roll (the image's up is ``up`` made perpendicular to the view direction);
    ``fov`` is the vertical field of view [degrees]; the horizontal one follows from the aspect
    ratio. The ray of pixel (row i, column j) of a W x H image goes through the pixel's centre:
    direction ``forward + u tan(fov_x/2) right + v tan(fov/2) up`` with ``u = 2 (j + 0.5) / W - 1``,
    ``v = 1 - 2 (i + 0.5) / H`` (row 0 is the top of the image).
    """

    position: tuple
    target: tuple
    up: tuple = (0.0, 0.0, 1.0)
    fov: float = 35.0

    def __post_init__(self):
        for name in ("position", "target", "up"):
            v = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"camera {name} must be 3 finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, tuple(float(x) for x in v))
        if not 0.0 < float(self.fov) < 180.0:
            raise ValueError(f"camera fov must be in (0, 180) degrees, got {self.fov!r}")
        object.__setattr__(self, "fov", float(self.fov))
        self.frame()  # checks that position != target and up is not along the view

    def frame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(eye, forward, right, up) in float64; the last three unit and orthogonal."""
        eye = np.array(self.position)
        forward = _unit(np.array(self.target) - eye, "camera target - position")
        right = np.cross(forward, np.array(self.up))
        if np.linalg.norm(right) < 1e-9 * np.linalg.norm(self.up):
            raise ValueError(f"camera up {self.up} is parallel to the view direction {forward.tolist()}")
        right = _unit(right)
        return eye, forward, right, np.cross(right, forward)

    def tangents(self, width: int, height: int) -> tuple[float, float]:
        """Tangents of the horizontal and vertical half fields of view."""
        ty = math.tan(math.radians(0.5 * self.fov))
        return ty * width / height, ty

    def kernel_basis(self, width: int, height: int):
        """(eye, forward, right * tan_x, up * tan_y), as the ray-casting kernel takes them."""
        eye, forward, right, up = self.frame()
        tx, ty = self.tangents(width, height)
        return eye, forward, right * tx, up * ty

    def ray_directions(self, width: int, height: int) -> np.ndarray:
        """(H, W, 3) float64 unit directions of the pixels' rays (all leave ``position``)."""
        eye, forward, right, up = self.kernel_basis(width, height)
        u = 2.0 * (np.arange(width) + 0.5) / width - 1.0
        v = 1.0 - 2.0 * (np.arange(height) + 0.5) / height
        d = forward + u[None, :, None] * right + v[:, None, None] * up
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def project(self, points, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Image positions of world points: ((n, 2) [column, row] in pixels, (n,) depth [m]).

        Pixel (row i, column j) covers ``[j, j+1) x [i, i+1)``; its centre is at (j + 0.5, i + 0.5).
        The depth is the distance along the view direction (negative behind the camera).
        """
        eye, forward, right, up = self.frame()
        tx, ty = self.tangents(width, height)
        rel = np.asarray(points, dtype=np.float64).reshape(-1, 3) - eye
        z = rel @ forward
        with np.errstate(divide="ignore", invalid="ignore"):
            u = (rel @ right) / (z * tx)
            v = (rel @ up) / (z * ty)
        return np.column_stack([0.5 * (u + 1.0) * width, 0.5 * (1.0 - v) * height]), z

    @classmethod
    def frame_box(
        cls,
        lower,
        upper,
        width: int,
        height: int,
        *,
        up=(0.0, 0.0, 1.0),
        azimuth: float = -60.0,
        elevation: float = 50.0,
        fov: float = 35.0,
        margin: float = 1.06,
    ) -> Camera:
        """A camera that sees the whole box [lower, upper] from a raised oblique direction.

        The view direction comes from ``azimuth`` (degrees about ``up``, 0 along the first axis
        perpendicular to up: x for up = z) and ``elevation`` (degrees above the horizontal, from -90,
        a view from straight below, to 90, from straight above); the box is centred in the image and
        its corners fill it up to ``margin``. The image's horizontal axis is perpendicular to the
        azimuth's direction, so a top view keeps the roll of the views just below it.
        """
        lo = np.asarray(lower, dtype=np.float64).reshape(3)
        hi = np.asarray(upper, dtype=np.float64).reshape(3)
        up_v = _unit(up, "up")
        e1, e2 = _perpendicular_basis(up_v)
        az, el = math.radians(azimuth), math.radians(elevation)
        if not (math.isfinite(azimuth) and math.isfinite(elevation) and -90.0 <= elevation <= 90.0):
            raise ValueError(f"azimuth must be finite and elevation in [-90, 90] degrees, got {azimuth}, {elevation}")
        back = math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(el) * up_v
        forward = -back
        # forward x up, normalised, for any elevation below 90 degrees; defined at +-90 as well, where
        # forward is along up and the cross product vanishes.
        right = _unit(-math.sin(az) * e1 + math.cos(az) * e2)
        cam_up = np.cross(right, forward)
        ty = math.tan(math.radians(0.5 * fov)) / margin
        tx = ty * width / height
        corners = np.array([[(hi if k >> a & 1 else lo)[a] for a in range(3)] for k in range(8)])
        size = max(float(np.linalg.norm(hi - lo)), 1e-9)
        target = 0.5 * (lo + hi)

        def distance(t):
            rel = corners - t
            x, y, z = rel @ right, rel @ cam_up, rel @ forward
            need = np.maximum(np.abs(x) / tx, np.abs(y) / ty) - z
            return max(float(need.max()), float((-z).max()) + 1e-3 * size, 1e-6 * size)

        for _ in range(4):  # centre the projected box: shift the target in the image plane
            dist = distance(target)
            rel = corners - (target - dist * forward)
            z = rel @ forward
            u, v = (rel @ right) / (z * tx), (rel @ cam_up) / (z * ty)
            target = target + 0.5 * (u.min() + u.max()) * tx * dist * right
            target = target + 0.5 * (v.min() + v.max()) * ty * dist * cam_up
        dist = distance(target)
        return cls(position=tuple(target + dist * back), target=tuple(target), up=tuple(cam_up), fov=fov)


def _as_camera(camera) -> Camera:
    if isinstance(camera, Camera):
        return camera
    if isinstance(camera, dict):
        unknown = set(camera) - {"position", "target", "up", "fov"}
        if unknown:
            raise ValueError(f"unknown camera keys {sorted(unknown)}; use position, target, up, fov")
        return Camera(**camera)
    raise TypeError(f"camera must be a Camera, a dict or None, got {type(camera).__name__}")


def _plane_list(planes) -> list[tuple[np.ndarray, np.ndarray]]:
    """(point, unit normal) of each plane: PlaneWall-like objects, dicts or (point, normal) pairs."""
    out = []
    for k, p in enumerate(planes or ()):
        if hasattr(p, "point") and hasattr(p, "normal"):
            point, normal = p.point, p.normal
        elif isinstance(p, dict):
            point, normal = p["point"], p["normal"]
        else:
            point, normal = p
        point = np.asarray(point, dtype=np.float64).reshape(3)
        out.append((point, _unit(normal, f"planes[{k}] normal")))
    return out


def _mesh_list(mesh_walls) -> list[tuple[np.ndarray, np.ndarray]]:
    """(world vertices (nv, 3), triangles (nf, 3)) of each mesh wall: MeshWall-like objects (their
    vertices at t = 0), dicts with ``vertices`` and ``triangles``, or (vertices, triangles) pairs."""
    out = []
    for k, w in enumerate(mesh_walls or ()):
        if isinstance(w, dict):
            v, t = w["vertices"], w["triangles"]
        elif hasattr(w, "vertices"):
            v, t = w.vertices, w.triangles
        else:
            v, t = w
        v = np.asarray(v, dtype=np.float64)
        t = np.asarray(t)
        if v.ndim != 2 or v.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 3:
            raise ValueError(f"mesh_walls[{k}] needs (nv, 3) vertices and (nf, 3) triangles, got {v.shape}, {t.shape}")
        if len(t) and (t.min() < 0 or t.max() >= len(v)):
            raise ValueError(f"mesh_walls[{k}] triangles must index its {len(v)} vertices")
        out.append((v, t.astype(np.int64)))
    return out


def posed_mesh_walls(mesh_walls, mesh_q=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """(world vertices, triangles) of a scene's mesh walls at the poses ``mesh_q`` ((M, 7): the
    position of each wall's pivot [m] and quaternion xyzw, as ``State.mesh_q``); None: at t = 0."""
    from polydem.quaternions import quat_to_matrix

    out = []
    for k, w in enumerate(mesh_walls):
        v = np.asarray(w.vertices, dtype=np.float64)
        if mesh_q is not None and w.moving:
            pose = np.asarray(mesh_q[k], dtype=np.float64)
            q = pose[3:] / np.linalg.norm(pose[3:])
            v = (v - np.asarray(w.pivot, dtype=np.float64)) @ quat_to_matrix(q).T + pose[:3]
        out.append((v, np.asarray(w.triangles)))
    return out


def _shape_set(shapes, device) -> ShapeSet:
    if isinstance(shapes, ShapeSet):
        if shapes.precision == "float32" and shapes.device == device:
            return shapes
        shapes = shapes.shapes
    return ShapeSet(list(shapes), device=device, precision="float32")


def _colors(body_shape, num_shapes, shape_colors, body_colors) -> np.ndarray:
    n = len(body_shape)
    if body_colors is not None:
        c = np.asarray(body_colors, dtype=np.float64)
        if c.shape != (n, 3):
            raise ValueError(f"body_colors must have shape ({n}, 3), got {c.shape}")
        return c
    if shape_colors is None:
        table = PALETTE[np.arange(num_shapes) % len(PALETTE)]
    else:
        table = np.asarray(shape_colors, dtype=np.float64)
        if table.shape != (num_shapes, 3):
            raise ValueError(f"shape_colors must have shape ({num_shapes}, 3), got {table.shape}")
    return table[body_shape] if n else np.zeros((0, 3))


def _bounds(pos, quat, body_shape, shapes) -> tuple[np.ndarray, np.ndarray]:
    """World box around the bodies: each shape's vertex box, turned with the body, boxed again."""
    if len(pos) == 0:
        return -np.ones(3), np.ones(3)
    verts = [np.asarray(s.vertices, dtype=np.float64) for s in shapes]
    centre = np.array([0.5 * (v.min(axis=0) + v.max(axis=0)) for v in verts])[body_shape]
    half = np.array([0.5 * (v.max(axis=0) - v.min(axis=0)) for v in verts])[body_shape]
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    chunk = 65536  # a million bodies stay within a few MB at a time
    for k in range(0, len(pos), chunk):
        rows = slice(k, k + chunk)
        rot = quat_to_matrix(quat[rows])
        c = pos[rows] + np.einsum("nij,nj->ni", rot, centre[rows])
        h = np.einsum("nij,nj->ni", np.abs(rot), half[rows])
        lo = np.minimum(lo, (c - h).min(axis=0))
        hi = np.maximum(hi, (c + h).max(axis=0))
    return lo, hi


def render_layers(
    positions,
    orientations_xyzw,
    body_shape,
    shapes,
    planes=None,
    width: int = 800,
    height: int = 600,
    camera=None,
    device=None,
    *,
    light=None,
    shadows: bool = True,
    up=(0.0, 0.0, 1.0),
    shape_colors=None,
    body_colors=None,
    visible=None,
    mesh_walls=None,
    checker: float | None = None,
    azimuth: float = -60.0,
    elevation: float = 50.0,
    fov: float = 35.0,
) -> dict:
    """Like :func:`render` without supersampling, returning every layer as numpy arrays.

    Returns a dict: ``image`` (H, W, 3) uint8, ``color`` (H, W, 3) float32 RGB in [0, 1],
    ``depth`` (H, W) float64 distance from the eye [m] (inf where nothing is hit), ``hit``
    (H, W) int32 (body index; ``-2 - p`` for plane p; ``-2 - P - w`` for mesh wall w, P planes; -1
    for nothing) and ``camera`` (the :class:`Camera` used).
    """
    device = wp.get_device(device)
    width, height = _checked_size(width, height, 1, device, layers=True)
    color, depth, hit, trees, owner, camera = _cast(
        positions,
        orientations_xyzw,
        body_shape,
        shapes,
        planes,
        width,
        height,
        camera,
        device,
        light=light,
        shadows=shadows,
        up=up,
        shape_colors=shape_colors,
        body_colors=body_colors,
        visible=visible,
        mesh_walls=mesh_walls,
        checker=checker,
        azimuth=azimuth,
        elevation=elevation,
        fov=fov,
    )
    rgb = color.numpy().reshape(height, width, 3)
    depth_np = depth.numpy().astype(np.float64)
    hit_np = hit.numpy()
    del trees
    depth_np[hit_np == -1] = np.inf
    if owner is not None:
        hit_np = np.where(hit_np >= 0, owner[np.maximum(hit_np, 0)], hit_np)
    return {"image": _to_uint8(rgb), "color": rgb, "depth": depth_np, "hit": hit_np, "camera": camera}


def _cast(
    positions,
    orientations_xyzw,
    body_shape,
    shapes,
    planes,
    width: int,
    height: int,
    camera,
    device,
    *,
    light=None,
    shadows: bool = True,
    up=(0.0, 0.0, 1.0),
    shape_colors=None,
    body_colors=None,
    visible=None,
    mesh_walls=None,
    checker: float | None = None,
    azimuth: float = -60.0,
    elevation: float = 50.0,
    fov: float = 35.0,
):
    """Casts the rays of a ``width`` x ``height`` picture (checked by the caller): (colour, depth and
    hit Warp arrays, the trees to keep until they are read, the body owning each convex part or
    None, the camera). The arguments are those of :func:`render_layers`."""
    device = wp.get_device(device)
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    n = len(pos)
    quat = np.asarray(orientations_xyzw, dtype=np.float64).reshape(-1, 4)
    body_shape = np.asarray(body_shape).reshape(-1)
    if quat.shape[0] != n or body_shape.shape[0] != n:
        raise ValueError(
            f"positions ({n}), orientations ({quat.shape[0]}) and body_shape ({body_shape.shape[0]}) "
            "must have one row per body"
        )
    shape_set = _shape_set(shapes, device)
    num_shapes = len(shape_set.shapes)
    owner = None
    if n and (body_shape.min() < 0 or body_shape.max() >= num_shapes):
        raise ValueError(
            f"body_shape must index the {num_shapes} shapes, got values in [{body_shape.min()}, {body_shape.max()}]"
        )
    body_shape = body_shape.astype(np.int32)
    norms = np.linalg.norm(quat, axis=1, keepdims=True)
    if n and not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat)) and np.all(norms > 0.0)):
        raise ValueError("positions and orientations must be finite, with non-zero quaternions")
    quat = quat / np.where(norms > 0.0, norms, 1.0)
    shown = np.ones(n, dtype=bool) if visible is None else np.asarray(visible, dtype=bool).reshape(-1)
    if shown.shape != (n,):
        raise ValueError(f"visible must have one entry per body ({n}), got shape {shown.shape}")
    colors = _colors(body_shape, num_shapes, shape_colors, body_colors)
    up_v = _unit(up, "up")
    if shape_set.compound:
        # The ray caster intersects convex shapes: a compound grain is drawn as its parts (their
        # union is the grain); hits are reported by body.
        convex, body_shape, pos, quat, owner = expand_bodies(shape_set.shapes, body_shape, pos, quat)
        body_shape = body_shape.astype(np.int32)
        shown, colors = shown[owner], colors[owner]
        shape_set = ShapeSet(convex, device=device, precision="float32")
        n = len(pos)

    radius = np.array([s.radius for s in shape_set.shapes])[body_shape]
    if camera is None:
        lo, hi = _bounds(pos[shown], quat[shown], body_shape[shown], shape_set.shapes)
        camera = Camera.frame_box(lo, hi, width, height, up=up_v, azimuth=azimuth, elevation=elevation, fov=fov)
    camera = _as_camera(camera)
    eye, forward, right, cam_up = camera.frame()
    view_distance = float(np.linalg.norm(np.array(camera.target) - eye))

    if light is None:  # from above, behind the camera and to its right: both visible sides get some light
        horizontal = forward - up_v * np.dot(forward, up_v)
        horizontal = horizontal / max(float(np.linalg.norm(horizontal)), 1e-12)
        light = 1.0 * up_v + 0.35 * right - 0.5 * horizontal
    light = _unit(light, "light")

    plane_list = _plane_list(planes)
    if checker is None:
        checker = 4.0 * float(np.median(radius[shown])) if shown.any() else 0.05 * view_distance
    checker = float(checker)
    if not checker > 0.0:
        raise ValueError(f"checker (square size in m) must be positive, got {checker}")
    pn = np.zeros((len(plane_list), 3))
    po = np.zeros(len(plane_list))
    pu = np.zeros((len(plane_list), 3))
    pv = np.zeros((len(plane_list), 3))
    for k, (point, normal) in enumerate(plane_list):
        e1, e2 = _perpendicular_basis(normal)
        pn[k], po[k], pu[k], pv[k] = normal, float(point @ normal), e1 / checker, e2 / checker

    def arr(a, dtype):
        return wp.array(
            np.ascontiguousarray(a, dtype=np.float32 if dtype is not int else np.int32), dtype=dtype, device=device
        )

    meshes = _mesh_list(mesh_walls)
    tri_vertex = np.zeros((0, 3))
    tri_wall = np.zeros(0, dtype=np.int32)
    if meshes:
        tri_vertex = np.concatenate([v[t].reshape(-1, 3) for v, t in meshes])
        tri_wall = np.concatenate([np.full(len(t), k, dtype=np.int32) for k, (_, t) in enumerate(meshes)])

    body_q = arr(np.hstack([pos, quat]).reshape(-1, 7), wp.transform)
    bvh_body = arr(np.flatnonzero(shown), int)
    scale = max(view_distance, float(np.abs(eye).max()), 1e-30)
    color, depth, hit, trees = launch_raycast(
        shape_set,
        arr(body_shape, int),
        arr(colors.reshape(-1, 3), wp.vec3),
        bvh_body,
        (arr(pn, wp.vec3), arr(po, float), arr(pu, wp.vec3), arr(pv, wp.vec3)),
        body_q,
        camera.kernel_basis(width, height),
        light,
        up_v,
        width,
        height,
        shadows=shadows,
        shadow_offset=1e-5 * scale,
        fade_distance=3.0 * view_distance,
        device=device,
        triangles=(arr(tri_vertex, wp.vec3), arr(tri_wall, int)),
    )
    return color, depth, hit, trees, owner, camera


def _to_uint8(rgb: np.ndarray) -> np.ndarray:
    # In place on one float32 copy: a large picture holds two copies of its colour at most.
    x = np.multiply(rgb, 255.0, dtype=np.float32)
    np.rint(x, out=x)
    np.clip(x, 0, 255, out=x)
    return x.astype(np.uint8)


def _gpu_room(device) -> int | None:
    """Bytes a picture can take on a CUDA device: its free memory, plus what Warp's memory pool
    keeps after frees (up to its release threshold), which counts as used yet serves Warp's next
    allocations; None where Warp cannot tell."""
    try:
        room = int(device.free_memory)
        if wp.is_mempool_enabled(device):
            room += int(wp.get_mempool_release_threshold(device))
        return min(room, int(device.total_memory))
    except Exception:  # a Warp without these queries: the allocation itself will tell
        return None


def check_picture(width: int, height: int, supersample: int = 1, device=None) -> None:
    """Raises :class:`~polydem.picture_memory.PictureSizeError` (a ValueError) where :func:`render`
    could not hold a ``width`` x ``height`` picture of ``supersample``^2 rays per pixel on ``device``
    (None: Warp's default) in the memory free now, and ValueError for a size below 1."""
    _checked_size(width, height, supersample, wp.get_device(device), layers=False)


def _checked_size(width, height, supersample, device, *, layers: bool) -> tuple[int, int]:
    """(width, height) as ints; ValueError for a size below 1, PictureSizeError for a picture
    the memory of the host (or of ``device``, a GPU) cannot hold, before anything is allocated."""
    width, height = int(width), int(height)
    if width < 1 or height < 1:
        raise ValueError(f"width and height must be positive, got {width} x {height}")
    gpu = device.is_cuda
    check_picture_size(
        width,
        height,
        supersample,
        gpu=gpu,
        layers=layers,
        gpu_available=_gpu_room(device) if gpu else None,
        gpu_name=str(device.alias),
    )
    return width, height


def render(
    positions,
    orientations_xyzw,
    body_shape,
    shapes,
    planes=None,
    width: int = 800,
    height: int = 600,
    camera=None,
    device=None,
    *,
    supersample: int = 1,
    **options,
) -> np.ndarray:
    """Renders bodies (convex polyhedra) and walls; returns an (height, width, 3) uint8 RGB image.

    Args:
        positions: (N, 3) body centroids [m] (the body frame's origin, as ``Simulation.state()``).
        orientations_xyzw: (N, 4) quaternions [x, y, z, w], body frame -> world (normalised here).
        body_shape: (N,) shape index of each body.
        shapes: the shapes, a list of :class:`~polydem.ConvexShape` (body frames) or a
            :class:`~polydem.shapeset.ShapeSet`.
        planes: walls drawn as infinite planes, seen from the side their normal points to: a list
            of :class:`~polydem.PlaneWall`, of dicts with ``point`` and ``normal``, or of
            (point, normal) pairs. None: no walls.
            Mesh walls go in the keyword ``mesh_walls``: a list of
            :class:`~polydem.scene.walls.MeshWall` (drawn at their t = 0 pose), of dicts with
            world ``vertices`` and ``triangles``, or of (vertices, triangles) pairs; like the planes,
            a triangle is drawn from its front side only (see :func:`posed_mesh_walls`).
        width, height: image size [pixels].
        camera: a :class:`Camera` (or a dict of its fields); None frames every visible body from
            a raised oblique direction (:meth:`Camera.frame_box`).
        device: Warp device ("cpu", "cuda:0"); None: Warp's default device.
        supersample: rays per pixel along each axis (anti-aliasing; the cost grows as its square).

    A picture that the memory free now cannot hold (:mod:`polydem.picture_memory`: 20 bytes per ray
    on the rendering device, the picture's own on the host) raises
    :class:`~polydem.picture_memory.PictureSizeError`, a ValueError, before anything is allocated.

    Keyword options (see :func:`render_layers`): ``light`` (direction towards the light; default
    from above, over the camera's right shoulder), ``shadows`` (default True), ``up`` (world up,
    for the automatic camera, the light and the sky; default +z), ``shape_colors`` ((S, 3) RGB in
    [0, 1]; default :data:`PALETTE`), ``body_colors`` ((N, 3), overrides the shape colours),
    ``visible`` ((N,) bool, bodies to draw), ``mesh_walls`` (see ``planes``), ``checker`` (square
    size of the walls' checker [m]; default four times the median body radius); ``azimuth``,
    ``elevation``, ``fov`` (degrees, for the automatic camera: -60, 50, 35).
    """
    if isinstance(supersample, bool) or int(supersample) != supersample or supersample < 1:
        raise ValueError(f"supersample must be a positive integer, got {supersample!r}")
    s = int(supersample)
    device = wp.get_device(device)
    width, height = _checked_size(width, height, s, device, layers=False)
    # The automatic camera depends on the aspect ratio only, the same for the larger image.
    color, depth, hit, trees, _, _ = _cast(
        positions, orientations_xyzw, body_shape, shapes, planes, width * s, height * s, camera, device, **options
    )
    del depth, hit  # only the colour makes the picture: the other layers never come to the host
    rgb = color.numpy().reshape(height, s, width, s, 3)
    del trees  # after the read, which waits for the launch that uses them
    if s > 1:
        rgb = rgb.mean(axis=(1, 3), dtype=np.float32)
    del color
    return _to_uint8(rgb.reshape(height, width, 3))


def render_simulation(sim, path: str | PathLike | None = None, *, cutaway: bool = True, **kw) -> np.ndarray:
    """Renders the current state of a :class:`~polydem.Simulation`; writes a PNG when ``path`` is given.

    The scene's planes and mesh walls (at their current poses) are drawn, fixed and kinematic
    bodies (containers, drums) get :data:`FIXED_COLOR` unless ``body_colors`` or ``shape_colors``
    is given, ``up`` defaults to minus gravity, and the simulation's device renders. The camera
    frames every body.

    ``cutaway`` (default True, unless ``visible`` is given): the fixed and kinematic bodies that
    stand between the camera and free bodies are left out, so that a closed container (a drum, a
    box seen from the side) shows the grains inside it; the parts behind the grains stay. Other
    keywords go to :func:`render`. Returns the image.
    """
    if path is not None:
        _check_png_path(path)
    scene = sim.scene
    state = sim.state()
    kw.setdefault("device", sim.device)
    current_planes = getattr(sim, "current_planes", None)  # where they are now (a decomposed run's: at rest)
    kw.setdefault("planes", current_planes() if current_planes is not None else scene.planes)
    if "mesh_walls" not in kw and getattr(scene, "mesh_walls", None):
        current = getattr(sim, "current_state", None)
        mesh_q = current.mesh_q.numpy() if current is not None else getattr(sim, "mesh_q", None)
        kw["mesh_walls"] = posed_mesh_walls(scene.mesh_walls, mesh_q)
    shapes = getattr(sim.model, "grain_shapes", sim.model.shapes)  # without the mesh walls' cells
    g = np.asarray(scene.gravity, dtype=np.float64)
    if "up" not in kw and np.linalg.norm(g) > 0.0:
        kw["up"] = -g / np.linalg.norm(g)
    body_shape = np.asarray(scene.body_shape)
    container = np.asarray(sim.model.body_flags_np) != BodyKind.FREE
    if "body_colors" not in kw and "shape_colors" not in kw:
        num_shapes = len(scene.shape_names)
        colors = _colors(body_shape, num_shapes, None, None)
        colors[container] = FIXED_COLOR
        kw["body_colors"] = colors
    pos, quat = state["body_position"], state["body_orientation"]
    # The picture asked for first: a refusal names its size, not that of the cut-away's small pictures.
    check_picture(kw.get("width", 800), kw.get("height", 600), kw.get("supersample", 1), kw["device"])
    if cutaway and kw.get("visible") is None and container.any() and not container.all():
        kw["camera"], kw["visible"] = _cut_away(pos, quat, body_shape, shapes, container, kw)
    image = render(pos, quat, body_shape, shapes, **kw)
    if path is not None:
        save_png(image, path)
    return image


def _cut_away(pos, quat, body_shape, shapes, container, kw) -> tuple[Camera, np.ndarray]:
    """(camera, visible): the picture's camera (framing every body) and the bodies to draw: all but
    the container bodies that hide a free body in some pixel of a small picture."""
    width, height = int(kw.get("width", 800)), int(kw.get("height", 600))
    up = _unit(kw.get("up", (0.0, 0.0, 1.0)), "up")
    camera = kw.get("camera")
    if camera is None:
        q = np.asarray(quat, dtype=np.float64).reshape(-1, 4)
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        shape_set = _shape_set(shapes, wp.get_device(kw.get("device")))
        lo, hi = _bounds(np.asarray(pos, dtype=np.float64).reshape(-1, 3), q, body_shape, shape_set.shapes)
        angles = {k: kw[k] for k in ("azimuth", "elevation", "fov") if k in kw}
        camera = Camera.frame_box(lo, hi, width, height, up=up, **angles)
    camera = _as_camera(camera)
    f = min(1.0, CUTAWAY_PIXELS / max(width, height))
    w, h = max(1, round(width * f)), max(1, round(height * f))
    common = {k: kw[k] for k in ("device", "up", "mesh_walls") if k in kw}
    common.update(camera=camera, shadows=False, width=w, height=h)
    everything = render_layers(pos, quat, body_shape, shapes, **common)["hit"]
    grains = render_layers(pos, quat, body_shape, shapes, visible=~container, **common)["hit"]
    hiding = (grains >= 0) & (everything >= 0)
    hiding[hiding] = container[everything[hiding]]
    visible = np.ones(len(container), dtype=bool)
    visible[np.unique(everything[hiding])] = False
    return camera, visible


# ------------------------------------------------------------------------------------------- PNG


def _check_png_path(path) -> Path:
    p = Path(path)
    if p.suffix.lower() != ".png":
        raise ValueError(f"can only write PNG images: the file name must end in .png, got {str(path)!r}")
    return p


def save_png(image, path: str | PathLike) -> Path:
    """Writes an 8-bit image as a PNG file (Pillow); returns the path.

    ``image``: uint8 array (H, W) grey, (H, W, 3) RGB or (H, W, 4) RGBA.
    """
    from PIL import Image

    p = _check_png_path(path)
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"image must be uint8 (0-255), got dtype {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] in (3, 4))) or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"image must have shape (H, W), (H, W, 3) or (H, W, 4), got {np.shape(image)}")
    tmp = p.with_name(p.name + ".tmp")  # a failed write leaves neither a broken picture nor a temporary file
    try:
        Image.fromarray(np.ascontiguousarray(img)).save(tmp, format="PNG")
        os.replace(tmp, p)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return p
