"""The pair-kernel variants (how pair_geometry holds its working set) give the same bits.

Each variant of :func:`polydem.kernels.geometry.make_geometry` only moves data differently
(planes recomputed where read, active faces as bitmasks, the polygon streamed), so every output of
the overlap kernel must equal that of the "buffered" variant (per-thread tables, as before the
variants) bit for bit: on random pairs of cubes, rocks and a 64-vertex hull (shallow, deep and
separated), on stacked aligned cubes (the coincident-face rule) and on enclosed pairs (the fallback).
"""

import numpy as np
import pytest
import warp as wp
from polydem.kernels.geometry import DEFAULT_PAIR_VARIANT, PAIR_FEATURES, make_geometry, pair_variant
from polydem.kernels.narrowphase import OVERLAP_OUTPUTS, launch_overlap
from scipy.spatial.transform import Rotation

from polydem import ConvexShape
from polydem.shapeset import ShapeSet

ALL_FEATURES = "+".join(PAIR_FEATURES)
SETS = {
    # At most 64 faces per shape: the "masks" feature is in use.
    "cube_rock": lambda: [ConvexShape.box(1.0), ConvexShape.rock(n_points=20, size=0.7, seed=1)],
    # 64 to 128 faces: the masks take two words.
    "hull64": lambda: [ConvexShape.rock(n_points=64, size=1.0, seed=2), ConvexShape.box(0.5)],
}


def random_pairs(shapes, rng, n):
    """Shape indices and poses: random pairs at every depth (about half touching), aligned stacked
    copies of shape 0 (coincident faces, some shifted sideways) and pairs with one body inside."""
    k = len(shapes)
    sa = rng.integers(0, k, n)
    sb = rng.integers(0, k, n)
    reach = np.array([s.radius for s in shapes])
    qa = Rotation.random(n, random_state=rng).as_quat()
    qb = Rotation.random(n, random_state=rng).as_quat()
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    dist = rng.uniform(0.0, 1.1, n) * (reach[sa] + reach[sb])
    pa = np.hstack([rng.uniform(-2.0, 2.0, (n, 3)), qa])
    pb = np.hstack([pa[:, :3] + u * dist[:, None], qb])
    # Aligned copies of shape 0 stacked along z, 0-2% into each other, some shifted sideways.
    m = n // 8
    rows = np.arange(m)
    sa[rows] = 0
    sb[rows] = 0
    h = 2.0 * np.asarray(shapes[0].vertices)[:, 2].max()
    pa[rows] = [0.3, -0.2, 0.1, 0.0, 0.0, 0.0, 1.0]
    pb[rows, :3] = pa[rows, :3] + np.column_stack(
        [rng.choice([0.0, 0.25], m) * h, np.zeros(m), h * (1.0 - rng.uniform(0.0, 0.02, m))]
    )
    pb[rows, 3:] = pa[rows, 3:]
    # One body (nearly) inside the other: the fallback direction.
    rows = np.arange(m, 2 * m)
    pb[rows, :3] = pa[rows, :3] + rng.uniform(-0.05, 0.05, (m, 3))
    return sa, sb, pa, pb


def run(shapes, sa, sb, pa, pb, variant, pose_scalar, device):
    scalar = shapes.scalar
    tf = wp.types.transformation(pose_scalar)
    np_pose = np.float64 if pose_scalar == wp.float64 else np.float32
    n = len(sa)
    vec3 = wp.types.vector(3, scalar)
    out = {name: wp.zeros(n, dtype=vec3, device=device) for name in OVERLAP_OUTPUTS[1:]}
    out["pair_volume"] = wp.zeros(n, dtype=scalar, device=device)
    ns = launch_overlap(
        shapes,
        wp.array(sa.astype(np.int32), dtype=int, device=device),
        wp.array(sb.astype(np.int32), dtype=int, device=device),
        wp.array(pa.astype(np_pose), dtype=tf, device=device),
        wp.array(pb.astype(np_pose), dtype=tf, device=device),
        out,
        pose_scalar=pose_scalar,
        variant=variant,
    )
    assert ns.geometry.variant == pair_variant(variant)
    return {name: out[name].numpy() for name in OVERLAP_OUTPUTS}


@pytest.mark.parametrize("precision", ["float32", "mixed", "float64"])
@pytest.mark.parametrize("shape_set", sorted(SETS))
def test_variants_agree_bit_for_bit(device, shape_set, precision):
    shapes_list = SETS[shape_set]()
    shapes = ShapeSet(shapes_list, device=device, precision="float64" if precision == "float64" else "float32")
    assert (shapes.max_faces <= 64) == (shape_set == "cube_rock") and shapes.max_faces <= 128
    pose_scalar = wp.float32 if precision == "float32" else wp.float64
    sa, sb, pa, pb = random_pairs(shapes_list, np.random.default_rng(7), 1024)
    ref = run(shapes, sa, sb, pa, pb, "buffered", pose_scalar, device)
    touching = ref["pair_volume"] > 0.0
    assert 0.3 * len(sa) < touching.sum() < 0.9 * len(sa)  # overlapping and separated pairs both
    assert (np.linalg.norm(ref["pair_fallback_a"], axis=1) > 0.0).sum() > 10  # enclosed pairs
    for variant in sorted({*PAIR_FEATURES, "masks+popc", ALL_FEATURES, DEFAULT_PAIR_VARIANT}):
        got = run(shapes, sa, sb, pa, pb, variant, pose_scalar, device)
        # On CUDA the compiler may contract a streamed vertex's arithmetic (read from the shape or
        # held back) otherwise than a buffered one's: those variants agree to rounding there (seen
        # on an H100: the all-features variant's V differed in the last bits). Everything else,
        # and everything on the CPU, agrees bit for bit.
        streamed = "stream" in variant and wp.get_device(device).is_cuda
        for name in OVERLAP_OUTPUTS:
            a = got[name].reshape(len(sa), -1)
            b = ref[name].reshape(len(sa), -1)
            if streamed:
                scale = float(np.max(np.abs(b))) if b.size else 0.0
                bad = ~np.all(np.abs(a - b) <= 1e-4 * np.abs(b) + 1e-6 * scale, axis=1)
                assert not bad.any(), (
                    f"{variant}: {name} differs from 'buffered' beyond rounding in {np.flatnonzero(bad)[:10]}"
                )
                continue
            # Compared as raw bytes: equal bits, not merely equal values (-0.0 == 0.0).
            same = np.all(a.view(np.uint8) == b.view(np.uint8), axis=1)
            assert same.all(), f"{variant}: {name} differs from 'buffered' in {np.flatnonzero(~same)[:10]}"


def test_variant_names():
    assert pair_variant("stream-out+planes") == "planes+stream-out"
    assert pair_variant("buffered") == "buffered"
    assert make_geometry(wp.float32, 8, 6, variant="masks+planes").variant == "planes+masks"
    with pytest.raises(ValueError, match="unknown pair-kernel variant"):
        pair_variant("planes+fast")
