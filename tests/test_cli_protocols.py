"""``polydem tap``, ``polydem compress`` and ``polydem anneal`` (issue 26): the records the command prints and
writes are those of polydem.protocols on the same scene, bit for bit; bad options are refused before anything
runs; a run stopped part-way keeps its records and its state."""

import csv
import dataclasses
import json
import math

import numpy as np
import pytest
from cli_helpers import run, write_scene

import polydem
from polydem import protocols
from polydem.checkpoint import read_checkpoint


def header(name: str, simulation: str = "") -> str:
    """The [simulation] (with the lines ``simulation``) and [materials.grain] tables of the scenes below: hertz,
    mixed, the automatic step."""
    return f"""\
[simulation]
name = "{name}"
dt = "auto"
gravity = [0.0, 0.0, -9.81]
{simulation}
[materials.grain]
density = 2500.0
law = "hertz"
k = 1.0e8
restitution = 0.3
friction = 0.5
"""


# Four cubes in a small box tapped twice at 50 Hz, 0.05 s apart: the whole protocol in 0.15 s.
TAPS = (
    header("taps")
    + """

[motions.taps]
frequency = 50.0
gamma = 2.0
start = 0.05
period = 0.05
count = 2

[shapes.cube]
type = "box"
size = 0.02

[[walls]]
type = "box"
center = [0.0, 0.0, 0.03]
inner_size = [0.045, 0.045, 0.06]
material = "grain"
motion = "taps"

[[bodies]]
shape = "cube"
material = "grain"
position = [-0.011, -0.011, 0.0102]

[[bodies]]
shape = "cube"
material = "grain"
position = [0.011, -0.011, 0.0102]

[[bodies]]
shape = "cube"
material = "grain"
position = [-0.011, 0.011, 0.0102]

[[bodies]]
shape = "cube"
material = "grain"
position = [0.011, 0.011, 0.0102]
"""
)

# A cube on a floor pressed by a lid that comes down at 0.1 m/s from 1 mm above it.
PRESS = (
    header("press", "duration = 0.012\n")
    + """

[motions.press]
kind = "ramp"
axis = [0.0, 0.0, -1.0]
speed = 0.1
distance = 0.0011

[shapes.cube]
type = "box"
size = 0.02

[shapes.lid]
type = "box"
size = [0.04, 0.04, 0.01]

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "grain"

[[bodies]]
shape = "cube"
material = "grain"
position = [0.0, 0.0, 0.01]

[[bodies]]
shape = "lid"
material = "grain"
position = [0.0, 0.0, 0.026]
kind = "kinematic"
motion = "press"
"""
)

# Two cubes side by side on a floor, for friction annealing.
PAIR = (
    header("pair")
    + """

[shapes.cube]
type = "box"
size = 0.02

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "grain"

[[bodies]]
shape = "cube"
material = "grain"
position = [0.0, 0.0, 0.0101]

[[bodies]]
shape = "cube"
material = "grain"
position = [0.0205, 0.0, 0.0101]
"""
)


def _plain(record):
    out = {}
    for k, v in dataclasses.asdict(record).items():
        if isinstance(v, np.ndarray):
            v = v.tolist()
        out[k] = None if isinstance(v, float) and not math.isfinite(v) else v
    return out


def _api(path, device, protocol):
    sim = polydem.Simulation(polydem.Scene.from_toml(path), device=device)
    return [_plain(r) for r in protocol(sim)], sim


def _written(folder, command):
    doc = json.loads((folder / f"{command}.json").read_text())
    with (folder / f"{command}.csv").open() as f:
        rows = list(csv.reader(f))
    return doc, rows


def test_tap_command_writes_the_records_of_the_protocol(tmp_path, capsys, device):
    path = write_scene(tmp_path, TAPS)
    out_dir = tmp_path / "out"
    code, out, err = run(["tap", path, "--device", device, "--out", out_dir, "--margin", 0.25], capsys)
    assert code == 0, err
    doc, rows = _written(out_dir, "tap")
    expected, sim = _api(path, device, lambda sim: protocols.tap(sim, "taps", margin=0.25))
    assert doc["records"] == expected  # bit for bit: the same scene, device and protocol
    assert [r["tap"] for r in doc["records"]] == [0, 1, 2]
    assert doc["options"] == {"motion": "taps", "margin": 0.25, "lead": 0.1, "taps": 2}
    assert doc["interrupted"] is False and doc["num_bodies"] == 9 and doc["dt"] == sim.dt
    assert rows[0] == ["tap", "time", "packing_fraction", "kinetic", "fastest"] and len(rows) == 4
    assert [float(x) for x in rows[3][1:]] == [doc["records"][2][k] for k in rows[0][1:]]
    # The table on stdout: a heading and one line per tap, then the files.
    lines = out.splitlines()
    assert "packing fraction" in lines[1] and len([x for x in lines if x.strip()[:1].isdigit()]) == 3
    assert f"wrote {out_dir / 'tap.json'}" in out
    # The final checkpoint holds the state after the last record.
    cp = read_checkpoint(out_dir / "checkpoints" / "final.npz")
    assert cp.time == pytest.approx(doc["records"][-1]["time"], abs=0.5 * sim.dt)
    np.testing.assert_array_equal(cp.arrays["body_q"], sim.current_state.body_q.numpy())


