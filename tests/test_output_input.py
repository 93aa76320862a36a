"""Bad input to the outputs: pictures too large for the memory, a USD file drawn with another scene's
shapes, a VTK frame without contacts, and bad arguments to polydem.analysis (CPU)."""

import json
import math

import numpy as np
import pytest
from cli_helpers import run, write_scene

import polydem
from polydem import picture_memory
from polydem.analysis import angle_of_repose, discharge_rate, fit_beverloo
from polydem.picture_memory import PictureSizeError, check_picture_size, picture_bytes

GB = 10**9

# 6 cubes in an open box of fixed slabs, 30 steps: the run's outputs in about a second.
SMALL = """\
[simulation]
name = "small"
dt = "auto"
steps = 30

[materials.stone]
density = 2500.0
law = "hertz"
k = 1.0e8
restitution = 0.4
friction = 0.5

[shapes.cube]
type = "box"
size = 0.02

[[walls]]
type = "box"
center = [0.0, 0.0, 0.04]
inner_size = [0.16, 0.16, 0.08]
wall_thickness = 0.01
material = "stone"

[[emitters]]
shape = "cube"
material = "stone"
count = 6
region = { min = [-0.08, -0.08, 0.0], max = [0.08, 0.08, 0.08] }
seed = 1

[output]
fps = 2000
usd = "small.usda"
"""


def one_line_error(err, *words):
    """The command's stderr is one 'polydem: error:' line holding every word."""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("polydem: error: "), err
    assert "Traceback" not in err
    for word in words:
        assert word in lines[0], (word, lines[0])
    return lines[0]


@pytest.fixture
def memory(monkeypatch):
    """This machine with 8 GB available, whatever it has: the limits below do not depend on the host."""
    monkeypatch.setattr(picture_memory, "host_memory_available", lambda: 8 * GB)


# ------------------------------------------------------------------ pictures and memory


def test_picture_bytes_counts_every_buffer_of_the_ray_caster():
    # CPU: colour (12), depth (4) and hit (4) per ray in host memory, and the picture's own 40 per pixel.
    assert picture_bytes(800, 600) == (800 * 600 * (20 + 40), 0)
    assert picture_bytes(800, 600, 3) == (800 * 600 * (9 * 20 + 40), 0)
    # GPU: the buffers on the device, the colour back on the host.
    assert picture_bytes(800, 600, 2, gpu=True) == (800 * 600 * (4 * 12 + 40), 800 * 600 * 4 * 20)
    assert picture_bytes(10, 10, layers=True) == (100 * (20 + 65), 0)


def test_check_picture_size_names_the_memory_and_the_largest_that_fits():
    with pytest.raises(PictureSizeError) as info:
        check_picture_size(100000, 100000, host_available=8 * GB)
    exc = info.value
    assert isinstance(exc, ValueError) and exc.needed == 600 * GB and exc.available == 8 * GB
    assert str(exc).startswith("a 100000 x 100000 picture needs about 600 GB of memory, more than the 8 GB available")
    w, h = exc.largest
    check_picture_size(w, h, host_available=8 * GB)  # the size it suggests fits
    with pytest.raises(PictureSizeError):
        check_picture_size(int(w * 1.02) + 1, int(h * 1.02) + 1, host_available=8 * GB)
    with pytest.raises(PictureSizeError, match="GPU memory of cuda:0") as info:
        check_picture_size(800, 600, 100, gpu=True, host_available=10**15, gpu_available=80 * GB, gpu_name="cuda:0")
    s = info.value.largest_supersample
    check_picture_size(800, 600, s, gpu=True, host_available=10**15, gpu_available=80 * GB)
    with pytest.raises(PictureSizeError):
        check_picture_size(800, 600, s + 1, gpu=True, host_available=10**15, gpu_available=80 * GB)
    # A side longer than a Warp array's int32 byte strides allow, whatever the memory.
    with pytest.raises(PictureSizeError, match="a side over"):
        check_picture_size(200_000_000, 1, host_available=10**18)


def test_host_memory_available_is_a_positive_number_of_bytes():
    room = picture_memory.host_memory_available()
    assert room is None or room > 0


def test_run_refuses_a_picture_size_beyond_the_memory_before_the_run(tmp_path, capsys, memory):
    scene = write_scene(tmp_path, SMALL, "small.toml")
    out_dir = tmp_path / "out"
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "--picture-size", "100000x100000"], capsys)
    assert code == 2 and out == ""
    one_line_error(err, "--picture-size", "600 GB", "8 GB available", "give a smaller --picture-size")
    assert not out_dir.exists()  # nothing ran, nothing was written
    code, _, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "--picture-size", "30000x30000"], capsys)
    assert code == 2
    one_line_error(err, "--picture-size", "54 GB")


