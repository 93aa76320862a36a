"""The polydem command: outputs, user errors, interruption and resume, validate, render, info (CPU)."""

import glob
import importlib.util
import io
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cli_helpers
import numpy as np
import pytest
from cli_helpers import run

import polydem
from polydem import cli
from polydem.cli import main, parser
from polydem.cli import progress as cli_progress
from polydem.cli.progress import duration
from polydem.cli.report import Report
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

STATE_KEYS = ("steps_done", "body_q", "body_v", "body_w", "body_dissipated", "wall_xi", "wall_turn", "step_count")


def write_scene(folder, text=TINY, name="tiny.toml", replace=()):
    return cli_helpers.write_scene(folder, text, name, replace)


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
    for command in ("run", "validate", "render", "tap", "compress", "anneal", "info"):
        assert command in proc.stdout
    assert "Traceback" not in proc.stderr


def test_every_option_is_described(capsys):
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if hasattr(a, "choices") and isinstance(a.choices, dict))
    assert set(sub.choices) == {"run", "validate", "render", "tap", "compress", "anneal", "info"}
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
        "largest_depth",
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
    # A tetrahedron's corner 3.5% of its volume into the floor is 7 mm deep: half its size (cube root of its volume).
    deepest = summary["largest_depth"]
    assert 0.0 < deepest["final"]["relative"] < 1.0 and deepest["max_over_frames"] > 0.0
    assert "largest depth (of the smaller body's size" in out
    assert set(summary["energy"]["final"]) >= {"kinetic", "contact", "gravity", "dissipated", "total"}
    region = summary["settled_region"]
    assert set(region) >= {"packing_fraction", "coordination_number", "bodies"}
    assert "packing_fraction" in summary["measures"] or summary["measures"]["note"].startswith("no settled region")
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


@pytest.mark.parametrize("precision", ["mixed", "float64"])
def test_run_in_float64_precisions(tmp_path, capsys, precision):
    """Before: --precision float64 was refused (exit 2, "float32 only") and "mixed" was no choice.
    Now the run goes through, the summary says which, the checkpoint holds float64 poses, and a
    resume in another precision is refused naming both."""
    scene = write_scene(tmp_path, replace=[('usd = "tiny.usda"', "usd = false"), ("pictures = [1]", "")])
    base = ["run", scene, "--device", "cpu", "--steps", "150", "--out", tmp_path / "o", "-q"]
    code, _, err = run([*base, "--precision", precision], capsys)
    assert code == 0, err
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["precision"] == precision
    checkpoint = tmp_path / "o" / "checkpoints" / "step_000000150.npz"
    with np.load(checkpoint) as data:
        assert data["body_q"].dtype == np.float64
    other = ["run", scene, "--device", "cpu", "--out", tmp_path / "p", "--resume", checkpoint]
    code, _, err = run([*other, "--precision", "float32"], capsys)
    assert_user_error(code, err, f"simulation.precision differs: checkpoint '{precision}', scene 'float32'")


def test_float32_checkpoint_resumes_with_the_precision_named(tmp_path, capsys):
    """A float32 checkpoint (every run's before "mixed" became the default) resumed with a scene that
    gives no precision is refused with the fix (exit 2); with --precision float32 it resumes."""
    scene = write_scene(tmp_path, replace=[('usd = "tiny.usda"', "usd = false"), ("pictures = [1]", "")])
    assert "precision" not in scene.read_text()
    code, _, err = run(["run", scene, "--device", "cpu", "--steps", "150", "--out", tmp_path / "o", "-q"], capsys)
    assert code == 0, err
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["precision"] == "mixed"
    code, _, err = run(
        ["run", scene, "--device", "cpu", "--steps", "150", "--out", tmp_path / "f", "-q", "--precision", "float32"],
        capsys,
    )
    assert code == 0, err
    checkpoint = tmp_path / "f" / "checkpoints" / "step_000000150.npz"
    resume = ["run", scene, "--device", "cpu", "--steps", "200", "--out", tmp_path / "p", "-q", "--resume", checkpoint]
    code, _, err = run(resume, capsys)
    assert_user_error(
        code,
        err,
        "simulation.precision differs: checkpoint 'float32', scene 'mixed'",
        'add precision = "float32" to the scene\'s [simulation] table',
        "pass --precision float32",
    )
    code, _, err = run([*resume, "--precision", "float32"], capsys)
    assert code == 0, err
    assert json.loads((tmp_path / "p" / "summary.json").read_text())["precision"] == "float32"


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
        (["--precision", "double"], ["--precision", "invalid choice", "'float32', 'mixed', 'float64'"]),
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


def files_of(folder):
    """Every file under ``folder`` with its bytes (to show that a refused resume changed nothing)."""
    return {p.relative_to(folder): p.read_bytes() for p in sorted(Path(folder).rglob("*")) if p.is_file()}


@pytest.fixture
def earlier_run(tmp_path, unbroken):
    """A copy of the unbroken run's output folder (outputs a refused resume must leave alone): (scene, folder)."""
    import shutil

    scene, out_dir = unbroken
    folder = tmp_path / "out"
    shutil.copytree(out_dir, folder)
    return scene, folder


@pytest.mark.parametrize(
    "replace, words",
    [
        (
            [("steps = 400", "steps = 400\ngravity = [0.0, 0.0, -3.0]")],
            ["simulation.gravity differs: checkpoint [0, 0, -9.81], scene [0, 0, -3]"],
        ),
        (
            [("restitution = 0.4", "restitution = 0.9")],
            ["materials.stone.restitution differs: checkpoint 0.4, scene 0.9"],
        ),
        ([("friction = 0.5", "friction = 0.2")], ["materials.stone.friction differs: checkpoint 0.5, scene 0.2"]),
        ([("k = 1.0e8", "k = 2.0e8")], ["materials.stone.k differs: checkpoint 1e+08, scene 2e+08", "simulation.dt"]),
        ([("density = 2500.0", "density = 3000.0")], ["materials.stone.density differs", "simulation.dt differs"]),
        (
            [('law = "hertz"\nk = 1.0e8', 'law = "linear"\nk = 1.0e10')],
            ["materials.stone.law differs: checkpoint 'hertz', scene 'linear'"],
        ),
        ([('dt = "auto"', "dt = 3.0e-5")], ["simulation.dt differs", "scene 3e-05"]),
        (
            [("size = 0.02", "size = 0.019")],
            ["shapes.cube.vertices differ: checkpoint 8 vertices within 0.02 x 0.02 x 0.02 m, scene 8 vertices"],
        ),
        (
            [("size = 0.02", "size = [0.02, 0.02, 0.019]")],
            ["shapes.cube.vertices differ", "0.02 x 0.02 x 0.019 m"],
        ),
        ([('shape = ["cube", "tet"]', 'shape = ["tet", "cube"]')], ["bodies[", "].shape differs", "bodies differ"]),
        (
            [
                (
                    "seed = 1\n",
                    'seed = 1\n\n[[walls]]\ntype = "plane"\npoint = [0, 0, 0]\nnormal = [0, 0, 1]\n'
                    'material = "stone"\n',
                )
            ],
            ["planes differ: checkpoint 0 planes, scene 1"],
        ),
    ],
    ids=["gravity", "restitution", "friction", "k", "density", "law", "dt", "size", "shape", "kinds", "walls"],
)
def test_resume_refuses_other_physics(tmp_path, capsys, earlier_run, replace, words):
    """Before: accepted (exit 0) and run on with the new scene's physics, or refused for a time step
    only. Now: exit code 2 naming what differs, and the earlier outputs stay as they were."""
    _, out_dir = earlier_run
    other = write_scene(tmp_path, name="other.toml", replace=replace)
    before = files_of(out_dir)
    checkpoint = out_dir / "checkpoints" / "step_000000150.npz"
    code, _, err = run(["run", other, "--device", "cpu", "--out", out_dir, "--resume", checkpoint], capsys)
    # The scene is validated before the checkpoint is compared: a linear law under gravity gets its warning
    # (scene.checks.check_loads) on a line of its own above the error; no other scene here warns.
    warnings = [line for line in err.splitlines() if line.startswith("polydem: warning: ")]
    expected = ["law = 'linear' cannot bring a body to rest on a face"] if 'law = "linear"' in other.read_text() else []
    assert len(warnings) == len(expected) and all(w in line for w, line in zip(expected, warnings, strict=True)), err
    err = "".join(line + "\n" for line in err.splitlines() if line not in warnings)
    assert_user_error(
        code,
        err,
        "step_000000150.npz: --resume: the checkpoint was written for other physics",
        *words,
        "resume with the scene the checkpoint was written from",
    )
    assert files_of(out_dir) == before