def test_compress_command_writes_the_stress_strain_records(tmp_path, capsys, device):
    path = write_scene(tmp_path, PRESS)
    out_dir = tmp_path / "out"
    code, out, err = run(["compress", path, "--device", device, "--out", out_dir, "--interval", 0.002], capsys)
    assert code == 0, err
    doc, rows = _written(out_dir, "compress")
    expected, _ = _api(path, device, lambda sim: protocols.compress(sim, "press", 0.012, 0.002))
    assert doc["records"] == expected
    assert doc["options"] == {"motions": ["press"], "duration": 0.012, "interval": 0.002}
    # The lid has come down its 1.1 mm and presses on the cube: the grains push it back.
    last = doc["records"][-1]
    assert last["displacement"] == pytest.approx(0.0011, abs=1e-9) and last["force"] > 0.0
    assert last["stress"] == pytest.approx(last["force"] / 0.04**2, rel=1e-12)
    assert rows[0][:3] == ["time", "displacement", "force"] and len(rows) == len(doc["records"]) + 1


def test_anneal_command_restores_the_scene_friction(tmp_path, capsys, device):
    path = write_scene(tmp_path, PAIR)
    out_dir = tmp_path / "out"
    args = ["anneal", path, "--device", device, "--out", out_dir, "--mu-fill", 0.1, "--fill-time", 0.05, "--margin", 0]
    code, out, err = run([*args, "--settle-time", 0.05], capsys)
    assert code == 0, err
    doc, _ = _written(out_dir, "anneal")
    expected, sim = _api(path, device, lambda sim: protocols.anneal(sim, 0.1, None, 0.05, 0.05, margin=0.0))
    assert doc["records"] == expected
    assert [(r["stage"], r["friction"]) for r in doc["records"]] == [("fill", 0.1), ("final", 0.5)]
    assert doc["options"]["mu_final"] == {"grain": 0.5} and sim.material_friction() == {"grain": 0.5}


@pytest.mark.parametrize(
    ("scene", "args", "needle"),
    [
        (PAIR, ["tap"], "motions: the scene must have one motion of taps"),
        (TAPS, ["tap", "--motion", "tapz"], "--motion: no motion named 'tapz'; the scene's motions: taps"),
        (PRESS, ["tap", "--motion", "press"], "--motion: motion 'press' is not a train of taps"),
        (TAPS, ["compress"], "motions: the scene has no piston to compress with"),
        (TAPS, ["compress", "--motion", "taps"], "motion 'taps' is a cycle (vibration, taps)"),
        (PAIR, ["compress", "--motion", "x"], "--motion: no motion named 'x'"),
        (PRESS.replace("duration = 0.012", ""), ["compress"], "--duration: how long to compress?"),
        (PAIR.replace("friction = 0.5", "friction = 0.0"), ["anneal"], "materials: the scene has no friction"),
        (PAIR, ["anneal", "--material", "steel"], "--material: unknown material 'steel'"),
    ],
)
def test_protocol_commands_refuse_bad_options_before_running(device, tmp_path, capsys, scene, args, needle):
    path = write_scene(tmp_path, scene)
    if args[0] == "anneal":
        args = [*args, "--mu-fill", "0.1", "--fill-time", "0.1", "--settle-time", "0.1"]
    code, out, err = run([args[0], path, *args[1:], "--device", device, "--out", tmp_path / "out"], capsys)
    assert code == 2 and needle in err, err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["tap", "s.toml", "--lead", "1.5"], "--lead: expected a fraction of the rest between taps between 0 and 1"),
        (["tap", "s.toml", "--margin", "-1"], "--margin: expected a number of grain sizes >= 0"),
        (["compress", "s.toml", "--interval", "0"], "--interval: expected a simulated time in seconds > 0"),
        (["anneal", "s.toml", "--fill-time", "1", "--settle-time", "1"], "--mu-fill"),
        (["anneal", "s.toml", "--mu-fill", "-0.1", "--fill-time", "1", "--settle-time", "1"], "friction coefficient"),
    ],
)
def test_protocol_command_options_are_checked(capsys, args, needle):
    code, _, err = run(args, capsys)
    assert code == 2 and needle in err, err


def test_a_stopped_tap_run_keeps_its_records_and_state(device, tmp_path, capsys, monkeypatch):
    """A signal during the run (here: seen after the first record) stops it after that record; the record,
    the reason and the state at that time are written, and the exit code is a stopped run's."""
    from polydem import signals

    path = write_scene(tmp_path, TAPS)
    out_dir = tmp_path / "out"
    monkeypatch.setattr(signals, "received", lambda: True)
    code, out, err = run(["tap", path, "--device", device, "--out", out_dir, "--margin", 0.25], capsys)
    assert code == 130, err
    doc, rows = _written(out_dir, "tap")
    assert doc["interrupted"] is True and "Ctrl-C" in doc["reason"] and len(doc["records"]) == 1
    assert "stopped early" in out and len(rows) == 2
    cp = read_checkpoint(out_dir / "checkpoints" / "interrupted.npz")
    assert cp.time == pytest.approx(doc["records"][0]["time"], abs=1e-9)
    assert not (out_dir / "checkpoints" / "final.npz").exists()


