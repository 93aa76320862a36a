"""The broad phase against brute force: scenes of equal and mixed sizes, flags, overflow, Verlet skin."""

import numpy as np
import pytest
import warp as wp
from polydem.kernels.broadphase import BroadPhase, all_pairs
from scipy.spatial.transform import Rotation

FREE, FIXED, KINEMATIC = 0, 1, 2
# Pairs whose distance lies within this relative band of the cut-off may be decided either way
# (float32 in the kernel, float64 in the reference); everything else must agree exactly.
BAND = 1.0e-5


def poses(positions, quats=None):
    positions = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
    q = np.zeros((len(positions), 7), dtype=np.float32)
    q[:, :3] = positions
    if quats is None:
        q[:, 6] = 1.0
    else:
        q[:, 3:] = quats
    return q


class Scene:
    """Host copies of a scene and its device arrays."""

    def __init__(self, device, positions, radii, flags=None, quats=None):
        self.device = device
        self.positions = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
        self.radii = np.asarray(radii, dtype=np.float32).reshape(-1)
        n = len(self.positions)
        self.flags = np.zeros(n, dtype=np.int32) if flags is None else np.asarray(flags, dtype=np.int32)
        self.quats = quats
        self.body_q = wp.array(poses(self.positions, quats), dtype=wp.transform, device=device)
        self.body_radius = wp.array(self.radii, dtype=float, device=device)
        self.body_flags = wp.array(self.flags, dtype=int, device=device)

    @property
    def n(self):
        return len(self.positions)

    def args(self):
        return self.body_q, self.body_radius, self.body_flags

    def set_poses(self, positions, quats=None):
        """Writes new poses into the same device array (so captured graphs see them)."""
        self.positions = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
        self.quats = quats
        self.body_q.assign(poses(self.positions, quats))


def check_against_reference(bp, scene, skin):
    """Asserts the pairs are sorted, consistent and equal to brute force; returns the keys."""
    n = scene.n
    a, b, key = bp.pairs_numpy()
    assert np.all(a < b)
    assert np.all(np.diff(key) > 0), "keys must be strictly increasing"
    np.testing.assert_array_equal(key, a.astype(np.int64) * n + b)
    assert np.all(bp.pair_a.numpy()[len(a) :] == -1)
    assert np.all((scene.flags[a] == FREE) | (scene.flags[b] == FREE))

    ra, rb = all_pairs(scene.positions, scene.radii, scene.flags, skin)
    ref = ra * n + rb
    diff = np.setxor1d(key, ref)
    if len(diff):
        da, db = diff // n, diff % n
        dist = np.linalg.norm(scene.positions[da].astype(np.float64) - scene.positions[db], axis=1)
        cut = scene.radii[da].astype(np.float64) + scene.radii[db] + skin
        assert np.all(np.abs(dist - cut) <= BAND * cut), f"{len(diff)} pairs differ from brute force"
    return key


def random_scene(device, n, rng, r_min, r_max, box=1.0, p_fixed=0.0, p_kinematic=0.0):
    positions = rng.uniform(0.0, box, (n, 3))
    radii = np.exp(rng.uniform(np.log(r_min), np.log(r_max), n))
    u = rng.random(n)
    flags = np.where(u < p_fixed, FIXED, np.where(u < p_fixed + p_kinematic, KINEMATIC, FREE))
    return Scene(device, positions, radii, flags)


# ---------------------------------------------------------------------------------------------
# Equality with brute force


def test_uniform_sizes(device):
    rng = np.random.default_rng(1)
    scene = random_scene(device, 600, rng, 0.03, 0.03)
    bp = BroadPhase(scene.n, device, skin=0.01)
    count = bp.build(*scene.args())
    assert count == bp.num_pairs == int(bp.pair_count.numpy()[0]) > 0
    check_against_reference(bp, scene, 0.01)


