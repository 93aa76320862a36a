"""Compound (non-convex) grains against slow, obviously right references: a grain cut into parts that
only touch against the same grain as one convex shape, finite differences of the summed volume, the
union's mass properties from the parts, and what a scene file, the checks and the output make of them."""

import numpy as np
import pytest
import trimesh

import polydem
from polydem import CompoundShape, ConvexShape, Scene, SceneError, Simulation
from polydem.compound import CompoundShapeError, expand_bodies, place
from polydem.quaternions import quat_multiply

H = 0.01
QZ = [0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)]


def split_cube():
    """A cube of edge H cut into two slabs, one of them given turned by 90 degrees about z (so the
    parts' frames differ from the grain's)."""
    return CompoundShape(
        [place(ConvexShape.box(H, H / 2, H), (-H / 4, 0, 0), QZ), place(ConvexShape.box(H / 2, H, H), (H / 4, 0, 0))],
        name="split",
    )


def l_partition():
    """An L of three unit cells as a 2-cell bar and a cell that touch."""
    return CompoundShape(
        [place(ConvexShape.box(2 * H, H, H), (H / 2, 0, 0)), place(ConvexShape.box(H, H, H), (0, H, 0))], name="L"
    )


def l_overlapping():
    """The same L as two 2-cell bars that share the corner cell."""
    return CompoundShape(
        [place(ConvexShape.box(2 * H, H, H), (H / 2, 0, 0)), place(ConvexShape.box(H, 2 * H, H), (0, H / 2, 0))],
        name="L",
    )


def random_poses(rng, n, centre, spread):
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.hstack([np.asarray(centre) + rng.normal(size=(n, 3)) * spread, q])


# ------------------------------------------------------------------------------ mass properties


def test_parts_that_touch_have_the_mass_properties_of_the_whole():
    c, cube = split_cube(), ConvexShape.box(H)
    assert not c.overlapping and c.num_parts == 2
    np.testing.assert_allclose(c.volume, cube.volume, rtol=1e-12)
    np.testing.assert_allclose(c.inertia, cube.inertia, rtol=1e-9)
    np.testing.assert_allclose(c.radius, cube.radius, rtol=1e-12)
    np.testing.assert_allclose(c.input_translation, 0.0, atol=1e-15)


def test_overlapping_parts_count_their_common_volume_once():
    a, b = l_partition(), l_overlapping()
    assert b.overlapping and not a.overlapping
    np.testing.assert_allclose(b.volume, 3 * H**3, rtol=1e-12)
    np.testing.assert_allclose(b.volume, a.volume, rtol=1e-12)
    np.testing.assert_allclose(b.inertia, a.inertia, rtol=1e-9)
    np.testing.assert_allclose(b.input_translation, a.input_translation, atol=1e-15)
    # centroid of the L: mean of its three cells' centres
    np.testing.assert_allclose(a.input_translation, [H / 3, H / 3, 0.0], atol=1e-15)
    np.testing.assert_allclose(b.radius, a.radius, rtol=1e-12)


def test_union_mass_properties_need_no_boolean_library(monkeypatch):
    """Without manifold3d the mass properties are the same (inclusion-exclusion over the parts'
    common pieces); only the surface drawn is the parts' surfaces together."""
    import builtins

    real = builtins.__import__

    def no_manifold(name, *args, **kw):
        if name == "manifold3d":
            raise ImportError(name)
        return real(name, *args, **kw)

    monkeypatch.setattr(builtins, "__import__", no_manifold)
    b = l_overlapping()
    np.testing.assert_allclose(b.volume, 3 * H**3, rtol=1e-12)
    np.testing.assert_allclose(b.inertia, l_partition().inertia, rtol=1e-9)


def test_three_overlapping_parts_by_inclusion_exclusion():
    """Three bars along x, y and z through one cube cell (a 3D cross of 7 cells): the cell shared by
    all three counted once."""
    bars = [ConvexShape.box(*(3 * H if k == axis else H for k in range(3))) for axis in range(3)]
    cross = CompoundShape(bars)
    cells = CompoundShape(
        [ConvexShape.box(3 * H, H, H)]
        + [place(ConvexShape.box(H), s * H * np.eye(3)[axis]) for axis in (1, 2) for s in (-1, 1)]
    )
    assert cross.overlapping and not cells.overlapping
    np.testing.assert_allclose(cross.volume, 7 * H**3, rtol=1e-12)
    np.testing.assert_allclose(cross.inertia, cells.inertia, rtol=1e-12)
    np.testing.assert_allclose(cross.input_translation, 0.0, atol=1e-17)


