"""The damping load of a body (kernels/forces.py ``damping_load_kernel``) and what it bounds.

Each contact's tangential dashpot is taken explicitly. A grain held by many contacts at a long step
met dashpots whose sum changed the velocity at its rim by more than that velocity in one step: it rang
at the step's period and never came to rest (a settle pile of 1000 cubes at 4 dt_rec, CPU: 98 grains
at 3.7e-4 m/s from 0.7 s to 1.5 s, their angular velocity flipping sign every step; with the dashpots
off they stopped at once). Each step now sums, per body, dt (1/m + r^2 / I_min) times its contacts'
dashpots (its damping load), and the next step scales a contact's dashpot by DAMPING_SHARE over the
larger load of its two bodies where that exceeds DAMPING_SHARE.
"""

import math
from pathlib import Path

import numpy as np
import pytest
from benchmark_scripts import load_benchmark
from polydem.kernels.response import DAMPING_SHARE

from polydem import ConvexShape, Scene, SettleCriterion, Simulation
from polydem.checkpoint import load_checkpoint, save_checkpoint


def _benchmark_settle():
    return load_benchmark("settle")


def pile(n, dt_scale, friction=0.5):
    """benchmarks/settle.py's pour of ``n`` cubes (section 7's k, the volume rule) at ``dt_scale`` x dt_rec."""
    settle = _benchmark_settle()
    options = settle.scene_options(precision="mixed", k_rule="volume", friction=friction)
    scene, _ = settle.make_scene(n, options, seed=0)
    scene.dt = dt_scale * scene.time_step().recommended
    return scene


def dashpot(kt, e, inv_mass):
    # kernels/response.py dashpot, in float64
    ln_e = math.log(max(e, 1e-6))
    zeta = -ln_e / math.sqrt(ln_e * ln_e + math.pi**2)
    return 2.0 * zeta * math.sqrt(kt / inv_mass)


def loads_from_contacts(sim):
    """Each body's damping load from Simulation.contacts() (the contacts of the last step) and the model."""
    m = sim.model
    c = sim.contacts()
    inv_mass = m.body_inv_mass.numpy().astype(np.float64)
    inertia = m.body_inertia.numpy().astype(np.float64)
    radius = m.body_radius.numpy().astype(np.float64)
    material = m.body_material.numpy()
    count = int(round(math.sqrt(len(m.material_kt.numpy()))))
    kt = m.material_kt.numpy().astype(np.float64).reshape(count, count)
    e = m.material_e.numpy().astype(np.float64).reshape(count, count)
    wall_material = m.wall_material.numpy()
    total = np.zeros(m.num_bodies)
    mu = m.material_mu.numpy().astype(np.float64).reshape(count, count)
    for a, b in zip(c["body_a"], c["body_b"], strict=True):
        if b >= 0:
            ma, mb = material[a], material[b]
            ct = dashpot(kt[ma, mb], e[ma, mb], inv_mass[a] + inv_mass[b]) if mu[ma, mb] > 0.0 else 0.0
            total[a] += ct
            total[b] += ct
        else:
            ma, mw = material[a], wall_material[-1 - b]
            total[a] += dashpot(kt[ma, mw], e[ma, mw], inv_mass[a]) if mu[ma, mw] > 0.0 else 0.0
    reach = inv_mass + 1.25 * radius**2 / inertia.min(axis=1)
    free = m.body_flags.numpy() == 0
    return np.where(free, sim.dt * reach * total, 0.0)


def mesh_floor_scene():
    """Three 2 cm cubes sliding on a jittered mesh floor of 288 triangles (hertz, friction 0.5, e = 0.5)."""
    from test_meshwall import floor_grid

    scene = Scene(gravity=(0.0, 0.0, -9.81), dt="auto", precision="mixed")
    scene.add_material("m", density=2500.0, k=1.0e8, restitution=0.5, friction=0.5, law="hertz")
    scene.add_shape("cube", ConvexShape.box(0.02))
    scene.add_mesh_wall(floor_grid(12, size=0.3, jitter=0.3), "m")
    for k, x in enumerate((0.0, 0.03, 0.07)):
        scene.add_body("cube", "m", position=(x, 0.003 * k, 0.01 - 1e-6), velocity=(0.05, 0.02, 0.0))
    return scene


@pytest.mark.parametrize("scene_name", ["pile", "cube_drop", "mesh_floor"])
def test_the_damping_load_is_the_sum_of_the_contacts_dashpots(device, scene_name, tmp_path):
    """The loads the step writes, against a float64 sum over Simulation.contacts() of the same step: pairs
    (the pile, in a box of fixed slabs), plane walls (cube_drop.toml's cube put on its floor, sliding) and a
    mesh wall (whose contacts come after the gather: the load kernel of its own)."""
    if scene_name == "pile":
        scene = pile(64, 4.0)
        steps = 2500
    elif scene_name == "mesh_floor":
        scene = mesh_floor_scene()
        steps = 300
    else:
        text = (Path(__file__).resolve().parents[1] / "scenes" / "cube_drop.toml").read_text()
        text = text.replace("position = [0.0, 0.0, 0.2]", "position = [0.0, 0.0, 0.04999999995]")
        text = text.replace("velocity = [0.0, 0.0, 0.0]", "velocity = [0.05, 0.0, 0.0]")
        (tmp_path / "on_floor.toml").write_text(text)
        scene = Scene.from_toml(tmp_path / "on_floor.toml")
        steps = 300
    sim = Simulation(scene, device=device)
    assert sim.stepper.loads_in_gather == (scene_name != "mesh_floor")
    sim.step(steps)
    want = loads_from_contacts(sim)
    got = sim.current_state.body_damping.numpy().astype(np.float64)
    assert np.count_nonzero(want) > 0
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=0.0)
    if scene_name == "pile":
        assert got.max() > DAMPING_SHARE  # the scale acts in this pile


