"""The stopping rule of a run that goes on until its pile has settled (polydem.settle).

The check is compared with independent code: the energies of Simulation.energy() (the kinetic
energy kernel of the integrator and the gravitational energy summed on the host) and the speeds of
Simulation.state() with the cube's bounding radius, stepped chunk by chunk in a second run of the
same scene, which finds when the last body last moved fast.
"""

import math

import numpy as np
import pytest

from polydem import ConvexShape, Scene, SettleCriterion, Simulation
from polydem.run_settings import run_settings
from polydem.settle import SPEED_FRACTION, SettleCheck, grain_radius
from polydem.simulation import CHUNK_STEPS

FRACTION = 1e-4
# The default speed limit of the drop scene's 0.1 m cubes: 3e-4 sqrt(g r), r = sqrt(3) 0.05 m.
CUBE_RADIUS = math.sqrt(3.0) * 0.05
DROP_LIMIT = 3e-4 * math.sqrt(9.81 * CUBE_RADIUS)


def drop_scene(n=4, gravity=(0.0, 0.0, -9.81)):
    """``n`` 0.1 m cubes dropped side by side from gaps of 3 to 12 cm onto a plane (soft, damped)."""
    s = Scene(gravity=gravity, dt="auto")
    s.add_material("m", density=1000.0, law="hertz", k=1e7, restitution=0.2, friction=0.5)
    s.add_shape("cube", ConvexShape.box(0.1))
    for i in range(n):
        s.add_body("cube", "m", position=(0.15 * i, 0.0, 0.08 + 0.03 * i))
    s.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    return s


def test_cubes_settle_after_their_last_impact(device):
    sim = Simulation(drop_scene(), device=device)
    result = sim.run_until_settled(1.0)  # the default criterion: kinetic fraction 1e-4 and the speed limit
    assert result.settled
    assert result.speed_limit == pytest.approx(DROP_LIMIT, rel=1e-6)
    assert result.largest_speed < DROP_LIMIT
    assert result.steps_done % CHUNK_STEPS == 0 and result.steps == result.steps_done
    assert result.time == pytest.approx(result.steps * sim.dt)
    assert result.time - result.held_from >= 0.02 - 1e-12
    assert result.time < 0.5  # well before the maximum
    # The measurements at the stop agree with Simulation.energy() (another kernel and a host sum), both
    # in float64 under the default precision (mixed): measured identical, bit for bit, on the CPU.
    e = sim.energy()
    assert result.kinetic == pytest.approx(e["kinetic"], rel=1e-12, abs=1e-15)
    released = e0_gravity(drop_scene(), device) - e["gravity"]
    assert result.released == pytest.approx(released, rel=1e-12)
    assert result.kinetic < FRACTION * result.released

    # A second run, checked with energy() and state() at every chunk: the last check at which the
    # bodies moved faster than the criterion allows (the last impact, bounce or rocking) comes before
    # the stretch that counted as settled, and after the stop they stay settled.
    ref = Simulation(drop_scene(), device=device)
    g0 = ref.energy()["gravity"]
    last_fast = 0.0
    while ref.steps_done < result.steps_done + int(round(0.2 / ref.dt)):
        ref.step(CHUNK_STEPS)
        e = ref.energy()
        st = ref.state()
        speed = np.linalg.norm(st["body_velocity"], axis=1) + np.linalg.norm(st["body_angular_velocity"], axis=1) * (
            CUBE_RADIUS
        )
        fast = e["kinetic"] >= FRACTION * (g0 - e["gravity"]) or speed.max() >= DROP_LIMIT * (1.0 - 1e-5)
        if ref.steps_done <= result.steps_done:
            if fast:
                last_fast = ref.time
        else:
            assert not fast, f"moving again at t = {ref.time:.4g} s after settling at {result.time:.4g} s"
    assert 0.1 < last_fast < result.held_from  # the bodies fell for at least 0.1 s
    # and the stop is no later than the hold after that check (plus one check)
    assert result.held_from <= last_fast + CHUNK_STEPS * sim.dt * 1.0001


def e0_gravity(scene, device):
    return Simulation(scene, device=device).energy()["gravity"]


