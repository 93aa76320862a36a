"""polydem.vtk: ParaView output (.pvd series of .vtu frames), read back with meshio; polydem run --vtk."""

import json
import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest

meshio = pytest.importorskip("meshio")

import cli_helpers  # noqa: E402
from cli_helpers import run  # noqa: E402

import polydem  # noqa: E402
from polydem.scene import quat_from_axis_angle, quat_to_matrix  # noqa: E402
from polydem.vtk import CONTACT_TYPES, SERIES, VtkWriter, read_pvd  # noqa: E402

STEPS = 7  # simulation steps between frames
FRAMES = 4
GAP = 1e-4  # [m] between the bodies at the start: no contact in frame 0, contacts soon after


def lowest(shape, q):
    """Lowest z of the shape's vertices turned by q, relative to its centre."""
    return float((shape.vertices @ quat_to_matrix(q).T)[:, 2].min())


def make_scene():
    scene = polydem.Scene(gravity=(0, 0, -9.81), dt="auto", name="vtk-test")
    scene.add_material("steel", density=7800, law="hertz", k=1e10, restitution=0.5, friction=0.3)
    cube = polydem.ConvexShape.box(0.1, 0.08, 0.06)
    tet = polydem.ConvexShape.tetrahedron(0.12)
    scene.add_shape("cube", cube)
    scene.add_shape("tet", tet)
    scene.add_shape("prism", polydem.ConvexShape.prism(5, 0.05, 0.1))  # pentagons: "polygon" cells
    q_cube = quat_from_axis_angle((0, 0, 1), 0.3)
    z_cube = GAP - lowest(cube, q_cube)
    scene.add_body("cube", "steel", position=(0, 0, z_cube), orientation=q_cube, velocity=(0, 0, -1))
    q_tet = quat_from_axis_angle((1, 2, 3), 1.1)  # every component non-zero: an xyzw/wxyz mix-up shows
    top = z_cube + float((cube.vertices @ quat_to_matrix(q_cube).T)[:, 2].max())
    scene.add_body(
        "tet",
        "steel",
        position=(0.0, 0.0, top + GAP - lowest(tet, q_tet)),
        orientation=q_tet,
        velocity=(0.1, 0, -3),
        angular_velocity=(1, 2, 3),
    )
    scene.add_body("prism", "steel", position=(0.4, 0, 0.3), kind="kinematic", velocity=(0, 0.5, 0))
    scene.add_body("cube", "steel", position=(-0.4, 0, 0.3), kind="fixed")
    scene.add_plane(point=(0, 0, 0), normal=(0, 0, 1), material="steel")
    # The reference overlap's step, not the smaller one that resolves a body resting under its own
    # weight (issue 11): the frames are a fixed number of steps apart and must see the impacts.
    scene.dt = scene.time_step().period / 50
    return scene


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """A VtkWriter's folder and, per frame, (time, state, contacts) as the simulation reported them."""
    folder = tmp_path_factory.mktemp("vtk") / "vtk"
    scene = make_scene()
    sim = polydem.Simulation(scene, device="cpu")
    frames = []
    with VtkWriter(folder, sim) as writer:
        for k in range(FRAMES):
            st, c = sim.state(), sim.contacts()
            assert writer.record_simulation(sim) == k
            frames.append((sim.time, st, c))
            sim.step(STEPS)
    assert writer.closed and writer.frames == FRAMES
    assert len(frames[0][2]["volume"]) == 0  # frame 0: no contact yet (an empty contacts file)
    last = frames[-1][2]
    assert (last["body_b"] >= 0).any() and (last["body_b"] < 0).any()  # a pair and a wall contact
    return scene, folder, frames


def number_of_cells(path):
    return int(ET.parse(path).getroot().find("./UnstructuredGrid/Piece").get("NumberOfCells"))


def frame_file(folder, name, k):
    return folder / name / f"{name}_{k:06d}.vtu"


def cell_arrays(mesh, name):
    """A cell data array over every cell block, in cell order."""
    return np.concatenate(mesh.cell_data[name])


