"""The initial-overlap check of body pairs on the device (polydem.overlap_check) against the scene's own check on the
host (polydem.scene.overlaps): the same records, and the same warning or error from a Simulation either way."""

import warnings

import numpy as np
import pytest
import warp as wp

from polydem import ConvexShape, Scene, SceneError, Simulation
from polydem.compound import CompoundShape, place
from polydem.overlap_check import device_check_applies, device_pair_overlaps, median_by_counts
from polydem.scene import SceneWarning, overlaps

SHAPES = {
    "cube": ConvexShape.box(0.01),
    "tet": ConvexShape.tetrahedron(0.015),
    "rock": ConvexShape.rock(20, size=0.012, seed=1),
    "slab": ConvexShape.box(0.02, 0.006, 0.012),
}


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def cloud(n=240, seed=9, big=False):
    """Bodies of four shapes at random in a box container: many overlaps, some deep; ``big``: and a free boulder
    (more than 4 times the median radius: the host test takes it first in its pairs)."""
    sc = Scene(gravity=(0.0, 0.0, -9.81), dt="auto")
    sc.add_material("m", density=2500.0, law="hertz", k=1e9, restitution=0.5, friction=0.5)
    for name, shape in SHAPES.items():
        sc.add_shape(name, shape)
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-0.034, 0.034, (n, 3))
    q = random_quats(rng, n)
    per = n // 4
    for k, name in enumerate(SHAPES):
        sc.add_bodies(name, "m", pos[k * per : (k + 1) * per], orientations=q[k * per : (k + 1) * per])
    if big:
        sc.add_shape("boulder", ConvexShape.rock(20, size=0.08, seed=3))
        sc.add_body("boulder", "m", position=(0.01, -0.005, 0.0))
    sc.add_box_container((0.0, 0.0, 0.0), (0.06, 0.06, 0.06), "m", wall_thickness=0.01)
    return sc


def records_of(found):
    """{(free body, other): (rel, depth)} of OverlapRecords from the pair check."""
    return {
        (int(found.body[k]), int(found.words(k)[0].split()[2])): (float(found.rel[k]), float(found.depth[k]))
        for k in range(len(found))
    }


@pytest.mark.parametrize("big", [False, True])
def test_device_records_are_the_host_records(device, big):
    sc = cloud(big=big)
    sim = Simulation(sc, device, validate=False)  # unvalidated: the cloud's deep overlaps would raise
    host = records_of(overlaps._pair_overlaps(list(sc.shapes.values()), sc.body_label, sc.body_arrays()))
    dev = records_of(device_pair_overlaps(sc, sim.model, sim.current_contacts, sim.current_state))
    assert len(host) > 100
    assert dev.keys() == host.keys()
    got = np.array([dev[k] for k in host])
    want = np.array([host[k] for k in host])
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-15)
    if big:
        boulder = int(np.flatnonzero(sc.body_arrays()["shape"] == list(sc.shapes).index("boulder"))[0])
        # the free boulder comes first in its pairs, the record's body even against grains listed before it
        assert any(k[0] == boulder and k[1] < boulder for k in host)


def pile(depth_share=0.05, deep=False):
    """Cubes stacked in columns on a floor box, some pushed into the cube below by ``depth_share`` of an edge (and
    one tetrahedron column beside them): shallow overlaps only, a warning and no error; ``deep``: and one cube 70%
    of an edge into the one below, an error."""
    sc = Scene(gravity=(0.0, 0.0, -9.81), dt="auto")
    sc.add_material("m", density=2500.0, law="hertz", k=1e9, restitution=0.5, friction=0.5)
    sc.add_shape("cube", ConvexShape.box(0.01))
    sc.add_shape("tet", ConvexShape.tetrahedron(0.015))
    rng = np.random.default_rng(4)
    cols = np.array([(x, y) for x in range(5) for y in range(5)], dtype=float) * 0.02
    layers = 5
    pos = np.array([(x, y, 0.005 + 0.0102 * k) for x, y in cols for k in range(layers)])
    pushed = rng.random(len(pos)) < 0.3
    pushed[::layers] = False  # the lowest of each column stays on the floor
    # a share and its own depth each, so that no two overlaps are equally deep
    pos[pushed, 2] -= 0.0002 + 0.01 * depth_share * rng.random(int(pushed.sum()))
    if deep:
        pos[7, 2] -= 0.007
    sc.add_bodies("cube", "m", pos)
    sc.add_bodies("tet", "m", np.array([(0.11, 0.05, 0.006 + 0.0125 * k) for k in range(3)]))
    sc.add_box_container((0.05, 0.05, 0.05), (0.16, 0.16, 0.1), "m", open_top=True)
    return sc


