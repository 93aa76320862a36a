"""The host build without Python loops over bodies (issue 27): each vectorised path against the loop it replaced
(kept here as the reference), bit for bit where the build's arrays or messages come from it."""

import numpy as np
import pytest

from polydem import ConvexShape, Scene, SceneError
from polydem.compound import CompoundShape, expand_bodies, place
from polydem.model import Model, _body_motions
from polydem.quaternions import quat_from_matrices, quat_from_matrix, quat_to_matrix
from polydem.scene import overlaps
from polydem.scene.emitters import _lowest_cells


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# ------------------------------------------------------------------------------------------ motions


def test_body_motions_lookup_matches_the_per_body_lookup():
    rng = np.random.default_rng(1)
    for trial in range(50):
        n = int(rng.integers(1, 400))
        driven = rng.choice(n, size=int(rng.integers(0, n + 1)), replace=False)
        names = ["a", "b", "c", "unknown"]
        body_motion = {int(i): str(rng.choice(names)) for i in driven}
        which = {"a": 0, "b": 1, "c": 2}
        index = rng.permutation(n)[: int(rng.integers(1, n + 1))].astype(np.int64)
        reference = np.array([which.get(body_motion.get(int(i)), -1) for i in index], dtype=np.int32)
        got = _body_motions(body_motion, which, index)
        assert got.dtype == np.int32
        np.testing.assert_array_equal(got, reference, err_msg=str(trial))


def driven_scene():
    """Free cubes in a box that follows a cycle, and kinematic plates that follow another (no contacts between
    the plates and the cubes: the test reads the model's arrays alone)."""
    sc = Scene(gravity=(0.0, 0.0, -9.81), dt="auto")
    sc.add_material("m", density=2500.0, law="hertz", k=5e8, restitution=0.5, friction=0.5)
    sc.add_shape("cube", ConvexShape.box(0.01))
    sc.add_shape("plate", ConvexShape.box(0.03, 0.03, 0.005))
    sc.add_motion("shake", 20.0, amplitude=1e-3)
    sc.add_motion("tap", 5.0, amplitude=2e-3, period=0.5, count=2)
    g = np.stack(np.meshgrid(np.arange(4), np.arange(4), np.arange(3), indexing="ij"), -1).reshape(-1, 3)
    sc.add_bodies("cube", "m", (g - 1.5) * 0.02 + [0.0, 0.0, 0.04])
    plates = sc.add_bodies("plate", "m", [[0.5, 0.0, 0.1], [0.6, 0.0, 0.1], [0.7, 0.0, 0.1]], kind="kinematic")
    sc.drive(plates[[0, 2]], "tap")
    sc.add_box_container((0.0, 0.0, 0.06), (0.1, 0.1, 0.12), "m", motion="shake")
    return sc


def test_model_motions_of_the_whole_scene_and_of_a_share(device):
    sc = driven_scene()
    which = {name: k for k, name in enumerate(sc.motions)}
    for bodies in (None, np.array([50, 3, 49, 52, 0, 48, 51]), np.arange(sc.num_bodies)[::-1].copy()):
        model = Model(sc, device, bodies=bodies)
        index = model.body_index
        reference = np.array([which.get(sc.body_motion.get(int(i)), -1) for i in index], dtype=np.int32)
        np.testing.assert_array_equal(model.body_motion.numpy(), reference)
        np.testing.assert_array_equal(model.body_rest.numpy(), sc.body_position[index])
        assert model.has_motions


def test_drive_takes_the_bodies_before_a_refused_one():
    sc = driven_scene()
    assert np.flatnonzero(sc.body_kind == 2)[:3].tolist() == [48, 49, 50]  # the plates, then the box's walls
    before = dict(sc.body_motion)
    sc.drive(np.array([49]), "shake")
    assert sc.body_motion[49] == "shake" and list(sc.body_motion) == [*before, 49]
    with pytest.raises(SceneError, match=r"body 7 is not a kinematic body of this scene"):
        sc.drive([48, 49, 7, 50], "shake")
    assert [sc.body_motion[i] for i in (48, 49, 50)] == ["shake", "shake", "tap"]  # one by one, up to body 7
    assert list(sc.body_motion) == [*before, 49]  # in the order they were first driven
    with pytest.raises(SceneError, match=r"body 99 is not a kinematic body"):
        sc.drive([99], "tap")