def test_a_picture_that_fails_at_the_end_loses_only_itself(tmp_path, capsys, monkeypatch):
    """Warp's failed allocation at the last picture: the summary, the USD file and the checkpoint are written."""
    import polydem.render

    def no_memory(*args, **kwargs):
        raise RuntimeError("Failed to allocate 120000000000 bytes on device 'cpu'")

    monkeypatch.setattr(polydem.render, "launch_raycast", no_memory)
    scene = write_scene(tmp_path, SMALL, "small.toml")
    out_dir = tmp_path / "out"
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir], capsys)
    assert code == 1 and "Traceback" not in err
    line = [x for x in err.splitlines() if x.startswith("polydem: error:")]
    assert line == ["polydem: error: cannot draw the picture pictures/last.png: RuntimeError: Failed to allocate "
                    "120000000000 bytes on device 'cpu'"]  # fmt: skip
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["steps"] == 30 and summary["outputs"]["pictures"] == []
    assert "pictures/last.png" in summary["not_written"][0]
    assert (out_dir / "small.usda").is_file() and (out_dir / "checkpoints" / "final.npz").is_file()
    assert not (out_dir / "pictures" / "last.png").exists()


def test_a_picture_refused_at_the_end_loses_only_itself(tmp_path, capsys, monkeypatch):
    """The memory checked before the run is gone at its end (the run took it): the picture is refused, not drawn."""
    calls = []

    def shrinking():
        calls.append(1)
        return 8 * GB if len(calls) == 1 else 10**6

    monkeypatch.setattr(picture_memory, "host_memory_available", shrinking)
    scene = write_scene(tmp_path, SMALL, "small.toml")
    out_dir = tmp_path / "out"
    code, _, err = run(["run", scene, "--device", "cpu", "--out", out_dir], capsys)
    assert code == 1 and "Traceback" not in err and len(calls) >= 2
    assert "polydem: error: cannot draw the picture pictures/last.png: a 800 x 600 picture needs about 28.8 MB" in err
    assert "give a smaller --picture-size" in err
    summary = json.loads((out_dir / "summary.json").read_text())
    assert summary["outputs"]["pictures"] == [] and (out_dir / "small.usda").is_file()


@pytest.mark.parametrize(
    ("options", "key", "words"),
    [
        # 800 x 600 x 28^2 rays take 20 bytes each and the picture 40 bytes per pixel: 7.55 GB of the 8.
        (["--supersample", "100"], "--supersample", ["96 GB", "8 GB available", "give --supersample 28 or less"]),
        (
            ["--width", "100000", "--height", "100000"],
            "--width/--height",
            ["600 GB", "give a smaller --width/--height"],
        ),
        (
            ["--width", "100000", "--height", "100000", "--supersample", "3"],
            "--width/--height",
            ["with --supersample 1"],
        ),
    ],
)
def test_render_refuses_a_picture_beyond_the_memory(tmp_path, capsys, memory, options, key, words):
    scene = write_scene(tmp_path, SMALL, "small.toml")
    png = tmp_path / "x.png"
    code, out, err = run(["render", scene, "--out", png, "--device", "cpu", *options], capsys)
    assert code == 2 and out == "" and not png.exists()
    one_line_error(err, f"error: {key}: ", *words)


def test_render_library_refuses_before_allocating(monkeypatch, memory):
    import polydem.render as render

    def never(*args, **kwargs):
        raise AssertionError("the ray caster ran")

    monkeypatch.setattr(render, "launch_raycast", never)
    cube = polydem.ConvexShape.box(0.1)
    args = ([[0, 0, 0]], [[0, 0, 0, 1]], [0], [cube])
    with pytest.raises(PictureSizeError, match="100000 x 100000 picture needs about 600 GB"):
        render.render(*args, width=100000, height=100000, device="cpu")
    with pytest.raises(ValueError, match="100 x 100 rays per pixel"):
        render.render(*args, width=800, height=600, supersample=100, device="cpu")
    with pytest.raises(ValueError, match="about 850 GB"):
        render.render_layers(*args, width=100000, height=100000, device="cpu")
    for bad in (0, -1, 2.5, True, "2"):
        with pytest.raises((ValueError, TypeError), match="supersample"):
            render.render(*args, width=8, height=6, supersample=bad, device="cpu")
    for w, h in ((0, 6), (8, -1)):
        with pytest.raises(ValueError, match="width and height must be positive"):
            render.render(*args, width=w, height=h, device="cpu")


