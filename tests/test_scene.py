"""Tests of polydem.scene: building scenes in Python and from TOML, validation and error messages.

Host-only: no Warp kernels run here.
"""

import math
import pickle
import re
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from polydem.scene import (
    KIND_FIXED,
    KIND_FREE,
    KIND_KINEMATIC,
    Body,
    Material,
    PlaneWall,
    Scene,
    SceneError,
    pair_material,
    quat_from_axis_angle,
    quat_to_matrix,
)
from polydem.shapes import ConvexShape

SCENES = Path(__file__).resolve().parent.parent / "scenes"

STEEL = dict(density=7800.0, law="hertz", k=2.0e11, restitution=0.5, friction=0.3)
GLASS = dict(density=2500.0, law="hertz", k=5.0e10, restitution=0.8, friction=0.2)

BASE_TOML = """\
[simulation]
dt = "auto"
gravity = [0.0, 0.0, -9.81]
steps = 100

[materials.steel]
density = 7800.0
law = "hertz"
k = 2.0e11
restitution = 0.5
friction = 0.3

[materials.glass]
density = 2500.0
law = "hertz"
k = 5.0e10
restitution = 0.8
friction = 0.2

[shapes.cube]
type = "box"
size = [0.1, 0.1, 0.1]

[[bodies]]
shape = "cube"
material = "steel"
position = [0.0, 0.0, 0.2]

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "steel"
"""


def basic_scene():
    scene = Scene()
    scene.add_material("steel", **STEEL)
    scene.add_material("glass", **GLASS)
    scene.add_shape("cube", ConvexShape.box(0.1))
    return scene