def test_pvd_series_list_every_frame_with_its_time(written):
    _, folder, frames = written
    for name in SERIES:
        root = ET.parse(folder / f"{name}.pvd").getroot()
        assert root.tag == "VTKFile" and root.get("type") == "Collection"
        sets = root.findall("./Collection/DataSet")
        assert [d.get("file") for d in sets] == [f"{name}/{name}_{k:06d}.vtu" for k in range(FRAMES)]
        assert [float(d.get("timestep")) for d in sets] == [t for t, _, _ in frames]  # repr: exact
        entries = read_pvd(folder / f"{name}.pvd")
        assert all(f.is_file() for _, f in entries)
    assert not list(folder.rglob("*.tmp"))


def test_particles_are_the_polyhedra_in_world_coordinates(written):
    scene, folder, frames = written
    for k, (_, st, _) in enumerate(frames):
        mesh = meshio.read(frame_file(folder, "particles", k))
        body = cell_arrays(mesh, "body_id")
        loops = [mesh.points[c].astype(np.float64) for block in mesh.cells for c in block.data]
        assert len(loops) == len(body) == sum(len(scene.shapes[scene.shape_names[s]].faces) for s in scene.body_shape)
        for i in range(scene.num_bodies):
            s = int(scene.body_shape[i])
            shape = scene.shapes[scene.shape_names[s]]
            rot = quat_to_matrix(st["body_orientation"][i])
            expected = [shape.vertices[f] @ rot.T + st["body_position"][i] for f in shape.faces]
            got = [loops[j] for j in np.flatnonzero(body == i)]
            # Every face of the body, as the same loop of vertices (counter-clockwise from outside).
            assert len(got) == len(expected)
            for face in expected:
                assert any(g.shape == face.shape and np.allclose(g, face, atol=1e-6) for g in got)
            rows = body == i
            assert (cell_arrays(mesh, "shape_id")[rows] == s).all()
            assert (cell_arrays(mesh, "kind")[rows] == scene.body_kind[i]).all()
            for key, value in (("velocity", "body_velocity"), ("angular_velocity", "body_angular_velocity")):
                got = cell_arrays(mesh, key)[rows]
                np.testing.assert_array_equal(got, np.broadcast_to(np.float32(st[value][i]), got.shape))
        assert {block.type for block in mesh.cells} == {"quad", "triangle", "polygon"}


def test_centres_carry_the_state(written):
    scene, folder, frames = written
    moved = 0.0
    for k, (_, st, _) in enumerate(frames):
        mesh = meshio.read(frame_file(folder, "centres", k))
        d = mesh.point_data
        np.testing.assert_array_equal(mesh.points, np.float32(st["body_position"]))  # the simulator's float32
        np.testing.assert_array_equal(d["body_id"], np.arange(scene.num_bodies))
        np.testing.assert_array_equal(d["shape_id"], scene.body_shape)
        np.testing.assert_array_equal(d["kind"], scene.body_kind)
        np.testing.assert_allclose(d["orientation"], st["body_orientation"], atol=1e-7)
        np.testing.assert_array_equal(d["velocity"], np.float32(st["body_velocity"]))
        np.testing.assert_array_equal(d["angular_velocity"], np.float32(st["body_angular_velocity"]))
        shapes = [scene.shapes[scene.shape_names[s]] for s in scene.body_shape]
        np.testing.assert_allclose(d["radius"], [s.radius for s in shapes], rtol=1e-6)
        np.testing.assert_allclose(
            4.0 / 3.0 * math.pi * d["equivalent_radius"].astype(np.float64) ** 3, [s.volume for s in shapes], rtol=1e-5
        )
        assert [c.type for c in mesh.cells] == ["vertex"] and len(mesh.cells[0].data) == scene.num_bodies
        moved = max(moved, float(np.abs(st["body_position"] - frames[0][1]["body_position"]).max()))
    assert moved > 1e-4  # the frames differ