@pytest.mark.parametrize(
    ("options", "words"),
    [
        (["--supersample", "0"], ["--supersample", "at least 1 ray per pixel side"]),
        (["--supersample", "2.5"], ["--supersample", "whole number"]),
        (["--width", "-3"], ["--width", "at least 1 pixel"]),
        (["--height", "nan"], ["--height", "whole number"]),
        (["--elevation", "91"], ["--elevation", "from -90 to 90"]),
        (["--azimuth", "inf"], ["--azimuth", "finite"]),
    ],
)
def test_render_options_that_are_not_numbers_of_the_range(tmp_path, capsys, options, words):
    scene = write_scene(tmp_path, SMALL, "small.toml")
    code, out, err = run(["render", scene, "--out", tmp_path / "x.png", *options], capsys)
    assert code == 2 and out == ""
    one_line_error(err, *words)


@pytest.mark.parametrize("size", ["0x600", "800x", "800x-1", "1e3x600", "big"])
def test_picture_size_that_is_not_a_size(tmp_path, capsys, size):
    scene = write_scene(tmp_path, SMALL, "small.toml")
    code, _, err = run(["run", scene, "--out", tmp_path / "out", f"--picture-size={size}"], capsys)
    assert code == 2
    one_line_error(err, "--picture-size", "WIDTHxHEIGHT")
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------ USD: the scene's shapes

OTHER_SHAPES = ('[shapes.cube]\ntype = "box"\nsize = 0.02', '[shapes.cube]\ntype = "tetrahedron"\nedge = 0.028')


def write_usd(tmp_path, scene_path, name="run.usda"):
    """A USD file of the scene at ``scene_path`` (its initial poses, two frames), as polydem run writes it."""
    from polydem.usd import UsdRecorder

    scene = polydem.Scene.from_toml(scene_path)
    path = tmp_path / name
    with UsdRecorder(path, scene, fps=10) as rec:
        rec.set_metadata(scene_file=str(scene_path.resolve()))
        rec.record(0.0, scene.body_position, scene.body_orientation)
        rec.record(0.1, scene.body_position, scene.body_orientation)
    return path


def test_render_refuses_a_usd_file_with_another_scenes_shapes(tmp_path, capsys):
    scene = write_scene(tmp_path, SMALL, "small.toml")
    other = write_scene(tmp_path, SMALL, "other.toml", replace=[OTHER_SHAPES])
    assert polydem.Scene.from_toml(other).num_bodies == polydem.Scene.from_toml(scene).num_bodies
    usd = write_usd(tmp_path, scene)
    png = tmp_path / "x.png"
    size = ["--width", "32", "--height", "24", "--device", "cpu"]
    code, out, err = run(["render", usd, "--scene", other, "--out", png, *size], capsys)
    assert code == 2 and out == "" and not png.exists()
    one_line_error(err, f"{usd}: --scene: ", "other shapes", "--scene SCENE")
    code, out, err = run(["render", usd, "--scene", scene, "--out", png, *size], capsys)
    assert code == 0 and err == "" and png.is_file()
    code, out, err = run(["render", usd, "--out", png, *size], capsys)  # the scene file it records
    assert code == 0 and err == ""


def test_render_refuses_a_usd_file_whose_scene_file_changed_since(tmp_path, capsys):
    scene = write_scene(tmp_path, SMALL, "small.toml")
    usd = write_usd(tmp_path, scene)
    write_scene(tmp_path, SMALL, "small.toml", replace=[OTHER_SHAPES])
    code, _, err = run(["render", usd, "--out", tmp_path / "x.png", "--width", "32", "--height", "24"], capsys)
    assert code == 2
    one_line_error(err, "have changed since", "--scene SCENE")


