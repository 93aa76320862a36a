"""What Simulation.contacts() and the contact-force average report: the forces the steps applied.

contacts() gives the contacts of the last step with the forces that step integrated, so that per
body the reported forces plus m g are m dv/dt of that step (the impulses balance); before, it ran a
diagnostics pass at the state after the step, whose forces are those of the next step.
contact_average() gives each contact's impulse over an interval divided by its length, so that per
body the averaged forces plus m g are m (v_end - v_start) / T.
"""

import json

import numpy as np
import pytest

import polydem

G = np.array([0.0, 0.0, -9.81])
# Per body, |sum of reported forces + m g - m dv/dt| relative to the largest contact force or
# weight in the step. float64: rounding only (measured 2e-13). mixed: the contacts are float32
# (normal and normal force rounded apart, measured 2e-10 of the weight), the bodies float64.
TOLERANCE = {"float64": 1e-9, "mixed": 1e-5}


def steel_scene(precision="float64", gravity=(0.0, 0.0, -9.81)):
    scene = polydem.Scene(gravity=gravity, dt="auto", precision=precision)
    scene.add_material("steel", density=7800, law="hertz", k=1e10, restitution=0.5, friction=0.3)
    scene.add_shape("cube", polydem.ConvexShape.box(0.1))
    return scene


def impact_scene(precision="float64"):
    """A spinning cube landing on the plane (friction), and a cube landing on another that rests on
    the plane (a pair and two wall contacts): every contact force changes fast from step to step."""
    scene = steel_scene(precision)
    scene.add_body("cube", "steel", position=(0.0, 0.0, 0.05), velocity=(0.3, 0.0, -0.5), angular_velocity=(0, 2, 1))
    scene.add_body("cube", "steel", position=(0.4, 0.0, 0.05))
    scene.add_body("cube", "steel", position=(0.4, 0.01, 0.15), velocity=(0.2, 0.1, -0.8))
    scene.add_plane(point=(0, 0, 0), normal=(0, 0, 1), material="steel")
    return scene


def forces_per_body(body_a, body_b, force, n):
    """(n, 3) total force on each body from rows of forces on A (B gets the opposite)."""
    out = np.zeros((n, 3))
    np.add.at(out, body_a, force)
    pair = body_b >= 0
    np.subtract.at(out, body_b[pair], force[pair])
    return out


def reported_forces(c, n):
    force = -c["normal_force"][:, None] * c["normal"] + c["tangential_force"]
    return forces_per_body(c["body_a"], c["body_b"], force, n)


def forces_at_current_state(sim):
    """What contacts() reported before: the diagnostics pass at the state after the step."""
    d = sim.diagnostics()
    bp = sim.current_contacts.broadphase
    count = len(d["pair_volume"])
    on = d["pair_volume"] > 0.0
    force = -d["pair_fn"][on, None] * d["pair_normal"][on] + d["pair_ft"][on]
    a, b = bp.pair_a.numpy()[:count][on], bp.pair_b.numpy()[:count][on]
    out = forces_per_body(a, b, force, sim.num_bodies)
    body, wall = np.nonzero(d["wall_volume"] > 0.0)
    normal = -sim.model.plane_normal.numpy()[wall]
    np.add.at(out, body, -d["wall_fn"][body, wall, None] * normal + d["wall_ft"][body, wall])
    return out


