"""More bad input: decomposed runs (mpiexec) fed bad arguments and scenes, scales no run can resolve
(positions, stiffness, density, time step), and messages that name the real cause.

Each case: what is fed, the exit code, the one line, and nothing already written lost.
"""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run, write_scene

HERE = Path(__file__).resolve().parent

# One steel cube over a plane: 20 steps, nothing written but the summary and the checkpoint.
CUBE = """\
[simulation]
name = "cube"
dt = "auto"
steps = 20

[materials.steel]
density = 7800.0
law = "hertz"
k = 1.0e10
restitution = 0.5
friction = 0.3

[shapes.cube]
type = "box"
size = 0.1

[[bodies]]
shape = "cube"
material = "steel"
position = [0.0, 0.0, 0.2]

[[bodies]]
shape = "cube"
material = "steel"
position = [0.3, 0.0, 0.2]

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "steel"

[output]
usd = false
pictures = false
"""

# scenes/box_pour of tests/distributed_scenes.py as a file: 80 grains thrown into a box, moving between
# the ranks' slabs; checkpoints every 500 steps.
POUR = """\
[simulation]
name = "pour"
gravity = [0, 0, -9.81]
precision = "mixed"
dt = "auto"
steps = 1500

[materials.g]
density = 2500
law = "hertz"
k = 1e9
restitution = 0.4
friction = 0.5

[shapes.cube]
type = "box"
size = 0.01

[shapes.big]
type = "tetrahedron"
edge = 0.022

[[walls]]
type = "box"
center = [0.0, 0.0, 0.2]
inner_size = [0.24, 0.08, 0.4]
material = "g"

[[emitters]]
shape = ["cube", "big"]
weights = [3, 1]
material = "g"
count = 80
region = { min = [-0.115, -0.035, 0.005], max = [0.115, 0.035, 0.2] }
orientation = "random"
velocity = [0.0, 0.0, -1.0]
velocity_jitter = 1.0
seed = 3

[output]
usd = false
pictures = false
fps = 100
checkpoint = { steps = 500 }
"""


def _mpiexec():
    here = Path(sys.executable).parent / "mpiexec"
    return str(here) if here.exists() else shutil.which("mpiexec")


def _have_mpi():
    try:
        import mpi4py  # noqa: F401
    except ImportError:
        return False
    return _mpiexec() is not None


needs_mpi = pytest.mark.skipif(not _have_mpi(), reason="needs mpi4py and mpiexec (pip install '.[test]')")


def _command(args, ranks, cwd, timeout=300):
    """``polydem ARGS`` (``mpiexec -n RANKS`` for RANKS > 1) in ``cwd``: the finished process."""
    cmd = [sys.executable, "-m", "polydem", *[str(a) for a in args]]
    if ranks > 1:
        cmd = [_mpiexec(), "-n", str(ranks), *cmd]
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout)


def _files(folder):
    """{relative path: bytes} of every file under ``folder``."""
    folder = Path(folder)
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# ---------------------------------------------------------------------- decomposed runs fed bad input


def _earlier_checkpoint(tmp_path, capsys):
    """A checkpoint at step 20 of CUBE, written by a run of one process."""
    scene = write_scene(tmp_path, CUBE, "cube.toml")
    code, _, err = run(["run", scene, "--out", tmp_path / "earlier", "--device", "cpu", "-q"], capsys)
    assert code == 0, err
    return tmp_path / "earlier" / "checkpoints" / "final.npz"


