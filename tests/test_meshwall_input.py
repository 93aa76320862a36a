"""Mesh-wall input that used to be accepted and then fail in a run (issue 24): each is refused by the scene's
checks (SceneError naming the key and the fix), warned about (SceneWarning), or made fast."""

import time
import warnings

import numpy as np
import pytest
import trimesh
from cli_helpers import run, write_scene

from polydem import ConvexShape, Scene, SceneError, Simulation
from polydem.scene import SceneWarning

CUBE = 0.02


def floor(n=4, size=1.0):
    """A square floor z = 0 of 2 n^2 triangles facing +z."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    x, y = np.meshgrid(xs, xs, indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return v, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


def scene(precision="float64"):
    sc = Scene(gravity=(0.0, 0.0, -9.81), dt="auto", precision=precision)
    sc.add_material("m", density=2500.0, k=1.0e8, restitution=0.5, friction=0.0, law="hertz")
    sc.add_shape("cube", ConvexShape.box(CUBE))
    return sc


def validate(sc):
    """``sc.validate()``; returns the SceneWarnings' messages."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sc.validate()
    return [str(w.message) for w in caught if issubclass(w.category, SceneWarning)]


def box(extents, center=(0.0, 0.0, 0.0)):
    m = trimesh.creation.box(extents=extents)
    m.apply_translation(center)
    return m


# ---------------------------------------------------------------------- row 1: grains in the solid


def test_grain_behind_a_flipped_floor_is_refused():
    """The floor's triangles face down, so its solid lies above it, where the cube sits: refused, naming the
    body, the triangle and the depth, with the hint to flip the normals (it was thrown out at 38.8 m/s)."""
    sc = scene()
    sc.add_mesh_wall(floor(), "m", flip_normals=True)
    sc.add_body("cube", "m", position=(0.01, 0.02, 0.5 * CUBE + 1e-4))
    with pytest.raises(SceneError) as err:
        sc.validate()
    assert err.value.key == "bodies[0].position"
    msg = err.value.message
    assert msg.startswith("body 0 (shape 'cube', free) starts 0.0201 m behind triangle ")
    assert "of the mesh wall mesh_walls[0] (wholly)" in msg
    assert "set flip_normals = true (mesh_walls[0].flip_normals)" in msg


@pytest.mark.parametrize("size", [0.05, 0.1])
def test_grain_inside_a_closed_box_mesh_is_refused(size):
    """A cube inside a closed box mesh facing out (solid inside): within the cells' reach (the 5 cm box) or
    past it (the 10 cm box, by the winding number of the closed surface)."""
    sc = scene()
    sc.add_mesh_wall(box([size] * 3), "m")
    sc.add_body("cube", "m", position=(0.001, 0.002, 0.003))
    with pytest.raises(SceneError) as err:
        sc.validate()
    assert err.value.key == "bodies[0].position"
    if size == 0.05:
        assert (
            "m behind triangle" in err.value.message
            and "% of its thickness along the triangle's normal" in err.value.message
        )
    else:
        assert "or more inside the closed mesh wall mesh_walls[0]" in err.value.message
    assert "flip_normals = true" in err.value.message


def test_grain_slightly_in_a_mesh_warns_and_runs(device):
    """A cube 1 mm into the floor mesh (5% of its thickness) is pushed out at the start: a warning, as for a
    plane wall, and the run goes on without throwing it far."""
    sc = scene()
    sc.add_mesh_wall(floor(), "m")
    sc.add_body("cube", "m", position=(0.01, 0.02, 0.5 * CUBE - 1e-3))
    found = validate(sc)
    assert len(found) == 1
    assert "body 0 (shape 'cube', free) 0.001 m behind triangle " in found[0] and "(5.0%)" in found[0]
    sim = Simulation(sc, device=device)
    sim.step(200)
    assert np.linalg.norm(sim.state()["body_velocity"][0]) < 2.0