def write(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def load_error(tmp_path, text) -> SceneError:
    path = write(tmp_path, text)
    with pytest.raises(SceneError) as info:
        Scene.from_toml(path)
    err = info.value
    assert err.file == path, "every error from a scene file must name the file"
    assert str(err).startswith(f"{path}: ")
    return err


# ---------------------------------------------------------------------- building in Python


def test_build_in_python():
    scene = basic_scene()
    i = scene.add_body("cube", "steel", position=(1.0, 2.0, 3.0), velocity=(0.0, 0.0, -1.0))
    j = scene.add_body("cube", "glass", position=(0.0, 0.0, 1.0), angular_velocity=(0.0, 0.0, 2.0), kind="kinematic")
    k = scene.add_body("cube", "steel", kind="fixed")
    plane = scene.add_plane((0, 0, 0), (0, 0, 2.0), "steel")
    assert (i, j, k) == (0, 1, 2)
    assert scene.num_bodies == 3
    assert list(scene.shapes) == ["cube"] and isinstance(scene.shapes["cube"], ConvexShape)
    assert list(scene.materials) == ["steel", "glass"] and isinstance(scene.materials["glass"], Material)
    assert scene.planes == [plane] and plane.normal == (0.0, 0.0, 1.0)
    np.testing.assert_array_equal(scene.body_kind, [KIND_FREE, KIND_KINEMATIC, KIND_FIXED])
    np.testing.assert_array_equal(scene.body_material, [0, 1, 0])
    np.testing.assert_array_equal(scene.body_shape, [0, 0, 0])
    np.testing.assert_allclose(scene.body_position[0], [1, 2, 3])
    np.testing.assert_allclose(scene.body_angular_velocity[1], [0, 0, 2])
    np.testing.assert_allclose(scene.body_mass(), [7.8, 2.5, 7.8])
    np.testing.assert_allclose(scene.body_inertia()[0], 7800.0 * 0.1**5 / 6.0)
    body = scene.body(1)
    assert body == Body("cube", "glass", (0, 0, 1), (0, 0, 0, 1), (0, 0, 0), (0, 0, 2), "kinematic")
    assert scene.validate() is scene
    assert "3 bodies" not in repr(scene) and "bodies=3" in repr(scene)
    assert "1 free, 1 fixed, 1 kinematic" in scene.describe()


def test_body_arrays_are_read_only_views():
    scene = basic_scene()
    scene.add_body("cube", "steel")
    with pytest.raises(ValueError):
        scene.body_position[0, 0] = 1.0
    assert scene.body_shape.dtype == np.int32 and scene.body_kind.dtype == np.int32
    assert scene.body_position.dtype == np.float64 and scene.body_orientation.shape == (1, 4)


def test_add_bodies_is_vectorised_and_fast():
    scene = basic_scene()
    n = 100_000
    rng = np.random.default_rng(1)
    pos = rng.uniform(-1, 1, size=(n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    t0 = time.perf_counter()
    idx = scene.add_bodies("cube", "glass", pos, orientations=q, velocities=(0.0, 0.0, -1.0))
    scene.validate()
    elapsed = time.perf_counter() - t0
    assert elapsed < 1.0, f"add_bodies + validate of {n} bodies took {elapsed:.2f} s"
    np.testing.assert_array_equal(idx, np.arange(n))
    assert scene.num_bodies == n
    assert isinstance(scene.body_position, np.ndarray) and scene.body_position.shape == (n, 3)
    np.testing.assert_allclose(scene.body_position, pos)  # a cube's body frame is its input frame
    np.testing.assert_allclose(scene.body_orientation, q, atol=1e-15)
    np.testing.assert_allclose(scene.body_velocity, np.broadcast_to([0, 0, -1.0], (n, 3)))
    assert np.all(scene.body_material == 1) and np.all(scene.body_kind == KIND_FREE)
    # appending after a bulk add keeps everything
    assert scene.add_body("cube", "steel", position=(5, 5, 5)) == n
    np.testing.assert_allclose(scene.body_position[:n], pos)
    np.testing.assert_allclose(scene.body_position[n], [5, 5, 5])


def test_many_single_adds_grow_storage():
    scene = basic_scene()
    for i in range(100):
        scene.add_body("cube", "steel", position=(i, 0, 0))
    np.testing.assert_allclose(scene.body_position[:, 0], np.arange(100))


def test_pose_is_given_in_the_input_frame():
    # A box's principal axes are sorted by moment, so its body frame is a permutation of the input
    # axes; the user places the box as it was defined and the scene stores the body frame.
    scene = basic_scene()
    box = scene.add_shape("slab", ConvexShape.box(0.5, 0.1, 0.3))
    assert not np.allclose(box.input_rotation, np.eye(3))
    q = quat_from_axis_angle((0, 0, 1), math.pi / 2)  # long edge from x to y
    scene.add_body("slab", "steel", position=(1.0, 2.0, 3.0), orientation=q)
    v = scene.body_vertices(0)
    np.testing.assert_allclose(v.min(axis=0), [1 - 0.05, 2 - 0.25, 3 - 0.15], atol=1e-12)
    np.testing.assert_allclose(v.max(axis=0), [1 + 0.05, 2 + 0.25, 3 + 0.15], atol=1e-12)
    body = scene.body(0)
    np.testing.assert_allclose(body.orientation, q, atol=1e-12)
    np.testing.assert_allclose(body.position, (1, 2, 3), atol=1e-12)
    # body_orientation maps body-frame vertices to world: R_user @ R_input
    np.testing.assert_allclose(
        quat_to_matrix(scene.body_orientation[0]), quat_to_matrix(q) @ box.input_rotation, atol=1e-12
    )


def test_position_of_an_off_centre_shape_is_its_input_origin():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float) + 10.0
    tet = ConvexShape.from_points(pts, name="tet")
    scene = basic_scene()
    scene.add_body(tet, "steel", position=(0, 0, 0))  # a ConvexShape is registered under its name
    assert "tet" in scene.shapes
    np.testing.assert_allclose(scene.body_position[0], pts.mean(axis=0), atol=1e-12)
    v = scene.body_vertices(0)
    for p in pts:  # the mesh appears exactly where its points are
        assert np.min(np.linalg.norm(v - p, axis=1)) < 1e-12
    np.testing.assert_allclose(scene.body(0).position, (0, 0, 0), atol=1e-12)


def test_quaternion_normalised_within_tolerance():
    scene = basic_scene()
    scene.add_body("cube", "steel", orientation=(0, 0, 0, 1 + 5e-7))
    assert np.linalg.norm(scene.body_orientation[0]) == pytest.approx(1.0, abs=1e-15)


def test_box_container():
    scene = basic_scene()
    walls = scene.add_box_container((0, 0, 1.0), (1.0, 2.0, 0.5), "steel")
    assert len(walls) == 5
    assert np.all(scene.body_kind[walls] == KIND_FIXED)
    t = 0.05  # 10% of the smallest inner size
    verts = np.vstack([scene.body_vertices(i) for i in walls])
    np.testing.assert_allclose(verts.min(axis=0), [-0.5 - t, -1.0 - t, 0.75 - t], atol=1e-12)
    np.testing.assert_allclose(verts.max(axis=0), [0.5 + t, 1.0 + t, 1.25], atol=1e-12)
    boxes = [(scene.body_vertices(i).min(axis=0), scene.body_vertices(i).max(axis=0)) for i in walls]
    cavity = (np.array([-0.5, -1.0, 0.75]), np.array([0.5, 1.0, 1.25]))
    for a, (lo, hi) in enumerate(boxes):
        overlap = np.minimum(hi, cavity[1]) - np.maximum(lo, cavity[0])
        assert np.any(overlap <= 1e-12), "a wall reaches into the cavity"
        for lo2, hi2 in boxes[a + 1 :]:
            assert np.any(np.minimum(hi, hi2) - np.maximum(lo, lo2) <= 1e-12), "walls overlap"
    # a closed box has a lid; identical walls share one registered shape
    closed = basic_scene()
    lid = closed.add_box_container((0, 0, 0), (1.0, 1.0, 1.0), "glass", wall_thickness=0.2, open_top=False)
    assert len(lid) == 6
    assert len(closed.shapes) == 1 + 3  # cube + plate + x wall + y wall
    assert closed.body_vertices(lid[-1]).max(axis=0)[2] == pytest.approx(0.7)
    closed.validate()


# ---------------------------------------------------------------------- errors in Python


def test_scene_error_format_and_attributes():
    scene = basic_scene()
    with pytest.raises(SceneError) as info:
        scene.add_body("cube", "stel")
    err = info.value
    assert isinstance(err, ValueError)
    assert err.key == "bodies[0].material" and err.file is None
    assert (
        str(err) == "bodies[0].material: unknown material 'stel'; did you mean 'steel'? Known materials: steel, glass"
    )
    err.file = "scene.toml"
    assert str(err).startswith("scene.toml: bodies[0].material: unknown material 'stel'; did you mean 'steel'?")
    again = pickle.loads(pickle.dumps(err))
    assert (again.key, again.file, str(again)) == (err.key, err.file, str(err))


@pytest.mark.parametrize(
    "kwargs, key, match",
    [
        (dict(shape="cub"), "bodies[0].shape", r"unknown shape 'cub'; did you mean 'cube'\? Known shapes: cube"),
        (
            dict(kind="frozen"),
            "bodies[0].kind",
            r"unknown body kind 'frozen'.*Valid body kinds: free, fixed, kinematic",
        ),
        (dict(orientation=(0, 0, 0, 0)), "bodies[0].orientation", r"is zero; give a unit quaternion"),
        (dict(orientation=(0, 0, 0.17, 0.98)), "bodies[0].orientation", r"not a unit quaternion.*Normalised it is"),
        (dict(orientation=(0, 0, 1)), "bodies[0].orientation", r"expected 4 numbers \[x, y, z, w\], got 3"),
        (dict(position=(0, float("nan"), 0)), "bodies[0].position", r"finite"),
        (dict(position=(0, "a", 0)), "bodies[0].position", r"expected a number at position 1.*got string 'a'"),
        (dict(kind="fixed", velocity=(1, 0, 0)), "bodies[0].velocity", r"fixed body cannot move.*kinematic"),
    ],
)
def test_add_body_errors(kwargs, key, match):
    scene = basic_scene()
    args = dict(shape="cube", material="steel") | kwargs
    with pytest.raises(SceneError, match=match) as info:
        scene.add_body(args.pop("shape"), args.pop("material"), **args)
    assert info.value.key == key
    assert scene.num_bodies == 0, "a rejected body must not be stored"


def test_add_bodies_errors_name_the_row():
    scene = basic_scene()
    q = np.tile([0.0, 0.0, 0.0, 1.0], (10, 1))
    q[7] = [0, 0, 0, 2.0]
    with pytest.raises(SceneError, match="not a unit quaternion") as info:
        scene.add_bodies("cube", "steel", np.zeros((10, 3)), orientations=q)
    assert info.value.key == "bodies[7].orientation"
    pos = np.zeros((4, 3))
    pos[2, 1] = np.inf
    with pytest.raises(SceneError, match="finite") as info:
        scene.add_bodies("cube", "steel", pos)
    assert info.value.key == "bodies[2].position"
    with pytest.raises(SceneError, match=r"expected an array of shape \(4, 4\).*got shape \(3, 4\)"):
        scene.add_bodies("cube", "steel", np.zeros((4, 3)), orientations=np.tile([0.0, 0.0, 0.0, 1.0], (3, 1)))
    with pytest.raises(SceneError, match=r"expected an array of shape \(4, 3\)"):
        scene.add_bodies("cube", "steel", np.zeros((4, 3)), velocities=np.zeros((5, 3)))
    assert scene.num_bodies == 0


def test_plane_errors():
    scene = basic_scene()
    with pytest.raises(SceneError, match=r"normal \[0.0, 0.0, 0.0\] is zero") as info:
        scene.add_plane((0, 0, 0), (0, 0, 0), "steel")
    assert info.value.key == "planes[0].normal"
    with pytest.raises(SceneError, match="did you mean 'glass'") as info:
        scene.add_plane((0, 0, 0), (0, 0, 1), "glas")
    assert info.value.key == "planes[0].material"
    assert PlaneWall((0, 0, 0), (3, 0, 4), "x").normal == (0.6, 0.0, 0.8)


@pytest.mark.parametrize(
    "change, key, match",
    [
        (dict(density=-1.0), "materials.m.density", r"must be positive \(> 0\), got -1 \(density in kg/m\^3"),
        (dict(density="heavy"), "materials.m.density", r"expected a number, got string 'heavy'"),
        (dict(density=True), "materials.m.density", r"expected a number, got boolean true"),
        (dict(k=0.0), "materials.m.k", r"must be positive.*J/m\^4.5"),
        (dict(restitution=0.0), "materials.m.restitution", r"must be in \(0, 1\]"),
        (dict(restitution=1.5), "materials.m.restitution", r"must be in \(0, 1\]"),
        (dict(friction=-0.1), "materials.m.friction", r"must not be negative"),
        (dict(law="hertzian"), "materials.m.law", r"did you mean 'hertz'\?.*Valid contact laws: linear, hertz, power"),
        (dict(law="power"), "materials.m.m", r"needs the exponent m"),
        (dict(law="power", m=0.5), "materials.m.m", r"must be >= 1"),
        (dict(m=2.0), "materials.m.m", r"only used by law = 'power'"),
        (dict(tangential_stiffness=-5.0), "materials.m.tangential_stiffness", r"must be positive"),
        (dict(frictoin=0.3), "materials.m.frictoin", r"unknown key 'frictoin'; did you mean 'friction'\?"),
    ],
)
def test_material_errors(change, key, match):
    scene = Scene()
    with pytest.raises(SceneError, match=match) as info:
        scene.add_material("m", **(STEEL | change))
    assert info.value.key == key


def test_material_missing_property_and_duplicate():
    scene = Scene()
    props = dict(STEEL)
    del props["friction"]
    with pytest.raises(SceneError, match=r"missing required key 'friction' \(Coulomb friction") as info:
        scene.add_material("m", **props)
    assert info.value.key == "materials.m.friction"
    scene.add_material("m", **STEEL)
    with pytest.raises(SceneError, match="already defined"):
        scene.add_material("m", **STEEL)


def test_power_law_material():
    mat = Material(name="p", density=1000.0, law="power", k=1e12, m=2, restitution=1.0, friction=0.0)
    assert mat.exponent == 2.0 and isinstance(mat.m, float)
    assert Material(name="l", **(STEEL | dict(law="linear"))).exponent == 1.0


def test_simulation_settings_errors():
    with pytest.raises(SceneError, match='"auto"') as info:
        Scene(dt="fast")
    assert info.value.key == "simulation.dt"
    with pytest.raises(SceneError, match="must be positive"):
        Scene(dt=-1e-5)
    with pytest.raises(SceneError, match="expected 3 numbers"):
        Scene(gravity=(0, -9.81))
    with pytest.raises(SceneError, match="either steps or duration"):
        Scene(steps=10, duration=1.0)
    with pytest.raises(SceneError, match="expected an integer, got float 2.5"):
        Scene(steps=2.5)
    assert Scene(dt=1e-5, steps=10).dt == 1e-5


def test_validate_errors():
    scene = basic_scene()
    with pytest.raises(SceneError, match="no bodies") as info:
        scene.validate()
    assert info.value.key == "bodies"
    scene.add_material("soft", **(STEEL | dict(law="linear", k=1e6)))
    scene.add_body("cube", "steel")
    with pytest.raises(SceneError, match=r"material 'soft' uses law 'linear'.*must share one contact law") as info:
        scene.validate()
    assert info.value.key == "materials.soft.law"


def test_validate_rejects_free_body_without_volume():
    scene = basic_scene()
    flat = ConvexShape.box(0.1, name="flat")
    flat.volume = 0.0  # a fresh object: stands in for a degenerate shape from elsewhere
    scene.add_shape("flat", flat)
    scene.add_body("flat", "steel", kind="fixed")
    scene.validate()  # fixed bodies need no mass
    scene.add_body("flat", "steel")
    with pytest.raises(SceneError, match="needs a positive volume") as info:
        scene.validate()
    assert info.value.key == "bodies[1].shape"


def test_add_shape_errors():
    scene = basic_scene()
    with pytest.raises(SceneError, match="already registered"):
        scene.add_shape("cube", ConvexShape.box(0.2))
    scene.add_shape("cube", scene.shapes["cube"])  # same object again: fine
    with pytest.raises(SceneError, match="expected a polydem.ConvexShape"):
        scene.add_shape("ball", "sphere")
    empty = Scene()
    empty.add_material("steel", **STEEL)
    with pytest.raises(SceneError, match="no shapes are defined"):
        empty.add_body("cube", "steel")


# ---------------------------------------------------------------------- mixing rule


def test_pair_material_mixing():
    a = Material(name="a", **(STEEL | dict(tangential_stiffness=1e6)))
    b = Material(name="b", **(GLASS | dict(tangential_stiffness=3e6)))
    pm = pair_material(a, b)
    assert pm.k == pytest.approx(2 * 2e11 * 5e10 / (2e11 + 5e10)) == pytest.approx(8e10)
    assert pm.restitution == 0.5 and pm.friction == 0.2
    assert pm.tangential_stiffness == pytest.approx(1.5e6)
    assert pm.law == "hertz" and pm.exponent == 1.5
    same = pair_material(a, a)
    assert same.k == pytest.approx(a.k) and same.tangential_stiffness == pytest.approx(1e6)
    c = Material(name="c", **GLASS)
    assert pair_material(a, c).tangential_stiffness is None
    with pytest.raises(SceneError, match="different contact laws") as info:
        pair_material(a, Material(name="lin", **(STEEL | dict(law="linear"))))
    assert info.value.key == "materials.lin.law"
    p2 = Material(name="p2", **(STEEL | dict(law="power", m=2.0)))
    p3 = Material(name="p3", **(STEEL | dict(law="power", m=3.0)))
    with pytest.raises(SceneError, match="different contact laws"):
        pair_material(p2, p3)


def test_scene_pair_table():
    scene = basic_scene()
    table = scene.pair_table()
    np.testing.assert_allclose(table["k"], [[2e11, 8e10], [8e10, 5e10]])
    np.testing.assert_allclose(table["friction"], [[0.3, 0.2], [0.2, 0.2]])
    np.testing.assert_allclose(table["restitution"], [[0.5, 0.5], [0.5, 0.8]])
    assert np.all(np.isnan(table["tangential_stiffness"]))
    assert table["law"] == "hertz" and table["exponent"] == 1.5
    assert scene.pair_material("steel", "glass").k == pytest.approx(8e10)


# ---------------------------------------------------------------------- scene files


@pytest.mark.parametrize("path", sorted(SCENES.glob("*.toml")), ids=lambda p: p.name)
def test_scene_files_load_and_validate(path):
    scene = Scene.from_toml(path)
    assert scene.num_bodies >= 1 and scene.file == path
    scene.validate()
    assert scene.describe()


def test_shipped_scenes_exist():
    assert {"cube_drop.toml", "incline.toml"} <= {p.name for p in SCENES.glob("*.toml")}


def test_cube_drop_scene():
    scene = Scene.from_toml(SCENES / "cube_drop.toml")
    (plane,) = scene.planes
    assert plane.normal == (0.0, 0.0, 1.0)
    v = scene.body_vertices(0)
    assert v[:, 2].min() == pytest.approx(0.15) and np.ptp(v, axis=0) == pytest.approx([0.1, 0.1, 0.1])
    assert scene.materials["steel"].density == 7800.0


def test_incline_scene():
    scene = Scene.from_toml(SCENES / "incline.toml")
    (plane,) = scene.planes
    n = np.array(plane.normal)
    assert math.degrees(math.acos(n[2])) == pytest.approx(20.0)
    assert scene.pair_material("stone", "stone").friction == 0.5
    assert scene.pair_material("stone", "stone").friction > math.tan(math.radians(20.0))  # the block sticks
    d = scene.body_vertices(0) @ n - np.dot(plane.point, n)
    assert d.min() == pytest.approx(0.0, abs=1e-12)  # touching, not overlapping
    assert np.sum(np.abs(d) < 1e-12) == 4  # a whole face lies on the plane


def test_base_toml_loads(tmp_path):
    scene = Scene.from_toml(write(tmp_path, BASE_TOML))
    assert scene.steps == 100 and scene.duration is None and scene.dt == "auto"
    assert scene.name == "scene" and scene.num_bodies == 1 and len(scene.planes) == 1


def test_toml_all_features(tmp_path):
    obj = tmp_path / "meshes" / "cube.obj"
    obj.parent.mkdir()
    trimesh.creation.box(extents=(1.0, 1.0, 1.0)).export(obj)  # a 1 "mm" cube, scaled by 0.01 below
    text = (
        BASE_TOML.replace("steps = 100", "duration = 0.5\nname = 'all'")
        + """
[shapes.tet]
type = "tetrahedron"
edge = 0.1

[shapes.oct]
type = "octahedron"
edge = 0.1

[shapes.dod]
type = "dodecahedron"
edge = 0.05

[shapes.ico]
type = "icosahedron"
edge = 0.05

[shapes.hex]
type = "prism"
n = 6
radius = 0.05
height = 0.1

[shapes.stone]
type = "rock"
n_points = 12
size = 0.1
seed = 3

[shapes.ball]
type = "sphere"
subdivisions = 1
radius = 0.05

[shapes.mm_cube]
type = "mesh"
file = "meshes/cube.obj"
scale = 0.01

[shapes.wedge]
type = "points"
points = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]

[[bodies]]
shape = "stone"
material = "glass"
position = [1.0, 0.0, 0.5]
rotation = { axis = [0.0, 0.0, 1.0], degrees = 90.0 }
velocity = [0.0, 0.0, -1.0]
angular_velocity = [0.0, 0.0, 3.0]

[[bodies]]
shape = "hex"
material = "steel"
position = [0.0, 1.0, 0.5]
kind = "kinematic"
velocity = [0.1, 0.0, 0.0]

[[walls]]
type = "box"
center = [0.0, 0.0, 1.0]
inner_size = [2.0, 2.0, 1.0]
material = "steel"
wall_thickness = 0.1
open_top = false
"""
    )
    scene = Scene.from_toml(write(tmp_path, text))
    assert scene.duration == 0.5 and scene.name == "all"
    assert set(scene.shapes) >= {"cube", "tet", "oct", "dod", "ico", "hex", "stone", "ball", "mm_cube", "wedge"}
    assert scene.shapes["mm_cube"].volume == pytest.approx(1e-6)
    assert scene.shapes["ico"].num_vertices == 12 and scene.shapes["hex"].num_faces == 8
    assert scene.num_bodies == 3 + 6
    body = scene.body(1)
    np.testing.assert_allclose(body.orientation, quat_from_axis_angle((0, 0, 1), math.pi / 2), atol=1e-15)
    np.testing.assert_allclose(body.position, (1.0, 0.0, 0.5), atol=1e-12)
    assert scene.body(2).kind == "kinematic"
    assert np.all(scene.body_kind[3:] == KIND_FIXED)
    # to_dict / from_dict round trip
    again = Scene.from_dict(scene.to_dict())
    assert again.num_bodies == scene.num_bodies and list(again.shapes) == list(scene.shapes)
    np.testing.assert_allclose(again.body_position, scene.body_position, atol=1e-12)
    np.testing.assert_allclose(again.body_orientation, scene.body_orientation, atol=1e-12)
    np.testing.assert_array_equal(again.body_kind, scene.body_kind)


def test_to_dict_round_trip_of_python_shapes():
    scene = basic_scene()
    scene.add_shape("slab", ConvexShape.box(0.5, 0.1, 0.3))
    q = quat_from_axis_angle((1, 1, 0), 0.7)
    scene.add_body("slab", "glass", position=(0, 0, 1), orientation=q, velocity=(1, 2, 3))
    again = Scene.from_dict(scene.to_dict())
    np.testing.assert_allclose(again.body_vertices(0), scene.body_vertices(0), atol=1e-12)
    np.testing.assert_allclose(again.body_velocity, scene.body_velocity)


def test_missing_file(tmp_path):
    path = tmp_path / "nope.toml"
    with pytest.raises(SceneError, match=r"scene file not found \(looked for '.*nope.toml'\)") as info:
        Scene.from_toml(path)
    assert info.value.file == path and info.value.key is None


def test_toml_syntax_error_has_line(tmp_path):
    err = load_error(tmp_path, "[simulation]\ndt = 'auto'\ngravity = [0, 0, -9.81\nsteps = 3\n")
    assert "invalid TOML syntax" in str(err) and "line 4" in str(err)


@pytest.mark.parametrize(
    "old, new, key, match",
    [
        # unknown keys at every level, with did-you-mean and the valid keys
        ("[simulation]", "[simulaton]", "simulaton", r"did you mean 'simulation'\?.*Valid keys: simulation, "),
        ("steps = 100", "step = 100", "simulation.step", r"unknown key 'step'; did you mean 'steps'\?"),
        ("friction = 0.3", "frction = 0.3", "materials.steel.frction", r"did you mean 'friction'\?"),
        ("size = [0.1, 0.1, 0.1]", "sise = 0.1", "shapes.cube.sise", r"Valid keys for type = 'box': type, size$"),
        (
            "position = [0.0, 0.0, 0.2]",
            "position = [0.0, 0.0, 0.2]\nvelocty = [0.0, 0.0, 0.0]",
            "bodies[0].velocty",
            r"did you mean 'velocity'",
        ),
        (
            "normal = [0.0, 0.0, 1.0]",
            "normal = [0.0, 0.0, 1.0]\nnormals = 1",
            "walls[0].normals",
            r"did you mean 'normal'\?",
        ),
        # unknown names
        (
            'material = "steel"\nposition',
            'material = "stel"\nposition',
            "bodies[0].material",
            r"unknown material 'stel'; did you mean 'steel'\? Known materials: steel, glass",
        ),
        ('shape = "cube"', 'shape = "cueb"', "bodies[0].shape", r"did you mean 'cube'\? Known shapes: cube"),
        ('type = "box"', 'type = "boxx"', "shapes.cube.type", r"unknown shape type 'boxx'; did you mean 'box'\?"),
        ('type = "plane"', 'type = "plain"', "walls[0].type", r"did you mean 'plane'\?"),
        ('law = "hertz"\nk = 2.0e11', 'law = "hertzz"\nk = 2.0e11', "materials.steel.law", r"did you mean 'hertz'"),
        ('dt = "auto"', 'dt = "automatic"', "simulation.dt", r"expected a time step in seconds or \"auto\""),
        # wrong types
        ("density = 7800.0", "density = 'abc'", "materials.steel.density", r"expected a number, got string 'abc'"),
        ("steps = 100", "steps = 1.5", "simulation.steps", r"expected an integer, got float 1.5"),
        ("gravity = [0.0, 0.0, -9.81]", "gravity = -9.81", "simulation.gravity", r"expected an array of 3 numbers"),
        (
            "position = [0.0, 0.0, 0.2]",
            "position = [0.0, 'x', 0.2]",
            "bodies[0].position",
            r"expected a number at position 1 of \[x, y, z\], got string 'x'",
        ),
        ("[[bodies]]", "[bodies]", "bodies", r"expected an array of tables \[\[bodies\]\]"),
        # wrong vector length
        ("position = [0.0, 0.0, 0.2]", "position = [0.0, 0.2]", "bodies[0].position", r"expected 3 numbers .*got 2"),
        ("size = [0.1, 0.1, 0.1]", "size = [0.1, 0.1]", "shapes.cube.size", r"expected 3 numbers \[sx, sy, sz\]"),
        (
            "position = [0.0, 0.0, 0.2]",
            "position = [0.0, 0.0, 0.2]\norientation = [0.0, 0.0, 1.0]",
            "bodies[0].orientation",
            r"expected 4 numbers \[x, y, z, w\], got 3",
        ),
        # negative or zero where positive is required, and other bad values
        ("density = 7800.0", "density = 0.0", "materials.steel.density", r"must be positive \(> 0\), got 0"),
        ("k = 2.0e11", "k = -2.0e11", "materials.steel.k", r"must be positive"),
        ("size = [0.1, 0.1, 0.1]", "size = [0.1, -0.1, 0.1]", "shapes.cube.size", r"must be positive"),
        ("size = [0.1, 0.1, 0.1]", "size = 0", "shapes.cube.size", r"must be positive"),
        ("steps = 100", "steps = 0", "simulation.steps", r"must be an integer >= 1, got 0"),
        ('dt = "auto"', "dt = -0.001", "simulation.dt", r"must be positive"),
        ("normal = [0.0, 0.0, 1.0]", "normal = [0.0, 0.0, 0.0]", "walls[0].normal", r"is zero"),
        (
            "position = [0.0, 0.0, 0.2]",
            "position = [0.0, 0.0, 0.2]\norientation = [0.0, 0.0, 0.5, 0.5]",
            "bodies[0].orientation",
            r"not a unit quaternion",
        ),
        (
            "position = [0.0, 0.0, 0.2]",
            'position = [0.0, 0.0, 0.2]\nkind = "fixd"',
            "bodies[0].kind",
            r"did you mean 'fixed'\?",
        ),
        ("restitution = 0.5", "restitution = 1.2", "materials.steel.restitution", r"must be in \(0, 1\]"),
        # missing required keys and exclusive keys
        (
            'material = "steel"\nposition = [0.0, 0.0, 0.2]',
            'material = "steel"',
            "bodies[0].position",
            r"missing required key 'position'",
        ),
        ("density = 7800.0", "", "materials.steel.density", r"missing required key 'density' \(density in kg/m\^3"),
        ('type = "box"\n', "", "shapes.cube.type", r"missing required key 'type' \(one of box, tetrahedron"),
        (
            "position = [0.0, 0.0, 0.2]",
            "position = [0.0, 0.0, 0.2]\norientation = [0.0, 0.0, 0.0, 1.0]\n"
            "rotation = {axis = [0.0, 0.0, 1.0], degrees = 10.0}",
            "bodies[0].rotation",
            r"not both",
        ),
        (
            "position = [0.0, 0.0, 0.2]",
            "position = [0.0, 0.0, 0.2]\nrotation = {axis = [0.0, 0.0, 1.0], deg = 1.0}",
            "bodies[0].rotation.deg",
            r"did you mean 'degrees'",
        ),
    ],
)
def test_toml_errors(tmp_path, old, new, key, match):
    assert old in BASE_TOML
    err = load_error(tmp_path, BASE_TOML.replace(old, new, 1))
    assert err.key == key, str(err)
    assert re.search(match, err.message), str(err)


def test_toml_missing_mesh_file_is_relative_to_the_scene(tmp_path):
    sub = tmp_path / "scenes"
    sub.mkdir()
    text = BASE_TOML + '\n[shapes.rock]\ntype = "mesh"\nfile = "meshes/rock.obj"\n'
    path = write(sub, text)
    with pytest.raises(SceneError) as info:
        Scene.from_toml(path)
    err = info.value
    assert err.key == "shapes.rock.file" and err.file == path
    assert "mesh file 'meshes/rock.obj' not found" in str(err)
    assert str(sub / "meshes" / "rock.obj") in str(err)


def test_toml_unknown_wall_key_for_type(tmp_path):
    text = BASE_TOML + '\n[[walls]]\ntype = "box"\ncenter = [0, 0, 0]\ninner_size = [1, 1, 1]\nmaterial = "steel"\n'
    text += "normal = [0, 0, 1]\n"
    err = load_error(tmp_path, text)
    assert err.key == "walls[1].normal"
    assert "Valid keys for type = 'box': type, center, inner_size, material, wall_thickness, open_top" in err.message


def test_toml_degenerate_shape(tmp_path):
    text = BASE_TOML + '\n[shapes.flat]\ntype = "points"\npoints = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]\n'
    err = load_error(tmp_path, text)
    assert err.key == "shapes.flat" and "cannot build the points shape" in err.message


def test_toml_mixed_laws(tmp_path):
    err = load_error(tmp_path, BASE_TOML.replace('law = "hertz"\nk = 5.0e10', 'law = "linear"\nk = 5.0e10'))
    assert err.key == "materials.glass.law" and "must share one contact law" in err.message


def test_toml_without_bodies(tmp_path):
    text = BASE_TOML.split("[[bodies]]")[0]
    err = load_error(tmp_path, text)
    assert err.key == "bodies" and "no bodies" in err.message