# (what is fed: the arguments after "polydem run", with SCENE, OUT and CK standing for the scene file, the
# output folder and an earlier checkpoint; the scene's text changes; what the one line says)
DECOMPOSED_CASES = {
    "missing scene": (["missing.toml", "--out", "OUT"], (), ["missing.toml: scene file not found"]),
    "output folder is a file": (["SCENE", "--out", "OUT/file.txt"], (), ["--out: the output folder is a file"]),
    "missing checkpoint": (["SCENE", "--out", "OUT", "--resume", "nope.npz"], (), ["--resume: checkpoint not found"]),
    "bad scene value": (
        ["SCENE", "--out", "OUT"],
        (("friction = 0.3", "friction = -1.0"),),
        ["cube.toml: materials.steel.friction:"],
    ),
    "body far from the origin": (
        ["SCENE", "--out", "OUT"],
        (("position = [0.0, 0.0, 0.2]", "position = [0.0, 0.0, 1e20]"),),
        ["bodies[0].position:", "float64 numbers are"],
    ),
    "checkpoint past the end": (
        ["SCENE", "--out", "OUT", "--resume", "CK", "--steps", "10"],
        (),
        ["--resume: the checkpoint is at step 20", "already reaches the 10 steps"],
    ),
    "settle option without --until-settled": (
        ["SCENE", "--out", "OUT", "--settle-hold", "0.1"],
        (),
        ["--settle-hold: --settle-hold sets the criterion of a run until settled"],
    ),
}


@needs_mpi
@pytest.mark.parametrize("case", list(DECOMPOSED_CASES))
def test_decomposed_run_refuses_bad_input_in_one_line(tmp_path, capsys, case):
    """Before: every rank printed the error (rank 0's and rank 1's line, then MPICH's "Abort(2) on node 1"
    lines; the missing scene also an UnboundLocalError of rank 1 after MPI_Abort returned). Now every rank
    checks, they agree, rank 0 prints the one line a run of one process prints and all exit with code 2;
    the output folder keeps what an earlier run wrote and gains nothing."""
    args, replace, expected = DECOMPOSED_CASES[case]
    scene = write_scene(tmp_path, CUBE, "cube.toml", replace=replace)
    out = tmp_path / "out"
    out.mkdir()
    (out / "file.txt").write_text("written before\n")
    (out / "checkpoints").mkdir()
    (out / "checkpoints" / "final.npz").write_bytes(b"an earlier run's checkpoint")
    before = _files(out)
    ck = _earlier_checkpoint(tmp_path, capsys) if "CK" in args else None
    subs = {"SCENE": scene, "OUT": out, "OUT/file.txt": out / "file.txt", "CK": ck}
    done = _command(["run", *[subs.get(a, a) for a in args], "--device", "cpu", "-q"], 2, tmp_path)
    lines = done.stderr.splitlines()
    assert done.returncode == 2, done.stdout + done.stderr
    assert len(lines) == 1 and lines[0].startswith("polydem: error: "), done.stderr
    for text in expected:
        assert text in lines[0], lines[0]
    assert "Abort" not in done.stdout + done.stderr and "rank" not in lines[0]
    assert _files(out) == before


def test_an_error_of_another_rank_is_named_once(capsys):
    """Where only rank 1 failed before the run (its node cannot read a file, say), rank 0 prints its
    line naming it, and the others return the same exit code without printing."""
    from polydem.cli import CliError
    from polydem.cli.run import _agree

    class Comm:
        def __init__(self, rank):
            self.rank = rank

        def Get_rank(self):
            return self.rank

        def Get_size(self):
            return 3

        def allgather(self, mine):
            return [None, (True, "cube.toml: scene file not found", ""), (True, "later rank", "")]

    with pytest.raises(CliError) as exc:
        _agree(Comm(0), None)
    assert str(exc.value) == "rank 1 of 3: cube.toml: scene file not found"
    assert _agree(Comm(2), None) == 2
    assert capsys.readouterr() == ("", "")

    class Fine(Comm):
        def allgather(self, mine):
            return [None, None, None]

    assert _agree(Fine(0), None) is None