def test_contacts_are_the_force_network(written):
    _, folder, frames = written
    checked = 0
    for k, (_, st, c) in enumerate(frames):
        path = frame_file(folder, "contacts", k)
        m = len(c["volume"])
        mesh = meshio.read(path)
        if m == 0:  # one vertex cell inside body 0 stands for no contact: meshio reads no grid without cells
            assert [b.type for b in mesh.cells] == ["vertex"] and len(mesh.cells[0].data) == 1
            np.testing.assert_array_equal(mesh.points, np.float32(st["body_position"][:1]))
            cd = {key: np.concatenate(v) for key, v in mesh.cell_data.items()}
            assert cd["body_a"].tolist() == cd["body_b"].tolist() == cd["wall"].tolist() == [-1]
            assert not np.any(cd["force"]) and not np.any(mesh.point_data["normal_force_magnitude"])
            continue
        assert [b.type for b in mesh.cells] == ["line"] and len(mesh.cells[0].data) == m
        cd = {key: np.concatenate(v) for key, v in mesh.cell_data.items()}
        assert "contact_type" not in cd  # off by default (VtkWriter(contact_types=True))
        a, b = c["body_a"], c["body_b"]
        wall = b < 0
        np.testing.assert_array_equal(cd["body_a"], a)
        np.testing.assert_array_equal(cd["body_b"], np.where(wall, -1, b))
        np.testing.assert_array_equal(cd["wall"], np.where(wall, -1 - b, -1))
        ends = mesh.points[mesh.cells[0].data]  # (m, 2, 3)
        x = st["body_position"]
        np.testing.assert_allclose(ends[:, 0], x[a], atol=1e-7)
        np.testing.assert_allclose(ends[:, 1], np.where(wall[:, None], c["point"], x[np.maximum(b, 0)]), atol=1e-7)
        fn = c["normal_force"]
        assert (fn > 0).any()
        np.testing.assert_array_equal(cd["normal_force_magnitude"], np.float32(fn))
        np.testing.assert_allclose(cd["normal_force"], -fn[:, None] * c["normal"], rtol=1e-6, atol=1e-6 * fn.max())
        np.testing.assert_allclose(np.linalg.norm(cd["normal_force"], axis=1), fn, rtol=1e-5)
        np.testing.assert_array_equal(cd["tangential_force"], np.float32(c["tangential_force"]))
        np.testing.assert_allclose(
            cd["tangential_force_magnitude"], np.linalg.norm(c["tangential_force"], axis=1), rtol=1e-6, atol=1e-6
        )
        np.testing.assert_allclose(cd["force"], cd["normal_force"] + cd["tangential_force"], rtol=1e-6, atol=1e-3)
        np.testing.assert_array_equal(cd["overlap_volume"], np.float32(c["volume"]))
        np.testing.assert_array_equal(cd["contact_point"], np.float32(c["point"]))
        np.testing.assert_array_equal(cd["normal"], np.float32(c["normal"]))
        # Tube filters scale by point data: both ends of a line carry its normal force.
        np.testing.assert_array_equal(
            mesh.point_data["normal_force_magnitude"][mesh.cells[0].data], np.float32(fn)[:, None].repeat(2, 1)
        )
        checked += 1
    assert checked >= 1


# ----------------------------------------------------------------------------- contact types

# The cases worked by hand in tests/test_measures.py: cubes of 1 cm sunk 1e-6 m into a floor by a
# face, an edge and a corner, and into each other face on face, edge on face, corner on face and
# edge across edge (the overlap a slab, a wedge, a pyramid, and a pyramid whose normal is 45 degrees
# from every face).
EDGE = 0.01  # [m]
SINK = 1e-6  # [m]
FACE_DOWN = np.array([0.0, 0.0, 0.0, 1.0])
EDGE_DOWN = quat_from_axis_angle((1, 0, 0), math.pi / 4)  # an edge along x lowest
EDGE_DOWN_Y = quat_from_axis_angle((0, 1, 0), math.pi / 4)  # an edge along y lowest
CORNER_DOWN = quat_from_axis_angle((-1, 1, 0), math.acos(-1.0 / math.sqrt(3.0)))  # the corner (1, 1, 1) lowest
CODE = {name: code for code, name in CONTACT_TYPES.items()}


def highest(shape, q):
    """Highest z of the shape's vertices turned by q, relative to its centre."""
    return float((shape.vertices @ quat_to_matrix(q).T)[:, 2].max())


