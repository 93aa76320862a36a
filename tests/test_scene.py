"""Tests of polydem.scene: building scenes in Python and from TOML, validation and error messages;
emitters, drums, output settings, the shipped scene files and the default scene.

Host-only: no Warp kernels run here (Model only allocates arrays, on the CPU).
"""

import math
import pickle
import re
import time
import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from polydem.default_scene import default_scene, default_scene_path
from polydem.scene import (
    KIND_FIXED,
    KIND_FREE,
    KIND_KINEMATIC,
    Body,
    Material,
    Output,
    PlaneWall,
    Scene,
    SceneError,
    SceneWarning,
    pair_material,
    quat_from_axis_angle,
    quat_to_matrix,
)
from polydem.shapes import ConvexShape

ROOT = Path(__file__).resolve().parent.parent
SCENES = ROOT / "scenes"
PACKAGED_DEFAULT = ROOT / "src" / "polydem" / "scenes" / "default.toml"

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
    # A grid of pitch 0.2 m (> the cube's bounding diameter 0.17 m): validate() rejects deep initial overlaps.
    pos = 0.2 * np.stack(np.unravel_index(rng.permutation(47**3)[:n], (47, 47, 47)), axis=1) - 4.6
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
    with pytest.raises(SceneError, match="no body has a mass.*add a free body or give dt") as info:
        scene.validate()  # nothing to derive the automatic time step from
    assert info.value.key == "simulation.dt"
    scene.add_body("cube", "steel", position=(1.0, 0.0, 0.0))
    scene.validate()  # fixed bodies need no mass
    scene.add_body("flat", "steel", position=(-1.0, 0.0, 0.0))
    with pytest.raises(SceneError, match="needs a positive volume") as info:
        scene.validate()
    assert info.value.key == "bodies[2].shape"


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
    shipped = {"default.toml", "cube_drop.toml", "incline.toml", "cubes_10k.toml", "tetrahedra_100k.toml", "drum.toml"}
    assert shipped <= {p.name for p in SCENES.glob("*.toml")}


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


# ---------------------------------------------------------------------- shipped scenes and the default scene


def radii(scene) -> np.ndarray:
    """(N,) bounding radius of every body about its centre of mass."""
    return np.array([s.radius for s in scene.shapes.values()])[scene.body_shape]


def assert_spheres_apart(scene, idx):
    """No two bounding spheres of the bodies ``idx`` overlap."""
    pos, r = scene.body_position[idx], radii(scene)[idx]
    pairs = cKDTree(pos).query_pairs(2.0 * r.max(), output_type="ndarray")
    if len(pairs):
        d = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1)
        gap = d - r[pairs[:, 0]] - r[pairs[:, 1]]
        assert gap.min() > 0.0, f"bounding spheres overlap by {-gap.min():.3g} m"


def assert_inside(scene, idx, lo, hi):
    """Every bounding sphere of the bodies ``idx`` lies inside the box [lo, hi]."""
    pos, r = scene.body_position[idx], radii(scene)[idx][:, None]
    assert np.all(pos - r >= np.asarray(lo) - 1e-12) and np.all(pos + r <= np.asarray(hi) + 1e-12)


@pytest.mark.parametrize("path", sorted(SCENES.glob("*.toml")), ids=lambda p: p.name)
def test_scene_files_build_a_model_within_the_time_step_limit(path):
    import warp as wp

    from polydem.model import Model

    wp.config.quiet = True
    scene = Scene.from_toml(path)
    model = Model(scene, device="cpu")
    assert model.num_bodies == scene.num_bodies
    assert model.dt <= model.dt_limit
    if scene.dt == "auto":
        # cube_drop's stiff steel cube resting on a face needs the smallest: 3.45e-6 s.
        assert 2e-6 <= model.dt <= 1e-4, f"auto time step {model.dt:.3g} s is unreasonable"
    free = scene.body_kind == KIND_FREE
    assert_spheres_apart(scene, np.flatnonzero(free))


def test_time_step_above_the_limit_names_the_file_and_key(tmp_path):
    import warp as wp

    from polydem.model import Model

    wp.config.quiet = True
    path = write(tmp_path, (SCENES / "default.toml").read_text().replace('dt = "auto"', "dt = 1.0e-2"))
    # validate() checks it (polydem validate needs no Warp), and so does a Model of an unvalidated scene.
    err = load_error(tmp_path, path.read_text())
    assert re.search(r"time step 0\.01 s is above the stable limit \S+ s.*use dt = \"auto\"", err.message), err.message
    assert err.key == "simulation.dt"
    scene = Scene.from_toml(path, validate=False)
    with pytest.raises(SceneError, match=r"above the stable limit") as info:
        Model(scene, device="cpu")
    assert info.value.key == "simulation.dt" and info.value.file == path


def test_scene_files_with_emitters_and_output():
    for name, count in (("default.toml", 300), ("cubes_10k.toml", 10_000), ("tetrahedra_100k.toml", 100_000)):
        scene = Scene.from_toml(SCENES / name)
        assert np.sum(scene.body_kind == KIND_FREE) == count
        assert len(scene.emitters) == 1 and scene.emitters[0]["count"] == count
        assert scene.output.summary == "summary.json" and scene.output.usd.endswith(".usd")
        assert scene.precision == "mixed"
        # every free body sits inside the box's cavity, above the floor at z = 0
        verts_z = np.array([scene.body_vertices(i)[:, 2].min() for i in np.flatnonzero(scene.body_kind == 0)[:200]])
        assert verts_z.min() > 0.0
    drum = Scene.from_toml(SCENES / "drum.toml")
    assert len(drum.drums) == 1 and len(drum.drums[0].bodies) == 24 + 2
    assert np.sum(drum.body_kind == KIND_FREE) == 300
    assert drum.output.pictures == "last" and drum.output.fps == 30
    u, e = drum.drums[0].interior_planes()
    for i in np.flatnonzero(drum.body_kind == KIND_FREE):
        assert np.all(drum.body_vertices(i) @ u.T <= e), "a body starts outside the drum"


def test_static_overlap_estimate_of_the_packings():
    """Under the weight of the settled bed the overlap stays below ~1% of a body's volume.

    Hertz-type law W = 2/3 k V^1.5: a vertex pressed into a face with an area vector |S| ~ V^(2/3)
    carries F = k V^(7/6), the worst case; the bed (solid fraction 0.6) presses the bottom layer
    with p = rho 0.6 g h, about F = p L^2 per body.
    """
    for name in ("default.toml", "cubes_10k.toml", "tetrahedra_100k.toml", "drum.toml"):
        scene = Scene.from_toml(SCENES / name)
        free = scene.body_kind == KIND_FREE
        vol = np.array([s.volume for s in scene.shapes.values()])[scene.body_shape[free]]
        mat = scene.materials["stone"]
        if scene.drums:
            d = scene.drums[0]
            area = 2.0 * d.radius * d.length  # lower bound of the bed's width times the length
        else:
            box = [scene.body_vertices(i) for i in np.flatnonzero(scene.body_kind == KIND_FIXED)]
            ext = np.ptp(np.vstack(box), axis=0)
            area = ext[0] * ext[1]
        height = vol.sum() / (0.6 * area)
        force = mat.density * 0.6 * 9.81 * height * np.cbrt(vol.mean()) ** 2
        overlap = (force / mat.k) ** (6.0 / 7.0) / vol.min()
        assert overlap < 0.01, f"{name}: ~{overlap:.2%} overlap under the bed's weight"


def test_packaged_default_scene_is_the_repository_file():
    assert PACKAGED_DEFAULT.read_bytes() == (SCENES / "default.toml").read_bytes()
    # Installed or editable, the package's copy is the same file.
    assert Path(str(default_scene_path())).read_bytes() == PACKAGED_DEFAULT.read_bytes()


def test_default_scene():
    scene = default_scene()
    assert scene.name == "default" and scene.duration == 0.6 and scene.dt == "auto"
    assert scene.num_bodies == 305
    np.testing.assert_array_equal(np.bincount(scene.body_kind), [300, 5])
    counts = np.bincount(scene.body_shape[scene.body_kind == KIND_FREE])
    assert dict(zip(scene.shape_names, counts, strict=False)) == {
        "cube": 60,
        "tetrahedron": 60,
        "octahedron": 60,
        "prism6": 60,
        "rock": 60,
    }
    stone = scene.materials["stone"]
    assert (stone.density, stone.law, stone.k, stone.restitution, stone.friction) == (2500.0, "hertz", 1e8, 0.4, 0.5)
    assert scene.shapes["cube"].volume == pytest.approx(0.02**3)
    free = np.flatnonzero(scene.body_kind == KIND_FREE)
    assert_spheres_apart(scene, free)
    assert_inside(scene, free, (-0.182, -0.182, 0.0), (0.182, 0.182, 0.22))
    # same file, same scene; a seed or a count changes it
    np.testing.assert_array_equal(default_scene().body_position, scene.body_position)
    other = default_scene(seed=1)
    assert not np.allclose(other.body_position, scene.body_position)
    big = default_scene(1000)
    assert np.sum(big.body_kind == KIND_FREE) == 1000 and "1000 mixed polyhedra" in big.description
    assert_spheres_apart(big, np.flatnonzero(big.body_kind == KIND_FREE))
    with pytest.raises(SceneError, match="count must be an integer >= 1"):
        default_scene(0)


