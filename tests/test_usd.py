"""polydem.usd: streaming USD recorder (stage metadata, prototypes, instancer poses, walls, saving)."""

import shutil
import subprocess
import sys

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")

from conftest import DEVICES  # noqa: E402  (the first test device: these tests are about the file, not the device)
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
    # The reference overlap's step, not the smaller one that resolves a body resting under its own
    # weight (issue 11): the frames are a fixed number of steps apart and must see the impacts.
    scene.dt = scene.time_step().period / 50
    return scene


@pytest.fixture(scope="module")
def run():
    """The scene, the simulation's dt and FRAMES states (time, positions, orientations) STEPS apart."""
    scene = make_scene()
    sim = polydem.Simulation(scene, device=DEVICES[0])
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
    sim = polydem.Simulation(scene, device=DEVICES[0])
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


# ---------------------------------------------------------------------- precision and velocities


def random_quaternions(n, seed=0):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def cubes(n):
    scene = polydem.Scene(name="many")
    scene.add_material("m", density=1000, law="linear", k=1e6, restitution=0.5, friction=0.0)
    scene.add_shape("cube", polydem.ConvexShape.box(0.1))
    for i in range(n):
        scene.add_body("cube", "m", position=(0.2 * i, 0, 0))
    return scene


def instance_rotations(inst, code):
    """(N, 3, 3) rotations of the instances as USD computes them (column-vector convention)."""
    xforms = inst.ComputeInstanceTransformsAtTime(Usd.TimeCode(code), Usd.TimeCode(code))
    return np.array([np.array(m.ExtractRotationMatrix()).T for m in xforms])


@pytest.mark.parametrize("ext", [".usdc", ".usda"])
def test_orientations_in_float_by_default_and_in_half_for_old_readers(tmp_path, ext):
    n = 500
    scene = cubes(n)
    q = random_quaternions(n)
    path = tmp_path / f"q{ext}"
    with UsdRecorder(path, scene, fps=10.0) as rec:
        rec.record(0.1, scene.body_position, q)
    assert rec.orientation_precision == "float"  # this usd-core has orientationsf
    stage = Usd.Stage.Open(str(path))
    inst = UsdGeom.PointInstancer.Get(stage, "/World/Bodies")
    qf = np.asarray(inst.GetOrientationsfAttr().Get(1), dtype=np.float64)
    qh = np.asarray(inst.GetOrientationsAttr().Get(1), dtype=np.float64)  # what an older reader sees
    assert np.abs(np.linalg.norm(qf, axis=1) - 1.0).max() < 1e-6
    assert 1e-5 < np.abs(np.linalg.norm(qh, axis=1) - 1.0).max() < 5e-4  # half precision: the old error
    np.testing.assert_allclose(read_frame(path, 1)[1], q, atol=1e-7)  # same signs: q[0] ... as given
    # OpenUSD takes orientationsf where both are authored: the instances turn in float precision.
    np.testing.assert_allclose(instance_rotations(inst, 1), quat_to_matrix(q), atol=1e-6)


def test_half_orientations_when_asked_or_when_usd_core_has_no_orientationsf(tmp_path, monkeypatch):
    n = 200
    scene = cubes(n)
    q = random_quaternions(n, seed=1)
    with UsdRecorder(tmp_path / "half.usda", scene, fps=10.0, orientation_precision="half") as rec:
        rec.record(0.0, scene.body_position, q)
    monkeypatch.delattr(UsdGeom.PointInstancer, "CreateOrientationsfAttr")  # an older usd-core
    with UsdRecorder(tmp_path / "old.usda", scene, fps=10.0) as old:
        old.record(0.0, scene.body_position, q)
    with pytest.raises(ValueError, match="no PointInstancer.orientationsf.*'half'"):
        UsdRecorder(tmp_path / "f.usda", scene, orientation_precision="float")
    monkeypatch.undo()
    assert rec.orientation_precision == old.orientation_precision == "half"
    for path in (tmp_path / "half.usda", tmp_path / "old.usda"):
        stage = Usd.Stage.Open(str(path))
        inst = UsdGeom.PointInstancer.Get(stage, "/World/Bodies")
        assert not inst.GetOrientationsfAttr().HasAuthoredValue()
        assert_same_rotation(read_frame(path, 0)[1], q, 2e-3)
        assert np.abs(instance_rotations(inst, 0) - quat_to_matrix(q)).max() > 1e-5  # half precision


@pytest.fixture(scope="module")
def moving():
    """FRAMES states (time, positions, orientations, velocities, angular velocities) STEPS apart."""
    scene = make_scene()
    sim = polydem.Simulation(scene, device=DEVICES[0])
    frames = []
    for _ in range(FRAMES):
        st = sim.state()
        frames.append((sim.time, *(st[k] for k in ("body_position", "body_orientation", "body_velocity"))))
        frames[-1] += (st["body_angular_velocity"],)
        sim.step(STEPS)
    return scene, sim.dt, frames