# ------------------------------------------------------------------------------------------ rotations


def test_quat_from_matrices_is_quat_from_matrix_bit_for_bit():
    rng = np.random.default_rng(2)
    r = quat_to_matrix(random_quats(rng, 20000))
    # Near the branches' edges: half turns, the identity, axis swaps.
    axis = rng.normal(size=(2000, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.pi - rng.random(2000) * 1e-7
    half = np.column_stack([axis * np.sin(angle / 2)[:, None], np.cos(angle / 2)])
    special = np.array([np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])])
    r = np.concatenate([r, quat_to_matrix(half), special, r @ r[::-1]])
    got = quat_from_matrices(r)
    reference = np.array([quat_from_matrix(m) for m in r])
    assert got.view(np.int64).tolist() == reference.view(np.int64).tolist()
    assert quat_from_matrices(r[:6].reshape(2, 3, 3, 3)).shape == (2, 3, 4)


def test_expand_bodies_part_orientations_bit_for_bit():
    h = 0.01
    qz = [0.0, 0.0, np.sin(np.pi / 8), np.cos(np.pi / 8)]
    grain = CompoundShape(
        [place(ConvexShape.box(h, h / 2, h), (-h / 4, 0, 0), qz), place(ConvexShape.box(h / 2, h, h))]
    )
    rng = np.random.default_rng(3)
    n = 500
    q = random_quats(rng, n)
    shapes = [ConvexShape.box(h), grain]
    sid = rng.integers(0, 2, n)
    convex, part, pos, quat, owner = expand_bodies(shapes, sid, rng.normal(size=(n, 3)), q)
    rot_b = quat_to_matrix(q[owner])
    frames = [np.eye(3)] + [grain.part_rotation[k] for k in range(grain.num_parts)]
    rot_p = np.array(frames)[part]
    moved = ~np.all(rot_p == np.eye(3), axis=(1, 2))
    assert moved.any()
    reference = q[owner].copy()
    reference[moved] = [quat_from_matrix(m) for m in rot_b[moved] @ rot_p[moved]]
    assert quat.view(np.int64).tolist() == reference.view(np.int64).tolist()


# ------------------------------------------------------------------------------------------ scene checks


def test_lowest_cells_are_the_first_of_the_sort_by_layer_and_draw():
    rng = np.random.default_rng(5)
    for _ in range(300):
        layer = np.sort(rng.integers(0, 6, int(rng.integers(1, 300))))
        draw = rng.choice([0.1, 0.2, 0.3, 0.5], len(layer)) if rng.random() < 0.5 else rng.random(len(layer))
        count = int(rng.integers(1, len(layer) + 1))
        reference = np.sort(np.lexsort((draw, layer))[:count])
        np.testing.assert_array_equal(_lowest_cells(layer, draw, count), reference)


# ------------------------------------------------------------------------------------------ initial overlaps


def test_deepest_of_each_pair_is_the_record_loop():
    rng = np.random.default_rng(6)
    for _ in range(300):
        m = int(rng.integers(1, 60))
        rel = rng.choice([0.02, 0.05, 0.1, 0.3], m)
        key = rng.integers(0, 8, m) if rng.random() < 0.7 else rng.permutation(m)
        # The loop the vectorised pass replaced: a record per new pair or deeper one, then the deepest per pair.
        seen, out = {}, []
        for k in range(m):
            if key[k] in seen and seen[key[k]] >= rel[k]:
                continue
            seen[key[k]] = rel[k]
            out.append(k)
        best = {}
        for k in out:
            if key[k] not in best or rel[k] > rel[best[key[k]]]:
                best[key[k]] = k
        np.testing.assert_array_equal(overlaps._deepest_of_each_pair(rel, key), list(best.values()))


