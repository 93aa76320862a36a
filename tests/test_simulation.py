"""Verification of polydem.Simulation: closed forms against the integrator, and physics checks.

Scenes are sized for Warp's single-threaded CPU backend (the file takes about 3 minutes there besides
the 512-body pour, 75 s on an idle core; 16 to 26 s of it the 10^5-step energy run). Units SI. Scenes
run in the default precision, "mixed" (float64 state, velocities and force sums; float32 contact
geometry), and the closed-form and conservation tests in "float64" and "float32" beside it, each held
to the unit roundoff of the state's scalar (UNIT_ROUNDOFF: 2^-53 for mixed and float64, 2^-24 for
float32). The integrator (kernels/integrate.py) is symplectic Euler for translation (v += dt a, then
x += dt v) with a Strang-split free-rotor drift for rotation.

Energy checks use the first-order *modified energy* of symplectic Euler. For the kick-then-drift
map the conserved quantity is, to O(dt^2),

    H~ = H + (dt / 2) * sum_free (v . F + w . tau)          (F includes gravity)

so H itself swings by O(dt) F.v inside every contact and comes back afterwards; H~ does not swing
(in free fall it is conserved exactly: H drifts by -m g^2 dt^2 / 2 per step, the correction by the
opposite amount). F and tau are the contact wrench of the last step (State.body_f, State.body_t),
evaluated one step earlier than v, which changes H~ only at O(dt^2).
"""

import math
import re

import numpy as np
import pytest

import polydem
from polydem import ConvexShape, Scene, SceneError, Simulation, SimulationError
from polydem.scene import quat_from_axis_angle, quat_to_matrix

G = 9.81
# Unit roundoff of the body state (positions, velocities, per-body force sums) in each precision.
UNIT_ROUNDOFF = {"float32": 2.0**-24, "mixed": 2.0**-53, "float64": 2.0**-53}


# ---------------------------------------------------------------------------------------------
# Helpers


def single_material_scene(gravity=(0.0, 0.0, -G), dt="auto", precision="mixed", **material):
    props = dict(density=1000.0, law="hertz", k=1.0e9, restitution=1.0, friction=0.0)
    props.update(material)
    if props.get("m") is None:
        props.pop("m", None)
    scene = Scene(gravity=gravity, dt=dt, precision=precision)
    scene.add_material("m", **props)
    return scene


def modified_energy(sim, energy=None):
    """H~ = total energy (including the dissipated part) + dt/2 sum(v.F + w.tau), see the module docstring."""
    e = sim.energy() if energy is None else energy
    m = sim.model
    free = m.body_flags_np == 0
    mass = m.body_mass[free].astype(np.float64)
    st = sim.current_state
    v = st.body_v.numpy()[free].astype(np.float64)
    w = st.body_w.numpy()[free].astype(np.float64)
    f = st.body_f.numpy()[free].astype(np.float64) + mass[:, None] * np.asarray(m.gravity, dtype=np.float64)
    tau = st.body_t.numpy()[free].astype(np.float64)
    return e["total"] + 0.5 * sim.dt * (np.sum(f * v) + np.sum(tau * w))


def contact_volume(sim):
    """Total overlap volume of the current contacts [m^3]."""
    return float(np.sum(sim.contacts()["volume"]))


def body_rotation(shape, orientation):
    """World rotation of the body (principal) frame for a shape placed with `orientation` (xyzw)."""
    return quat_to_matrix(orientation) @ shape.input_rotation


def angular_momentum(scene, state):
    """Total angular momentum about the origin, sum x cross m v + R I R^T w [kg m^2/s] (float64)."""
    mass = scene.body_mass()
    inertia = scene.body_inertia()
    rot = quat_to_matrix(state["body_orientation"])
    w_body = np.einsum("nji,nj->ni", rot, state["body_angular_velocity"])
    spin = np.einsum("nij,nj->ni", rot, inertia * w_body)
    orbit = np.cross(state["body_position"], mass[:, None] * state["body_velocity"])
    return (orbit + spin).sum(axis=0)


# ---------------------------------------------------------------------------------------------
# 1. Free fall and projectile: the closed form of symplectic Euler


@pytest.mark.parametrize("precision", ["mixed", "float64", "float32"])
def test_free_fall_and_projectile_closed_form(device, precision):
    # A large step (2 ms; the soft material's stable limit is seconds) makes the closed form's
    # first-order term g t dt / 2 large against float32 rounding of the position.
    scene = single_material_scene(dt=2.0e-3, k=1.0e3, precision=precision)
    cube = scene.add_shape("cube", ConvexShape.box(0.1))
    x0 = np.array([[0.0, 0.0, 1.0], [0.5, -0.2, 0.5]])
    v0 = np.array([[0.0, 0.0, 0.0], [1.5, -0.7, 4.0]])
    scene.add_body(cube, "m", position=x0[0])
    scene.add_body(cube, "m", position=x0[1], velocity=v0[1], angular_velocity=(2.0, -1.0, 3.0))
    sim = Simulation(scene, device)
    steps = 500
    sim.step(steps)
    st = sim.state()

    eps = UNIT_ROUNDOFF[precision]
    dt = float(np.float32(sim.dt)) if precision == "float32" else sim.dt  # the dt of the integrator's scalar
    t = steps * dt
    g = np.array([0.0, 0.0, -G])
    x_exact = x0 + v0 * t + 0.5 * g * t * t + 0.5 * g * t * dt
    v_exact = v0 + g * t
    # Worst case, every one of the `steps` additions x += dt v and v += dt g rounds by half an ulp of
    # its result, the same way (errors add up linearly, and the velocity error is carried into x for
    # the remaining time): steps * eps * (max|x| + t max|v|) and steps * eps * max|v|. In float64
    # (mixed, float64) that is 1e-12 m; gravity 1e-4 off moves the bodies 4.9e-4 m.
    vmax = np.abs(v0).max() + G * t
    tol_x = steps * eps * (np.abs(x_exact).max() + np.abs(x0).max() + t * vmax)
    tol_v = steps * eps * vmax
    err_x = np.abs(st["body_position"] - x_exact).max()
    err_v = np.abs(st["body_velocity"] - v_exact).max()
    print(f"\nfree fall: t = {t:.4f} s, |x - exact| = {err_x:.2e} m (tol {tol_x:.1e}), |v - exact| = {err_v:.2e}")
    assert err_x <= tol_x
    assert err_v <= tol_v
    # The closed form differs from the exact parabola by g t dt / 2; make sure the test resolves it.
    assert 0.5 * G * t * dt > 10 * tol_x
    # No contact ever happened: the spin of the projectile is untouched (a cube is isotropic, so its
    # angular velocity is constant in the torque-free case; rounding of the drift only, at most one
    # unit of |w| per step).
    np.testing.assert_allclose(st["body_angular_velocity"][1], [2.0, -1.0, 3.0], rtol=0, atol=steps * eps * 4.0)
    assert np.all(st["body_angular_velocity"][0] == 0.0)


# ---------------------------------------------------------------------------------------------
# 2. Restitution and the energy of a corner impact