@pytest.mark.parametrize("precision", ["float64", "mixed"])
def test_contacts_balance_the_impulses_of_the_last_step(device, precision):
    scene = impact_scene(precision)
    sim = polydem.Simulation(scene, device)
    mass = scene.body_mass()[:, None]
    tol = TOLERANCE[precision]
    worst = old_worst = 0.0
    seen = set()
    for _ in range(30):
        v0 = sim.state()["body_velocity"]
        sim.step(1)
        c = sim.contacts()
        seen.update(zip(c["body_a"].tolist(), c["body_b"].tolist(), strict=True))
        assert np.abs(c["tangential_force"]).max() > 0.0  # friction acts
        want = mass * (sim.state()["body_velocity"] - v0) / sim.dt  # m dv/dt of the step
        scale = max(np.abs(reported_forces(c, 3)).max(), float(mass.max()) * 9.81)
        worst = max(worst, np.abs(reported_forces(c, 3) + mass * G - want).max() / scale)
        old_worst = max(old_worst, np.abs(forces_at_current_state(sim) + mass * G - want).max() / scale)
    print(f"\n{precision}: impulse balance to {worst:.2e} of the largest force (the old report: {old_worst:.2e})")
    assert seen == {(0, -1), (1, -1), (1, 2)}  # the landing cube, the resting one and the pair
    assert worst < tol
    assert old_worst > 1e3 * tol  # the state after the step is one step off: this test tells them apart


def test_contacts_before_a_step_after_a_chunk_and_after_a_restore(device):
    """Before the first step and after restore(): the forces the next step applies; after step(n):
    those of its last step, as step(n - 1) then step(1) gives them (the captured graphs on CUDA)."""
    scene = impact_scene()
    sim = polydem.Simulation(scene, device)
    first = sim.contacts()  # step 0: the forces the first step will apply
    assert len(first["volume"]) > 0
    f0 = sim.state()["body_velocity"]
    sim.step(1)
    for k in first:
        np.testing.assert_array_equal(sim.contacts()[k], first[k], err_msg=k)
    mass = scene.body_mass()[:, None]
    want = mass * (sim.state()["body_velocity"] - f0) / sim.dt - mass * G
    scale = max(np.abs(want).max(), float(mass.max()) * 9.81)
    np.testing.assert_allclose(reported_forces(first, 3), want, rtol=0, atol=TOLERANCE["float64"] * scale)

    other = polydem.Simulation(scene, device)
    sim.step(6)
    other.step(6)
    other.step(1)
    snap = other.snapshot()
    other.forget_diagnostics()  # the last step's report stays as it ran
    got, want_c = other.contacts(), sim.contacts()
    for k in want_c:
        np.testing.assert_array_equal(got[k], want_c[k], err_msg=k)
    third = polydem.Simulation(scene, device)
    third.advance(7)  # the stepping of a decomposed run: its last step keeps copies of its inputs
    got = third.contacts()
    for k in want_c:
        np.testing.assert_array_equal(got[k], want_c[k], err_msg=k)

    other.step(4)
    other.restore(snap)  # no last step now: the next step's forces, at the restored state
    upcoming = other.contacts()
    other.step(1)
    for k in upcoming:
        np.testing.assert_array_equal(other.contacts()[k], upcoming[k], err_msg=k)


def test_average_of_a_resting_cube_is_its_weight(device):
    scene = steel_scene()
    scene.add_body("cube", "steel", position=(0.0, 0.0, 0.05))
    scene.add_plane(point=(0, 0, 0), normal=(0, 0, 1), material="steel")
    sim = polydem.Simulation(scene, device)
    sim.step(300)  # settles onto the plane
    weight = float(scene.body_mass()[0]) * 9.81
    sim.start_contact_average()
    sim.step(200)
    a = sim.contact_average()
    assert a["steps"] == 200 and a["end_time"] - a["start_time"] == pytest.approx(200 * sim.dt)
    assert a["body_a"].tolist() == [0] and a["body_b"].tolist() == [-1]
    np.testing.assert_allclose(a["force"][0], [0.0, 0.0, weight], rtol=0, atol=1e-6 * weight)
    assert a["normal_force"][0] == pytest.approx(weight, rel=1e-6)
    np.testing.assert_allclose(a["normal"][0], [0.0, 0.0, -1.0], atol=1e-9)
    assert a["contact_time"][0] == pytest.approx(200 * sim.dt)
    assert abs(a["point"][0, 2]) < 1e-4  # on the plane, below the centre
    np.testing.assert_allclose(a["point"][0, :2], [0.0, 0.0], atol=1e-9)