@pytest.mark.parametrize("average", [False, True])
def test_the_gather_writes_the_load_kernels_bits(device, average):
    """Without mesh walls the gather writes the loads (one launch fewer): the same bits as the load kernel on
    the same contact history, also while contacts are averaged (the report variant steps)."""
    sim = Simulation(pile(64, 4.0), device=device)
    assert sim.stepper.loads_in_gather
    if average:
        sim.start_contact_average()
    sim.step(2000)
    state = sim.current_state
    got = state.body_damping.numpy().copy()
    assert got.max() > DAMPING_SHARE
    state.body_damping.zero_()
    sim.stepper.damping_load(state, sim.current_contacts, sim.dt)
    np.testing.assert_array_equal(state.body_damping.numpy(), got)


def test_a_pile_comes_to_rest_at_four_recommended_steps(device):
    """200 cubes at 4 dt_rec settle by the default criterion (every grain below 3e-4 sqrt(g r_min)) within 1 s
    (measured on the CPU: at 0.527 s). Without the scale: not settled at 1.5 s, 11 grains ringing at up to
    2.6e-4 m/s."""
    sim = Simulation(pile(200, 4.0), device=device)
    result = sim.run_until_settled(1.0, SettleCriterion())
    assert result.settled, result


def test_a_checkpoint_resumes_the_loads_bit_for_bit(device, tmp_path):
    """A checkpoint does not keep the loads: loading one computes them again from the contact history, the
    same bits as the unbroken run's, and the run goes on bit for bit."""
    scene = pile(64, 4.0)
    a = Simulation(scene, device=device)
    a.step(1500)
    path = tmp_path / "ck.npz"
    save_checkpoint(a, path)
    b = Simulation(scene, device=device)
    load_checkpoint(b, path)
    np.testing.assert_array_equal(b.current_state.body_damping.numpy(), a.current_state.body_damping.numpy())
    assert a.current_state.body_damping.numpy().max() > DAMPING_SHARE
    a.step(300)
    b.step(300)
    for k in ("body_q", "body_v", "body_w", "body_damping"):
        np.testing.assert_array_equal(getattr(b.current_state, k).numpy(), getattr(a.current_state, k).numpy(), k)


def test_no_friction_no_load(device):
    """Without friction there is no dashpot: the loads stay 0."""
    sim = Simulation(pile(27, 4.0, friction=0.0), device=device)
    sim.step(800)
    assert not sim.model.friction
    assert len(sim.contacts()["body_a"]) > 0
    assert not np.any(sim.current_state.body_damping.numpy())


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_the_material_tables_damping_factor_gives_the_dashpots_bits(device, precision):
    """The gather and the wall contacts take each dashpot's factor of e from the material table (kernels/response.py
    make_damping, filled where the model is built): factor x sqrt(kt / (1/m)) is the same bits as the pair kernel's
    dashpot(kt, e, 1/m) and as the expression both were written as before the table, on this device's compiler."""
    import warp as wp
    from polydem.kernels.response import fill_damping_factors, make_response

    scalar = wp.float32 if precision == "float32" else wp.float64
    resp = make_response(scalar, "hertz", True)

    @wp.kernel(enable_backward=False, module="unique")
    def dashpots(
        e: wp.array(dtype=scalar),
        factor: wp.array(dtype=scalar),
        kt: wp.array(dtype=scalar),
        inv_mass: wp.array(dtype=scalar),
        out: wp.array2d(dtype=scalar),
    ):
        i = wp.tid()
        # the expression of kernels/response.py's dashpot before the table
        old = scalar(0.0)
        if inv_mass[i] > scalar(0.0):
            ln_e = wp.log(wp.max(e[i], scalar(1.0e-6)))
            zeta = -ln_e / wp.sqrt(ln_e * ln_e + scalar(9.8696044))
            old = scalar(2.0) * zeta * wp.sqrt(kt[i] / wp.max(inv_mass[i], scalar(1.0e-30)))
        out[i, 0] = old
        out[i, 1] = resp.dashpot(kt[i], e[i], inv_mass[i])
        out[i, 2] = resp.dashpot_factored(factor[i], kt[i], inv_mass[i])

    rng = np.random.default_rng(5)
    n = 4096
    dtype = np.float32 if precision == "float32" else np.float64
    e_np = np.concatenate([[0.0, 1e-9, 1e-6, 0.1, 0.5, 0.9, 1.0], rng.uniform(0.0, 1.0, n - 7)]).astype(dtype)
    kt_np = 10.0 ** rng.uniform(2.0, 9.0, n)
    im_np = np.where(np.arange(n) % 97 == 0, 0.0, 10.0 ** rng.uniform(-2.0, 6.0, n))
    e = wp.array(e_np, dtype=scalar, device=device)
    factor = wp.empty_like(e)
    fill_damping_factors(e, factor)
    out = wp.zeros((n, 3), dtype=scalar, device=device)
    args = [e, factor, wp.array(kt_np.astype(dtype), dtype=scalar, device=device)]
    inv_mass = wp.array(im_np.astype(dtype), dtype=scalar, device=device)
    wp.launch(dashpots, dim=n, inputs=[*args, inv_mass, out], device=device)
    got = out.numpy()
    assert (got[:, 0] > 0).sum() > n // 2
    np.testing.assert_array_equal(got[:, 1], got[:, 0])
    np.testing.assert_array_equal(got[:, 2], got[:, 0])