def _edit(path, out, **changes):
    with np.load(path) as f:
        data = dict(f)
    for key, change in changes.items():
        if change is None:
            data.pop(key)
        else:
            data[key] = change(data[key].copy())
    np.savez(out, **data)


def _entry(index, value):
    def change(a):
        a[index] = value
        return a

    return change


def _changed(text, old, new):
    assert old in text
    return text.replace(old, new)


def _run_record(change):
    def edit(text):
        rec = json.loads(str(text))
        change(rec)
        return np.array(json.dumps(rec))

    return edit


EDITED = {
    "zero quaternion": ({"body_q": _entry((6, slice(3, 7)), 0.0)}, ["orientation of body 6", "has length 0, not 1"]),
    "scaled quaternion": ({"body_q": lambda q: q * np.float32(3.0)}, ["orientation of body 0", "has length 3"]),
    "rows missing": ({"body_q": lambda q: q[:-2]}, ["body_q has shape (15, 7), expected (17, 7)"]),
    "velocity rows missing": ({"body_v": lambda v: v[:-2]}, ["body_v has shape (15, 3), expected (17, 3)"]),
    "wrong dtype": ({"body_w": lambda w: w.astype(complex)}, ["body_w holds complex128 values"]),
    "NaN": ({"body_q": _entry((8, 1), np.nan)}, ["body_q[8, 1] is nan", "must be finite"]),
    "inf": ({"body_v": _entry((8, 1), np.inf)}, ["body_v[8, 1] is inf"]),
    "negative steps": ({"steps_done": lambda s: np.array(-150)}, ["steps_done = -150 is negative"]),
    "NaN time": ({"time": lambda t: np.array(np.nan)}, ["time = nan s is not a finite time"]),
    "fake pair key": ({"pair_key": _entry(-1, 17 * 17 + 3)}, ["is not a pair of bodies a < b < 17"]),
    "repeated pair key": ({"pair_key": lambda k: np.r_[k[:1], k[:-1]]}, ["repeats"]),
    "pair keys out of order": ({"pair_key": lambda k: k[::-1].copy()}, ["smaller than the one before"]),
    "physics record edited": (
        {"physics_json": lambda t: np.array(_changed(str(t), 'stone.friction":0.5', 'stone.friction":0.2'))},
        ["does not match its physics_fingerprint"],
    ),
    "run record edited": (
        {"run_json": _run_record(lambda rec: rec["history"]["kinetic"].pop())},
        ["history.kinetic of its run record is not a list of"],
    ),
    "run record ahead of the state": (
        {"run_json": _run_record(lambda rec: rec["history"]["time"].__setitem__(-1, 1.0))},
        ["its run record has a frame at t = 1 s, after the checkpoint's"],
    ),
}


@pytest.mark.parametrize("case", EDITED, ids=list(EDITED))
def test_resume_refuses_edited_checkpoints(tmp_path, capsys, earlier_run, case):
    """Before: accepted and run on (zero or scaled quaternions, rows of velocities missing, negative
    step counts, fake pair keys), or a traceback (NaN time). Now: exit code 2 and one line naming
    the entry; the earlier outputs stay as they were."""
    scene, out_dir = earlier_run
    changes, words = EDITED[case]
    bad = tmp_path / "edited.npz"
    with np.load(out_dir / "checkpoints" / "step_000000150.npz") as data:
        assert len(data["pair_key"]) > 2  # the keys to edit
    _edit(out_dir / "checkpoints" / "step_000000150.npz", bad, **changes)
    before = files_of(out_dir)
    code, _, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "--resume", bad], capsys)
    assert_user_error(code, err, "edited.npz: --resume: ", *words)
    assert files_of(out_dir) == before
    if not case.startswith("run record"):  # render reads the same checks (the run record is the summary's)
        png = tmp_path / "edited.png"
        code, _, err = run(["render", bad, "--scene", scene, "--device", "cpu", "--out", png], capsys)
        assert_user_error(code, err, "edited.npz: ", *words)
        assert not png.exists()


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda raw: raw[: len(raw) // 2], ["not a polydem checkpoint (BadZipFile"]),
        (lambda raw: raw[:-10], ["not a polydem checkpoint"]),
        (lambda raw: b"hello", ["not a polydem checkpoint (neither an .npz archive nor an .npy array)"]),
    ],
    ids=["truncated", "tail cut", "text"],
)
def test_resume_refuses_files_that_are_not_checkpoints(tmp_path, capsys, earlier_run, make, words):
    scene, out_dir = earlier_run
    bad = tmp_path / "bad.npz"
    bad.write_bytes(make((out_dir / "checkpoints" / "final.npz").read_bytes()))
    before = files_of(out_dir)
    code, _, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "--resume", bad], capsys)
    assert_user_error(code, err, "bad.npz: --resume: ", *words, "give a checkpoint written by polydem")
    assert files_of(out_dir) == before


def test_resume_refuses_another_frame_rate(tmp_path, capsys, earlier_run):
    scene, out_dir = earlier_run
    before = files_of(out_dir)
    checkpoint = out_dir / "checkpoints" / "step_000000150.npz"
    code, _, err = run(
        ["run", scene, "--device", "cpu", "--out", out_dir, "--fps", "250", "--resume", checkpoint], capsys
    )
    assert_user_error(code, err, "recorded its frames at 500.0 per simulated second", "give --fps 500.0")
    assert files_of(out_dir) == before


