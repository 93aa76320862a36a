"""src/polydem/plots.py on a small run: the energy and packing plots are written, and show something.

matplotlib is in the test extra, so it is imported here unconditionally: a test environment without it
fails instead of skipping (the command line turns a missing or failing matplotlib into a one-line
note, and a run without plots would otherwise pass unnoticed).
"""

import json

import matplotlib
import numpy as np
from cli_helpers import run, write_scene
from PIL import Image
from test_cli import TINY

from polydem import ConvexShape, Scene, Simulation
from polydem.plots import write_measure_plots, write_plots

# No display on CI; set before anything imports pyplot (plots.py asks for Agg too).
matplotlib.use("Agg")

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"

# 12 cubes and tetrahedra thrown into an open box: 400 steps, a frame every 2 ms (about 13 frames).
SMALL = (
    TINY.replace('name = "tiny"', 'name = "small"')
    .replace('usd = "tiny.usda"', 'usd = "small.usda"')
    .replace("checkpoint = { steps = 150 }\n", "")
    .replace("pictures = [1]\n", "pictures = false\n")
)


def assert_drawn(path):
    """A PNG with something on it: axes and labels (dark pixels) and curves (the colour cycle's
    saturated pixels; axes and text are grey), not a blank page or empty axes."""
    data = path.read_bytes()
    assert data[:8] == PNG_SIGNATURE, path
    image = np.asarray(Image.open(path).convert("RGB")).astype(int)
    assert image.shape[0] > 100 and image.shape[1] > 100
    dark = np.count_nonzero(image.sum(axis=2) < 3 * 128)
    assert dark > 0.005 * image.shape[0] * image.shape[1], f"{path.name}: {dark} dark pixels"
    coloured = np.count_nonzero(image.max(axis=2) - image.min(axis=2) > 80)
    assert coloured > 300, f"{path.name}: {coloured} coloured pixels"


def test_a_run_writes_its_plots(tmp_path, capsys, devices):
    scene = write_scene(tmp_path, SMALL, "small.toml")
    out = tmp_path / "out"
    code, stdout, err = run(["run", scene, "--device", devices[0], "--out", out, "-q"], capsys)
    assert code == 0, err
    assert "no plots" not in stdout, stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["outputs"]["plots"] == ["energy.png", "packing.png"]
    for name in ("energy.png", "packing.png"):
        path = out / name
        assert path.is_file() and path.stat().st_size > 5000, name
        assert not (out / f"{name}.tmp").exists()
        assert_drawn(path)
        assert name in stdout  # the closing lines name it


def test_write_plots_of_a_simulation(tmp_path, devices):
    """write_plots from a history recorded off a Simulation (a cube bouncing on a plane), with the packing
    fraction unknown at some frames (None), as a run records it before a pile forms."""
    scene = Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_material("m", density=1000.0, law="hertz", k=1.0e8, restitution=0.5, friction=0.3)
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("cube", "m", position=(0.0, 0.0, 0.08))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    sim = Simulation(scene, devices[0])
    keys = ("kinetic", "contact", "gravity", "dissipated", "total")
    history = {k: [] for k in ("time", *keys, "contacts", "packing_fraction")}
    for frame in range(20):
        sim.step(max(1, int(0.01 / sim.dt)))
        energy = sim.energy()
        history["time"].append(sim.time)
        for k in keys:
            history[k].append(energy[k])
        history["contacts"].append(len(sim.contacts()["volume"]))
        history["packing_fraction"].append(None if frame < 4 else 0.5 + 0.01 * frame)
    assert history["dissipated"][-1] > 0.0  # the cube did land (and bounce)
    paths = write_plots(history, tmp_path / "plots")
    assert [p.name for p in paths] == ["energy.png", "packing.png"]
    for p in paths:
        assert p.parent == tmp_path / "plots"
        assert_drawn(p)
    assert matplotlib.get_backend().lower() == "agg"
    # Fewer than two frames: a note, no files.
    assert "fewer than two" in write_plots({k: v[:1] for k, v in history.items()}, tmp_path / "none")
    assert not (tmp_path / "none").exists()


# Three layers of 10 x 10 cubes stacked face on face in a box that fits them: settled from the first step.
STACK = """\
[simulation]
name = "stack"
dt = "auto"
gravity = [0.0, 0.0, -9.81]
steps = 300

[materials.m]
density = 2500.0
law = "hertz"
k = 1.0e8
restitution = 0.3
friction = 0.5

[shapes.cube]
type = "box"
size = 0.02

[[walls]]
type = "box"
center = [0.0, 0.0, 0.04]
inner_size = [0.2011, 0.2011, 0.08]
material = "m"

[output]
fps = 2000
pictures = false
""" + "".join(
    f'\n[[bodies]]\nshape = "cube"\nmaterial = "m"\nposition = [{x}, {y}, {z}]\n'
    for z in (0.01, 0.03, 0.05)
    for y in (0.0201 * (k - 4.5) for k in range(10))
    for x in (0.0201 * (k - 4.5) for k in range(10))
)


def test_a_settled_run_plots_its_measures(tmp_path, capsys, devices):
    """measures.png: P(f/<f>), the normals' rose, the packing profile and the contact types of the settled
    region, written beside the other plots and named in the summary and the closing lines."""
    scene = write_scene(tmp_path, STACK, "stack.toml")
    out = tmp_path / "out"
    code, stdout, err = run(["run", scene, "--device", devices[0], "--out", out, "-q"], capsys)
    assert code == 0, err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["measures"]["contact_features"]["face-face"] > 0
    assert summary["outputs"]["plots"] == ["energy.png", "packing.png", "measures.png"]
    assert_drawn(out / "measures.png")
    assert "measures.png" in stdout


def test_write_measure_plots_says_why_it_draws_nothing(tmp_path, devices):
    from polydem import measures

    scene = Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_material("m", density=1000.0, law="hertz", k=1.0e8, restitution=0.5, friction=0.3)
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("cube", "m", position=(0.0, 0.0, 0.05))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    sim = Simulation(scene, devices[0])
    sim.step(10)
    grains = measures.Grains.from_simulation(sim)
    box = measures.Box.around(grains)
    note = write_measure_plots(grains, sim.contacts(), box, {}, tmp_path / "m")
    assert note == "no measure plots: no pair contact in the settled region"
    assert not (tmp_path / "m").exists()
