"""The polydem command: outputs, user errors, interruption and resume, validate, render, info (CPU)."""

import glob
import io
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import polydem
from polydem import cli
from polydem.cli import main
from polydem.simulation import Simulation, SimulationError

REPO = Path(__file__).resolve().parents[1]
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
STEPS = 400

# 12 cubes and tetrahedra thrown down (1.5 m/s) into an open box of fixed slabs: contacts (and
# friction springs) from about step 60 on, 400 steps in well under a second on one CPU core.
TINY = """\
[simulation]
name = "tiny"
dt = "auto"
steps = 400

[materials.stone]
density = 2500.0
law = "hertz"
k = 1.0e8
restitution = 0.4
friction = 0.5

[shapes.cube]
type = "box"
size = 0.02

[shapes.tet]
type = "tetrahedron"
edge = 0.028

[[walls]]
type = "box"
center = [0.0, 0.0, 0.04]
inner_size = [0.16, 0.16, 0.08]
wall_thickness = 0.01
material = "stone"

[[emitters]]
shape = ["cube", "tet"]
material = "stone"
count = 12
region = { min = [-0.08, -0.08, 0.0], max = [0.08, 0.08, 0.08] }
velocity = [0.0, 0.0, -1.5]
seed = 1

[output]
fps = 500
usd = "tiny.usda"
checkpoint = { steps = 150 }
pictures = [1]
"""

STATE_KEYS = ("steps_done", "body_q", "body_v", "body_w", "body_dissipated", "plane_xi", "plane_turn", "step_count")


def write_scene(folder, text=TINY, name="tiny.toml", replace=()):
    for old, new in replace:
        assert old in text, old
        text = text.replace(old, new)
    path = Path(folder) / name
    path.write_text(text)
    return path


def run(args, capsys):
    """main(args) in this process: (exit code, stdout, stderr)."""
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def expected_frames(steps, dt, fps):
    """Frames k = 0, 1, ... whose step ceil(k / fps / dt) the run reaches."""
    k = 0
    while math.ceil(k / fps / dt - 1e-9) <= steps:
        k += 1
    return k


def springs(data):
    """Friction springs of a checkpoint by pair key (the candidate list itself depends on rebuild times)."""
    on = np.any(data["pair_xi"] != 0.0, axis=1)
    return dict(zip(data["pair_key"][on].tolist(), map(tuple, data["pair_xi"][on].tolist()), strict=True))


def turning_volumes(data):
    """Turning volumes of the normal hysteresis of a checkpoint by pair key."""
    on = data["pair_turn"] != 0.0
    return dict(zip(data["pair_key"][on].tolist(), data["pair_turn"][on].tolist(), strict=True))


def assert_same_state(path_a, path_b):
    with np.load(path_a) as a, np.load(path_b) as b:
        for key in STATE_KEYS:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        assert springs(a) == springs(b)
        assert turning_volumes(a) == turning_volumes(b)
        # The run carries pair history across the checkpoint (at the end of this one the pairs are
        # leaving the dents of their impacts: turning volumes, but no normal force, so no springs).
        assert len(springs(a)) + len(turning_volumes(a)) > 0


def assert_user_error(code, err, *needles):
    assert code == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("polydem: error: ")
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


@pytest.fixture(scope="module")
def unbroken(tmp_path_factory):
    """An uninterrupted run of the tiny scene: (scene file, output folder)."""
    folder = tmp_path_factory.mktemp("unbroken")
    scene = write_scene(folder)
    assert main(["run", str(scene), "--device", "cpu", "--out", str(folder / "out"), "--quiet"]) == 0
    return scene, folder / "out"


# ---------------------------------------------------------------------- help


def test_module_help_subprocess():
    proc = subprocess.run(
        [sys.executable, "-m", "polydem", "--help"], capture_output=True, text=True, timeout=60, cwd=REPO
    )
    assert proc.returncode == 0, proc.stderr
    for command in ("run", "validate", "render", "info"):
        assert command in proc.stdout
    assert "Traceback" not in proc.stderr