def test_old_checkpoint_resumes_with_a_warning(tmp_path, capsys):
    """A checkpoint of the previous format (no physics record, no run record) still resumes, with a
    warning on stderr and a note in the summary that it covers the resumed part only. That format
    held float32 arrays only, so the run it comes from is pinned to float32."""
    scene = write_scene(tmp_path, replace=[("steps = 400", 'steps = 400\nprecision = "float32"')])
    out_dir = tmp_path / "unbroken"
    assert main(["run", str(scene), "--device", "cpu", "--out", str(out_dir), "--quiet"]) == 0
    capsys.readouterr()
    old = tmp_path / "old.npz"
    with np.load(out_dir / "checkpoints" / "step_000000300.npz") as f:
        data = {k: v for k, v in f.items() if not k.startswith("physics_") and k != "run_json"}
    data["format"] = np.array("polydem-checkpoint-2")
    np.savez(old, **data)
    code, _, err = run(["run", scene, "--device", "cpu", "--out", tmp_path / "o", "-q", "--resume", old], capsys)
    assert code == 0, err
    assert "polydem: warning: " in err and "cannot be checked to come from this scene" in err
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["history_from_step"] == 300
    assert any("no record of the run before step 300" in note for note in summary["notes"])
    assert_same_state(out_dir / "checkpoints" / "final.npz", tmp_path / "o" / "checkpoints" / "final.npz")


def test_resumed_summary_covers_the_whole_run(tmp_path, capsys, unbroken):
    """Before: the summary of a resumed run held only the resumed part (its frames, the energy at the
    resume as the initial one, its wall time and files). Now, after runs to step 200, 300 and the
    end, it equals the unbroken run's over the whole run and lists every part and file."""
    scene, unbroken_dir = unbroken
    out_dir = tmp_path / "out"
    base = ["run", scene, "--device", "cpu", "--out", out_dir, "-q"]
    code, _, err = run([*base, "--steps", "200"], capsys)
    assert code == 0, err
    code, _, err = run([*base, "--steps", "300", "--resume", out_dir / "checkpoints" / "final.npz"], capsys)
    assert code == 0, err
    code, out, err = run([*base, "--resume", out_dir / "checkpoints" / "final.npz"], capsys)
    assert code == 0, err
    # The closing lines name this part's files only (the earlier parts' in a line of their own, if any).
    assert "1 picture" not in out.split("earlier parts")[0]

    whole = json.loads((unbroken_dir / "summary.json").read_text())
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["frames"] == whole["frames"] == expected_frames(STEPS, whole["dt"], 500.0)
    assert set(summary["history"]) == set(whole["history"])
    for key, values in whole["history"].items():
        assert len(summary["history"][key]) == len(values), key
        np.testing.assert_allclose(
            np.array(summary["history"][key], dtype=float), np.array(values, dtype=float), rtol=1e-9, err_msg=key
        )
    assert summary["history"]["time"][0] == 0.0
    assert summary["contacts"] == pytest.approx(whole["contacts"])
    assert summary["largest_overlap"]["max_over_frames"] == pytest.approx(whole["largest_overlap"]["max_over_frames"])
    assert summary["largest_depth"]["max_over_frames"] == pytest.approx(whole["largest_depth"]["max_over_frames"])
    assert summary["energy"]["initial"] == pytest.approx(whole["energy"]["initial"])
    assert summary["energy"]["final"] == pytest.approx(whole["energy"]["final"])
    assert summary["energy"]["at_resume"]["total"] != pytest.approx(whole["energy"]["initial"]["total"], rel=1e-9)
    assert summary["steps"] == STEPS and summary["steps_this_run"] == STEPS - 300
    assert summary["resumed_at_step"] == 300 and summary["history_from_step"] == 0
    assert summary["wall_time"] > summary["wall_time_this_run"] > 0.0
    # Which part wrote which steps and frames, into which USD file.
    parts = summary["parts"]
    assert [(p["from_step"], p["to_step"]) for p in parts] == [(0, 200), (200, 300), (300, STEPS)]
    assert [p["usd"] for p in parts] == ["tiny.usda", "tiny.from_step_200.usda", "tiny.from_step_300.usda"]
    assert [p["resumed_from"] for p in parts] == [None, "checkpoints/final.npz", "checkpoints/final.npz"]
    from polydem.usd import read_time_codes

    codes = []
    for p in parts:
        file_codes = read_time_codes(out_dir / p["usd"]).tolist()
        assert p["usd_frames"] == len(file_codes) and p["usd_time_codes"] == [file_codes[0], file_codes[-1]]
        codes += file_codes
    assert sorted(set(codes)) == list(range(whole["frames"]))
    assert sum(p["wall_time"] for p in parts) == pytest.approx(summary["wall_time"])
    # Files of the earlier parts are kept in the lists.
    assert summary["outputs"]["pictures"] == ["pictures/frame_000001.png"]
    assert summary["outputs"]["checkpoints"] == [
        "checkpoints/step_000000150.npz",
        "checkpoints/final.npz",
        "checkpoints/step_000000300.npz",
    ]
    assert summary["outputs"]["usd"] == "tiny.from_step_300.usda"


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
    # The summary continues the unbroken run's record up to step 150, whose files lie in its folder.
    whole = json.loads((unbroken_dir / "summary.json").read_text())
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["history"]["time"] == pytest.approx(whole["history"]["time"], rel=1e-9)
    assert summary["history"]["total"] == pytest.approx(whole["history"]["total"], rel=1e-9)
    first = (unbroken_dir / "pictures" / "frame_000001.png").resolve()
    assert summary["outputs"]["pictures"] == [str(first)]
    assert summary["parts"][0]["folder"] == str(unbroken_dir.resolve())


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
            # raise_signal delivers it to this thread before it returns (os.kill may reach another
            # thread of the process first); the handler only sets a flag: this step still runs.
            signal.raise_signal(signal.SIGINT)
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


def test_run_prints_a_scene_warning_as_one_line(tmp_path, capsys):
    """The same moderate overlap in a run: one "polydem: warning:" line, not Python's warning format."""
    body = '[[bodies]]\nshape = "cube"\nmaterial = "stone"\nposition = [0.0, 0.0, 0.007]\n\n[[walls]]'
    path = write_scene(tmp_path, replace=[("[[walls]]", body)])
    code, out, err = run(["run", path, "--device", "cpu", "--steps", "2", "--out", tmp_path / "o", "-q"], capsys)
    assert code == 0, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"polydem: warning: {path}: 1 initial overlaps "), err
    assert "SceneWarning" not in err


