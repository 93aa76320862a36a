"""The order of the pairs by body B (kernels/pairlist.py ``launch_body_ranges``) and each body's ranges.

The gather sums a body's B pairs in that order, so it must stay the order of the keys ``b * N + a``: by B,
then by A. The sort is on int32 keys ``b`` alone and relies on being stable over slots in increasing
``a * N + b``; these tests would see an unstable sort, a key that loses a bit, or a misplaced sentinel.
"""

import numpy as np
import pytest
import warp as wp
from polydem.kernels.pairlist import launch_body_ranges

import polydem
from polydem import Simulation
from polydem.default_scene import default_scene


def pair_list(n, count, rng, hub=True):
    """``count`` distinct pairs a < b of ``n`` bodies in increasing key ``a * n + b`` (as the broad phase
    leaves them); with ``hub`` the last body pairs with every other, so that many pairs share that B."""
    keys = set()
    if hub:
        keys |= {a * n + (n - 1) for a in range(n - 1)}
    while len(keys) < count:
        a, b = sorted(rng.choice(n, 2, replace=False))
        keys.add(int(a) * n + int(b))
    key = np.array(sorted(keys), dtype=np.int64)
    return key // n, key % n, key


def ranges(sorted_bodies, n):
    i = np.arange(n)
    return np.stack([np.searchsorted(sorted_bodies, i, "left"), np.searchsorted(sorted_bodies, i + 1, "left")], 1)


def check_order(n, a, b, by_b, ranges_a, ranges_b):
    """``by_b`` (the first ``len(b)`` entries) and the ranges against numpy; a, b in slot order."""
    count = len(b)
    # The former int64 keys b * n + a, sorted: the order the gather has always summed in.
    expected = np.lexsort((a, b))
    np.testing.assert_array_equal(expected, np.argsort(b, kind="stable"))
    np.testing.assert_array_equal(by_b[:count], expected)
    np.testing.assert_array_equal(ranges_a, ranges(a, n))
    np.testing.assert_array_equal(ranges_b, ranges(b[expected], n))
    for i in range(n):
        lo, hi = ranges_b[i]
        assert np.all(b[by_b[lo:hi]] == i)
        assert np.all(np.diff(a[by_b[lo:hi]]) > 0)


# n = 64 and 1024 are powers of two: the sentinel n needs one bit more than the largest body index.
@pytest.mark.parametrize("n,count,capacity", [(64, 900, 1200), (1024, 20000, 20000), (1000, 3000, 7000), (2, 1, 3)])
def test_by_b_is_the_order_of_b_then_a(device, n, count, capacity):
    rng = np.random.default_rng(n + count)
    a, b, key = pair_list(n, count, rng, hub=n > 2)
    pad = capacity - count

    def padded(x, fill, dtype):
        return wp.array(np.concatenate([x, np.full(pad, fill)]).astype(dtype), device=device)

    # The keys' buffer is scratch lent by the broad phase: whatever it held must not matter.
    keys_b = wp.array(rng.integers(-(2**31), 2**31 - 1, 2 * capacity, dtype=np.int32), device=device)
    by_b = wp.array(rng.integers(-(2**31), 2**31 - 1, 2 * capacity, dtype=np.int32), device=device)
    ra = wp.zeros(n, dtype=wp.vec2i, device=device)
    rb = wp.zeros(n, dtype=wp.vec2i, device=device)
    launch_body_ranges(
        num_bodies=n,
        pair_b=padded(b, -1, np.int32),
        pair_key=padded(key, n * n, np.int64),
        pair_count=wp.array([count], dtype=int, device=device),
        keys_b=keys_b,
        by_b=by_b,
        body_pairs_a=ra,
        body_pairs_b=rb,
    )
    out = by_b.numpy()
    check_order(n, a, b, out, ra.numpy(), rb.numpy())
    # The empty slots (sentinel keys) come last, in their slot order.
    np.testing.assert_array_equal(out[count:capacity], np.arange(count, capacity))


def test_no_pairs(device):
    n, capacity = 5, 4
    rb = wp.full(n, wp.vec2i(7, 7), dtype=wp.vec2i, device=device)
    by_b = wp.zeros(2 * capacity, dtype=int, device=device)
    launch_body_ranges(
        num_bodies=n,
        pair_b=wp.full(capacity, -1, dtype=int, device=device),
        pair_key=wp.full(capacity, n * n, dtype=wp.int64, device=device),
        pair_count=wp.zeros(1, dtype=int, device=device),
        keys_b=wp.zeros(2 * capacity, dtype=int, device=device),
        by_b=by_b,
        body_pairs_a=wp.zeros(n, dtype=wp.vec2i, device=device),
        body_pairs_b=rb,
    )
    np.testing.assert_array_equal(rb.numpy(), 0)
    np.testing.assert_array_equal(by_b.numpy()[:capacity], np.arange(capacity))


