"""Batch contact geometry and contact laws, for researchers and for tests.

:func:`overlap` runs the narrow-phase kernel over N pairs of poses of two shapes and returns the
exact energy-model quantities as numpy arrays; :func:`contact_forces` turns them and a
:class:`ContactLaw` into forces and torques. Both launch the Warp functions that the simulator's
contacts use (:mod:`polydem.kernels.geometry` and :mod:`polydem.kernels.response`).

Frames. By default (``frame="input"``) a pose places a shape the way :meth:`polydem.Scene.add_body`
and scene files do: its position is where the shape's *input-frame* origin goes (the origin of the
coordinates its points or mesh were given in) and its quaternion turns the input axes into world
axes. So ``ConvexShape.box(0.05, 0.05, 0.17)`` at the identity stands with its long edge along
world z, and a rock or mesh at the origin sits where its points were. ``frame="body"`` takes poses
of the *body frame* instead (the centre of mass and the principal axes of inertia, what a shape's
``vertices`` are given in and what ``Simulation.state()`` reports as ``body_position`` and
``body_orientation``). Either way every result is in world coordinates: points (centroid, contact
point) are world positions, ``moment`` is taken about the world origin, ``position_a`` and
``position_b`` are the centres of mass, and :func:`contact_forces` gives torques about them.

Degenerate pairs. When one body lies (almost) wholly inside the other, or two identical bodies
sit on top of each other, the gradient of the overlap volume vanishes and so would the force.
Such a pair is flagged ``enclosed`` (|S_A| < 1e-4 V^(2/3)) and pushed apart along the direction
of least penetration instead (the face normal, of either body, along which the shorter
translation separates them), with the projected area of the smaller body along it as effective
area (``enclosed_area_vector``): the force on A is ``-W'(V) enclosed_area_vector``, applied at
the overlap centroid, and it goes on without a jump from the force just before the body sank in
wholly. Pairs without overlap have V = 0, S = 0, zero force, their normal along the line of
centres and their centroid and contact point on it, between the bounding spheres. No output is
ever NaN or infinite for finite input.
"""

from dataclasses import dataclass

import numpy as np
import warp as wp

from polydem.compound import CompoundShape
from polydem.kernels.laws import LAW_SPECS, LAWS
from polydem.kernels.narrowphase import BatchPairs, launch_depth, launch_overlap
from polydem.kernels.response import ENCLOSED, batch_overlaps, launch_contact_force, launch_contact_frame
from polydem.quaternions import quat_from_matrix, quat_multiply, quat_rotate
from polydem.shapes import ConvexShape
from polydem.shapeset import ShapeSet, scalar_type

__all__ = ["ContactLaw", "OverlapResult", "ContactForces", "overlap", "contact_forces", "FRAMES"]

FRAMES = ("input", "body")
"""The frames :func:`overlap` takes poses in (see the module docstring)."""


@dataclass(frozen=True)
class ContactLaw:
    """Contact energy W(V) of the overlap volume V [m^3]; ``kind`` names a
    :class:`polydem.kernels.laws.Law` (a string or the enum), whose W and W' this evaluates.

    * ``linear``: W = k V, W' = k (k in Pa = J/m^3)
    * ``hertz``: W = 2/3 k V^1.5, W' = k V^0.5 (k in J/m^4.5)
    * ``power``: W = k V^m / m, W' = k V^(m-1), with m >= 1
    """

    kind: str = "linear"
    k: float = 1.0e6
    m: float = 1.0

    def __post_init__(self):
        if self.kind not in LAWS:
            raise ValueError(f"contact law must be one of {', '.join(LAWS)}, got {self.kind!r}")
        # A Law is kept by its name, as the kernels and messages take it.
        object.__setattr__(self, "kind", str(self.kind))
        if not np.isfinite(self.k) or self.k <= 0.0:
            raise ValueError(f"contact stiffness k must be a positive finite number, got {self.k!r}")
        if LAW_SPECS[self.kind].fixed_exponent is None and (not np.isfinite(self.m) or self.m < 1.0):
            raise ValueError(
                f"{self.kind}-law exponent m must be >= 1 (m < 1 gives an infinite force at first touch), "
                f"got {self.m!r}"
            )

    @property
    def exponent(self):
        """The exponent m of W = k V^m / m (1 linear, 1.5 Hertz-type, ``m`` power)."""
        return LAW_SPECS[self.kind].exponent(self.m)

    def energy(self, volume):
        """W(V) [J] for an array of overlap volumes [m^3]."""
        v = np.maximum(np.asarray(volume, dtype=np.float64), 0.0)
        return LAW_SPECS[self.kind].energy(v, self.k, self.exponent)

    def derivative(self, volume):
        """W'(V) [Pa] for an array of overlap volumes [m^3]."""
        v = np.maximum(np.asarray(volume, dtype=np.float64), 0.0)
        return LAW_SPECS[self.kind].derivative(v, self.k, self.exponent)