def test_validate_and_run_print_the_tunnelling_warning(tmp_path, capsys):
    """Emitted grains at 300 m/s into a box of 1 cm walls: one warning line in validate and in run."""
    path = write_scene(tmp_path, replace=[("velocity = [0.0, 0.0, -1.5]", "velocity = [0.0, 0.0, -300.0]")])
    for args in (["validate", path], ["run", path, "--device", "cpu", "--steps", "2", "--out", tmp_path / "o", "-q"]):
        code, out, err = run(args, capsys)
        assert code == 0, err
        lines = [line for line in err.splitlines() if "may pass through" in line]
        assert len(lines) == 1 and lines[0].startswith(f"polydem: warning: {path}: body "), err
        assert " starts at 300 m/s, above the " in lines[0] and "Warning" not in err


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
    # The frame count follows from the auto step (400 steps at 500 frames/s): it was 8 (0 to 7) before the
    # step came from each shape's largest face (0.64x shorter for the tetrahedra: 5 frames, 0 to 4).
    summary = json.loads((out_dir / "summary.json").read_text())
    frames = expected_frames(STEPS, summary["dt"], 500.0)
    assert summary["outputs"]["usd_frames"] == frames > 1
    cases = [
        (["render", scene, "--out", tmp_path / "pic.jpg"], ["pic.jpg", "--out", ".png"]),
        (["render", scene, "--out", png, "--frame", "3"], ["tiny.toml", "--frame", "frame 0 only"]),
        (
            ["render", out_dir / "tiny.usda", "--scene", scene, "--frame", "99", "--out", png],
            ["no frame 99", f"{frames} frames, 0 to {frames - 1}"],
        ),
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
    # what a run under mpiexec would have: the test extra installs mpi4py (nccl4py where a GPU machine has it)
    assert "several processes: mpi4py present; nccl4py " in out


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


def test_measures_of_the_settled_region_of_a_regular_packing():
    """The summary's measures in the same region of the cubic stack: the cubes fill it, so the grains clipped
    by it fill it exactly (the centre count above gives another number); no cube overlaps a neighbour, so
    every grain is a rattler and no coordination is left. A region without a box gives a note."""
    from polydem.cli.report import Report

    scene = polydem.Scene(gravity=(0, 0, -9.81), name="stack")
    scene.add_material("m", density=1000, law="linear", k=1e6, restitution=0.5, friction=0.0)
    scene.add_shape("cube", polydem.ConvexShape.box(1.0))
    for i in range(12):
        for j in range(12):
            for k in range(4):
                scene.add_body("cube", "m", position=(i, j, k + 0.5))
    sim = polydem.Simulation(scene, device="cpu")
    contacts = sim.contacts()
    region = cli.settled_region(scene, sim.state(), contacts)
    region["at_rest"] = True
    m = Report._measures(scene, sim, region, contacts)
    assert region["packing_fraction"] != pytest.approx(1.0)
    assert m["packing_fraction"] == pytest.approx(1.0, abs=1e-12)
    assert m["coordination"]["z"] is None and m["coordination"]["rattler_fraction"] == 1.0
    assert m["at_rest"] is True and sum(m["contact_features"].values()) == 0
    empty = Report._measures(scene, sim, {"bodies": 0, "note": "too narrow"}, contacts)
    assert empty == {"note": "no settled region to measure: too narrow"}


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


# ---------------------------------------------------------------------- the outputs a run names


def written_lines(out):
    """The closing lines after 'written to FOLDER/:' (the files, one kind per line)."""
    lines = out.splitlines()
    k = next(i for i, line in enumerate(lines) if line.strip().startswith("written to "))
    files = []
    for line in lines[k + 1 :]:
        if not line.startswith("    "):
            break
        files.append(line.strip())
    return lines[k].strip(), files


def test_closing_lines_name_every_file_and_a_picture_of_the_end(tmp_path, capsys):
    """No pictures key: pictures/last.png; the closing lines name each file the summary lists."""
    scene = write_scene(tmp_path, replace=[("pictures = [1]\n", "")])
    out_dir = tmp_path / "out"
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "-q"], capsys)
    assert code == 0, err
    assert (out_dir / "pictures" / "last.png").read_bytes()[:8] == PNG_SIGNATURE
    head, files = written_lines(out)
    assert head == f"written to {out_dir}{os.sep}:"
    text = "\n".join(files)
    summary = json.loads((out_dir / "summary.json").read_text())
    o = summary["outputs"]
    named = [o["usd"], o["summary"], *o["pictures"], *o["checkpoints"]]
    if importlib.util.find_spec("matplotlib") is not None:
        assert o["plots"] == ["energy.png", "packing.png"]
        named += o["plots"]
    assert "pictures/last.png" in named and "checkpoints/final.npz" in named
    for name in named:
        assert name in text, name
        assert (out_dir / name).is_file() and (out_dir / name).stat().st_size > 0
    on_disk = sorted(str(p.relative_to(out_dir)) for p in out_dir.rglob("*") if p.is_file())
    assert on_disk == sorted(named)  # nothing written that the closing lines do not name
    # The frame count follows from the auto step (it was 8 before the step came from each shape's largest face).
    frames = expected_frames(STEPS, summary["dt"], 500.0)
    assert o["usd_frames"] == frames > 1
    assert f"USD animation, {frames} frames" in text and "picture of the final state" in text


def test_pictures_true_is_the_last_frame(tmp_path, capsys):
    scene = write_scene(tmp_path, replace=[("pictures = [1]", "pictures = true")])
    code, out, err = run(["run", scene, "--device", "cpu", "--steps", "50", "--out", tmp_path / "o", "-q"], capsys)
    assert code == 0, err
    assert [p.name for p in (tmp_path / "o" / "pictures").iterdir()] == ["last.png"]


@pytest.mark.parametrize("setting", ["pictures = false", "pictures = []"])
def test_no_pictures_when_the_scene_says_so(tmp_path, capsys, setting):
    scene = write_scene(tmp_path, replace=[("pictures = [1]", setting)])
    code, out, err = run(["run", scene, "--device", "cpu", "--steps", "50", "--out", tmp_path / "o", "-q"], capsys)
    assert code == 0, err
    assert not (tmp_path / "o" / "pictures").exists()
    assert not any("picture" in line for line in written_lines(out)[1])