def test_grain_resting_on_a_mesh_and_a_ridge_is_accepted():
    """A cube resting on a floor mesh (0.1 um in) and one over a box mesh's edge: nothing to say."""
    sc = scene()
    sc.add_mesh_wall(floor(), "m")
    sc.add_mesh_wall(box([0.1, 0.1, 0.1], (0.3, 0.0, 0.05)), "m")
    sc.add_body("cube", "m", position=(0.01, 0.02, 0.5 * CUBE - 1e-7))
    sc.add_body(
        "cube",
        "m",
        position=(0.3, 0.0, 0.1 + 0.5 * CUBE * np.sqrt(2.0) + 1e-4),
        orientation=(0.0, 0.3826834, 0.0, 0.9238795),
    )
    assert validate(sc) == []


def test_mesh_corner_in_a_grain_is_found():
    """A box mesh's corner poking into a big grain, no grain vertex in the box's cells: the corner's depth."""
    sc = scene()
    sc.add_shape("slab", ConvexShape.box(0.3, 0.3, 0.05))
    sc.add_mesh_wall(box([0.1, 0.1, 0.1]), "m", thickness=0.02)
    # The slab's lower face 3 mm below the box's top corners, turned so that no slab vertex is over the box.
    sc.add_body("slab", "m", position=(0.0, 0.0, 0.05 + 0.025 - 0.003), orientation=(0.0, 0.0, 0.3826834, 0.9238795))
    found = validate(sc)
    assert len(found) == 1 and "0.003 m onto vertex " in found[0] and "mesh_walls[0], which pokes into it" in found[0]


def test_default_thickness_over_half_a_thin_closed_wall_warns():
    """A plate 5 cm thick as a closed mesh, with the default thickness (the cube's diameter, 3.5 cm): the cells
    behind its top and bottom overlap. A thinner given thickness, or a cube-shaped box (whose cells stop at
    its centre whatever their depth), says nothing."""
    sc = scene()
    sc.add_mesh_wall(box([0.3, 0.3, 0.05]), "m")
    sc.add_body("cube", "m", position=(0.0, 0.0, 0.5))
    found = validate(sc)
    assert len(found) == 1
    assert found[0].startswith("mesh wall mesh_walls[0]: its thickness 0.0346 m (the default: the free bodies'")
    assert "0.05 m through to triangle" in found[0] and "give a thickness below 0.025 m" in found[0]
    for thickness, extents in ((0.02, [0.3, 0.3, 0.05]), (None, [0.05, 0.05, 0.05])):
        sc = scene()
        sc.add_mesh_wall(box(extents), "m", thickness=thickness)
        sc.add_body("cube", "m", position=(0.0, 0.0, 0.5))
        assert validate(sc) == []


def test_scene_file_with_a_grain_in_a_mesh_exits_2(tmp_path, capsys):
    """The command says it in one line and exits 2."""
    v, f = floor()
    trimesh.Trimesh(v, f[:, ::-1], process=False).export(tmp_path / "down.stl")
    path = write_scene(tmp_path, SCENE, replace=[("FLOOR", "down.stl")])
    code, out, err = run(["validate", path], capsys)
    assert code == 2 and out == "" and err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"polydem: error: {path}: bodies[0].position: body 0 (shape 'cube', free) starts ")
    assert "walls[0].flip_normals" in err


SCENE = """
[simulation]
dt = "auto"
steps = 10
[materials.m]
density = 2500.0
law = "hertz"
k = 1.0e8
restitution = 0.5
friction = 0.5
[shapes.cube]
type = "box"
size = 0.02
[[bodies]]
shape = "cube"
material = "m"
position = [0.01, 0.02, 0.0101]
[[walls]]
type = "mesh"
file = "FLOOR"
material = "m"
"""


# ---------------------------------------------------------------------- row 2: large meshes