def test_too_short_a_maximum_is_not_settled(device):
    sim = Simulation(drop_scene(2), device=device)
    result = sim.run_until_settled(0.05)
    assert not result.settled
    assert result.steps == math.ceil(0.05 / sim.dt - 1e-9) == sim.steps_done
    assert result.kinetic > FRACTION * result.released  # still falling


def test_speed_alone_without_gravity(device):
    scene = drop_scene(2, gravity=(0.0, 0.0, 0.0))
    sim = Simulation(scene, device=device)
    with pytest.raises(ValueError, match="no gravity"):
        sim.run_until_settled(0.1)
    # At rest in space: settled at the first check that has held for the hold time.
    result = sim.run_until_settled(0.1, SettleCriterion(kinetic_fraction=None, max_speed=1e-3, hold=0.0))
    assert result.settled and result.steps == CHUNK_STEPS and result.largest_speed == 0.0


def test_speed_criterion_sees_the_fastest_point(device):
    # A cube spinning in space at 2 rad/s about z: its fastest point moves at 2 r, its centre not at all.
    scene = Scene(gravity=(0.0, 0.0, 0.0), dt=1e-4)
    scene.add_material("m", density=1000.0, law="hertz", k=1e7, restitution=0.2, friction=0.5)
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("cube", "m", position=(0.0, 0.0, 0.0), angular_velocity=(0.0, 0.0, 2.0))
    sim = Simulation(scene, device=device)
    r = float(np.sqrt(3.0) * 0.05)
    result = sim.run_until_settled(0.02, SettleCriterion(kinetic_fraction=None, max_speed=2.0 * r * 0.999))
    assert not result.settled
    assert result.largest_speed == pytest.approx(2.0 * r, rel=1e-5)
    result = sim.run_until_settled(0.02, SettleCriterion(kinetic_fraction=None, max_speed=2.0 * r * 1.001, hold=0))
    assert result.settled


def test_default_speed_limit_comes_from_the_grains_and_gravity():
    """3e-4 sqrt(|g| r_min), r_min the smallest bounding radius of a free body (a fixed body's does
    not count); a given max_speed replaces it; without gravity only max_speed can set it."""
    assert SPEED_FRACTION == 3e-4
    scene = drop_scene()
    assert grain_radius(run_settings(scene)) == pytest.approx(CUBE_RADIUS, rel=1e-12)
    assert SettleCriterion().speed_limit_of(scene) == pytest.approx(DROP_LIMIT, rel=1e-12)
    # A grain 4x smaller (r / 4) under 9x the gravity: the limit is 3/2 of the drop scene's.
    s = Scene(gravity=(0.0, 9.0 * 9.81, 0.0))
    s.add_material("m", density=1000.0, law="hertz", k=1e7, restitution=0.2, friction=0.5)
    s.add_shape("cube", ConvexShape.box(0.1))
    s.add_shape("small", ConvexShape.box(0.025))
    s.add_shape("pebble", ConvexShape.box(0.001))
    s.add_body("cube", "m", position=(0.0, 0.0, 0.0))
    s.add_body("small", "m", position=(0.2, 0.0, 0.0))
    s.add_body("pebble", "m", position=(0.4, 0.0, 0.0), kind="fixed")
    assert grain_radius(run_settings(s)) == pytest.approx(CUBE_RADIUS / 4.0, rel=1e-12)
    assert SettleCriterion().speed_limit_of(s) == pytest.approx(1.5 * DROP_LIMIT, rel=1e-12)
    assert SettleCriterion(speed_fraction=1e-2).speed_limit_of(s) == pytest.approx(1.5 * DROP_LIMIT / 0.03, rel=1e-12)
    assert SettleCriterion(max_speed=0.5).speed_limit_of(s) == 0.5
    assert SettleCriterion(speed_fraction=None).speed_limit_of(s) is None
    assert "largest speed < 0.000415 m/s = 0.0003 sqrt(g r_min)" in SettleCriterion().describe(s)
    s.gravity = (0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="speed_fraction criterion scales with sqrt"):
        SettleCriterion(kinetic_fraction=None).speed_limit_of(s)
    assert SettleCriterion(kinetic_fraction=None, max_speed=0.5).speed_limit_of(s) == 0.5


