"""polydem.usd: streaming USD recorder (stage metadata, prototypes, instancer poses, walls, saving)."""

import shutil
import subprocess
import sys

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")

from pxr import Gf, Sdf, Usd, UsdGeom  # noqa: E402

import polydem  # noqa: E402
from polydem.scene import quat_from_axis_angle, quat_to_matrix  # noqa: E402
from polydem.usd import PALETTE, UsdRecorder, read_frame, read_time_codes  # noqa: E402

STEPS = 60  # simulation steps between frames
FRAMES = 4
EXTS = [".usda", ".usdc", ".usd"]


def make_scene():
    scene = polydem.Scene(gravity=(0, 0, -9.81), dt="auto", name="usd-test")
    scene.add_material("steel", density=7800, law="hertz", k=1e10, restitution=0.5, friction=0.3)
    scene.add_shape("cube", polydem.ConvexShape.box(0.1, 0.08, 0.06))
    scene.add_shape("tet", polydem.ConvexShape.tetrahedron(0.12))
    scene.add_shape("rock.1", polydem.ConvexShape.rock(n_points=12, size=0.1, seed=1))  # '.' is no prim name
    q = quat_from_axis_angle((1, 2, 3), 1.1)  # every component non-zero: an xyzw/wxyz mix-up shows
    scene.add_body("cube", "steel", position=(0, 0, 0.2), orientation=q, angular_velocity=(20, 30, 10))
    scene.add_body("tet", "steel", position=(0.3, 0, 0.2), orientation=quat_from_axis_angle((1, 1, 0), 0.7))
    scene.add_body("rock.1", "steel", position=(-0.3, 0, 0.2), velocity=(0, 0, -1))
    scene.add_body("cube", "steel", position=(0, 0.3, 0.05), kind="fixed")
    scene.add_body(
        "tet", "steel", position=(0, -0.3, 0.3), velocity=(0.5, 0, 0), angular_velocity=(3, 0, 40), kind="kinematic"
    )
    scene.add_plane(point=(0, 0, 0), normal=(0, 0, 1), material="steel")
    return scene


@pytest.fixture(scope="module")
def run():
    """The scene, the simulation's dt and FRAMES states (time, positions, orientations) STEPS apart."""
    scene = make_scene()
    sim = polydem.Simulation(scene, device="cpu")
    frames = []
    for _ in range(FRAMES):
        st = sim.state()
        frames.append((sim.time, st["body_position"], st["body_orientation"]))
        sim.step(STEPS)
    return scene, sim.dt, frames


def write(path, run, **kw):
    scene, dt, frames = run
    kw.setdefault("fps", 30.0)
    kw.setdefault("frame_dt", dt * STEPS)  # frame k at time code k
    with UsdRecorder(path, scene, **kw) as rec:
        codes = [rec.record(t, p, q) for t, p, q in frames]
    assert rec.closed
    assert codes == list(range(FRAMES))
    return path


def world_vertices(shape, p, q):
    return shape.vertices @ quat_to_matrix(q).T + p


def assert_same_rotation(q_a, q_b, atol):
    np.testing.assert_allclose(quat_to_matrix(q_a), quat_to_matrix(q_b), atol=atol)


def proto_meshes(stage):
    inst = UsdGeom.PointInstancer.Get(stage, "/World/Bodies")
    return inst, [UsdGeom.Mesh(stage.GetPrimAtPath(t)) for t in inst.GetPrototypesRel().GetTargets()]