def test_cells_of_thousands_of_triangles_build_fast():
    """5,120 triangles of a sphere (every cell cut by vertex planes too): 0.15 s of CPU (5 to 14 s before)."""
    from polydem.meshwall import build_cells

    m = trimesh.creation.icosphere(subdivisions=4)
    t0 = time.process_time()
    cells = build_cells(m.vertices, m.faces, 0.03)
    assert time.process_time() - t0 < 1.5
    assert len(cells.cells) == 5120
    # Each cell is its triangle's: the triangle is its front face.
    v, f = cells.vertices, cells.faces
    for k in (0, 1234, 5119):
        c = cells.cells[k]
        corners = v[f[k]] - c.center
        assert np.all(np.abs(corners @ c.face_normals.T - c.face_offsets).min(axis=1) < 1e-12)


def test_set_up_reports_its_progress(monkeypatch, capsys):
    """A callable gets (done, total) after each block; by default a set-up past PROGRESS_AFTER seconds
    prints its progress on stderr."""
    import polydem.meshwall as mw

    m = trimesh.creation.icosphere(subdivisions=3)
    calls = []
    monkeypatch.setattr(mw, "BLOCK", 256)
    mw.build_cells(m.vertices, m.faces, 0.03, progress=lambda done, total: calls.append((done, total)))
    assert calls[-1] == (1280, 1280) and len(calls) == 5
    assert [d for d, _ in calls] == sorted(d for d, _ in calls)
    monkeypatch.setattr(mw, "PROGRESS_AFTER", 0.0)
    mw.build_cells(m.vertices, m.faces, 0.03, label="mesh wall walls[0]")
    err = capsys.readouterr().err
    assert "polydem: mesh wall walls[0]: cells of 256 of 1,280 triangles built" in err


# ---------------------------------------------------------------------- row 3: fast walls


def test_fast_turning_mesh_wall_warns():
    """A floor mesh turning at 1e9 rad/s about its centre: the drum parts' tunnelling warning (its energy grew
    from 15 J to 9.2e8 J in 5 steps); at 1 rad/s nothing."""
    for omega, expected in ((1e9, 1), (1.0, 0)):
        sc = scene()
        sc.add_mesh_wall(floor(), "m", angular_velocity=(0.0, omega, 0.0))
        sc.add_body("cube", "m", position=(0.01, 0.02, 0.5 * CUBE + 1e-3))
        found = validate(sc)
        assert len(found) == expected
    assert found == [] and "moves its farthest point (0.707 m from the pivot) at 7.07e+08 m/s" in validate_spinning()
    assert "lower its angular_velocity (mesh_walls[0].angular_velocity)" in validate_spinning()


def validate_spinning():
    sc = scene()
    sc.add_mesh_wall(floor(), "m", angular_velocity=(0.0, 1e9, 0.0))
    sc.add_body("cube", "m", position=(0.01, 0.02, 0.5 * CUBE + 1e-3))
    return validate(sc)[0]


# ---------------------------------------------------------------------- row 4: thickness and scale


@pytest.mark.parametrize(
    ("option", "key", "fix"),
    [
        ({"thickness": 1e9}, "thickness", "give a thickness from 1.86e-07 m to 1.86e+05 m"),
        ({"scale": 1e9}, "scale", "a scale from 1.86e-07 to 1.86e+05"),
    ],
)
def test_thickness_or_scale_the_cells_cannot_resolve_is_refused(option, key, fix):
    """Validation said OK and the run failed with "the mesh folds back on itself": now the true reason."""
    sc = scene()
    sc.add_mesh_wall(floor(), "m", **option)
    sc.add_body("cube", "m", position=(0.01, 0.02, 0.5 * CUBE + 1e-3))
    with pytest.raises(SceneError) as err:
        sc.validate()
    assert err.value.key == f"mesh_walls[0].{key}"
    assert "times apart" in err.value.message and fix in err.value.message


