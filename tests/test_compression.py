"""Compression and friction protocols (issue 26): ramp and servo motions, polydem.protocols.compress,
Simulation.set_friction and polydem.protocols.anneal.

Small on the CPU: eight cubes of 1 cm in a box under a kinematic lid, a few thousand steps.
"""

import math

import numpy as np
import pytest
import warp as wp

import polydem
from polydem.protocols import anneal, compress

CUBE = 0.01
LID_AREA = 0.02 * 0.02


def boxed_cubes(motion: dict, friction=0.3):
    """Eight cubes stacked 2 x 2 x 2 in a box of 2 x 2 cm, a lid 0.08 mm above them (0.1 mm once they have
    settled) that follows ``motion`` (a ``[motions.press]`` table as keyword arguments); returns (scene,
    container slabs, lid)."""
    sc = polydem.Scene(gravity=(0.0, 0.0, -9.81))
    sc.add_material("m", density=2500.0, k=1e9, restitution=0.3, friction=friction, law="hertz")
    sc.add_motion("press", **motion)
    sc.add_shape("cube", polydem.ConvexShape.box(CUBE))
    sc.add_shape("lid", polydem.ConvexShape.box(0.02, 0.02, 0.005))
    walls = sc.add_box_container((0.0, 0.0, 0.03), (0.02, 0.02, 0.06), "m", open_top=True)
    for x in (-0.005, 0.005):
        for y in (-0.005, 0.005):
            for z in (0.00501, 0.01502):
                sc.add_body("cube", "m", position=(x, y, z))
    lid = sc.add_body("lid", "m", position=(0.0, 0.0, 0.0226), kind="kinematic", motion="press")
    return sc, walls, lid


def travel(sim):
    """(d [m], v [m/s], F [N]) of the scene's only motion at the last step."""
    return sim.current_state.motion_travel.numpy()[0].astype(np.float64)


def lid_force(sim, lid):
    """The force on the lid along z from the contacts of the last step (Simulation.contacts) [N]."""
    c = sim.contacts()
    force_on_a = -c["normal_force"][:, None] * c["normal"] + c["tangential_force"]
    on = force_on_a[c["body_a"] == lid, 2].sum() - force_on_a[c["body_b"] == lid, 2].sum()
    return float(on)


SERVO = dict(kind="servo", axis=(0.0, 0.0, -1.0), stress=20.0 / LID_AREA, gain=4e-3, max_speed=0.05)


def test_servo_lid_comes_to_rest_at_its_target_force(device):
    """A servo lid (stress 50 kPa on its 4 cm^2: 20 N, 100 times the cubes' weight) comes down at
    gain x 20 N, meets the cubes and comes to rest where they push back with 20 N: within 0.1% after 3000
    steps, the grains at rest; the force it measured on the device is the one Simulation.contacts()
    reports on the lid; the lid is where its displacement puts it."""
    sc, _, lid = boxed_cubes(SERVO)
    sim = polydem.Simulation(sc, device=device)
    assert sim.model.motion_area[0] == pytest.approx(LID_AREA, rel=1e-12)
    sim.step(3000)
    d, v, f = travel(sim)
    assert f == pytest.approx(20.0, rel=1e-3), (d, v, f)
    assert abs(v) < 1e-4 and sim.energy()["kinetic"] < 1e-9
    # The grains settle to 0.1 mm below the lid and deflect by a few micrometres under 20 N.
    assert 5e-5 < d < 3e-4
    # Up, against the axis: the same pair forces summed in another order.
    assert lid_force(sim, lid) == pytest.approx(f, rel=2e-5)
    z = sim.state()["body_position"][lid, 2]
    assert z == pytest.approx(0.0226 - d, abs=1e-12)