@pytest.mark.parametrize("ext", EXTS)
def test_file_metadata_and_prototypes(tmp_path, run, ext):
    scene = run[0]
    path = write(tmp_path / f"rec{ext}", run)
    head = path.read_bytes()[:8]
    assert head.startswith(b"#usda") if ext == ".usda" else head == b"PXR-USDC"

    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetTimeCodesPerSecond() == 30.0 and stage.GetFramesPerSecond() == 30.0
    assert stage.GetStartTimeCode() == 0.0 and stage.GetEndTimeCode() == FRAMES - 1
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/World")
    assert list(read_time_codes(path)) == list(range(FRAMES))

    inst, meshes = proto_meshes(stage)
    assert len(meshes) == len(scene.shape_names) == 3
    for k, (name, mesh) in enumerate(zip(scene.shape_names, meshes, strict=True)):
        shape = scene.shapes[name]
        assert mesh and mesh.GetPrim().GetCustomDataByKey("polydem:shape") == name
        counts = list(mesh.GetFaceVertexCountsAttr().Get())
        assert counts == [len(f) for f in shape.faces] and len(counts) == shape.num_faces
        assert list(mesh.GetFaceVertexIndicesAttr().Get()) == np.concatenate(shape.faces).tolist()
        np.testing.assert_allclose(np.asarray(mesh.GetPointsAttr().Get()), shape.vertices, atol=1e-7)
        assert mesh.GetSubdivisionSchemeAttr().Get() == UsdGeom.Tokens.none
        normals = np.asarray(mesh.GetNormalsAttr().Get())
        assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.faceVarying and len(normals) == sum(counts)
        np.testing.assert_allclose(mesh.GetDisplayColorPrimvar().Get()[0], PALETTE[k], atol=1e-6)
    assert mesh.GetPath().name == "rock_1"  # sanitised prim name
    np.testing.assert_array_equal(np.asarray(inst.GetProtoIndicesAttr().Get()), scene.body_shape)
    assert not inst.GetProtoIndicesAttr().ValueMightBeTimeVarying()

    # The wall: one quad in the plane, facing the plane's normal (counter-clockwise from that side).
    walls = [UsdGeom.Mesh(p) for p in stage.GetPrimAtPath("/World/Walls").GetChildren()]
    assert len(walls) == len(scene.planes) == 1
    pts = np.asarray(walls[0].GetPointsAttr().Get(), dtype=np.float64)
    plane = scene.planes[0]
    assert list(walls[0].GetFaceVertexCountsAttr().Get()) == [4]
    np.testing.assert_allclose((pts - plane.point) @ np.array(plane.normal), 0.0, atol=1e-7)
    n = np.cross(pts[1] - pts[0], pts[2] - pts[1])
    np.testing.assert_allclose(n / np.linalg.norm(n), plane.normal, atol=1e-7)
    assert (pts.min(axis=0)[:2] < scene.body_position.min(axis=0)[:2] - 0.2).all()
    assert (pts.max(axis=0)[:2] > scene.body_position.max(axis=0)[:2] + 0.2).all()


@pytest.mark.parametrize("ext", EXTS)
@pytest.mark.parametrize("precision", ["half", "float"])
def test_frames_match_simulation(tmp_path, run, ext, precision):
    scene, _, frames = run
    path = write(tmp_path / f"rec{ext}", run, orientation_precision=precision)
    atol_q = 2e-3 if precision == "half" else 1e-6

    stage = Usd.Stage.Open(str(path))
    inst, meshes = proto_meshes(stage)
    authored = inst.GetOrientationsfAttr() if precision == "float" else inst.GetOrientationsAttr()
    assert authored.HasAuthoredValue() and len(authored.GetTimeSamples()) == FRAMES
    proto_points = [np.asarray(m.GetPointsAttr().Get(), dtype=np.float64) for m in meshes]
    moved = 0.0
    for code, (_, p, q) in enumerate(frames):
        pos, quat = read_frame(path, code)
        np.testing.assert_allclose(pos, p, atol=1e-6)
        assert_same_rotation(quat, q, atol_q)
        moved = max(moved, np.abs(p - frames[0][1]).max())
        # Every vertex of every body through the instancer's transform = the body's world vertex.
        xforms = inst.ComputeInstanceTransformsAtTime(Usd.TimeCode(code), Usd.TimeCode(code))
        assert len(xforms) == scene.num_bodies
        for i, m in enumerate(xforms):
            s = int(scene.body_shape[i])
            usd_world = np.array([m.Transform(Gf.Vec3d(*v)) for v in proto_points[s]])
            expected = world_vertices(scene.shapes[scene.shape_names[s]], p[i], q[i])
            np.testing.assert_allclose(usd_world, expected, atol=2e-6 + 0.1 * atol_q)
        lo, hi = (np.asarray(v) for v in inst.GetExtentAttr().Get(code))
        assert (lo <= p.min(axis=0)).all() and (hi >= p.max(axis=0)).all()
        assert inst.GetPrim().GetAttribute("polydem:time").Get(code) == pytest.approx(frames[code][0])
    assert moved > 1e-3  # the frames differ (free and kinematic bodies move)
    np.testing.assert_array_equal(frames[-1][1][3], frames[0][1][3])  # the fixed body stays


def test_record_simulation_and_reopen_same_path(tmp_path):
    scene = make_scene()
    sim = polydem.Simulation(scene, device="cpu")
    path = tmp_path / "sub" / "sim.usdc"  # the folder is made
    with UsdRecorder(path, sim, fps=24.0, frame_dt=sim.dt * STEPS, up_axis="y", save_every=1) as rec:
        for k in range(3):
            assert rec.record_simulation(sim) == k
            sim.step(STEPS)
    pos, quat = read_frame(path, 2)
    st = sim.state()  # one frame further on
    assert np.abs(st["body_position"] - pos).max() > 1e-4
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y and stage.GetEndTimeCode() == 2
    del stage
    # Recording again to the same path starts a new file.
    with UsdRecorder(path, scene, fps=24.0) as rec:
        rec.record(0.0, scene.body_position, scene.body_orientation)
    assert list(read_time_codes(path)) == [0.0]
    np.testing.assert_allclose(read_frame(path, 0)[0], scene.body_position, atol=1e-6)


