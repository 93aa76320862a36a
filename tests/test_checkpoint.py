"""Checkpoint and resume give the same result as an unbroken run."""

from pathlib import Path

import numpy as np
import pytest

# The file-format tests need one device that runs (the GPU machine's Warp has no CPU compiler).
from conftest import DEVICES

import polydem
from polydem.checkpoint import load_checkpoint, save_checkpoint
from polydem.default_scene import default_scene

HOST = DEVICES[0]


@pytest.mark.parametrize("precision", [None, "float32"], ids=["default", "float32"])
def test_resume_equals_unbroken_run(device, tmp_path, precision):
    """In the default precision and in float32 (no longer the default, still offered)."""
    scene = default_scene(count=40, seed=2)
    if precision is not None:
        scene.precision = precision
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


# ---------------------------------------------------------------------- physics record and sound files


def stack(
    friction=0.5,
    restitution=0.4,
    k=1.0e8,
    density=2500.0,
    size=0.02,
    gravity=-9.81,
    plane=True,
    dt=2e-5,
    precision=None,
):
    """Five cubes falling onto a floor plane (a plane wall, springs and candidate pairs at once), in
    ``precision`` (None: the default)."""
    from polydem.scene import Scene
    from polydem.shapes import ConvexShape

    scene = Scene(gravity=(0.0, 0.0, gravity), dt=dt, name="stack")
    if precision is not None:
        scene.precision = precision
    scene.add_material("stone", density=density, law="hertz", k=k, restitution=restitution, friction=friction)
    scene.add_shape("cube", ConvexShape.box(size, name="cube"))
    if plane:
        scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "stone")
    for i in range(5):
        scene.add_body("cube", "stone", position=(0.003 * i, 0.0, 0.0102 + 0.0201 * i), velocity=(0.0, 0.0, -0.5))
    return scene


def _saved(tmp_path_factory, precision=None):
    """A checkpoint of the stack after 300 steps (with pairs, springs and a run record): its path."""
    sim = polydem.Simulation(stack(precision=precision), device=HOST)
    sim.step(300)
    path = tmp_path_factory.mktemp("ck") / "stack.npz"
    save_checkpoint(sim, path, run={"note": "the run so far"})
    with np.load(path) as data:
        assert len(data["pair_key"]) >= 3 and np.any(data["pair_xi"] != 0.0)
    return path


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """The stack's checkpoint in the default precision."""
    return _saved(tmp_path_factory)


@pytest.fixture(scope="module")
def saved_float32(tmp_path_factory):
    """The stack's checkpoint in float32 (its body state is float32)."""
    return _saved(tmp_path_factory, "float32")


def edited(saved, tmp_path, **changes):
    """A copy of the saved checkpoint with entries replaced (None: removed)."""
    with np.load(saved) as f:
        data = dict(f)
    for key, value in changes.items():
        if value is None:
            data.pop(key)
        else:
            data[key] = value(data) if callable(value) else value
    path = tmp_path / "edited.npz"
    np.savez(path, **data)
    return path


def _set(name, index, value):
    def change(data):
        a = data[name].copy()
        a[index] = value
        return a

    return change