def test_candidate_pairs_are_the_pairs_of_meeting_spheres():
    rng = np.random.default_rng(7)
    n = 3000
    pos = rng.uniform(-1.0, 1.0, (n, 3))
    rad = np.full(n, 0.03)
    rad[:3] = [5.0, 0.5, 0.3]  # a sphere holding every body (the pass), two holding few (the query's lists)
    rad[3:40] = rng.uniform(0.2, 0.4, 37)
    pairs = overlaps._candidate_pairs(pos, rad)
    d = np.linalg.norm(pos[:, None] - pos[None], axis=2)
    meet = np.argwhere(np.triu(d < rad[:, None] + rad[None], 1))
    as_sets = {tuple(sorted(p)) for p in pairs.tolist()}
    assert len(as_sets) == len(pairs) and as_sets == {tuple(p) for p in meet.tolist()}
    # A first cut of the big bodies' candidates keeps their order and drops only what it drops.
    keep_odd = lambda b, pos_t, rad_idx: np.isin(pos_t[0], pos[1::2, 0])  # noqa: E731
    cut = overlaps._candidate_pairs(pos, rad, keep_odd, 0.0)
    big = rad > 4.0 * np.median(rad)
    dropped = big[pairs[:, 0]] & ~big[pairs[:, 1]] & (pairs[:, 1] % 2 == 0)
    np.testing.assert_array_equal(cut, pairs[~dropped])


SHAPES = {
    "cube": ConvexShape.box(0.01),
    "tet": ConvexShape.tetrahedron(0.015),
    "rock": ConvexShape.rock(20, size=0.012, seed=1),
    "slab": ConvexShape.box(0.02, 0.006, 0.012),
}


@pytest.mark.parametrize("pair", [("cube", "cube"), ("cube", "tet"), ("rock", "slab"), ("tet", "rock")])
def test_apart_never_drops_an_overlap(pair):
    sa, sb = SHAPES[pair[0]], SHAPES[pair[1]]
    rng = np.random.default_rng(8)
    p = 20000
    d = rng.normal(size=(p, 3)) * 0.008
    qa, qb = random_quats(rng, p), random_quats(rng, p)
    ra, rb = quat_to_matrix(qa), quat_to_matrix(qb)
    ea, eb = overlaps.edge_directions(sa), overlaps.edge_directions(sb)
    depth, thin = overlaps._sat_depth(sa, sb, np.zeros((p, 3)), d, ra, rb, ea, eb)
    rot_a, rot_b = overlaps._rotations(qa), overlaps._rotations(qb)
    apart = overlaps._apart(sa, sb, np.ascontiguousarray(d.T), rot_a, rot_b, np.full(p, 1e-15))
    assert 0.2 < apart.mean() < 0.95
    assert not np.any(apart & (depth > 0.0))


def slow_pair_records(shapes, a):
    """Every pair of bodies (one free) through the separating-axis test, no cuts: (rel, depth, free body, other)."""
    n = len(a["kind"])
    ii, jj = np.triu_indices(n, 1)
    free = a["kind"] == 0
    out = set()
    sid = a["shape"]
    for g in {(int(x), int(y)) for x, y in zip(sid[ii], sid[jj], strict=True)}:
        rows = np.flatnonzero((sid[ii] == g[0]) & (sid[jj] == g[1]) & (free[ii] | free[jj]))
        if not rows.size:
            continue
        i, j = ii[rows], jj[rows]
        sa, sb = shapes[g[0]], shapes[g[1]]
        ra, rb = quat_to_matrix(a["orientation"][i]), quat_to_matrix(a["orientation"][j])
        edges = overlaps.edge_directions(sa), overlaps.edge_directions(sb)
        depth, thin = overlaps._sat_depth(sa, sb, a["position"][i], a["position"][j], ra, rb, *edges)
        for k in np.flatnonzero(depth / thin > overlaps.INITIAL_OVERLAP_WARNING).tolist():
            b1, b2 = (i[k], j[k]) if free[i[k]] else (j[k], i[k])
            out.add((float(depth[k] / thin[k]), float(depth[k]), int(b1), int(b2)))
    return out