def contact_type_scene(wall):
    """Bodies 0-2 on the floor (a plane or a flat mesh wall) by a face, an edge and a corner; pairs
    (3, 4), (5, 6), (7, 8), (9, 10) half a metre up, B sunk onto A. Returns (scene, {(body_a, body_b
    or -1 for the floor): expected code})."""
    scene = polydem.Scene(gravity=(0.0, 0.0, -9.81), dt="auto", precision="mixed")
    scene.add_material("grain", density=2500.0, law="hertz", k=4.9e8, restitution=0.3, friction=0.5)
    cube = polydem.ConvexShape.box(EDGE)
    scene.add_shape("cube", cube)
    expected = {}
    for k, (q, name) in enumerate(((FACE_DOWN, "face-face"), (EDGE_DOWN, "edge-face"), (CORNER_DOWN, "vertex-face"))):
        scene.add_body("cube", "grain", position=(0.05 * k, 0.0, -lowest(cube, q) - SINK), orientation=q)
        expected[(k, -1)] = CODE[name]
    pairs = [
        (FACE_DOWN, FACE_DOWN, "face-face"),
        (FACE_DOWN, EDGE_DOWN, "edge-face"),
        (FACE_DOWN, CORNER_DOWN, "vertex-face"),
        (EDGE_DOWN, EDGE_DOWN_Y, "edge-edge"),
    ]
    for k, (qa, qb, name) in enumerate(pairs):
        a = scene.add_body("cube", "grain", position=(0.05 * k, 0.0, 0.5), orientation=qa)
        z = 0.5 + highest(cube, qa) - lowest(cube, qb) - SINK
        b = scene.add_body("cube", "grain", position=(0.05 * k, 0.0, z), orientation=qb)
        expected[(int(a), int(b))] = CODE[name]
    if wall == "plane":
        scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "grain")
    else:
        square = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]]) * 0.2
        scene.add_mesh_wall((square, np.array([[0, 1, 2], [0, 2, 3]])), "grain")
    return scene, expected


def read_types(path):
    """{(body_a, body_b, or -1 for a wall): contact_type} of a contacts file."""
    mesh = meshio.read(path)
    cd = {key: np.concatenate(v) for key, v in mesh.cell_data.items()}
    keys = zip(cd["body_a"].tolist(), cd["body_b"].tolist(), strict=True)
    return dict(zip(keys, cd["contact_type"].tolist(), strict=True)), cd


@pytest.mark.parametrize("wall", ["plane", "mesh"])
@pytest.mark.parametrize("method", [True, "overlap"])
def test_contact_types_of_cubes_by_face_edge_corner_and_crossed_edges(tmp_path, wall, method):
    """Each line carries the code of its contact's kind, for pairs and wall contacts, by either method."""
    scene, expected = contact_type_scene(wall)
    sim = polydem.Simulation(scene, device="cpu")
    folder = tmp_path / "vtk"
    with VtkWriter(folder, sim, contact_types=method) as writer:
        assert writer.contact_types == ("features" if method is True else method)
        writer.record_simulation(sim)
        c = sim.contacts()
        st = sim.state()
        # Without the contacts' depth a mesh wall's contacts are not classified; the rest are.
        shallow = {key: v for key, v in c.items() if key != "depth"}
        writer.record(1.0, st, shallow)
        # A contact that only the average has (it ended before the frame) is not classified.
        ended = {"body_a": np.array([1]), "body_b": np.array([2]), "point": np.zeros((1, 3)),
                 "force": np.ones((1, 3)), "tangential_force": np.zeros((1, 3)), "normal_force": np.ones(1),
                 "contact_time": np.ones(1)}  # fmt: skip
        writer.record(2.0, st, c, average=ended)
    assert sorted(zip(c["body_a"].tolist(), np.maximum(c["body_b"], -1).tolist(), strict=True)) == sorted(expected)
    got, cd = read_types(frame_file(folder, "contacts", 0))
    assert got == expected
    assert cd["contact_type"].dtype == np.int32
    assert sorted(got.values()) == [0, 0, 1, 1, 2, 2, 3]  # every kind: not a constant
    got, _ = read_types(frame_file(folder, "contacts", 1))
    assert got == {k: (-1 if wall == "mesh" and k[1] == -1 else v) for k, v in expected.items()}
    got, cd = read_types(frame_file(folder, "contacts", 2))
    assert got == {**expected, (1, 2): -1}
    assert cd["current"].tolist() == [1] * len(expected) + [0]