def test_a_check_of_the_scaled_limit_needs_it():
    with pytest.raises(ValueError, match="give speed_limit"):
        SettleCheck(SettleCriterion(), 1.0)
    with pytest.raises(ValueError, match="not the criterion's max_speed"):
        SettleCheck(SettleCriterion(max_speed=0.1), 1.0, speed_limit=0.2)
    check = SettleCheck(SettleCriterion(max_speed=0.1), 1.0)
    assert check.speed_limit == 0.1 and check.record()["speed_limit"] == 0.1
    # The limit, not max_speed (None here), decides.
    check = SettleCheck(SettleCriterion(hold=0.0), 1.0, speed_limit=1e-3)
    assert not check.update(64, 1e-4, 0.0, 0.5, 1e-3)
    assert check.update(128, 1e-4, 0.0, 0.5, 0.999e-3)


def test_a_continued_check_settles_as_the_unbroken_run(device):
    """Two calls continuing one SettleCheck (as a resumed run does) stop at the step of one call."""
    whole = Simulation(drop_scene(), device=device).run_until_settled(1.0)
    sim = Simulation(drop_scene(), device=device)
    check = sim.settle_check()
    first = sim.run_until_settled(0.21, check=check)  # off the check cadence: the hold goes on from the last check
    assert not first.settled and first.steps_done % CHUNK_STEPS
    second = sim.run_until_settled(1.0 - first.time, check=check)
    assert whole.settled and second.settled
    assert (second.steps_done, second.held_from, second.speed_limit) == (
        whole.steps_done,
        whole.held_from,
        whole.speed_limit,
    )


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"kinetic_fraction": 0.0}, "kinetic_fraction must be > 0"),
        ({"kinetic_fraction": -1e-3}, "kinetic_fraction must be > 0"),
        ({"kinetic_fraction": 1.0}, "kinetic_fraction must be < 1"),
        ({"kinetic_fraction": float("nan")}, "kinetic_fraction must be finite"),
        ({"max_speed": 0.0}, "max_speed must be > 0"),
        ({"hold": -0.01}, "hold must be >= 0"),
        ({"kinetic_fraction": None, "speed_fraction": None}, "nothing is checked"),
        ({"speed_fraction": 0.0}, "speed_fraction must be > 0"),
        ({"speed_fraction": float("inf")}, "speed_fraction must be finite"),
        ({"hold": "1"}, "hold must be a number"),
    ],
)
def test_bad_criteria(kwargs, match):
    with pytest.raises(ValueError, match=match):
        SettleCriterion(**kwargs)


def test_bad_run_arguments():
    sim = Simulation(drop_scene(1), device="cpu")
    with pytest.raises(ValueError, match="max_time must be"):
        sim.run_until_settled(0.0)
    with pytest.raises(TypeError, match="SettleCriterion"):
        sim.run_until_settled(0.1, {"kinetic_fraction": 1e-3})
    assert sim.steps_done == 0


def test_scene_without_free_bodies():
    s = Scene()
    s.add_material("m", density=1000.0, law="hertz", k=1e7, restitution=0.2, friction=0.5)
    s.add_shape("cube", ConvexShape.box(0.1))
    s.add_body("cube", "m", position=(0.0, 0.0, 0.0), kind="fixed")
    with pytest.raises(ValueError, match="no free bodies"):
        Simulation(s, device="cpu").run_until_settled(0.1)


def test_every_precision_settles_at_the_same_check(device):
    """The measuring kernel in each precision's scalar: the three runs stop at the same check. By the
    kinetic part alone: the largest speed near its limit crosses it a check earlier or later with the
    rounding of each precision (on CUDA: steps 2240 and 2304 under the default)."""
    steps = set()
    for precision in ("float32", "mixed", "float64"):
        scene = drop_scene()
        scene.precision = precision
        result = Simulation(scene, device=device).run_until_settled(1.0, SettleCriterion(speed_fraction=None))
        assert result.settled and result.kinetic_fraction < FRACTION
        steps.add(result.steps)
    assert len(steps) == 1, steps