# ---------------------------------------------------------------------- emitters


def stone_scene(**kw):
    scene = Scene(**kw)
    scene.add_material("stone", density=2500.0, law="hertz", k=1e8, restitution=0.4, friction=0.5)
    scene.add_shape("cube", ConvexShape.box(0.02))
    scene.add_shape("tet", ConvexShape.tetrahedron(0.028))
    scene.add_shape("rock", ConvexShape.rock(20, 0.024, seed=3))  # its input origin is not its centroid
    return scene


REGION = {"min": [-0.2, -0.1, 0.0], "max": [0.2, 0.1, 0.3]}


def test_emit_places_count_without_overlaps_inside_the_region():
    scene = stone_scene()
    idx = scene.emit(["cube", "tet", "rock"], "stone", 250, REGION, seed=4)
    np.testing.assert_array_equal(idx, np.arange(250))
    assert scene.num_bodies == 250 and np.all(scene.body_kind == KIND_FREE)
    assert_spheres_apart(scene, idx)
    assert_inside(scene, idx, REGION["min"], REGION["max"])
    np.testing.assert_array_equal(np.bincount(scene.body_shape), [84, 83, 83])  # exact shares
    q = scene.body_orientation
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    assert np.std(q[:, 3]) > 0.2  # random orientations
    assert scene.emitters == [{"key": "emitters[0]", "count": 250, "first": 0, "last": 249}]
    scene.validate()


def test_emit_is_deterministic_for_a_seed():
    def build(seed):
        scene = stone_scene()
        scene.emit(["cube", "rock"], "stone", 120, REGION, seed=seed, scale_range=[0.8, 1.2], velocity_jitter=0.1)
        return scene

    a, b, c = build(7), build(7), build(8)
    for name in ("body_position", "body_orientation", "body_velocity", "body_shape"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.body_position, c.body_position)
    assert a.shape_names == b.shape_names


def test_emit_fills_from_the_bottom_against_gravity():
    bottom = stone_scene()
    bottom.emit("cube", "stone", 40, REGION)
    top = stone_scene()
    top.emit("cube", "stone", 40, REGION, fill="random", seed=1)
    assert bottom.body_position[:, 2].max() < 0.05 < top.body_position[:, 2].max()
    # gravity along -x stacks the layers from the -x side
    sideways = stone_scene(gravity=(-9.81, 0.0, 0.0))
    sideways.emit("cube", "stone", 40, REGION)
    assert sideways.body_position[:, 0].max() < -0.12  # two layers of 5 x 7 cells at the -x end
    assert sideways.body_position[:, 2].max() > 0.2


def test_emit_aligned_orientation_and_velocity():
    scene = stone_scene()
    idx = scene.emit("cube", "stone", 30, REGION, orientation="aligned", velocity=(0, 0, -1), velocity_jitter=0.2)
    np.testing.assert_array_equal(scene.body_orientation, np.tile([0.0, 0.0, 0.0, 1.0], (30, 1)))
    v = scene.body_velocity[idx]
    assert np.all(np.abs(v - [0.0, 0.0, -1.0]) <= 0.2) and np.std(v[:, 0]) > 0.01
    assert np.all(scene.body_angular_velocity == 0.0)


def test_emit_jitter_and_spacing():
    scene = stone_scene()
    idx = scene.emit("cube", "stone", 64, {"min": [0, 0, 0], "max": [0.3, 0.3, 0.3]}, jitter=0.0, spacing=2.0)
    pos = scene.body_position[idx]
    cell = 2.0 * 2.0 * scene.shapes["cube"].radius  # 0.069 m: 4 cells along each axis
    # no jitter: the centres form the grid, centred in the region
    for axis in range(3):
        np.testing.assert_allclose(
            np.unique(np.round(pos[:, axis], 12)), 0.15 + cell * np.array([-1.5, -0.5, 0.5, 1.5]), atol=1e-12
        )
    with pytest.raises(SceneError, match=r"must be >= 1") as info:
        scene.emit("cube", "stone", 1, REGION, spacing=0.9)
    assert info.value.key == "emitters[1].spacing"


def test_emit_avoids_walls_and_bodies_already_there():
    scene = stone_scene()
    scene.add_box_container((0, 0, 0.1), (0.3, 0.3, 0.2), "stone", wall_thickness=0.02)
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "stone")
    scene.add_plane((0.0, 0.0, 0.0), (1.0, 0.0, 0.0), "stone")  # cuts the region at x = 0
    scene.add_shape("block", ConvexShape.box(0.1, 0.1, 0.05))
    block = scene.add_body("block", "stone", (0.08, 0.0, 0.025), quat_from_axis_angle((0, 0, 1), 0.4), kind="fixed")
    # the region spills over the walls: cells crossing them are left out
    idx = scene.emit(["cube", "rock"], "stone", 30, {"min": [-0.2, -0.2, -0.05], "max": [0.2, 0.2, 0.2]}, seed=2)
    assert_spheres_apart(scene, idx)
    pos, r = scene.body_position[idx], radii(scene)[idx]
    assert np.all(pos[:, 0] - r >= 0.0), "a body crosses the plane x = 0"
    assert np.all(pos[:, :2] - r[:, None] >= -0.15) and np.all(pos[:, :2] + r[:, None] <= 0.15)
    assert np.all(pos[:, 2] - r >= 0.0), "a body reaches into the floor"
    # and none touches the fixed block: its bounding sphere is clear of every face plane it faces
    verts = scene.body_vertices(block)
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    near = np.all((pos + r[:, None] > lo) & (pos - r[:, None] < hi), axis=1)
    rot = quat_to_matrix(scene.body_orientation[block])
    shape = scene.shapes["block"]
    for i in np.flatnonzero(near):
        local = rot.T @ (pos[i] - scene.body_position[block])
        assert np.max(shape.face_normals @ local - shape.face_offsets) >= r[i] - 1e-12


def test_emit_into_a_drum_stays_inside_it():
    scene = stone_scene()
    drum = scene.add_drum((0.0, 0.0, 0.3), (0.0, 1.0, 0.0), 0.2, 0.15, "stone", rpm=10.0)
    idx = scene.emit(["cube", "tet"], "stone", 150, {"min": [-0.25, -0.1, 0.0], "max": [0.25, 0.1, 0.6]}, seed=5)
    u, e = drum.interior_planes()
    for i in idx:
        assert np.all(scene.body_vertices(i) @ u.T <= e + 1e-12)
    with pytest.raises(SceneError, match=r"holds at most \d+ bodies.*cross walls or bodies") as info:
        scene.emit("cube", "stone", 500, {"min": [-0.25, -0.1, 0.0], "max": [0.25, 0.1, 0.6]})
    assert info.value.key == "emitters[1].count"


def test_emit_region_too_small():
    scene = stone_scene()
    with pytest.raises(SceneError) as info:
        scene.emit("cube", "stone", 1000, REGION)
    err = info.value
    assert err.key == "emitters[0].count"
    m = re.search(r"holds at most (\d+) bodies, fewer than count = 1000", err.message)
    assert m, err.message
    fit = int(m.group(1))
    assert f"Lower count to {fit}" in err.message and "enlarge the region" in err.message
    assert scene.num_bodies == 0
    assert len(scene.emit("cube", "stone", fit, REGION)) == fit  # exactly that many fit
    with pytest.raises(SceneError, match=r"region is 0.02 m along y, too small for one body") as info:
        scene.emit("cube", "stone", 1, {"min": [0, 0, 0], "max": [1, 0.02, 1]})
    assert info.value.key == "emitters[1].region"