def test_servo_state_is_carried_by_snapshots_and_checkpoints(device, tmp_path):
    """The servo's displacement is summed step by step on the device: a restored snapshot or checkpoint
    goes on exactly as the unbroken run."""
    from polydem.checkpoint import read_checkpoint, save_checkpoint

    sc, _, lid = boxed_cubes(SERVO)
    sim = polydem.Simulation(sc, device=device)
    sim.step(600)
    snap = sim.snapshot()
    path = save_checkpoint(sim, tmp_path / "c.npz") or tmp_path / "c.npz"
    sim.step(300)
    ref = (travel(sim), sim.state()["body_position"])
    sim.restore(snap)
    sim.step(300)
    np.testing.assert_array_equal(travel(sim), ref[0])
    np.testing.assert_array_equal(sim.state()["body_position"], ref[1])
    other = polydem.Simulation(sc, device=device)
    ck = read_checkpoint(path)
    other.restore_from_arrays(ck.arrays, ck.steps_done, ck.time)
    other.step(300)
    np.testing.assert_array_equal(travel(other), ref[0])
    np.testing.assert_array_equal(other.state()["body_position"], ref[1])


def test_ramp_lid_follows_its_speed_and_compress_records_the_stress_strain_curve(device):
    """A ramp lid moves at 1 cm/s for 0.2 mm (0.02 s), its pose from the step counter (to rounding of
    float64), then holds still; compress() records the displacement, the force rising once the lid meets
    the cubes (after 0.1 mm: they settle by their gaps), the stress on the lid's area and the packing
    fraction of the box below the lid, rising as the lid comes down."""
    speed, distance = 0.01, 2e-4
    ramp = dict(kind="ramp", axis=(0.0, 0.0, -1.0), speed=speed, distance=distance)
    sc, _, lid = boxed_cubes(ramp)
    sim = polydem.Simulation(sc, device=device)

    def cavity(grains):  # the box's inside below the lid
        top = sim.state()["body_position"][lid, 2] - 0.0025
        return polydem.measures.Box((-0.01, -0.01, 0.0), (0.01, 0.01, top))

    records = compress(sim, lid, duration=0.024, interval=0.002, box=cavity)
    assert len(records) == 13 and records[0].time == 0.0
    for r in records:
        d = speed * min(r.time, distance / speed)
        assert r.displacement == pytest.approx(d, abs=1e-15 + 1e-12 * d)
        assert r.velocity == (speed if 0.0 < r.time < distance / speed else 0.0)  # at rest before the first step
        assert r.stress == pytest.approx(r.force / LID_AREA, rel=1e-12)
        assert 0.99 < r.packing_fraction < 1.01
    z = sim.state()["body_position"][lid, 2]
    assert z == pytest.approx(0.0226 - distance, abs=1e-12)
    force = np.array([r.force for r in records])
    touching = np.array([r.displacement > 1.1e-4 for r in records])
    assert np.all(force[~touching] == 0.0) and np.all(force[touching] > 0.0)
    pressing = force[touching & (np.array([r.velocity for r in records]) > 0.0)]
    assert len(pressing) >= 5 and np.all(np.diff(pressing) > 0.0)  # loaded at a set strain rate
    assert force.max() > 20.0
    fraction = np.array([r.packing_fraction for r in records])
    assert np.all(np.diff(fraction[:11]) > 0.0) and fraction[-1] > fraction[0] + 0.005
    strain = np.array([r.strain for r in records])
    np.testing.assert_allclose(strain, np.array([r.displacement for r in records]) / 0.02, rtol=1e-3)  # 2 cm of cubes


def test_isotropic_compression_by_six_servo_walls(device):
    """Six kinematic slabs around eight cubes without gravity, each a servo pressing inwards at 10 N:
    the sample comes to rest with every wall at its target force."""
    sc = polydem.Scene(gravity=(0.0, 0.0, 0.0))
    sc.add_material("m", density=2500.0, k=1e9, restitution=0.3, friction=0.3, law="hertz")
    sc.add_shape("cube", polydem.ConvexShape.box(CUBE))
    sc.add_shape("slab", polydem.ConvexShape.box(0.03, 0.03, 0.005))
    names = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            name = f"{'xyz'[axis]}{'+' if sign > 0 else '-'}"
            inward = np.zeros(3)
            inward[axis] = -sign
            sc.add_motion(name, kind="servo", axis=tuple(inward), force=10.0, gain=4e-3, max_speed=0.05)
            # The slab's thin side along `axis`, its face 0.05 mm outside the cubes.
            turn = {0: (0.0, math.sqrt(0.5), 0.0, math.sqrt(0.5)), 1: (math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5))}
            position = -inward * (0.01 + 0.0025 + 5e-5)
            slab = sc.add_body("slab", "m", position=tuple(position), orientation=turn.get(axis, (0.0, 0.0, 0.0, 1.0)),
                               kind="kinematic", motion=name)  # fmt: skip
            assert sc.body_motion[slab] == name
            names.append(name)
    for x in (-0.005, 0.005):
        for y in (-0.005, 0.005):
            for z in (-0.005, 0.005):
                sc.add_body("cube", "m", position=(x * 1.001, y * 1.001, z * 1.001))
    sim = polydem.Simulation(sc, device=device)
    np.testing.assert_allclose(sim.model.motion_area, 9e-4, rtol=1e-12)
    records = compress(sim, names, duration=3000 * sim.dt, interval=1000 * sim.dt)
    last = records[-1]
    assert last.force.shape == (6,)
    np.testing.assert_allclose(last.force, 10.0, rtol=2e-3)
    np.testing.assert_allclose(last.stress, 10.0 / 9e-4, rtol=2e-3)
    assert np.all(last.displacement > 0.0) and last.kinetic < 1e-9