@dataclass
class OverlapResult:
    """Energy-model contact geometry of N pairs; one row per pair, world axes and world positions.

    The same whichever frame the poses were given in (:func:`overlap`'s ``frame``): points are in
    world coordinates and moments are about the world origin or, where said, a centre of mass.

    Attributes:
        volume: (N,) overlap volume V [m^3].
        centroid: (N, 3) centroid of the overlap, world position [m].
        area_vector: (N, 3) S_A = sum of A's facet areas times A's outward normals [m^2]; the
            gradient of V under translation of A.
        moment: (N, 3) M_A = sum A_k (c_k x n_k) about the world origin [m^3]; ``M_A - c x S_A`` is
            the gradient of V under rotation of A about the point c: ``M_A - position_a x S_A``
            about A's centre of mass; for input-frame poses, ``M_A - p x S_A`` with p the pose's
            position under a turn of the pose's quaternion (which turns A about p).
        normal: (N, 3) unit contact normal S_A/|S_A|, pointing from A into B.
        contact_point: (N, 3) world position where the wrench's central axis meets the plane
            through the centroid normal to ``normal`` [m].
        area_vector_b, moment_b: (N, 3) the same sums over B's facets (S_B = -S_A, M_B = -M_A).
        enclosed: (N,) bool, the gradient of V vanishes (see the module docstring).
        enclosed_area_vector: (N, 3) the effective area vector that pushes an enclosed pair
            apart (taking the place of S_A) [m^2]; zero for the other pairs.
        depth: (N,) penetration depth [m]: the shortest translation along a face normal of either
            body that separates them (for a corner or edge in a face, its depth below that face;
            where two edges cross, an upper bound), 0 where V = 0.
        position_a, position_b: (N, 3) world positions of the bodies' centres of mass [m] (for
            ``frame="input"`` not the positions given, unless the shape's input origin is its
            centroid, as for every generated shape except ``rock``).
    """

    volume: np.ndarray
    centroid: np.ndarray
    area_vector: np.ndarray
    moment: np.ndarray
    normal: np.ndarray
    contact_point: np.ndarray
    area_vector_b: np.ndarray
    moment_b: np.ndarray
    enclosed: np.ndarray
    enclosed_area_vector: np.ndarray
    depth: np.ndarray
    position_a: np.ndarray
    position_b: np.ndarray

    def __len__(self):
        return len(self.volume)


@dataclass
class ContactForces:
    """Forces [N] and torques [N m], (N, 3) arrays in world axes.

    ``torque_a`` and ``torque_b`` are about each body's centre of mass (``OverlapResult.position_a``
    and ``position_b``), whichever frame the poses were given in; about another point p the torque
    on A is ``torque_a + (position_a - p) x force_a``.
    """

    force_a: np.ndarray
    torque_a: np.ndarray
    force_b: np.ndarray
    torque_b: np.ndarray
    energy: np.ndarray  # (N,) W(V) [J]