def test_every_option_is_described(capsys):
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if hasattr(a, "choices") and isinstance(a.choices, dict))
    assert set(sub.choices) == {"run", "validate", "render", "info"}
    for name, command in sub.choices.items():
        code, out, _ = run([name, "--help"], capsys)
        assert code == 0
        assert command.description and command.description.split()[0] in out
        for action in command._actions:
            assert action.help, (name, action.dest)
            for option in action.option_strings:
                assert option in out, (name, option)
    code, out, _ = run(["run", "--help"], capsys)
    for word in ("--resume", "interrupted.npz", "from_step", "80th percentile", "exit codes"):
        assert word in out


# ---------------------------------------------------------------------- run


def test_run_writes_every_output(tmp_path, capsys):
    scene = write_scene(tmp_path)
    out_dir = tmp_path / "out"
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "--picture-size", "64x48"], capsys)
    assert code == 0, err
    assert "Traceback" not in err
    assert out.startswith("tiny: 17 bodies (12 free) on cpu")
    assert "done: 400 steps" in out
    # Progress: not a terminal, so one line per 5% and no carriage returns.
    progress = [line for line in err.splitlines() if "steps/s" in line]
    assert 15 <= len(progress) <= 21 and "\r" not in err
    assert "contacts" in progress[-1] and "kinetic" in progress[-1] and "100.0%" in progress[-1]

    summary = json.loads((out_dir / "summary.json").read_text())
    for key in (
        "steps",
        "simulated_time",
        "wall_time",
        "bodies",
        "contacts",
        "energy",
        "largest_overlap",
        "settled_region",
        "interrupted",
        "reason",
        "outputs",
        "frames",
    ):
        assert key in summary, key
    assert summary["steps"] == STEPS and summary["interrupted"] is False and summary["reason"] is None
    assert summary["bodies"] == {"total": 17, "free": 12, "fixed": 5, "kinematic": 0}
    dt = summary["dt"]
    assert summary["simulated_time"] == pytest.approx(STEPS * dt)
    frames = expected_frames(STEPS, dt, 500.0)
    assert summary["frames"] == frames
    assert summary["contacts"]["max"] >= summary["contacts"]["mean"] > 0
    assert summary["contacts"]["final"] > 0
    assert 0.0 < summary["largest_overlap"]["final"]["relative"] < 0.5
    assert summary["largest_overlap"]["max_over_frames"] > 0.0
    assert set(summary["energy"]["final"]) >= {"kinetic", "contact", "gravity", "dissipated", "total"}
    region = summary["settled_region"]
    assert set(region) >= {"packing_fraction", "coordination_number", "bodies"}
    assert summary["outputs"]["checkpoints"] == [
        "checkpoints/step_000000150.npz",
        "checkpoints/step_000000300.npz",
        "checkpoints/final.npz",
    ]

    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(out_dir / "tiny.usda"))
    inst = UsdGeom.PointInstancer.Get(stage, "/World/Bodies")
    samples = inst.GetPositionsAttr().GetTimeSamples()
    assert samples == [float(k) for k in range(frames)]
    assert summary["outputs"]["usd_frames"] == frames
    del inst, stage

    picture = out_dir / "pictures" / "frame_000001.png"
    assert picture.read_bytes()[:8] == PNG_SIGNATURE
    for name in ("step_000000150.npz", "step_000000300.npz", "final.npz"):
        with np.load(out_dir / "checkpoints" / name) as data:
            assert int(data["steps_done"]) == int(name[5:14]) if name.startswith("step") else STEPS


def test_default_folder_duration_and_usd_default(tmp_path, capsys, monkeypatch):
    # No usd key in the scene file: trajectory.usdc; --duration counts from t = 0; --fps overrides.
    text = TINY.replace('usd = "tiny.usda"\n', "").replace("pictures = [1]\n", 'pictures = "last"\n')
    scene = write_scene(tmp_path, text)
    monkeypatch.chdir(tmp_path)
    code, out, err = run(["run", scene, "--device", "cpu", "--duration", "0.004", "--fps", "1000", "-q"], capsys)
    assert code == 0, err
    assert err == ""  # --quiet: no progress
    out_dir = tmp_path / "polydem_out" / "tiny"
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["steps"] == math.ceil(0.004 / summary["dt"])
    assert summary["fps"] == 1000.0
    assert (out_dir / "trajectory.usdc").is_file()
    assert summary["outputs"]["usd_frames"] == expected_frames(summary["steps"], summary["dt"], 1000.0)
    assert (out_dir / "pictures" / "last.png").read_bytes()[:8] == PNG_SIGNATURE