def test_motion_kinds_from_a_scene_file_and_their_errors(tmp_path):
    text = """
[materials.m]
density = 2500.0
law = "hertz"
k = 1e9
restitution = 0.3
friction = 0.5
[motions.press]
kind = "servo"
axis = [0.0, 0.0, -1.0]
stress = 1e4
gain = 1e-3
max_speed = 0.1
[motions.push]
kind = "ramp"
axis = [1.0, 0.0, 0.0]
speed = 0.01
duration = 0.5
[shapes.cube]
type = "box"
size = 0.02
[[bodies]]
shape = "cube"
material = "m"
position = [0.0, 0.0, 0.011]
[[bodies]]
shape = "cube"
material = "m"
position = [0.0, 0.0, 0.1]
kind = "kinematic"
motion = "press"
"""
    path = tmp_path / "press.toml"
    path.write_text(text)
    sc = polydem.Scene.from_toml(path)
    assert sc.motions["press"].kind == "servo" and sc.motions["push"].ramp_duration() == 0.5
    again = polydem.Scene.from_dict(sc.to_dict())
    assert again.motions == sc.motions and again.body_motion == sc.body_motion

    def error(old, new):
        with pytest.raises(polydem.SceneError) as info:
            polydem.Scene.from_toml(_write(tmp_path, text.replace(old, new)))
        return str(info.value)

    assert "motions.push.frequency: frequency is a key of cycle motions, and this one is kind = 'ramp'" in error(
        "speed = 0.01", "speed = 0.01\nfrequency = 30.0"
    )
    assert "give how far the ramp goes as duration (in s) or as distance (in m), not both" in error(
        "duration = 0.5", "duration = 0.5\ndistance = 0.1"
    )
    assert "motions.push.speed: missing speed" in error("speed = 0.01\n", "")
    assert "motions.press.stress: give the servo's target as stress" in error("stress = 1e4", "stress = 1e4\nforce = 3")
    assert "motions.press.gain: missing gain" in error("gain = 1e-3\n", "")
    assert "motions.press.max_speed" in error("max_speed = 0.1", "max_speed = -0.1")
    assert "motions.press.kind" in error('kind = "servo"', 'kind = "sevro"')
    # Without its kind a motion is a cycle (the default): the servo's keys are named as not its own.
    assert "motions.press.stress: stress is a key of servo motions, and this one is kind = 'cycle'" in error(
        'kind = "servo"\n', ""
    )
    with pytest.raises(polydem.SceneError, match="motions.c.frequency: missing frequency: a cycle motion needs"):
        polydem.Scene().add_motion("c", axis=(1.0, 0.0, 0.0))


def _write(tmp_path, text):
    path = tmp_path / "case.toml"
    path.write_text(text)
    return path


def test_servo_refuses_a_stress_without_an_area():
    sc = polydem.Scene()
    m = sc.add_motion("s", kind="servo", stress=1e4, gain=1e-3, max_speed=0.1)
    with pytest.raises(polydem.SceneError, match="needs an area to act on"):
        m.target_force(0.0)
    assert m.target_force(2e-4) == pytest.approx(2.0)