@pytest.mark.parametrize("precision", ["float64", "mixed"])
def test_average_of_a_bounce_is_the_momentum_change_over_the_interval(device, precision):
    """A cube dropped onto the plane bounces off inside the interval: its contact lasted part of the
    interval and counts over the whole of it (impulse / interval). The resting cube beside it too."""
    scene = steel_scene(precision)
    scene.add_body("cube", "steel", position=(0.0, 0.0, 0.0502), velocity=(0.3, 0.0, -1.0), angular_velocity=(0, 3, 0))
    scene.add_body("cube", "steel", position=(0.4, 0.0, 0.05))
    scene.add_plane(point=(0, 0, 0), normal=(0, 0, 1), material="steel")
    sim = polydem.Simulation(scene, device)
    mass = scene.body_mass()[:, None]
    v0 = sim.state()["body_velocity"]
    sim.start_contact_average()
    sim.step(400)
    a = sim.contact_average()
    period = a["end_time"] - a["start_time"]
    want = mass * (sim.state()["body_velocity"] - v0) / period - mass * G
    got = forces_per_body(a["body_a"], a["body_b"], a["force"], 2)
    print(f"\n{precision}: mean forces {got.tolist()}, momentum change / T {want.tolist()}")
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())
    bounce = a["body_a"] == 0
    assert sim.state()["body_velocity"][0, 2] > 0.2 and 0 not in sim.contacts()["body_a"]  # it bounced and left
    assert 0.0 < a["contact_time"][bounce][0] < 0.5 * period  # the contact lasted part of the interval
    assert a["force"][bounce][0, 2] > 10 * float(mass[0, 0]) * 9.81
    assert a["tangential_force"][bounce][0, 0] < 0.0  # friction against the sliding
    np.testing.assert_allclose(a["force"] - a["tangential_force"], -a["normal"] * np.linalg.norm(
        a["force"] - a["tangential_force"], axis=1, keepdims=True), atol=1e-9 * np.abs(a["force"]).max())  # fmt: skip


def head_on_scene(pairs=1):
    """``pairs`` pairs of cubes flying at each other in zero gravity (with a sideways slip): each
    pair meets and flies apart. The pair list keeps a pair until the bounding spheres are a skin
    apart (0.07 m more for cubes that met face to face): soft cubes, whose time step is long, get
    there in a few hundred steps."""
    scene = polydem.Scene(gravity=(0.0, 0.0, 0.0), dt="auto", precision="float64")
    scene.add_material("soft", density=1000, law="hertz", k=1e7, restitution=0.5, friction=0.3)
    scene.add_shape("cube", polydem.ConvexShape.box(0.1))
    for k in range(pairs):
        y = 0.5 * k
        scene.add_body("cube", "soft", position=(-0.0501, y, 0.0), velocity=(2.0, 0.2, 0.0))
        scene.add_body("cube", "soft", position=(0.0501, y + 0.01, 0.0), velocity=(-2.0, 0.0, 0.0))
    return scene


def test_average_counts_contacts_that_left_the_pair_list(device):
    """Two cubes meet and fly apart further than the skin: a rebuild drops their pair from the list,
    and its sums still count (the retired list)."""
    scene = head_on_scene()
    sim = polydem.Simulation(scene, device, skin=1e-3)
    mass = scene.body_mass()[:, None]
    v0 = sim.state()["body_velocity"]
    sim.start_contact_average()
    sim.step(500)
    assert sim.current_contacts.count() == 0  # the pair left the list
    a = sim.contact_average()
    assert a["body_a"].tolist() == [0] and a["body_b"].tolist() == [1]
    period = a["end_time"] - a["start_time"]
    want = mass * (sim.state()["body_velocity"] - v0) / period
    got = forces_per_body(a["body_a"], a["body_b"], a["force"], 2)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9 * np.abs(want).max())
    assert got[0, 0] < 0.0 < got[1, 0] and abs(a["tangential_force"][0, 1]) > 0.0  # pushed apart, with friction


