"""Plane and mesh walls that follow a motion (issue 26: containers of every kind tapped, shaken or driven).

The walls are where the closed form of their motion puts them at every step (d(t) from the step counter), a
cube resting on a shaken plane floor and on the same floor made of a mesh rides along alike, a floor driven up
by a ramp carries a cube at its speed, taps above one g throw it off, and a snapshot, a checkpoint and a CUDA
graph (on a GPU) carry on from any step.
"""

import math

import numpy as np
import pytest

import polydem
from polydem.scene import SceneWarning

SIZE = 0.02
SQUARE = (
    np.array([[-0.05, -0.05, 0.0], [0.05, -0.05, 0.0], [0.05, 0.05, 0.0], [-0.05, 0.05, 0.0]]),
    np.array([[0, 1, 2], [0, 2, 3]]),
)


def floor_scene(kind, gamma=0.5, precision="mixed", count=2, motion=None):
    """A cube resting on a floor (a plane, or a square mesh) that follows ``motion`` (default: taps)."""
    sc = polydem.Scene(gravity=(0.0, 0.0, -9.81), precision=precision)
    sc.add_material("m", density=2500.0, k=1e8, restitution=0.3, friction=0.5, law="hertz")
    if motion is None:
        sc.add_motion("floor", 25.0, gamma=gamma, period=0.1, count=count)
    else:
        sc.add_motion("floor", **motion)
    if kind == "plane":
        sc.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m", motion="floor")
    else:
        sc.add_mesh_wall(SQUARE, "m", motion="floor")
    sc.add_shape("cube", polydem.ConvexShape.box(SIZE))
    cube = sc.add_body("cube", "m", position=(0.0, 0.0, 0.5 * SIZE + 1e-5))
    return sc, cube


def floor_height(sim, kind):
    if kind == "plane":
        point, normal = sim.current_planes()[0]
        return float(point @ normal)
    return float(sim.current_state.mesh_q.numpy()[0][2])


def lift(motion, gravity, t):
    a = motion.amplitude_in(gravity)
    s = t % motion.cycle_period()
    on = t < motion.count * motion.cycle_period() and motion.omega * s < 2 * math.pi
    return a * (1.0 - math.cos(motion.omega * s)) if on else 0.0


def lift_speed(motion, gravity, t):
    """d lift / dt: the velocity the contacts must see the floor move at."""
    a = motion.amplitude_in(gravity)
    s = t % motion.cycle_period()
    on = t < motion.count * motion.cycle_period() and motion.omega * s < 2 * math.pi
    return a * motion.omega * math.sin(motion.omega * s) if on else 0.0


def floor_speed(sim, kind):
    """The floor's vertical velocity as the contact kernels take it (the Stepper's driven walls)."""
    v = sim.stepper.planes.v if kind == "plane" else sim.stepper.meshes.v
    return float(v.numpy()[0][2])


@pytest.mark.parametrize("kind", ["plane", "mesh"])
def test_a_shaken_floor_follows_its_motion_and_carries_a_cube(device, kind):
    sc, cube = floor_scene(kind)
    sim = polydem.Simulation(sc, device=device)
    motion = sc.motions["floor"]
    amp = motion.amplitude_in(sc.gravity)
    rest = None
    chunk = max(1, round(0.005 / sim.dt))
    for _ in range(50):  # two taps (0 and 0.1 s, 0.04 s each), then rest
        sim.step(chunk)
        d = lift(motion, sc.gravity, sim.time)
        assert floor_height(sim, kind) == pytest.approx(d, abs=1e-12 + 1e-6 * amp)
        speed = amp * motion.omega
        assert floor_speed(sim, kind) == pytest.approx(lift_speed(motion, sc.gravity, sim.time), abs=1e-7 * speed)
        z = sim.state()["body_position"][cube, 2]
        if rest is None:
            rest = z - d
        # Gamma = 0.5: the cube never leaves the floor; its depth changes by far less than the lift.
        assert abs(z - d - rest) < 1e-3 * amp + 5e-7, (sim.time, z - d - rest)
    assert np.abs(sim.state()["body_velocity"][cube]).max() < 1e-3