@pytest.mark.parametrize("e", [0.3, 0.6, 0.9])
def test_restitution_face_down_cube(device, e):
    """A cube lands flat on a plane (hertz, no friction) and leaves with e times its impact speed.

    The cube starts 0.5 mm above the plane with the speed of a 5 cm drop (1 m/s), under gravity.
    Impact speed: the velocity at the first state with an overlap (no contact force has acted on
    it yet); rebound speed: at the first state without overlap afterwards.
    """
    impact = 1.0
    probe = single_material_scene(restitution=e)
    probe.add_shape("cube", ConvexShape.box(0.1))
    probe.add_body("cube", "m", position=(0.0, 0.0, 0.0505), velocity=(0.0, 0.0, -impact))
    probe.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    # Time step: a quarter of the recommended one, where the bound can be tight. This impact only
    # reaches 0.08 mm (0.08% of the size) and its face contact, in the hertz law's resolved toe,
    # lasts 45 to 70 steps at dt = "auto" (test_restitution_at_the_default_step holds that to 1.5%:
    # measured +0.39%, +0.61%, +0.41% for e = 0.3, 0.6, 0.9; 1.4% was seen at an earlier auto step).
    # Measured at a quarter step: -0.04%, +0.08%, +0.09%.
    dt = Simulation(probe, device).model.dt_recommended / 4
    scene = single_material_scene(dt=dt, restitution=e)
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("cube", "m", position=(0.0, 0.0, 0.0505), velocity=(0.0, 0.0, -impact))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    sim = Simulation(scene, device)

    v_in = v_out = None
    max_volume = 0.0
    for _ in range(20000):
        sim.step(1)
        volume = contact_volume(sim)
        vz = sim.state()["body_velocity"][0, 2]
        if v_in is None and volume > 0.0:
            v_in = vz
        if v_in is not None:
            max_volume = max(max_volume, volume)
            if volume == 0.0:
                v_out = vz
                break
    assert v_in is not None and v_out is not None, "the cube never hit or never left the plane"
    # Gravity works against the rebound while the cube is in the plane: with the deepest overlap
    # d (volume / face area), loading stores m v_in^2 / 2 + m g d, unloading returns e^2 of it,
    # so v_out^2 = e^2 v_in^2 - 2 g d (1 - e^2) (a 0.8% correction for e = 0.3).
    depth = max_volume / 0.01
    e_expected = math.sqrt(e * e - 2.0 * G * depth * (1.0 - e * e) / (v_in * v_in))
    e_measured = -v_out / v_in
    print(f"\nrestitution e = {e}: v_in = {v_in:.4f}, v_out = {v_out:.4f}, measured {e_measured:.4f}, "
          f"expected {e_expected:.4f} ({100 * (e_measured / e_expected - 1):+.2f}%)")  # fmt: skip
    assert v_in < -0.99 * impact  # the cube did land with the intended speed
    # Measured within 0.4% at this step; the issue asked for 5%, 1% catches a restitution 1% off.
    assert abs(e_measured / e_expected - 1.0) < 0.01


def vertex_down_orientation():
    """Rotation taking the cube diagonal (1, 1, 1) to -z: a vertex points down."""
    a = np.array([1.0, 1.0, 1.0]) / math.sqrt(3.0)
    b = np.array([0.0, 0.0, -1.0])
    axis = np.cross(a, b)
    return quat_from_axis_angle(axis, math.acos(float(a @ b)))


def feature_down(feature, edge=0.1):
    """(orientation, height of the centre over the lowest point) of a cube with a face, an edge (along
    x) or a corner pointing straight down: the contact force then passes through the centre."""
    if feature == "face":
        return np.array([0.0, 0.0, 0.0, 1.0]), 0.5 * edge
    if feature == "edge":
        return quat_from_axis_angle((1.0, 0.0, 0.0), 0.25 * math.pi), 0.5 * edge * math.sqrt(2.0)
    return vertex_down_orientation(), 0.5 * edge * math.sqrt(3.0)


# Bounds of |measured / expected - 1| at dt = "auto". Measured at 1 m/s (mixed and float64 alike):
# corner -0.02% (e 0.6), -0.01% (0.9); edge -0.01%, -0.02%, -0.01% (0.3, 0.6, 0.9); face +0.39%, +0.61%,
# +0.41%, and up to +1.2% at 0.3 m/s. The face is the hardest to resolve: its hertz contact sits in the
# resolved toe, 0.08 mm deep, and lasts 45 to 70 steps (a corner, 1 cm deep, some 5000); a face
# contact 1.4% off has been seen, so the face keeps 1.5% here and 1% at a quarter step
# (test_restitution_face_down_cube).
RESTITUTION_BOUND = {"corner": 0.01, "edge": 0.01, "face": 0.015}


@pytest.mark.parametrize(
    "feature, e, precision",
    [(f, e, "mixed") for f, e in [("corner", 0.6), ("corner", 0.9), ("edge", 0.3), ("edge", 0.6), ("edge", 0.9)]]
    + [("face", 0.3, "mixed"), ("face", 0.9, "mixed")]
    + [("corner", 0.9, "float64"), ("edge", 0.6, "float64"), ("face", 0.9, "float64")],
)
def test_restitution_at_the_default_step(device, feature, e, precision):
    """A cube lands on a plane corner, edge or face first (hertz, the law of the shipped scenes; no
    friction; gravity) at 1 m/s and dt = "auto", and leaves with e times its impact speed, less what
    gravity takes back over the deepest penetration d: v_out^2 = e^2 v_in^2 - 2 g d (1 - e^2) (loading
    stores m v_in^2 / 2 + m g d, unloading returns e^2 of it, and the cube climbs d). A corner at e = 0.3
    sinks 1 cm and cannot climb out against gravity, so corners start at e = 0.6."""
    impact = 1.0
    scene = single_material_scene(restitution=e, precision=precision)
    scene.add_shape("cube", ConvexShape.box(0.1))
    q, height = feature_down(feature)
    scene.add_body("cube", "m", position=(0.0, 0.0, height + 5e-4), orientation=q, velocity=(0.0, 0.0, -impact))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    sim = Simulation(scene, device)
    assert scene.dt == "auto"
    v_in = v_out = None
    deepest = 0.0
    for _ in range(20000):
        sim.step(1)
        c = sim.contacts()
        vz = sim.state()["body_velocity"][0, 2]
        touching = len(c["volume"]) > 0 and float(c["volume"].sum()) > 0.0
        if v_in is None and touching:
            v_in = vz
        if v_in is not None:
            if not touching:
                v_out = vz
                break
            deepest = max(deepest, float(c["depth"].max()))
    assert v_in is not None and v_out is not None, "the cube never hit or never left the plane"
    e_expected = math.sqrt(e * e - 2.0 * G * deepest * (1.0 - e * e) / (v_in * v_in))
    e_measured = -v_out / v_in
    spin = float(np.abs(sim.state()["body_angular_velocity"][0]).max())
    print(f"\n{feature} down, e = {e}, {precision}, dt {sim.dt:.3g} s: v_in {v_in:.4f}, v_out {v_out:.4f}, "
          f"depth {deepest:.3g} m; measured {e_measured:.4f}, expected {e_expected:.4f} "
          f"({100 * (e_measured / e_expected - 1):+.2f}%), spin {spin:.1e} rad/s")  # fmt: skip
    assert v_in < -0.99 * impact
    # The force passed through the centre: a straight bounce, no spin (rounding of the float32 geometry).
    assert spin < 1e-5
    assert abs(e_measured / e_expected - 1.0) < RESTITUTION_BOUND[feature]