def test_bad_parts_are_refused():
    with pytest.raises(CompoundShapeError, match="at least one part"):
        CompoundShape([])
    with pytest.raises(CompoundShapeError, match="not a ConvexShape"):
        CompoundShape([ConvexShape.box(H), "box"])
    with pytest.raises(CompoundShapeError, match="quaternion"):
        place(ConvexShape.box(H), (0, 0, 0), (0, 0, 0, 0))
    with pytest.raises(CompoundShapeError, match="position"):
        place(ConvexShape.box(H), (0, 0), (0, 0, 0, 1))


# ------------------------------------------------------------------------------ the pair geometry


@pytest.mark.parametrize("precision,tol", [("float64", 1e-12), ("float32", 2e-6)])
def test_pair_sum_over_touching_parts_equals_the_whole(device, precision, tol):
    """Every quantity of the contact, grain against a rock and grain against grain, equals that of
    the uncut cube (the faces where the parts touch cancel)."""
    rng = np.random.default_rng(1)
    rock = ConvexShape.rock(20, 1.2 * H, seed=3)
    pa = random_poses(rng, 150, (0, 0, 0), 0.1 * H)
    pb = random_poses(rng, 150, (0.9 * H, 0, 0), 0.4 * H)
    split, cube = split_cube(), ConvexShape.box(H)
    for a, b, ref_a, ref_b in ((split, rock, cube, rock), (rock, split, rock, cube), (split, split, cube, cube)):
        got = polydem.overlap(a, pa, b, pb, device=device, precision=precision)
        ref = polydem.overlap(ref_a, pa, ref_b, pb, device=device, precision=precision)
        assert (ref.volume > 0).sum() > 50
        vmax, smax = ref.volume.max(), np.abs(ref.area_vector).max()
        np.testing.assert_allclose(got.volume, ref.volume, atol=tol * vmax)
        np.testing.assert_allclose(got.area_vector, ref.area_vector, atol=tol * smax)
        np.testing.assert_allclose(got.area_vector_b, ref.area_vector_b, atol=tol * smax)
        np.testing.assert_allclose(got.moment, ref.moment, atol=tol * smax * H)
        np.testing.assert_allclose(got.moment_b, ref.moment_b, atol=tol * smax * H)
        touching = ref.volume > 1e-6 * vmax
        np.testing.assert_allclose(got.centroid[touching], ref.centroid[touching], atol=1e3 * tol * H)


def test_summed_volume_has_the_summed_area_vector_as_gradient(device):
    """dV/dx_A = S_A and the rotational derivative M_A - x_A x S_A for the sum over the part pairs
    of a grain whose parts overlap (the sum, not the union's volume, is the energy's argument)."""
    grain, rock = l_overlapping(), ConvexShape.rock(20, 1.5 * H, seed=5)
    rng = np.random.default_rng(2)
    pa = random_poses(rng, 40, (0.002, 0.001, 0.0), 0.0)
    pb = random_poses(rng, 40, (0.004, 0.004, 0.006), 0.002)
    base = polydem.overlap(grain, pa, rock, pb, device=device, precision="float64")
    checked = 0
    eps = 1e-7
    for i in np.flatnonzero(base.volume > 1e-3 * base.volume.max()):
        for k in range(3):
            plus, minus = pa[i].copy(), pa[i].copy()
            plus[k] += eps
            minus[k] -= eps
            v = polydem.overlap(grain, np.array([plus, minus]), rock, pb[i], device=device, precision="float64").volume
            np.testing.assert_allclose((v[0] - v[1]) / (2 * eps), base.area_vector[i, k], rtol=1e-5, atol=1e-9 * H**2)
            # a turn of A by eps about axis k, about its centre
            axis = np.eye(3)[k]
            dq = np.concatenate([np.sin(eps / 2) * axis, [np.cos(eps / 2)]])
            turned = []
            for sign in (1, -1):
                p = pa[i].copy()
                p[3:] = quat_multiply(dq * [sign, sign, sign, 1], pa[i, 3:])
                turned.append(p)
            v = polydem.overlap(grain, np.array(turned), rock, pb[i], device=device, precision="float64").volume
            torque_arm = base.moment[i] - np.cross(pa[i, :3], base.area_vector[i])
            np.testing.assert_allclose((v[0] - v[1]) / (2 * eps), torque_arm[k], rtol=1e-5, atol=1e-9 * H**3)
        checked += 1
    assert checked >= 10