def test_usd_false_writes_no_usd(tmp_path, capsys):
    scene = write_scene(tmp_path, replace=[('usd = "tiny.usda"', "usd = false"), ("pictures = [1]", "")])
    code, _, err = run(["run", scene, "--device", "cpu", "--steps", "50", "--out", tmp_path / "o", "-q"], capsys)
    assert code == 0, err
    assert not list((tmp_path / "o").glob("*.usd*"))
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["outputs"]["usd"] is None


# ---------------------------------------------------------------------- user errors


@pytest.mark.parametrize(
    "replace, needles",
    [
        ([("steps = 400", "stepz = 400")], ["tiny.toml", "simulation.stepz", "did you mean 'steps'"]),
        ([("density = 2500.0", 'density = "heavy"')], ["tiny.toml", "materials.stone.density", "expected a number"]),
        ([("count = 12", "count = -3")], ["tiny.toml", "emitters[0].count", ">= 1"]),
        ([("count = 12", "count = 200")], ["tiny.toml", "emitters[0].count", "region holds at most", "Lower count"]),
        ([('dt = "auto"', "dt = 0.01")], ["tiny.toml", "simulation.dt", "stable limit", 'dt = "auto"']),
        ([('law = "hertz"', 'law = "herz"')], ["tiny.toml", "materials.stone.law", "did you mean 'hertz'"]),
        ([("[output]", "[output]\nfsp = 3")], ["tiny.toml", "output.fsp", "did you mean 'fps'"]),
    ],
)
def test_scene_errors(tmp_path, capsys, replace, needles):
    scene = write_scene(tmp_path, replace=replace)
    code, _, err = run(["run", scene, "--device", "cpu", "--out", tmp_path / "o"], capsys)
    assert_user_error(code, err, *needles)
    assert not (tmp_path / "o" / "summary.json").exists()
    code, _, err = run(["validate", scene], capsys)
    assert_user_error(code, err, *needles)


def test_missing_scene_file(tmp_path, capsys):
    code, _, err = run(["run", tmp_path / "nope.toml"], capsys)
    assert_user_error(code, err, "nope.toml", "not found", "check the path")


@pytest.mark.parametrize(
    "args, needles",
    [
        (["--steps", "-3"], ["--steps", "at least 1 step"]),
        (["--steps", "0"], ["--steps", "at least 1 step"]),
        (["--steps", "abc"], ["--steps", "whole number", "'abc'"]),
        (["--steps", "2.5"], ["--steps", "whole number"]),
        (["--steps", "10", "--duration", "0.1"], ["--duration", "not allowed with", "--steps"]),
        (["--duration", "-1"], ["--duration", "> 0"]),
        (["--fps", "0"], ["--fps", "> 0"]),
        (["--precision", "float64"], ["--precision", "float32 only"]),
        (["--precision", "double"], ["--precision", "invalid choice"]),
        (["--device", "gpu"], ["--device", "unknown device 'gpu'"]),
        (["--device", "cuda:97"], ["--device", "'cuda:97' is not available"]),
        (["--picture-size", "big"], ["--picture-size", "WIDTHxHEIGHT"]),
        (["--bogus"], ["unrecognized arguments: --bogus"]),
    ],
)
def test_option_errors(tmp_path, capsys, args, needles):
    scene = write_scene(tmp_path)
    code, _, err = run(["run", scene, "--out", tmp_path / "o", *args], capsys)
    assert_user_error(code, err, *needles)