# (entries changed, words the error must hold)
EDITS = {
    "zero quaternion": ({"body_q": _set("body_q", (2, slice(3, 7)), 0.0)}, ["orientation of body 2", "length 0"]),
    "scaled quaternion": (
        {"body_q": lambda d: d["body_q"] * np.r_[1, 1, 1, 2, 2, 2, 2].astype(np.float32)},
        ["orientation of body 0", "length 2"],
    ),
    "rows missing": ({"body_q": lambda d: d["body_q"][:-1]}, ["body_q has shape (4, 7), expected (5, 7)"]),
    "velocity rows missing": ({"body_v": lambda d: d["body_v"][:3]}, ["body_v has shape (3, 3)"]),
    "wrong columns": ({"body_w": lambda d: d["body_w"][:, :2]}, ["body_w has shape (5, 2), expected (5, 3)"]),
    "string dtype": ({"body_v": lambda d: d["body_v"].astype(str)}, ["body_v holds", "expected real numbers"]),
    "complex dtype": ({"body_w": lambda d: d["body_w"].astype(complex)}, ["body_w holds complex128"]),
    "NaN position": ({"body_q": _set("body_q", (1, 2), np.nan)}, ["body_q[1, 2] is nan", "finite"]),
    "inf velocity": ({"body_v": _set("body_v", (0, 0), np.inf)}, ["body_v[0, 0] is inf"]),
    "NaN dissipated": ({"body_dissipated": _set("body_dissipated", 3, np.nan)}, ["body_dissipated[3] is nan"]),
    "NaN wall spring": ({"wall_xi": _set("wall_xi", (0, 0, 1), np.nan)}, ["wall_xi[0, 0, 1] is nan"]),
    "NaN turning volume": ({"pair_turn": _set("pair_turn", 0, np.nan)}, ["pair_turn[0] is nan"]),
    # float32: a float64 value beyond the float32 body state; mixed: beyond the float32 contact history.
    "float64 overflow": ({"body_w": lambda d: d["body_w"].astype(np.float64) + 1e300}, ["body_w[0, 0] is 1e+300"]),
    "float64 overflow of the history": (
        {"pair_turn": lambda d: d["pair_turn"].astype(np.float64) + 1e300},
        ["pair_turn[0] is 1e+300"],
    ),
    "negative steps": ({"steps_done": np.array(-5)}, ["steps_done = -5 is negative"]),
    "fractional steps": ({"steps_done": np.array(300.5)}, ["steps_done = 300.5 is not a whole number"]),
    "step count mismatch": ({"step_count": np.array([7], np.int32)}, ["step_count = [7] does not match"]),
    "NaN time": ({"time": np.array(np.nan)}, ["time = nan s is not a finite time"]),
    "time off": ({"time": np.array(1.0)}, ["time = 1.0 s does not match steps_done = 300"]),
    "NaN dt": ({"dt": np.array(np.nan)}, ["dt = nan"]),
    "no bodies": ({"num_bodies": np.array(0)}, ["num_bodies = 0"]),
    "pair key out of range": ({"pair_key": _set("pair_key", -1, 5 * 5 + 1)}, ["pair_key[", "is not a pair of bodies"]),
    "pair key of a body with itself": (
        {"pair_key": _set("pair_key", 0, 0)},
        ["pair_key[0] = 0 (bodies 0, 0) is not a pair"],
    ),
    "negative pair key": ({"pair_key": _set("pair_key", 0, -3)}, ["pair_key[0] = -3"]),
    "repeated pair key": ({"pair_key": lambda d: np.r_[d["pair_key"][:1], d["pair_key"][:-1]]}, ["repeats"]),
    "unsorted pair keys": ({"pair_key": lambda d: d["pair_key"][::-1].copy()}, ["smaller than the one before"]),
    "float pair keys": ({"pair_key": lambda d: d["pair_key"] + 0.5}, ["pair_key has shape", "whole numbers"]),
    "springs missing": ({"pair_xi": lambda d: d["pair_xi"][:-1]}, ["pair_xi has shape"]),
    "entry missing": ({"body_w": None}, ["it lacks body_w"]),
    "physics record edited": (
        {"physics_json": lambda d: np.array(str(d["physics_json"]).replace("0.5", "0.25"))},
        ["does not match its physics_fingerprint"],
    ),
    "run record not JSON": ({"run_json": np.array("{not json")}, ["run record is not JSON"]),
    "format unknown": ({"format": np.array("polydem-checkpoint-99")}, ["checkpoint format 'polydem-checkpoint-99'"]),
}


FLOAT32_EDITS = ("float64 overflow",)
"""Edits of the float32 checkpoint: in the default precision (mixed) the body state is float64."""