def test_a_decomposed_run_refuses_a_servo(device):
    """A rank's model holds some of the bodies: the force on a servo's wall would miss the others' grains."""
    from polydem.model import Model

    sc, _, lid = boxed_cubes(SERVO)
    with pytest.raises(polydem.SceneError, match="a servo motion needs the force of every grain"):
        Model(sc, device, bodies=np.arange(3))  # not even holding the lid
    ramp, _, lid = boxed_cubes(dict(kind="ramp", axis=(0.0, 0.0, -1.0), speed=0.01))
    assert Model(ramp, device, bodies=np.array([0, lid])).has_measured_motions  # a ramp's pose needs no force


def test_compress_names_what_it_cannot_record():
    sc, walls, lid = boxed_cubes(SERVO)
    sc.add_motion("shake", frequency=30.0, amplitude=1e-3)
    sc.add_motion("idle", kind="ramp", speed=0.01)
    sim = type("S", (), {"scene": sc})()  # compress reads the scene before it runs anything
    with pytest.raises(ValueError, match="body 0 follows no motion"):
        compress(sim, walls[0], 0.1, 0.01)
    with pytest.raises(ValueError, match="'shake' is a cycle"):
        compress(sim, "shake", 0.1, 0.01)
    with pytest.raises(ValueError, match="'idle' drives no body"):
        compress(sim, ["press", "idle"], 0.1, 0.01)
    with pytest.raises(polydem.SceneError, match="unknown motion 'pres'; did you mean 'press'"):
        compress(sim, "pres", 0.1, 0.01)


def test_shipped_compression_scene_loads_and_its_lid_comes_down(device):
    """scenes/compression.toml: a servo lid over a pour of cubes; the lid waits for the pour, and from its
    start comes down at its largest speed while no grain is under it."""
    from pathlib import Path

    path = Path(__file__).parents[1] / "scenes" / "compression.toml"
    scene = polydem.Scene.from_toml(path)
    press = scene.motions["press"]
    assert press.kind == "servo" and press.axis == (0.0, 0.0, -1.0) and press.start > 0.0
    sim = polydem.Simulation(scene, device=device)
    assert sim.model.motion_area[0] == pytest.approx(0.06 * 0.06)
    (lid,) = scene.body_motion
    z0 = sim.state()["body_position"][lid, 2]
    sim.step(50)
    assert tuple(travel(sim)[:2]) == (0.0, 0.0) and sim.state()["body_position"][lid, 2] == z0
    # The same scene started at once: 20 steps at max_speed.
    now = polydem.Scene.from_dict({**scene.to_dict(), "motions": {"press": {**press.to_dict(), "start": 0.0}}})
    sim = polydem.Simulation(now, device=device)
    sim.step(20)
    d, v, f = travel(sim)
    assert f == 0.0 and v == press.max_speed
    assert d == pytest.approx(press.max_speed * sim.dt * 20, rel=1e-12)
    assert sim.state()["body_position"][lid, 2] == pytest.approx(z0 - d, abs=1e-12)


def test_polydem_run_reports_the_servo(device, tmp_path, capsys):
    """`polydem run` runs a compression from its scene file and reports each ramp and servo in summary.json."""
    import json
    from pathlib import Path

    from cli_helpers import run, write_scene

    text = (Path(__file__).parents[1] / "scenes" / "compression.toml").read_text()
    # No USD: the report is the point, and the GPU machine's bundle has no usd-core.
    no_usd = ("fps = 50", "fps = 50\nusd = false")
    path = write_scene(tmp_path, text, replace=[("start = 0.5 ", "start = 0.0 "), no_usd])
    code, _, err = run(["run", path, "--device", device, "--steps", "40", "--out", tmp_path / "out"], capsys)
    assert code == 0, err
    press = json.loads((tmp_path / "out" / "summary.json").read_text())["motions"]["press"]
    assert press["kind"] == "servo" and press["force"] == 0.0 and press["velocity"] == 0.25
    dt = polydem.Scene.from_toml(path).time_step().dt
    assert press["displacement"] == pytest.approx(40 * 0.25 * dt, rel=1e-9)


# ---------------------------------------------------------------------- friction