def test_checkpoint_errors(tmp_path, capsys, unbroken):
    scene, out_dir = unbroken
    final = out_dir / "checkpoints" / "final.npz"
    base = ["run", scene, "--device", "cpu", "--out", tmp_path / "o"]

    code, _, err = run([*base, "--resume", tmp_path / "missing.npz"], capsys)
    assert_user_error(code, err, "missing.npz", "--resume", "checkpoint not found")

    (tmp_path / "junk.npz").write_bytes(b"not a checkpoint")
    code, _, err = run([*base, "--resume", tmp_path / "junk.npz"], capsys)
    assert_user_error(code, err, "junk.npz", "not a polydem checkpoint")

    # Another scene: other body count, or the same count with the container elsewhere.
    other = write_scene(tmp_path, name="other.toml", replace=[("count = 12", "count = 10")])
    code, _, err = run(["run", other, "--device", "cpu", "--out", tmp_path / "o", "--resume", final], capsys)
    assert_user_error(code, err, "final.npz", "--resume", "has 17 bodies", "has 15")
    moved = write_scene(
        tmp_path, name="moved.toml", replace=[("center = [0.0, 0.0, 0.04]", "center = [0.0, 0.0, 0.05]")]
    )
    code, _, err = run(["run", moved, "--device", "cpu", "--out", tmp_path / "o", "--resume", final], capsys)
    assert_user_error(code, err, "final.npz", "fixed body", "another scene")
    code, _, err = run(["run", "--device", "cpu", "--out", tmp_path / "o", "--resume", final], capsys)
    assert_user_error(code, err, "the built-in default scene has 305")

    # A checkpoint that already reaches the end.
    code, _, err = run([*base, "--resume", final], capsys)
    assert_user_error(code, err, "already reaches the 400 steps", "--steps or --duration")
    assert not (tmp_path / "o" / "summary.json").exists()


# ---------------------------------------------------------------------- interruption and resume


def interrupt_after(monkeypatch, calls, exc):
    """Make the `calls`-th Simulation.step call raise `exc` (before stepping)."""
    original = Simulation.step
    count = {"n": 0}

    def step(self, n=1):
        count["n"] += 1
        if count["n"] == calls:
            raise exc
        return original(self, n)

    monkeypatch.setattr(Simulation, "step", step)


def check_interrupted(out_dir, reason):
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["interrupted"] is True and reason in summary["reason"]
    steps = summary["steps"]
    assert 0 < steps < STEPS
    assert summary["outputs"]["checkpoints"][-1] == "checkpoints/interrupted.npz"
    with np.load(out_dir / "checkpoints" / "interrupted.npz") as data:
        assert int(data["steps_done"]) == steps == int(data["step_count"][0])
        assert np.all(np.isfinite(data["body_q"]))
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(out_dir / "tiny.usda"))
    samples = UsdGeom.PointInstancer.Get(stage, "/World/Bodies").GetPositionsAttr().GetTimeSamples()
    assert len(samples) == summary["outputs"]["usd_frames"] == expected_frames(steps, summary["dt"], 500.0)
    return steps


def test_ctrl_c_keeps_outputs_and_resume_equals_unbroken_run(tmp_path, capsys, monkeypatch, unbroken):
    scene, unbroken_dir = unbroken
    out_dir = tmp_path / "out"
    interrupt_after(monkeypatch, 5, KeyboardInterrupt())
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir], capsys)
    monkeypatch.undo()
    assert code == 130
    assert "Traceback" not in err
    assert "interrupted:" in out and "--resume" in err
    steps = check_interrupted(out_dir, "Ctrl-C")

    code, out, err = run(
        ["run", scene, "--device", "cpu", "--out", out_dir, "--resume", out_dir / "checkpoints" / "interrupted.npz"],
        capsys,
    )
    assert code == 0, err
    assert_same_state(unbroken_dir / "checkpoints" / "final.npz", out_dir / "checkpoints" / "final.npz")
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["interrupted"] is False and summary["steps"] == STEPS
    assert summary["steps_this_run"] == STEPS - steps
    assert summary["resumed_from"].endswith("interrupted.npz")
    # The resumed frames go to their own USD file; its time codes continue the first file's.
    resumed = out_dir / f"tiny.from_step_{steps}.usda"
    assert summary["outputs"]["usd"] == resumed.name
    from polydem.usd import read_time_codes

    first = read_time_codes(out_dir / "tiny.usda")
    second = read_time_codes(resumed)
    assert second[0] > first[-1]
    assert len(first) + len(second) == expected_frames(STEPS, summary["dt"], 500.0)