@pytest.mark.parametrize("case", EDITS, ids=list(EDITS))
def test_edited_checkpoints_are_refused(saved, saved_float32, tmp_path, case):
    from polydem.checkpoint import CheckpointError, read_checkpoint

    changes, words = EDITS[case]
    path = edited(saved_float32 if case in FLOAT32_EDITS else saved, tmp_path, **changes)
    with pytest.raises(CheckpointError) as info:
        read_checkpoint(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ") and "\n" not in message
    for word in words:
        assert word in message, (word, message)


def test_sound_checkpoint_reads(saved):
    from polydem.checkpoint import read_checkpoint

    ck = read_checkpoint(saved)
    assert ck.steps_done == 300 and ck.run == {"note": "the run so far"}
    assert ck.physics["materials.stone.friction"] == 0.5 and len(ck.physics["shapes.cube.vertices"]) == 8


@pytest.mark.parametrize(
    "make, words",
    [
        (lambda p: p.write_bytes(b"not a checkpoint"), ["not a polydem checkpoint"]),
        (lambda p, src=None: p.write_bytes(b""), ["not a polydem checkpoint"]),
        (lambda p: np.save(open(p, "wb"), np.zeros(3)), ["a single .npy array"]),
    ],
    ids=["text", "empty", "npy"],
)
def test_foreign_files_are_refused(tmp_path, make, words):
    from polydem.checkpoint import CheckpointError, read_checkpoint

    path = tmp_path / "x.npz"
    make(path)
    with pytest.raises(CheckpointError) as info:
        read_checkpoint(path)
    for word in words:
        assert word in str(info.value)
    assert "allow_pickle" not in str(info.value)  # numpy's advice to unpickle the file is not passed on


def test_truncated_and_damaged_files_are_refused(saved, tmp_path):
    import zipfile

    from polydem.checkpoint import CheckpointError, read_checkpoint

    raw = saved.read_bytes()
    for cut in (len(raw) // 2, len(raw) - 10):
        path = tmp_path / f"cut{cut}.npz"
        path.write_bytes(raw[:cut])
        with pytest.raises(CheckpointError, match="not a polydem checkpoint"):
            read_checkpoint(path)
    damaged = tmp_path / "member.npz"
    with zipfile.ZipFile(saved) as src, zipfile.ZipFile(damaged, "w") as dst:
        for name in src.namelist():
            data = src.read(name)
            dst.writestr(name, data[: len(data) // 2] if name == "body_v.npy" else data)
    with pytest.raises(CheckpointError, match="array 'body_v' cannot be read"):
        read_checkpoint(damaged)


@pytest.mark.parametrize(
    "other, words",
    [
        ({"friction": 0.3}, ["materials.stone.friction differs: checkpoint 0.5, scene 0.3"]),
        ({"restitution": 0.9}, ["materials.stone.restitution differs: checkpoint 0.4, scene 0.9"]),
        ({"k": 2.0e8}, ["materials.stone.k differs: checkpoint 1e+08, scene 2e+08"]),
        ({"density": 3000.0}, ["materials.stone.density differs: checkpoint 2500, scene 3000"]),
        ({"size": 0.021}, ["shapes.cube.vertices differ", "0.02 x 0.02 x 0.02 m", "0.021 x 0.021 x 0.021 m"]),
        ({"gravity": -3.0}, ["simulation.gravity differs: checkpoint [0, 0, -9.81], scene [0, 0, -3]"]),
        ({"plane": False}, ["planes differ: checkpoint 1 planes, scene 0"]),
        ({"dt": 1e-5}, ["simulation.dt differs: checkpoint 2e-05, scene 1e-05"]),
    ],
)
def test_checkpoint_of_other_physics_is_refused(saved, other, words):
    from polydem.checkpoint import CheckpointError

    sim = polydem.Simulation(stack(**other), device=HOST)
    with pytest.raises(CheckpointError) as info:
        load_checkpoint(sim, saved)
    message = str(info.value)
    assert "written for other physics" in message and "use the scene the checkpoint was written from" in message
    for word in words:
        assert word in message, (word, message)
    assert sim.steps_done == 0  # nothing was loaded


def test_physics_differences_of_drums_and_bodies(tmp_path):
    """Host only: the drum's speed, and bodies of another shape, are named with the first body that differs."""
    from polydem.checkpoint import physics_description, physics_differences
    from polydem.scene import Scene

    drum = (Path(__file__).resolve().parents[1] / "scenes" / "drum.toml").read_text()
    assert "rpm = 20.0" in drum
    (tmp_path / "fast.toml").write_text(drum.replace("rpm = 20.0", "rpm = 30.0"))
    a = physics_description(Scene.from_toml(tmp_path / "fast.toml"), 1e-5)
    b = physics_description(Scene.from_toml(Path(__file__).resolve().parents[1] / "scenes" / "drum.toml"), 1e-5)
    diffs = physics_differences(*a, *b)
    assert diffs[0] == "drums[0].omega differs: checkpoint 3.14159, scene 2.0944"
    assert any("angular_velocity of a kinematic body differs" in d for d in diffs)
    assert physics_differences(*b, *b) == []

    one, two = stack(), stack()
    two.add_shape("tet", polydem.ConvexShape.tetrahedron(0.03, name="tet"))
    two.add_body("tet", "stone", position=(0.0, 0.0, 0.5))
    one.add_body("cube", "stone", position=(0.0, 0.0, 0.5))
    diffs = physics_differences(*physics_description(one, 1e-5), *physics_description(two, 1e-5))
    assert "shapes differ: checkpoint ['cube'], scene ['cube', 'tet']" in diffs
    assert "bodies[5].shape differs: checkpoint 'cube', scene 'tet'" in diffs


def test_old_format_loads_with_a_warning(saved, tmp_path):
    from polydem.checkpoint import CheckpointWarning, read_checkpoint

    with np.load(saved) as f:
        data = {k: v for k, v in f.items() if not k.startswith("physics_") and k != "run_json"}
    data["format"] = np.array("polydem-checkpoint-2")
    np.savez(tmp_path / "old.npz", **data)
    assert read_checkpoint(tmp_path / "old.npz").physics is None
    sim = polydem.Simulation(stack(), device=HOST)
    with pytest.warns(CheckpointWarning, match="cannot be checked to come from this scene"):
        load_checkpoint(sim, tmp_path / "old.npz")
    assert sim.steps_done == 300


def test_checkpoint_with_the_old_wall_names_loads(saved, tmp_path):
    """Checkpoints written before issue 25 name the wall contacts' springs and turning volumes
    ``plane_xi`` and ``plane_turn``: they load into the same state as today's ``wall_*``."""
    with np.load(saved) as f:
        data = dict(f)
    assert np.any(data["wall_turn"] != 0.0)  # the floor's contacts carry a history to compare
    data["plane_xi"] = data.pop("wall_xi")
    data["plane_turn"] = data.pop("wall_turn")
    np.savez(tmp_path / "old_names.npz", **data)
    old = polydem.Simulation(stack(), device=HOST)
    load_checkpoint(old, tmp_path / "old_names.npz")
    today = polydem.Simulation(stack(), device=HOST)
    load_checkpoint(today, saved)
    for name in ("wall_xi", "wall_turn", "body_q"):
        np.testing.assert_array_equal(
            getattr(old.current_state, name).numpy(), getattr(today.current_state, name).numpy(), err_msg=name
        )


@pytest.mark.skipif(HOST != "cpu", reason="the stored checkpoint was written on the CPU: bit for bit only there")
def test_checkpoint_of_the_format_before_the_state_redesign_resumes(tmp_path):
    """tests/data/stack_base_format.npz was written by polydem before State and Contacts existed
    (the stack after 300 steps on the CPU): it loads into exactly the state it holds, and resumes as
    the same state written in today's format does, bit for bit. (Until issue 11 it also equalled an
    unbroken run; issue 11 changed the resting contacts' physics, so the file's steps are not
    today's.)"""
    from polydem.checkpoint import read_checkpoint

    path = Path(__file__).resolve().parent / "data" / "stack_base_format.npz"
    old = read_checkpoint(path)
    assert old.run == {"note": "written by polydem before issue 10"}
    # The file holds a float32 run: its scene is pinned to float32 (the default became "mixed").
    resumed = polydem.Simulation(stack(precision="float32"), device=HOST)
    load_checkpoint(resumed, path)
    assert resumed.steps_done == 300 and len(resumed.current_contacts.history_numpy()["pair_key"]) >= 3
    for name in ("body_q", "body_v", "body_w", "body_dissipated"):
        np.testing.assert_array_equal(getattr(resumed.current_state, name).numpy(), old.arrays[name], err_msg=name)
    save_checkpoint(resumed, tmp_path / "today.npz")
    again = polydem.Simulation(stack(precision="float32"), device=HOST)
    load_checkpoint(again, tmp_path / "today.npz")
    resumed.step(300)
    again.step(300)
    a, b = again.state(), resumed.state()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert again.energy() == resumed.energy()
    # Written again, it holds the same arrays as a checkpoint of the run resumed from today's format.
    save_checkpoint(again, tmp_path / "a.npz")
    save_checkpoint(resumed, tmp_path / "b.npz")
    with np.load(tmp_path / "a.npz") as fa, np.load(tmp_path / "b.npz") as fb:
        assert fa.files == fb.files
        for key in fa.files:
            np.testing.assert_array_equal(fa[key], fb[key], err_msg=key)


@pytest.mark.parametrize("precision", ["mixed", "float64"])
def test_resume_equals_unbroken_run_in_float64_precisions(device, tmp_path, precision):
    """A checkpoint of a "mixed" or "float64" run keeps the float64 state (and the history in its
    precision) and resumes bit for bit; before, precision = "float64" was refused and "mixed" did
    not exist."""
    from polydem.checkpoint import read_checkpoint

    scene = stack()
    scene.precision = precision
    unbroken = polydem.Simulation(scene, device=device)
    unbroken.step(600)
    first = polydem.Simulation(scene, device=device)
    first.step(300)
    save_checkpoint(first, tmp_path / "run.npz")
    with np.load(tmp_path / "run.npz") as data:
        assert data["body_q"].dtype == np.float64 and data["body_dissipated"].dtype == np.float64
        history = np.float64 if precision == "float64" else np.float32
        assert data["pair_turn"].dtype == history and data["wall_turn"].dtype == history
        assert len(data["pair_key"]) >= 3 and np.any(data["pair_xi"] != 0.0)
    assert read_checkpoint(tmp_path / "run.npz").arrays["body_q"].dtype == np.float64
    resumed = polydem.Simulation(scene, device=device)
    load_checkpoint(resumed, tmp_path / "run.npz")
    resumed.step(300)
    a, b = unbroken.state(), resumed.state()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert unbroken.energy()["dissipated"] == resumed.energy()["dissipated"]


def test_checkpoint_of_another_precision_is_refused(tmp_path):
    """A float64 checkpoint resumed in float32 (or the other way) is refused, naming the precisions."""
    from polydem.checkpoint import CheckpointError

    scene = stack()
    scene.precision = "float64"
    sim = polydem.Simulation(scene, device=HOST)
    sim.step(10)
    save_checkpoint(sim, tmp_path / "f64.npz")
    for other in ("float32", "mixed"):
        scene.precision = other
        with pytest.raises(
            CheckpointError, match=f"simulation.precision differs: checkpoint 'float64', scene '{other}'"
        ):
            load_checkpoint(polydem.Simulation(scene, device=HOST), tmp_path / "f64.npz")


def test_float32_checkpoint_resumed_in_the_default_precision_says_how(tmp_path):
    """A checkpoint written in float32 (as every run was before "mixed" became the default) and
    resumed with a scene that gives no precision is refused, and the message says how to resume it."""
    from polydem.checkpoint import CheckpointError
    from polydem.scene import Scene

    assert Scene().precision == "mixed"
    scene = stack()
    assert scene.precision == "mixed"
    scene.precision = "float32"
    sim = polydem.Simulation(scene, device=HOST)
    sim.step(10)
    save_checkpoint(sim, tmp_path / "f32.npz")
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(polydem.Simulation(stack(), device=HOST), tmp_path / "f32.npz")
    message = str(err.value)
    for words in (
        "simulation.precision differs: checkpoint 'float32', scene 'mixed'",
        'add precision = "float32" to the scene\'s [simulation] table',
        'Scene(precision="float32")',
        "--precision float32",
    ):
        assert words in message, message
    resumed = polydem.Simulation(scene, device=HOST)
    load_checkpoint(resumed, tmp_path / "f32.npz")
    assert resumed.steps_done == 10


# ---------------------------------------------------------------------- the pair list a checkpoint keeps


def test_pairs_with_history_keeps_the_pairs_that_carry_one():
    from polydem.checkpoint import pairs_with_history

    key = np.array([7, 3, 9, 3, 12, 20], dtype=np.int64)
    xi = np.zeros((6, 3), np.float32)
    turn = np.zeros(6, np.float32)
    xi[0, 1] = 1e-6  # a spring
    turn[2] = 2e-9  # a turning volume
    xi[4, 2] = -0.0  # the sign of a zero is carried on by the run
    turn[1] = turn[3] = 5e-9  # the same pair twice
    got = pairs_with_history({"pair_key": key, "pair_xi": xi, "pair_turn": turn})
    np.testing.assert_array_equal(got["pair_key"], [3, 7, 9, 12])
    np.testing.assert_array_equal(got["pair_turn"], turn[[1, 0, 2, 4]])
    np.testing.assert_array_equal(got["pair_xi"], xi[[1, 0, 2, 4]])
    assert np.signbit(got["pair_xi"][3, 2]) and got["pair_key"].dtype == np.int64
    # Without friction there are no springs: the turning volumes decide.
    none = pairs_with_history({"pair_key": key, "pair_xi": np.zeros((0, 3), np.float32), "pair_turn": turn})
    np.testing.assert_array_equal(none["pair_key"], [3, 9])
    assert none["pair_xi"].shape == (0, 3)


def test_checkpoint_keeps_only_pairs_with_history_and_resumes_the_same(tmp_path):
    """Before: a checkpoint held every candidate pair of the broad phase, most of them out of contact with a
    zero history, so a decomposed run (whose ranks list other candidates) wrote other pair lists than one
    process. Now only the pairs with a history, and resuming is still the unbroken run bit for bit."""
    scene = stack()
    scene.add_body("cube", "stone", position=(0.025, 0.0, 0.0102))  # beside the bottom cube, 5 mm off: a candidate
    sim = polydem.Simulation(scene, device=HOST)
    sim.step(300)
    hist = sim.current_contacts.history_numpy()
    live = np.any(hist["pair_xi"] != 0.0, axis=1) | (hist["pair_turn"] != 0.0)
    assert 3 <= live.sum() < len(hist["pair_key"])  # contacts, and candidates out of contact
    save_checkpoint(sim, tmp_path / "ck.npz")
    with np.load(tmp_path / "ck.npz") as data:
        np.testing.assert_array_equal(data["pair_key"], hist["pair_key"][live])
        np.testing.assert_array_equal(data["pair_xi"], hist["pair_xi"][live])
        np.testing.assert_array_equal(data["pair_turn"], hist["pair_turn"][live])
    resumed = polydem.Simulation(scene, device=HOST)
    load_checkpoint(resumed, tmp_path / "ck.npz")
    sim.step(500)
    resumed.step(500)
    a, b = sim.state(), resumed.state()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    c, d = sim.contacts(), resumed.contacts()
    for key in c:
        np.testing.assert_array_equal(c[key], d[key], err_msg=key)