def test_average_is_kept_through_a_redone_chunk(device):
    """A chunk redone (from the snapshot at its start, with the sums) after more pairs ended in it than
    the retired list holds gives the averages of a run that redid nothing, bit for bit. (A chunk is
    redone the same way after a clipped polygon or the pair list overflowed.)"""

    def run(cramped):
        sim = polydem.Simulation(head_on_scene(pairs=2), device, skin=1e-3)
        sim.start_contact_average()
        if cramped:
            sim._average._allocate_retired(1)  # the two pairs end at one rebuild: no room for both
        sim.step(500)
        return sim, sim.contact_average()

    (ref, want), (sim, got) = run(False), run(True)
    assert len(sim._average.retired_key) > 1  # the list grew: the chunk was redone
    assert ref.current_contacts.count() == 0 and len(want["body_a"]) == 2
    for k in want:
        np.testing.assert_array_equal(got[k], want[k], err_msg=k)


def test_restore_brings_the_average_back(device):
    scene = impact_scene()
    sim = polydem.Simulation(scene, device)
    before = sim.snapshot()
    sim.start_contact_average()
    sim.step(20)
    snap = sim.snapshot()
    at_snap = sim.contact_average()
    sim.step(20)
    at_end = sim.contact_average()
    sim.restore(snap)  # the same interval: its sums at that step
    for k, v in at_snap.items():
        np.testing.assert_array_equal(sim.contact_average()[k], v, err_msg=k)
    sim.step(20)
    for k, v in at_end.items():
        np.testing.assert_array_equal(sim.contact_average()[k], v, err_msg=k)
    sim.restore(before)  # taken before the interval: it starts again there
    assert sim.contact_average_steps == 0
    sim.step(20)
    for k, v in at_snap.items():
        np.testing.assert_array_equal(sim.contact_average()[k], v, err_msg=k)
    assert sim.stop_contact_average()["steps"] == 20 and sim.contact_average_steps is None


def test_average_errors(device):
    sim = polydem.Simulation(impact_scene(), device)
    with pytest.raises(RuntimeError, match="start_contact_average"):
        sim.contact_average()
    sim.start_contact_average()
    with pytest.raises(ValueError, match="no step yet"):
        sim.contact_average()
    assert sim.stop_contact_average() is None