def test_bad_buffers_are_refused():
    kw = dict(
        pair_b=wp.zeros(4, dtype=int, device="cpu"),
        pair_key=wp.zeros(4, dtype=wp.int64, device="cpu"),
        pair_count=wp.zeros(1, dtype=int, device="cpu"),
        by_b=wp.zeros(8, dtype=int, device="cpu"),
        body_pairs_a=wp.zeros(3, dtype=wp.vec2i, device="cpu"),
        body_pairs_b=wp.zeros(3, dtype=wp.vec2i, device="cpu"),
    )
    with pytest.raises(ValueError, match="int32"):
        launch_body_ranges(num_bodies=3, keys_b=wp.zeros(8, dtype=wp.int64, device="cpu"), **kw)
    with pytest.raises(ValueError, match="int32"):
        launch_body_ranges(num_bodies=3, keys_b=wp.zeros(7, dtype=int, device="cpu"), **kw)
    # The sentinel N would not fit an int32 key (checked before anything is launched).
    with pytest.raises(ValueError, match="2\\^31"):
        launch_body_ranges(num_bodies=2**31, keys_b=wp.zeros(8, dtype=int, device="cpu"), **kw)


def contacts_order(contacts):
    bp = contacts.broadphase
    count = contacts.count()
    a, b = bp.pair_a.numpy()[:count], bp.pair_b.numpy()[:count]
    return a, b, contacts.pair_by_b.numpy(), contacts.body_pairs_a.numpy(), contacts.body_pairs_b.numpy()


def test_simulation_pairs_by_b_after_host_and_device_rebuilds(device):
    sim = Simulation(default_scene(), device)
    contacts = sim.current_contacts
    n = contacts.num_bodies
    check_order(n, *contacts_order(contacts))
    # The sort's keys and values live in the scratch the force stage's outputs and the rebuild's previous
    # history share: no buffers of their own.
    lo, hi = contacts._scratch.ptr, contacts._scratch.ptr + contacts._scratch.capacity
    for arr in (contacts._keys_b, contacts._by_b, contacts.pair_force, contacts.previous.key):
        assert lo <= arr.ptr and arr.ptr + arr.capacity <= hi
    sim.step(300)
    check_order(n, *contacts_order(contacts))
    # A device rebuild sorts the whole capacity with padded keys, then sorts by B in the same buffers.
    contacts.rebuild_on_device(sim.current_state.body_q)
    a, b, by_b, ra, rb = contacts_order(contacts)
    assert len(b) > 0 and np.bincount(b).max() > 1
    check_order(n, a, b, by_b, ra, rb)


def check_thread_order(contacts):
    """The threads take every listed pair once, grouped by the cost class of the pair's shapes (ascending; with
    "contact" descending, and in each class the pairs that touched, by their turning volume read right after the
    rebuild, before the others), and in slot order within a group. Returns the number of pairs that touched."""
    count = contacts.count()
    thread = contacts.pair_thread.numpy()[:count]
    np.testing.assert_array_equal(np.sort(thread), np.arange(count))
    shape = contacts.model.body_shape_np
    a, b = contacts.pair_a.numpy()[:count], contacts.pair_b.numpy()[:count]
    key = contacts._pair_class[shape[a], shape[b]].astype(np.int64)
    touched = contacts.pair_turn.numpy()[:count] > 0.0
    if contacts.thread_grouping == "contact":
        key = 2 * (contacts._num_classes - 1 - key) + ~touched
    np.testing.assert_array_equal(thread, np.argsort(key, kind="stable"))
    return int(touched.sum())


