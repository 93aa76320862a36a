"""A turning drum, stepped: scenes/drum.toml with 40 grains for 0.4 s (a fifth of a turn).

The drum is 26 kinematic bodies turning about a pivot (kernels/integrate.py moves each on its circle),
and only friction and the corners of its 24-gon carry the grains. Through the scene file, so that the
file's drum (its axis, the sense of its turn, its pivot) is what is tested. About 7 s on one CPU core.
"""

import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

from polydem import Scene, Simulation
from polydem.scene import KIND_FREE

SCENE = Path(__file__).resolve().parents[1] / "scenes" / "drum.toml"
GRAINS = 40
DURATION = 0.4  # [s]
SAMPLE = 0.05  # [s]


def small_drum():
    data = tomllib.loads(SCENE.read_text())
    assert data["emitters"][0]["count"] == 300 and data["walls"][0]["type"] == "drum"
    data["emitters"][0]["count"] = GRAINS
    data.pop("output", None)
    return Scene.from_dict(data, file=str(SCENE), base_dir=SCENE.parent)


@pytest.fixture(scope="module")
def drum_run(devices):
    """Samples every SAMPLE s of the small drum on the first test device: times, free-body positions
    relative to the drum centre, velocities, energies; and the scene."""
    scene = small_drum()
    sim = Simulation(scene, devices[0])
    free = np.flatnonzero(scene.body_kind == KIND_FREE)
    centre = np.asarray(scene.drums[0].center)
    samples = []
    every = int(round(SAMPLE / sim.dt))
    while sim.time < DURATION - 0.5 * SAMPLE:
        sim.step(every)
        st = sim.state()
        samples.append((sim.time, st["body_position"][free] - centre, st["body_velocity"][free], sim.energy()))
    return scene, free, samples


def test_grains_ride_up_the_rising_side(drum_run):
    """The drum turns by the right-hand rule about its axis: the bed is carried up the side whose wall
    rises (up x axis, for a horizontal axis) and its angular momentum about the axis is in the drum's
    sense. Measured: from 0.25 s the grains carry 0.73 to 0.91 of the angular momentum of the bed turning
    rigidly with the drum, and at 0.4 s their centre of mass is 8.2 cm (4 grain sizes) towards the rising
    side. A drum turning the other way than its axis and rpm say, or parts that do not carry the grains,
    fail both."""
    scene, free, samples = drum_run
    drum = scene.drums[0]
    axis = np.asarray(drum.axis)
    mass = scene.body_mass()[free]
    gravity = np.asarray(scene.gravity)
    rising = np.cross(-gravity / np.linalg.norm(gravity), axis) * math.copysign(1.0, drum.omega)
    ratios, shifts = [], []
    for t, x, v, _ in samples:
        spin = (np.cross(x, mass[:, None] * v) @ axis).sum()
        radial = x - np.outer(x @ axis, axis)
        rigid = drum.omega * (mass * (radial**2).sum(axis=1)).sum()
        ratios.append(spin / rigid)
        shifts.append(float((mass[:, None] * x).sum(axis=0) @ rising / mass.sum()))
        print(f"t {t:.3f} s: angular momentum {spin / rigid:+.3f} of the rigid bed's, "
              f"centre of mass {shifts[-1] * 100:+.2f} cm towards the rising side")  # fmt: skip
    times = np.array([s[0] for s in samples])
    late = times > 0.2
    assert np.all(np.array(ratios)[late] > 0.4)
    size = 0.02  # the grains' size [m]
    assert shifts[-1] > 2.0 * size
    assert shifts[-1] > shifts[0] + 2.0 * size  # carried there, not set down there


def test_no_grain_leaves_and_energy_stays_bounded(drum_run):
    """Every grain's centre stays inside the drum (within the inradius of the 24-gon from the axis,
    within the end plates along it), and no grain moves faster than the drum's rim plus a fall across
    the drum's diameter: a grain pushed through a wall, or a blow-up, breaks one of the two."""
    scene, free, samples = drum_run
    drum = scene.drums[0]
    axis = np.asarray(drum.axis)
    v_max = abs(drum.omega) * drum.radius + math.sqrt(2.0 * np.linalg.norm(scene.gravity) * 2.0 * drum.radius)
    for t, x, v, energy in samples:
        along = x @ axis
        radial = np.linalg.norm(x - np.outer(along, axis), axis=1)
        assert np.all(radial < drum.radius), (t, radial.max())
        assert np.all(np.abs(along) < 0.5 * drum.length), (t, np.abs(along).max())
        speed = np.linalg.norm(v, axis=1)
        assert np.all(np.isfinite(speed)) and speed.max() < v_max, (t, speed.max())
        assert math.isfinite(energy["total"]) and energy["dissipated"] >= 0.0
    # The grains are moving with the drum, not at rest (and not flung about): the mean kinetic
    # energy per grain is between a hundredth and ten times that of turning with the rim.
    kinetic = samples[-1][3]["kinetic"]
    rim = 0.5 * scene.body_mass()[free].sum() * (drum.omega * drum.radius) ** 2
    assert 0.01 * rim < kinetic < 10.0 * rim