def test_vtk_contact_network_carries_the_average(tmp_path, device):
    meshio = pytest.importorskip("meshio")
    from polydem.vtk import VtkWriter

    scene = steel_scene()
    scene.add_body("cube", "steel", position=(0.0, 0.0, 0.0502), velocity=(0.3, 0.0, -1.0), angular_velocity=(0, 3, 0))
    scene.add_body("cube", "steel", position=(0.4, 0.0, 0.0499))
    scene.add_plane(point=(0, 0, 0), normal=(0, 0, 1), material="steel")
    sim = polydem.Simulation(scene, device)
    frames = []
    with VtkWriter(tmp_path / "vtk", sim) as writer:
        for _ in range(3):  # as polydem run: the average over the interval before each frame
            average = sim.contact_average() if sim.contact_average_steps else {}
            writer.record(sim.time, sim.state(), sim.contacts(), average=average)
            frames.append((sim.contacts(), average))
            sim.start_contact_average()
            sim.step(100)
    ended = 0
    for k, (c, average) in enumerate(frames):
        mesh = meshio.read(tmp_path / "vtk" / "contacts" / f"contacts_{k:06d}.vtu")
        cd = {key: np.concatenate(v) for key, v in mesh.cell_data.items()}
        m = len(c["volume"])
        current = cd["current"] == 1
        assert current[:m].all() and not current[m:].any()
        np.testing.assert_array_equal(cd["normal_force_magnitude"][:m], np.float32(c["normal_force"]))
        key_b = np.where(cd["wall"] >= 0, -1 - cd["wall"], cd["body_b"])
        rows = {(int(i), int(j)): r for r, (i, j) in enumerate(zip(cd["body_a"], key_b, strict=True))}
        assert len(rows) == len(cd["body_a"])
        for i, (a, b) in enumerate(zip(average.get("body_a", []), average.get("body_b", []), strict=True)):
            r = rows[(int(a), int(b))]
            np.testing.assert_array_equal(cd["mean_force"][r], np.float32(average["force"][i]))
            np.testing.assert_array_equal(cd["mean_tangential_force"][r], np.float32(average["tangential_force"][i]))
            assert cd["mean_normal_force_magnitude"][r] == np.float32(average["normal_force"][i])
            assert cd["contact_time"][r] == np.float32(average["contact_time"][i])
            if not current[r]:  # ended in the interval: no instantaneous force, its line ends at its mean point
                ended += 1
                assert cd["normal_force_magnitude"][r] == 0.0
                np.testing.assert_allclose(mesh.points[2 * r + 1], average["point"][i], atol=1e-6)
        extra = len(cd["body_a"]) - m
        assert extra == int(np.sum(~current))
        np.testing.assert_array_equal(
            mesh.point_data["mean_normal_force_magnitude"][mesh.cells[0].data][:, 0], cd["mean_normal_force_magnitude"]
        )
    assert ended >= 1  # the bounce ended between two frames


RUN_SCENE = """\
[simulation]
name = "average_run"
dt = "auto"
steps = 300

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
position = [0.0, 0.0, 0.05]

[[bodies]]
shape = "cube"
material = "steel"
position = [0.4, 0.0, 0.0502]
velocity = [0.0, 0.0, -1.0]

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "steel"

[output]
fps = 10000
usd = false
pictures = false
vtk = true
"""


def test_run_summary_and_vtk_carry_the_average(tmp_path, capsys):
    pytest.importorskip("meshio")
    from cli_helpers import run, write_scene

    from polydem.vtk import read_pvd

    scene = write_scene(tmp_path, RUN_SCENE)
    code, _, err = run(["run", scene, "--device", "cpu", "--out", tmp_path / "out", "-q"], capsys)
    assert code == 0, err
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    s = summary["contact_average"]
    dt = summary["dt"]
    assert s["steps"] > 0 and s["to_time"] == pytest.approx(summary["simulated_time"])
    assert s["to_time"] - s["from_time"] == pytest.approx(s["steps"] * dt)
    assert s["largest"]["wall"] == 0 and len(s["walls"]) == 1
    # The last frame is at the last step: its contacts file carries the same averages.
    import meshio

    last = read_pvd(tmp_path / "out" / "vtk" / "contacts.pvd")[-1][1]
    cd = {key: np.concatenate(v) for key, v in meshio.read(last).cell_data.items()}
    assert s["contacts"] == np.count_nonzero(cd["contact_time"] > 0) >= 1
    assert s["mean_normal_force"] == pytest.approx(cd["mean_normal_force_magnitude"][cd["contact_time"] > 0].mean())
    on_wall = cd["wall"] == 0
    np.testing.assert_allclose(s["walls"][0]["force"], -cd["mean_force"][on_wall].sum(axis=0), rtol=1e-6)
    assert s["walls"][0]["force"][2] < 0.0  # the cubes push the floor down

    # Without VTK output nothing is averaged (the steps keep the plain kernels).
    scene = write_scene(tmp_path, RUN_SCENE.replace("vtk = true", "vtk = false"), name="plain.toml")
    code, _, err = run(["run", scene, "--device", "cpu", "--out", tmp_path / "plain", "-q"], capsys)
    assert code == 0, err
    assert json.loads((tmp_path / "plain" / "summary.json").read_text())["contact_average"] is None
