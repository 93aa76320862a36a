"""Overlap geometry of bodies that may be compound grains (rigid unions of convex parts).

A body's shape s is made of the parts ``shapes.shape_part_start[s] .. [s + 1]``: part k is the
convex shape ``part_shape[k]`` at the pose ``part_q[k]`` in the body's frame (a convex shape is its
own single part). The functions here loop over the part pairs, clip each with the convex pair
geometry (:mod:`polydem.kernels.geometry`), move what it returns from the part's centre to the
body's, and sum: V, its first moment, S_A, M_A, S_B, M_B and the fallback area vector. The contact
law is then applied once to the sums (see :mod:`polydem.compound` for what the sum means where parts
of one grain overlap each other).

Variants: :func:`make_body_geometry` with ``compound=False`` returns the convex functions as they
are, so that a scene without compound grains pays nothing for them.
"""

import functools
from dataclasses import dataclass
from typing import Any

import warp as wp


@dataclass(frozen=True)
class BodyGeometry:
    """Overlap geometry per body pair and per body and plane wall, compound grains included."""

    compound: bool
    pair_geometry: Any  # (shapes, sa, sb, xa, xb) -> (V, first moment, S_A, M_A, S_B, M_B, fallback_A, overflow)
    plane_geometry: Any  # (shapes, s, xa, normal, offset) -> (V, first moment, S_A, M_A, fallback)
    pair_depth: Any  # (shapes, sa, sb, xa, xb) -> depth [m]
    plane_depth: Any  # (shapes, s, xa, normal, offset) -> depth [m]


@functools.cache
def make_body_geometry(geom, compound: bool) -> BodyGeometry:
    """The body-level geometry for a :class:`~polydem.kernels.geometry.Geometry`: with
    ``compound`` the part loops, without it the convex functions themselves."""
    prim = geom.primitives
    if not compound:
        return BodyGeometry(False, geom.pair_geometry, prim.plane_geometry, geom.pair_depth, prim.plane_depth)

    C = geom.scalar
    P = geom.pose_scalar
    Shapes = geom.shapes
    vec3c = wp.types.vector(3, C)
    vec3p = wp.types.vector(3, P)
    quat_p = wp.types.quaternion(P)
    transform_p = wp.types.transformation(P)
    zero3 = wp.constant(vec3c(C(0.0), C(0.0), C(0.0)))
    # The convex functions are called through ``geom`` (pair geometry and depth) and ``prim`` (the rest).

    @wp.func
    def part_pose(shapes: Shapes, x: transform_p, k: int):
        """Part k's pose in world (pose scalar), and its centre's offset from the body's centre
        (world axes, contact scalar)."""
        pq = shapes.part_q[k]
        x64, q64 = prim.pose_to_f64(x)
        d64 = wp.quat_rotate(q64, wp.transform_get_translation(pq))
        p64 = x64 + d64
        q = q64 * wp.transform_get_rotation(pq)
        pose = transform_p(vec3p(P(p64[0]), P(p64[1]), P(p64[2])), quat_p(P(q[0]), P(q[1]), P(q[2]), P(q[3])))
        return pose, prim.to_scalar3(d64)

    @wp.func
    def add_part(
        vol: C, first_moment: vec3c, s_a: vec3c, m_a: vec3c, fb_a: vec3c,
        v: C, fm: vec3c, sa_k: vec3c, ma_k: vec3c, fb_k: vec3c, d: vec3c,
    ):  # fmt: skip
        # The sums with a part's overlap, moved from the part's centre to the body's (d from the
        # body's to the part's): x = x' + d moves a first moment by V d and a moment of areas by d x S.
        return vol + v, first_moment + (fm + v * d), s_a + sa_k, m_a + (ma_k + wp.cross(d, sa_k)), fb_a + fb_k

    @wp.func
    def no_overlap():
        # The sums before the first part that overlaps: V, its first moment, S_A, M_A, the fallback.
        return C(0.0), zero3, zero3, zero3, zero3

    @wp.func
    def pair_geometry(shapes: Shapes, sa: int, sb: int, xa: transform_p, xb: transform_p):
        vol, first_moment, s_a, m_a, fb_a = no_overlap()
        s_b = zero3
        m_b = zero3
        overflow = int(0)
        for i in range(shapes.shape_part_start[sa], shapes.shape_part_start[sa + 1]):
            xpa, da = part_pose(shapes, xa, i)
            for j in range(shapes.shape_part_start[sb], shapes.shape_part_start[sb + 1]):
                xpb, db = part_pose(shapes, xb, j)
                v, fm, sa_k, ma_k, sb_k, mb_k, fb_k, of = geom.pair_geometry(
                    shapes, shapes.part_shape[i], shapes.part_shape[j], xpa, xpb
                )
                overflow = wp.max(overflow, of)
                if v > C(0.0):
                    vol, first_moment, s_a, m_a, fb_a = add_part(
                        vol, first_moment, s_a, m_a, fb_a, v, fm, sa_k, ma_k, fb_k, da
                    )
                    # B's moments are about A's centre too: moved by the same d.
                    s_b += sb_k
                    m_b += mb_k + wp.cross(da, sb_k)
        return vol, first_moment, s_a, m_a, s_b, m_b, fb_a, overflow

    @wp.func
    def plane_geometry(shapes: Shapes, s: int, xa: transform_p, normal: vec3p, offset: P):
        vol, first_moment, s_a, m_a, fb_a = no_overlap()
        for i in range(shapes.shape_part_start[s], shapes.shape_part_start[s + 1]):
            xp, d = part_pose(shapes, xa, i)
            v, fm, sa_k, ma_k, fb_k = prim.plane_geometry(shapes, shapes.part_shape[i], xp, normal, offset)
            if v > C(0.0):
                vol, first_moment, s_a, m_a, fb_a = add_part(
                    vol, first_moment, s_a, m_a, fb_a, v, fm, sa_k, ma_k, fb_k, d
                )
        return vol, first_moment, s_a, m_a, fb_a

    @wp.func
    def pair_depth(shapes: Shapes, sa: int, sb: int, xa: transform_p, xb: transform_p):
        """The deepest penetration of a part of A into a part of B [m]."""
        depth = C(0.0)
        for i in range(shapes.shape_part_start[sa], shapes.shape_part_start[sa + 1]):
            xpa, da = part_pose(shapes, xa, i)
            for j in range(shapes.shape_part_start[sb], shapes.shape_part_start[sb + 1]):
                xpb, db = part_pose(shapes, xb, j)
                depth = wp.max(depth, geom.pair_depth(shapes, shapes.part_shape[i], shapes.part_shape[j], xpa, xpb))
        return depth

    @wp.func
    def plane_depth(shapes: Shapes, s: int, xa: transform_p, normal: vec3p, offset: P):
        depth = C(0.0)
        for i in range(shapes.shape_part_start[s], shapes.shape_part_start[s + 1]):
            xp, d = part_pose(shapes, xa, i)
            depth = wp.max(depth, prim.plane_depth(shapes, shapes.part_shape[i], xp, normal, offset))
        return depth

    return BodyGeometry(True, pair_geometry, plane_geometry, pair_depth, plane_depth)