def test_render_warns_about_a_usd_file_without_a_record_of_its_shapes(tmp_path, capsys):
    from pxr import Sdf

    scene = write_scene(tmp_path, SMALL, "small.toml")
    usd = write_usd(tmp_path, scene)
    layer = Sdf.Layer.FindOrOpen(str(usd))
    data = dict(layer.customLayerData)
    del data["polydem:shapes_sha256"]  # as polydem wrote before it recorded the shapes
    layer.customLayerData = data
    layer.Save()
    del layer
    png = tmp_path / "x.png"
    code, out, err = run(["render", usd, "--scene", scene, "--out", png, "--width", "32", "--height", "24"], capsys)
    assert code == 0 and png.is_file() and "wrote" in out
    assert err.startswith("polydem: warning: ") and len(err.splitlines()) == 1
    assert "older polydem" in err and "cannot be checked" in err


def test_shapes_digest_sees_the_shapes_not_their_listing():
    from polydem.usd import shapes_digest

    def scene_of(shapes, body_shape):
        scene = polydem.Scene(gravity=(0, 0, 0), dt=1e-4)
        scene.add_material("m", density=1000, law="hertz", k=1e8, restitution=0.5, friction=0.3)
        for k, shape in enumerate(shapes):
            scene.add_shape(f"s{k}", shape)
        for i, s in enumerate(body_shape):
            scene.add_body(f"s{s}", "m", position=(0.1 * i, 0, 0))
        return scene

    box, rock = polydem.ConvexShape.box(0.02, 0.015, 0.01), polydem.ConvexShape.rock(n_points=12, size=0.1, seed=1)
    reference = shapes_digest(scene_of([box, rock], [0, 1, 0]))
    assert len(reference) == 64 and reference == shapes_digest(scene_of([box, rock], [0, 1, 0]))
    # The same shapes from their vertices in another order: other vertex and face lists, and the rock's
    # body frame from a hull summed in another order (last bits).
    rng = np.random.default_rng(0)
    shuffled = [polydem.ConvexShape.from_points(rng.permutation(np.asarray(s.vertices))) for s in (box, rock)]
    assert not np.array_equal(shuffled[0].vertices, box.vertices)
    assert shapes_digest(scene_of(shuffled, [0, 1, 0])) == reference
    assert shapes_digest(scene_of([polydem.ConvexShape.box(0.02, 0.015, 0.0101), rock], [0, 1, 0])) != reference
    assert shapes_digest(scene_of([box, rock], [1, 0, 0])) != reference  # other bodies of each shape
    assert shapes_digest(scene_of([rock, box], [1, 0, 1])) != reference  # shape indices: the colours


# ------------------------------------------------------------------ VTK: a frame without contacts


@pytest.mark.parametrize("average", [None, {}])
def test_vtk_frame_without_contacts_reads_back(tmp_path, average):
    meshio = pytest.importorskip("meshio")
    from polydem.vtk import VtkWriter

    scene = polydem.Scene.from_toml(write_scene(tmp_path, SMALL, "small.toml"))
    sim = polydem.Simulation(scene, device="cpu")
    contacts = sim.contacts()
    assert len(contacts["volume"]) == 0  # the emitter leaves the bodies apart
    with VtkWriter(tmp_path / "vtk", scene) as vtk:
        vtk.record(0.0, sim.state(), contacts, average=average)
    mesh = meshio.read(tmp_path / "vtk" / "contacts" / "contacts_000000.vtu")
    assert [b.type for b in mesh.cells] == ["vertex"] and len(mesh.points) == 1
    np.testing.assert_array_equal(mesh.points[0], np.float32(sim.state()["body_position"][0]))
    cells = {key: np.concatenate(v) for key, v in mesh.cell_data.items()}
    assert cells["body_a"].tolist() == cells["body_b"].tolist() == cells["wall"].tolist() == [-1]
    for key in ("normal_force_magnitude", "force", "overlap_volume", "tangential_force"):
        assert not np.any(cells[key]), key
    assert ("mean_force" in cells) == (average is not None)
    if average is not None:
        assert cells["current"].tolist() == [0] and not np.any(cells["mean_force"])


# ------------------------------------------------------------------ polydem.analysis