@pytest.mark.parametrize("class_ratio", [2.0, 8.0, float("inf")])
def test_mixed_sizes_20x(device, class_ratio):
    rng = np.random.default_rng(2)
    scene = random_scene(device, 600, rng, 0.01, 0.2, p_fixed=0.1, p_kinematic=0.1)
    bp = BroadPhase(scene.n, device, skin=0.02, class_ratio=class_ratio)
    bp.build(*scene.args())
    classes = {2.0: 5, 8.0: 2, float("inf"): 1}[class_ratio]  # a 20x range spans this many
    assert int(bp.class_max.numpy()[0]) == classes - 1
    check_against_reference(bp, scene, 0.02)


def test_container_walls_and_boulders(device):
    # Small grains in a unit box, six huge fixed spheres standing in for the walls, a few free
    # boulders 20x the grain size and a large kinematic paddle.
    rng = np.random.default_rng(3)
    n_grains = 500
    big = 100.0
    pos = list(rng.uniform(0.0, 1.0, (n_grains, 3)))
    rad = list(rng.uniform(0.01, 0.02, n_grains))
    flags = [FREE] * n_grains
    for axis in range(3):
        for side in (0.0, 1.0):
            c = np.full(3, 0.5)
            c[axis] = side + (big - 0.01 if side == 1.0 else -(big - 0.01))
            pos.append(c)
            rad.append(big)
            flags.append(FIXED)
    for _ in range(4):
        pos.append(rng.uniform(0.2, 0.8, 3))
        rad.append(0.3)
        flags.append(FREE)
    pos.append([0.5, 0.5, 0.5])
    rad.append(0.25)
    flags.append(KINEMATIC)
    perm = rng.permutation(len(pos))  # big bodies at random indices
    scene = Scene(device, np.array(pos)[perm], np.array(rad)[perm], np.array(flags)[perm])
    bp = BroadPhase(scene.n, device, skin=0.005)
    bp.build(*scene.args())
    key = check_against_reference(bp, scene, 0.005)
    walls = np.nonzero(scene.radii == big)[0]
    a, b = key // scene.n, key % scene.n
    assert np.isin(a, walls).sum() + np.isin(b, walls).sum() > 0
    assert not np.any(np.isin(a, walls) & np.isin(b, walls))


@pytest.mark.parametrize("mixed", [False, True])
def test_all_bodies_at_one_point(device, mixed):
    rng = np.random.default_rng(4)
    n = 80
    positions = np.array([1.0, -2.0, 3.0]) + rng.normal(0.0, 1e-6, (n, 3))
    radii = rng.uniform(0.01, 0.3, n) if mixed else np.full(n, 0.01)
    scene = Scene(device, positions, radii)
    bp = BroadPhase(n, device, skin=0.0)
    assert bp.build(*scene.args()) == n * (n - 1) // 2
    check_against_reference(bp, scene, 0.0)


def test_all_bodies_in_one_cell(device):
    rng = np.random.default_rng(5)
    n = 70
    scene = Scene(device, rng.uniform(0.0, 0.01, (n, 3)), np.full(n, 0.05))
    bp = BroadPhase(n, device, skin=0.01)
    assert bp.build(*scene.args()) == n * (n - 1) // 2
    check_against_reference(bp, scene, 0.01)


def test_tiny_scenes(device):
    for n in (0, 1, 2):
        scene = Scene(device, np.zeros((n, 3)), np.full(n, 0.1))
        bp = BroadPhase(n, device, skin=0.01)
        assert bp.build(*scene.args()) == n * (n - 1) // 2
        assert bp.update(*scene.args()) is False


# ---------------------------------------------------------------------------------------------
# Order, determinism, capacity


def test_deterministic(device):
    rng = np.random.default_rng(6)
    scene = random_scene(device, 500, rng, 0.01, 0.1, p_fixed=0.1)
    results = []
    for _ in range(2):
        bp = BroadPhase(scene.n, device, skin=0.01)
        for _ in range(2):
            bp.build(*scene.args())
            results.append([bp.pair_a.numpy(), bp.pair_b.numpy(), bp.pairs_numpy()[2]])
    for r in results[1:]:
        for x, y in zip(results[0], r, strict=True):
            np.testing.assert_array_equal(x, y)