def test_pair_overlaps_find_every_overlap_of_the_slow_test():
    sc = Scene(gravity=(0.0, 0.0, -9.81), dt="auto")
    sc.add_material("m", density=2500.0, law="hertz", k=1e9, restitution=0.5, friction=0.5)
    for name, shape in SHAPES.items():
        sc.add_shape(name, shape)
    rng = np.random.default_rng(9)
    n = 240
    pos = rng.uniform(-0.034, 0.034, (n, 3))
    q = random_quats(rng, n)
    for k, name in enumerate(SHAPES):
        sc.add_bodies(name, "m", pos[k * 60 : (k + 1) * 60], orientations=q[k * 60 : (k + 1) * 60])
    sc.add_box_container((0.0, 0.0, 0.0), (0.06, 0.06, 0.06), "m", wall_thickness=0.01)
    a = sc.body_arrays()
    shapes = list(sc.shapes.values())
    found = overlaps._pair_overlaps(shapes, sc.body_label, a)
    got = {
        (float(found.rel[k]), float(found.depth[k]), int(found.body[k]), int(found.words(k)[0].split()[2]))
        for k in range(len(found))
    }
    assert len(got) == len(found) > 100
    assert got == slow_pair_records(shapes, a)


def test_report_overlaps_of_records_and_of_tuples_alike():
    sc = Scene(gravity=(0.0, 0.0, -9.81), dt="auto")
    sc.add_material("m", density=2500.0, law="hertz", k=1e9, restitution=0.5, friction=0.5)
    sc.add_shape("cube", ConvexShape.box(0.01))
    sc.add_bodies("cube", "m", np.arange(6)[:, None] * [0.02, 0.0, 0.0])
    tuples = [(0.2, 0.002, 3, "into x", "basis", "fix a"), (0.3, 0.003, 1, "into y", "basis", "fix b")]
    tuples += [(0.2, 0.001, 4, "into z", "basis", "fix c"), (0.05, 0.0005, 5, "into w", "basis", "fix d")]
    records = overlaps.OverlapRecords(
        [t[0] for t in tuples], [t[1] for t in tuples], [t[2] for t in tuples], lambda k: tuples[k][3:6]
    )
    head, fix = "initial overlaps", "move them"
    assert overlaps.report_overlaps(sc, list(tuples), head, fix) == overlaps.report_overlaps(sc, records, head, fix)
    deep = [*tuples, (0.7, 0.007, 2, "into v", "its width", "fix e"), (0.6, 0.006, 0, "into u", "basis", "fix f")]
    messages = []
    for given in (deep, overlaps.OverlapRecords.of_tuples(deep)):
        with pytest.raises(SceneError) as err:
            overlaps.report_overlaps(sc, given, head, fix)
        messages.append(str(err.value))
    assert messages[0] == messages[1] and "(1 more bodies start this deep)" in messages[0]


def test_distinct_codes_are_numpys_unique():
    from polydem.scene.values import distinct_codes

    rng = np.random.default_rng(11)
    for size, n in ((1, 5), (7, 1000), (40, 3), (12, 0)):
        codes = rng.integers(0, size, n).astype(np.int32)
        np.testing.assert_array_equal(distinct_codes(codes, size), np.unique(codes))


def test_row_norms_are_numpys_bit_for_bit():
    from polydem.scene.values import row_norms

    rng = np.random.default_rng(12)
    x = rng.normal(size=(5000, 3)) * rng.uniform(0.0, 1e3, (5000, 1))
    x[:7] = 0.0
    np.testing.assert_array_equal(row_norms(x), np.linalg.norm(x, axis=1))


# ------------------------------------------------------------------------- codes, time step, run settings


def test_body_codes_are_the_int64_codes_in_the_smallest_dtype_that_holds_them():
    from polydem.scene.values import body_codes

    rng = np.random.default_rng(13)
    shape, material = rng.integers(0, 5, 300).astype(np.int32), rng.integers(0, 3, 300).astype(np.int32)
    codes = body_codes(shape, material, 5, 3)
    assert codes.dtype == np.int32
    np.testing.assert_array_equal(codes, shape.astype(np.int64) * 3 + material)
    big = body_codes(shape, material, 2**20, 2**12)  # 2^32 codes: past int32
    assert big.dtype == np.int64
    np.testing.assert_array_equal(big, shape.astype(np.int64) * 2**12 + material)