@pytest.mark.parametrize("ext", [".usdc", ".usda"])
def test_saved_file_is_valid_while_recording(tmp_path, run, ext):
    """An interrupted run leaves a valid file holding every frame up to the last save."""
    scene, dt, frames = run
    path = tmp_path / f"live{ext}"
    rec = UsdRecorder(path, scene, frame_dt=dt * STEPS, save_every=2)
    snapshots = []
    for t, p, q in frames:
        rec.record(t, p, q)
        copy = tmp_path / f"copy{len(snapshots)}{ext}"  # a copy: this process's open layer is not read
        shutil.copyfile(path, copy)
        snapshots.append(copy)
    rec.close()
    for k, copy in enumerate(snapshots):
        saved = 2 * ((k + 1) // 2)  # frames on disk after record k
        stage = Usd.Stage.Open(str(copy))
        assert stage.GetEndTimeCode() == max(saved - 1, 0)
        assert list(read_time_codes(copy)) == list(range(saved))
        for code in range(saved):
            np.testing.assert_allclose(read_frame(copy, code)[0], frames[code][1], atol=1e-6)


def test_meters_per_unit_scales_lengths(tmp_path, run):
    scene, _, frames = run
    path = write(tmp_path / "cm.usda", run, meters_per_unit=0.01)
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    inst, meshes = proto_meshes(stage)
    np.testing.assert_allclose(np.asarray(meshes[0].GetPointsAttr().Get()), 100 * scene.shapes["cube"].vertices, 1e-6)
    np.testing.assert_allclose(np.asarray(inst.GetPositionsAttr().Get(1)), 100 * frames[1][1], rtol=1e-6, atol=1e-5)
    np.testing.assert_allclose(read_frame(path, 1)[0], frames[1][1], atol=1e-6)  # back in metres


def test_orientation_signs_follow_previous_frame(tmp_path):
    scene = polydem.Scene()
    scene.add_material("m", density=1000, law="linear", k=1e6, restitution=0.5, friction=0.0)
    scene.add_shape("cube", polydem.ConvexShape.box(0.1))
    scene.add_body("cube", "m")
    path = tmp_path / "sign.usda"
    q = quat_from_axis_angle((0, 0, 1), 3.0)
    with UsdRecorder(path, scene, fps=10.0, orientation_precision="float") as rec:
        for k, sign in enumerate([1, -1, 1, -1]):
            rec.record(0.1 * k, np.zeros((1, 3)), sign * q[None])
    stored = np.array([read_frame(path, k)[1][0] for k in range(4)])
    assert (stored @ stored[0] > 0.99).all()


def test_errors(tmp_path, run):
    scene, dt, frames = run
    for name in ("out.abc", "out", "out.usdz"):
        with pytest.raises(ValueError, match=r"\.usda.*\.usdc.*\.usd"):
            UsdRecorder(tmp_path / name, scene)
    assert not any(tmp_path.iterdir())
    with pytest.raises(ValueError, match="up_axis"):
        UsdRecorder(tmp_path / "a.usda", scene, up_axis="X")
    with pytest.raises(ValueError, match="fps"):
        UsdRecorder(tmp_path / "a.usda", scene, fps=0)
    with pytest.raises(ValueError, match="orientation_precision"):
        UsdRecorder(tmp_path / "a.usda", scene, orientation_precision="double")

    with UsdRecorder(tmp_path / "b.usdc", scene, frame_dt=dt * STEPS) as rec:
        t, p, q = frames[1]
        rec.record(t, p, q)
        with pytest.raises(ValueError, match="time code"):
            rec.record(t, p, q)  # the same frame again
        with pytest.raises(ValueError, match=r"positions must have shape \(5, 3\)"):
            rec.record(frames[2][0], p[:3], q)
        with pytest.raises(ValueError, match="orientations"):
            rec.record(frames[2][0], p, q[:, :3])
        assert rec.record(*frames[2]) == 2  # still usable
        # The file is held open by the recorder: a second recorder on it is refused.
        with pytest.raises(RuntimeError, match="open in this process"):
            UsdRecorder(tmp_path / "b.usdc", scene)
    rec.close()  # again: no-op
    with pytest.raises(RuntimeError, match="closed"):
        rec.record(*frames[3])
    assert list(read_time_codes(tmp_path / "b.usdc")) == [1.0, 2.0]


def test_import_polydem_does_not_import_pxr():
    code = "import sys, polydem, polydem.usd; assert 'pxr' not in sys.modules, 'pxr imported'"
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)