def test_without_matplotlib_one_note_line(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib raises ImportError
    scene = write_scene(tmp_path)
    code, out, err = run(["run", scene, "--device", "cpu", "--steps", "100", "--out", tmp_path / "o", "-q"], capsys)
    assert code == 0, err
    assert "Traceback" not in err and err == ""
    out = out.replace(str(tmp_path), "TMP")  # the test's name is in the folder's
    notes = [line for line in out.splitlines() if "matplotlib" in line]
    assert notes == ['  note: no plots: matplotlib is not installed (pip install "polydem[plot]")']
    assert not (tmp_path / "o" / "energy.png").exists() and "plots" not in "\n".join(written_lines(out)[1])


# ---------------------------------------------------------------------- progress: the time left


def test_progress_says_how_long_it_will_take(monkeypatch):
    """The time left follows the recent rate (a pour slows down as its contacts grow)."""
    clock = {"t": 100.0}
    monkeypatch.setattr(cli_progress.time, "perf_counter", lambda: clock["t"])

    class Sim:
        steps_done = 0
        time = 0.0

        def energy(self):
            return {"kinetic": 1.0}

        def contacts(self):
            return {"volume": np.zeros(3)}

    sim, stream = Sim(), io.StringIO()
    progress = cli_progress.Progress(stream, 0, 10000, 1e-4, enabled=True)
    # 1000 steps per second, then 100 per second from step 5000 on.
    for steps, t in [(100, 100.5), (500, 100.9), (1000, 101.4), (2000, 102.4), (5000, 105.4), (5500, 110.4)]:
        clock["t"], sim.steps_done, sim.time = t, steps, steps * 1e-4
        progress.update(sim)
    lines = stream.getvalue().splitlines()
    assert "left" not in lines[0]  # 5%: not yet estimated
    assert lines[1].split("steps/s")[1].split("left")[0].strip() == "9.0 s"  # 10%: 9000 steps at 1000/s
    last = lines[-1]
    assert "55.0%" in last
    assert "45 s left" in last  # 4500 steps at the recent 100 steps/s, not at the mean rate (8 s)
    clock["t"], sim.steps_done = 160.0, 10000
    progress.update(sim)
    assert "took 1 min 00 s" in stream.getvalue().splitlines()[-1]
    assert duration(3.14) == "3.1 s" and duration(75) == "1 min 15 s" and duration(7322) == "2 h 02 min"


def test_progress_lines_off_a_terminal_also_follow_the_clock(monkeypatch):
    clock = {"t": 0.0}
    monkeypatch.setattr(cli_progress.time, "perf_counter", lambda: clock["t"])

    class Sim:
        time = 0.0

        def energy(self):
            return {"kinetic": 1.0}

        def contacts(self):
            return {"volume": np.zeros(0)}

    sim, stream = Sim(), io.StringIO()
    progress = cli_progress.Progress(stream, 0, 10**6, 1e-4, enabled=True)
    for k in range(1, 200):  # a slow run: 100 steps per second, far from the first 5% mark
        clock["t"], sim.steps_done = float(k), 100 * k
        progress.update(sim)
    lines = stream.getvalue().splitlines()
    assert 3 <= len(lines) <= 5  # after 10 s, then a minute apart
    assert "left" in lines[0] and "2 h 4" in lines[0]


def test_progress_on_a_terminal_costs_no_diagnostics_pass(monkeypatch):
    """On a terminal the line is redrawn every quarter second: it shows the numbers of the last
    frame recorded instead of computing the contacts and energies again."""
    clock = {"t": 0.0}
    monkeypatch.setattr(cli_progress.time, "perf_counter", lambda: clock["t"])

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    class Sim:
        steps_done = 0
        time = 0.0
        passes = 0

        def energy(self):
            Sim.passes += 1
            return {"kinetic": 1.0}

        def contacts(self):
            Sim.passes += 1
            return {"volume": np.zeros(2)}

    sim, stream = Sim(), Terminal()
    progress = cli_progress.Progress(stream, 0, 10000, 1e-4, enabled=True)
    progress.note(0, 7, 2.5)  # frame 0
    for k in range(1, 100):
        clock["t"], sim.steps_done = 0.5 * k, 100 * k
        progress.update(sim)
    assert Sim.passes == 0 and stream.getvalue().count("\r") == 99
    assert "7 contacts  kinetic 2.500e+00 J" in stream.getvalue().split("\r")[-1]


# ---------------------------------------------------------------------- outputs stay inside --out


@pytest.mark.parametrize(
    "replace, key, needles",
    [
        ("summary = '{abs}'", "output.summary", ["is an absolute path", "relative to it", "summary = 'summary.json'"]),
        ("usd = '../../x.usda'", "output.usd", ["leads out of the output folder", "--out DIR"]),
        ("usd = 'a/../../x.usda'", "output.usd", ["leads out of the output folder"]),
        ("usd = '{abs}.usda'", "output.usd", ["is an absolute path"]),
        ("checkpoint = { steps = 150, path = '../cp' }", "output.checkpoint.path", ["leads out of the output folder"]),
        ("checkpoint = { steps = 150, path = '{abs}' }", "output.checkpoint.path", ["is an absolute path"]),
    ],
)
def test_scene_outputs_stay_inside_the_output_folder(tmp_path, capsys, replace, key, needles):
    outside = tmp_path / "outside"
    outside.write_text("the user's file")
    text = TINY.replace('usd = "tiny.usda"\n', "").replace("checkpoint = { steps = 150 }\n", "")
    scene = write_scene(tmp_path, text.replace("[output]", "[output]\n" + replace.replace("{abs}", str(outside))))
    out_dir = tmp_path / "a" / "b"
    code, _, err = run(["run", scene, "--device", "cpu", "--out", out_dir], capsys)
    assert_user_error(code, err, "tiny.toml", key, *needles)
    code, _, err = run(["validate", scene], capsys)
    assert_user_error(code, err, "tiny.toml", key, *needles)
    assert outside.read_text() == "the user's file"
    assert not (tmp_path / "x.usda").exists() and not (tmp_path / "a" / "cp").exists()
    assert not out_dir.exists()


def test_paths_inside_the_output_folder_are_fine(tmp_path, capsys):
    scene = write_scene(
        tmp_path,
        replace=[
            ('usd = "tiny.usda"', 'usd = "anim/./tiny.usda"\nsummary = "x/../s.json"'),
            ("checkpoint = { steps = 150 }", 'checkpoint = { steps = 150, path = "state" }'),
        ],
    )
    out_dir = tmp_path / "o"
    code, _, err = run(["run", scene, "--device", "cpu", "--steps", "50", "--out", out_dir, "-q"], capsys)
    assert code == 0, err
    assert (out_dir / "anim" / "tiny.usda").is_file() and (out_dir / "s.json").is_file()
    assert (out_dir / "state" / "final.npz").is_file()


# ---------------------------------------------------------------------- outputs that cannot be written


def no_temporary_files(folder):
    return [str(p) for p in Path(folder).rglob("*") if ".tmp" in p.name]


LONG = "n" * 300


@pytest.mark.parametrize(
    "replace, block, key, needles",
    [
        ([('usd = "tiny.usda"', f'usd = "{LONG}.usda"')], None, "output.usd", ["File name too long", "shorter name"]),
        ([("[output]", f'[output]\nsummary = "{LONG}.json"')], None, "output.summary", ["File name too long"]),
        (
            [("checkpoint = { steps = 150 }", f'checkpoint = {{ steps = 150, path = "{LONG}" }}')],
            None,
            "output.checkpoint.path",
            ["File name too long"],
        ),
        ([], "checkpoints", "output.checkpoint.path", ["a file is in the way of a folder"]),
        ([], "pictures", "output.pictures", ["a file is in the way of a folder"]),
        ([], "summary.json/", "output.summary", ["a folder is in the way of the file"]),
    ],
)
def test_outputs_that_cannot_be_written_stop_before_the_run(tmp_path, capsys, replace, block, key, needles):
    scene = write_scene(tmp_path, replace=replace)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    if block is not None and block.endswith("/"):
        (out_dir / block).mkdir()
    elif block is not None:
        (out_dir / block).write_text("in the way")
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir], capsys)
    assert_user_error(code, err, key, *needles)
    assert "written to" not in out and "steps/s" not in err  # it did not start
    assert not list(out_dir.rglob("*.usda")) and not (out_dir / "summary.json").is_file()
    assert no_temporary_files(out_dir) == []