def test_same_pairs_on_every_device(devices):
    if len(devices) < 2:
        pytest.skip("needs a second device")
    keys = []
    for device in devices:
        scene = random_scene(device, 2000, np.random.default_rng(7), 0.01, 0.1, p_fixed=0.1)
        bp = BroadPhase(scene.n, device, skin=0.01)
        bp.build(*scene.args())
        keys.append(check_against_reference(bp, scene, 0.01))
    for k in keys[1:]:
        np.testing.assert_array_equal(keys[0], k)


def test_overflow_grows(device):
    rng = np.random.default_rng(8)
    scene = random_scene(device, 300, rng, 0.05, 0.1)
    bp = BroadPhase(scene.n, device, skin=0.01, capacity=3)
    count = bp.build(*scene.args())
    assert count > 3 and bp.capacity >= count
    assert len(bp.pair_a) == len(bp.pair_b) == len(bp.pair_key) == bp.capacity
    check_against_reference(bp, scene, 0.01)
    # Denser: everything moves towards the centre, the same object grows again.
    cap = bp.capacity
    scene.set_poses(0.5 + 0.3 * (scene.positions - 0.5))
    assert bp.update(*scene.args())
    assert bp.capacity > cap
    check_against_reference(bp, scene, 0.01)


def test_radii_change_between_builds(device):
    # The same object (and BVH) rebuilt after the size classes change.
    rng = np.random.default_rng(9)
    scene = random_scene(device, 300, rng, 0.03, 0.03)
    bp = BroadPhase(scene.n, device, skin=0.01)
    bp.build(*scene.args())
    check_against_reference(bp, scene, 0.01)
    scene2 = Scene(device, scene.positions, np.exp(rng.uniform(np.log(0.005), np.log(0.2), scene.n)), scene.flags)
    bp.build(*scene2.args())
    check_against_reference(bp, scene2, 0.01)


# ---------------------------------------------------------------------------------------------
# Flags


def test_flags(device):
    rng = np.random.default_rng(10)
    scene = random_scene(device, 400, rng, 0.03, 0.08, p_fixed=0.5, p_kinematic=0.3)
    bp = BroadPhase(scene.n, device, skin=0.01)
    bp.build(*scene.args())
    key = check_against_reference(bp, scene, 0.01)
    a, b = key // scene.n, key % scene.n
    fa, fb = scene.flags[a], scene.flags[b]
    assert not np.any((fa != FREE) & (fb != FREE))
    assert np.any((fa == KINEMATIC) | (fb == KINEMATIC))
    assert np.any((fa == FIXED) | (fb == FIXED))

    # Nothing free: no pairs at all, even with every body on one spot.
    n = 40
    scene = Scene(device, np.zeros((n, 3)), np.full(n, 0.1), np.where(np.arange(n) % 2, FIXED, KINEMATIC))
    bp = BroadPhase(n, device, skin=0.01)
    assert bp.build(*scene.args()) == 0
    # One free body among them pairs with every other.
    scene.flags[7] = FREE
    scene.body_flags.assign(scene.flags)
    assert bp.needs_rebuild(*scene.args()).numpy()[0] == 1  # a flag changed
    assert bp.build(*scene.args()) == n - 1


# ---------------------------------------------------------------------------------------------
# Verlet skin


def lattice_scene(device, n_side=5, spacing=0.1, radius=0.04):
    g = np.arange(n_side) * spacing
    pos = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    return Scene(device, pos, np.full(len(pos), radius))


def test_needs_rebuild_translation(device):
    skin = 0.02
    scene = lattice_scene(device)
    bp = BroadPhase(scene.n, device, skin=skin)
    assert bp.needs_rebuild(*scene.args()).numpy()[0] == 1  # never built
    bp.build(*scene.args())
    assert bp.needs_rebuild(*scene.args()).numpy()[0] == 0
    start = scene.positions.copy()
    d = np.array([1.0, 2.0, -2.0]) / 3.0
    for dist, expected in ((0.45 * skin, 0), (0.55 * skin, 1)):
        p = start.copy()
        p[17] += dist * d
        scene.set_poses(p)
        assert bp.needs_rebuild(*scene.args()).numpy()[0] == expected
    assert bp.update(*scene.args()) is True
    assert bp.needs_rebuild(*scene.args()).numpy()[0] == 0  # measured from the new build