def test_pair_threads_ordered_by_cost_give_the_same_bits(device):
    """Simulation(order_pair_threads=True): the default scene's mixed shapes fall in several cost classes; the
    pair kernel's threads take the pairs class by class (also after host and device rebuilds), and the run is
    the same, bit for bit. A scene of one shape has nothing to group and keeps the plain order."""
    runs = {}
    for ordered in (False, "cost"):
        sim = Simulation(default_scene(), device, order_pair_threads=ordered)
        contacts = sim.current_contacts
        assert contacts.thread_order is bool(ordered) and sim.stepper.thread_order is bool(ordered)
        if ordered:
            assert contacts._num_classes > 1
            check_thread_order(contacts)
        sim.step(300)
        runs[ordered] = sim.state()
        if ordered:
            check_thread_order(contacts)
            contacts.rebuild_on_device(sim.current_state.body_q)
            check_thread_order(contacts)
    for key, value in runs[False].items():
        np.testing.assert_array_equal(runs["cost"][key], value, err_msg=key)
    scene = default_scene()
    one = polydem.Scene(gravity=scene.gravity)
    one.add_material("m", density=2500.0, k=1e8, restitution=0.5, friction=0.5, law="hertz")
    one.add_shape("cube", polydem.ConvexShape.box(0.01))
    one.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    one.add_body("cube", "m", position=(0.0, 0.0, 0.006))
    one.add_body("cube", "m", position=(0.0, 0.0, 0.0165))
    sim = Simulation(one, device, order_pair_threads="cost")
    assert not sim.current_contacts.thread_order and len(sim.current_contacts.pair_thread) == 1
    # the default: grouped by cost and contact, one shape too
    for sc in (default_scene(), one):
        sim = Simulation(sc, device)
        assert sim.stepper.thread_order and sim.current_contacts.thread_grouping == "contact"


def test_pair_threads_ordered_by_cost_with_compound_grains(device):
    """scenes/heap.toml (compound elbows beside convex grains, a mesh funnel): classes count a compound grain's
    parts' faces together; the same bits with the threads ordered by cost and by cost and contact (checked after
    a rebuild where some pairs touch)."""
    from pathlib import Path

    scene = polydem.Scene.from_toml(Path(__file__).parents[1] / "scenes" / "heap.toml")
    runs = {}
    for ordered in (False, "cost", "contact"):
        sim = Simulation(scene, device, order_pair_threads=ordered)
        sim.step(8000)  # the first grains out of the funnel have landed: pairs of both kinds
        runs[ordered] = sim.state()
        if ordered:
            assert sim.current_contacts.thread_order and sim.current_contacts._num_classes > 1
            sim.current_contacts.build(sim.current_state.body_q)  # (the check reads the rebuild's history)
            touched = check_thread_order(sim.current_contacts)
            assert 0 < touched < sim.current_contacts.count()
    for key, value in runs[False].items():
        np.testing.assert_array_equal(runs["cost"][key], value, err_msg=key)
        np.testing.assert_array_equal(runs["contact"][key], value, err_msg=key)


@pytest.mark.parametrize("scene_name", ["default", "one shape"])
def test_pair_threads_grouped_by_contact_give_the_same_bits(device, scene_name):
    """order_pair_threads="contact": within each cost class the pairs that touched at the rebuild (a carried
    turning volume) apart from those that did not, in a pile of one shape too; checked right after host and
    device rebuilds of a settling pile, where both kinds are present; the run the same bits as in slot order."""
    if scene_name == "default":
        scene = default_scene()
    else:
        scene = polydem.Scene(gravity=(0.0, 0.0, -9.81), dt="auto")
        scene.add_material("m", density=2500.0, k=1e8, restitution=0.5, friction=0.5, law="hertz")
        scene.add_shape("cube", polydem.ConvexShape.box(0.01))
        scene.add_box_container((0.0, 0.0, 0.03), (0.06, 0.06, 0.06), "m")
        g = np.stack(np.meshgrid(np.arange(4), np.arange(4), np.arange(3), indexing="ij"), -1).reshape(-1, 3)
        scene.add_bodies("cube", "m", (g - [1.5, 1.5, 0.0]) * 0.0125 + [0.0, 0.0, 0.0065])
    runs = {}
    for order in (False, "contact"):
        sim = Simulation(scene, device, order_pair_threads=order)
        contacts = sim.current_contacts
        assert contacts.thread_grouping == ("contact" if order else "slot")
        sim.step(2600)  # the default scene's grains meet after some 2000 steps
        runs[order] = sim.state()
        if order:
            contacts.build(sim.current_state.body_q)
            touched = check_thread_order(contacts)
            assert 0 < touched < contacts.count()
            contacts.rebuild_on_device(sim.current_state.body_q)
            assert check_thread_order(contacts) == touched
    for key, value in runs[False].items():
        np.testing.assert_array_equal(runs["contact"][key], value, err_msg=key)


def test_thread_order_is_checked(device):
    from polydem.contacts import THREAD_ORDER, THREAD_ORDERS

    assert THREAD_ORDER in THREAD_ORDERS
    # truthy and falsy values of other types mean True and False
    assert Simulation(default_scene(), device, order_pair_threads=np.True_).current_contacts.thread_grouping == (
        THREAD_ORDER
    )
    assert Simulation(default_scene(), device, order_pair_threads=0).current_contacts.thread_grouping == "slot"
    with pytest.raises(ValueError, match="order_pair_threads must be True, False or one of"):
        Simulation(default_scene(), device, order_pair_threads="fast")