@needs_mpi
def test_decomposed_checkpoints_are_the_one_process_checkpoints(tmp_path):
    """Before: the pair lists of a decomposed run's checkpoints held the candidate pairs of its ranks'
    broad phases (25 against 24 at step 1500 here, the extra ones with zero history), and its time differed
    from one process's in the last bits (steps * dt against one process's sum over its chunks). Now both
    keep the pairs that carry a history, and every array is the same (the run record aside: wall times and
    folders); a decomposed checkpoint resumes on one process to the unbroken run."""
    scene = write_scene(tmp_path, POUR, "pour.toml")
    for ranks in (1, 2):
        done = _command(["run", scene, "--out", tmp_path / f"r{ranks}", "--device", "cpu", "-q"], ranks, tmp_path)
        assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    names = ("step_000000500.npz", "step_000001000.npz", "final.npz")
    for name in names:
        one = np.load(tmp_path / "r1" / "checkpoints" / name)
        two = np.load(tmp_path / "r2" / "checkpoints" / name)
        assert sorted(one.files) == sorted(two.files)
        for k in one.files:
            if k != "run_json":
                np.testing.assert_array_equal(one[k], two[k], err_msg=f"{name}: {k}")
    assert len(np.load(tmp_path / "r1" / "checkpoints" / "final.npz")["pair_key"]) > 3
    ck = tmp_path / "r2" / "checkpoints" / "step_000001000.npz"
    done = _command(["run", scene, "--out", tmp_path / "resumed", "--resume", ck, "--device", "cpu", "-q"], 1, tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    a = np.load(tmp_path / "r1" / "checkpoints" / "final.npz")
    b = np.load(tmp_path / "resumed" / "checkpoints" / "final.npz")
    for k in ("body_q", "body_v", "body_w", "pair_key", "pair_xi", "pair_turn", "steps_done"):
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


# ---------------------------------------------------------------------- scales no run can resolve

FAR = {
    "1e20 m": ("position = [0.0, 0.0, 0.2]", "position = [0.0, 0.0, 1e20]"),
    "1e27 m": ("position = [0.0, 0.0, 0.2]", "position = [0.0, 0.0, 1e27]"),
    "an integer past int64": ("position = [0.0, 0.0, 0.2]", "position = [0, 0, 1000000000000000000000000000]"),
}


@pytest.mark.parametrize("case", list(FAR))
def test_body_too_far_from_the_origin_is_refused(tmp_path, capsys, monkeypatch, case):
    """Before: accepted, and the cube at z = 1e20 (float64 numbers 16 km apart there) never moved. Now an
    error naming the body's position, the spacing, and how near the origin the scene must be."""
    monkeypatch.chdir(tmp_path)
    scene = write_scene(tmp_path, CUBE, "cube.toml", replace=[FAR[case]])
    code, out, err = run(["run", scene, "--device", "cpu", "-q"], capsys)
    assert code == 2 and out == ""
    assert err.startswith(f"polydem: error: {scene}: bodies[0].position: body 0 ") and err.count("\n") == 1, err
    assert "float64 numbers are" in err and "place the bodies within 5.5e+11 m of the origin" in err
    assert not (tmp_path / "polydem_out").exists()


def test_far_but_resolvable_positions_pass(tmp_path, capsys):
    """The bound is far out: both cubes and the floor 1e4 m up (float64 numbers 1.8e-12 m apart there) are
    a sound scene, as tests/test_precision.py runs it."""
    far = ("0.0, 0.2]", "0.0, 10000.2]")  # both cubes
    plane = ("point = [0.0, 0.0, 0.0]", "point = [0.0, 0.0, 10000.0]")
    scene = write_scene(tmp_path, CUBE, "far.toml", replace=[far, plane])
    code, _, err = run(["validate", scene], capsys)
    assert code == 0 and "numbers are" not in err, err


# (the scene's change, what the warning names)
SHORT_STEP = {
    "k = 1e30": (("k = 1.0e10", "k = 1.0e30"), ['dt = "auto" takes it from', "check k = 1e+30 and density = 7800.0"]),
    "density 1e-10": (("density = 7800.0", "density = 1e-10"), ["density = 1e-10 of materials.steel"]),
    "dt = 1e-300 without a duration": (
        ('dt = "auto"\nsteps = 20', "dt = 1e-300"),
        ["1000 steps of 1e-300 s (the default)", "simulation.dt = 1e-300 s sets it"],
    ),
}


@pytest.mark.parametrize("case", list(SHORT_STEP))
def test_a_run_that_cannot_move_anything_warns(tmp_path, capsys, case):
    """Before: accepted silently; the run covered 7e-25 s (k = 1e30), 9e-19 s (density 1e-10) or 1e-297 s
    (dt = 1e-300 for the default 1000 steps) and ended where it began. Now one warning line: what the steps
    cover, that no body moves by the spacing of its position numbers, and what sets the step."""
    change, expected = SHORT_STEP[case]
    scene = write_scene(tmp_path, CUBE, "cube.toml", replace=[change])
    code, _, err = run(["run", scene, "--out", tmp_path / "out", "--device", "cpu", "-q"], capsys)
    assert code == 0
    warnings = [line for line in err.splitlines() if line.startswith("polydem: warning: ")]
    assert len(warnings) == 1, err
    assert "move no body as far as the spacing of its position numbers" in warnings[0], warnings[0]
    for text in expected:
        assert text in warnings[0], warnings[0]


def test_default_steps_covering_next_to_no_time_warn(tmp_path, capsys):
    """dt = 1e-10 and no steps or duration: the default 1000 steps cover 1e-7 s (the cube falls 5e-14 m,
    so it does move). A warning names the default and simulation.dt; the scene's own 20 steps of the
    automatic step do not warn."""
    scene = write_scene(tmp_path, CUBE, "short.toml", replace=[('dt = "auto"\nsteps = 20', "dt = 1e-10")])
    code, _, err = run(["run", scene, "--out", tmp_path / "short", "--device", "cpu", "-q"], capsys)
    assert code == 0
    assert "polydem: warning: " in err and "1000 steps of 1e-10 s (the default) cover 1e-07 s, less than 1e-06 s" in err
    assert "simulation.dt = 1e-10 s sets it" in err
    plain = write_scene(tmp_path, CUBE, "plain.toml")
    code, _, err = run(["run", plain, "--out", tmp_path / "plain", "--device", "cpu", "-q"], capsys)
    assert code == 0 and "warning" not in err, err


# ---------------------------------------------------------------------- messages that name the cause


def test_long_name_without_out_blames_the_name(tmp_path, capsys, monkeypatch):
    """Before: "polydem_out/nnn...n (300 characters): --out: cannot create the output folder" for a run
    given no --out. Now the name and the fix; no polydem_out folder left behind."""
    monkeypatch.chdir(tmp_path)
    scene = write_scene(tmp_path, CUBE, "cube.toml", replace=[('name = "cube"', f'name = "{"n" * 300}"')])
    code, out, err = run(["run", scene, "--device", "cpu", "-q"], capsys)
    assert code == 2 and out == ""
    assert err.startswith(f"polydem: error: {scene}: simulation.name: the name (300 characters) is too long"), err
    assert "--out:" not in err and "give a shorter simulation.name, or an output folder with --out" in err
    assert not (tmp_path / "polydem_out").exists()
    code, _, err = run(["run", scene, "--device", "cpu", "-q", "--out", tmp_path / "given"], capsys)
    assert code == 0, err


def test_default_output_folder_that_is_a_file(tmp_path, capsys, monkeypatch):
    """No --out, and polydem_out/cube is a file: the message names that folder, not an --out never given;
    the file is left as it was."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "polydem_out").mkdir()
    (tmp_path / "polydem_out" / "cube").write_text("mine")
    scene = write_scene(tmp_path, CUBE, "cube.toml")
    code, _, err = run(["run", scene, "--device", "cpu", "-q"], capsys)
    assert code == 2
    folder = "the default output folder polydem_out/cube is a file"
    assert err == f"polydem: error: {folder}; remove it or give a folder with --out\n"
    assert (tmp_path / "polydem_out" / "cube").read_text() == "mine"


@pytest.mark.parametrize("name", ["", "   "])
def test_empty_name_is_refused(tmp_path, capsys, name):
    """Before: the run started and its header read ": 2 bodies (2 free) on cpu, ...". Now an error."""
    scene = write_scene(tmp_path, CUBE, "cube.toml", replace=[('name = "cube"', f'name = "{name}"')])
    code, out, err = run(["run", scene, "--out", tmp_path / "out", "--device", "cpu", "-q"], capsys)
    assert code == 2 and out == ""
    assert err.startswith(f"polydem: error: {scene}: simulation.name: the name is empty"), err
    assert "leave name out to use the file's ('cube')" in err
    assert not (tmp_path / "out").exists()


def test_huge_gravity_is_blamed_on_gravity(tmp_path, capsys):
    """Before: gravity = [0, 0, -1e30] was "materials.steel.k: ... too soft ... use smaller densities or
    larger bodies". Now the key is simulation.gravity, with the gravity as given and the largest one that
    any k within float32's range carries."""
    scene = write_scene(tmp_path, CUBE, "cube.toml", replace=[("steps = 20", "steps = 20\ngravity = [0, 0, -1e30]")])
    code, _, err = run(["validate", scene], capsys)
    assert code == 2
    assert err.startswith(f"polydem: error: {scene}: simulation.gravity: the contacts of body 0 "), err
    assert "the gravity [0.0, 0.0, -1e+30] (1.02e+29 times standard gravity) is too strong" in err
    assert "use a gravity of at most" in err and "materials.steel.k" not in err
    # Where standard gravity's weight is beyond every k too, the materials stay blamed.
    heavy = write_scene(tmp_path, CUBE, "heavy.toml", replace=[("density = 7800.0", "density = 1e30")])
    code, _, err = run(["validate", heavy], capsys)
    assert code == 2 and "simulation.gravity" not in err, err


def test_environment_gives_the_launched_rank(monkeypatch):
    from polydem.distributed.comm import launched_rank

    for name in ("PMI_SIZE", "PMI_RANK", "OMPI_COMM_WORLD_SIZE", "OMPI_COMM_WORLD_RANK", "PMIX_SIZE", "PMIX_RANK"):
        monkeypatch.delenv(name, raising=False)
    for name in ("SLURM_NTASKS", "SLURM_PROCID", "MPI_LOCALNRANKS", "ALPS_APP_PE"):
        monkeypatch.delenv(name, raising=False)
    assert launched_rank() == 0
    monkeypatch.setenv("PMI_SIZE", "4")
    monkeypatch.setenv("PMI_RANK", "3")
    assert launched_rank() == 3
    monkeypatch.setenv("PMI_SIZE", "1")
    assert launched_rank() == 0
    assert os.environ["PMI_RANK"] == "3"


# ---------------------------------------------------------------------- with the fixes outside these files
# (scene/materials.py, scene/values.py, shapes.py, cli/report.py, cli/__init__.py)


def test_restitution_is_printed_as_given(tmp_path, capsys):
    """Before: "must be in (0, 1], got 1" for restitution = 1.0000001."""
    scene = write_scene(tmp_path, CUBE, "cube.toml", replace=[("restitution = 0.5", "restitution = 1.0000001")])
    code, _, err = run(["validate", scene], capsys)
    assert code == 2 and "materials.steel.restitution: must be in (0, 1], got 1.0000001 " in err, err


def test_mesh_smaller_than_the_merge_tolerance(tmp_path, capsys):
    """Before: a cube mesh of 1e-9 m gave "at least 4 points are needed ..., got 1" (its 8 vertices merged
    into one). Now the message says the mesh is smaller than the distance within which vertices merge."""
    s = 1e-9
    corners = [(x * s, y * s, z * s) for x in (0, 1) for y in (0, 1) for z in (0, 1)]
    faces = [(1, 3, 4, 2), (5, 6, 8, 7), (1, 2, 6, 5), (3, 7, 8, 4), (1, 5, 7, 3), (2, 4, 8, 6)]
    text = "".join(f"v {x!r} {y!r} {z!r}\n" for x, y, z in corners) + "".join(
        f"f {a} {b} {c} {d}\n" for a, b, c, d in faces
    )
    (tmp_path / "tiny.obj").write_text(text)
    scene = write_scene(
        tmp_path, CUBE, "cube.toml", replace=[('type = "box"\nsize = 0.1', 'type = "mesh"\nfile = "tiny.obj"')]
    )
    code, _, err = run(["validate", scene], capsys)
    assert code == 2 and err.count("\n") == 1
    assert "shapes.cube:" in err and "its 8 vertices span only 1e-09 m" in err, err
    assert "too little against the distance within which vertices are merged (1e-08 m)" in err and "got 1" not in err


def test_resumed_run_lists_only_what_it_wrote(tmp_path, capsys):
    """Before: "written to B/:" named the earlier run's checkpoints and pictures (in A/) as well. Now they
    are named in a line of their own; the summary still lists the whole run's."""
    text = CUBE.replace("steps = 20", "steps = 40").replace("pictures = false", "pictures = [0]")
    text += "checkpoint = { steps = 10 }\n"
    scene = write_scene(tmp_path, text, "cube.toml")
    code, _, err = run(["run", scene, "--out", tmp_path / "A", "--steps", "20", "--device", "cpu", "-q"], capsys)
    assert code == 0, err
    ck = tmp_path / "A" / "checkpoints" / "final.npz"
    code, out, err = run(["run", scene, "--out", tmp_path / "B", "--resume", ck, "--device", "cpu", "-q"], capsys)
    assert code == 0, err
    written = out[out.index("written to") :]
    assert str(tmp_path / "A") not in written.split("earlier parts")[0], written
    assert (
        "    checkpoints/step_000000030.npz, checkpoints/step_000000040.npz, checkpoints/final.npz  checkpoints"
        in written
    )
    earlier = f"earlier parts of the run wrote 3 checkpoints and 1 picture (in {tmp_path / 'A'}; listed in the summary)"
    assert earlier in written
    import json

    summary = json.loads((tmp_path / "B" / "summary.json").read_text())
    assert len(summary["outputs"]["checkpoints"]) == 6 and len(summary["outputs"]["pictures"]) == 1


def test_packing_of_a_pile_still_falling_is_not_called_settled(tmp_path, capsys):
    """Before: "settled region (N bodies): packing fraction ..." while the grains were still in the air.
    Now the line says the region is not at rest, and the summary's settled_region has at_rest = false."""
    import json

    # The default scene 200 steps in (5 ms): its 300 grains are falling onto the floor of their box.
    code, out, err = run(["run", "--steps", "200", "--out", tmp_path / "out", "--device", "cpu", "-q"], capsys)
    assert code == 0, err
    assert "settled region" not in out and "region below the top, not at rest (" in out, out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["settled_region"]["at_rest"] is False


@needs_mpi
@pytest.mark.parametrize("option", [["--steps", "-5"], ["--bogus"]])
def test_decomposed_run_with_a_bad_option_says_it_once(tmp_path, option):
    """Before: one "polydem: error: argument ..." line per rank."""
    scene = write_scene(tmp_path, CUBE, "cube.toml")
    done = _command(["run", scene, *option, "--device", "cpu"], 2, tmp_path)
    assert done.returncode == 2
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("polydem: error: "), done.stderr