def block_on_incline(mu, angle=30.0):
    """A cube of 1 cm resting on a face on a plane tilted by ``angle`` degrees about y."""
    sc = polydem.Scene(gravity=(0.0, 0.0, -9.81))
    sc.add_material("m", density=2500.0, k=1e9, restitution=0.3, friction=mu, law="hertz")
    sc.add_shape("cube", polydem.ConvexShape.box(CUBE))
    a = math.radians(angle)
    n = (-math.sin(a), 0.0, math.cos(a))
    sc.add_plane((0.0, 0.0, 0.0), n, "m")
    c = 0.5 * CUBE + 1e-5
    sc.add_body(
        "cube", "m", position=(n[0] * c, 0.0, n[2] * c), orientation=(0.0, -math.sin(a / 2), 0.0, math.cos(a / 2))
    )
    return sc


def test_set_friction_lets_a_block_slide_and_stop_again(device):
    """On a 30 degree slope (tan = 0.577) a cube holds at mu = 0.8; at mu = 0 it slides with g sin 30
    (after the switch, in the same captured step); at mu = 0.8 again it stops within 0.03 s and stays."""
    sim = polydem.Simulation(block_on_incline(0.8), device=device)
    assert sim.material_friction() == {"m": 0.8}
    sim.step(1000)
    x0 = sim.state()["body_position"][0].copy()
    sim.step(500)
    assert np.linalg.norm(sim.state()["body_position"][0] - x0) < 2e-6  # holds
    sim.set_friction(0.0)
    assert sim.material_friction() == {"m": 0.0}
    t0, v0 = sim.time, sim.state()["body_velocity"][0]
    sim.step(1500)
    dv = np.linalg.norm(sim.state()["body_velocity"][0] - v0)
    assert dv == pytest.approx(9.81 * 0.5 * (sim.time - t0), rel=0.03)
    sim.set_friction(0.8, "m")
    sim.step(4500)  # 0.03 s: it stops after v / (g (0.8 cos 30 - sin 30)) = 0.035 m/s / 1.9 m/s^2 = 0.018 s
    x1 = sim.state()["body_position"][0].copy()
    sim.step(1000)
    assert np.linalg.norm(sim.state()["body_position"][0] - x1) < 2e-6


def test_set_friction_errors(device):
    sim = polydem.Simulation(block_on_incline(0.0, angle=0.0), device=device)
    sim.set_friction(0.0)  # nothing to change, and allowed
    with pytest.raises(ValueError, match="built without friction.*Build it with the friction"):
        sim.set_friction(0.5)
    assert sim.material_friction() == {"m": 0.0}
    sim2 = polydem.Simulation(block_on_incline(0.5, angle=0.0), device=device)
    with pytest.raises(ValueError, match="unknown material 'rock'; the scene's materials are m"):
        sim2.set_friction(0.2, "rock")
    with pytest.raises(ValueError, match="friction must be a number >= 0"):
        sim2.set_friction(-0.1)
    # The pair table mixes as the scene's: the smaller coefficient of the two.
    sim2.set_friction(0.25)
    assert sim2.model.material_mu.numpy().tolist() == [0.25]  # the device table the kernels read


def test_anneal_fills_at_low_friction_then_restores_it(device):
    """anneal(): the fill settles at mu_fill, then the final friction is set and the grains settle again."""
    sc = polydem.Scene(gravity=(0.0, 0.0, -9.81))
    sc.add_material("m", density=2500.0, k=1e9, restitution=0.3, friction=0.5, law="hertz")
    sc.add_shape("cube", polydem.ConvexShape.box(CUBE))
    sc.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    sc.add_body("cube", "m", position=(0.0, 0.0, 0.5 * CUBE + 2e-5))
    sc.add_body("cube", "m", position=(0.0102, 0.0, 0.5 * CUBE + 2e-5))
    sim = polydem.Simulation(sc, device=device)
    box = polydem.measures.Box((-0.005, -0.005, 0.0), (0.0152, 0.005, 0.01))
    records = anneal(sim, 0.1, 0.5, fill_time=0.1, settle_time=0.1, box=box)
    assert [r.stage for r in records] == ["fill", "final"] and [r.friction for r in records] == [0.1, 0.5]
    assert all(r.settled for r in records) and records[1].time > records[0].time
    assert records[1].packing_fraction == pytest.approx(2e-6 / box.volume, rel=1e-3)
    assert sim.material_friction() == {"m": 0.5}
    assert wp.get_device(device) == sim.device
