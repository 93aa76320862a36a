"""Checkpoint and resume give the same result as an unbroken run."""

import numpy as np
import pytest

import polydem
from polydem.checkpoint import load_checkpoint, save_checkpoint
from polydem.default_scene import default_scene


def test_resume_equals_unbroken_run(device, tmp_path):
    scene = default_scene(count=40, seed=2)
    unbroken = polydem.Simulation(scene, device=device)
    unbroken.step(3000)
    first = polydem.Simulation(scene, device=device)
    first.step(1400)
    save_checkpoint(first, tmp_path / "run.npz")
    resumed = polydem.Simulation(scene, device=device)
    load_checkpoint(resumed, tmp_path / "run.npz")
    assert resumed.steps_done == 1400
    resumed.step(1600)
    a, b = unbroken.state(), resumed.state()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert unbroken.energy()["dissipated"] == resumed.energy()["dissipated"]
    assert len(unbroken.contacts()["volume"]) > 0  # the run has contacts (and friction springs) to carry


def test_bad_checkpoints(device, tmp_path):
    scene = default_scene(count=10)
    sim = polydem.Simulation(scene, device=device)
    with pytest.raises(ValueError, match=".npz"):
        save_checkpoint(sim, tmp_path / "run.bin")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_checkpoint(sim, tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="not a polydem checkpoint"):
        load_checkpoint(sim, tmp_path / "junk.npz")
    save_checkpoint(sim, tmp_path / "ok.npz")
    other = polydem.Simulation(default_scene(count=12), device=device)
    with pytest.raises(ValueError, match="bodies"):
        load_checkpoint(other, tmp_path / "ok.npz")