# ------------------------------------------------------------------------------ simulations


def two_grain_scene(shape, precision="float64", restitution=0.5, friction=0.5, mesh_floor=False):
    sc = Scene(gravity=(0, 0, -9.81), precision=precision)
    sc.add_material("m", density=2500, law="hertz", k=1e10, restitution=restitution, friction=friction)
    if mesh_floor:
        v = np.array([[-0.1, -0.1, 0], [0.1, -0.1, 0], [0.1, 0.1, 0], [-0.1, 0.1, 0]])
        sc.add_mesh_wall(trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False), "m")
    else:
        sc.add_plane(normal=(0, 0, 1), point=(0, 0, 0), material="m")
    q = np.array([0.1, 0.2, 0.05, 1.0])
    sc.add_body(shape, "m", position=(0, 0, 0.0075), orientation=q / np.linalg.norm(q), velocity=(0, 0, -0.3),
                angular_velocity=(3, 1, 2))  # fmt: skip
    sc.add_body(shape, "m", position=(0.003, 0.001, 0.0195), velocity=(0, 0, -0.6))
    return sc


@pytest.mark.parametrize("precision", ["float64", "mixed"])
@pytest.mark.parametrize("mesh_floor", [False, True])
def test_grain_of_touching_parts_moves_like_the_whole(device, mesh_floor, precision):
    """Two cut cubes hit a floor (plane or 2-triangle mesh) and each other, with damping and
    friction: their run follows that of two whole cubes to rounding (float32 geometry in mixed:
    measured 6e-11 m, 5.7e-8 m/s and 4.7e-8 of the energy after 3000 steps)."""
    runs = []
    for shape in (split_cube(), ConvexShape.box(H, name="split")):
        sim = Simulation(two_grain_scene(shape, precision=precision, mesh_floor=mesh_floor), device=device)
        sim.step(3000)
        st = sim.state()
        runs.append((st["body_position"], st["body_velocity"], sim.energy()))
        assert runs[-1][2]["dissipated"] > 0.0 or len(runs) == 1
    (p1, v1, e1), (p2, v2, e2) = runs
    loose = precision == "mixed"
    np.testing.assert_allclose(p1, p2, atol=1e-9 if loose else 1e-11)
    np.testing.assert_allclose(v1, v2, atol=1e-6 if loose else 1e-8)
    np.testing.assert_allclose(e1["total"], e2["total"], rtol=1e-6 if loose else 1e-9)


@pytest.mark.filterwarnings("ignore:.*parts of this compound grain overlap")
def test_elastic_compound_grains_keep_their_energy(device):
    """Overlapping-part L grains dropped on a floor and on each other, elastic and frictionless:
    the energy (kinetic, gravity, contact) stays put (the summed volume is a potential)."""
    grain = l_overlapping()
    sc = Scene(gravity=(0, 0, -9.81), precision="float64")
    sc.add_material("m", density=2500, law="hertz", k=1e10, restitution=1.0, friction=0.0)
    sc.add_plane(normal=(0, 0, 1), point=(0, 0, 0), material="m")
    sc.add_body(grain, "m", position=(0, 0, 0.0051), velocity=(0, 0, -0.2))
    q = np.array([0.5, 0.5, 0.0, 1.0])
    sc.add_body(grain, "m", position=(0.002, 0.0, 0.03), orientation=q / np.linalg.norm(q), velocity=(0, 0, -1.0))
    sim = Simulation(sc, device=device)
    e0 = sim.energy()["total"]
    touched = False
    for _ in range(8):
        sim.step(2500)
        touched |= len(sim.contacts()["body_a"]) > 0
        e = sim.energy()
        assert e["dissipated"] == 0.0
        assert abs(e["total"] - e0) < 2e-3 * e0
    assert touched


# ------------------------------------------------------------------------------ scene files and checks


def scene_dict(shape_table, bodies=None):
    return {
        "simulation": {"gravity": [0, 0, -9.81], "precision": "float64"},
        "materials": {"m": {"density": 2500, "law": "hertz", "k": 1e10, "restitution": 0.5, "friction": 0.5}},
        "shapes": {"g": shape_table},
        "walls": [{"type": "plane", "normal": [0, 0, 1], "point": [0, 0, 0], "material": "m"}],
        "bodies": bodies or [{"shape": "g", "material": "m", "position": [0, 0, 0.02]}],
    }