_KIND_NAMES = {"b": "booleans", "c": "complex numbers", "U": "strings", "S": "bytes", "O": "Python objects"}


def _check_poses(poses, name):
    try:
        raw = np.asarray(poses)
    except ValueError:  # nested lists of different lengths
        raise ValueError(
            f"{name} must be an (N, 7) or (7,) array [px, py, pz, qx, qy, qz, qw], but its rows have different lengths"
        ) from None
    # np.asarray(..., dtype=float) would turn True into 1.0, "0.5" into 0.5 and drop imaginary parts.
    if raw.dtype.kind not in "iuf":
        what = _KIND_NAMES.get(raw.dtype.kind, "values")
        raise TypeError(
            f"{name} must hold real numbers (float or int) [px, py, pz, qx, qy, qz, qw], got {what} (dtype "
            f"{raw.dtype}); pass a float array, e.g. np.asarray(poses, dtype=float) of numbers"
        )
    p = raw.astype(np.float64)
    if p.ndim == 1:
        p = p[None, :]
    if p.ndim != 2 or p.shape[1] != 7:
        raise ValueError(
            f"{name} must have shape (N, 7) or (7,) as [px, py, pz, qx, qy, qz, qw], got shape {np.shape(poses)}"
        )
    bad = ~np.isfinite(p).all(axis=1)
    if bad.any():
        raise ValueError(f"{name} has non-finite values in rows {np.flatnonzero(bad)[:10].tolist()}")
    qn = np.linalg.norm(p[:, 3:], axis=1)
    if (qn == 0.0).any():
        raise ValueError(f"{name} has zero quaternions in rows {np.flatnonzero(qn == 0.0)[:10].tolist()}")
    off = np.abs(qn - 1.0) > 1e-5
    if off.any():
        rows = np.flatnonzero(off)[:10].tolist()
        raise ValueError(
            f"{name} has non-unit quaternions (|q| = {qn[off][0]:.6g} in row {rows[0]}; rows {rows}); "
            "normalise them first, e.g. q / np.linalg.norm(q, axis=1, keepdims=True)"
        )
    p[:, 3:] /= qn[:, None]
    return p


def _body_poses(shape, poses):
    """Body-frame poses of ``shape`` placed by its input frame at ``poses``, converted as
    :meth:`polydem.Scene.add_body` converts them: centre of mass ``p + R(q) t_in``, orientation
    ``q * q(R_in)``."""
    t_in = np.asarray(shape.input_translation, dtype=np.float64)
    q_in = quat_from_matrix(shape.input_rotation)
    out = poses.copy()
    # Skipping the no-op transforms keeps the poses of shapes built in their principal frame exact.
    if np.any(t_in):
        out[:, :3] = poses[:, :3] + quat_rotate(poses[:, 3:], np.broadcast_to(t_in, (len(poses), 3)))
    if not np.all(q_in == (0.0, 0.0, 0.0, 1.0)):
        q = quat_multiply(poses[:, 3:], q_in)
        out[:, 3:] = q / np.sqrt(np.einsum("ij,ij->i", q, q))[:, None]
    return out


