"""benchmarks/peers/newton_pour.py's estimate of Newton's SAP work (BENCHMARKS.md 26f) against a slow count: every
pair of shapes, each AABB from its rotated vertices. Newton itself is not needed (on the CPU machine with Newton
1.8 the estimate equalled its own count for the 1e4 pour, 4,758,375)."""

import itertools

import numpy as np
import pytest
from benchmark_scripts import load_benchmark


@pytest.fixture(scope="module")
def newton_pour():
    return load_benchmark("peers/newton_pour", "newton_pour_benchmark")


def rotate(q_xyzw, v):
    x, y, z, w = q_xyzw
    u = np.array([x, y, z])
    return v + 2.0 * w * np.cross(u, v) + 2.0 * np.cross(u, np.cross(u, v))


def random_export(n, seed):
    rng = np.random.default_rng(seed)
    edge = 0.01
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    corners = [
        [sx * 0.5 * edge, sy * 0.5 * edge, sz * 0.5 * edge] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)
    ]
    wq = rng.normal(size=4)
    wq /= np.linalg.norm(wq)
    return {
        "edge": edge,
        "cube_body_vertices": corners,
        "cubes": {"position": rng.uniform(0.0, 0.08, size=(n, 3)).tolist(), "orientation_xyzw": q.tolist()},
        "walls": [
            {
                "center": [0.04, 0.04, -0.005],
                "orientation_xyzw": [0.0, 0.0, 0.0, 1.0],
                "half_extents_body": [0.05, 0.05, 0.005],
            },
            {"center": [0.0, 0.04, 0.04], "orientation_xyzw": wq.tolist(), "half_extents_body": [0.04, 0.005, 0.03]},
        ],
    }


def slow_count(sc, gap, direction):
    boxes = []
    for p, q in zip(sc["cubes"]["position"], sc["cubes"]["orientation_xyzw"], strict=True):
        world = np.array([rotate(q, np.asarray(v)) for v in sc["cube_body_vertices"]]) + p
        boxes.append((world.min(0), world.max(0)))
    for w in sc["walls"]:
        h = np.asarray(w["half_extents_body"])
        world = np.array([rotate(w["orientation_xyzw"], h * s) for s in itertools.product((-1, 1), repeat=3)])
        world += w["center"]
        boxes.append((world.min(0), world.max(0)))
    d = direction / np.linalg.norm(direction)
    spans = [
        (
            (lo - gap) @ np.clip(d, 0, None) + (hi + gap) @ np.clip(d, None, 0),
            (hi + gap) @ np.clip(d, 0, None) + (lo - gap) @ np.clip(d, None, 0),
        )
        for lo, hi in boxes
    ]
    count = 0
    for (a_lo, a_hi), (b_lo, b_hi) in itertools.combinations(spans, 2):
        first_hi, second_lo = (a_hi, b_lo) if a_lo <= b_lo else (b_hi, a_lo)
        count += second_lo < first_hi
    return count


@pytest.mark.parametrize(("n", "seed", "gap"), [(60, 0, 0.0), (60, 1, 0.002), (150, 2, 0.001)])
def test_the_sap_estimate_counts_every_overlapping_projection(newton_pour, n, seed, gap):
    sc = random_export(n, seed)
    estimate = newton_pour.sap_work_estimate(sc, gap)
    assert estimate == slow_count(sc, gap, newton_pour.NEWTON_SAP_DIRECTION)
    assert 0 < estimate < n * (n + 1) // 2