@pytest.mark.parametrize("name", ["a_file/sub", "n" * 300])
def test_output_folder_that_cannot_be_made(tmp_path, capsys, name):
    (tmp_path / "a_file").write_text("in the way")
    code, _, err = run(["run", write_scene(tmp_path), "--device", "cpu", "--out", tmp_path / name], capsys)
    assert_user_error(code, err, "--out", "cannot create the output folder")


def test_an_output_failing_during_the_run_keeps_the_others(tmp_path, capsys, monkeypatch):
    """The checkpoint folder turns into a file during the run: exit code 1, one error line, the
    other outputs written, and the checkpoints not named as written."""
    scene = write_scene(tmp_path, replace=[("pictures = [1]", "")])
    out_dir = tmp_path / "out"
    original = Simulation.step
    count = {"n": 0}

    def step(self, n=1):
        count["n"] += 1
        if count["n"] == 2:
            if (out_dir / "checkpoints").is_dir():
                (out_dir / "checkpoints").rmdir()
            (out_dir / "checkpoints").write_text("in the way")
        return original(self, n)

    monkeypatch.setattr(Simulation, "step", step)
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "-q"], capsys)
    assert code == 1
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("polydem: error: cannot write the checkpoint checkpoints/step_")
    assert "a file is in the way of a folder" in lines[0]
    _, files = written_lines(out)
    assert not any(".npz" in f for f in files)
    assert "not written: cannot write the checkpoint checkpoints/interrupted.npz" in out
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["interrupted"] is True and "could not be written" in summary["reason"]
    assert summary["outputs"]["checkpoints"] == [] and len(summary["not_written"]) == 2
    from polydem.usd import read_time_codes

    assert len(read_time_codes(out_dir / "tiny.usda")) == summary["outputs"]["usd_frames"] > 0
    assert (out_dir / "pictures" / "last.png").is_file()
    assert no_temporary_files(out_dir) == []


def test_a_summary_that_cannot_be_written_after_the_run(tmp_path, capsys, monkeypatch):
    """The summary's place is taken by a folder once the run is over: exit code 1, the rest kept."""
    scene = write_scene(tmp_path, replace=[("pictures = [1]", "")])
    out_dir = tmp_path / "out"
    original = Report.summary

    def summary(self, *args):
        (out_dir / "summary.json").mkdir()
        return original(self, *args)

    monkeypatch.setattr(Report, "summary", summary)
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "-q"], capsys)
    assert code == 1
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "cannot write the summary summary.json" in lines[0] and "Traceback" not in err
    _, files = written_lines(out)
    assert not any(f.startswith("summary.json") for f in files)
    assert any(f.startswith("checkpoints/") for f in files) and (out_dir / "checkpoints" / "final.npz").is_file()
    assert (out_dir / "tiny.usda").is_file() and no_temporary_files(out_dir) == []


def test_render_picture_that_cannot_be_written(tmp_path, capsys, unbroken):
    scene, _ = unbroken
    (tmp_path / "a_file").write_text("in the way")
    for png in (tmp_path / "a_file" / "x.png", tmp_path / f"{'n' * 300}.png"):
        code, out, err = run(["render", scene, "--out", png, "--width", "16", "--height", "12"], capsys)
        assert_user_error(code, err, "--out", "cannot write the picture")
        assert "wrote" not in out
    assert no_temporary_files(tmp_path) == []


# ---------------------------------------------------------------------- render finds the scene


def test_render_finds_the_scene_of_a_usd_file(tmp_path, capsys):
    folder = tmp_path / "scenes"
    folder.mkdir()
    scene = write_scene(folder)
    out_dir = tmp_path / "out"
    code, _, err = run(["run", scene, "--device", "cpu", "--steps", "60", "--out", out_dir, "-q"], capsys)
    assert code == 0, err
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["scene_file"] == str(scene.resolve()) and summary["default_scene"] is False
    from polydem.usd import read_metadata

    assert read_metadata(out_dir / "tiny.usda")["scene_file"] == str(scene.resolve())
    png = tmp_path / "x.png"
    size = ["--width", "32", "--height", "24", "--device", "cpu"]
    code, out, err = run(["render", out_dir / "tiny.usda", "--out", png, *size], capsys)
    assert code == 0, err
    assert out.startswith(f"wrote {png} (32 x 24)") and "17 bodies" in out
    assert png.read_bytes()[:8] == PNG_SIGNATURE
    # The scene file is gone: say so, and how to go on.
    scene.rename(tmp_path / "elsewhere.toml")
    code, _, err = run(["render", out_dir / "tiny.usda", "--out", tmp_path / "y.png", *size], capsys)
    assert_user_error(code, err, "tiny.usda", str(scene.resolve()), "is gone", "--scene SCENE")
    code, _, err = run(
        ["render", out_dir / "tiny.usda", "--scene", tmp_path / "elsewhere.toml", "--out", tmp_path / "y.png", *size],
        capsys,
    )
    assert code == 0, err