def test_contact_types_codes_and_empty_frames(tmp_path):
    assert CONTACT_TYPES == {-1: "unclassified", 0: "face-face", 1: "edge-face", 2: "vertex-face", 3: "edge-edge"}
    scene, _ = contact_type_scene("plane")
    state = {
        "body_position": scene.body_position,
        "body_orientation": scene.body_orientation,
        "body_velocity": scene.body_velocity,
        "body_angular_velocity": scene.body_angular_velocity,
    }
    keys = ("body_a", "body_b", "normal", "point", "normal_force", "tangential_force", "volume")
    none = {key: np.zeros((0, 3) if key in ("normal", "point", "tangential_force") else 0) for key in keys}
    with VtkWriter(tmp_path / "vtk", scene, contact_types="features") as writer:
        writer.record(0.0, state, none)
    mesh = meshio.read(frame_file(tmp_path / "vtk", "contacts", 0))
    assert [b.type for b in mesh.cells] == ["vertex"]
    assert np.concatenate(mesh.cell_data["contact_type"]).tolist() == [-1]
    for bad in ("faces", 1, ""):
        with pytest.raises(ValueError, match="contact_types must be True, False, 'features' or 'overlap'"):
            VtkWriter(tmp_path / "bad", scene, contact_types=bad)


def test_walls_file(written):
    scene, folder, _ = written
    mesh = meshio.read(folder / "walls.vtu")
    assert [b.type for b in mesh.cells] == ["quad"] and len(mesh.cells[0].data) == len(scene.planes)
    plane = scene.planes[0]
    quad = mesh.points[mesh.cells[0].data[0]].astype(np.float64)
    np.testing.assert_allclose((quad - plane.point) @ plane.normal, 0.0, atol=1e-6)  # in the plane
    np.testing.assert_allclose(np.cross(quad[1] - quad[0], quad[2] - quad[1]) @ plane.normal > 0, True)  # faces out
    np.testing.assert_array_equal(np.concatenate(mesh.cell_data["normal"]), np.float32([plane.normal]))


def test_vtk_library_reads_every_file(written):
    """VTK's own XML reader (ParaView's) reads the files: the polyhedra are closed, outward surfaces."""
    vtk = pytest.importorskip("vtk")
    scene, folder, frames = written
    reader = vtk.vtkXMLUnstructuredGridReader()
    for name in SERIES:
        for k in range(FRAMES):
            reader.SetFileName(str(frame_file(folder, name, k)))
            reader.Update()
            grid = reader.GetOutput()
            lines = 2 * len(frames[k][2]["volume"]) or 1  # a frame without contacts: one point
            expected = {"particles": None, "centres": scene.num_bodies, "contacts": lines}
            if expected[name] is not None:
                assert grid.GetNumberOfPoints() == expected[name]
    reader.SetFileName(str(frame_file(folder, "particles", FRAMES - 1)))
    threshold = vtk.vtkThreshold()
    threshold.SetInputConnection(reader.GetOutputPort())
    threshold.SetInputArrayToProcess(0, 0, 0, vtk.vtkDataObject.FIELD_ASSOCIATION_CELLS, "body_id")
    threshold.SetLowerThreshold(1)
    threshold.SetUpperThreshold(1)
    surface = vtk.vtkGeometryFilter()
    surface.SetInputConnection(threshold.GetOutputPort())
    triangles = vtk.vtkTriangleFilter()
    triangles.SetInputConnection(surface.GetOutputPort())
    mass = vtk.vtkMassProperties()
    mass.SetInputConnection(triangles.GetOutputPort())
    mass.Update()
    assert mass.GetVolume() == pytest.approx(scene.shapes["tet"].volume, rel=1e-5)