def test_a_margin_that_leaves_no_box_is_a_user_error_that_keeps_the_state(device, tmp_path, capsys):
    path = write_scene(tmp_path, TAPS)
    out_dir = tmp_path / "out"
    code, out, err = run(["tap", path, "--device", device, "--out", out_dir, "--margin", 5], capsys)
    assert code == 2 and "leaves nothing of the box around the grains" in err and "give a smaller --margin" in err
    doc, _ = _written(out_dir, "tap")
    assert doc["records"] == [] and doc["interrupted"] is True
    assert (out_dir / "checkpoints" / "interrupted.npz").exists()


def test_a_stopped_tap_run_resumes_where_it_stopped(tmp_path, capsys, monkeypatch, device):
    """`polydem tap --resume` on the checkpoint of a run stopped after its first record makes the remaining taps:
    its tap.json holds the earlier record and the new ones, equal bit for bit to those of a run never stopped."""
    from polydem import signals

    path = write_scene(tmp_path, TAPS)
    whole, parts = tmp_path / "whole", tmp_path / "parts"
    code, _, err = run(["tap", path, "--device", device, "--out", whole, "--margin", 0.25], capsys)
    assert code == 0, err
    with monkeypatch.context() as m:
        m.setattr(signals, "received", lambda: True)
        code, _, err = run(["tap", path, "--device", device, "--out", parts, "--margin", 0.25], capsys)
    assert code == 130, err
    stopped = parts / "checkpoints" / "interrupted.npz"
    args = ["tap", path, "--device", device, "--out", parts, "--margin", 0.25, "--resume", stopped]
    code, out, err = run(args, capsys)
    assert code == 0, err
    doc, rows = _written(parts, "tap")
    assert doc["records"] == _written(whole, "tap")[0]["records"]  # taps 0, 1, 2: one before the stop, two after
    assert doc["resumed_from"] == str(stopped.resolve()) and len(rows) == 4
    assert len([x for x in out.splitlines() if x.strip()[:1].isdigit()]) == 2  # only the new taps are printed


@pytest.mark.parametrize("which", ["missing", "other scene", "other margin"])
def test_tap_resume_refuses_a_checkpoint_it_cannot_use(tmp_path, capsys, device, which):
    path = write_scene(tmp_path, TAPS)
    if which == "missing":
        checkpoint, needle = tmp_path / "nope.npz", "checkpoint not found"
    elif which == "other margin":  # its records were measured in another box: they would not go together
        code, _, err = run(["tap", path, "--device", device, "--out", tmp_path / "o", "--margin", 0.3], capsys)
        assert code == 0, err
        checkpoint, needle = tmp_path / "o" / "checkpoints" / "final.npz", "used --margin 0.3, this one --margin 2.0"
    else:
        other = write_scene(tmp_path, TAPS.replace("gamma = 2.0", "gamma = 2.5"), name="other.toml")
        code, _, err = run(["tap", other, "--device", device, "--out", tmp_path / "o", "--margin", 0.25], capsys)
        assert code == 0, err
        checkpoint = tmp_path / "o" / "checkpoints" / "final.npz"
        needle = "motions.taps.gamma differs: checkpoint 2.5, scene 2"  # the motions are part of the physics
    code, _, err = run(["tap", path, "--device", device, "--out", tmp_path / "r", "--resume", checkpoint], capsys)
    assert code == 2 and needle in err and "--resume" in err, err


def test_the_physics_record_of_motions_compares_equal_to_itself(tmp_path):
    """A checkpoint's record of the scene's motions (read back from JSON) matches the same scene, and names a
    changed motion; a scene without motions keeps the record it had before motions were recorded."""
    from polydem.checkpoint import physics_description, physics_differences

    desc, arrays = physics_description(polydem.Scene.from_toml(write_scene(tmp_path, TAPS)), 1e-5)
    stored = json.loads(json.dumps(desc))
    assert stored["bodies.motion"] and physics_differences(stored, arrays, desc, arrays) == []
    other = polydem.Scene.from_toml(write_scene(tmp_path, TAPS.replace("gamma = 2.0", "gamma = 2.5"), "o.toml"))
    assert physics_differences(stored, arrays, *physics_description(other, 1e-5)) == [
        "motions.taps.gamma differs: checkpoint 2, scene 2.5"
    ]
    plain, _ = physics_description(polydem.Scene.from_toml(write_scene(tmp_path, PAIR, "p.toml")), 1e-5)
    assert not any(k.startswith("motions") or k.endswith(".motion") for k in plain)