def test_render_finds_the_default_scene_of_a_usd_file(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, out, err = run(["run", "--device", "cpu", "--steps", "2", "--out", "o", "-q"], capsys)
    assert code == 0, err
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["default_scene"] is True and summary["scene_file"] is None
    from polydem.usd import read_metadata

    assert read_metadata(tmp_path / "o" / "default.usd")["default_scene"] is True
    code, out, err = run(["render", "o/default.usd", "--out", "x.png", "--width", "32", "--height", "24"], capsys)
    assert code == 0, err
    assert "305 bodies" in out and (tmp_path / "x.png").read_bytes()[:8] == PNG_SIGNATURE


@pytest.mark.parametrize("elevation", ["90", "-90"])
def test_render_from_straight_above_and_below(tmp_path, capsys, unbroken, elevation):
    scene, _ = unbroken
    png = tmp_path / "view.png"
    code, out, err = run(
        ["render", scene, "--out", png, "--width", "32", "--height", "24", "--elevation", elevation], capsys
    )
    assert code == 0, err
    assert png.read_bytes()[:8] == PNG_SIGNATURE


@pytest.mark.parametrize("value", ["91", "-90.5", "nan", "up"])
def test_render_elevation_out_of_range(tmp_path, capsys, unbroken, value):
    scene, _ = unbroken
    code, _, err = run(["render", scene, "--out", tmp_path / "v.png", f"--elevation={value}"], capsys)
    assert_user_error(code, err, "--elevation", "-90", "90")


# ---------------------------------------------------------------------- the README's example


def test_readme_cube_drop_example_includes_the_landing():
    """The README's cube_drop command runs long enough for the cube to land and come to rest."""
    import re

    readme = (REPO / "README.md").read_text()
    m = re.search(r"polydem run scenes/cube_drop\.toml [^`]*--duration ([0-9.]+)", readme)
    assert m, "the README gives no cube_drop example with --duration"
    duration = float(m.group(1))
    assert f"--duration {m.group(1)}" in parser.RUN_EPILOG  # polydem run --help gives the same example
    scene = polydem.Scene.from_toml(REPO / "scenes" / "cube_drop.toml")
    g = -scene.gravity[2]
    drop = scene.body_vertices(0)[:, 2].min() - scene.planes[0].point[2]
    e = scene.materials["steel"].restitution
    landing = math.sqrt(2.0 * drop / g)
    # Bounces: each e times the speed of the last; the flights add up to 2 v e / (g (1 - e)).
    resting = landing + 2.0 * g * landing * e / (g * (1.0 - e))
    assert duration > resting, (duration, landing, resting)


# ---------------------------------------------------------------------- Ctrl-C and SIGTERM (real processes)

LONG_TINY = TINY.replace("steps = 400", "steps = 1000000").replace("checkpoint = { steps = 150 }\n", "")
"""Minutes of steps: a signal that is swallowed shows as a run that goes on (finish() times out)."""

RUN_TINY = LONG_TINY.replace("steps = 1000000", "steps = 20000")
"""A progress line every 1000 steps; ignoring the signal, it would end with exit code 0."""


def spawn(args, cwd, importtime=False):
    cmd = [sys.executable, *(["-X", "importtime"] if importtime else []), "-m", "polydem", *map(str, args)]
    return subprocess.Popen(cmd, cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def wait_for(proc, stream, marker, timeout=300.0):
    """Read ``stream`` of ``proc`` until a line containing ``marker``, or, for ``-X importtime``
    output, naming a module that starts with ``marker[7:]`` when ``marker`` starts with "module:"."""
    t0 = time.monotonic()
    lines = []
    while time.monotonic() - t0 < timeout:
        line = stream.readline()
        if not line:
            break
        lines.append(line)
        if marker.startswith("module:"):
            if line.startswith("import time:") and line.split("|")[-1].strip().startswith(marker[7:]):
                return
        elif marker in line:
            return
    proc.kill()
    proc.communicate()
    raise AssertionError(f"no line with {marker!r} came: {''.join(lines[-20:])}")


def finish(proc, timeout=120.0):
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"the command went on after the signal: {err[-2000:]}") from None
    err = "\n".join(line for line in err.splitlines() if not line.startswith("import time:"))
    return out, err


@pytest.mark.parametrize(
    "marker",
    [
        "module:polydem.signals",  # the handlers are in, polydem.cli is not imported yet
        "module:trimesh.",  # inside trimesh's import, which catches BaseException around its own imports
        "module:warp._src",  # inside Warp's import
    ],
)
def test_ctrl_c_while_the_command_starts(tmp_path, marker):
    """Ctrl-C while modules import: one line, exit code 130, nothing written, and the run does not
    go on (the scene would take many minutes)."""
    scene = write_scene(tmp_path, LONG_TINY)
    proc = spawn(["run", scene, "--device", "cpu", "--out", tmp_path / "o"], tmp_path, importtime=True)
    wait_for(proc, proc.stderr, marker)
    proc.send_signal(signal.SIGINT)
    out, err = finish(proc)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err
    assert err.strip().splitlines() == ["polydem: stopped by Ctrl-C; nothing was written"]
    assert not (tmp_path / "o" / "summary.json").exists()


def test_signal_after_the_start_but_before_the_steps(tmp_path):
    """SIGTERM once the header is out (the model built, kernels loading): it stops at once (143)."""
    scene = write_scene(tmp_path, LONG_TINY)
    proc = spawn(["run", scene, "--device", "cpu", "--out", tmp_path / "o", "-q"], tmp_path)
    wait_for(proc, proc.stdout, "output in")
    proc.send_signal(signal.SIGTERM)
    out, err = finish(proc)
    assert proc.returncode == 143, err
    assert "Traceback" not in err
    # Either still starting (nothing written) or already stepping (outputs written, run interrupted).
    if "nothing was written" in err:
        assert err.strip().splitlines() == ["polydem: stopped by SIGTERM; nothing was written"]
    else:
        assert json.loads((tmp_path / "o" / "summary.json").read_text())["interrupted"] is True


@pytest.mark.parametrize("sig, code, word", [(signal.SIGTERM, 143, "SIGTERM"), (signal.SIGINT, 130, "Ctrl-C")])
def test_signal_during_the_run_keeps_every_output(tmp_path, sig, code, word):
    """SIGTERM (a batch scheduler) is Ctrl-C: the USD file with its frames, the summary and
    interrupted.npz are written, and the command says how to resume."""
    scene = write_scene(tmp_path, RUN_TINY)
    out_dir = tmp_path / "o"
    proc = spawn(["run", scene, "--device", "cpu", "--out", out_dir], tmp_path)
    wait_for(proc, proc.stderr, "steps/s")  # the first progress line: the run is stepping
    proc.send_signal(sig)
    out, err = finish(proc)
    assert proc.returncode == code, err
    assert "Traceback" not in err
    assert f"polydem: {word}: stopping after the steps under way" in err
    assert "interrupted:" in out and "--resume" in err
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["interrupted"] is True and word in summary["reason"]
    assert 0 < summary["steps"] < 20000
    from polydem.usd import read_time_codes

    frames = read_time_codes(out_dir / "tiny.usda")
    assert len(frames) == summary["outputs"]["usd_frames"] == expected_frames(summary["steps"], summary["dt"], 500.0)
    with np.load(out_dir / "checkpoints" / "interrupted.npz") as data:
        assert int(data["steps_done"]) == summary["steps"]


# ---------------------------------------------------------------------- run until settled

# Four soft 0.1 m cubes dropped from gaps of 3 to 12 cm onto a plane: settled by about 0.25 s
# (2000 steps of the automatic 1.3e-4 s).
DROP = """\
[simulation]
name = "drop"
dt = "auto"
duration = 1.0

[materials.m]
density = 1000.0
law = "hertz"
k = 1.0e7
restitution = 0.2
friction = 0.5

[shapes.cube]
type = "box"
size = 0.1

[[bodies]]
shape = "cube"
material = "m"
position = [0.0, 0.0, 0.08]

[[bodies]]
shape = "cube"
material = "m"
position = [0.15, 0.0, 0.11]

[[bodies]]
shape = "cube"
material = "m"
position = [0.3, 0.0, 0.14]

[[bodies]]
shape = "cube"
material = "m"
position = [0.45, 0.0, 0.17]

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "m"

[output]
fps = 50
"""


def summary_of(folder):
    return json.loads((Path(folder) / "summary.json").read_text())


@pytest.fixture(scope="module")
def settled_run(tmp_path_factory):
    """``polydem run --until-settled`` of the drop scene: (scene file, output folder, stdout)."""
    folder = tmp_path_factory.mktemp("settle")
    scene = write_scene(folder, DROP, "drop.toml")
    code = main(["run", str(scene), "--device", "cpu", "--until-settled", "--out", str(folder / "out"), "--quiet"])
    assert code == 0
    return scene, folder / "out"


def test_run_until_settled_stops_and_reports(tmp_path, capsys):
    """Before: polydem run had no --until-settled (exit 2, unrecognised argument) and always ran the
    whole duration; now it stops at the check where the pile has settled, well before the maximum."""
    scene = write_scene(tmp_path, DROP, "drop.toml")
    code, out, err = run(["run", scene, "--device", "cpu", "--until-settled", "--out", tmp_path / "out"], capsys)
    assert code == 0, err
    s = summary_of(tmp_path / "out")
    st = s["settle"]
    assert st["settled"] is True
    assert st["criterion"] == {"kinetic_fraction": 1e-4, "max_speed": None, "hold": 0.02, "speed_fraction": 3e-4}
    # The default speed limit: 3e-4 sqrt(g r) of the 0.1 m cubes (r = sqrt(3) 0.05 m).
    assert st["speed_limit"] == pytest.approx(3e-4 * np.sqrt(9.81 * np.sqrt(3.0) * 0.05), rel=1e-6)
    assert st["largest_speed"] < st["speed_limit"]
    assert st["steps"] == s["steps"] and st["steps"] % 64 == 0 and st["steps"] < s["target_steps"]
    assert st["time_s"] == pytest.approx(s["simulated_time"]) and 0.15 < st["time_s"] < 0.5
    assert 0.0 < st["wall_s"] <= s["wall_time"] and st["max_time_s"] == pytest.approx(1.0, abs=s["dt"])
    assert st["time_s"] - st["held_from_s"] >= 0.02 - 1e-9
    # The kinetic fraction agrees with the final energies of the summary (another kernel).
    e = s["energy"]
    released = e["initial"]["gravity"] - e["final"]["gravity"]
    assert st["kinetic_fraction"] == pytest.approx(e["final"]["kinetic"] / released, rel=1e-5)
    assert st["kinetic_fraction"] < 1e-4
    assert f"settled at t = {st['time_s']:.6g} s ({st['steps']} steps, " in out
    assert (
        "until settled (kinetic energy < 0.0001 of the gravitational energy released and largest speed < "
        "0.000277 m/s = 0.0003 sqrt(g r_min), held for 0.02 s)" in out
    )
    assert "kinetic/released" in err  # the progress lines
    assert (tmp_path / "out" / "checkpoints" / "final.npz").is_file()


def test_run_until_settled_within_too_short_a_maximum(tmp_path, capsys):
    scene = write_scene(tmp_path, DROP, "drop.toml")
    args = ["run", scene, "--device", "cpu", "--until-settled", "--duration", "0.05", "--out", tmp_path / "out", "-q"]
    code, out, _ = run(args, capsys)
    assert code == 0
    st = summary_of(tmp_path / "out")["settle"]
    assert st["settled"] is False and st["time_s"] is None and st["steps"] is None
    assert st["kinetic_fraction"] > 1e-4
    assert "not settled within the maximum duration (t = 0.05" in out


def test_resumed_run_until_settled_settles_as_the_unbroken_one(tmp_path, capsys, settled_run):
    scene, unbroken_out = settled_run
    first = tmp_path / "first"
    args = ["run", scene, "--device", "cpu", "--until-settled", "--settle-hold", "0.02", "-q"]
    code, _, _ = run([*args, "--duration", "0.2", "--out", first], capsys)
    assert code == 0 and summary_of(first)["settle"]["settled"] is False
    second = tmp_path / "second"
    code, out, _ = run([*args, "--resume", first / "checkpoints" / "final.npz", "--out", second], capsys)
    assert code == 0
    resumed, unbroken = summary_of(second)["settle"], summary_of(unbroken_out)["settle"]
    assert resumed["settled"] and resumed["steps"] == unbroken["steps"]
    assert resumed["held_from_s"] == unbroken["held_from_s"]
    with np.load(second / "checkpoints" / "final.npz") as a, np.load(unbroken_out / "checkpoints" / "final.npz") as b:
        for key in STATE_KEYS:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    # A checkpoint of a settled run has nothing to continue until settled.
    code, _, err = run([*args, "--resume", second / "checkpoints" / "final.npz", "--out", tmp_path / "x"], capsys)
    assert_user_error(code, err, "--resume", "settled at step", "leave out --until-settled")


def test_scene_until_settled_and_options_override_it(tmp_path, capsys):
    scene = write_scene(
        tmp_path, DROP, "drop.toml", replace=[("duration = 1.0", "duration = 1.0\nsettle = {max_speed = 1e-2}")]
    )
    code, out, _ = run(["run", scene, "--device", "cpu", "--out", tmp_path / "a", "-q"], capsys)
    assert code == 0
    st = summary_of(tmp_path / "a")["settle"]
    assert st["settled"] and st["criterion"] == {
        "kinetic_fraction": 1e-4,
        "max_speed": 1e-2,
        "hold": 0.02,
        "speed_fraction": 3e-4,
    }
    assert st["speed_limit"] == 1e-2  # max_speed replaces the limit of speed_fraction
    assert st["largest_speed"] < 1e-2
    code, out, _ = run(
        [
            "run",
            scene,
            "--device",
            "cpu",
            "--out",
            tmp_path / "b",
            "-q",
            "--settle-kinetic",
            "off",
            "--settle-hold",
            "0",
        ],
        capsys,
    )
    assert code == 0
    st = summary_of(tmp_path / "b")["settle"]
    assert st["criterion"] == {"kinetic_fraction": None, "max_speed": 1e-2, "hold": 0.0, "speed_fraction": 3e-4}


@pytest.mark.parametrize(
    ("args", "replace", "needles"),
    [
        (["--until-settled", "--settle-kinetic", "0"], [], ["--settle-kinetic", "between 0 and 1", "e.g."]),
        (["--until-settled", "--settle-kinetic=-1e-3"], [], ["--settle-kinetic", "between 0 and 1"]),
        (["--until-settled", "--settle-hold", "-1"], [], ["--settle-hold", ">= 0"]),
        (["--until-settled", "--settle-speed", "0"], [], ["--settle-speed", "> 0"]),
        (["--settle-speed", "0.1"], [], ["--settle-speed", "add --until-settled"]),
        (
            ["--until-settled", "--settle-kinetic", "off", "--settle-speed-fraction", "off"],
            [],
            ["--settle-kinetic", "give --settle-speed"],
        ),
        (["--until-settled", "--settle-speed-fraction", "0"], [], ["--settle-speed-fraction", "fraction > 0"]),
        (
            ["--until-settled"],
            [('name = "drop"', 'name = "drop"\ngravity = [0.0, 0.0, 0.0]')],
            ["--until-settled", "no gravity", "--settle-kinetic off --settle-speed V"],
        ),
    ],
)
def test_until_settled_option_errors(tmp_path, capsys, args, replace, needles):
    scene = write_scene(tmp_path, DROP, "drop.toml", replace=replace)
    code, _, err = run(["run", scene, "--device", "cpu", "--out", tmp_path / "out", *args], capsys)
    assert_user_error(code, err, *needles)


def test_resume_command_keeps_the_settle_options():
    args = cli.build_parser().parse_args(
        ["run", "s.toml", "--until-settled", "--settle-kinetic", "off", "--settle-speed", "0.01", "--settle-hold", "0"]
    )
    cmd = Report(args, None, None, log=None, outputs=None, schedule=None, pictures=None, energy_at_start=None)
    text = cmd.resume_command("cp.npz")
    assert "--until-settled --settle-kinetic off --settle-speed 0.01 --settle-hold 0.0" in text