def test_needs_rebuild_rotation(device):
    skin = 0.02
    scene = lattice_scene(device, radius=0.04)
    bp = BroadPhase(scene.n, device, skin=skin)
    bp.build(*scene.args())
    quats = np.tile([0.0, 0.0, 0.0, 1.0], (scene.n, 1))
    for arc, expected in ((0.45 * skin, 0), (0.55 * skin, 1)):
        q = quats.copy()
        axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
        q[30] = Rotation.from_rotvec(axis * arc / 0.04).as_quat()
        scene.set_poses(scene.positions, q)
        assert bp.needs_rebuild(*scene.args()).numpy()[0] == expected
    # Rotation and translation add up.
    q = quats.copy()
    q[30] = Rotation.from_rotvec([0.0, 0.0, 0.3 * skin / 0.04]).as_quat()
    p = scene.positions.copy()
    p[30, 0] += 0.3 * skin
    scene.set_poses(p, q)
    assert bp.needs_rebuild(*scene.args()).numpy()[0] == 1
    # Without the rotation term a pure rotation never asks for a rebuild.
    bp2 = BroadPhase(scene.n, device, skin=skin, rotation_term=False)
    scene.set_poses(scene.positions, quats)
    bp2.build(*scene.args())
    q = quats.copy()
    q[30] = Rotation.from_rotvec([1.0, 0.0, 0.0]).as_quat()
    scene.set_poses(scene.positions, q)
    assert bp2.needs_rebuild(*scene.args()).numpy()[0] == 0


def test_needs_rebuild_radius_growth(device):
    skin = 0.02
    scene = lattice_scene(device)
    bp = BroadPhase(scene.n, device, skin=skin)
    bp.build(*scene.args())
    r = scene.radii.copy()
    r[3] += 0.6 * skin
    scene.body_radius.assign(r)
    assert bp.needs_rebuild(*scene.args()).numpy()[0] == 1