def overlap_warnings(caught):
    return [str(w.message) for w in caught if issubclass(w.category, SceneWarning) and "overlap" in str(w.message)]


def test_simulation_warns_alike_on_host_and_device(device):
    said = {}
    for check in ("host", "device"):
        sc = pile()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            Simulation(sc, device, overlap_check=check)
        said[check] = (overlap_warnings(caught), list(sc.warnings))
        assert len(said[check][0]) == 1 and "initial overlaps" in said[check][0][0]
    assert said["device"] == said["host"]
    # Another Simulation of the same scene says nothing new.
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        Simulation(sc, device, overlap_check="device")
    assert not [w for w in caught if issubclass(w.category, SceneWarning)]
    assert sc.warnings == said["device"][1]


def test_simulation_raises_alike_on_host_and_device(device):
    messages = {}
    for check in ("host", "device"):
        sc = pile(deep=True)
        with pytest.raises(SceneError) as err:
            Simulation(sc, device, overlap_check=check)
        messages[check] = str(err.value)
    assert "starts" in messages["host"] and messages["device"] == messages["host"]


def test_where_the_device_check_applies():
    sc = pile()
    assert not device_check_applies(sc, "cpu")  # auto: CUDA only, and large scenes
    assert device_check_applies(sc, "cpu", overlap_check="device")
    assert not device_check_applies(sc, "cpu", overlap_check="host")
    with pytest.raises(ValueError, match="subset"):
        device_check_applies(sc, "cpu", bodies=np.arange(3), overlap_check="device")
    with pytest.raises(ValueError, match="'auto', 'host' or 'device'"):
        device_check_applies(sc, "cpu", overlap_check="gpu")
    h = 0.01
    sc.add_shape("elbow", CompoundShape([place(ConvexShape.box(h, h / 2, h), (-h / 4, 0, 0)), ConvexShape.box(h / 2)]))
    with pytest.raises(ValueError, match="compound"):
        device_check_applies(sc, "cpu", overlap_check="device")


def test_median_by_counts_is_numpys():
    rng = np.random.default_rng(2)
    for n in (1, 2, 5, 6):
        values = rng.random(n)
        counts = rng.integers(0, 4, n)
        counts[0] += 1
        assert median_by_counts(values, counts) == np.median(np.repeat(values, counts))


def lattice(kinematic=False):
    """Columns of cubes each pushed 4% of an edge into the one below, all alike: many overlaps equally deep (the
    host's search and the device list them in other orders); ``kinematic``: the lowest cube of each column driven."""
    sc = Scene(gravity=(0.0, 0.0, -9.81), dt="auto")
    sc.add_material("m", density=2500.0, law="hertz", k=1e9, restitution=0.5, friction=0.5)
    sc.add_shape("cube", ConvexShape.box(0.01))
    cols = [(0.02 * x, 0.02 * y) for x in range(7) for y in range(7)]
    pos = np.array([(x, y, 0.005 + 0.0096 * k) for x, y in cols for k in range(2)])
    lowest = np.arange(0, len(pos), 2)
    sc.add_bodies("cube", "m", np.delete(pos, lowest, axis=0))
    if kinematic:
        for p in pos[lowest]:
            sc.add_body("cube", "m", position=tuple(p), kind="kinematic")
    else:
        sc.add_bodies("cube", "m", pos[lowest])
    return sc