def overlap(shape_a, poses_a, shape_b, poses_b, *, frame="input", device=None, precision="float32"):
    """Contact geometry of ``shape_a`` at each of ``poses_a`` against ``shape_b`` at ``poses_b``.

    Args:
        shape_a, shape_b: :class:`~polydem.ConvexShape` or :class:`~polydem.CompoundShape` (a
            compound one's results are the sums over its part pairs, about its centre).
        poses_a, poses_b: (N, 7) arrays ``[px, py, pz, qx, qy, qz, qw]`` placing each shape in the
            world (positions in m, unit quaternions), in the frame that ``frame`` names; a single
            (7,) pose is broadcast.
        frame: ``"input"`` (default): the poses place each shape's input frame, the frame its
            points or mesh were given in, as :meth:`polydem.Scene.add_body` and scene files do;
            ``"body"``: they place its body frame (centre of mass, principal axes of inertia), as
            ``Simulation.state()``'s ``body_position`` and ``body_orientation`` do. The two agree
            where a shape's input frame is its body frame (``box(1.0)``, ``octahedron()``), not
            for ``box(0.05, 0.05, 0.17)``, whose body x axis is its input z axis (the axis of
            least inertia), nor for a ``rock``, whose centroid is off its input origin.
        device: Warp device ("cpu", "cuda:0", ...), default Warp's default device.
        precision: "float32" (default) or "float64" arithmetic in the clipping. The poses reach
            the kernel in float64 either way (the mixed mode for "float32"), relative to A's
            centre, so a depth far below the size of the bodies or their distance from the
            origin is not lost before the geometry starts.

    Returns:
        :class:`OverlapResult`, in world coordinates whatever ``frame`` (its ``position_a`` and
        ``position_b`` are the centres of mass).
    """
    if not isinstance(frame, str) or frame not in FRAMES:
        raise ValueError(
            f"frame must be 'input' (poses of the frame the shape's points were given in, as in scenes) or "
            f"'body' (poses of its centre of mass and principal axes, as Simulation.state() gives), got {frame!r}"
        )
    for s, name in ((shape_a, "shape_a"), (shape_b, "shape_b")):
        if not isinstance(s, ConvexShape | CompoundShape):
            raise TypeError(f"{name} must be a polydem.ConvexShape or CompoundShape, got {type(s).__name__}")
    scalar_type(precision)
    pa = _check_poses(poses_a, "poses_a")
    pb = _check_poses(poses_b, "poses_b")
    if frame == "input":
        pa = _body_poses(shape_a, pa)
        pb = _body_poses(shape_b, pb)
    if len(pa) != len(pb):
        if len(pa) == 1:
            pa = np.repeat(pa, len(pb), axis=0)
        elif len(pb) == 1:
            pb = np.repeat(pb, len(pa), axis=0)
        else:
            raise ValueError(f"poses_a has {len(pa)} rows and poses_b {len(pb)}; give equal counts or a single pose")
    n = len(pa)

    shapes = ShapeSet([shape_a, shape_b], device=device, precision=precision)
    # The kernel sees A's centre at the world origin: the subtraction of positions happens here
    # in float64 (and so does the pair set-up in the kernel).
    origin = pa[:, :3].copy()
    local_a = pa.copy()
    local_a[:, :3] = 0.0
    local_b = pb.copy()
    local_b[:, :3] -= origin

    dev = shapes.device
    pose_scalar = wp.float64
    transform = wp.types.transformation(pose_scalar)
    vec3 = wp.types.vector(3, shapes.scalar)
    out = {
        "pair_volume": wp.zeros(n, dtype=shapes.scalar, device=dev),
        "pair_volume_moment": wp.zeros(n, dtype=vec3, device=dev),
        "pair_area_a": wp.zeros(n, dtype=vec3, device=dev),
        "pair_moment_a": wp.zeros(n, dtype=vec3, device=dev),
        "pair_area_b": wp.zeros(n, dtype=vec3, device=dev),
        "pair_moment_b": wp.zeros(n, dtype=vec3, device=dev),
        "pair_fallback_a": wp.zeros(n, dtype=vec3, device=dev),
    }
    ids_a = wp.zeros(n, dtype=int, device=dev)
    ids_b = wp.ones(n, dtype=int, device=dev)
    poses_a64 = wp.array(local_a, dtype=transform, device=dev)
    poses_b64 = wp.array(local_b, dtype=transform, device=dev)
    pairs = BatchPairs(ids_a, ids_b, poses_a64, poses_b64)
    launch_overlap(shapes, pairs, out=out, pose_scalar=pose_scalar)
    res = {k: v.numpy().astype(np.float64) for k, v in out.items()}
    depth = launch_depth(shapes, pairs, pose_scalar=pose_scalar).numpy().astype(np.float64)
    # Bodies separated only along an edge-edge direction overlap along every face normal: no depth.
    res["pair_depth"] = np.where(res["pair_volume"] > 0.0, depth, 0.0)
    return _finish(res, origin, pb[:, :3], local_b[:, :3], shape_a.radius, shape_b.radius, dev)