def test_build_cells_gives_the_true_reason():
    from polydem.meshwall import MeshWallError, build_cells

    v, f = floor()
    with pytest.raises(MeshWallError, match="is over 1e\\+06 times the size of its smallest triangle"):
        build_cells(v, f, 1e9)


def test_scene_file_with_a_huge_thickness_exits_2(tmp_path, capsys):
    v, f = floor()
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "floor.stl")
    path = write_scene(tmp_path, SCENE, replace=[("FLOOR", "floor.stl")])
    path.write_text(path.read_text() + "thickness = 1e9\n")
    code, out, err = run(["validate", path], capsys)
    assert code == 2 and err.count("\n") == 1
    assert err.startswith(f"polydem: error: {path}: walls[0].thickness: the thickness 1e+09 m is over")


# ---------------------------------------------------------------------- row 5: decompose = "components"


def test_components_of_a_non_convex_piece_warn():
    """A torus is one connected piece: "components" takes its hull, as type = "mesh" does, and says so; two
    boxes say nothing."""
    from polydem.compound import CompoundShape

    with pytest.warns(SceneWarning, match=r"piece 0 of 1 of the mesh is not convex: mesh volume .*coacd"):
        CompoundShape.from_mesh(trimesh.creation.torus(0.1, 0.04), name="torus", decompose="components")
    two = trimesh.util.concatenate([box([0.1] * 3), box([0.1] * 3, (0.3, 0.0, 0.0))])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert CompoundShape.from_mesh(two, name="two", decompose="components").num_parts == 2


def test_scene_file_with_a_non_convex_component_warns(tmp_path, capsys):
    trimesh.creation.torus(0.01, 0.004).export(tmp_path / "torus.stl")
    ring = '[shapes.ring]\ntype = "compound"\nfile = "torus.stl"\ndecompose = "components"\n'
    ring += '[[bodies]]\nshape = "ring"\nmaterial = "m"\nposition = [0.2, 0.0, 0.1]\n'
    text = SCENE.replace("[[walls]]", ring + "[[walls]]")
    v, f = floor()
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "floor.stl")
    path = write_scene(tmp_path, text, replace=[("FLOOR", "floor.stl")])
    code, out, err = run(["validate", path], capsys)
    assert code == 0, err
    assert "polydem: warning: compound shape 'ring': piece 0 of 1 of the mesh is not convex" in err
    assert "decompose = 'coacd'" in err


def test_emitter_beside_a_mesh_its_cells_cannot_resolve_is_refused():
    """The emitter keeps its grains clear of a mesh wall's cells, built at the emitter's cell size; a mesh a
    million times smaller than that raised MeshWallError (a traceback from the command) before any check."""
    sc = scene()
    sc.add_mesh_wall(floor(size=1e-9), "m")
    with pytest.raises(SceneError) as err:
        sc.emit("cube", "m", 10, ((-0.1, -0.1, 0.05), (0.1, 0.1, 0.3)))
    assert err.value.key == "mesh_walls[0]"
    assert "times the size of its smallest triangle" in err.value.message


def test_folded_triangles_warn():
    """A floor whose middle vertex is dragged past its neighbours: the triangles turned over fold back onto
    theirs, and the grains that reach one would be pushed the wrong way: a warning names two of them."""
    v, f = floor(4)
    middle = int(np.argmin(np.linalg.norm(v, axis=1)))
    v[middle, 0] = 0.4  # past the vertices at x = 0.25
    sc = scene()
    sc.add_mesh_wall((v, f), "m")
    sc.add_body("cube", "m", position=(-0.3, -0.3, 0.5 * CUBE + 1e-3))
    found = validate(sc)
    assert len(found) == 1 and found[0].startswith("mesh wall mesh_walls[0]: triangles ")
    assert "fold back onto each other" in found[0] and "remesh" in found[0]
    sc = scene()
    sc.add_mesh_wall(floor(4), "m")
    sc.add_body("cube", "m", position=(-0.3, -0.3, 0.5 * CUBE + 1e-3))
    assert validate(sc) == []