def test_resume_continues_the_series_and_a_new_writer_starts_afresh(tmp_path):
    scene = make_scene()
    sim = polydem.Simulation(scene, device="cpu")
    states = []
    for _ in range(4):
        states.append((sim.time, sim.state(), sim.contacts()))
        sim.step(STEPS)
    folder = tmp_path / "vtk"
    with VtkWriter(folder, scene) as w:
        for k in range(3):
            w.record(*states[k], index=k)
    # A resumed run starts at frame 2 again (its checkpoint), then goes on.
    with VtkWriter(folder, scene, resume=True) as w:
        w.record(*states[2], index=2)
        w.record(*states[3], index=3)
    for name in SERIES:
        entries = read_pvd(folder / f"{name}.pvd")
        assert [t for t, _ in entries] == [s[0] for s in states]
        assert [f.name for _, f in entries] == [f"{name}_{k:06d}.vtu" for k in range(4)]
    # A fresh run in the same folder lists only its own frames, from the start.
    with VtkWriter(folder, scene) as w:
        for name in SERIES:
            assert read_pvd(folder / f"{name}.pvd") == []
        w.record(*states[0])
    assert [f.name for _, f in read_pvd(folder / "centres.pvd")] == ["centres_000000.vtu"]


def test_errors(tmp_path):
    scene = make_scene()
    state = {
        "body_position": scene.body_position,
        "body_orientation": scene.body_orientation,
        "body_velocity": scene.body_velocity,
        "body_angular_velocity": scene.body_angular_velocity,
    }
    no_contacts = {
        "body_a": np.zeros(0, int),
        "body_b": np.zeros(0, int),
        "normal": np.zeros((0, 3)),
        "point": np.zeros((0, 3)),
        "normal_force": np.zeros(0),
        "tangential_force": np.zeros((0, 3)),
        "volume": np.zeros(0),
    }
    (tmp_path / "file").write_text("keep")
    with pytest.raises(ValueError, match="is a file, not a folder"):
        VtkWriter(tmp_path / "file", scene)
    assert (tmp_path / "file").read_text() == "keep"
    w = VtkWriter(tmp_path / "v", scene)
    assert w.record(0.0, state, no_contacts, index=5) == 5
    with pytest.raises(ValueError, match="frame index 5 must be >= 0 and larger than the previous frame's"):
        w.record(0.1, state, no_contacts, index=5)  # would overwrite frame 5
    with pytest.raises(ValueError, match="finite time"):
        w.record(float("nan"), state, no_contacts)
    assert w.record(0.1, state, no_contacts) == 6
    w.close()
    with pytest.raises(RuntimeError, match="closed"):
        w.record(0.2, state, no_contacts)
    assert [f.name for _, f in read_pvd(tmp_path / "v" / "particles.pvd")] == [
        "particles_000005.vtu",
        "particles_000006.vtu",
    ]


# ---------------------------------------------------------------------- polydem run


SCENE = """\
[simulation]
name = "vtk_run"
dt = "auto"
steps = 120

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
position = [0.0, 0.0, 0.0501]
velocity = [0.0, 0.0, -1.0]

[[bodies]]
shape = "cube"
material = "steel"
position = [0.0, 0.02, 0.1503]
velocity = [0.0, 0.0, -3.0]
angular_velocity = [0.0, 0.0, 2.0]

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "steel"

[output]
fps = 20000
usd = "run.usda"
"""


def write_scene(folder, replace=()):
    return cli_helpers.write_scene(folder, SCENE, replace=replace)