@pytest.mark.parametrize("ext", [".usdc", ".usda"])
@pytest.mark.parametrize("fps", [30.0, None])  # slow motion (frame_dt = STEPS dt, played at 30 fps), real time
def test_velocities_and_angular_velocities(tmp_path, moving, ext, fps):
    from polydem.usd import read_velocities

    scene, dt, frames = moving
    frame_dt = dt * STEPS
    fps = fps or 1.0 / frame_dt
    per_second = frame_dt * fps  # simulated seconds per second of playback
    path = tmp_path / f"v{ext}"
    with UsdRecorder(path, scene, fps=fps, frame_dt=frame_dt) as rec:
        for t, p, q, v, w in frames:
            rec.record(t, p, q, v, w)
    stage = Usd.Stage.Open(str(path))
    inst = UsdGeom.PointInstancer.Get(stage, "/World/Bodies")
    assert inst.GetVelocitiesAttr().GetTimeSamples() == inst.GetPositionsAttr().GetTimeSamples()
    assert inst.GetAngularVelocitiesAttr().GetTimeSamples() == list(map(float, range(FRAMES)))
    spinning = 0.0
    for code, (_, p, q, v, w) in enumerate(frames):
        # The schema's units: position units and degrees per second of playback.
        usd_v = np.asarray(inst.GetVelocitiesAttr().Get(code), dtype=np.float64)
        usd_w = np.asarray(inst.GetAngularVelocitiesAttr().Get(code), dtype=np.float64)
        np.testing.assert_allclose(usd_v, v * per_second, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(usd_w, np.degrees(w) * per_second, rtol=1e-6, atol=1e-12)
        back_v, back_w = read_velocities(path, code)
        np.testing.assert_allclose(back_v, v, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(back_w, w, rtol=1e-6, atol=1e-12)
        spinning = max(spinning, np.abs(w).max())
        # Between frames a renderer moves the bodies by them: half a frame on = frame_dt / 2 of motion.
        xforms = inst.ComputeInstanceTransformsAtTime(Usd.TimeCode(code + 0.5), Usd.TimeCode(code))
        h = 0.5 * frame_dt
        for i, m in enumerate(xforms):
            np.testing.assert_allclose(np.array(m.ExtractTranslation()), p[i] + v[i] * h, atol=1e-6)
            angle = np.linalg.norm(w[i]) * h
            turn = quat_from_axis_angle(w[i], angle) if angle > 0 else np.array([0.0, 0.0, 0.0, 1.0])
            expected = quat_to_matrix(turn) @ quat_to_matrix(q[i])  # world axes: the turn applies last
            np.testing.assert_allclose(np.array(m.ExtractRotationMatrix()).T, expected, atol=1e-5)
    assert spinning > 1.0


def test_record_simulation_writes_velocities_and_frames_agree(tmp_path, moving):
    from polydem.usd import read_velocities

    scene = make_scene()
    sim = polydem.Simulation(scene, device=DEVICES[0])
    with UsdRecorder(tmp_path / "s.usdc", sim, frame_dt=sim.dt * STEPS) as rec:
        for _ in range(2):
            rec.record_simulation(sim)
            sim.step(STEPS)
    for code in range(2):
        _, _, _, v, w = moving[2][code]
        back_v, back_w = read_velocities(tmp_path / "s.usdc", code)
        np.testing.assert_allclose(back_v, v, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(back_w, w, rtol=1e-6, atol=1e-12)


def test_velocity_errors(tmp_path, moving):
    from polydem.usd import read_velocities

    scene, dt, frames = moving
    t, p, q, v, w = frames[0]
    with UsdRecorder(tmp_path / "e.usda", scene, frame_dt=dt * STEPS) as rec:
        with pytest.raises(ValueError, match="both velocities and angular_velocities, or neither"):
            rec.record(t, p, q, v)
        with pytest.raises(ValueError, match=r"velocities must have shape \(5, 3\)"):
            rec.record(t, p, q, v[:2], w)
        assert rec.record(t, p, q, v, w) == 0  # still usable
        with pytest.raises(ValueError, match="first frame of this file was recorded with velocities"):
            rec.record(frames[1][0], frames[1][1], frames[1][2])
        assert rec.record(*frames[1]) == 1
    assert list(read_time_codes(tmp_path / "e.usda")) == [0.0, 1.0]
    with UsdRecorder(tmp_path / "n.usda", scene, frame_dt=dt * STEPS) as rec:
        rec.record(t, p, q)
        with pytest.raises(ValueError, match="recorded without velocities"):
            rec.record(*frames[1])
    assert read_velocities(tmp_path / "n.usda", 0) is None  # like a file of an older polydem


RENDER_SCENE = """\
[simulation]
name = "render"
dt = "auto"

[materials.steel]
density = 7800.0
law = "hertz"
k = 1.0e10
restitution = 0.5
friction = 0.3

[shapes.cube]
type = "box"
size = 0.1

[shapes.tet]
type = "tetrahedron"
edge = 0.12

[[bodies]]
shape = "cube"
material = "steel"
position = [0.0, 0.0, 0.2]
rotation = { axis = [1.0, 2.0, 3.0], degrees = 50.0 }
angular_velocity = [5.0, 3.0, 20.0]

[[bodies]]
shape = "tet"
material = "steel"
position = [0.2, 0.0, 0.2]
velocity = [0.0, 0.0, -1.0]

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "steel"
"""


def test_polydem_render_reads_old_and_new_files(tmp_path, capsys):
    """`polydem render x.usd` reads files with quath orientations only (older polydem) and new ones."""
    from polydem.cli import main

    toml = tmp_path / "render.toml"
    toml.write_text(RENDER_SCENE)
    scene = polydem.Scene.from_toml(toml)
    sim = polydem.Simulation(scene, device=DEVICES[0])
    old, new = tmp_path / "old.usdc", tmp_path / "new.usdc"
    with (
        UsdRecorder(old, scene, frame_dt=sim.dt * STEPS, orientation_precision="half") as rec_old,
        UsdRecorder(new, scene, frame_dt=sim.dt * STEPS) as rec_new,
    ):
        for _ in range(2):
            st = sim.state()
            rec_old.record(sim.time, st["body_position"], st["body_orientation"])  # what polydem wrote before
            rec_new.record_simulation(sim)
            sim.step(STEPS)
    (pos_old, q_old), (pos_new, q_new) = read_frame(old, 1), read_frame(new, 1)
    np.testing.assert_allclose(pos_old, pos_new, atol=1e-7)
    np.testing.assert_allclose(q_new, st["body_orientation"], atol=1e-7)
    assert_same_rotation(q_old, q_new, 2e-3)
    for path in (old, new):
        png = tmp_path / f"{path.stem}.png"
        args = ["render", path, "--scene", toml, "--frame", "1", "--out", png, "--width", "48", "--height", "32"]
        code = main([str(a) for a in [*args, "--device", DEVICES[0]]])
        out, err = capsys.readouterr()
        assert code == 0, err
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "frame 1" in out


def mesh_wall_scene():
    """A cube above a fixed 2-triangle floor and a turning square plate (both mesh walls)."""
    scene = polydem.Scene(gravity=(0, 0, -9.81), dt=1e-3, name="usd-mesh")  # no contact in the recorded time
    scene.add_material("steel", density=7800, law="hertz", k=1e6, restitution=0.5, friction=0.3)
    scene.add_shape("cube", polydem.ConvexShape.box(0.1))
    scene.add_body("cube", "steel", position=(0, 0, 0.2))
    square = np.array([[-0.5, -0.5, 0], [0.5, -0.5, 0], [0.5, 0.5, 0], [-0.5, 0.5, 0]], dtype=float)
    tri = np.array([[0, 1, 2], [0, 2, 3]])
    scene.add_mesh_wall((square, tri), "steel")
    scene.add_mesh_wall(
        (0.2 * square, tri), "steel", position=(1.0, 0, 0.5), pivot=(1.0, 0.1, 0.5), angular_velocity=(0, 3.0, 1.0)
    )
    return scene


@pytest.mark.parametrize("mpu", [1.0, 0.01])
def test_mesh_walls_written_and_moving_one_time_sampled(tmp_path, device, mpu):
    scene = mesh_wall_scene()
    sim = polydem.Simulation(scene, device=device)
    path = tmp_path / "mesh.usda"
    poses = []
    with UsdRecorder(path, sim, fps=24.0, frame_dt=sim.dt * 10, meters_per_unit=mpu) as rec:
        for _ in range(3):
            poses.append(sim.current_state.mesh_q.numpy()[:2].astype(np.float64))
            rec.record_simulation(sim)
            sim.step(10)
    assert np.abs(poses[2][1] - poses[0][1]).max() > 1e-3  # the plate turned
    stage = Usd.Stage.Open(str(path))
    for k, wall in enumerate(scene.mesh_walls):
        mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/World/Walls/mesh_{k}"))
        assert mesh and len(mesh.GetPointsAttr().Get()) == len(wall.vertices)
        assert len(mesh.GetFaceVertexCountsAttr().Get()) == len(wall.triangles)
        assert mesh.GetPrim().GetCustomDataByKey("polydem:material") == "steel"
        for code in range(3):
            m = np.array(mesh.ComputeLocalToWorldTransform(code), dtype=np.float64)  # row vectors: x' = x M
            pts = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)
            world = (np.c_[pts, np.ones(len(pts))] @ m)[:, :3] * mpu
            p, q = poses[code][k, :3], poses[code][k, 3:]
            expect = (wall.vertices - wall.pivot) @ quat_to_matrix(q).T + p
            if not wall.moving:
                expect = wall.vertices
            np.testing.assert_allclose(world, expect, atol=1e-5)
    orient = [stage.GetPrimAtPath(f"/World/Walls/mesh_{k}").GetAttribute("xformOp:orient") for k in range(2)]
    assert orient[0].GetTimeSamples() == [] and list(orient[1].GetTimeSamples()) == [0.0, 1.0, 2.0]


def test_mesh_walls_keep_initial_pose_from_positions_only(tmp_path):
    scene = mesh_wall_scene()
    path = tmp_path / "mesh.usda"
    with UsdRecorder(path, scene) as rec:
        rec.record(0.0, scene.body_position, scene.body_orientation)
        rec.record(0.1, scene.body_position, scene.body_orientation)
    stage = Usd.Stage.Open(str(path))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/World/Walls/mesh_1"))
    m = np.array(mesh.ComputeLocalToWorldTransform(1), dtype=np.float64)
    pts = np.array(mesh.GetPointsAttr().Get(), dtype=np.float64)
    np.testing.assert_allclose((np.c_[pts, np.ones(len(pts))] @ m)[:, :3], scene.mesh_walls[1].vertices, atol=1e-6)


@pytest.mark.parametrize("precision", ["float", "half"])
def test_record_simulation_made_on_the_device_matches_record_from_the_state(tmp_path, device, precision):
    """record_simulation builds the frame on the device (polydem.kernels.export); record() from
    Simulation.state() on the host: the same positions and velocities bit for bit, the same quaternions up to
    the last bit of their float32 norm, in both orientation precisions."""
    from polydem.usd import read_velocities

    sim = polydem.Simulation(make_scene(), device=device)
    paths = tmp_path / "device.usdc", tmp_path / "host.usdc"
    kw = {"frame_dt": sim.dt * STEPS, "meters_per_unit": 0.01, "orientation_precision": precision}
    with UsdRecorder(paths[0], sim, **kw) as on_device, UsdRecorder(paths[1], sim, **kw) as on_host:
        for _ in range(3):
            st = sim.state()
            assert on_device.record_simulation(sim) == on_host.record(sim.time, *st.values())
            sim.step(STEPS)
    for code in range(3):
        (p_dev, q_dev), (p_host, q_host) = read_frame(paths[0], code), read_frame(paths[1], code)
        np.testing.assert_array_equal(p_dev, p_host)
        np.testing.assert_allclose(q_dev, q_host, rtol=0, atol=1.2e-7 if precision == "float" else 1e-3)
        assert np.all(np.einsum("ij,ij->i", q_dev, q_host) > 0.0)  # the same sign chosen
        for a, b in zip(read_velocities(paths[0], code), read_velocities(paths[1], code), strict=True):
            np.testing.assert_array_equal(a, b)


def test_record_and_record_simulation_keep_one_sign_between_them(tmp_path, device):
    """Frames alternately from the host and the device: each quaternion keeps the sign nearest the frame
    before, whichever path wrote that one (q and -q are the same turn; a flip would spin it the long way)."""
    sim = polydem.Simulation(make_scene(), device=device)
    st = sim.state()
    pose = sim.current_state.body_q.numpy()
    flipped = pose.copy()
    flipped[:, 3:] *= -1.0  # the same orientations with the other sign
    path = tmp_path / "mix.usda"
    with UsdRecorder(path, sim, frame_dt=sim.dt, orientation_precision="float") as rec:
        rec.record(0.0, st["body_position"], st["body_orientation"], st["body_velocity"], st["body_angular_velocity"])
        for code, source in ((1, flipped), (2, None), (3, flipped)):
            sim.time = code * sim.dt  # the recorder reads the time; nothing steps
            if source is None:
                rec.record(sim.time, st["body_position"], -st["body_orientation"], st["body_velocity"],
                           st["body_angular_velocity"])  # fmt: skip
            else:
                sim.current_state.body_q.assign(source)
                rec.record_simulation(sim)
    first = read_frame(path, 0)[1]
    np.testing.assert_allclose(first, st["body_orientation"], atol=1e-7)
    for code in (1, 2, 3):
        np.testing.assert_allclose(read_frame(path, code)[1], first, atol=1e-7)