def test_resume_from_periodic_checkpoint(tmp_path, capsys, unbroken):
    scene, unbroken_dir = unbroken
    code, _, err = run(
        [
            "run",
            scene,
            "--device",
            "cpu",
            "--out",
            tmp_path / "out",
            "-q",
            "--resume",
            unbroken_dir / "checkpoints" / "step_000000150.npz",
        ],
        capsys,
    )
    assert code == 0, err
    assert_same_state(unbroken_dir / "checkpoints" / "final.npz", tmp_path / "out" / "checkpoints" / "final.npz")


def test_interrupt_inside_a_step_rolls_back(tmp_path, capsys, monkeypatch, unbroken):
    """A KeyboardInterrupt part-way through Simulation.step (the second Ctrl-C) leaves a consistent checkpoint."""
    scene, unbroken_dir = unbroken
    original = Simulation._run_chunk
    count = {"n": 0}

    def run_chunk(self, steps):
        original(self, steps)  # the state moves on, but steps_done is not counted yet
        count["n"] += 1
        if count["n"] == 4:
            raise KeyboardInterrupt

    monkeypatch.setattr(Simulation, "_run_chunk", run_chunk)
    out_dir = tmp_path / "out"
    code, _, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "-q"], capsys)
    monkeypatch.undo()
    assert code == 130 and "Traceback" not in err
    check_interrupted(out_dir, "Ctrl-C")
    code, _, err = run(
        ["run", scene, "--device", "cpu", "--out", out_dir, "-q", "--resume", out_dir / "checkpoints/interrupted.npz"],
        capsys,
    )
    assert code == 0, err
    assert_same_state(unbroken_dir / "checkpoints" / "final.npz", out_dir / "checkpoints" / "final.npz")


def test_first_ctrl_c_stops_after_the_steps_under_way(tmp_path, capsys, monkeypatch, unbroken):
    """A real SIGINT: the run finishes the steps under way, then writes its outputs (exit code 130)."""
    scene, unbroken_dir = unbroken
    original = Simulation.step
    count = {"n": 0}

    def step(self, n=1):
        count["n"] += 1
        if count["n"] == 3:
            os.kill(os.getpid(), signal.SIGINT)  # the handler only sets a flag: this step still runs
        return original(self, n)

    monkeypatch.setattr(Simulation, "step", step)
    out_dir = tmp_path / "out"
    code, _, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "-q"], capsys)
    monkeypatch.undo()
    assert code == 130 and "Traceback" not in err
    assert "stopping after the steps under way" in err
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored
    check_interrupted(out_dir, "Ctrl-C")
    code, _, err = run(
        ["run", scene, "--device", "cpu", "--out", out_dir, "-q", "--resume", out_dir / "checkpoints/interrupted.npz"],
        capsys,
    )
    assert code == 0, err
    assert_same_state(unbroken_dir / "checkpoints" / "final.npz", out_dir / "checkpoints" / "final.npz")


def test_internal_error_keeps_traceback_and_outputs(tmp_path, capsys, monkeypatch):
    scene = write_scene(tmp_path)
    interrupt_after(monkeypatch, 3, RuntimeError("a bug"))
    out_dir = tmp_path / "out"
    with pytest.raises(RuntimeError, match="a bug"):  # not caught: Python prints the traceback, exit code 1
        main(["run", str(scene), "--device", "cpu", "--out", str(out_dir), "-q"])
    capsys.readouterr()
    check_interrupted(out_dir, "internal error: RuntimeError: a bug")


def test_progress_on_a_terminal_updates_one_line(tmp_path, capsys, monkeypatch):
    class Terminal(io.StringIO):
        def isatty(self):
            return True

    scene = write_scene(tmp_path, replace=[("pictures = [1]", "")])
    terminal = Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    code, _, _ = run(["run", scene, "--device", "cpu", "--out", tmp_path / "o", "--steps", "200"], capsys)
    assert code == 0
    text = terminal.getvalue()
    assert text.startswith("\r") and text.endswith("\n") and text.count("\n") == 1
    assert "100.0%" in text.split("\r")[-1] and "steps/s" in text and "contacts" in text