def test_emit_size_distributions():
    scene = stone_scene()
    base = scene.shapes["cube"]
    idx = scene.emit("cube", "stone", 10, REGION | {"max": [0.2, 0.1, 0.15]}, scale=1.5)
    (name,) = {scene.shape_names[s] for s in scene.body_shape[idx]}
    assert name == "cube_x1.5" and scene.shapes[name].volume == pytest.approx(1.5**3 * base.volume)
    assert scene.emit("cube", "stone", 5, REGION | {"min": [-0.2, -0.1, 0.15]}, scale=1.5)[0] == 10
    assert scene.shape_names.count("cube_x1.5") == 1  # registered once

    uni = stone_scene()
    idx = uni.emit(["cube", "tet"], "stone", 400, {"min": [0, 0, 0], "max": [1, 1, 1]}, scale_range=[0.5, 1.0])
    used = sorted({uni.shape_names[s] for s in uni.body_shape[idx]})
    assert len(used) == 2 * 8  # 8 bins per base shape
    cube_rows = np.array([uni.shape_names[s].startswith("cube") for s in uni.body_shape])
    factor = np.cbrt(np.array([s.volume for s in uni.shapes.values()])[uni.body_shape[cube_rows]] / base.volume)
    assert factor.min() >= 0.5 and factor.max() <= 1.0
    assert factor.mean() == pytest.approx(0.75, abs=0.03)
    assert_spheres_apart(uni, idx)

    logn = stone_scene()
    idx = logn.emit(
        "cube", "stone", 2000, {"min": [0, 0, 0], "max": [2, 2, 1]}, scale_lognormal={"mean": 1.0, "sigma": 0.2}
    )
    factor = np.cbrt(np.array([s.volume for s in logn.shapes.values()])[logn.body_shape[idx]] / base.volume)
    assert factor.mean() == pytest.approx(1.0, abs=0.02)
    assert np.std(np.log(factor)) == pytest.approx(0.2, abs=0.03)
    assert len(np.unique(factor)) <= 8
    big = np.cbrt(np.array([s.volume for s in logn.shapes.values()]) / base.volume).max()
    assert big <= math.exp(-0.02 + 3 * 0.2) + 1e-9  # truncated at 3 sigma
    assert_spheres_apart(logn, idx)

    with pytest.raises(SceneError, match="one size distribution.*not both scale and scale_range") as info:
        stone_scene().emit("cube", "stone", 1, REGION, scale=1.0, scale_range=[1, 2])
    assert info.value.key == "emitters[0].scale_range"


def test_emit_mix_weights():
    scene = stone_scene()
    scene.emit(["cube", "tet", "rock"], "stone", 100, REGION, weights=[2, 1, 1])
    np.testing.assert_array_equal(np.bincount(scene.body_shape), [50, 25, 25])
    table = stone_scene()
    table.emit({"cube": 1, "rock": 3}, "stone", 10, REGION)
    counts = dict(zip(table.shape_names, np.bincount(table.body_shape, minlength=3), strict=True))
    assert counts == {"cube": 3, "tet": 0, "rock": 7}  # 2.5 and 7.5: the tie goes to the first
    with pytest.raises(SceneError, match="expected 3 weights") as info:
        stone_scene().emit(["cube", "tet", "rock"], "stone", 10, REGION, weights=[1, 2])
    assert info.value.key == "emitters[0].weights"
    with pytest.raises(SceneError, match="listed twice"):
        stone_scene().emit(["cube", "cube"], "stone", 10, REGION)


def test_emit_rock_centroid_and_kinematic():
    scene = stone_scene()
    idx = scene.emit("rock", "stone", 20, REGION, kind="kinematic", velocity=(0.1, 0, 0), orientation="aligned")
    assert np.all(scene.body_kind == KIND_KINEMATIC)
    assert_inside(scene, idx, REGION["min"], REGION["max"])  # centroids are placed, not input origins
    with pytest.raises(SceneError, match="fixed bodies cannot move") as info:
        scene.emit("cube", "stone", 1, REGION, kind="fixed", velocity_jitter=0.1)
    assert info.value.key == "emitters[1].velocity"


def test_emit_a_hundred_thousand_bodies_quickly():
    scene = stone_scene()
    scene.add_shape("grain", ConvexShape.tetrahedron(0.01))
    scene.add_shape("pebble", ConvexShape.rock(12, 0.01, seed=1))
    scene.add_box_container((0, 0, 0.5), (1.0, 1.0, 1.0), "stone")
    t0 = time.perf_counter()
    region = {"min": [-0.5, -0.5, 0.0], "max": [0.5, 0.5, 1.0]}
    idx = scene.emit(["grain", "pebble"], "stone", 100_000, region, scale_range=[0.8, 1.0])
    elapsed = time.perf_counter() - t0
    assert len(idx) == 100_000
    assert elapsed < 3.0, f"emitting 10^5 bodies took {elapsed:.2f} s"
    assert_spheres_apart(scene, idx)


# ---------------------------------------------------------------------- drums and pivots


@pytest.mark.parametrize("axis", [(0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (1.0, 2.0, -0.5)])
def test_drum_slabs_move_consistently(axis):
    scene = stone_scene()
    center = np.array([0.1, -0.2, 0.3])
    drum = scene.add_drum(center, axis, 0.25, 0.3, "stone", omega=-2.0, sides=16, thickness=0.03)
    a = np.asarray(axis) / np.linalg.norm(axis)
    np.testing.assert_allclose(drum.axis, a)
    assert drum.sides == 16 and drum.caps and len(drum.bodies) == 18
    idx = np.array(drum.bodies)
    assert np.all(scene.body_kind[idx] == KIND_KINEMATIC)
    pos = scene.body_position[idx]
    w = scene.body_angular_velocity[idx]
    np.testing.assert_allclose(w, np.tile(-2.0 * a, (18, 1)), atol=1e-15)
    np.testing.assert_allclose(scene.body_pivot[idx], np.tile(center, (18, 1)))
    # velocity = omega x r for every part; the slabs' centres lie at radius + thickness / 2
    np.testing.assert_allclose(scene.body_velocity[idx], np.cross(w, pos - center), atol=1e-14)
    rel = pos[:16] - center
    radial = rel - np.outer(rel @ a, a)
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1), 0.25 + 0.015)
    np.testing.assert_allclose(rel @ a, 0.0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(scene.body_velocity[idx[:16]], axis=1), 2.0 * 0.265)
    # the caps sit on the axis beyond the ends and only spin
    np.testing.assert_allclose((pos[16:] - center) @ a, [0.165, -0.165])
    np.testing.assert_allclose(scene.body_velocity[idx[16:]], 0.0, atol=1e-14)
    # inner faces form the 16-gon of inradius 0.25: every slab vertex is at least that far from the
    # axis, each slab has a face at exactly that distance, and neighbours meet at the corners
    u, e = drum.interior_planes()
    for k in range(16):
        v = scene.body_vertices(int(idx[k])) - center
        dist = np.linalg.norm(v - np.outer(v @ a, a), axis=1)
        assert dist.min() == pytest.approx(0.25 / math.cos(math.pi / 16))
        assert np.sum(np.isclose(v @ (-u[k]), -0.25, atol=1e-12)) == 4
        assert np.all(np.abs(v @ a) <= 0.15 + 1e-12)
    corners = [scene.body_vertices(int(i)) for i in idx[:16]]
    for k in range(16):
        shared = np.min(np.linalg.norm(corners[k][:, None] - corners[(k + 1) % 16][None], axis=2), axis=1)
        assert np.sum(shared < 1e-12) == 2  # two inner corners (one edge) shared with the neighbour
    # a short rigid rotation of the whole drum moves each centre by omega x r dt
    dt = 1e-6
    rot = quat_to_matrix(quat_from_axis_angle(a, -2.0 * dt))
    moved = (pos - center) @ rot.T + center
    np.testing.assert_allclose((moved - pos) / dt, scene.body_velocity[idx], atol=1e-6)
    scene.validate()


def test_drum_options_and_errors():
    scene = stone_scene()
    drum = scene.add_drum((0, 0, 0), (0, 1, 0), 0.2, 0.1, "stone", rpm=30.0, caps=False)
    assert drum.omega == pytest.approx(math.pi) and len(drum.bodies) == 24 and drum.thickness == pytest.approx(0.02)
    assert scene.drums == [drum] and "24 slabs, omega 3.142 rad/s (30 rpm)" in scene.describe()
    with pytest.raises(SceneError, match="exactly one of omega") as info:
        scene.add_drum((0, 0, 0), (0, 1, 0), 0.2, 0.1, "stone")
    assert info.value.key == "drums[1].omega"
    with pytest.raises(SceneError, match="exactly one of omega"):
        scene.add_drum((0, 0, 0), (0, 1, 0), 0.2, 0.1, "stone", omega=1.0, rpm=10.0)
    with pytest.raises(SceneError, match="axis .* is zero"):
        scene.add_drum((0, 0, 0), (0, 0, 0), 0.2, 0.1, "stone", omega=1.0)
    with pytest.raises(SceneError, match=r"must be an integer >= 3") as info:
        scene.add_drum((0, 0, 0), (0, 1, 0), 0.2, 0.1, "stone", omega=1.0, sides=2)
    assert info.value.key == "drums[1].sides"


