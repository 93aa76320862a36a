"""Self-tests of the independent float64 overlap reference (tests/reference_geometry.py)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

try:
    from reference_geometry import halfspaces_from_points, reference_overlap
except ImportError:  # tests/ imported as a package
    from tests.reference_geometry import halfspaces_from_points, reference_overlap


def box(lo, hi) -> np.ndarray:
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


UNIT = box([0, 0, 0], [1, 1, 1])


def random_hull(rng: np.random.Generator, n: int = 14) -> np.ndarray:
    """Random convex body: points on a perturbed ellipsoid, randomly rotated and offset."""
    dirs = rng.normal(size=(n, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    radii = rng.uniform(0.6, 1.4, size=3)
    pts = dirs * radii * rng.uniform(0.85, 1.0, size=(n, 1))
    rot = Rotation.random(random_state=rng).as_matrix()
    return pts @ rot.T + rng.uniform(-0.5, 0.5, size=3)


def random_pairs(count: int, seed: int):
    rng = np.random.default_rng(seed)
    pairs = []
    while len(pairs) < count:
        a = random_hull(rng)
        b = random_hull(rng)
        if reference_overlap(a, b)["volume"] > 0.05:
            pairs.append((a, b))
    return pairs


def rotate_about(points: np.ndarray, center: np.ndarray, axis: int, angle: float) -> np.ndarray:
    rv = np.zeros(3)
    rv[axis] = angle
    rot = Rotation.from_rotvec(rv).as_matrix()
    return (points - center) @ rot.T + center


def test_halfspaces_of_cube():
    normals, offsets = halfspaces_from_points(UNIT)
    assert normals.shape == (6, 3) and offsets.shape == (6,)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-14)
    # every vertex satisfies n.x <= d, and each plane is tight at 4 vertices
    res = UNIT @ normals.T - offsets
    assert res.max() <= 1e-14
    assert np.all((np.abs(res) <= 1e-14).sum(axis=0) == 4)


@pytest.mark.parametrize("shift", [(0.3, 0.2, -0.4), (-0.75, 0.1, 0.6), (0.05, -0.9, 0.33)])
def test_overlapping_unit_cubes(shift):
    shift = np.asarray(shift)
    out = reference_overlap(UNIT, UNIT + shift)
    lo = np.maximum(0.0, shift)
    hi = np.minimum(1.0, 1.0 + shift)
    np.testing.assert_allclose(out["volume"], np.prod(hi - lo), rtol=1e-12)
    np.testing.assert_allclose(out["centroid"], 0.5 * (lo + hi), atol=1e-12)
    # A contributes the faces of the intersection box on the side B was shifted to
    expected_s = np.array([np.sign(s) * np.prod(np.delete(hi - lo, i)) for i, s in enumerate(shift)])
    np.testing.assert_allclose(out["area_vector"], expected_s, atol=1e-12)
    np.testing.assert_allclose(out["area_vector_b"], -expected_s, atol=1e-12)


def test_cube_shifted_along_x_area_vector():
    out = reference_overlap(UNIT, UNIT + [0.3, 0.0, 0.0])
    np.testing.assert_allclose(out["volume"], 0.7, rtol=1e-12)
    np.testing.assert_allclose(out["centroid"], [0.65, 0.5, 0.5], atol=1e-12)
    np.testing.assert_allclose(out["area_vector"], [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(out["area_vector_b"], [-1.0, 0.0, 0.0], atol=1e-12)
    # A's +x face at x = 1 with centroid (1, .5, .5); coincident y/z faces cancel pairwise
    np.testing.assert_allclose(out["moment"], [0.0, 0.5, -0.5], atol=1e-12)
    np.testing.assert_allclose(out["moment_b"], [0.0, -0.5, 0.5], atol=1e-12)


def test_far_from_origin_is_conditioned():
    o = np.array([1e4, -3e4, 2e4])
    shift = np.array([0.3, 0.2, -0.4])
    near = reference_overlap(UNIT, UNIT + shift)
    far = reference_overlap(UNIT + o, UNIT + o + shift)
    np.testing.assert_allclose(far["volume"], near["volume"], rtol=1e-9)
    np.testing.assert_allclose(far["centroid"], near["centroid"] + o, rtol=1e-12, atol=1e-8)
    np.testing.assert_allclose(far["area_vector"], near["area_vector"], atol=1e-9)
    np.testing.assert_allclose(far["moment"], near["moment"] + np.cross(o, near["area_vector"]), rtol=1e-9, atol=1e-5)


@pytest.mark.parametrize("shift", [(1.5, 0.0, 0.0), (1.0, 0.2, 0.1), (0.0, 0.0, -1.0), (3.0, -2.0, 5.0)])
def test_separated_or_touching_bodies_give_zeros(shift):
    out = reference_overlap(UNIT, UNIT + np.asarray(shift))
    assert out["volume"] == 0.0
    for key in ("centroid", "area_vector", "moment", "area_vector_b", "moment_b"):
        assert np.all(out[key] == 0.0) and np.all(np.isfinite(out[key]))


def test_separated_random_hulls_give_zeros():
    rng = np.random.default_rng(7)
    a = random_hull(rng)
    b = random_hull(rng) + [10.0, 0.0, 0.0]
    assert reference_overlap(a, b)["volume"] == 0.0


def test_small_cube_inside_big_one():
    small = box([0.2, 0.3, 0.1], [0.5, 0.7, 0.35])
    big = box([-1, -1, -1], [2, 2, 2])
    out = reference_overlap(small, big)
    np.testing.assert_allclose(out["volume"], 0.3 * 0.4 * 0.25, rtol=1e-12)
    np.testing.assert_allclose(out["centroid"], [0.35, 0.5, 0.225], atol=1e-12)
    # every facet of the overlap is a facet of A: the closed surface sums to zero
    np.testing.assert_allclose(out["area_vector"], 0.0, atol=1e-12)
    np.testing.assert_allclose(out["moment"], 0.0, atol=1e-12)
    np.testing.assert_allclose(out["area_vector_b"], 0.0, atol=0.0)
    # swapped roles: A big, B small
    out2 = reference_overlap(big, small)
    np.testing.assert_allclose(out2["volume"], 0.03, rtol=1e-12)
    np.testing.assert_allclose(out2["area_vector"], 0.0, atol=0.0)
    np.testing.assert_allclose(out2["area_vector_b"], 0.0, atol=1e-12)


def test_random_pairs_closed_surface_and_volume():
    for a, b in random_pairs(8, seed=1):
        out = reference_overlap(a, b)
        np.testing.assert_allclose(out["area_vector"] + out["area_vector_b"], 0.0, atol=1e-12)
        np.testing.assert_allclose(out["moment"] + out["moment_b"], 0.0, atol=1e-12)
        assert np.linalg.norm(out["area_vector"]) > 1e-3
        # symmetric in the roles of A and B
        swapped = reference_overlap(b, a)
        np.testing.assert_allclose(swapped["volume"], out["volume"], rtol=1e-12)
        np.testing.assert_allclose(swapped["centroid"], out["centroid"], atol=1e-12)
        np.testing.assert_allclose(swapped["area_vector"], out["area_vector_b"], atol=1e-12)
        np.testing.assert_allclose(swapped["moment"], out["moment_b"], atol=1e-12)


def test_random_pairs_volume_monte_carlo():
    """Coarse independent check of V and the centroid by rejection sampling."""
    rng = np.random.default_rng(3)
    for a, b in random_pairs(2, seed=11):
        out = reference_overlap(a, b)
        na, da = halfspaces_from_points(a)
        nb, db = halfspaces_from_points(b)
        lo = np.minimum(a.min(axis=0), b.min(axis=0))
        hi = np.maximum(a.max(axis=0), b.max(axis=0))
        x = rng.uniform(lo, hi, size=(400_000, 3))
        inside = np.all(x @ na.T <= da, axis=1) & np.all(x @ nb.T <= db, axis=1)
        v_mc = inside.mean() * np.prod(hi - lo)
        assert abs(v_mc - out["volume"]) < 0.03 * out["volume"] + 1e-3
        np.testing.assert_allclose(x[inside].mean(axis=0), out["centroid"], atol=0.02)


def test_translation_gradient_matches_area_vector():
    h = 1e-6
    for a, b in random_pairs(6, seed=2):
        out = reference_overlap(a, b)
        grad = np.empty(3)
        for i in range(3):
            e = np.zeros(3)
            e[i] = h
            grad[i] = (reference_overlap(a + e, b)["volume"] - reference_overlap(a - e, b)["volume"]) / (2 * h)
        np.testing.assert_allclose(grad, out["area_vector"], atol=1e-6)
        # and for B
        grad_b = np.empty(3)
        for i in range(3):
            e = np.zeros(3)
            e[i] = h
            grad_b[i] = (reference_overlap(a, b + e)["volume"] - reference_overlap(a, b - e)["volume"]) / (2 * h)
        np.testing.assert_allclose(grad_b, out["area_vector_b"], atol=1e-6)


def test_rotation_gradient_matches_moment():
    h = 1e-6
    for a, b in random_pairs(6, seed=4):
        out = reference_overlap(a, b)
        c_a = a.mean(axis=0)
        expected = out["moment"] - np.cross(c_a, out["area_vector"])
        grad = np.empty(3)
        for i in range(3):
            vp = reference_overlap(rotate_about(a, c_a, i, h), b)["volume"]
            vm = reference_overlap(rotate_about(a, c_a, i, -h), b)["volume"]
            grad[i] = (vp - vm) / (2 * h)
        np.testing.assert_allclose(grad, expected, atol=1e-6)