def test_plane_and_mesh_floors_move_a_cube_alike(device):
    """The same floor as a plane and as a mesh: the cube's path under the same taps agrees."""
    paths = {}
    for kind in ("plane", "mesh"):
        sc, cube = floor_scene(kind, gamma=0.8)
        sim = polydem.Simulation(sc, device=device)
        chunk = max(1, round(0.004 / sim.dt))
        paths[kind] = []
        for _ in range(15):
            sim.step(chunk)
            paths[kind].append(sim.state()["body_position"][cube, 2])
    amp = 0.8 * 9.81 / (2 * math.pi * 25.0) ** 2
    np.testing.assert_allclose(paths["mesh"], paths["plane"], rtol=0, atol=1e-4 * amp)
    assert max(paths["plane"]) - min(paths["plane"]) > amp  # it did ride the taps


@pytest.mark.parametrize("kind", ["plane", "mesh"])
def test_taps_above_one_g_throw_the_cube_off_a_driven_floor(device, kind):
    sc, cube = floor_scene(kind, gamma=3.0, count=1)
    sim = polydem.Simulation(sc, device=device)
    amp = sc.motions["floor"].amplitude_in(sc.gravity)
    gap = []
    for _ in range(25):
        sim.step(max(1, round(0.002 / sim.dt)))
        gap.append(sim.state()["body_position"][cube, 2] - 0.5 * SIZE - floor_height(sim, kind))
    assert max(gap) > 0.2 * amp


@pytest.mark.parametrize("kind", ["plane", "mesh"])
def test_a_ramp_floor_lifts_the_cube_at_its_speed(device, kind):
    """A floor that rises at 5 cm/s from t = 0.01 s for 0.02 s carries the cube up at that speed (its velocity,
    not only its position, reaches the contact: the friction and damping see the wall move), then stops."""
    ramp = {"kind": "ramp", "axis": (0.0, 0.0, 1.0), "speed": 0.05, "start": 0.01, "duration": 0.02}
    sc, cube = floor_scene(kind, motion=ramp)
    sim = polydem.Simulation(sc, device=device)
    z0 = sim.state()["body_position"][cube, 2]
    sim.step(round(0.025 / sim.dt))
    assert floor_height(sim, kind) == pytest.approx(0.05 * (sim.time - 0.01), rel=1e-9)
    assert sim.state()["body_velocity"][cube, 2] == pytest.approx(0.05, rel=0.05)
    sim.step(round(0.03 / sim.dt))
    assert floor_height(sim, kind) == pytest.approx(1e-3, rel=1e-12)
    assert sim.state()["body_position"][cube, 2] - z0 == pytest.approx(1e-3, rel=0.02)


def test_a_sideways_vibration_drags_the_cube_by_friction(device):
    """A plane floor shaken along x (in its own plane: its offset stays) moves the cube through friction alone:
    the wall's velocity reaches the friction spring."""
    shake = {"frequency": 10.0, "amplitude": 1e-3, "axis": (1.0, 0.0, 0.0), "period": 0.1, "count": 1}
    sc, cube = floor_scene("plane", motion=shake)
    sim = polydem.Simulation(sc, device=device)
    sim.step(round(0.05 / sim.dt))  # half the cycle: the floor is 2 mm along x
    assert floor_height(sim, "plane") == pytest.approx(0.0, abs=1e-15)
    # Peak acceleration A w^2 = 0.4 g < mu g: the cube sticks and moves with the floor, behind it by the
    # stretch of its friction spring (m A w^2 / k_t, about 45 um here), and comes back with it.
    assert sim.state()["body_position"][cube, 0] == pytest.approx(2e-3, abs=1e-4)
    sim.step(round(0.1 / sim.dt))
    assert abs(sim.state()["body_position"][cube, 0]) < 1e-4


def test_snapshot_and_checkpoint_resume_a_driven_wall_bit_for_bit(device, tmp_path):
    from polydem.checkpoint import load_checkpoint, save_checkpoint

    sc, cube = floor_scene("mesh", gamma=2.0)
    sim = polydem.Simulation(sc, device=device)
    sim.step(700)
    snap = sim.snapshot()
    save_checkpoint(sim, tmp_path / "c.npz")
    sim.step(900)
    end = sim.state()
    sim.restore(snap)
    sim.step(900)
    np.testing.assert_array_equal(sim.state()["body_position"], end["body_position"])
    other = polydem.Simulation(floor_scene("mesh", gamma=2.0)[0], device=device)
    load_checkpoint(other, tmp_path / "c.npz")
    other.step(900)
    np.testing.assert_array_equal(other.state()["body_position"], end["body_position"])
    np.testing.assert_array_equal(other.current_state.mesh_q.numpy(), sim.current_state.mesh_q.numpy())