def test_pivot_bodies():
    scene = stone_scene()
    i = scene.add_body(
        "cube", "stone", (1.0, 0.0, 0.0), angular_velocity=(0, 0, 2.0), kind="kinematic", pivot=(0, 0, 0)
    )
    np.testing.assert_allclose(scene.body_velocity[i], [0.0, 2.0, 0.0])
    assert scene.body(i).pivot == (0.0, 0.0, 0.0)
    j = scene.add_body("cube", "stone", (0.0, 0.0, 1.0))
    assert np.all(np.isnan(scene.body_pivot[j])) and scene.body(j).pivot is None
    with pytest.raises(SceneError, match="only a kinematic body can turn about a pivot") as info:
        scene.add_body("cube", "stone", pivot=(0, 0, 0))
    assert info.value.key == "bodies[2].pivot"
    with pytest.raises(SceneError, match="leave velocity out") as info:
        scene.add_body("cube", "stone", velocity=(1, 0, 0), kind="kinematic", pivot=(0, 0, 0))
    assert info.value.key == "bodies[2].velocity"


# ---------------------------------------------------------------------- simulation settings and output


def test_device_and_precision():
    assert Scene(device="cuda:1").device == "cuda:1" and Scene().device is None
    assert Scene().precision == "mixed"
    for precision in ("float32", "mixed", "float64"):
        assert Scene(precision=precision).precision == precision
    valid = r"unknown precision 'float16'.*Valid precisions: float32, mixed, float64"
    with pytest.raises(SceneError, match=valid) as info:
        Scene(precision="float16")
    assert info.value.key == "simulation.precision"
    with pytest.raises(SceneError, match=r"unknown device 'gpu'.*\"cuda:N\"") as info:
        Scene(device="gpu")
    assert info.value.key == "simulation.device"
    scene = stone_scene()
    scene.add_body("cube", "stone")
    scene.precision = "float64"
    scene.validate()
    scene.precision = "double"
    with pytest.raises(SceneError, match="unknown precision 'double'"):
        scene.validate()


@pytest.mark.parametrize("precision", ["float32", "mixed", "float64"])
def test_toml_precision(tmp_path, precision):
    """Before: precision = "float64" in a scene file was refused ("float32 only"); now it and "mixed"
    load, and write back; a file that gives no precision is "mixed", and "float32" stays a choice."""
    assert "precision" not in BASE_TOML
    assert Scene.from_toml(write(tmp_path, BASE_TOML)).precision == "mixed"
    scene = Scene.from_toml(
        write(tmp_path, BASE_TOML.replace("steps = 100", f'steps = 100\nprecision = "{precision}"'))
    )
    assert scene.precision == precision
    assert scene.to_dict()["simulation"]["precision"] == precision


def test_output_settings():
    out = Output.from_dict(
        {"usd": "run/traj.usda", "fps": 24, "summary": "s.json", "pictures": [30, 0, 30], "checkpoint": {"steps": 500}}
    )
    assert out == Output(usd="run/traj.usda", fps=24.0, summary="s.json", pictures=(0, 30), checkpoint_steps=500)
    assert out.checkpoint_path == "checkpoints" and out.checkpoint_seconds is None
    default = Output()
    assert (default.usd, default.summary, default.pictures, default.fps) == (None, "summary.json", (), 60.0)
    flags = Output.from_dict({"usd": True, "summary": False, "pictures": "last", "checkpoint": {"seconds": 0.1}})
    assert (flags.usd, flags.summary, flags.pictures, flags.checkpoint_seconds) == ("trajectory.usd", None, "last", 0.1)
    assert Output.from_dict(out.to_dict()) == out and Output.from_dict(flags.to_dict()) == flags


@pytest.mark.parametrize(
    "table, key, match",
    [
        ({"fsp": 30}, "output.fsp", r"unknown key 'fsp'; did you mean 'fps'\?"),
        ({"fps": -1}, "output.fps", r"must be positive"),
        ({"fps": "fast"}, "output.fps", r"expected a number, got string 'fast'"),
        ({"usd": "out.obj"}, "output.usd", r"must end in \.usd, \.usda, \.usdc"),
        ({"usd": 3}, "output.usd", r"expected a file path string"),
        ({"summary": 1}, "output.summary", r"expected a file path string"),
        ({"pictures": "first"}, "output.pictures", r"expected a list of frame numbers or \"last\""),
        ({"pictures": [0, -2]}, "output.pictures[1]", r"must be an integer >= 0"),
        ({"pictures": [0.5]}, "output.pictures[0]", r"expected an integer"),
        ({"checkpoint": 100}, "output.checkpoint", r"expected a table such as checkpoint = \{steps = 10000\}"),
        ({"checkpoint": {}}, "output.checkpoint", r"give the checkpoint interval"),
        ({"checkpoint": {"step": 10}}, "output.checkpoint.step", r"did you mean 'steps'\?"),
        ({"checkpoint": {"steps": 10, "seconds": 1.0}}, "output.checkpoint.seconds", r"not both"),
        ({"checkpoint": {"steps": 0}}, "output.checkpoint.steps", r"must be an integer >= 1"),
    ],
)
def test_output_errors(table, key, match):
    with pytest.raises(SceneError, match=match) as info:
        Output.from_dict(table, file="x.toml")
    assert info.value.key == key and info.value.file == "x.toml"


# ---------------------------------------------------------------------- the new tables in scene files


EMITTER_TOML = (
    BASE_TOML.replace("steps = 100", 'steps = 100\ndevice = "cpu"\nprecision = "float32"')
    + """
[shapes.rock]
type = "rock"
n_points = 12
size = 0.1

[[emitters]]
shape = ["cube", "rock"]
weights = [1.0, 1.0]
material = "glass"
count = 50
region = { min = [-0.5, -0.5, 0.5], max = [0.5, 0.5, 1.5] }
orientation = "random"
seed = 3
velocity = [0.0, 0.0, -0.5]
velocity_jitter = 0.05
scale_range = [0.9, 1.1]
scale_bins = 4
kind = "free"
spacing = 1.2
jitter = 0.5
fill = "bottom"

[[walls]]
type = "drum"
center = [3.0, 0.0, 1.0]
axis = [1.0, 0.0, 0.0]
radius = 0.5
length = 0.4
rpm = 12.0
sides = 12
thickness = 0.05
caps = false
material = "steel"

[output]
usd = "emit.usd"
fps = 30
summary = "summary.json"
pictures = [0, 10]
checkpoint = { seconds = 0.5, path = "ck" }
"""
)


def test_toml_emitters_drums_and_output(tmp_path):
    scene = Scene.from_toml(write(tmp_path, EMITTER_TOML))
    assert scene.device == "cpu" and scene.precision == "float32"
    assert scene.num_bodies == 1 + 12 + 50  # the body, the drum's slabs (no caps), the emitted
    (drum,) = scene.drums
    assert drum.omega == pytest.approx(12 * 2 * math.pi / 60) and not drum.caps
    emitted = np.arange(13, 63)
    np.testing.assert_array_equal(np.bincount(scene.body_shape[emitted], minlength=1)[0], 0)
    assert len({scene.shape_names[s] for s in scene.body_shape[emitted]}) <= 2 * 4
    assert np.all(np.abs(scene.body_velocity[emitted] - [0, 0, -0.5]) <= 0.05)
    assert_spheres_apart(scene, np.arange(63)[scene.body_kind == KIND_FREE])
    assert scene.output == Output(
        usd="emit.usd", fps=30, summary="summary.json", pictures=(0, 10), checkpoint_seconds=0.5, checkpoint_path="ck"
    )
    # the round trip keeps bodies, pivots and output
    again = Scene.from_dict(scene.to_dict())
    np.testing.assert_allclose(again.body_position, scene.body_position, atol=1e-12)
    np.testing.assert_allclose(again.body_velocity, scene.body_velocity, atol=1e-12)
    np.testing.assert_array_equal(np.isnan(again.body_pivot), np.isnan(scene.body_pivot))
    assert again.output == scene.output and again.device == "cpu"