@pytest.mark.parametrize("spread, threads", [(37, 10**9), (10**7, 10**9), (10**7, 55), (10**7, 0)])
def test_spread_pairs_give_the_same_bits(device, spread, threads):
    """The first pairs of the thread order spread over SPREAD_LANES lanes each (the default on a GPU, none on the
    CPU, whose kernel runs one thread after another): as many as the room of ``threads`` (some pairs, more than
    the list holds) or, with little room, the pairs of costly shapes (counted at each rebuild, checked against
    numpy; 55 threads: the list grows from 43 to 109 pairs, within two "waves"), or none (no room, the list longer
    than two waves of 0). Every pair is still computed once, by one thread: the run and the contacts it reports are
    the same bits as without."""
    from polydem.kernels.forces import spread_room

    from polydem.contacts import COSTLY_FACES

    assert spread_room("cpu") == (0, 0)
    if wp.get_device(device).is_cuda:
        stepper = Simulation(default_scene(), device).stepper
        assert (stepper.spread_pairs, stepper.spread_threads) == spread_room(device) and stepper.spread_pairs > 0
    runs = {}
    for pairs in (0, spread):
        sim = Simulation(default_scene(), device)
        sim.stepper.set_spread(pairs, threads)
        assert sim.stepper.kernels.spread is (pairs > 0)
        sim.step(2600)  # the grains meet after some 2000 steps
        runs[pairs] = sim.state(), sim.contacts()
        contacts = sim.current_contacts
        contacts.build(sim.current_state.body_q)
        a, b = contacts.pair_a.numpy()[: contacts.count()], contacts.pair_b.numpy()[: contacts.count()]
        faces = np.array([s.num_faces for s in sim.model.shapes.shapes])
        shape = sim.model.body_shape.numpy()
        costly = int((faces[shape[a]] * faces[shape[b]] > COSTLY_FACES).sum())
        assert int(contacts.pair_costly.numpy()[0]) == costly
    assert 0 < costly < contacts.count()  # the default scene's rocks: some pairs of each kind
    assert len(runs[0][1]["body_a"]) > 10
    for got, want in zip(runs[spread], runs[0], strict=True):
        for key, value in want.items():
            np.testing.assert_array_equal(got[key], value, err_msg=key)


def test_spread_variant_only_where_the_buffers_could_spread(device, monkeypatch):
    """Pair buffers of more than SPREAD_CAPACITY_WAVES waves (and SPREAD_MIN_CAPACITY pairs) never spread a pair: the
    step launches the plain pair kernel there, without the spread variant's idle threads. The same bits."""
    from polydem.kernels import forces

    import polydem.simulation as simulation

    wave = 67_584
    assert forces.spread_fits(forces.SPREAD_CAPACITY_WAVES * wave, wave)
    assert not forces.spread_fits(forces.SPREAD_CAPACITY_WAVES * wave + 1, wave)
    floor = forces.SPREAD_MIN_CAPACITY
    assert forces.spread_fits(floor, 0) and not forces.spread_fits(floor + 1, 0)
    # The default scene's buffers (1024 pairs) are below the floor: without it, 55 threads a wave are too few.
    monkeypatch.setattr(forces, "SPREAD_MIN_CAPACITY", 0)
    launched = []
    launch = simulation.launch_pair_contacts

    def spy(kernels, **kwargs):
        launched.append((kernels.spread, kwargs["pairs"].capacity))
        return launch(kernels, **kwargs)

    monkeypatch.setattr(simulation, "launch_pair_contacts", spy)
    runs = {}
    for threads in (10**9, 55):
        sim = Simulation(default_scene(), device)
        sim.stepper.set_spread(10**7, threads)
        assert sim.stepper.kernels.spread
        launched.clear()
        sim.step(2600)
        capacity = sim.current_contacts.capacity
        assert capacity > 4 * 55 and launched
        assert {spread for spread, _ in launched} == {threads == 10**9}, (threads, capacity)
        runs[threads] = sim.state(), sim.contacts()
    assert len(runs[55][1]["body_a"]) > 10
    for got, want in zip(runs[55], runs[10**9], strict=True):
        for key, value in want.items():
            np.testing.assert_array_equal(got[key], value, err_msg=key)


def test_spread_needs_the_thread_order(device):
    for order in (False, "cost"):
        sim = Simulation(default_scene(), device, order_pair_threads=order)
        assert sim.stepper.spread_pairs == 0
        with pytest.raises(ValueError, match="needs the pair threads grouped by contact"):
            sim.stepper.set_spread(10)
    with pytest.raises(ValueError, match="spread pairs must be >= 0"):
        Simulation(default_scene(), device).stepper.set_spread(-1)