def test_simulation_error_keeps_outputs(tmp_path, capsys, monkeypatch):
    scene = write_scene(tmp_path)
    interrupt_after(monkeypatch, 4, SimulationError("the state became non-finite at step 123 (test)"))
    out_dir = tmp_path / "out"
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "-q"], capsys)
    assert code == 1
    assert "Traceback" not in err
    assert "the simulation failed: the state became non-finite at step 123" in err
    check_interrupted(out_dir, "SimulationError")


# ---------------------------------------------------------------------- validate, render, info


def test_validate_every_shipped_scene_quickly(capsys):
    files = sorted(glob.glob(str(REPO / "scenes" / "*.toml")))
    assert len(files) >= 5
    t0 = time.perf_counter()
    code, out, err = run(["validate", *files], capsys)
    elapsed = time.perf_counter() - t0
    assert code == 0, err
    assert err == ""
    assert out.count("is a valid scene") == len(files)
    assert "stable limit" in out and "tetrahedra_100k" in out
    assert elapsed < 10.0, f"validate took {elapsed:.1f} s"
    code, out, _ = run(["validate", "--quiet", files[0]], capsys)
    assert code == 0 and out.count("\n") == 1 and ": OK, " in out


def test_validate_reports_every_bad_file(tmp_path, capsys):
    good = write_scene(tmp_path)
    bad = write_scene(tmp_path, name="bad.toml", replace=[("count = 12", "count = -1")])
    code, out, err = run(["validate", good, bad], capsys)
    assert code == 2
    assert "Traceback" not in err and err.count("\n") == 1 and "bad.toml: emitters[0].count" in err
    assert f"OK: {good} is a valid scene" in out


@pytest.mark.parametrize(
    ("replace", "key", "fix"),
    [
        # Issue 9: each of these validated (exit 0) and then hung or failed in a run.
        ([("density = 2500.0", "density = 1e300")], "materials.stone.density", "use a density between"),
        ([("k = 1.0e8", "k = 1e-10")], "materials.stone.k", "raise k of 'stone' to at least"),
        ([('law = "hertz"', 'law = "power"\nm = 100')], "materials.stone.m", "use m between 1 and"),
        ([("size = 0.02", "size = 1e-9")], "shapes.cube", "give the shape a bounding radius between"),
        ([("count = 12", "count = 1e9")], "emitters[0].count", "lower count"),
        ([("[[walls]]", '[[bodies]]\nshape = "cube"\nmaterial = "stone"\nposition = [0.0, 0.0, -0.005]\n\n[[walls]]')],
         "bodies[0].position", "move the two apart"),
    ],
)  # fmt: skip
def test_validate_rejects_what_a_run_cannot_do(tmp_path, capsys, replace, key, fix):
    bad = write_scene(tmp_path, name="bad.toml", replace=replace)
    t0 = time.perf_counter()
    code, out, err = run(["validate", bad], capsys)
    assert time.perf_counter() - t0 < 5.0
    assert code == 2 and out == ""
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"polydem: error: {bad}: {key}: ") and fix in err


def test_validate_prints_warnings_and_passes(tmp_path, capsys):
    """A moderate initial overlap (the cube 3 mm into the 1 cm floor slab: 30% of the thinner one) warns."""
    body = '[[bodies]]\nshape = "cube"\nmaterial = "stone"\nposition = [0.0, 0.0, 0.007]\n\n[[walls]]'
    path = write_scene(tmp_path, replace=[("[[walls]]", body)])
    code, out, err = run(["validate", path], capsys)
    assert code == 0 and f"OK: {path} is a valid scene" in out
    assert err.count("\n") == 1
    assert err.startswith(f"polydem: warning: {path}: 1 initial overlaps ")
    assert "body 0 (shape 'cube', free) 0.003 m into body " in err and ", fixed) (30.0%); move the bodies" in err


def test_render_scene_checkpoint_and_usd_frame(tmp_path, capsys, unbroken):
    scene, out_dir = unbroken
    size = ["--width", "64", "--height", "48", "--device", "cpu"]
    for source, extra in (
        (scene, []),
        (out_dir / "checkpoints" / "final.npz", ["--scene", scene]),
        (out_dir / "tiny.usda", ["--scene", scene, "--frame", "3"]),
        (out_dir / "tiny.usda", ["--scene", scene]),  # the last frame
    ):
        png = tmp_path / "pic.png"
        png.unlink(missing_ok=True)
        code, out, err = run(["render", source, "--out", png, *size, *extra], capsys)
        assert code == 0, err
        assert png.read_bytes()[:8] == PNG_SIGNATURE
        assert out.startswith(f"wrote {png} (64 x 48)")