def test_toml_pivot_body(tmp_path):
    text = BASE_TOML + (
        '\n[[bodies]]\nshape = "cube"\nmaterial = "steel"\nposition = [0.5, 0.0, 1.0]\nkind = "kinematic"\n'
        "angular_velocity = [0.0, 0.0, 1.0]\npivot = [0.0, 0.0, 1.0]\n"
    )
    scene = Scene.from_toml(write(tmp_path, text))
    np.testing.assert_allclose(scene.body_velocity[1], [0.0, 0.5, 0.0])
    err = load_error(tmp_path, text.replace("pivot =", "velocity = [0.0, 0.5, 0.0]\npivot ="))
    assert err.key == "bodies[1].velocity" and "not both" in err.message
    err = load_error(tmp_path, text.replace('kind = "kinematic"', 'kind = "free"'))
    assert err.key == "bodies[1].pivot" and "only a kinematic body" in err.message


EMITTER_BASE = (
    BASE_TOML
    + """
[[emitters]]
shape = "cube"
material = "steel"
count = 20
region = { min = [-0.5, -0.5, 0.5], max = [0.5, 0.5, 1.0] }
"""
)


@pytest.mark.parametrize(
    "old, new, key, match",
    [
        ("count = 20", "cuont = 20", "emitters[0].cuont", r"unknown key 'cuont'; did you mean 'count'\?"),
        ("count = 20", "count = -5", "emitters[0].count", r"must be an integer >= 1, got -5"),
        ("count = 20", "count = 2.5", "emitters[0].count", r"expected an integer, got float 2.5"),
        ("count = 20", "count = '20'", "emitters[0].count", r"expected an integer, got string '20'"),
        ("count = 20", "", "emitters[0].count", r"missing required key 'count' \(number of bodies"),
        ("count = 20", "count = 100000", "emitters[0].count", r"holds at most \d+ bodies.*Lower count to \d+"),
        (
            'shape = "cube"\nmaterial = "steel"\ncount',
            'shape = "cueb"\nmaterial = "steel"\ncount',
            "emitters[0].shape",
            r"unknown shape 'cueb'; did you mean 'cube'\?",
        ),
        (
            'shape = "cube"\nmaterial = "steel"\ncount',
            'shape = []\nmaterial = "steel"\ncount',
            "emitters[0].shape",
            r"the list of shapes is empty",
        ),
        (
            '"cube"\nmaterial = "steel"\ncount',
            '"cube"\nweights = [1]\nmaterial = "steel"\ncount',
            "emitters[0].weights",
            r"go with a list of shapes",
        ),
        (
            'shape = "cube"\nmaterial = "steel"\ncount',
            'shape = ["cube"]\nweights = [-1]\nmaterial = "steel"\ncount',
            "emitters[0].weights[0]",
            r"must not be negative",
        ),
        ('material = "steel"\ncount', 'material = "stel"\ncount', "emitters[0].material", r"did you mean 'steel'"),
        ("max = [0.5, 0.5, 1.0]", "mx = [0.5, 0.5, 1.0]", "emitters[0].region.mx", r"did you mean 'max'\?"),
        (
            "max = [0.5, 0.5, 1.0]",
            "max = [0.5, 0.5, 0.4]",
            "emitters[0].region.max",
            r"along z min = 0.5 and max = 0.4",
        ),
        ("max = [0.5, 0.5, 1.0]", "max = [0.5, 0.5]", "emitters[0].region.max", r"expected 3 numbers"),
        ("max = [0.5, 0.5, 1.0]", "max = [0.5, 0.5, 0.51]", "emitters[0].region", r"too small for one body"),
        ("count = 20", "count = 20\norientation = 'randon'", "emitters[0].orientation", r"did you mean 'random'\?"),
        ("count = 20", "count = 20\nfill = 'botom'", "emitters[0].fill", r"did you mean 'bottom'\?"),
        ("count = 20", "count = 20\nkind = 'fixd'", "emitters[0].kind", r"did you mean 'fixed'\?"),
        ("count = 20", "count = 20\nseed = -1", "emitters[0].seed", r"must be an integer >= 0"),
        ("count = 20", "count = 20\njitter = 2.0", "emitters[0].jitter", r"must be in \[0, 1\]"),
        ("count = 20", "count = 20\nvelocity_jitter = -1", "emitters[0].velocity_jitter", r"must not be negative"),
        ("count = 20", "count = 20\nvelocity = [0, 0]", "emitters[0].velocity", r"expected 3 numbers"),
        ("count = 20", "count = 20\nscale = 0", "emitters[0].scale", r"must be positive"),
        ("count = 20", "count = 20\nscale_range = [2, 1]", "emitters[0].scale_range", r"expected 0 < lo <= hi"),
        (
            "count = 20",
            "count = 20\nscale_lognormal = {mean = 1.0}",
            "emitters[0].scale_lognormal.sigma",
            r"missing required key 'sigma'",
        ),
        (
            "count = 20",
            "count = 20\nscale_lognormal = {mean = 1.0, sigma = 0.1, mode = 1}",
            "emitters[0].scale_lognormal.mode",
            r"unknown key 'mode'",
        ),
        ("count = 20", "count = 20\nscale_bins = 0", "emitters[0].scale_bins", r"must be an integer >= 1"),
        ("[[emitters]]", "[emitters]", "emitters", r"expected an array of tables \[\[emitters\]\]"),
        # simulation settings
        (
            "steps = 100",
            'steps = 100\nprecision = "float16"',
            "simulation.precision",
            r"unknown precision 'float16'.*float32, mixed, float64",
        ),
        ("steps = 100", 'steps = 100\ndevice = "gpu"', "simulation.device", r"unknown device 'gpu'"),
        ("steps = 100", "steps = 100\ndevice = 0", "simulation.device", r"expected a device name"),
        ("steps = 100", "steps = 100\nprecison = 'float32'", "simulation.precison", r"did you mean 'precision'\?"),
        # output
        ("[[emitters]]", "[output]\nfps = 0\n\n[[emitters]]", "output.fps", r"must be positive"),
        ("[[emitters]]", "[output]\nusd = 'a.txt'\n\n[[emitters]]", "output.usd", r"must end in"),
        ("[[emitters]]", "[outptu]\nfps = 1\n\n[[emitters]]", "outptu", r"did you mean 'output'\?"),
        # drums
        (
            "[[emitters]]",
            "[[walls]]\ntype = 'drum'\ncenter = [0, 0, 3]\naxis = [0, 1, 0]\nradius = 0.5\nlength = 0.2\n"
            "material = 'steel'\nrmp = 10\n\n[[emitters]]",
            "walls[1].rmp",
            r"did you mean 'rpm'\?.*Valid keys for type = 'drum'",
        ),
        (
            "[[emitters]]",
            "[[walls]]\ntype = 'drum'\ncenter = [0, 0, 3]\naxis = [0, 1, 0]\nradius = -0.5\nlength = 0.2\n"
            "material = 'steel'\nrpm = 10\n\n[[emitters]]",
            "walls[1].radius",
            r"must be positive",
        ),
        (
            "[[emitters]]",
            "[[walls]]\ntype = 'drum'\ncenter = [0, 0, 3]\naxis = [0, 1, 0]\nradius = 0.5\n"
            "material = 'steel'\nrpm = 10\n\n[[emitters]]",
            "walls[1].length",
            r"missing required key 'length'",
        ),
        ('type = "plane"', 'type = "drun"', "walls[0].type", r"did you mean 'drum'\?"),
    ],
)
def test_toml_emitter_and_settings_errors(tmp_path, old, new, key, match):
    assert old in EMITTER_BASE
    err = load_error(tmp_path, EMITTER_BASE.replace(old, new, 1))
    assert err.key == key, str(err)
    assert re.search(match, err.message), str(err)


# ---------------------------------------------------------------------- what a run needs (issue 9)
# Each case passed validate() before and then hung or failed in a run; the BEFORE behaviour is in
# the comments. Messages name the key and the fix.


def toml_error(tmp_path, old, new, count=1) -> SceneError:
    assert old in BASE_TOML
    return load_error(tmp_path, BASE_TOML.replace(old, new, count))


def assert_valid_after(tmp_path, old, new):
    """The fix an error message suggests makes the scene valid (so the message can be trusted)."""
    scene = Scene.from_toml(write(tmp_path, BASE_TOML.replace(old, new), name="fixed.toml"))
    assert scene.time_step().dt > 0.0