def assert_user_error(code, err, *needles):
    assert code == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("polydem: error: ")
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def check_run_vtk(out_dir, out):
    """The VTK series of a run agree with its USD file and summary; returns the summary."""
    from polydem.usd import read_frame, read_time_codes

    summary = json.loads((out_dir / "summary.json").read_text())
    vtk = summary["outputs"]["vtk"]
    files = ["vtk/particles.pvd", "vtk/centres.pvd", "vtk/contacts.pvd", "vtk/walls.vtu"]
    assert vtk == {"files": files, "frames": summary["frames"]}
    assert vtk["frames"] == summary["outputs"]["usd_frames"] >= 3
    closing = out[out.index("written to") :]
    assert all(name in closing for name in files) and f"{vtk['frames']} frames" in closing
    codes = read_time_codes(out_dir / "run.usda")
    entries = read_pvd(out_dir / "vtk" / "centres.pvd")
    assert [f.name for _, f in entries] == [f"centres_{int(k):06d}.vtu" for k in codes]  # frame k = time code k
    for (t, f), code in zip(entries, codes, strict=True):
        assert t == pytest.approx(int(code) / summary["fps"], abs=summary["dt"])  # the first step at or after k / fps
        np.testing.assert_allclose(meshio.read(f).points, read_frame(out_dir / "run.usda", code)[0], atol=1e-7)
    contacts = [number_of_cells(f) for _, f in read_pvd(out_dir / "vtk" / "contacts.pvd")]
    assert max(contacts) > 0
    return summary


def test_run_vtk_option_writes_the_series(tmp_path, capsys):
    scene = write_scene(tmp_path)
    out_dir = tmp_path / "out"
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "--vtk", "-q"], capsys)
    assert code == 0, err
    check_run_vtk(out_dir, out)


def test_run_vtk_contact_types_option_writes_the_types(tmp_path, capsys):
    """--vtk-contact-types turns the VTK files on with the contacts' contact_type (features by default)."""
    scene = write_scene(tmp_path)
    out_dir = tmp_path / "out"
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "--vtk-contact-types", "-q"], capsys)
    assert code == 0, err
    check_run_vtk(out_dir, out)
    kinds = [meshio.read(f).cell_data["contact_type"][0] for _, f in read_pvd(out_dir / "vtk" / "contacts.pvd")]
    seen = np.concatenate(kinds)
    assert set(seen.tolist()) <= set(CONTACT_TYPES) and (seen >= 0).any()
    code, _, err = run(["run", scene, "--out", tmp_path / "x", "--vtk-contact-types", "faces"], capsys)
    assert code == 2 and "invalid choice: 'faces'" in err


def test_output_vtk_in_the_scene_turns_it_on_and_it_is_off_by_default(tmp_path, capsys):
    scene = write_scene(tmp_path, [("[output]\n", "[output]\nvtk = true\n")])
    code, out, err = run(["validate", scene], capsys)
    assert code == 0 and "VTK files in vtk/" in out, err
    code, out, err = run(["run", scene, "--device", "cpu", "--out", tmp_path / "on", "-q"], capsys)
    assert code == 0, err
    check_run_vtk(tmp_path / "on", out)
    assert polydem.Scene.from_toml(scene).output.to_dict()["vtk"] is True

    scene = write_scene(tmp_path)
    code, out, err = run(["run", scene, "--device", "cpu", "--out", tmp_path / "off", "--steps", "10", "-q"], capsys)
    assert code == 0, err
    assert not (tmp_path / "off" / "vtk").exists()
    assert json.loads((tmp_path / "off" / "summary.json").read_text())["outputs"]["vtk"] is None
    assert "vtk/" not in out


def test_output_vtk_must_be_true_or_false(tmp_path, capsys):
    scene = write_scene(tmp_path, [("[output]\n", '[output]\nvtk = "yes"\n')])
    code, _, err = run(["validate", scene], capsys)
    assert_user_error(code, err, "scene.toml", "output.vtk", "expected true or false")
    code, _, err = run(["run", scene, "--device", "cpu", "--out", tmp_path / "o"], capsys)
    assert_user_error(code, err, "output.vtk", "expected true or false")
    assert not (tmp_path / "o").exists()


def test_vtk_folder_that_is_a_file_is_a_user_error(tmp_path, capsys):
    scene = write_scene(tmp_path)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    (out_dir / "vtk").write_text("not a folder")
    (out_dir / "summary.json").write_text("{}")  # an earlier run's output
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "--vtk"], capsys)
    assert_user_error(code, err, str(out_dir / "vtk"), "--vtk", "is a file", "give another --out")
    assert (out_dir / "vtk").read_text() == "not a folder"
    assert (out_dir / "summary.json").read_text() == "{}"
    assert sorted(p.name for p in out_dir.iterdir()) == ["summary.json", "vtk"]