def test_scene_file_compound_from_parts():
    table = {
        "type": "compound",
        "parts": [
            {"type": "box", "size": [2 * H, H, H], "position": [H / 2, 0, 0]},
            {"type": "box", "size": [H, H, H], "position": [0, H, 0], "rotation": {"axis": [0, 0, 1], "degrees": 90}},
        ],
    }
    sc = Scene.from_dict(scene_dict(table))
    g = sc.shapes["g"]
    assert isinstance(g, CompoundShape) and g.num_parts == 2
    np.testing.assert_allclose(g.volume, l_partition().volume, rtol=1e-12)
    np.testing.assert_allclose(g.inertia, l_partition().inertia, rtol=1e-9)
    again = Scene.from_dict(sc.to_dict())  # the normalised spec round-trips
    np.testing.assert_allclose(again.shapes["g"].inertia, g.inertia, rtol=1e-12)


def test_overlapping_parts_are_warned_about_touching_parts_are_not():
    import warnings

    from polydem.scene import SceneWarning

    def parts(shift):
        return {
            "type": "compound",
            "parts": [
                {"type": "box", "size": [2 * H, H, H], "position": [H / 2, 0, 0]},
                {"type": "box", "size": H, "position": [0, shift, 0]},
            ],
        }

    with pytest.warns(SceneWarning, match=r"shapes\.g: parts of this compound grain overlap each other"):
        Scene.from_dict(scene_dict(parts(0.5 * H))).validate()
    with warnings.catch_warnings():
        warnings.simplefilter("error", SceneWarning)
        Scene.from_dict(scene_dict(parts(H))).validate()


def test_python_compound_is_written_as_parts_of_points():
    sc = Scene.from_dict(scene_dict({"type": "box", "size": H}))
    sc.add_shape("L", l_partition())
    table = sc.to_dict()["shapes"]["L"]
    assert table["type"] == "compound" and len(table["parts"]) == 2
    back = Scene.from_dict(scene_dict(table)).shapes["g"]
    np.testing.assert_allclose(back.inertia, l_partition().inertia, rtol=1e-9)


@pytest.mark.parametrize(
    "table,key,words",
    [
        ({"type": "compound"}, "shapes.g", "either parts"),
        ({"type": "compound", "parts": []}, "shapes.g.parts", "non-empty array"),
        ({"type": "compound", "parts": [{"type": "compound", "parts": []}]}, "shapes.g.parts[0].type", "convex"),
        ({"type": "compound", "parts": [{"type": "box", "size": H, "colour": 1}]}, "shapes.g.parts[0]", "colour"),
        ({"type": "compound", "parts": [{"type": "box", "size": H, "position": [0, 0]}]}, "position", "3"),
        ({"type": "compound", "parts": [{"type": "box", "size": H}], "threshold": 0.1}, "threshold", "mesh file"),
        ({"type": "compound", "file": "missing.obj"}, "shapes.g.file", "not found"),
        ({"type": "compound", "file": "x.obj", "parts": [{"type": "box", "size": H}]}, "shapes.g", "not both"),
    ],
)
def test_bad_compound_tables_name_the_key(table, key, words):
    with pytest.raises(SceneError) as err:
        Scene.from_dict(scene_dict(table))
    assert key in str(err.value) and words in str(err.value)


def l_mesh(path):
    """A closed non-convex L prism as an OBJ file."""
    a = trimesh.creation.box((2 * H, H, H))
    a.apply_translation((H / 2, 0, 0))
    b = trimesh.creation.box((H, H, H))
    b.apply_translation((0, H, 0))
    m = trimesh.util.concatenate([a, b])
    m.export(path)
    return path


def test_compound_from_a_file_by_components(tmp_path):
    l_mesh(tmp_path / "l.obj")
    sc = Scene.from_dict(
        scene_dict({"type": "compound", "file": "l.obj", "decompose": "components"}), base_dir=tmp_path
    )
    g = sc.shapes["g"]
    assert g.num_parts == 2
    np.testing.assert_allclose(g.volume, 3 * H**3, rtol=1e-12)


def test_compound_from_a_file_by_coacd(tmp_path):
    pytest.importorskip("coacd")
    pytest.importorskip("manifold3d")
    m = trimesh.boolean.union([trimesh.creation.box((2 * H, H, H)), trimesh.creation.box((H, 3 * H, H))])
    m.export(tmp_path / "t.stl")
    g = CompoundShape.from_mesh(tmp_path / "t.stl", decompose="coacd", threshold=0.05, seed=1)
    assert g.num_parts >= 2
    # the parts cover the mesh: the union's volume is the mesh's within CoACD's tolerance
    assert abs(g.volume - m.volume) < 0.05 * m.volume