def test_wall_motion_keys_from_a_scene_file_and_back(tmp_path):
    text = """
[simulation]
steps = 10
[materials.m]
density = 2500.0
law = "hertz"
k = 1e9
restitution = 0.3
friction = 0.5
[motions.tap]
frequency = 30.0
gamma = 4.0
period = 0.5
count = 20
[motions.press]
kind = "servo"
axis = [0.0, 0.0, -1.0]
force = 1.0
gain = 0.01
max_speed = 0.1
[shapes.cube]
type = "box"
size = 0.02
[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "m"
motion = "tap"
[[walls]]
type = "mesh"
vertices = [[-0.05, -0.05, 0.1], [0.05, -0.05, 0.1], [0.0, 0.05, 0.1]]
triangles = [[0, 2, 1]]
material = "m"
motion = "tap"
[[bodies]]
shape = "cube"
material = "m"
position = [0.0, 0.0, 0.011]
"""
    path = tmp_path / "walls.toml"
    path.write_text(text)
    sc = polydem.Scene.from_toml(path)
    assert sc.planes[0].motion == "tap" and sc.mesh_walls[0].motion == "tap"
    again = polydem.Scene.from_dict(sc.to_dict())
    assert again.planes[0].motion == "tap" and again.mesh_walls[0].motion == "tap"
    bad = [
        ('motion = "tap"\n[[walls]]', 'motion = "tapp"\n[[walls]]', r"walls\[0\].motion: unknown motion 'tapp'"),
        ('motion = "tap"\n[[walls]]', 'motion = "press"\n[[walls]]', r"walls\[0\].motion: motion 'press' is a servo"),
        ('material = "m"\nmotion = "tap"\n[[bodies]]', 'material = "m"\nmotion = "press"\n[[bodies]]',
         r"walls\[1\].motion: motion 'press' is a servo"),
        ('material = "m"\nmotion = "tap"\n[[bodies]]', 'material = "m"\nmotion = "tap"\nvelocity = [0.1, 0, 0]\n'
         "[[bodies]]", r"walls\[1\].velocity: a mesh wall follows either its motion \('tap'\) or its velocity"),
    ]  # fmt: skip
    for old, new, message in bad:
        assert old in text
        path.write_text(text.replace(old, new, 1))
        with pytest.raises(polydem.SceneError, match=message):
            polydem.Scene.from_toml(path)


def test_a_picture_draws_the_plane_where_it_is_now(device):
    sc, _ = floor_scene("plane", motion={"kind": "ramp", "axis": (0.0, 0.0, 1.0), "speed": 0.1})
    sim = polydem.Simulation(sc, device=device)
    sim.step(round(0.01 / sim.dt))
    ((point, normal),) = sim.current_planes()
    assert point @ normal == pytest.approx(0.1 * sim.time, rel=1e-9)
    fixed, _ = floor_scene("plane")
    ((point, _),) = polydem.Simulation(fixed, device=device).current_planes()
    assert point.tolist() == [0.0, 0.0, 0.0]


@pytest.mark.parametrize("kind", ["plane", "mesh"])
def test_contacts_report_the_forces_of_the_last_step_against_a_moving_wall(device, kind):
    """contacts() runs the last step's force stage again: with the wall where its motion had it at that step
    (not one step on), the reported forces balance the step's impulse, m dv/dt = F + m g."""
    from test_contact_report import reported_forces

    sc, cube = floor_scene(kind, gamma=2.0, precision="float64")
    sim = polydem.Simulation(sc, device=device)
    mass = sc.body_mass()[:, None]
    g = np.asarray(sc.gravity)
    sim.step(round(0.01 / sim.dt))  # into the first tap: the floor's speed changes every step
    worst = 0.0
    for _ in range(20):
        v0 = sim.state()["body_velocity"]
        sim.step(1)
        c = sim.contacts()
        assert len(c["volume"]) == 1
        want = mass * (sim.state()["body_velocity"] - v0) / sim.dt
        worst = max(worst, float(np.abs(reported_forces(c, 1) + mass * g - want).max() / (mass.max() * 9.81)))
    assert worst < 1e-9


def test_a_motion_faster_than_the_grains_can_take_is_warned():
    sc, _ = floor_scene("plane", motion={"frequency": 25.0, "amplitude": 0.1})
    with pytest.warns(SceneWarning, match=r"motion 'floor' moves planes\[0\] at up to 15.7 m/s, above the"):
        sc.validate()
    slow, _ = floor_scene("plane", motion={"frequency": 25.0, "amplitude": 0.001})
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        slow.validate()