def test_interrupted_run_resumes_the_series(tmp_path, capsys, monkeypatch):
    from polydem.simulation import Simulation

    scene = write_scene(tmp_path)
    out_dir = tmp_path / "out"
    original = Simulation.step
    calls = {"n": 0}

    def step(self, n=1):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return original(self, n)

    monkeypatch.setattr(Simulation, "step", step)
    code, out, err = run(["run", scene, "--device", "cpu", "--out", out_dir, "--vtk", "-q"], capsys)
    monkeypatch.undo()
    assert code == 130, err
    first = json.loads((out_dir / "summary.json").read_text())
    assert first["outputs"]["vtk"]["frames"] == len(read_pvd(out_dir / "vtk" / "particles.pvd")) >= 2
    assert "--vtk" in err  # the resume command given keeps the VTK output on
    checkpoint = out_dir / "checkpoints" / "interrupted.npz"
    code, out, err = run(
        ["run", scene, "--device", "cpu", "--out", out_dir, "--vtk", "-q", "--resume", checkpoint], capsys
    )
    assert code == 0, err
    summary = json.loads((out_dir / "summary.json").read_text())
    frames = expected_frames(summary["steps"], summary["dt"], summary["fps"])
    for name in SERIES:
        entries = read_pvd(out_dir / "vtk" / f"{name}.pvd")
        # The whole run: the first run's frames before the checkpoint, then the resumed run's.
        assert [f.name for _, f in entries] == [f"{name}_{k:06d}.vtu" for k in range(frames)]
        times = [t for t, _ in entries]
        assert times == sorted(times) and len(set(times)) == frames
    assert summary["outputs"]["vtk"]["frames"] < frames


def expected_frames(steps, dt, fps):
    """Frames k = 0, 1, ... whose step ceil(k / fps / dt) the run reaches."""
    k = 0
    while math.ceil(k / fps / dt - 1e-9) <= steps:
        k += 1
    return k


def test_mesh_walls_fixed_in_walls_file_moving_in_a_series(tmp_path):
    scene = polydem.Scene(gravity=(0, 0, -9.81), dt=1e-3)  # no contact in the recorded time
    scene.add_material("steel", density=7800, law="hertz", k=1e6, restitution=0.5, friction=0.0)
    scene.add_shape("cube", polydem.ConvexShape.box(0.1))
    scene.add_body("cube", "steel", position=(0, 0, 0.3))
    scene.add_plane(point=(0, 0, -1), normal=(0, 0, 1), material="steel")
    square = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]], dtype=float)
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    scene.add_mesh_wall((square, tri), "steel")
    turning = scene.add_mesh_wall((0.2 * square, tri), "steel", position=(1, 0, 0.5), angular_velocity=(0, 20.0, 0))
    sim = polydem.Simulation(scene, device="cpu")
    folder = tmp_path / "vtk"
    poses = []
    with VtkWriter(folder, sim) as writer:
        for _ in range(2):
            poses.append(sim.current_state.mesh_q.numpy()[1].astype(np.float64))
            writer.record_simulation(sim)
            sim.step(20)
    assert folder / "moving_walls.pvd" in writer.files
    walls = meshio.read(folder / "walls.vtu")
    assert [b.type for b in walls.cells] == ["quad", "triangle"]
    fixed = scene.mesh_walls[0]
    np.testing.assert_allclose(walls.points[walls.cells[1].data], fixed.vertices[fixed.triangles], atol=1e-6)
    np.testing.assert_array_equal(walls.cell_data["wall"][1], [1, 1])  # after the plane
    np.testing.assert_allclose(walls.cell_data["normal"][1], [[0, 0, 1], [0, 0, 1]])
    entries = read_pvd(folder / "moving_walls.pvd")
    assert len(entries) == 2
    for (_, path), pose in zip(entries, poses, strict=True):
        mesh = meshio.read(path)
        expect = (turning.vertices - turning.pivot) @ quat_to_matrix(pose[3:]).T + pose[:3]
        np.testing.assert_allclose(mesh.points[mesh.cells[0].data], expect[turning.triangles], atol=1e-6)
    assert np.abs(poses[1] - poses[0]).max() > 0.1  # the wall turned between the frames