def test_equally_deep_overlaps_say_the_same_once(device):
    """The CLI's flow (the scene validated on loading, the Simulation's check on the device after it): with
    overlaps equally deep, the same message, said once; finishing twice keeps one message in the warnings."""
    said = {}
    for check in ("host", "device"):
        sc = lattice()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            sc.validate()
            Simulation(sc, device, overlap_check=check)
        said[check] = overlap_warnings(caught)
        assert len(said[check]) == 1 and said[check][0].startswith("49 initial overlaps")
        assert sc.warnings.count(said[check][0]) == 1
    assert said["device"] == said["host"]
    sc.finish_overlap_check()
    assert sc.warnings.count(said["host"][0]) == 1


def test_pairs_left_by_validate_are_finished_by_the_simulation(device):
    """Scene.validate(pair_overlaps=False) and Simulation(validate=False), as `polydem run` does: the Simulation
    finishes the check (on the device where it applies, else on the host) and says it as the full check does."""
    full = lattice()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        full.validate()
    want = overlap_warnings(caught)
    for check in ("host", "device"):
        sc = lattice()
        sc.validate(pair_overlaps=False)
        assert sc.pair_overlaps_pending and not [m for m in sc.warnings if "overlap" in m]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            Simulation(sc, device, validate=False, overlap_check=check)
        assert overlap_warnings(caught) == want and not sc.pair_overlaps_pending
        assert sc.warnings == full.warnings


@pytest.mark.parametrize("precision", ["float32", "mixed"])
def test_device_check_takes_the_scene_poses_in_any_precision(device, precision):
    """A float32 state rounds the poses; the device check takes the scene's float64 ones, as the host check."""
    sc = pile()
    sc.precision = precision
    sc.validate(pair_overlaps=False)
    sim = Simulation(sc, device, validate=False, overlap_check="host")
    host = records_of(overlaps._pair_overlaps(list(sc.shapes.values()), sc.body_label, sc.body_arrays()))
    dev = records_of(device_pair_overlaps(sc, sim.model, sim.current_contacts, sim.current_state))
    assert len(host) > 10 and dev.keys() == host.keys()
    np.testing.assert_allclose([dev[k] for k in host], [host[k] for k in host], rtol=1e-9, atol=1e-15)


def test_kinematic_bodies_and_the_room_for_records(device, monkeypatch):
    """Kinematic bodies count as not free (a pair of two is no record); more records than the output's first room:
    the test runs again with room for all of them."""
    from polydem import overlap_check

    sc = lattice(kinematic=True)
    sc.validate(pair_overlaps=False)
    sim = Simulation(sc, device, validate=False, overlap_check="host")
    host = records_of(overlaps._pair_overlaps(list(sc.shapes.values()), sc.body_label, sc.body_arrays()))
    real = overlap_check.launch_pair_overlaps
    rooms = []

    def small_room(*args, room):
        rooms.append(room)
        return real(*args, room=3)

    monkeypatch.setattr(overlap_check, "launch_pair_overlaps", small_room)
    dev = records_of(device_pair_overlaps(sc, sim.model, sim.current_contacts, sim.current_state))
    assert rooms and len(host) == 49 and dev.keys() == host.keys()
    assert all(sc.body_arrays()["kind"][k[0]] == 0 for k in dev)


def test_auto_takes_the_device_for_large_scenes_on_cuda(monkeypatch):
    from polydem import overlap_check

    sc = pile()
    monkeypatch.setattr(overlap_check, "DEVICE_CHECK_MIN_BODIES", 10)
    assert not device_check_applies(sc, "cpu")
    if wp.get_cuda_device_count():
        assert device_check_applies(sc, "cuda:0")
    monkeypatch.setattr(overlap_check, "DEVICE_CHECK_MIN_BODIES", 10**6)
    if wp.get_cuda_device_count():
        assert not device_check_applies(sc, "cuda:0")


def test_simulation_refuses_an_unknown_overlap_check():
    with pytest.raises(ValueError, match="overlap_check must be"):
        Simulation(pile(), "cpu", validate=False, overlap_check="gpu")