def test_render_errors(tmp_path, capsys, unbroken):
    scene, out_dir = unbroken
    png = tmp_path / "pic.png"
    cases = [
        (["render", scene, "--out", tmp_path / "pic.jpg"], ["pic.jpg", "--out", ".png"]),
        (["render", scene, "--out", png, "--frame", "3"], ["tiny.toml", "--frame", "frame 0 only"]),
        (["render", out_dir / "tiny.usda", "--scene", scene, "--frame", "99", "--out", png], ["no frame 99", "0 to 7"]),
        (["render", out_dir / "checkpoints" / "final.npz", "--out", png], ["built-in default scene has 305"]),
        (
            ["render", out_dir / "checkpoints" / "final.npz", "--scene", scene, "--frame", "1", "--out", png],
            ["one state"],
        ),
        (["render", tmp_path / "missing.npz", "--out", png], ["missing.npz", "not found"]),
        (["render", scene], ["--out"]),
    ]
    for args, needles in cases:
        code, _, err = run(args, capsys)
        assert_user_error(code, err, *needles)
    assert not png.exists()


def test_info(capsys):
    code, out, err = run(["info"], capsys)
    assert code == 0, err
    assert f"polydem {polydem.__version__}" in out
    import warp as wp

    assert f"Warp {wp.config.version}" in out and "cpu" in out


def test_settled_region_of_a_regular_packing():
    """The definition of the settled region on a simple cubic stack of unit cubes, 4 layers high."""
    scene = polydem.Scene(gravity=(0, 0, -9.81), name="stack")
    scene.add_material("m", density=1000, law="linear", k=1e6, restitution=0.5, friction=0.0)
    scene.add_shape("cube", polydem.ConvexShape.box(1.0))
    n = 12
    for i in range(n):
        for j in range(n):
            for k in range(4):
                scene.add_body("cube", "m", position=(i, j, k + 0.5))
    state = {"body_position": np.array(scene.body_position), "body_orientation": np.array(scene.body_orientation)}
    contacts = {"body_a": np.zeros(0, int), "body_b": np.zeros(0, int), "volume": np.zeros(0)}
    region = cli.settled_region(scene, state, contacts)
    d = (6.0 / math.pi) ** (1.0 / 3.0)
    assert region["diameter"] == pytest.approx(d)
    # Floor at z = 0 (the lowest vertex), top at the 80th percentile of the centre heights (3.5);
    # the columns whose centres lie 2 d inside the box of the centres, all 4 layers.
    assert region["lower"][2] == pytest.approx(0.0) and region["upper"][2] == pytest.approx(3.5)
    inside = [x for x in range(n) if 2 * d <= x <= n - 1 - 2 * d]
    assert region["bodies"] == len(inside) ** 2 * 4
    width = (n - 1) - 4 * d
    assert region["packing_fraction"] == pytest.approx(len(inside) ** 2 * 4 / (width**2 * 3.5))
    assert region["coordination_number"] == 0.0


if os.environ.get("POLYDEM_TEST_DEVICES", "cpu").split(",")[0] != "cpu":  # the CLI tests need the CPU
    pytestmark = pytest.mark.skip(reason="the command-line tests run on the CPU")


def test_plots_of_a_run(tmp_path):
    pytest.importorskip("matplotlib")
    from polydem.plots import write_plots

    history = {k: [0.0, 1.0, 2.0] for k in ("time", "kinetic", "contact", "gravity", "dissipated", "total")}
    history["contacts"] = [0, 3, 5]
    history["packing_fraction"] = [None, 0.5, 0.55]
    paths = write_plots(history, tmp_path)
    assert [p.name for p in paths] == ["energy.png", "packing.png"]
    for p in paths:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "fewer than two" in write_plots({k: [0.0] for k in history}, tmp_path)