@pytest.mark.parametrize("wanted_count", [0, 1, 3, 8, 9, 30])
def test_first_with_code_is_the_first_index_of_any_wanted_code(wanted_count):
    from polydem.scene.values import FEW_CODES, first_with_code

    assert FEW_CODES == 8  # the parameters take both sides of it
    rng = np.random.default_rng(wanted_count)
    for trial in range(40):
        size = int(rng.integers(1, 60))
        codes = rng.integers(0, size + 1, int(rng.integers(0, 500))).astype(np.int32)
        wanted = rng.choice(size + 1, size=min(wanted_count, size + 1), replace=False)
        if trial % 3 == 0:  # codes outside [0, size] never match
            wanted = np.concatenate([wanted, [-1, -size - 1, size + 1, 2 * size + 3]])
        hits = np.flatnonzero(np.isin(codes, wanted[(wanted >= 0) & (wanted <= size)]))
        assert first_with_code(codes, wanted, size) == (int(hits[0]) if hits.size else -1), trial


def many_kinds_scene(rng, n, kinds=(0, 1, 2), moving=False):
    """Bodies of three shapes and four materials (two of the same density: equal masses), kinds at random; with
    ``moving`` the free bodies start at random velocities and spins."""
    from polydem.scene.bodies import KINDS

    sc = Scene(gravity=(0.0, 0.0, -9.81), dt="auto")
    for name, rho in (("a", 2500.0), ("b", 1200.0), ("c", 1200.0), ("d", 7800.0)):
        sc.add_material(name, density=rho, law="hertz", k=float(rng.uniform(1e8, 1e9)), restitution=0.5, friction=0.5)
    sc.add_shape("cube", ConvexShape.box(0.01))
    sc.add_shape("plate", ConvexShape.box(0.03, 0.02, 0.004))
    sc.add_shape("bar", ConvexShape.box(0.008, 0.008, 0.03))
    grid = np.stack(np.meshgrid(np.arange(10), np.arange(10), np.arange(10), indexing="ij"), -1).reshape(-1, 3)
    spots = grid[rng.choice(len(grid), n, replace=False)] * 0.05
    shape = rng.integers(0, 3, n)
    material = rng.integers(0, 4, n)
    kind = rng.choice(np.array(kinds), n)
    for i in range(n):
        free = kind[i] == 0
        sc.add_body(
            ["cube", "plate", "bar"][shape[i]],
            "abcd"[material[i]],
            spots[i],
            orientation=tuple(random_quats(rng, 1)[0]),
            velocity=tuple(rng.normal(size=3) * 50.0) if moving and free else (0.0, 0.0, 0.0),
            angular_velocity=tuple(rng.normal(size=3) * 500.0) if moving and free else (0.0, 0.0, 0.0),
            kind=KINDS[kind[i]],
        )
    return sc


def lexsorted_lightest(sc):
    """The reference (what time_step did before): every body's mass, the pooled bodies (free, or with a mass where
    none is free) sorted by shape, then mass, then index; (the shapes in use, the first body of each)."""
    from polydem.scene.bodies import KIND_FREE

    mass = np.asarray(sc.body_mass(), dtype=np.float64)
    free = sc.body_kind == KIND_FREE
    pooled = np.flatnonzero(free if free.any() else mass > 0.0)
    pool_shape = np.asarray(sc.body_shape)[pooled]
    order = np.lexsort((mass[pooled], pool_shape))
    used, first = np.unique(pool_shape[order], return_index=True)
    return used, pooled[order[first]]


def test_lightest_body_of_each_shape_is_the_lexsorted_one():
    from polydem.scene.checks import lightest_of_each_shape

    rng = np.random.default_rng(14)
    for trial in range(30):
        kinds = (0, 1, 2) if trial % 3 else (1, 2)  # some scenes have no free body: the bodies with a mass
        sc = many_kinds_scene(rng, int(rng.integers(1, 60)), kinds)
        used, lightest = lexsorted_lightest(sc)
        got_used, got = lightest_of_each_shape(sc)
        np.testing.assert_array_equal(got_used, used, err_msg=str(trial))
        np.testing.assert_array_equal(got, lightest, err_msg=str(trial))
        assert sc.time_step().lightest in set(got.tolist())