def _finish(res, origin, position_b, rel_b, radius_a, radius_b, device):
    volume = np.maximum(res["pair_volume"], 0.0)
    s_a = res["pair_area_a"]
    m_local = res["pair_moment_a"]  # about A's centre
    # Normal, enclosed push and contact point: the Warp function of the simulator's contacts, in
    # float64 whatever the precision of the overlap.
    pairs = batch_overlaps(
        wp.float64,
        device,
        volume=volume,
        first_moment=res["pair_volume_moment"],
        area=s_a,
        moment=m_local,
        fallback=res["pair_fallback_a"],
        r_ab=rel_b,
    )
    kind, normal, point_local = launch_contact_frame(
        pairs, r_min=min(radius_a, radius_b), share_a=radius_a / (radius_a + radius_b)
    )
    touching = volume > 0.0
    centroid_local = point_local.copy()  # between the bounding spheres where nothing overlaps
    centroid_local[touching] = res["pair_volume_moment"][touching] / volume[touching, None]
    return OverlapResult(
        volume=volume,
        centroid=centroid_local + origin,
        area_vector=s_a,
        moment=m_local + np.cross(origin, s_a),
        normal=normal,
        contact_point=point_local + origin,
        area_vector_b=res["pair_area_b"],
        moment_b=res["pair_moment_b"] + np.cross(origin, res["pair_area_b"]),
        enclosed=kind == ENCLOSED,
        enclosed_area_vector=np.where((kind == ENCLOSED)[:, None], res["pair_fallback_a"], 0.0),
        depth=res["pair_depth"],
        position_a=origin,
        position_b=np.asarray(position_b, dtype=np.float64),
    )


def contact_forces(result, law, *, device=None):
    """Forces and torques of the energy model for an :class:`OverlapResult` and a :class:`ContactLaw`.

    Force on A ``-W'(V) S_A``, torque on A about its centre of mass x_A (``result.position_a``)
    ``-W'(V) (M_A - x_A x S_A)``; B gets the exact opposite force and the torque about its centre of
    mass that balances the pair. The poses' frame (:func:`overlap`'s ``frame``) changes none of this.
    Enclosed pairs are pushed apart along their ``enclosed_area_vector`` (module docstring). Computed
    in float64 by the simulator's contact response function on ``device`` (default Warp's default
    device).
    """
    if not isinstance(result, OverlapResult):
        raise TypeError(f"result must be an OverlapResult from polydem.overlap(), got {type(result).__name__}")
    if not isinstance(law, ContactLaw):
        raise TypeError(f"law must be a polydem.ContactLaw, got {type(law).__name__}")
    xa = result.position_a
    xb = result.position_b
    volume = result.volume
    # The decision overlap() took: enclosed pairs carry their fallback area vector; an infinite
    # radius leaves any other pair with a vanishing S_A without force (a sliver).
    fallback = np.where(result.enclosed[:, None], result.enclosed_area_vector, 0.0)
    r_min = np.where(result.enclosed, 0.0, np.inf)
    pairs = batch_overlaps(
        wp.float64,
        wp.get_device(device),
        volume=volume,
        first_moment=volume[:, None] * (result.centroid - xa),
        area=result.area_vector,
        moment=result.moment - np.cross(xa, result.area_vector),
        fallback=fallback,
        r_ab=xb - xa,
    )
    force_a, torque_a, energy = launch_contact_force(pairs, law=law.kind, k=law.k, m=law.exponent, r_min=r_min)
    force_b = -force_a
    # Moment of the pair's wrench about B's centre: balance with A's about a common point.
    torque_b = -torque_a - np.cross(xa - xb, force_a)
    return ContactForces(force_a, torque_a, force_b, torque_b, energy)
