"""The stopping rule of a run that goes on until its pile has settled (polydem.settle).

The check is compared with independent code: the energies of Simulation.energy() (the kinetic
energy kernel of the integrator and the gravitational energy summed on the host), stepped chunk by
chunk in a second run of the same scene, which finds when the last body last moved fast.
"""

import math

import numpy as np
import pytest

from polydem import ConvexShape, Scene, SettleCriterion, Simulation
from polydem.simulation import CHUNK_STEPS

FRACTION = 1e-4


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
    result = sim.run_until_settled(1.0, SettleCriterion(kinetic_fraction=FRACTION, hold=0.02))
    assert result.settled
    assert result.steps_done % CHUNK_STEPS == 0 and result.steps == result.steps_done
    assert result.time == pytest.approx(result.steps * sim.dt)
    assert result.time - result.held_from >= 0.02 - 1e-12
    assert result.time < 0.5  # well before the maximum
    # The measurements at the stop agree with Simulation.energy() (another kernel and a host sum).
    e = sim.energy()
    assert result.kinetic == pytest.approx(e["kinetic"], rel=1e-6, abs=1e-12)
    released = e0_gravity(drop_scene(), device) - e["gravity"]
    assert result.released == pytest.approx(released, rel=1e-9)
    assert result.kinetic < FRACTION * result.released

    # A second run, checked with energy() at every chunk: the last check at which the bodies moved
    # faster than the criterion allows (the last impact or bounce) comes before the stretch that
    # counted as settled, and after the stop they stay settled.
    ref = Simulation(drop_scene(), device=device)
    g0 = ref.energy()["gravity"]
    last_fast = 0.0
    while ref.steps_done < result.steps_done + int(round(0.2 / ref.dt)):
        ref.step(CHUNK_STEPS)
        e = ref.energy()
        fast = e["kinetic"] >= FRACTION * (g0 - e["gravity"])
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


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"kinetic_fraction": 0.0}, "kinetic_fraction must be > 0"),
        ({"kinetic_fraction": -1e-3}, "kinetic_fraction must be > 0"),
        ({"kinetic_fraction": 1.0}, "kinetic_fraction must be < 1"),
        ({"kinetic_fraction": float("nan")}, "kinetic_fraction must be finite"),
        ({"max_speed": 0.0}, "max_speed must be > 0"),
        ({"hold": -0.01}, "hold must be >= 0"),
        ({"kinetic_fraction": None}, "give kinetic_fraction, max_speed or both"),
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
    """The measuring kernel in each precision's scalar: the three runs stop at the same check."""
    steps = set()
    for precision in ("float32", "mixed", "float64"):
        scene = drop_scene()
        scene.precision = precision
        result = Simulation(scene, device=device).run_until_settled(1.0)
        assert result.settled and result.kinetic_fraction < FRACTION
        steps.add(result.steps)
    assert len(steps) == 1, steps