T = np.linspace(0.0, 1.0, 50)
D = np.array([0.03, 0.04, 0.05, 0.06, 0.07])
W = 500.0 * (D - 1.5 * 0.005) ** 2.5
HEAP = np.random.default_rng(0).random((100, 3))
NAN = math.nan


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: discharge_rate([], []), "at least 3 samples"),
        (lambda: discharge_rate(np.ones((3, 3)), np.ones((3, 3))), "1-D of one length"),
        (lambda: discharge_rate(T, T[:-1]), "1-D of one length"),
        (lambda: discharge_rate(np.where(T > 0.5, NAN, T), 2 * T), "times must be finite, got nan at flat index 25"),
        (lambda: discharge_rate(T, np.r_[2 * T[:-1], np.inf]), "discharged must be finite, got inf"),
        (lambda: discharge_rate(np.zeros(50), 2 * T), "times must increase"),
        (lambda: discharge_rate(T[::-1], 2 * T), "times must increase"),
        (lambda: discharge_rate(T, 2 * T, lo=NAN), "lo must be a finite number"),
        (lambda: discharge_rate(T, 2 * T, lo=0.8, hi=0.2), "need 0 <= lo < hi <= 1"),
        (lambda: discharge_rate("abc", "abd"), "times must be an array of numbers"),
        (lambda: discharge_rate(None, None), "times must be an array of numbers"),
        (lambda: discharge_rate([[1, 2], [3]], [1, 2]), "ragged"),
        (lambda: discharge_rate(T + 1j, T), "real numbers"),
        (lambda: fit_beverloo([], [], 0.005, 2.5), "at least 3 different orifice sizes"),
        (lambda: fit_beverloo(D, np.r_[W[:-1], NAN], 0.005, 2.5), "W must be finite"),
        (lambda: fit_beverloo(np.r_[D[:-1], NAN], W, 0.005, 2.5), "D must be finite"),
        (lambda: fit_beverloo(D, np.r_[W[:-1], NAN], 0.005), "W must be finite"),
        (lambda: fit_beverloo(D, W, NAN, 2.5), "d (the grain size) must be a finite number > 0"),
        (lambda: fit_beverloo(D, W, 0.0, 2.5), "d (the grain size) must be a finite number > 0"),
        (lambda: fit_beverloo(D, W, 0.005, 0.0), "n (the exponent) must be a finite number > 0"),
        (lambda: fit_beverloo(D, W, 0.005, NAN), "n (the exponent)"),
        (lambda: fit_beverloo(-D, W, 0.005, 2.5), "orifice size D must be positive"),
        (lambda: fit_beverloo(np.full(5, 0.05), W, 0.005, 2.5), "3 different orifice sizes to fit C, k, got 1"),
        (lambda: fit_beverloo(np.full(5, 0.05), W, 0.005), "4 different orifice sizes to fit C, k and n, got 1"),
        (lambda: fit_beverloo(np.ones((2, 3)), np.ones((2, 3)), 0.005), "1-D of one length"),
        (lambda: angle_of_repose(np.zeros((0, 3)), 0.01), "N >= 20"),
        (lambda: angle_of_repose(np.zeros((30, 2)), 0.01), "(N, 3)"),
        (lambda: angle_of_repose(np.where(HEAP > 0.5, NAN, HEAP), 0.05), "positions must be finite"),
        (lambda: angle_of_repose(np.where(HEAP > 0.9, np.inf, HEAP), 0.05), "positions must be finite"),
        (lambda: angle_of_repose(HEAP, 0.0), "grain_size must be a finite number > 0"),
        (lambda: angle_of_repose(HEAP, NAN), "grain_size must be a finite number > 0"),
        (lambda: angle_of_repose(HEAP, -0.1), "grain_size must be a finite number > 0"),
        (lambda: angle_of_repose(HEAP, 1e-300), "too small for a heap"),
        (lambda: angle_of_repose(HEAP, 0.05, bins=0), "bins must be a whole number >= 1"),
        (lambda: angle_of_repose(HEAP, 0.05, bins=2.5), "bins must be a whole number >= 1"),
        (lambda: angle_of_repose(HEAP, 0.05, flank=(0.8, 0.2)), "flank must be (start, end)"),
        (lambda: angle_of_repose(HEAP, 0.05, flank=(NAN, 0.2)), "flank must be a finite number"),
        (lambda: angle_of_repose(HEAP, 0.05, axis=(1, 2, 3)), "axis must be the heap's (x, y)"),
        (lambda: angle_of_repose(HEAP, 0.05, axis=(NAN, 0)), "axis must be finite"),
        (lambda: angle_of_repose(HEAP, 0.05, floor=NAN), "floor must be a finite number"),
        (lambda: angle_of_repose("abc", 0.05), "positions must be an array of numbers"),
    ],
)
def test_analysis_says_what_is_wrong_with_its_arguments(call, message):
    with pytest.raises(ValueError) as info:
        call()
    assert type(info.value) is ValueError  # not a LinAlgError, OverflowError or ZeroDivisionError
    text = str(info.value)
    assert message in text and "\n" not in text, text
