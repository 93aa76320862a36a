"""A step split in two parts (Stepper.split_at, Simulation.advance_split): the same bits as the whole step, and
the rows launched between the parts (kernels/ghosts.py launch_step_rows) are the flagged bodies' state at its end.

A decomposed run splits its steps so that the ghosts' rows travel while the second part runs
(tests/test_distributed.py checks that run against the undivided one); here one process, on every device, with
CUDA graphs where the device has them.
"""

import numpy as np
import pytest
import warp as wp
from distributed_scenes import build
from polydem.kernels.ghosts import launch_pack_rows, launch_step_rows

from polydem import Simulation


def _rows(sim, index):
    st = sim.current_state
    scalar = sim.model.scalar
    rows = wp.zeros((len(index), 14), dtype=scalar, device=sim.device)
    q, v, w = (getattr(st, f).view(scalar) for f in ("body_q", "body_v", "body_w"))
    idx = wp.array(index.astype(np.int32), dtype=int, device=sim.device)
    launch_pack_rows(q=q, v=v, w=w, damping=st.body_damping, index=idx, rows=rows)
    return rows.numpy()


@pytest.mark.parametrize(
    "scene, ordered, graphs", [("box_pour", True, True), ("box_pour", False, True), ("box_pour", True, False),
                               ("chain", True, True)]
)  # fmt: skip
def test_split_step_is_the_step(device, scene, ordered, graphs):
    """``ordered``: the pair threads grouped (the default), the first part's pairs first in their order and the
    first part launching threads for them alone; else each part's kernels skip the other part's pairs. On a GPU
    the first part runs on a stream of its own beside the other pairs, from captured graphs or (``graphs``
    off) launched one by one."""
    if not graphs and not wp.get_device(device).is_cuda:
        pytest.skip("graphs are a GPU's")
    whole = Simulation(build(scene), device=device)
    split = Simulation(build(scene), device=device, order_pair_threads=ordered, use_graph=graphs)
    n = whole.model.num_bodies
    rng = np.random.default_rng(1)
    flags = rng.random(n) < 0.3
    flags &= whole.model.body_flags_np == 0  # free bodies: a decomposed run sends no other
    index = np.flatnonzero(flags)
    assert len(index) > 5
    split.split_at(flags)
    assert split.stepper.kernels.phased and split.stepper.kernels.thread_order == ordered
    st, m = split.current_state, split.model
    rows = wp.zeros((len(index), 14), dtype=m.scalar, device=split.device)
    idx = wp.array(index.astype(np.int32), dtype=int, device=split.device)

    def between():
        launch_step_rows(model=m.bodies, gravity=m.gravity, dt=split.dt, bodies=st.bodies, damping=st.body_damping,
                         index=idx, rows=rows)  # fmt: skip

    def probe_first_part():
        # The first part's pairs come first in the order; with too few threads for them the step notices (a
        # caller grows them and redoes it).
        first = int(split.current_contacts.pair_first_count.numpy()[0])
        assert 0 < first < split.current_contacts.count()
        snap = split.snapshot()
        split.stepper.first_room = 1
        split.advance_split(lambda: None, key="too few")
        assert split.stepper.buffers_overflowed()
        split.stepper.grow_buffers()
        assert split.stepper.first_room == 2 and not split.stepper.buffers_overflowed()
        split.restore(snap)
        split.split_at(flags)  # room for the pairs there are
        assert split.stepper.first_room == max(1024, 2 * first)

    steps = 3000 if scene == "box_pour" else 1500  # as in test_distributed: grains in contact by then
    checked = 0
    for k in range(steps):
        whole.advance(1)
        event = split.advance_split(between, key="test")
        if event is not None:
            wp.synchronize_event(event)
        if ordered and k == steps // 2:
            probe_first_part()
        if k % 100 == 99:
            np.testing.assert_array_equal(rows.numpy(), _rows(whole, index))
            checked += 1
    wp.synchronize_device(split.device)
    assert checked == steps // 100
    want, got = whole.state(), split.state()
    assert np.abs(want["body_velocity"]).max() > 0.0
    for k, v in want.items():
        np.testing.assert_array_equal(got[k], v, err_msg=k)
    assert whole.contacts()["body_a"].size > 10
    for k, v in whole.contacts().items():
        np.testing.assert_array_equal(split.contacts()[k], v, err_msg=k)


def test_split_needs_one_flag_per_body_and_no_mesh_walls(device):
    sim = Simulation(build("box_pour"), device=device)
    with pytest.raises(ValueError, match="one flag per body"):
        sim.split_at(np.ones(3, dtype=bool))
    with pytest.raises(RuntimeError, match="split_at"):
        sim.stepper.step_part(sim.current_state, sim.current_contacts, sim.dt, 1)
    mixer = Simulation(build("mixer"), device=device)
    with pytest.raises(ValueError, match="mesh walls"):
        mixer.split_at(np.ones(mixer.model.num_bodies, dtype=bool))