def test_lightest_body_of_each_of_many_shapes_is_the_lexsorted_one():
    """More shapes in use than FEW_CODES: the first body of every code in one pass."""
    from polydem.scene.checks import lightest_of_each_shape
    from polydem.scene.values import FEW_CODES

    rng = np.random.default_rng(16)
    for trial in range(6):
        sc = Scene(gravity=(0.0, 0.0, -9.81), dt="auto")
        for name, rho in (("a", 2500.0), ("b", 1200.0), ("c", 1200.0)):
            sc.add_material(name, density=rho, law="hertz", k=5e8, restitution=0.5, friction=0.5)
        count = FEW_CODES + 4
        for k in range(count):
            sc.add_shape(f"s{k}", ConvexShape.box(*rng.uniform(0.004, 0.02, 3)))
        n = 300
        shape = rng.integers(0, count, n)
        material = rng.integers(0, 3, n)
        kind = rng.choice(np.array(["free", "free", "fixed"] if trial % 2 else ["fixed", "kinematic"]), n)
        spots = np.stack(np.meshgrid(np.arange(10), np.arange(10), np.arange(3), indexing="ij"), -1).reshape(-1, 3)
        for i in range(n):
            sc.add_body(f"s{shape[i]}", "abc"[material[i]], spots[i] * 0.05, kind=str(kind[i]))
        used, lightest = lexsorted_lightest(sc)
        got_used, got = lightest_of_each_shape(sc)
        assert got_used.size > FEW_CODES
        np.testing.assert_array_equal(got_used, used, err_msg=str(trial))
        np.testing.assert_array_equal(got, lightest, err_msg=str(trial))


def test_run_settings_and_tunnelling_limits_match_the_per_body_reference():
    import warnings

    from polydem.run_settings import SKIN_FRACTION, run_settings
    from polydem.scene import checks
    from polydem.scene.bodies import KIND_FIXED, KIND_FREE

    rng = np.random.default_rng(15)
    for trial in range(12):
        moving = bool(trial % 2)
        sc = many_kinds_scene(rng, int(rng.integers(2, 40)), (0, 0, 1, 2) if trial % 4 else (1, 2), moving)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            sc.validate()
        rs = run_settings(sc)
        a = sc.body_arrays()
        radius = np.array([sh.radius for sh in sc.shapes.values()])[a["shape"]]
        free = a["kind"] == KIND_FREE
        r32 = radius.astype(np.float32)
        pool = radius[free] if free.any() else radius
        assert rs.skin == SKIN_FRACTION * float((r32[free] if free.any() else r32).min())
        assert rs.radius_max == float(pool.max())
        assert rs.radius_min == (float(radius[free].min()) if free.any() else None)
        positive = free & (r32 > 0.0)
        assert rs.radius_ref == (float(r32[positive].min()) if positive.any() else None)
        # every body's limit from the docstring's formulas, body by body
        widths = np.array([checks.shape_width(sh) for sh in sc.shapes.values()])
        h = 0.5 * widths[a["shape"]].min()
        assert rs.tunnel.half_thickness == h and widths[a["shape"][rs.tunnel.thinnest]] == 2.0 * h
        assert rs.tunnel.thinnest == int(np.flatnonzero(widths[a["shape"]] == 2.0 * h)[0])
        k_pair = np.asarray(sc.pair_table()["k"])
        mats = sorted(set(a["material"].tolist()))
        shapes = list(sc.shapes.values())
        densities = [m.density for m in sc.materials.values()]
        for i in range(sc.num_bodies):
            sh, mi = shapes[a["shape"][i]], a["material"][i]
            w = widths[a["shape"][i]]
            k = k_pair[mi, mats].min()
            v_c = sh.volume / w * min(w, 2.0 * h)
            energy = k * v_c**1.5 / 1.5
            v_energy = np.sqrt(2.0 * checks.TUNNEL_ENERGY_FRACTION * energy / (densities[mi] * sh.volume))
            v_step = checks.TUNNEL_STEP_FRACTION * h / rs.dt
            np.testing.assert_allclose(rs.tunnel.body_speed_limit[i], min(v_step, v_energy), rtol=1e-12)
            assert rs.tunnel.body_step_bound[i] == (v_step <= v_energy)
        # the initial speeds: warned exactly where some moving body is above its limit (said once, by validate)
        speed = np.linalg.norm(a["velocity"], axis=1) + np.linalg.norm(a["angular_velocity"], axis=1) * radius
        fast = (a["kind"] != KIND_FIXED) & (speed > rs.tunnel.body_speed_limit)
        assert rs.starts_too_fast == bool(fast.any())
        assert any("may pass through" in str(w.message) for w in caught) == bool(fast.any())
        assert fast.any() == moving or not free.any()