@pytest.mark.parametrize("density", ["1e300", "1e-300"])
def test_density_beyond_float32(tmp_path, density):
    # BEFORE: 1e300 gave an automatic dt of 1e143 s (the run hung); 1e-300 a non-finite state at step 1.
    err = toml_error(tmp_path, "density = 7800.0", f"density = {density}")
    assert err.key == "materials.steel.density"
    m = re.search(
        r"mass of (\S+) kg.*float32.*use a density between (\S+) and (\S+) kg/m\^3 for this shape", err.message
    )
    assert m, err.message
    assert float(m.group(1)) == pytest.approx(float(density) * 1e-3, rel=1e-6)
    lo, hi = float(m.group(2)), float(m.group(3))
    assert lo < 7800.0 < hi
    for ok in (lo * 1.01, hi / 1.01):
        Material(name="x", **(STEEL | dict(density=ok)))  # the range is the float32 one, not a cap
        scene = basic_scene()
        scene.add_material("x", **(STEEL | dict(density=ok, k=1e30)))
        scene.add_body("cube", "x", position=(0.0, 0.0, 1.0))
        scene.validate()


@pytest.mark.parametrize("size", ["1e-9", "1e9"])
def test_shape_size_beyond_float32(tmp_path, size):
    # BEFORE: both validated; the run became non-finite at step 1 (float32 inertia under- or overflow).
    err = toml_error(tmp_path, "size = [0.1, 0.1, 0.1]", f"size = {size}")
    assert err.key == "shapes.cube"
    assert re.search(r"too (small|large) for the simulator's float32 arithmetic", err.message), err.message
    assert re.search(r"give the shape a bounding radius between 1\S* m and 1\S* m", err.message), err.message


def test_soft_contact_under_an_automatic_time_step(tmp_path):
    # BEFORE: k = 1e-10 validated with an automatic dt of 1.1e5 s; a run ended with total energy -9e13 J.
    err = toml_error(tmp_path, "k = 2.0e11", "k = 1e-10", count=2)
    assert err.key == "materials.steel.k"
    assert "under its own weight" in err.message and "into what carries it" in err.message
    assert re.search(
        r"the automatic time step, \S+ s, is \S+ times the \S+ s it takes to fall its own size", err.message
    )
    m = re.search(r"raise k of 'steel' to at least (\S+) J/m\^4\.5", err.message)
    assert m, err.message
    k_min = float(m.group(1))
    # The suggested k holds the cube's weight at 10% of its size: a hertz face contact (area A, depth
    # d) carries k sqrt(A d) A = M g, so k = M g / (sqrt(A 0.1 L) A) with M = 7.8 kg, L = 0.1 m.
    assert k_min == pytest.approx(7.8 * 9.81 / (math.sqrt(0.01 * 0.01) * 0.01), rel=1e-3)
    assert_valid_after(tmp_path, "k = 2.0e11", f"k = {2.0 * k_min:g}")
    # A given dt is the user's choice: the same soft contact then only warns.
    with pytest.warns(SceneWarning, match=r"materials\.steel\.k"):
        Scene.from_toml(write(tmp_path, BASE_TOML.replace("k = 2.0e11", "k = 1e-10").replace('"auto"', "1e-6")))


@pytest.mark.parametrize("m", [10, 100, 1000])
def test_power_law_exponent_beyond_float32(tmp_path, m):
    # BEFORE: m = 10 gave an automatic dt of 3.5e20 s (a hang), m = 100 and 1000 dt = inf and a traceback.
    text = BASE_TOML.replace('law = "hertz"', f'law = "power"\nm = {m}')
    err = load_error(tmp_path, text)
    assert err.key == "materials.steel.m"
    hit = re.search(
        r"V = 1e-06 m\^3\) the law's V\^m = 1e-0?(\d+) is outside .*use m between 1 and (\S+) for", err.message
    )
    assert hit, err.message
    assert int(hit.group(1)) == 6 * m
    m_max = float(hit.group(2))
    # V^m stays within float32's range with the margin: 1e-6^m_max = 1.2e-32.
    assert m_max == pytest.approx(math.log(np.finfo(np.float32).tiny * 1e6) / math.log(1e-6), rel=1e-3)
    # Inside the range the law works once k holds the weight; the check then names that k.
    inside = text.replace(f"m = {m}", "m = 5").replace("k = 2.0e11", "k = 1e10")
    err = load_error(tmp_path, inside)
    assert err.key == "materials.steel.k", err.message
    k_min = float(re.search(r"raise k of 'steel' to at least (\S+) J/m\^\(3m\)", err.message).group(1))
    Scene.from_toml(write(tmp_path, inside.replace("k = 1e10", f"k = {2.0 * k_min:g}"), name="ok.toml"))


def test_stiffening_law_with_a_given_time_step_too_long_for_its_resting_overlap(tmp_path):
    """m > 2: the stable limit of dt (taken at 0.1% overlap) is too long where the weight presses the body."""
    text = BASE_TOML.replace('law = "hertz"', 'law = "power"\nm = 5').replace("k = 2.0e11", "k = 1e25")
    dt_limit = (
        Scene.from_toml(write(tmp_path, text.replace('dt = "auto"', "dt = 1e-9"), name="a.toml")).time_step().limit
    )
    err = load_error(tmp_path, text.replace('dt = "auto"', f"dt = {0.9 * dt_limit!r}"))
    assert err.key == "simulation.dt"
    assert re.search(r"m = 5 > 2 stiffens with depth\) has a stiffness of \S+ N/m and the time step", err.message)
    assert "lower dt" in err.message


def test_run_longer_than_the_step_counter(tmp_path):
    err = toml_error(tmp_path, "steps = 100", "duration = 1e6")
    assert err.key == "simulation.duration"
    assert re.search(r"a run of \S+ steps of \S+ s is more than the simulator counts \(2147483647", err.message)
    assert "shorten the run" in err.message
    err = toml_error(tmp_path, "steps = 100", "steps = 3000000000")
    assert err.key == "simulation.steps"


def test_time_step_is_host_side_and_the_model_uses_it():
    """polydem validate takes dt from Scene.time_step (numpy only); a Model must get the same numbers."""
    ts = Scene.from_toml(SCENES / "cube_drop.toml").time_step()
    dt, rec, limit = ts.dt, ts.recommended, ts.limit
    assert dt == rec and rec < limit
    import warp as wp

    from polydem.model import Model

    wp.config.quiet = True
    model = Model(Scene.from_toml(SCENES / "cube_drop.toml"), device="cpu")
    assert (model.dt, model.dt_recommended, model.dt_limit) == (dt, rec, limit)


def test_emitter_count_is_checked_before_allocating():
    # BEFORE: count = 1e9 allocated 7.5 GiB of per-body arrays before "the region holds at most N".
    for count, match in (
        (
            10**9,
            r"count = 1000000000 would make 1e\+09 bodies, more than a scene can hold \(101,000,000\).*lower count",
        ),
        (10**7, r"the region holds at most 350 bodies, fewer than count = 10000000: .*lower count or enlarge"),
    ):
        scene = stone_scene()
        tracemalloc.start()
        t0 = time.perf_counter()
        with pytest.raises(SceneError, match=match) as info:
            scene.emit("cube", "stone", count, REGION)
        elapsed = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert info.value.key == "emitters[0].count"
        assert elapsed < 1.0 and peak < 10 * 2**20, (elapsed, peak)
        assert scene.num_bodies == 0


def test_body_count_limit(monkeypatch):
    import polydem.scene.bodies as scene_module

    monkeypatch.setattr(scene_module, "MAX_BODIES", 10)
    scene = basic_scene()
    scene.add_bodies("cube", "steel", np.arange(30.0).reshape(10, 3))
    with pytest.raises(SceneError, match=r"1 more bodies would make 11, more than a scene can hold") as info:
        scene.add_body("cube", "steel", position=(5.0, 5.0, 5.0))
    assert info.value.key == "bodies[10]" and scene.num_bodies == 10


@pytest.mark.parametrize(
    ("spec", "key", "match"),
    [
        ('type = "prism"\nn = 100000\nradius = 0.05\nheight = 0.1', "shapes.big.n", r"<= 1024.*faces of at most 1024"),
        ('type = "rock"\nn_points = 100000\nsize = 0.1', "shapes.big.n_points", r"<= 10242.*at most 20480"),
    ],
)
def test_shape_size_limits_in_a_scene_file(tmp_path, spec, key, match):
    # BEFORE: both took minutes to build (n = 10000 already takes 15 s for the prism).
    t0 = time.perf_counter()
    err = load_error(tmp_path, BASE_TOML + f"\n[shapes.big]\n{spec}\n")
    assert time.perf_counter() - t0 < 2.0
    assert err.key == key and re.search(match, err.message), err.message