def test_interlocked_grains_are_not_reported_as_overlapping():
    """Two L grains, one turned by 180 degrees with its corner cell in the other's notch: their hulls
    overlap but their parts do not, so no initial-overlap warning; pushed into each other, one
    record for the pair (not one per part pair)."""
    d = 1e-4
    sc = Scene(gravity=(0, 0, -9.81), precision="float64")
    sc.add_material("m", density=2500, law="hertz", k=1e10, restitution=0.5, friction=0.5)
    sc.add_shape("L", l_partition())
    sc.add_body("L", "m", position=(0, 0, 0))
    sc.add_body("L", "m", position=(H + d, 2 * H + d, 0), orientation=(0, 0, 1, 0))
    a = sc.body_arrays()
    assert sc.check_initial_overlaps(a) == []
    a["position"][1, 0] -= 0.3 * H
    found = sc.check_initial_overlaps(a)
    assert len(found) == 1 and found[0].startswith("1 initial overlaps")


def test_expand_bodies_places_the_parts():
    grain = split_cube()
    q = np.array([0.3, -0.2, 0.5, 0.8])
    q /= np.linalg.norm(q)
    convex, part, pos, quat, owner = expand_bodies([ConvexShape.box(H), grain], [1, 0], [[1, 2, 3], [0, 0, 0]], [q, q])
    assert owner.tolist() == [0, 0, 1] and part.tolist() == [1, 2, 0]
    from polydem.quaternions import quat_to_matrix

    for k in range(2):
        world = convex[part[k]].vertices @ quat_to_matrix(quat[k]).T + pos[k]
        body = (grain.part_vertices()[k]) @ quat_to_matrix(q).T + [1, 2, 3]
        np.testing.assert_allclose(world, body, atol=1e-15)


# ------------------------------------------------------------------------------ output


def test_picture_draws_the_grain_not_its_hull(device):
    """Seen from above, the notch of an L shows the floor; its arms show the grain."""
    from polydem.quaternions import quat_from_matrix
    from polydem.render import Camera, render_layers

    grain = l_partition()
    # the grain's input frame (the corner cell's centre at its origin) at (0, 0, H/2), unturned
    centre = grain.input_translation + [0, 0, H / 2]
    q = quat_from_matrix(grain.input_rotation)
    cam = Camera(position=(0.0, 0.0, 0.3), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov=10.0)
    layers = render_layers([centre], [q], [0], [grain], width=64, height=64, camera=cam, device=device, shadows=False)
    hit = layers["hit"]

    def at(x, y):  # the pixel looking at world (x, y) on the floor
        u = 32 + x / (0.3 * np.tan(np.radians(5))) * 32
        v = 32 - y / (0.3 * np.tan(np.radians(5))) * 32
        return hit[int(v), int(u)]

    assert at(0.0, 0.0) == 0 and at(H, 0.0) == 0 and at(0.0, H) == 0
    assert at(H, H) == -1  # the notch


def test_usd_prototype_is_the_union_surface(tmp_path):
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    from polydem.usd import UsdRecorder

    sc = two_grain_scene(l_partition())
    with UsdRecorder(tmp_path / "c.usda", sc) as rec:
        rec.record(0.0, sc.body_position, sc.body_orientation)
    stage = Usd.Stage.Open(str(tmp_path / "c.usda"))
    inst = UsdGeom.PointInstancer.Get(stage, "/World/Bodies")
    (target,) = inst.GetPrototypesRel().GetTargets()
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(target))
    pts = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
    tri = np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3)
    assert trimesh.Trimesh(pts, tri).volume == pytest.approx(3 * H**3, rel=1e-6)


def test_checkpoint_knows_the_parts(tmp_path):
    from polydem.checkpoint import physics_description

    a = physics_description(two_grain_scene(l_partition()), 1e-6)[0]
    moved = CompoundShape(
        [place(ConvexShape.box(2 * H, H, H), (H / 2, 0, 0)), place(ConvexShape.box(H, H, H), (0, H, 0), QZ)], name="L"
    )
    b = physics_description(two_grain_scene(moved), 1e-6)[0]
    assert any(k.startswith("shapes.L.parts[1]") and a[k] != b[k] for k in a)