def test_old_list_holds_overlaps_after_small_moves(device):
    rng = np.random.default_rng(11)
    skin = 0.02
    scene = random_scene(device, 500, rng, 0.02, 0.15, p_fixed=0.05)
    bp = BroadPhase(scene.n, device, skin=skin)
    bp.build(*scene.args())
    old_key = bp.pairs_numpy()[2].copy()
    start = scene.positions.copy()
    for _ in range(3):
        # Every free body moves and turns from its build pose; translation plus radius * angle
        # stays below skin/2.
        dirs = rng.normal(size=(scene.n, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        budget = 0.49 * skin * rng.uniform(0.5, 1.0, scene.n)
        share = rng.uniform(0.0, 1.0, scene.n)
        free = scene.flags == FREE
        p = start + (free * share * budget)[:, None] * dirs
        axes = rng.normal(size=(scene.n, 3))
        axes /= np.linalg.norm(axes, axis=1, keepdims=True)
        angle = free * (1.0 - share) * budget / scene.radii * 0.999
        scene.set_poses(p, Rotation.from_rotvec(axes * angle[:, None]).as_quat())
        assert bp.needs_rebuild(*scene.args()).numpy()[0] == 0
        assert bp.update(*scene.args()) is False
        ta, tb = all_pairs(scene.positions, scene.radii, scene.flags, 0.0)
        touching = ta * scene.n + tb
        assert len(touching) > 0
        assert np.all(np.isin(touching, old_key))
    # A larger step asks for a rebuild, after which the list is exact again.
    p = scene.positions.copy()
    p[np.argmax(scene.flags == FREE)] += [0.6 * skin, 0.0, 0.0]
    scene.set_poses(p)
    assert bp.update(*scene.args()) is True
    check_against_reference(bp, scene, skin)


# ---------------------------------------------------------------------------------------------
# Device-only path (capture_if); runs eagerly on every device and inside a CUDA graph on a GPU


def test_update_on_device(device):
    rng = np.random.default_rng(12)
    skin = 0.01
    scene = random_scene(device, 400, rng, 0.01, 0.1, p_fixed=0.1)
    bp = BroadPhase(scene.n, device, skin=skin)
    bp.build(*scene.args())
    first = bp.pairs_numpy()[2].copy()
    scene.set_poses(scene.positions + [0.3 * skin, 0.0, 0.0])  # below skin/2: no rebuild
    bp.update_on_device(*scene.args())
    assert int(bp.device_rebuilds.numpy()[0]) == 0
    np.testing.assert_array_equal(bp.pairs_numpy()[2], first)
    scene.set_poses(scene.positions + rng.normal(0.0, 0.02, (scene.n, 3)))
    bp.update_on_device(*scene.args())
    assert not bp.check_host_build_needed()
    assert int(bp.device_rebuilds.numpy()[0]) == 1
    key = check_against_reference(bp, scene, skin)
    # Same result as the host build of the same poses.
    bp2 = BroadPhase(scene.n, device, skin=skin)
    bp2.build(*scene.args())
    np.testing.assert_array_equal(bp2.pairs_numpy()[2], key)
    np.testing.assert_array_equal(bp2.pair_a.numpy(), bp.pair_a.numpy()[: bp2.capacity])


def test_device_overflow_is_flagged(device):
    rng = np.random.default_rng(13)
    scene = random_scene(device, 300, rng, 0.02, 0.05)
    bp = BroadPhase(scene.n, device, skin=0.01, capacity=1)
    count = bp.build(*scene.args())
    assert bp.capacity < 2 * count  # headroom, not a doubling of a huge buffer
    scene.set_poses(0.5 + 0.2 * (scene.positions - 0.5))
    bp.rebuild_on_device(*scene.args())
    assert bp.check_host_build_needed()
    assert int(bp.pair_count.numpy()[0]) == bp.capacity
    bp.build(*scene.args())  # the host build grows and clears the flag
    assert not bp.check_host_build_needed()
    check_against_reference(bp, scene, 0.01)


def test_host_build_after_device_overflow_has_room_for_it(device):
    # A chunk is redone from the poses at its start, where the pairs may still fit: the host build
    # must still make room for what the overflowed device rebuild saw, or the redo overflows again.
    rng = np.random.default_rng(16)
    scene = random_scene(device, 300, rng, 0.02, 0.05)
    start = scene.positions.copy()
    bp = BroadPhase(scene.n, device, skin=0.01, capacity=1)
    count_start = bp.build(*scene.args())
    scene.set_poses(0.5 + 0.2 * (start - 0.5))
    bp.rebuild_on_device(*scene.args())
    assert bp.check_host_build_needed()
    needed = int(bp.pair_count_peak.numpy()[0])
    assert needed > bp.capacity >= count_start
    scene.set_poses(start)  # back to the start of the chunk
    assert bp.build(*scene.args()) == count_start
    assert bp.capacity >= needed
    scene.set_poses(0.5 + 0.2 * (start - 0.5))
    bp.rebuild_on_device(*scene.args())  # the redo now fits
    assert not bp.check_host_build_needed()
    check_against_reference(bp, scene, 0.01)


def test_device_rebuild_flags_change_is_flagged(device):
    rng = np.random.default_rng(15)
    scene = random_scene(device, 200, rng, 0.02, 0.08)
    bp = BroadPhase(scene.n, device, skin=0.01)
    bp.build(*scene.args())
    scene.flags[::2] = FIXED
    scene.body_flags.assign(scene.flags)
    bp.update_on_device(*scene.args())  # the changed flags ask for a rebuild ...
    assert bp.check_host_build_needed()  # ... which needs new groups: the host must build
    assert bp.update(*scene.args())
    assert not bp.check_host_build_needed()
    check_against_reference(bp, scene, 0.01)


def test_cuda_graph_capture(device):
    if not wp.get_device(device).is_cuda:
        pytest.skip("CUDA graph capture needs a GPU")
    rng = np.random.default_rng(14)
    skin = 0.01
    scene = random_scene(device, 3000, rng, 0.005, 0.05, p_fixed=0.1)
    bp = BroadPhase(scene.n, device, skin=skin)
    bp.build(*scene.args())
    first = bp.pairs_numpy()[2].copy()
    with wp.ScopedCapture(device=device, force_module_load=False) as capture:
        bp.update_on_device(*scene.args())
    # Small move: the graph runs, the branch is skipped.
    scene.set_poses(scene.positions + [0.0, 0.3 * skin, 0.0])
    wp.capture_launch(capture.graph)
    assert int(bp.device_rebuilds.numpy()[0]) == 0
    np.testing.assert_array_equal(bp.pairs_numpy()[2], first)
    # Large move: the graph rebuilds on the device.
    scene.set_poses(scene.positions + rng.normal(0.0, 0.03, (scene.n, 3)))
    wp.capture_launch(capture.graph)
    assert not bp.check_host_build_needed()
    assert int(bp.device_rebuilds.numpy()[0]) == 1
    check_against_reference(bp, scene, skin)
    # A second large move, replayed again.
    scene.set_poses(scene.positions + rng.normal(0.0, 0.03, (scene.n, 3)))
    wp.capture_launch(capture.graph)
    assert int(bp.device_rebuilds.numpy()[0]) == 2
    check_against_reference(bp, scene, skin)


# ---------------------------------------------------------------------------------------------
# Tree renewal: the device rebuilds refit the tree of the last host build; renew_tree rebuilds it


def mixing_moves(rng, positions, fraction):
    """New positions: a ``fraction`` of the bodies trade places at random (the rest stay), plus a jitter."""
    out = positions.copy()
    k = int(fraction * len(out))
    chosen = rng.choice(len(out), k, replace=False)
    out[chosen] = out[rng.permutation(chosen)]
    return out + rng.normal(0.0, 0.005, out.shape)


def test_tree_degradation_measures_mixing(device):
    rng = np.random.default_rng(21)
    scene = random_scene(device, 500, rng, 0.01, 0.03, p_fixed=0.05)
    bp = BroadPhase(scene.n, device, skin=0.01)
    bp.build(*scene.args())
    assert abs(bp.tree_degradation() - 1.0) < 1e-6  # the tree order is the fresh Morton order
    # Small moves leave the tree good: no rebuild at a ratio of 1.2; off by default.
    scene.set_poses(scene.positions + rng.normal(0.0, 0.003, (scene.n, 3)))
    bp.rebuild_on_device(*scene.args())
    assert bp.tree_degradation() < 1.1
    assert not bp.renew_tree()
    assert not bp.renew_tree(1.2)
    assert not bp.renew_tree(0.0)  # no device rebuild since the last check
    # Bodies that trade places across the box make the refitted nodes span it.
    scene.set_poses(mixing_moves(rng, scene.positions, 0.5))
    bp.rebuild_on_device(*scene.args())
    assert not bp.renew_tree(None)
    assert not bp.renew_tree()
    assert bp.num_tree_rebuilds == 0
    assert bp.renew_tree(1.2)
    assert bp.tree_ratio > 3.0
    assert bp.num_tree_rebuilds == 1
    assert abs(bp.tree_degradation() - 1.0) < 1e-6
    check_against_reference(bp, scene, 0.01)


@pytest.mark.parametrize("class_ratio", [2.0, float("inf")])
def test_tree_rebuild_keeps_pairs(device, class_ratio):
    # A broad phase whose tree is rebuilt after every device rebuild against one that only refits:
    # the same pairs bit for bit (keys and unpacked arrays), equal to brute force. Several size
    # classes and fixed bodies: the group roots move with a rebuilt tree.
    rng = np.random.default_rng(22)
    skin = 0.01
    scene = random_scene(device, 400, rng, 0.005, 0.05, p_fixed=0.05)
    refit = BroadPhase(scene.n, device, skin=skin, class_ratio=class_ratio)
    fresh = BroadPhase(scene.n, device, skin=skin, class_ratio=class_ratio)
    refit.build(*scene.args())
    fresh.build(*scene.args())
    for _ in range(4):
        scene.set_poses(mixing_moves(rng, scene.positions, 0.3))
        refit.update_on_device(*scene.args())
        fresh.update_on_device(*scene.args())
        assert not refit.check_host_build_needed() and not fresh.check_host_build_needed()
        key = check_against_reference(refit, scene, skin)
        np.testing.assert_array_equal(fresh.pairs_numpy()[2], key)
        np.testing.assert_array_equal(fresh.pair_a.numpy(), refit.pair_a.numpy())
        np.testing.assert_array_equal(fresh.pair_b.numpy(), refit.pair_b.numpy())
        assert fresh.renew_tree(0.0)
    assert fresh.num_tree_rebuilds == 4 and refit.num_tree_rebuilds == 0
    assert refit.tree_degradation() > 2.0


def test_tree_rebuild_between_graph_launches(device):
    if not wp.get_device(device).is_cuda:
        pytest.skip("CUDA graph capture needs a GPU")
    rng = np.random.default_rng(23)
    skin = 0.01
    scene = random_scene(device, 3000, rng, 0.005, 0.05, p_fixed=0.1)
    bp = BroadPhase(scene.n, device, skin=skin)
    bp.build(*scene.args())
    with wp.ScopedCapture(device=device, force_module_load=False) as capture:
        bp.update_on_device(*scene.args())
    for _ in range(3):
        scene.set_poses(mixing_moves(rng, scene.positions, 0.3))
        wp.capture_launch(capture.graph)
        assert not bp.check_host_build_needed()
        check_against_reference(bp, scene, skin)
        assert bp.renew_tree(0.0)  # in place: the graph stays valid
    assert int(bp.device_rebuilds.numpy()[0]) == 3


def test_pair_capacity_beyond_int32_indices_is_refused(device):
    """Room for more candidate pairs than the int32 indices reach: a clear error before any allocation."""
    bp = BroadPhase(4, device, skin=0.01)
    with pytest.raises(RuntimeError, match="int32 indices reach"):
        bp._allocate(2**30)
    assert bp.capacity < 2**30


def test_boxes_by_shape_give_the_pairs_of_boxes_by_body(device):
    """body_box as a box per shape and each body's shape, or as a box per body: the same pairs (fixed and
    kinematic bodies are tested by their boxes); indices out of range are refused."""
    rng = np.random.default_rng(5)
    scene = random_scene(device, 400, rng, 0.01, 0.05, p_fixed=0.2, p_kinematic=0.1)
    shape_lo = np.array([[-0.01, -0.02, -0.005], [-0.03, -0.01, -0.02], [-0.004, -0.004, -0.004]])
    shape_hi = -shape_lo * np.array([1.0, 0.5, 1.0])
    shape = rng.integers(0, 3, scene.n)
    pairs = []
    for box in ((shape_lo[shape], shape_hi[shape]), (shape_lo, shape_hi, shape)):
        bp = BroadPhase(scene.n, device, skin=0.01, body_box=box)
        # each body's box, the same bits either way
        of = bp.body_box.numpy()
        np.testing.assert_array_equal(bp.body_box_lower.numpy()[of], shape_lo[shape].astype(np.float32))
        np.testing.assert_array_equal(bp.body_box_upper.numpy()[of], shape_hi[shape].astype(np.float32))
        count = bp.build(*scene.args())
        pairs.append((bp.pair_a.numpy()[:count].copy(), bp.pair_b.numpy()[:count].copy()))
    assert len(pairs[0][0]) > 10
    for got, want in zip(pairs[1], pairs[0], strict=True):
        np.testing.assert_array_equal(got, want)
    with pytest.raises(ValueError, match="box indices must lie in"):
        BroadPhase(scene.n, device, skin=0.01, body_box=(shape_lo, shape_hi, shape + 1))