def test_body_below_a_plane_wall(tmp_path):
    # BEFORE: validated; the run launched the cube at hundreds of m/s.
    err = toml_error(tmp_path, "position = [0.0, 0.0, 0.2]", "position = [0.0, 0.0, -0.2]")
    assert err.key == "bodies[0].position"
    assert err.message.startswith("body 0 (shape 'cube', free) starts 0.25 m behind the plane wall walls[0] (wholly)")
    assert "move it by at least 0.25 m along the wall's normal [0, 0, 1]" in err.message
    err = toml_error(tmp_path, "position = [0.0, 0.0, 0.2]", "position = [0.0, 0.0, -0.02]")  # 70% below
    assert "0.07 m behind the plane wall walls[0] (70% of its thickness)" in err.message
    with pytest.warns(
        SceneWarning, match=r"body 0 \(shape 'cube', free\) 0.01 m behind the plane wall walls\[0\] \(10\.0%\)"
    ):
        Scene.from_toml(write(tmp_path, BASE_TOML.replace("0.0, 0.2]", "0.0, 0.04]")))
    with warnings.catch_warnings():
        warnings.simplefilter("error", SceneWarning)
        Scene.from_toml(write(tmp_path, BASE_TOML.replace("0.0, 0.2]", "0.0, 0.05]")))  # resting on it


def two_cubes(offset, qa=(0.0, 0.0, 0.0, 1.0), qb=(0.0, 0.0, 0.0, 1.0), kind_b="free"):
    scene = basic_scene()
    scene.add_body("cube", "steel", position=(0.0, 0.0, 1.0), orientation=qa)
    scene.add_body("cube", "steel", position=np.add((0.0, 0.0, 1.0), offset), orientation=qb, kind=kind_b)
    return scene


def test_body_deep_inside_another():
    for offset, kind, share in (((0.0, 0.0, 0.0), "free", "wholly"), ((0.04, 0.0, 0.0), "fixed", "60% of")):
        with pytest.raises(SceneError) as info:
            two_cubes(offset, kind_b=kind).validate()
        err = info.value
        assert err.key == "bodies[0].position"
        assert re.match(
            rf"body 0 \(shape 'cube', free\) starts \S+ m into body 1 \(shape 'cube', {kind}\) \({share}", err.message
        )
        assert "move the two apart by at least" in err.message
    with pytest.warns(
        SceneWarning, match=r"1 initial overlaps .* 0.005 m into body 1 .* \(5\.0%\); move the bodies apart"
    ):
        two_cubes((0.0, 0.0, 0.095)).validate()
    # Touching, and crossed edges just apart (a face-normal test alone would call them overlapping).
    qa, qb = quat_from_axis_angle((1, 0, 0), math.pi / 4), quat_from_axis_angle((0, 1, 0), math.pi / 4)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SceneWarning)
        two_cubes((0.0, 0.0, 0.1)).validate()
        two_cubes((0.0, 0.0, 0.1 * math.sqrt(2.0) * 1.0001), qa, qb).validate()
    with pytest.warns(SceneWarning, match=r"\(3\.0%\)"):
        two_cubes((0.0, 0.0, 0.1 * math.sqrt(2.0) * 0.97), qa, qb).validate()


def test_body_inside_a_container_wall():
    scene = basic_scene()
    scene.add_box_container((0.0, 0.0, 0.5), (1.0, 1.0, 1.0), "steel", wall_thickness=0.1)
    scene.add_body("cube", "glass", position=(0.53, 0.0, 0.5))  # 80% of the +x slab's thickness
    with pytest.raises(
        SceneError, match=r"body 5 \(shape 'cube', free\) starts 0.08 m into body 2 \(shape 'wall_box_"
    ) as info:
        scene.validate()
    assert info.value.key == "bodies[5].position"


def fast_cube(speed, slab):
    """A 0.1 m steel cube (hertz, k = 1e10) at ``speed`` down onto a plane or a fixed 1 cm slab."""
    scene = Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_material("steel", density=7800.0, law="hertz", k=1.0e10, restitution=0.5, friction=0.3)
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("cube", "steel", position=(0.0, 0.0, 0.2), velocity=(0.0, 0.0, -speed))
    if slab:
        scene.add_shape("slab", ConvexShape.box(1.0, 1.0, 0.01))
        scene.add_body("slab", "steel", kind="fixed")
    else:
        scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "steel")
    return scene


@pytest.mark.parametrize(
    "speed, slab, limit", [(1000.0, False, r"164 m/s"), (100.0, True, r"29\.2 m/s"), (1.0, True, None)]
)
def test_initial_speed_that_tunnels_is_warned(speed, slab, limit):
    # BEFORE: no warning; the 1000 m/s cube passed through the plane, the 100 m/s one through the slab.
    # The limits: half the kinetic energy at which the cube has crossed the plane (its own 1e-3 m^3
    # in it) or the slab (1e-4 m^3: its face times 1 cm) on the loading curve 2/3 k V^1.5.
    scene = fast_cube(speed, slab)
    if limit is None:
        with warnings.catch_warnings():
            warnings.simplefilter("error", SceneWarning)
            scene.validate()
        return
    with pytest.warns(SceneWarning, match=rf"body 0 \(shape 'cube', free\) starts at \S+ m/s, above the {limit} "):
        scene.validate()
    assert any("may pass through what it hits" in w for w in scene.warnings)


def test_time_step_bound_of_tunnelling():
    # A 2 mm slab and a dt near the stable limit: at 8 m/s the cube moves 0.52 mm a step, above half
    # the slab's 1 mm half-thickness, before its energy (limit 8.7 m/s) could carry it through.
    scene = Scene(gravity=(0.0, 0.0, -9.81), dt=6.5e-5)
    scene.add_material("steel", density=7800.0, law="hertz", k=1.0e10, restitution=0.5, friction=0.3)
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_shape("slab", ConvexShape.box(1.0, 1.0, 0.002))
    scene.add_body("cube", "steel", position=(0.0, 0.0, 0.2), velocity=(0.0, 0.0, -8.0))
    scene.add_body("slab", "steel", kind="fixed")
    with pytest.warns(SceneWarning, match=r"above the 7\.69 m/s at which a step of 6\.5e-05 s moves it 0\.5 .*dt"):
        scene.validate()


def test_initial_overlap_check_is_fast_and_quiet_for_the_shipped_scenes():
    for path in sorted(SCENES.glob("*.toml")):
        scene = Scene.from_toml(path, validate=False)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("error", SceneWarning)
            scene.validate()
        elapsed = time.perf_counter() - t0
        assert scene.warnings == []
        assert elapsed < (3.0 if scene.num_bodies > 50_000 else 0.5), f"{path.name}: {elapsed:.2f} s"
    with warnings.catch_warnings():
        warnings.simplefilter("error", SceneWarning)
        default_scene(2000)


def test_mesh_file_errors_in_a_scene_file(tmp_path):
    (tmp_path / "nan.obj").write_text(
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv nan 0.5 0.5\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
    )
    (tmp_path / "noise.stl").write_bytes(np.random.default_rng(1).integers(0, 256, 500, dtype=np.uint8).tobytes())
    for name, match in (
        ("nan.obj", r"mesh file '\S+nan.obj', line 5: vertex 5 'v nan 0.5 0.5' has a non-finite coordinate"),
        ("noise.stl", r"cannot read mesh file '\S+noise.stl': not a valid STL file .*re-export it as OBJ, STL or PLY"),
    ):
        err = load_error(tmp_path, BASE_TOML + f'\n[shapes.mesh]\ntype = "mesh"\nfile = "{name}"\n')
        assert err.key == "shapes.mesh" and re.search(match, err.message), err.message
        assert "charset_normalizer" not in err.message


def test_toml_until_settled(tmp_path):
    """Before: [simulation] until_settled and [simulation.settle] were unknown keys; now they give the
    scene a SettleCriterion (duration or steps then is the maximum), written back by to_dict."""
    from polydem import SettleCriterion

    assert Scene.from_toml(write(tmp_path, BASE_TOML)).settle is None
    on = BASE_TOML.replace("steps = 100", "steps = 100\nuntil_settled = true")
    assert Scene.from_toml(write(tmp_path, on)).settle == SettleCriterion()
    table = BASE_TOML.replace(
        "steps = 100", "steps = 100\n[simulation.settle]\nkinetic_fraction = 1e-3\nmax_speed = 0.01\nhold = 0.1"
    )
    scene = Scene.from_toml(write(tmp_path, table))
    assert scene.settle == SettleCriterion(kinetic_fraction=1e-3, max_speed=0.01, hold=0.1)
    assert Scene.from_dict(scene.to_dict()).settle == scene.settle
    assert "until settled (kinetic energy < 0.001" in scene.describe()
    table = table.replace("hold = 0.1", "hold = 0.1\nspeed_fraction = 1e-3")
    table = table.replace("max_speed = 0.01\n", "")
    scene = Scene.from_toml(write(tmp_path, table))
    assert scene.settle == SettleCriterion(kinetic_fraction=1e-3, speed_fraction=1e-3, hold=0.1)
    assert Scene.from_dict(scene.to_dict()).settle == scene.settle
    speed = BASE_TOML.replace(
        "steps = 100", "steps = 100\nuntil_settled = true\nsettle = {kinetic_fraction = false, max_speed = 0.01}"
    )
    scene = Scene.from_toml(write(tmp_path, speed))
    assert scene.settle == SettleCriterion(kinetic_fraction=None, max_speed=0.01)
    assert Scene.from_dict(scene.to_dict()).settle == scene.settle


