"""The prescribed motions of containers (kernels/motion.py) against their closed form."""

import math

import numpy as np
import pytest
import warp as wp
from polydem.kernels.motion import Motions, launch_drive_bodies
from polydem.kernels.structs import filled


def closed_form(t, amplitude, omega, start, period, count):
    tau = t - start
    k = np.floor(tau / period)
    s = tau - k * period
    on = (tau >= 0) & ((count == 0) | (k < count)) & (omega * s < 2 * math.pi)
    d = np.where(on, amplitude * (1 - np.cos(omega * s)), 0.0)
    return d, np.where(on, amplitude * omega * np.sin(omega * s), 0.0)


MOTIONS = [  # (amplitude [m], frequency [Hz], start [s], period [s] or None for continuous, count)
    (1e-3, 30.0, 0.0, None, 0),  # a vibration without end
    (2e-3, 25.0, 0.01, 0.2, 3),  # three taps, 0.2 s apart, the first at 10 ms
]


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_driven_bodies_follow_the_cycles(device, precision):
    scalar = wp.float64 if precision == "float64" else wp.float32
    transform = wp.types.transformation(scalar)
    vec3 = wp.types.vector(3, scalar)
    axis = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]])
    amp = np.array([m[0] for m in MOTIONS])
    omega = np.array([2 * math.pi * m[1] for m in MOTIONS])
    start = np.array([m[2] for m in MOTIONS])
    period = np.array([m[3] if m[3] is not None else 1.0 / m[1] for m in MOTIONS])
    count = np.array([m[4] for m in MOTIONS], dtype=np.int32)
    rest = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [5.0, 5.0, 5.0]])
    cycles = {"amplitude": amp, "omega": omega, "start": start, "period": period}
    cycles = {k: wp.array(a, dtype=wp.float64, device=device) for k, a in cycles.items()}
    motions = filled(
        Motions,
        axis=wp.array(axis, dtype=wp.vec3d, device=device),
        **cycles,
        count=wp.array(count, dtype=int, device=device),
        body_motion=wp.array([0, 1, -1], dtype=int, device=device),
        body_rest=wp.array(rest, dtype=wp.vec3d, device=device),
    )
    pose = np.hstack([rest, np.tile([0.0, 0.0, 0.6, 0.8], (3, 1))])
    body_q = wp.array(pose, dtype=transform, device=device)
    body_v = wp.array(np.full((3, 3), 7.0), dtype=vec3, device=device)
    dt = 1e-4
    tol = 1e-15 if precision == "float64" else 4e-7
    for step in [0, 1, 99, 100, 333, 1666, 2101, 2500, 4100, 6100, 6200, 12345, 10**6 + 7]:
        launch_drive_bodies(motions, wp.array([step], dtype=int, device=device), 1, dt, body_q, body_v, device=device)
        t = (step + 1) * dt
        q, v = body_q.numpy().astype(np.float64), body_v.numpy().astype(np.float64)
        for b, m in ((0, 0), (1, 1)):
            d, s = closed_form(t, amp[m], omega[m], start[m], period[m], count[m])
            # The time within the cycle is t less whole periods: it carries t's rounding (GPU and CPU
            # round the subtraction differently), a phase error of omega * 8 eps t.
            phase = omega[m] * 8.0 * np.finfo(np.float64).eps * t
            x_tol = tol * 10 * np.abs(rest[b]).max() + amp[m] * phase + tol * amp[m]
            v_tol = amp[m] * omega[m] * (phase + 10 * tol)
            np.testing.assert_allclose(q[b, :3], rest[b] + axis[m] * d, rtol=0, atol=x_tol, err_msg=(step, b))
            np.testing.assert_allclose(v[b], axis[m] * s, rtol=0, atol=v_tol, err_msg=(step, b))
        stored = pose.astype(np.float64 if precision == "float64" else np.float32).astype(np.float64)
        np.testing.assert_array_equal(q[:, 3:], stored[:, 3:])  # orientations untouched
        np.testing.assert_array_equal(q[2], stored[2])  # an undriven body keeps its state
        np.testing.assert_array_equal(v[2], 7.0)


def test_cycle_closed_form_properties():
    """One cycle starts and ends at rest in place, lifts by 2 A, and its peak acceleration is A w^2 (the Gamma
    of a tap); the taps rest between cycles and stop after ``count``."""
    a, f = 1e-3, 30.0
    w = 2 * math.pi * f
    t = np.linspace(0, 1 / f, 20001)
    d, v = closed_form(t[:-1], a, w, 0.0, 0.2, 2)
    assert d[0] == 0 and v[0] == 0 and d.max() == pytest.approx(2 * a, rel=1e-8)
    acc = np.gradient(v, t[:-1])
    assert np.abs(acc[5:-5]).max() == pytest.approx(a * w * w, rel=1e-3)
    d, v = closed_form(np.array([0.01, 0.21, 0.41, 0.1]), a, w, 0.0, 0.2, 2)
    lift = a * (1 - math.cos(w * 0.01))
    np.testing.assert_allclose(d, [lift, lift, 0.0, 0.0], rtol=1e-9)


def shaken_box(gamma, precision="mixed", count=2):
    import polydem

    sc = polydem.Scene(gravity=(0.0, 0.0, -9.81), precision=precision)
    sc.add_material("m", density=2500.0, k=1e9, restitution=0.3, friction=0.5, law="hertz")
    sc.add_motion("shaker", 25.0, gamma=gamma, period=0.1, count=count)
    sc.add_shape("cube", polydem.ConvexShape.box(0.02))
    walls = sc.add_box_container((0.0, 0.0, 0.05), (0.1, 0.1, 0.1), "m", motion="shaker")
    cube = sc.add_body("cube", "m", position=(0.0, 0.0, 0.01 + 2e-5))
    return sc, walls, cube


