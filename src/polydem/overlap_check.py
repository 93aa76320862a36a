"""The initial-overlap check of body pairs on a simulation's device, for scenes too large for the host's search.

:meth:`Scene.validate` searches the pairs whose bounding spheres meet with a k-d tree on the host, then takes the
separating-axis test over them (:mod:`polydem.scene.overlaps`): the largest part of a large scene's build
(BENCHMARKS.md 19). A :class:`~polydem.Simulation` has those pairs already, from its first broad phase on the device
(each pair of bounding spheres that meet is a candidate pair); here the same test runs over them on the device
(:mod:`polydem.kernels.initial_overlaps`), in float64 from the scene's own poses, and the scene reports what it finds
as its own check would (:meth:`Scene.finish_overlap_check`: the same warning, or the same error for an overlap too
deep; equally deep overlaps are listed by body in both).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from polydem.compound import is_compound
from polydem.kernels.initial_overlaps import launch_pair_overlaps
from polydem.scene.overlaps import (
    BIG_RADIUS_RATIO,
    INITIAL_OVERLAP_WARNING,
    MAX_EDGE_AXES,
    edge_directions,
    pair_records,
)

# Where Simulation(overlap_check="auto") checks the pairs on the device: a CUDA device and at least this many
# bodies (below, the host's check takes a second or less).
DEVICE_CHECK_MIN_BODIES = 200_000
OVERLAP_CHECKS = ("auto", "host", "device")


def median_by_counts(values: np.ndarray, counts: np.ndarray) -> float:
    """``np.median(np.repeat(values, counts))`` without the repeated array (a value per shape, bodies per shape)."""
    order = np.argsort(values, kind="stable")
    ends = np.cumsum(counts[order])
    n = int(ends[-1])

    def at(k):
        return float(values[order[np.searchsorted(ends, k, side="right")]])

    if n % 2:
        return at(n // 2)
    return float(np.mean([at(n // 2 - 1), at(n // 2)]))


class OverlapGeometry:
    """What the device test reads of the shapes beyond the model's :class:`~polydem.shapeset.ShapeSet` (whose
    float64 vertices and face planes, ``vert64`` and ``face_plane64``, it takes as they are): each face's least
    offset over its own shape's vertices, unit edge directions (parallel edges once), and whether a shape is big (a
    bounding radius more than BIG_RADIUS_RATIO times the bodies' median, as the host test takes it: first in its
    pairs).

    Attributes (device arrays; S shapes, F their faces):
        shapeset: the model's shapes (its first S entries are the scene's shapes, in order: convex ones only).
        face_lo: (F,) float64 [m]; shape_edge_start: (S+1,) int32; edge_dir: (E,) vec3d unit; shape_big: (S,)
        int32 0/1; max_edge_axes: edge-direction pairs a body pair tests, beyond which it takes face normals only.
    """

    def __init__(self, shapeset, body_shape: np.ndarray):
        shapes = shapeset.shapes
        if any(is_compound(s) for s in shapes):
            raise ValueError(
                "the device overlap check takes convex shapes only (a compound grain is checked on the host)"
            )
        device = shapeset.device
        counts = np.bincount(np.asarray(body_shape), minlength=len(shapes))
        radius = np.array([s.radius for s in shapes], dtype=np.float64)
        median = median_by_counts(radius, counts)
        edges = [edge_directions(s) for s in shapes]
        self.shapeset = shapeset
        # the scene's shapes are the set's first entries: their faces are its first faces, in this order
        lo = np.concatenate([(s.vertices @ s.face_normals.T).min(axis=0) for s in shapes])
        self.face_lo = wp.array(lo, dtype=wp.float64, device=device)
        edge_start = np.concatenate([[0], np.cumsum([len(e) for e in edges])]).astype(np.int32)
        self.shape_edge_start = wp.array(edge_start, dtype=int, device=device)
        self.edge_dir = wp.array(np.concatenate(edges).reshape(-1, 3), dtype=wp.vec3d, device=device)
        self.shape_big = wp.array((radius > BIG_RADIUS_RATIO * median).astype(np.int32), dtype=int, device=device)
        self.max_edge_axes = MAX_EDGE_AXES


def check_overlap_check(overlap_check) -> None:
    """A ValueError unless ``overlap_check`` is one of :data:`OVERLAP_CHECKS`."""
    if overlap_check not in OVERLAP_CHECKS:
        raise ValueError(f"overlap_check must be 'auto', 'host' or 'device', got {overlap_check!r}")


def device_check_applies(scene, device, bodies=None, overlap_check: str = "auto") -> bool:
    """Whether a Simulation of ``scene`` on ``device`` checks the initial overlaps of body pairs on the device:
    ``overlap_check`` "host" never, "device" always (a ValueError where it cannot: compound grains, or a subset
    of the bodies), "auto" on a CUDA device for scenes of :data:`DEVICE_CHECK_MIN_BODIES` bodies or more."""
    check_overlap_check(overlap_check)
    if overlap_check == "host":
        return False
    compound = any(is_compound(s) for s in scene.shapes.values())
    if overlap_check == "device":
        if compound or bodies is not None:
            raise ValueError(
                "overlap_check='device' takes a whole scene of convex grains: "
                + ("this one has compound grains" if compound else "this simulation steps a subset of the bodies")
                + "; use overlap_check='host' or 'auto'"
            )
        return True
    return (
        wp.get_device(device).is_cuda
        and not compound
        and bodies is None
        and scene.num_bodies >= DEVICE_CHECK_MIN_BODIES
    )


def device_pair_overlaps(scene, model, contacts, state):
    """The initial overlaps of body pairs (one free at least) among the contacts' candidate pairs, tested on their
    device: :class:`~polydem.scene.overlaps.OverlapRecords` for :meth:`Scene.finish_overlap_check`. The poses are
    the scene's, in float64 (a float32 state's are rounded: its own poses would move the depths by 1e-5 of them)."""
    device = model.body_shape.device
    body_q = state.body_q
    if body_q.dtype != wp.transformd:
        a = scene.body_arrays()
        body_q = wp.array(np.hstack([a["position"], a["orientation"]]), dtype=wp.transformd, device=device)
    geometry = OverlapGeometry(model.shapes, model.body_shape_np)
    bodies, rel, depth = launch_pair_overlaps(
        geometry,
        model.body_shape,
        model.body_flags,
        body_q,
        contacts.pair_a,
        contacts.pair_b,
        contacts.pair_count,
        len(contacts.pair_a),
        INITIAL_OVERLAP_WARNING,
        room=min(len(contacts.pair_a), max(1024, model.num_bodies // 8)),
    )
    return pair_records(rel, depth, bodies[:, 0], bodies[:, 1], scene.body_label)