@pytest.mark.parametrize(
    ("lines", "key", "match"),
    [
        ("until_settled = 1", "simulation.until_settled", "expected true or false"),
        ("until_settled = false\nsettle = {hold = 0.1}", "simulation.until_settled", "set until_settled = true"),
        ("settle = 0.1", "simulation.settle", "expected a table"),
        ("settle = {kinetic_fraction = 0.0}", "simulation.settle.kinetic_fraction", "must be positive"),
        ("settle = {kinetic_fraction = -1e-4}", "simulation.settle.kinetic_fraction", "must be positive"),
        ("settle = {kinetic_fraction = 2.0}", "simulation.settle.kinetic_fraction", "must be < 1"),
        ("settle = {hold = -0.1}", "simulation.settle.hold", "must not be negative"),
        ("settle = {max_speed = 0}", "simulation.settle.max_speed", "must be positive"),
        (
            "settle = {kinetic_fraction = false, speed_fraction = false}",
            "simulation.settle.max_speed",
            "give max_speed",
        ),
        ("settle = {speed_fraction = 0}", "simulation.settle.speed_fraction", "must be positive"),
        ("settle = {hodl = 0.1}", "simulation.settle.hodl", "did you mean 'hold'"),
        ("until_settled = true", "simulation.settle", "no gravity: give max_speed alone"),
    ],
)
def test_toml_until_settled_errors(tmp_path, lines, key, match):
    text = BASE_TOML.replace("steps = 100", f"steps = 100\n{lines}")
    if "no gravity" in match:
        text = text.replace("gravity = [0.0, 0.0, -9.81]", "gravity = [0.0, 0.0, 0.0]")
    err = load_error(tmp_path, text)
    assert err.key == key
    assert re.search(match, str(err)), str(err)
    assert "\n" not in str(err)


def test_derived_tangential_spring_has_the_normal_frequency():
    """The derived friction spring is k_n / rotation_factor: a sticking contact's tangential-rotational
    oscillation then has the normal contact's frequency (BEFORE: kt = k_n, so a cube's sticking corner
    contact oscillated 2.35x faster than dt = "auto" assumed, and a packed pile gained 2e-2 of its
    released energy at 4x the step). A given spring enters the time step with the factor."""
    from polydem.scene.checks import reference_stiffness, rotation_factor

    cube = ConvexShape.box(0.02)
    assert rotation_factor(cube, 2500.0 * cube.volume, 2500.0 * np.asarray(cube.inertia)) == pytest.approx(5.5)
    # A sphere (fine icosphere): 1 + m r^2 / (2/5 m r^2) = 3.5, the usual kt = 2/7 k_n.
    ball = ConvexShape.from_points(trimesh.creation.icosphere(subdivisions=3, radius=0.01).vertices)
    assert rotation_factor(ball, 1000.0 * ball.volume, 1000.0 * np.asarray(ball.inertia)) == pytest.approx(
        3.5, rel=0.02
    )
    assert rotation_factor(cube, 0.0, np.zeros(3)) == 1.0

    scene = Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_material("stone", density=2500.0, law="hertz", k=1e8, restitution=0.4, friction=0.5)
    scene.add_shape("cube", ConvexShape.box(0.02))
    scene.add_body("cube", "stone", position=(0.0, 0.0, 0.1))
    ts = scene.time_step()
    k_n = float(reference_stiffness("hertz", 1e8, 1.5, cube.volume))
    assert float(ts.tangential_stiffness[0, 0]) == pytest.approx(k_n / 5.5)
    # The same spring given in the material: the same step; k_n given: the step shrinks by sqrt(5.5).
    for kt, ratio in ((k_n / 5.5, 1.0), (k_n, math.sqrt(5.5))):
        other = Scene(gravity=(0.0, 0.0, -9.81))
        other.add_material(
            "stone", density=2500.0, law="hertz", k=1e8, restitution=0.4, friction=0.5, tangential_stiffness=kt
        )
        other.add_shape("cube", ConvexShape.box(0.02))
        other.add_body("cube", "stone", position=(0.0, 0.0, 0.1))
        assert other.time_step().period == pytest.approx(ts.period / ratio, rel=1e-9)


def validation_warnings(scene, word):
    """The warnings ``scene.validate()`` issues that contain ``word``."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene.validate()
    return [str(w.message) for w in caught if word in str(w.message)]


@pytest.mark.parametrize(
    "law, scale, warned",
    [
        ("hertz", 4.0, True),
        ("hertz", 2.0, False),
        ("hertz", None, False),
        ("power2", 4.0, False),
        ("linear", 4.0, False),
    ],
)
def test_a_step_above_the_toes_reach_is_warned_about(law, scale, warned):
    """Under hertz a given dt above 2 recommended steps puts the pile's small overlaps on the step's toe, whose
    V_c grows as dt^4 (BENCHMARKS.md 24-25: at 4 dt_rec the pour's pile is another): a warning that says so and
    how to mend it; none at 2, none for "auto", none for laws without the toe (power m = 2, linear)."""
    kw = {"power2": dict(law="power", m=2.0, k=1e12), "linear": dict(law="linear", k=1e6)}.get(
        law, dict(law=law, k=1e9)
    )
    scene = Scene(gravity=(0.0, 0.0, -9.81))
    scene.add_material("m", density=2500.0, restitution=0.5, friction=0.5, **kw)
    scene.add_shape("cube", ConvexShape.box(0.01))
    scene.add_body("cube", "m", position=(0.0, 0.0, 0.005))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    recommended = scene.time_step().recommended
    if scale is not None:
        scene.dt = scale * recommended
    found = validation_warnings(scene, "resolved toe")
    if not warned:
        assert not found
        return
    assert len(found) == 1 and found == [w for w in scene.warnings if "resolved toe" in w]
    text = found[0]
    assert "simulation.dt" in text and "4 times the recommended step" in text and "dt^4" in text
    assert "256 times larger" in text and f"({2.0 * recommended:.3g} s)" in text and '"auto"' in text


@pytest.mark.parametrize(
    "law, m, e, gravity, warned",
    [
        ("power", 2.0, 0.1, True, True),
        ("power", 3.0, 0.15, True, True),
        ("power", 2.0, 0.2, True, False),
        ("power", 1.75, 0.1, True, False),
        ("hertz", None, 0.1, True, False),
        ("power", 2.0, 0.1, False, False),
    ],
)
def test_a_power_law_without_the_toe_at_small_restitution_is_warned_about(law, m, e, gravity, warned):
    """Power m >= 2 has no resolved toe, and below e = 0.2 a contact that comes to rest rings (BENCHMARKS.md 26e):
    a warning naming the materials, the law and what to do; none from e = 0.2, none with the toe (hertz, power
    m < 2), none without gravity. Only the lower of two materials' mixed restitutions counts."""
    scene = Scene(gravity=(0.0, 0.0, -9.81) if gravity else (0.0, 0.0, 0.0))
    extra = {} if m is None else {"m": m}
    k = {2.0: 1e12, 3.0: 1e16, 1.75: 1e11}.get(m, 1e9)
    scene.add_material("steel", density=7800.0, law=law, k=k, restitution=e, friction=0.5, **extra)
    scene.add_material("rubber", density=1200.0, law=law, k=k, restitution=0.9, friction=0.5, **extra)
    scene.add_shape("cube", ConvexShape.box(0.01))
    scene.add_body("cube", "steel", position=(0.0, 0.0, 0.005))
    scene.add_body("cube", "rubber", position=(0.0, 0.0, 0.02))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "steel")
    found = validation_warnings(scene, "rings")
    if not warned:
        assert not found
        return
    assert len(found) == 1 and found == [w for w in scene.warnings if "rings" in w]
    text = found[0]
    assert f"restitution {e:g} between 'steel'" in text and f"m = {m:g}" in text
    assert "restitution >= 0.2" in text and 'law = "hertz"' in text