@pytest.mark.parametrize("e", [1.0, 0.5])
def test_corner_impact_gains_no_energy(device, e):
    """A cube falling corner-first tips over and bounces on edges and faces without gaining energy."""
    scene = single_material_scene(restitution=e)
    scene.add_shape("cube", ConvexShape.box(0.1))
    q = vertex_down_orientation()
    height = 0.05 * math.sqrt(3.0)  # centre to vertex
    v_impact = 1.0
    scene.add_body(
        "cube", "m", position=(0.0, 0.0, height + 0.002), orientation=q, velocity=(0.0, 0.0, -v_impact),
        angular_velocity=(3.0, 1.0, 0.0),
    )  # fmt: skip
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    sim = Simulation(scene, device)
    e0 = sim.energy()
    h0 = modified_energy(sim, e0)
    # Energy scale: what the first impact brings in (kinetic energy, 1 kg cube, plus the 2 mm fall).
    scale = 0.5 * v_impact**2 + G * 0.002
    steps = int(0.12 / sim.dt)
    every = 5
    raw_gain, mod_gain, mod_loss, in_contact = -np.inf, -np.inf, np.inf, 0
    for _ in range(steps // every):
        sim.step(every)
        en = sim.energy()
        raw_gain = max(raw_gain, en["total"] - e0["total"])
        dh = modified_energy(sim, en) - h0
        mod_gain = max(mod_gain, dh)
        mod_loss = min(mod_loss, dh)
        in_contact += en["contact"] > 0.0
    st = sim.state()
    print(f"\ncorner drop e = {e}: max gain of total energy {raw_gain / scale:.2e}, of the modified energy "
          f"{mod_gain / scale:.2e} (min {mod_loss / scale:.2e}) of the impact energy; dissipated "
          f"{en['dissipated'] / scale:.3f}; {in_contact} of {steps // every} samples in contact")  # fmt: skip
    assert in_contact > 20  # the cube did hit the plane (and it turned: the vertex no longer points down)
    assert abs(st["body_orientation"][0] @ q) < 0.999
    # The modified energy is conserved to O(dt^2) in contact: measured gains <= 4e-5 of the impact
    # energy. 1e-3 leaves room, and still fails for an O(dt) error (the raw energy swings by 2.7e-3).
    assert mod_gain < 1e-3 * scale
    # The raw total energy swings by O(dt/2 F.v) inside a contact (measured 2.7e-3, up to 6e-3 in
    # longer runs); 2% of the impact energy bounds that swing, not a gain that stays.
    assert raw_gain < 2e-2 * scale
    if e == 1.0:
        # Nothing is lost either (same bound as the gain).
        assert mod_loss > -1e-3 * scale
        assert en["dissipated"] == 0.0
    else:
        # The loss is booked as dissipated, exactly (the contact energy is a function of the
        # overlap and the turning volume): the modified energy keeps within the elastic case's
        # bound (measured min -5.4e-5).
        assert en["dissipated"] > 0.5 * scale
        assert mod_loss > -1e-3 * scale


# ---------------------------------------------------------------------------------------------
# 3. Block on an incline (gravity tilted by theta; plane z = 0)

BLOCK = (0.2, 0.1, 0.05)  # along the slope, across, height [m]; 1 kg at 1000 kg/m^3
BLOCK_AREA = BLOCK[0] * BLOCK[1]
INCLINE_K = 1.0e10  # power law m = 2: a face contact is a linear spring of stiffness k A^2 = 4e6 N/m
# The friction tests run under two laws: the power law with m = 2 (force k V S, a linear spring k A^2
# for a face, resting 2.3 um deep here) and the hertz law of the shipped scenes, whose face contact
# rests in the resolved toe of the step (kernels/response.py toe_volume). Its k, 1e7, is softer than
# scenes/incline.toml's 1e9 so that dt = "auto" is the power law's 6.3e-5 s instead of the resting
# step of 4.4e-6 s (test_at_rest.py runs the shipped stiffness). Either block starts at rest at the
# equilibrium depth of its law: set down touching, an undamped (e = 1) hertz block would bounce on
# its contact forever, its normal force and friction cap falling to 0 at the top of every bounce.
FRICTION_LAWS = {"power": dict(law="power", m=2.0, k=INCLINE_K), "hertz": dict(law="hertz", k=1.0e7)}


def incline_scene(theta_deg, e, mu=0.5, law="power", precision="mixed", depth=None):
    """A 1 kg block at rest on a plane tilted by theta (gravity turned instead, so along-slope is x),
    ``depth`` into it (default: the depth at which its face carries it under the law and the step)."""
    th = math.radians(theta_deg)
    scene = single_material_scene(
        gravity=(G * math.sin(th), 0.0, -G * math.cos(th)), restitution=e, friction=mu, precision=precision,
        **FRICTION_LAWS[law],
    )  # fmt: skip
    scene.add_shape("block", ConvexShape.box(*BLOCK))
    if depth is None:
        from polydem.scene import depth as depth_model

        probe = incline_scene(theta_deg, e, mu, law, precision, depth=0.0)
        mat, mass = probe.materials["m"], float(probe.body_mass()[0])
        toe = depth_model.Toe(e, probe.time_step().toe_dt, 1.0 / mass)
        load = mass * G * math.cos(th)
        rest = depth_model.resting_contact(
            probe.shapes["block"], mat.law, mat.k, load, "face", m=mat.m, toe=toe, shallowest=True
        )
        depth = rest.depth
    scene.add_body("block", "m", position=(0.0, 0.0, 0.5 * BLOCK[2] - depth))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    return scene


def incline_run(device, theta_deg, mu, e, duration, law="power"):
    """Times, along-slope positions and velocities of a block on a plane tilted by theta, and the
    tangential stiffness of its contact."""
    sim = Simulation(incline_scene(theta_deg, e, mu, law), device)
    samples = 300
    every = max(1, int(duration / sim.dt) // samples)
    t, x, v = [], [], []
    for _ in range(samples):
        sim.step(every)
        st = sim.state()
        t.append(sim.time)
        x.append(st["body_position"][0, 0])
        v.append(st["body_velocity"][0, 0])
    kt = float(sim.model.material_kt.numpy()[0])
    return np.array(t), np.array(x), np.array(v), kt


@pytest.mark.parametrize("law", ["power", "hertz"])
@pytest.mark.parametrize("e", [1.0, 0.9, 0.3])
def test_incline_sticks_below_friction_angle(device, e, law):
    theta, mu = 20.0, 0.5  # tan(20 deg) = 0.36 < mu
    t, x, v, kt = incline_run(device, theta, mu, e, duration=0.3, law=law)
    fn = G * math.cos(math.radians(theta))
    creep = mu * fn / kt  # the longest the friction spring gets before it slips [m]
    late = t > 0.1
    print(f"\nincline {theta} deg, mu {mu}, e {e}, {law}: displacement {x[-1]:.3e} m, range after settling "
          f"{np.ptp(x[late]):.3e} m, creep bound mu Fn/kt {creep:.3e} m")  # fmt: skip
    # From rest with an unstretched spring, the load m g sin(theta) swings the spring to twice its
    # static stretch (2 x 5.7e-6 m), past the slip limit (7.8e-6 m): one small slip, after which it
    # oscillates within the limit. So: never more than 3 creep lengths overall (measured at the end
    # 2.6 for e = 1 under the power law, 1.9 under hertz), and after settling a spring that holds
    # moves the block by at most 2 creep lengths (+-limit).
    # A sliding block (a = 1.25 m/s^2 without friction's hold) would be 5e-2 m away.
    assert np.abs(x).max() < 3.0 * creep
    assert np.ptp(x[late]) < 2.0 * creep


@pytest.mark.parametrize("law", ["power", "hertz"])
@pytest.mark.parametrize("theta, e", [(35.0, 0.3), (45.0, 0.9)])
def test_incline_slides_above_friction_angle(device, theta, e, law):
    mu = 0.5
    t, x, v, _ = incline_run(device, theta, mu, e, duration=0.25, law=law)
    th = math.radians(theta)
    a_expected = G * (math.sin(th) - mu * math.cos(th))
    late = t > 0.05  # after the spring's transient (it loads to mu Fn within ~1 ms)
    a_fit = np.polyfit(t[late], v[late], 1)[0]
    print(f"\nincline {theta} deg, mu {mu}, e {e}, {law}: a = {a_fit:.4f} m/s^2, expected {a_expected:.4f} "
          f"({100 * (a_fit / a_expected - 1):+.3f}%)")  # fmt: skip
    # Measured within 0.001% under either law. The issue asked for 2%; 0.5% catches a friction cap 1%
    # high, which slows the block by 2.5% at 35 degrees and 1% at 45.
    assert abs(a_fit / a_expected - 1.0) < 0.005


# ---------------------------------------------------------------------------------------------
# 4. Torque-free brick


@pytest.mark.parametrize("precision", ["mixed", "float64", "float32"])
def test_torque_free_brick_conserves_energy_and_momentum(device, precision):
    """A 1 x 2 x 3 brick spun near its intermediate axis tumbles (flips) for 10^4 steps."""
    dt = 1.0e-3
    wdt = 0.03  # |w| dt, the docstring's test case
    scene = single_material_scene(gravity=(0.0, 0.0, 0.0), dt=dt, k=1.0e3, precision=precision)
    brick = scene.add_shape("brick", ConvexShape.box(1.0, 2.0, 3.0).scaled(0.1))
    q = np.array([0.1, 0.2, 0.3, 0.9])
    q /= np.linalg.norm(q)
    inertia = brick.inertia
    mid = int(np.argsort(inertia)[1])
    w_body = np.full(3, 0.05)
    w_body[mid] = 1.0
    w_body *= wdt / dt / np.linalg.norm(w_body)
    w0 = body_rotation(brick, q) @ w_body
    scene.add_body(brick, "m", position=(0.3, -0.2, 0.1), orientation=q, angular_velocity=w0)
    sim = Simulation(scene, device)
    l0 = angular_momentum(scene, sim.state())
    k0 = sim.energy()["kinetic"]
    dl, dk, flips, sign = [], [], 0, 1.0
    for _ in range(100):
        sim.step(100)
        st = sim.state()
        lt = angular_momentum(scene, st)
        dl.append(np.linalg.norm(lt - l0) / np.linalg.norm(l0))
        dk.append(sim.energy()["kinetic"] / k0 - 1.0)
        pi_mid = (quat_to_matrix(st["body_orientation"][0]).T @ lt)[mid]
        if np.sign(pi_mid) != sign:
            flips += 1
            sign = np.sign(pi_mid)
    dl, dk = np.array(dl), np.array(dk)
    print(f"\nbrick, {precision}: {sim.steps_done} steps, |w| dt = {wdt}: max |dL|/|L| = {dl.max():.2e}, "
          f"max |dK|/K = {np.abs(dk).max():.2e}, {flips} flips")  # fmt: skip
    assert sim.steps_done == 10_000
    assert flips >= 4  # it did tumble about the unstable axis
    # integrate.py: L is kept to rounding, an unbiased walk of ~4 eps per sqrt(step); the bound is four
    # times that walk after 10^4 steps: 9.6e-5 in float32 (measured 8.4e-6), 1.8e-13 in mixed and
    # float64 (measured 2.5e-14).
    rounding = 16.0 * math.sqrt(sim.steps_done) * UNIT_ROUNDOFF[precision]
    assert dl.max() < rounding
    # The energy error has the same rounding walk plus the splitting's bounded O((|w| dt)^2)
    # term, (|w| dt)^2 / 12 = 7.5e-5 for a Strang splitting; measured 2.1e-5 in float32, 1.1e-5 in float64.
    assert np.abs(dk).max() < rounding + wdt**2 / 12


# ---------------------------------------------------------------------------------------------
# 5. Energy and momentum conservation of elastic, frictionless collisions


def mixed_shapes(scene):
    shapes = [
        ConvexShape.box(0.1, name="cube"),
        ConvexShape.tetrahedron(0.15, name="tet"),
        ConvexShape.rock(12, 0.13, seed=1, name="rock"),
    ]
    for s in shapes:
        scene.add_shape(s.name, s)
    return shapes


def random_quats(n, seed):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_energy_conserved_in_closed_box(device):
    """8 polyhedra (cubes, tetrahedra, rocks) colliding inside a closed box, e = 1, mu = 0, no gravity.

    10^5 steps at the recommended step (dt = "auto"): 15 s on one CPU thread.
    """
    scene = single_material_scene(gravity=(0.0, 0.0, 0.0), restitution=1.0, friction=0.0)
    shapes = mixed_shapes(scene)
    rng = np.random.default_rng(0)
    grid = np.array([(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float)
    quats = random_quats(8, 1)
    for n, p in enumerate((grid - 0.5) * 0.2):
        scene.add_body(
            shapes[n % 3].name, "m", position=p, orientation=quats[n], velocity=rng.normal(size=3) * 0.5,
            angular_velocity=rng.normal(size=3) * 5.0,
        )  # fmt: skip
    scene.add_box_container((0.0, 0.0, 0.0), (0.4, 0.4, 0.4), "m", open_top=False)
    sim = Simulation(scene, device)
    e0 = sim.energy()
    assert e0["contact"] == 0.0
    h0 = e0["kinetic"]
    steps, every = 100_000, 100
    mod, raw_free, raw_contact, pairs = [], [], [], set()
    for _ in range(steps // every):
        sim.step(every)
        en = sim.energy()
        h = en["kinetic"] + en["contact"]
        mod.append(modified_energy(sim, en) - h0)
        (raw_contact if en["contact"] > 0.0 else raw_free).append(h - h0)
        c = sim.contacts()
        pairs.update(zip(c["body_a"].tolist(), c["body_b"].tolist(), strict=True))
    mod, raw_free, raw_contact = np.abs(mod) / h0, np.abs(raw_free) / h0, np.abs(raw_contact) / h0
    body_pairs = {p for p in pairs if p[0] < 8 and p[1] < 8}
    print(f"\nclosed box, {steps} steps of {sim.dt:.3g} s: modified energy max rel. error {mod.max():.2e}; "
          f"K + W: max {raw_free.max():.2e} over {len(raw_free)} contact-free samples, {raw_contact.max():.2e} "
          f"over {len(raw_contact)} samples in contact; {len(body_pairs)} body pairs and "
          f"{len(pairs) - len(body_pairs)} body-wall pairs met")  # fmt: skip
    assert sim.steps_done == steps
    assert en["dissipated"] == 0.0
    # The run is busy: bodies met each other and the walls, and some samples fell between contacts.
    assert len(body_pairs) >= 3 and len(pairs) - len(body_pairs) >= 5
    assert len(raw_free) >= 20
    # The criterion, 1e-3 relative. Between contacts K + W is itself the invariant
    # (measured 7e-5); inside contacts symplectic Euler's H swings by dt/2 F.v (measured up to
    # 2e-3, not a drift) and the modified energy is the invariant (measured 1.3e-4).
    assert raw_free.max() < 1e-3
    assert mod.max() < 1e-3
    st = sim.state()
    assert np.all(np.abs(st["body_position"][:8]) < 0.2)  # nobody left the box


@pytest.mark.parametrize("precision", ["mixed", "float64", "float32"])
def test_momentum_conserved_without_walls(device, precision):
    """8 free bodies thrown together in zero gravity: linear and angular momentum stay put, to the
    rounding of the precision's state (a reaction 1e-4 short of its action changes P by 1e-4 of the
    impulses exchanged, far above the float64 bound and below float32's)."""
    scene = single_material_scene(gravity=(0.0, 0.0, 0.0), restitution=0.7, friction=0.4, precision=precision)
    shapes = mixed_shapes(scene)
    rng = np.random.default_rng(3)
    grid = np.array([(i, j, k) for i in (0, 1) for j in (0, 1) for k in (0, 1)], dtype=float)
    pos = (grid - 0.5) * 0.2 + np.array([0.5, -0.3, 0.2])
    quats = random_quats(8, 2)
    for n in range(8):
        # Towards the group's centre at 1-2 m/s, plus spin: they meet within ~20 ms.
        vel = -(pos[n] - pos.mean(axis=0)) * 10.0 + rng.normal(size=3) * 0.3
        scene.add_body(
            shapes[n % 3].name, "m", position=pos[n], orientation=quats[n], velocity=vel,
            angular_velocity=rng.normal(size=3) * 5.0,
        )  # fmt: skip
    sim = Simulation(scene, device)
    mass = scene.body_mass()
    st = sim.state()
    p0 = (mass[:, None] * st["body_velocity"]).sum(axis=0)
    l0 = angular_momentum(scene, st)
    p_scale = float(np.sum(mass * np.linalg.norm(st["body_velocity"], axis=1)))
    # Long enough for the bodies to meet whatever the recommended step (about 0.12 s).
    steps = 50 * int(np.ceil(0.12 / sim.dt / 50))
    dp, dl, met = 0.0, 0.0, set()
    for _ in range(steps // 50):
        sim.step(50)
        st = sim.state()
        dp = max(dp, np.abs((mass[:, None] * st["body_velocity"]).sum(axis=0) - p0).max())
        dl = max(dl, np.abs(angular_momentum(scene, st) - l0).max())
        c = sim.contacts()
        met.update(zip(c["body_a"].tolist(), c["body_b"].tolist(), strict=True))
    en = sim.energy()
    # Pair forces and torques act on both bodies with one value (float32 in float32 and mixed, float64
    # in float64), summed per body and integrated in the state's scalar, so the momenta change only by
    # the rounding of those sums and of v += dt F/m and w's update: at most eps of sum m|v| per step,
    # added up linearly over the steps as the worst case. float32: 5.8e-3 kg m/s (measured ~1e-6);
    # mixed and float64: 1.1e-11 (measured 8.8e-15 and 2.8e-13 for L).
    tol = steps * UNIT_ROUNDOFF[precision] * p_scale
    print(f"\nfree collisions, {precision}: {steps} steps, {len(met)} pairs met; max |dP| = {dp:.2e} "
          f"(scale {p_scale:.2f} kg m/s, bound {tol:.1e}), max |dL| = {dl:.2e}; "
          f"dissipated {en['dissipated']:.3f} J")  # fmt: skip
    assert len(met) >= 4 and en["dissipated"] > 0.0  # they collided (and friction and damping acted)
    assert dp < tol
    # Angular momentum about the origin: the same per step, with lever arms up to 1 m.
    assert dl < 2.0 * tol


# ---------------------------------------------------------------------------------------------
# 6. A pour into a box container


def test_pour_settles_in_box(device):
    """512 mixed polyhedra dropped from an 8 x 8 x 8 grid into an open box settle: finite, inside,
    small overlaps, kinetic energy gone. About 5 min on one CPU thread (a 6 x 6 x 5 grid takes 100 s)."""
    pour(device, 8, 8)


def pour(device, nx, nz):
    size = 0.1
    scene = single_material_scene(k=1.0e8, restitution=0.3, friction=0.5)
    shapes = [
        ConvexShape.box(0.8 * size, name="cube"),
        ConvexShape.tetrahedron(1.2 * size, name="tet"),
        ConvexShape.octahedron(0.8 * size, name="oct"),
        ConvexShape.rock(16, size, seed=3, name="rock"),
        ConvexShape.prism(6, 0.5 * size, 0.8 * size, name="hex"),
    ]
    for s in shapes:
        scene.add_shape(s.name, s)
    gap = 1.5 * size  # grid pitch, larger than any body's diameter (0.147 m): no initial overlap
    width = nx * gap
    depth = nz * gap + 0.3
    scene.add_box_container((0.0, 0.0, 0.5 * depth), (width, width, depth), "m")
    n_walls = scene.num_bodies
    rng = np.random.default_rng(1)
    g1 = (np.arange(nx) - 0.5 * (nx - 1)) * gap
    pts = np.array([(x, y, (iz + 0.5) * gap) for iz in range(nz) for y in g1 for x in g1])
    kinds = rng.integers(0, len(shapes), len(pts))
    quats = random_quats(len(pts), 4)
    for i, p in enumerate(pts):
        scene.add_body(shapes[kinds[i]].name, "m", position=p, orientation=quats[i], velocity=rng.normal(size=3) * 0.2)
    free = slice(n_walls, None)
    assert max(s.radius for s in shapes) * 2 < gap

    sim = Simulation(scene, device)
    assert len(sim.contacts()["volume"]) == 0  # no initial overlaps
    duration = 1.5
    chunk = 1000
    ke = []
    while sim.time < duration:
        sim.step(chunk)
        ke.append(sim.energy()["kinetic"])
    ke = np.array(ke)
    st = sim.state()
    x = st["body_position"][free]

    # Overlaps: each contact's volume against the smaller body's (walls are far larger).
    volumes = np.array([s.volume for s in scene.shapes.values()])[scene.body_shape]
    c = sim.contacts()
    ref = np.minimum(volumes[c["body_a"]], volumes[c["body_b"]])
    worst = float(np.max(c["volume"] / ref))
    mass = scene.body_mass()[free]
    speed = np.linalg.norm(st["body_velocity"][free], axis=1)
    print(f"\npour of {len(pts)} bodies, {sim.steps_done} steps of {sim.dt:.3g} s: kinetic energy peak "
          f"{ke.max():.3g} J, final {ke[-1]:.3g} J (last 5: {np.array2string(ke[-5:], precision=2)}); largest "
          f"overlap {100 * worst:.2f}% of a body; max speed {speed.max():.3g} m/s; pile top {x[:, 2].max():.3f} m "
          f"(grid top {pts[:, 2].max():.3f} m)")  # fmt: skip

    assert np.all(np.isfinite(st["body_position"])) and np.all(np.isfinite(st["body_velocity"]))
    # Nobody escaped: every centre inside the cavity (walls at +-width/2, floor at 0).
    assert np.all(np.abs(x[:, :2]) < 0.5 * width)
    assert np.all(x[:, 2] > 0.0) and np.all(x[:, 2] < depth)
    # The criterion: the largest overlap below 1% of the body volume (measured 0.47%).
    assert worst < 0.01
    # The fall's kinetic energy is gone (measured: peak 380 J, final 7e-3 J) and stays gone over the
    # last 0.3 s (measured below 3e-5 of the peak); what is left is the contact chatter of
    # hysteretic damping at rest, 1 cm/s rms (the bodies hit the heap at 3-4 m/s).
    assert ke[-1] < 1e-3 * ke.max()
    assert np.all(ke[-5:] < 1e-3 * ke.max())
    rms = math.sqrt(2.0 * ke[-1] / mass.sum())
    assert rms < 0.03
    # Settled into a heap: lower than half the starting grid.
    assert x[:, 2].max() < 0.5 * pts[:, 2].max()
    return rms


# ---------------------------------------------------------------------------------------------
# 7. Determinism


def busy_box_scene():
    """27 mixed bodies thrown about in a box container with a floor plane: many contacts and rebuilds."""
    scene = single_material_scene(restitution=0.5, friction=0.5, k=1.0e6)  # soft: dt = 0.5 ms, 0.35 s in all
    shapes = mixed_shapes(scene)
    scene.add_box_container((0.0, 0.0, 0.35), (0.7, 0.7, 0.7), "m")
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")  # a wall plane too (coincides with the floor)
    rng = np.random.default_rng(5)
    g1 = (np.arange(3) - 1.0) * 0.2  # pitch 0.2 m > the largest diameter (0.18 m): no initial overlap
    pts = np.array([(x, y, 0.1 + 0.2 * k) for k in range(3) for y in g1 for x in g1])
    quats = random_quats(len(pts), 6)
    for i, p in enumerate(pts):
        scene.add_body(
            shapes[i % 3].name, "m", position=p, orientation=quats[i], velocity=rng.normal(size=3),
            angular_velocity=rng.normal(size=3) * 5.0,
        )  # fmt: skip
    return scene


def test_same_scene_twice_is_bit_identical(device):
    scene = busy_box_scene()

    def run():
        sim = Simulation(scene, device)
        sim.step(700)
        return sim.state(), sim.energy(), sim.contacts()

    (s1, e1, c1), (s2, e2, c2) = run(), run()
    assert len(c1["volume"]) > 10  # busy: many contacts, friction springs and rebuilds
    for k in s1:
        assert np.array_equal(s1[k], s2[k]), k
    assert e1 == e2
    for k in c1:
        assert np.array_equal(c1[k], c2[k]), k


def test_tree_rebuild_leaves_results_bit_identical(device):
    # The device broad phase refits its tree; a tree rebuilt after every chunk with a device rebuild
    # (tree_rebuild=0) must give the same run bit for bit as the tree of the first build refitted
    # throughout (None): the tree only filters the candidates, whose list is sorted by key.
    scene = busy_box_scene()

    def run(tree_rebuild):
        sim = Simulation(scene, device, tree_rebuild=tree_rebuild)
        # The device rebuild path (refit, conditional branch) also where there is no graph (the CPU).
        sim.stepper.device_rebuild = True
        sim.step(700)
        return sim.state(), sim.contacts(), sim.current_contacts.broadphase

    (s1, c1, bp1), (s2, c2, bp2) = run(None), run(0.0)
    assert bp1.num_tree_rebuilds == 0 and bp2.num_tree_rebuilds >= 5
    assert bp1.num_builds == bp2.num_builds == 1  # no redone chunk: every later rebuild was a device one
    assert len(c1["volume"]) > 10
    for k in s1:
        assert np.array_equal(s1[k], s2[k]), k
    for k in c1:
        assert np.array_equal(c1[k], c2[k]), k


def test_tree_rebuild_option_is_checked():
    with pytest.raises(ValueError, match="tree_rebuild"):
        Simulation(busy_box_scene(), "cpu", tree_rebuild=-1.0)


def test_stepper_writes_the_next_state(device):
    """Stepper.step(state_in, state_out, ...) leaves state_in as it was and gives state_out the state
    that stepping in place gives; a snapshot brings a simulation back to its step, bit for bit."""
    from polydem.simulation import Stepper

    scene = single_material_scene(restitution=0.5, friction=0.5, k=1.0e7)
    shapes = mixed_shapes(scene)
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    quats = random_quats(4, 7)
    for i in range(4):  # two stacks: the upper bodies fall onto the lower ones, on the floor
        x, z = 0.4 * (i // 2) + 0.03 * (i % 2), 0.09 + 0.17 * (i % 2)
        scene.add_body(shapes[i % 3].name, "m", position=(x, 0.0, z), orientation=quats[i], velocity=(0.0, 0.0, -1.0))
    sim = Simulation(scene, device, use_graph=False)
    # In contact with the floor and each other: springs and turning volumes to carry (the step is the
    # scene's "auto" one, so the count of steps until then is not fixed).
    for _ in range(80):
        sim.step(50)
        c = sim.contacts()
        if np.count_nonzero(c["body_b"] >= 0) >= 1 and np.count_nonzero(c["body_b"] < 0) >= 1:
            break
    assert np.count_nonzero(c["body_b"] >= 0) >= 1 and np.count_nonzero(c["body_b"] < 0) >= 1
    n0 = sim.steps_done
    snap = sim.snapshot()
    before = sim.current_state.numpy(sim.current_state.FIELDS)

    assert np.any(sim.current_contacts.pair_xi.numpy() != 0.0)  # friction springs are stretched

    stepper = Stepper(sim.model)
    state_in = sim.current_state
    state_out = state_in.copy()
    state_out.body_v.zero_()
    stepper.step(state_in, state_out, sim.current_contacts, sim.dt)  # the step also moves the pair history on
    for k, a in state_in.numpy(state_in.FIELDS).items():
        assert np.array_equal(a, before[k]), k  # the state in is only read
    out = state_out.numpy(state_out.FIELDS)
    assert int(out["step_count"][0]) == n0 + 1 and not np.array_equal(out["body_q"], before["body_q"])
    sim.restore(snap)  # the history of step n0 again (the pair list found afresh)
    stepper.step(sim.current_state, sim.current_state, sim.current_contacts, sim.dt)
    for k, a in sim.current_state.numpy(state_in.FIELDS).items():
        assert np.array_equal(a, out[k]), k

    sim.restore(snap)
    sim.step(40)
    first = sim.state(), sim.energy()
    sim.restore(snap)
    assert sim.steps_done == n0 and sim.time == snap.time
    sim.step(40)
    second = sim.state(), sim.energy()
    for k in first[0]:
        assert np.array_equal(first[0][k], second[0][k]), k
    assert first[1] == second[1]


def test_restore_last_good_after_an_interrupted_step(device):
    """A step interrupted inside a chunk (Ctrl-C) is rolled back to the step count it started from."""
    scene = single_material_scene()
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("cube", "m", position=(0.0, 0.0, 1.0))
    sim = Simulation(scene, device, use_graph=False)
    sim.step(10)
    assert sim.restore_last_good()  # nothing to undo
    expected = sim.state()
    step, calls = sim.stepper.step, []

    def interrupted(*args):
        step(*args)
        calls.append(1)
        if len(calls) == 5:
            raise KeyboardInterrupt

    sim.stepper.step = interrupted
    with pytest.raises(KeyboardInterrupt):
        sim.step(20)
    sim.stepper.step = step
    assert sim.steps_done == 10 and not sim.is_consistent()  # the state moved on 5 steps
    assert sim.restore_last_good() and sim.steps_done == 10
    for k, a in sim.state().items():
        assert np.array_equal(a, expected[k]), k


# ---------------------------------------------------------------------------------------------
# 8, 9. Errors


def test_nonfinite_state_names_step_and_body(device):
    scene = single_material_scene()
    scene.add_shape("cube", ConvexShape.box(0.1))
    for i in range(4):
        scene.add_body("cube", "m", position=(0.5 * i, 0.0, 1.0))  # far apart: no contacts
    sim = Simulation(scene, device)
    sim.step(100)  # more than one chunk of steps
    v = sim.current_state.body_v.numpy()
    v[2, 1] = np.nan
    sim.current_state.body_v.assign(v)
    with pytest.raises(SimulationError) as info:
        sim.step(10)
    msg = str(info.value)
    print(f"\n{msg}")
    # The first bad state is the one after step 101 (the 1st step of this call), body 2 only.
    assert re.search(r"\bstep 101\b", msg), msg
    assert re.search(r"bodies \[2\]", msg), msg


def test_time_step_above_stable_limit(device):
    scene = single_material_scene()
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("cube", "m", position=(0.0, 0.0, 0.06))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    model = Simulation(scene, device).model
    assert model.dt_recommended < model.dt_limit

    scene.dt = 1.5 * model.dt_limit
    with pytest.raises(SceneError) as info:
        Simulation(scene, device)
    assert info.value.key == "simulation.dt"
    assert "stable limit" in str(info.value)

    scene.dt = 0.9 * model.dt_limit  # just below: accepted, and the contact stays bounded
    sim = Simulation(scene, device)
    assert sim.dt == scene.dt
    sim.step(2000)
    assert np.all(np.isfinite(sim.state()["body_position"]))


def test_package_exports():
    assert polydem.Simulation is Simulation and polydem.SimulationError is SimulationError
    assert issubclass(SimulationError, RuntimeError)


# ---------------------------------------------------------------------------------------------
# 10. Redone chunks and the diagnostics pass (polygon overflow)


def overlapping_spheres_scene():
    """Two overlapping icospheres (triangular faces: a buffer of 3 vertices overflows on any clip)
    and a cube far away from both, in zero gravity."""
    scene = single_material_scene(gravity=(0.0, 0.0, 0.0), k=1.0e7, friction=0.4)
    scene.add_shape("ball", ConvexShape.sphere(subdivisions=2, radius=0.05))
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("ball", "m", position=(0.0, 0.0, 0.0))
    scene.add_body("ball", "m", position=(0.0975, 0.01, 0.005), velocity=(-0.1, 0.0, 0.0))
    scene.add_body("cube", "m", position=(5.0, 0.0, 0.0))
    return scene


def test_redone_chunk_forgets_its_nonfinite_step(device):
    """A chunk redone after a polygon overflow does not raise for a NaN of the discarded chunk.

    BEFORE: SimulationError "non-finite at step 2" although the redone chunk stays finite.
    """
    reference = Simulation(overlapping_spheres_scene(), device, use_graph=False)
    reference.step(10)
    sim = Simulation(overlapping_spheres_scene(), device, use_graph=False)
    sim.stepper.poly_capacity = 3
    sim.stepper._kernels()
    step, calls = sim.stepper.step, []

    def poisoned_once(state_in, state_out, contacts, dt):
        step(state_in, state_out, contacts, dt)
        calls.append(1)
        if len(calls) == 1:  # the first chunk only: the one that overflows and is redone
            v = state_out.body_v.numpy()
            v[2, 0] = np.nan
            state_out.body_v.assign(v)

    sim.stepper.step = poisoned_once
    sim.step(10)
    assert sim.stepper.poly_capacity > 3  # the overflow was real: the chunk was redone
    assert len(calls) > 10
    for k, a in sim.state().items():
        np.testing.assert_array_equal(a, reference.state()[k], err_msg=k)


def test_restore_forgets_a_nonfinite_step(device):
    """After a SimulationError, restoring a good snapshot lets the run go on."""
    scene = single_material_scene()
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("cube", "m", position=(0.0, 0.0, 1.0))
    sim = Simulation(scene, device, use_graph=False)
    sim.step(5)
    good = sim.snapshot()
    v = sim.current_state.body_v.numpy()
    v[0, 2] = np.inf
    sim.current_state.body_v.assign(v)
    with pytest.raises(SimulationError):
        sim.step(3)
    sim.restore(good)
    sim.step(3)  # BEFORE: raised again for the step of the discarded state
    assert sim.steps_done == 8 and np.all(np.isfinite(sim.state()["body_velocity"]))


def test_contacts_regrow_the_polygon_buffer(device):
    """contacts() and energy() with a polygon buffer too small for the contact: grown and rerun.

    BEFORE: the diagnostics pass ignored its overflow flag: a wrong volume and energy, and the
    step's flag left set (the next chunk was redone for nothing).
    """
    ref = Simulation(overlapping_spheres_scene(), device)
    expected, expected_energy = ref.contacts(), ref.energy()
    assert len(expected["volume"]) == 1 and not ref.stepper.buffers_overflowed()
    sim = Simulation(overlapping_spheres_scene(), device)
    sim.stepper.poly_capacity = 3
    sim.stepper._kernels()
    got = sim.contacts()
    print(f"\nvolume {got['volume']} expected {expected['volume']}")
    assert sim.stepper.poly_capacity > 3 and not sim.stepper.buffers_overflowed()
    for k in ("body_a", "body_b", "volume", "normal", "normal_force"):
        np.testing.assert_array_equal(got[k], expected[k], err_msg=k)
    assert sim.energy() == expected_energy


# ---------------------------------------------------------------------------------------------
# 11. Tunnelling


def fast_cube_scene(speed, slab):
    """A 0.1 m steel cube (hertz, k = 1e10) at ``speed`` down onto a plane or a fixed 1 cm slab."""
    scene = single_material_scene(density=7800.0, k=1.0e10, restitution=0.5, friction=0.3)
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("cube", "m", position=(0.0, 0.0, 0.12), velocity=(0.0, 0.0, -speed))
    if slab:
        scene.add_shape("slab", ConvexShape.box(1.0, 1.0, 0.01))
        scene.add_body("slab", "m", kind="fixed")
    else:
        scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    return scene


@pytest.mark.parametrize("speed, slab", [(1000.0, False), (100.0, True)])
def test_tunnelling_is_warned_in_the_run(device, speed, slab):
    """A body that becomes fast during the run: a SimulationWarning naming it, its speed and the limit.

    BEFORE: the cube passed through the plane (1000 m/s) or the 1 cm slab (100 m/s) without a word.
    Since the enclosed push leaves through the nearest face (issue 11), the cube that reaches the
    middle of the slab comes back out of its top at 100 m/s; through the plane it still goes.
    """
    import warnings

    scene = fast_cube_scene(0.0, slab)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # at rest: nothing to warn about at the start
        sim = Simulation(scene, device)
    v = sim.current_state.body_v.numpy()
    v[0, 2] = -speed
    sim.current_state.body_v.assign(v)
    with pytest.warns(polydem.SimulationWarning, match=r"body 0 \(shape 'cube', free\) reached .* may pass through"):
        sim.step(2 * int(0.12 / speed / sim.dt) + 10)
    if not slab:
        # The warning was right: the cube went through.
        assert sim.state()["body_position"][0, 2] < -0.01


def test_normal_drop_is_not_warned_about_tunnelling(device):
    import warnings

    scene = fast_cube_scene(0.0, slab=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sim = Simulation(scene, device)
        sim.step(int(0.2 / sim.dt))  # the fall of 2 cm and the first impacts
    assert sim.state()["body_position"][0, 2] > 0.04


# ---------------------------------------------------------------------------------------------
# 12. The energy balance of friction


def tumbling_cube_scene(e, law="power"):
    """A 1 kg cube thrown spinning onto a floor (mu 0.5): it tumbles on edges and faces, slides and sticks."""
    scene = single_material_scene(restitution=e, friction=0.5, **FRICTION_LAWS[law])
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("cube", "m", position=(0.0, 0.0, 0.1), velocity=(0.5, 0.0, -0.5), angular_velocity=(15.0, 5.0, 2.0))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    return scene


def friction_energy_run(device, scene, duration, dt_factor=1.0, every=2):
    """(dissipated [J], largest |change| of the modified energy [J], its final change [J], most
    negative change of the dissipated energy between two samples [J]) of a run."""
    if dt_factor != 1.0:
        scene.dt = Simulation(scene, device).dt * dt_factor
    sim = Simulation(scene, device)
    e0 = sim.energy()
    h0 = modified_energy(sim, e0)
    prev, worst_step, drift = e0["dissipated"], 0.0, 0.0
    for _ in range(int(duration / sim.dt) // every):
        sim.step(every)
        en = sim.energy()
        worst_step = min(worst_step, en["dissipated"] - prev)
        prev = en["dissipated"]
        change = modified_energy(sim, en) - h0
        drift = max(drift, abs(change))
    return en["dissipated"], drift, change, worst_step


# Largest |change| of the modified energy over the dissipated energy. BEFORE (friction work booked
# as -ft.vt dt less the spring's change: this step's force with the last step's displacement):
# slide 2.5e-3 (e = 1 and 0.3), stick 0.115 (e = 1), tumble 4.7e-2 (e = 1) and 5.5e-3 (e = 0.5), all
# first order in dt. AFTER: 7.8e-5, 4.3e-5, 4.3e-3 (float32 positions: 1e-7 J), 7.3e-4, 5.9e-4.
@pytest.mark.parametrize("law", ["power", "hertz"])
@pytest.mark.parametrize(
    "case, e, bound",
    [("slide", 1.0, 5e-4), ("slide", 0.3, 5e-4), ("stick", 1.0, 1e-2), ("tumble", 1.0, 2e-3), ("tumble", 0.5, 2e-3)],
)
def test_friction_energy_balance(device, case, e, bound, law):
    """kinetic + contact + gravity + dissipated stays constant to the integrator's error, and no step
    books a negative dissipation (the friction springs create no energy): a block sliding down and one
    sticking on an incline, a cube thrown spinning onto a floor."""
    scene = {"slide": lambda: incline_scene(35.0, e, law=law), "stick": lambda: incline_scene(20.0, e, law=law)}.get(
        case, lambda: tumbling_cube_scene(e, law)
    )()
    dissipated, drift, _, worst_step = friction_energy_run(device, scene, 0.3 if case == "tumble" else 0.1)
    print(f"\n{case} e = {e}, {law}: dissipated {dissipated:.4e} J, largest |change| of the modified energy "
          f"{drift:.3e} J ({drift / dissipated:.2e} of it), most negative step {worst_step:.2e} J")  # fmt: skip
    assert dissipated > 0.0
    assert worst_step >= -1e-7 * dissipated  # rounding only
    assert drift < bound * dissipated


@pytest.mark.parametrize("law", ["power", "hertz"])
def test_sliding_friction_with_its_dashpot_books_what_it_dissipates(device, law):
    """A cube thrown spinning onto a floor with e = 0.5 slides with the tangential dashpot on: the
    modified energy's drift shrinks with dt. BEFORE: a sliding spring was re-pointed along the capped
    total force, which the dashpot turns towards vt, and the turn of an unchanged length was booked as
    slip: +7.2e-3, +1.0e-2 and +1.1e-2 of the dissipated energy at dt, dt/2 and dt/4 (with the
    derived spring k_n / 5.5). AFTER: 9.6e-4, 5.0e-4, 2.5e-4.

    Under the hertz law too: its resolved toe is that of the recommended step at dt/2 as at dt (Model.toe_dt),
    so both runs integrate the same law. BEFORE that, the toe shrank with the run's step (V_c ~ dt^4) and
    dt/2 was another problem (the test ran the power law only)."""
    coarse = friction_energy_run(device, tumbling_cube_scene(0.5, law), 0.3)
    fine = friction_energy_run(device, tumbling_cube_scene(0.5, law), 0.3, dt_factor=0.5)
    print(f"\ntumble with dashpot, {law}: drift {coarse[1] / coarse[0]:.2e} at dt, {fine[1] / fine[0]:.2e} at dt/2")
    assert coarse[1] < 2e-3 * coarse[0]
    assert fine[1] < 0.7 * coarse[1] * fine[0] / coarse[0]


@pytest.mark.parametrize("law", ["power", "hertz"])
def test_friction_energy_error_of_a_sticking_block_is_second_order(device, law):
    """The damped sticking block (e = 0.3): the final change of the modified energy at dt and dt/2.

    BEFORE: +2.3e-7 J and +1.5e-7 J (first order: the booked kt |vt|^2 dt^2 / 2 per step).
    AFTER: -4.5e-8 J and -1.4e-8 J.

    Under the hertz law too (as the dashpot test above): when its toe followed the run's step, the block
    at dt/2 rested on another toe than at dt and started away from its equilibrium (-4.0e-8 J and
    -1.7e-7 J: the finer step the worse).
    """
    _, _, coarse, _ = friction_energy_run(device, incline_scene(20.0, 0.3, law=law), 0.1)
    _, _, fine, _ = friction_energy_run(device, incline_scene(20.0, 0.3, law=law), 0.1, dt_factor=0.5)
    print(f"\nsticking block, e = 0.3, {law}: change of the modified energy {coarse:.3e} J at dt, {fine:.3e} J at dt/2")
    assert abs(fine) < 0.45 * abs(coarse)


def test_friction_books_no_negative_dissipation_in_one_step(device):
    """respond() in float64 for random springs, tilted normals (the spring is turned), velocities,
    spins (the twist channel and the rocking damping), restitutions (the dashpot) and caps: the booked
    loss of a step is >= 0 to rounding. face_area 0: no toe (the law is linear anyway)."""
    import warp as wp
    from polydem.kernels.response import make_response

    sc = wp.float64
    vec3 = wp.types.vector(3, sc)
    respond = make_response(sc, "linear", True).respond

    @wp.kernel(enable_backward=False, module="unique")
    def one_step(
        area: wp.array(dtype=vec3),
        v_a: wp.array(dtype=vec3),
        w_a: wp.array(dtype=vec3),
        xi: wp.array(dtype=vec3),
        e: wp.array(dtype=sc),
        mu: wp.array(dtype=sc),
        lost: wp.array(dtype=sc),
        scale: wp.array(dtype=sc),
    ):
        i = wp.tid()
        z = vec3(sc(0.0), sc(0.0), sc(0.0))
        c = vec3(sc(0.0), sc(0.0), sc(0.05))
        vol = sc(1.0e-8)
        kt = sc(1.0e6)
        dt = sc(1.0e-4)
        out = respond(
            vol, c * vol, area[i], wp.cross(c, area[i]), z, c * sc(2.0), v_a[i], w_a[i], z, z,
            sc(1.0e4), sc(1.0), e[i], mu[i], kt, xi[i], sc(0.0), dt, dt, sc(0.05), sc(0.0), sc(1.0), sc(1.0),
        )  # fmt: skip
        lost[i] = out[5]
        xi_new = out[2]
        scale[i] = (
            sc(0.5) * kt * (wp.dot(xi[i], xi[i]) + wp.dot(xi_new, xi_new)) + wp.length(out[9]) * wp.length(v_a[i]) * dt
        )

    rng = np.random.default_rng(3)
    n = 20000
    normal = np.array([0.0, 0.0, 1.0]) + rng.normal(size=(n, 3)) * rng.choice([0.0, 0.01, 0.3], size=(n, 1))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    arrays = {
        "area": -0.01 * normal,
        "v_a": rng.normal(size=(n, 3)) * rng.choice([1e-4, 1e-2, 1.0], size=(n, 1)),
        "w_a": rng.normal(size=(n, 3)) * rng.choice([0.0, 1.0], size=(n, 1)),
        "xi": rng.normal(size=(n, 3)) * rng.choice([1e-7, 1e-5, 1e-3], size=(n, 1)),
    }
    ins = [wp.array(a, dtype=vec3, device=device) for a in arrays.values()]
    ins += [wp.array(rng.choice(c, size=n), dtype=sc, device=device) for c in ([1.0, 0.9, 0.3, 0.05], [0.1, 0.5, 1.0])]
    lost = wp.zeros(n, dtype=sc, device=device)
    scale = wp.zeros(n, dtype=sc, device=device)
    wp.launch(one_step, dim=n, inputs=ins, outputs=[lost, scale], device=device)
    rel = lost.numpy() / np.maximum(scale.numpy(), 1e-300)
    print(f"\nbooked loss of one step over the energies in play: min {rel.min():.2e}")
    assert rel.min() > -1e-12


# ---------------------------------------------------------------------------------------------
# Penetration depth in contacts()


@pytest.mark.parametrize("precision", ["float32", "mixed", "float64"])
def test_contacts_report_penetration_depth(device, precision):
    """contacts()["depth"]: a cube tilted about x by 0.3 rad whose lowest edge lies 2 mm below a wall
    plane, and two aligned cubes overlapping face to face by 3 mm (no vertex of one lies strictly inside
    the other); the depth is the shortest separating translation (before, contacts() gave volumes only)."""
    edge = 0.1
    scene = single_material_scene(gravity=(0.0, 0.0, 0.0))
    scene.add_shape("cube", ConvexShape.box(edge, edge, edge))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    angle = 0.3
    q = quat_from_axis_angle((1.0, 0.0, 0.0), angle)
    lowest = 0.5 * edge * (math.cos(angle) + math.sin(angle))  # centre height of the lowest edge
    scene.add_body("cube", "m", position=(0.0, 0.0, lowest - 0.002), orientation=q)
    scene.add_body("cube", "m", position=(1.0, 0.0, 0.5))
    scene.add_body("cube", "m", position=(1.0 + edge - 0.003, 0.0, 0.5))
    scene.precision = precision
    sim = Simulation(scene, device=device)
    c = sim.contacts()
    depth = {(int(a), int(b)): float(d) for a, b, d in zip(c["body_a"], c["body_b"], c["depth"], strict=True)}
    assert set(depth) == {(0, -1), (1, 2)}
    tol = 1e-6 if precision != "float64" else 1e-12
    assert depth[(0, -1)] == pytest.approx(0.002, abs=tol)
    assert depth[(1, 2)] == pytest.approx(0.003, abs=tol)


# ---------------------------------------------------------------------------------------------
# A body resting flat under its own weight


def resting_cube_scene(precision, dt="auto"):
    """cube_drop's 0.1 m steel cube (hertz k = 1e10, e = 0.5), set down 10 um above a plane."""
    scene = Scene(gravity=(0.0, 0.0, -G), dt=dt)
    scene.add_material("steel", density=7800.0, law="hertz", k=1.0e10, restitution=0.5, friction=0.3)
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_body("cube", "steel", position=(0.0, 0.0, 0.05 + 1.0e-5))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "steel")
    scene.precision = precision
    return scene


def test_resting_time_step_of_a_flat_hertz_contact():
    """dt = "auto" resolves a body resting on a face under its own weight: for cube_drop's cube the
    resting depth is (W / (k A^1.5))^2 = 5.9e-11 m, the tangent stiffness W / (2 d) = 6.5e11 N/m and
    the step min(1, 2 e) / sqrt(k_rest / m) = 3.45e-6 s, a third of the reference overlap's 1.11e-5 s."""
    scene = resting_cube_scene("mixed")
    ts = scene.time_step()
    weight = 7800.0 * 1e-3 * G
    depth = (weight / (1.0e10 * 1e-3)) ** 2
    omega = math.sqrt(weight / (2.0 * depth) / 7.8)
    assert ts.resting == pytest.approx(1.0 / omega, rel=1e-9)
    assert ts.dt == ts.recommended == pytest.approx(ts.resting, rel=1e-12)
    assert ts.period / 50 == pytest.approx(1.11e-5, rel=0.01)
    # Without gravity (nothing rests) or with the linear law (no resting depth) it does not bind.
    scene.gravity = (0.0, 0.0, 0.0)
    assert scene.time_step().resting == math.inf
    linear = single_material_scene(law="linear", k=1.0e6)
    linear.add_shape("cube", ConvexShape.box(0.1))
    linear.add_body("cube", "m")
    assert linear.time_step().resting == math.inf


@pytest.mark.parametrize("precision", ["mixed", "float64"])
def test_lone_cube_rests_in_contact(device, precision):
    """A cube set down on a plane comes to rest in contact: every sample of the last 10 ms finds the
    contact. BEFORE: at the old dt = "auto" (1.11e-5 s, 3.2 times the resting step) it hopped by
    nanometres and was found in contact in 4 of 20 samples (cube_drop's summary said 0 contacts);
    in float32 its position near z = 0.05 m rounds to 3.7e-9 m, 60 times its resting depth, so
    float32 finds it in contact in 2 of 20 samples even at the resting step (BENCHMARKS.md 5d)."""
    sim = Simulation(resting_cube_scene(precision), device=device)
    sim.step(int(0.05 / sim.dt))
    found = []
    for _ in range(20):
        sim.step(int(5e-4 / sim.dt))
        found.append(len(sim.contacts()["volume"]) > 0)
    assert all(found), f"in contact in {sum(found)} of 20 samples"
    assert sim.energy()["contact"] > 0.0