@pytest.mark.parametrize("precision", ["mixed", "float64"])
def test_a_shaken_box_follows_its_motion_and_carries_a_cube_below_one_g(device, precision):
    """The container's slabs are where the motion puts them at every step (no drift from summed velocities),
    and a cube resting on the floor rides along at Gamma = 0.5 (its lift within its resting depth), then
    rests again after the last tap."""
    import polydem

    sc, walls, cube = shaken_box(0.5, precision)
    sim = polydem.Simulation(sc, device=device)
    motion = sc.motions["shaker"]
    amp = motion.amplitude_in(sc.gravity)
    rest = np.asarray(sc.body_position)[walls]
    z0 = None
    chunk = max(1, round(0.01 / sim.dt))
    for _ in range(26):  # 0.26 s: two taps (0 and 0.1 s, 0.04 s each), then rest
        sim.step(chunk)
        t = sim.time
        d = amp * (1.0 - math.cos(motion.omega * (t % 0.1))) if t < 0.2 and (t % 0.1) < 0.04 else 0.0
        pos = sim.state()["body_position"]
        np.testing.assert_allclose(pos[walls, 2] - rest[:, 2], d, rtol=0, atol=1e-9 + 1e-6 * amp)
        np.testing.assert_allclose(pos[walls, :2], rest[:, :2], rtol=0, atol=1e-12)
        if z0 is None and t > 0.0:
            z0 = pos[cube, 2] - d
        assert abs(pos[cube, 2] - d - z0) < 2e-5, (t, pos[cube, 2] - d - z0)
    assert abs(sim.state()["body_velocity"][cube]).max() < 1e-3


def test_taps_above_one_g_throw_the_cube_off_the_floor(device):
    """At Gamma = 3 the floor decelerates faster than g in the middle of each tap: the cube leaves it, rises
    above where the floor carries it and lands again."""
    import polydem

    sc, walls, cube = shaken_box(3.0, count=1)
    sim = polydem.Simulation(sc, device=device)
    motion = sc.motions["shaker"]
    floor0 = np.asarray(sc.body_position)[walls[0], 2]
    gap = []
    chunk = max(1, round(0.002 / sim.dt))
    for _ in range(30):
        sim.step(chunk)
        pos = sim.state()["body_position"]
        gap.append(pos[cube, 2] - 0.01 - (pos[walls[0], 2] - floor0) - (floor0 + 0.5 * (0.01)))
    assert max(gap) > 0.2 * motion.amplitude_in(sc.gravity)


def test_motion_keys_from_a_scene_file_and_back(tmp_path):
    import polydem

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
[shapes.cube]
type = "box"
size = 0.02
[[walls]]
type = "box"
center = [0.0, 0.0, 0.05]
inner_size = [0.1, 0.1, 0.1]
material = "m"
motion = "tap"
[[bodies]]
shape = "cube"
material = "m"
position = [0.0, 0.0, 0.011]
"""
    path = tmp_path / "tap.toml"
    path.write_text(text)
    sc = polydem.Scene.from_toml(path)
    assert sc.motions["tap"].count == 20 and len(sc.body_motion) == 5
    again = polydem.Scene.from_dict(sc.to_dict())
    assert again.body_motion == sc.body_motion and again.motions == sc.motions
    path.write_text(text.replace('motion = "tap"', 'motion = "tapp"'))
    with pytest.raises(polydem.SceneError, match="walls\\[0\\].motion: unknown motion 'tapp'; did you mean 'tap'"):
        polydem.Scene.from_toml(path)
    path.write_text(text.replace("gamma = 4.0", "gamma = 4.0\namplitude = 0.001"))
    with pytest.raises(polydem.SceneError, match="motions.tap.amplitude: give the motion's size as amplitude"):
        polydem.Scene.from_toml(path)


def test_tap_protocol_measures_before_each_tap(device):
    """polydem.protocols.tap: a record before the first tap and after each, taken while the container rests
    (its slabs at their rest positions), the grains come to rest again, the packing fraction a fraction."""
    import polydem
    from polydem.measures import Box
    from polydem.protocols import tap

    sc = polydem.Scene(gravity=(0.0, 0.0, -9.81))
    sc.add_material("m", density=2500.0, k=1e9, restitution=0.3, friction=0.5, law="hertz")
    sc.add_motion("taps", 25.0, gamma=2.0, start=0.3, period=0.25, count=1)
    sc.add_shape("cube", polydem.ConvexShape.box(0.01))
    walls = sc.add_box_container((0.0, 0.0, 0.05), (0.06, 0.06, 0.1), "m", motion="taps")
    sc.emit("cube", "m", 18, ((-0.029, -0.029, 0.006), (0.029, 0.029, 0.1)), seed=3)
    sim = polydem.Simulation(sc, device=device)
    records = tap(sim, "taps", Box((-0.03, -0.03, 0.0), (0.03, 0.03, 0.01)))
    assert [r.tap for r in records] == [0, 1]
    np.testing.assert_allclose([r.time for r in records], [0.279, 0.529], atol=2 * sim.dt)
    rest = np.asarray(sc.body_position)[walls]
    np.testing.assert_allclose(sim.state()["body_position"][walls], rest, rtol=0, atol=1e-12)
    for r in records:  # poured and settled before the tap, and again after it
        assert 0.2 < r.packing_fraction < 0.8 and r.fastest < 0.05, r
    with pytest.raises(ValueError, match="no end"):
        sc2 = polydem.Scene()
        sc2.add_motion("v", 30.0, amplitude=1e-3)
        tap(type("S", (), {"scene": sc2, "time": 0.0})(), "v")
