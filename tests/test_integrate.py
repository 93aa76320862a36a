"""The rigid-body integrator: closed forms, fixed and kinematic bodies, long torque-free runs.

Each physics test runs the integrator in both of its scalars: float32 (the "float32" precision) and
float64 (the "mixed" default and "float64": both integrate in float64). Rounding bounds are written
in the unit roundoff of the scalar in use, eps = 2^-24 = 6.0e-8 or 2^-53 = 1.1e-16, so a float64 run
is held to float64 rounding, not to a float32 bound it would pass with any small fault.
"""

import functools

import numpy as np
import pytest
import warp as wp
from polydem.kernels.integrate import (
    BODY_FIXED,
    BODY_FREE,
    BODY_KINEMATIC,
    integrate_bodies,
    kinetic_energy,
    make_integrator,
)
from scipy.spatial.transform import Rotation

IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])
UNIT_ROUNDOFF = {wp.float32: 2.0**-24, wp.float64: 2.0**-53}


@pytest.fixture(params=[wp.float32, wp.float64], ids=["float32", "float64"])
def scalar(request):
    """The integrator's scalar: float32, or float64 (what "mixed", the default, and "float64" use)."""
    return request.param


# -------------------------------------------------------------------------------------------------
# Reference kernels of the tests (the simulation needs neither: it checks finiteness per step in
# polydem.simulation and reports momenta from the host state)
# -------------------------------------------------------------------------------------------------

# Initial value of the "first offending body" slot of the finiteness check (int32 max).
NO_BODY = 2147483647


@functools.cache
def momentum_kernel(scalar):
    """The momentum diagnostics kernel in ``scalar``, with the integrator's own body_momentum."""
    ig = make_integrator(scalar)
    vec3 = ig.vec3

    @wp.kernel(enable_backward=False, module="unique")
    def kernel(
        body_inv_mass: wp.array(dtype=scalar),
        body_inertia: wp.array(dtype=vec3),
        body_flags: wp.array(dtype=int),
        body_q: wp.array(dtype=ig.transform),
        body_v: wp.array(dtype=vec3),
        body_w: wp.array(dtype=vec3),
        linear: wp.array(dtype=vec3),
        angular: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        p = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        h = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        inv_mass = body_inv_mass[i]
        if body_flags[i] == BODY_FREE and inv_mass > scalar(0.0):
            tf = body_q[i]
            q = wp.transform_get_rotation(tf)
            p = body_v[i] / inv_mass
            # R I R^T w: the spin's angular momentum.
            spin = wp.quat_rotate(q, ig.body_momentum(q, body_inertia[i], body_w[i]))
            h = wp.cross(wp.transform_get_translation(tf), p) + spin
        linear[i] = p
        angular[i] = h

    return kernel


def momentum(body_inv_mass, body_inertia, body_flags, body_q, body_v, body_w):
    """Per-body linear momentum m v [kg m/s] and angular momentum about the world origin
    x x m v + R I R^T w [kg m^2/s] (in the scalar of the state, on the device); fixed and kinematic
    bodies count 0."""
    n = body_q.shape[0]
    scalar = body_inv_mass.dtype
    linear = wp.empty(n, dtype=body_v.dtype, device=body_q.device)
    angular = wp.empty(n, dtype=body_v.dtype, device=body_q.device)
    wp.launch(
        momentum_kernel(scalar),
        dim=n,
        inputs=[body_inv_mass, body_inertia, body_flags, body_q, body_v, body_w],
        outputs=[linear, angular],
        device=body_q.device,
    )
    return linear, angular


@wp.kernel(enable_backward=False)
def check_finite_kernel(
    body_q: wp.array(dtype=wp.transform),
    body_v: wp.array(dtype=wp.vec3),
    body_w: wp.array(dtype=wp.vec3),
    flag: wp.array(dtype=int),
    first_body: wp.array(dtype=int),
):
    i = wp.tid()
    tf = body_q[i]
    ok = (
        wp.isfinite(wp.transform_get_translation(tf))
        and wp.isfinite(wp.transform_get_rotation(tf))
        and wp.isfinite(body_v[i])
        and wp.isfinite(body_w[i])
    )
    if not ok:
        flag[0] = 1
        wp.atomic_min(first_body, 0, i)


def reset_finite_check(flag, first_body):
    """Clear a finiteness flag (to 0) and its first-offending-body slot (to ``NO_BODY``)."""
    flag.zero_()
    first_body.fill_(NO_BODY)


def check_finite(body_q, body_v, body_w, flag=None, first_body=None):
    """``(flag, first_body)``: flag[0] = 1 when a body's state is not finite, first_body[0] the lowest
    such body (``NO_BODY``: none). Given arrays are not cleared (sticky until reset_finite_check)."""
    device = body_q.device
    if flag is None:
        flag = wp.zeros(1, dtype=int, device=device)
    if first_body is None:
        first_body = wp.array(np.array([NO_BODY], dtype=np.int32), dtype=int, device=device)
    wp.launch(
        check_finite_kernel,
        dim=body_q.shape[0],
        inputs=[body_q, body_v, body_w],
        outputs=[flag, first_body],
        device=device,
    )
    return flag, first_body


class Bodies:
    """A small set of bodies on one device, with the model and state arrays of the integrator in
    ``scalar`` (float32 or float64)."""

    def __init__(
        self, device, x, q, v, w, inv_mass, inertia, flags, f=None, t=None, gravity=(0.0, 0.0, 0.0), scalar=wp.float32
    ):
        n = len(x)
        self.device = device
        self.n = n
        self.gravity = gravity
        self.scalar = scalar
        self.eps = UNIT_ROUNDOFF[scalar]
        ig = make_integrator(scalar)
        npdt = np.float64 if scalar == wp.float64 else np.float32

        def vec3s(a):
            a = np.zeros((n, 3)) if a is None else np.broadcast_to(np.asarray(a, dtype=np.float64), (n, 3))
            return wp.array(a.astype(npdt), dtype=ig.vec3, device=device)

        q = np.broadcast_to(np.asarray(q, dtype=np.float64), (n, 4))
        q = q / np.linalg.norm(q, axis=1, keepdims=True)
        pose = np.concatenate([np.asarray(x, dtype=np.float64), q], axis=1)
        self.body_q = wp.array(pose.astype(npdt), dtype=ig.transform, device=device)
        self.body_v = vec3s(v)
        self.body_w = vec3s(w)
        self.body_f = vec3s(f)
        self.body_t = vec3s(t)
        self.body_inv_mass = wp.array(np.broadcast_to(inv_mass, n).astype(npdt), dtype=scalar, device=device)
        self.body_inertia = vec3s(inertia)
        self.body_flags = wp.array(np.broadcast_to(flags, n).astype(np.int32), dtype=int, device=device)

    def model(self):
        return self.body_inv_mass, self.body_inertia, self.body_flags

    def state(self):
        return self.body_q, self.body_v, self.body_w

    def step(self, dt):
        integrate_bodies(*self.model(), self.gravity, *self.state(), self.body_f, self.body_t, dt, device=self.device)

    def run(self, steps, dt, record=False):
        """Advance `steps` steps; with `record`, return the pose and angular velocity after each step,
        shapes (steps, n, 7) and (steps, n, 3), as float64 copies of the state."""
        if not record:
            for _ in range(steps):
                self.step(dt)
            return None
        hist_q = wp.empty(steps * self.n, dtype=self.body_q.dtype, device=self.device)
        hist_w = wp.empty(steps * self.n, dtype=self.body_w.dtype, device=self.device)
        for s in range(steps):
            self.step(dt)
            wp.copy(hist_q, self.body_q, dest_offset=s * self.n, count=self.n)
            wp.copy(hist_w, self.body_w, dest_offset=s * self.n, count=self.n)
        q = hist_q.numpy().reshape(steps, self.n, 7).astype(np.float64)
        w = hist_w.numpy().reshape(steps, self.n, 3).astype(np.float64)
        return q, w

    def numpy_state(self):
        return tuple(a.numpy().astype(np.float64) for a in self.state())


def rigid_body_invariants(pose, w, inertia):
    """Float64 rotational kinetic energy and world angular momentum (about the centre) of float32
    states: pose (..., 7), w (..., 3) world, inertia broadcastable to (..., 3)."""
    shape = w.shape
    rot = Rotation.from_quat(pose[..., 3:].reshape(-1, 4))
    w_body = rot.inv().apply(w.reshape(-1, 3)).reshape(shape)
    pi = w_body * inertia
    energy = 0.5 * np.sum(w_body * pi, axis=-1)
    spin = rot.apply(pi.reshape(-1, 3)).reshape(shape)
    return energy, spin


def quat_distance(a, b):
    """Distance between unit quaternions up to sign."""
    return np.minimum(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))


# -------------------------------------------------------------------------------------------------
# Translation
# -------------------------------------------------------------------------------------------------


def test_free_fall_and_projectile(device, scalar):
    """Symplectic Euler under a constant acceleration a = f/m + g has the exact discrete solution
    v_n = v_0 + n dt a, x_n = x_0 + n dt v_0 + dt^2 a n (n + 1) / 2, which is the continuous
    x_0 + t v_0 + a t^2 / 2 plus exactly a t dt / 2 (first order in dt)."""
    g = np.array([0.0, 0.0, -9.81])
    x0 = np.array([[0.0, 0.0, 10.0], [1.0, -2.0, 0.5], [-3.0, 1.0, 2.0]])
    v0 = np.array([[0.0, 0.0, 0.0], [3.0, 1.0, 4.0], [-1.0, 0.5, 2.0]])
    inv_mass = np.array([1.0, 0.25, 2.0])
    force = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, -0.5, 3.0]])  # body 2: thrust as well
    bodies = Bodies(
        device, x0, IDENTITY, v0, 0.0, inv_mass, (1.0, 1.0, 1.0), BODY_FREE, f=force, gravity=g, scalar=scalar
    )
    eps = bodies.eps
    dt, steps = 1.0e-3, 800
    bodies.run(steps, dt)
    pose, v, w = bodies.numpy_state()

    a = force * inv_mass[:, None] + g
    t = steps * dt
    v_exact = v0 + t * a
    x_discrete = x0 + t * v0 + dt * dt * a * steps * (steps + 1) / 2
    x_continuous = x0 + t * v0 + 0.5 * a * t * t
    # Accumulation: `steps` additions, each rounded at eps times the size of the sum. In float64 that is
    # 8e-13 m; gravity 1e-4 off is 6e-4 m away.
    scale = np.abs(x_discrete).max() + 1.0
    np.testing.assert_allclose(v, v_exact, rtol=0, atol=steps * eps * (np.abs(v_exact).max() + 1.0))
    np.testing.assert_allclose(pose[:, :3], x_discrete, rtol=0, atol=steps * eps * scale)
    # Against the continuous solution: off by exactly a t dt / 2 = O(dt).
    np.testing.assert_allclose(pose[:, :3] - x_continuous, 0.5 * a * t * dt, rtol=0, atol=steps * eps * scale)
    assert np.all(np.abs(pose[:, :3] - x_continuous) <= 0.5 * np.abs(a) * t * dt + steps * eps * scale)
    # No torque, no spin: the orientation stays put.
    np.testing.assert_array_equal(pose[:, 3:], np.tile(IDENTITY, (3, 1)))
    np.testing.assert_array_equal(w, 0.0)


# -------------------------------------------------------------------------------------------------
# Fixed and kinematic bodies
# -------------------------------------------------------------------------------------------------


def test_fixed_bodies_do_not_move(device, scalar):
    rng = np.random.default_rng(3)
    n = 4
    x0 = rng.normal(size=(n, 3))
    q0 = Rotation.random(n, random_state=4).as_quat()
    v0 = rng.normal(size=(n, 3))  # ignored for a fixed body, and left as it was
    w0 = rng.normal(size=(n, 3))
    bodies = Bodies(
        device,
        x0,
        q0,
        v0,
        w0,
        0.0,
        (1.0, 2.0, 3.0),
        BODY_FIXED,
        f=rng.normal(size=(n, 3)),
        t=rng.normal(size=(n, 3)),
        gravity=(0.0, 0.0, -9.81),
        scalar=scalar,
    )
    before = [a.numpy().copy() for a in bodies.state()]
    bodies.run(50, 1.0e-2)
    for a, b in zip(before, bodies.state(), strict=True):
        np.testing.assert_array_equal(b.numpy(), a)


def test_kinematic_body_follows_its_prescription(device, scalar):
    """Position x_0 + t v, orientation exp(t w) q_0 (world axes); v and w unchanged; forces ignored."""
    x0 = np.array([[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]])
    v = np.array([[0.5, -1.0, 0.25], [0.0, 0.0, 0.0]])
    w = np.array([[0.3, -1.2, 2.0], [0.0, 0.0, 0.0]])  # body 1: resting kinematic body
    q0 = Rotation.from_rotvec([[0.4, 0.1, -0.7], [1.0, 0.0, 0.0]]).as_quat()
    bodies = Bodies(
        device,
        x0,
        q0,
        v,
        w,
        0.0,
        (1.0, 2.0, 3.0),
        BODY_KINEMATIC,
        f=[[100.0, 0.0, 0.0]] * 2,
        t=[[0.0, 50.0, 0.0]] * 2,
        gravity=(0.0, 0.0, -9.81),
        scalar=scalar,
    )
    eps = bodies.eps
    npdt = np.float64 if scalar == wp.float64 else np.float32
    dt, steps = 1.0e-2, 1000
    q_hist, w_hist = bodies.run(steps, dt, record=True)
    pose, v_now, w_now = bodies.numpy_state()

    np.testing.assert_array_equal(v_now, v.astype(npdt))
    np.testing.assert_array_equal(w_now, w.astype(npdt))
    t = steps * dt
    np.testing.assert_allclose(pose[:, :3], x0 + t * v, rtol=0, atol=steps * eps * 10.0)
    np.testing.assert_array_equal(pose[1], np.concatenate([x0[1], q0[1]]).astype(npdt))
    # Orientation after every step against the exact rotation; rounding adds up over the steps.
    times = dt * np.arange(1, steps + 1)
    exact = (Rotation.from_rotvec(times[:, None] * w[0]) * Rotation.from_quat(q0[0])).as_quat()
    err = quat_distance(q_hist[:, 0, 3:], exact)
    assert err.max() < 4.0 * steps * eps, err.max()
    assert np.abs(np.linalg.norm(q_hist[:, :, 3:], axis=-1) - 1.0).max() < 4.0 * eps


# -------------------------------------------------------------------------------------------------
# Rotation
# -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("inertia", [(2.0, 2.0, 2.0), (1.0, 2.0, 3.0)])
def test_constant_torque_gives_linear_angular_momentum(device, inertia, scalar):
    """dL/dt = tau in world axes for any body; the kick adds dt tau and the drift keeps the world L,
    so L_n = L_0 + n dt tau up to rounding. For the sphere-like body also w = L / I."""
    tau = np.array([0.3, -0.2, 0.5])
    w0 = np.array([1.0, 0.5, -0.25])
    q0 = Rotation.from_rotvec([0.3, -0.6, 0.9]).as_quat()
    inertia = np.array(inertia)
    bodies = Bodies(device, [[0.0, 0.0, 0.0]], q0, 0.0, w0, 1.0, inertia, BODY_FREE, t=[tau], scalar=scalar)
    l0 = rigid_body_invariants(np.concatenate([[0.0, 0.0, 0.0], q0])[None], w0[None], inertia)[1][0]
    dt, steps = 2.0e-3, 1000
    bodies.run(steps, dt)
    t = steps * dt

    # Diagnostics kernel: angular momentum about the origin (the body sits at the origin, at rest).
    linear, angular = momentum(*bodies.model(), *bodies.state())
    l_exact = l0 + t * tau
    np.testing.assert_array_equal(linear.numpy(), 0.0)
    # Rounding of 1000 kicks and drifts: measured 107 eps of |L| in float32, 81 in float64.
    eps = bodies.eps
    np.testing.assert_allclose(angular.numpy()[0], l_exact, rtol=0, atol=200.0 * eps * np.linalg.norm(l_exact))
    if np.all(inertia == inertia[0]):
        # Measured 147 eps of |w0| in float32, 100 in float64.
        w_now = bodies.body_w.numpy()[0]
        np.testing.assert_allclose(w_now, l_exact / inertia, rtol=0, atol=1e3 * eps * np.abs(w0).max())


# Torque-free bodies of the long runs: (principal inertia, body-frame angular velocity).
TORQUE_FREE = [
    ((1.0, 2.0, 3.0), (0.01, 1.0, 0.01)),  # near the unstable intermediate axis: flips periodically
    ((1.0, 2.0, 3.0), (0.6, -0.8, 0.5)),  # general spin
    ((13.0 / 12.0, 10.0 / 12.0, 5.0 / 12.0), (-0.7, 0.4, 0.9)),  # a 1 x 2 x 3 brick of 1 kg, general spin
]


def torque_free_bodies(device, dt_omega, scalar=wp.float32):
    """The TORQUE_FREE bodies at random orientations, and dt so that max |w| dt = dt_omega."""
    inertia = np.array([b[0] for b in TORQUE_FREE])
    w_body = np.array([b[1] for b in TORQUE_FREE])
    q0 = Rotation.random(len(TORQUE_FREE), random_state=11).as_quat()
    w0 = Rotation.from_quat(q0).apply(w_body)
    x0 = np.zeros((len(TORQUE_FREE), 3))
    bodies = Bodies(device, x0, q0, 0.0, w0, 1.0, inertia, BODY_FREE, scalar=scalar)
    # The invariants of the initial state as stored, evaluated in float64.
    e0, l0 = rigid_body_invariants(*bodies.numpy_state()[::2], inertia)
    dt = dt_omega / np.linalg.norm(w_body, axis=1).max()
    return bodies, inertia, e0, l0, dt


def test_torque_free_long_run(device, scalar):
    """10^4 steps at |w| dt = 0.03 (about 50 turns; the body near the intermediate axis flips
    several times).

    Angular momentum: every sub-step is an exact rotation, so in exact arithmetic the world L is
    constant. Each step rounds a handful of operations; the integrator removes the biased parts
    (module docstring), leaving a random walk with a per-step spread of about 4 eps relative
    (float32: measured 1.4e-7 to 2.6e-7), i.e. about 4 sqrt(N) eps = 400 eps after N = 10^4 steps
    (measured 268 eps in float32, 186 eps = 2.1e-14 in float64). The tolerance 16 sqrt(N) eps (1e-4
    in float32, 1.8e-13 in float64) is four times that; a bias of a single eps per step would reach
    N eps.

    Energy: the Strang splitting conserves a modified Hamiltonian H + dt^2 H_2 + ..., so the energy
    error stays bounded at O((|w| dt)^2) without drift. H_2 is a sum of double Poisson brackets of the
    H_k = pi_k^2 / (2 I_k) with coefficients 1/24 and 1/12; each bracket is at most of size
    |w|^2 E times an inertia ratio (<= 3 here), so |E(t) - E(0)| <= (|w| dt)^2 E is a safe bound
    (the convergence test below measures the constant at 0.003 to 0.05). Rounding adds the same
    random walk as for L, with the same bound. Drift: the mean energy over the last thousand steps
    equals that over the first thousand to the rounding bound plus 2e-3 (|w| dt)^2 (in float64 the
    splitting's bounded oscillation, not averaged out over a thousand steps, is what is left:
    measured 6.3e-4 (|w| dt)^2; in float32 it hides under the rounding, 421 eps = 2.5e-5), whereas a
    non-symplectic scheme drifts by O(dt^p) per unit time.
    """
    dt_omega, steps = 0.03, 10_000
    bodies, inertia, e0, l0, dt = torque_free_bodies(device, dt_omega, scalar)
    q_hist, w_hist = bodies.run(steps, dt, record=True)
    energy, spin = rigid_body_invariants(q_hist, w_hist, inertia)

    # The near-intermediate-axis body does flip: its angular velocity changes sign along axis 2.
    w_body = Rotation.from_quat(q_hist[:, 0, 3:]).inv().apply(w_hist[:, 0])
    assert w_body[:, 1].max() > 0.9 and w_body[:, 1].min() < -0.9

    rounding = 16.0 * np.sqrt(steps) * bodies.eps
    l_err = np.linalg.norm(spin - l0, axis=-1) / np.linalg.norm(l0, axis=-1)
    assert l_err.max() < rounding, l_err.max(axis=0)

    rel_e = (energy - e0) / e0
    h = dt * np.linalg.norm([b[1] for b in TORQUE_FREE], axis=1)  # |w| dt per body
    assert np.all(np.abs(rel_e).max(axis=0) < h**2 + rounding), np.abs(rel_e).max(axis=0)
    drift = rel_e[-1000:].mean(axis=0) - rel_e[:1000].mean(axis=0)
    assert np.all(np.abs(drift) < 2.0e-3 * h**2 + rounding), drift

    qnorm = np.linalg.norm(q_hist[..., 3:], axis=-1)
    assert np.abs(qnorm - 1.0).max() < 4.0 * bodies.eps

    # The diagnostics kernels agree with the float64 evaluation of the final state (measured 10 and 3
    # eps in float32, 4 and 3 eps in float64).
    e_lin, e_ang = kinetic_energy(*bodies.model(), *bodies.state())
    np.testing.assert_array_equal(e_lin.numpy(), 0.0)
    np.testing.assert_allclose(e_ang.numpy(), energy[-1], rtol=32.0 * bodies.eps)
    _, angular = momentum(*bodies.model(), *bodies.state())
    l_scale = np.linalg.norm(l0, axis=-1).max()
    np.testing.assert_allclose(angular.numpy(), spin[-1], rtol=0, atol=16.0 * bodies.eps * l_scale)


def test_many_float32_spins_keep_their_angular_momentum_unbiased(device):
    """512 bodies of inertia 1:2:3 at random spins and orientations, 10^4 steps at max |w| dt = 0.03, float32.

    The rounded cosine and sine of each sub-rotation scale pi by nearly the same factor every step, a bias
    that grows like N; the drift restores |pi| (module docstring). Over many bodies the random walk of the
    rest averages out and a bias shows: measured spread 203 eps and mean -51 eps of d|L|/|L| (2.0 and
    0.5 sqrt(N) eps); without the restoration 1859 and -938 eps. (float64 rounds its sub-rotations below
    the rest: 161 eps either way, so only float32 can tell.)"""
    nb, steps = 512, 10_000
    rng = np.random.default_rng(1)
    inertia = np.tile([1.0, 2.0, 3.0], (nb, 1))
    w_body = rng.normal(size=(nb, 3))
    q0 = Rotation.random(nb, random_state=3).as_quat()
    bodies = Bodies(device, np.zeros((nb, 3)), q0, 0.0, Rotation.from_quat(q0).apply(w_body), 1.0, inertia, BODY_FREE)
    _, l0 = rigid_body_invariants(*bodies.numpy_state()[::2], inertia)
    bodies.run(steps, 0.03 / np.linalg.norm(w_body, axis=1).max())
    _, l1 = rigid_body_invariants(*bodies.numpy_state()[::2], inertia)
    rel = (np.linalg.norm(l1, axis=-1) - np.linalg.norm(l0, axis=-1)) / np.linalg.norm(l0, axis=-1)
    walk = np.sqrt(steps) * bodies.eps
    assert rel.std() < 6.0 * walk and abs(rel.mean()) < 2.0 * walk, (rel.std() / walk, rel.mean() / walk)


def test_energy_error_is_second_order(device, scalar):
    """Halving dt divides the maximal energy error over a fixed time by about 4.

    |w| dt = 0.4, 0.2, 0.1 make the splitting error (0.003 to 0.05 times (|w| dt)^2 relative, at
    least 3e-5 at the finest) dominate the float32 rounding (a random walk of about 5e-6 over the
    2000 steps of the finest run). Measured ratios 3.6 to 4.1 in float32, 3.8 to 4.1 in float64."""
    errors = []
    for dt_omega in (0.4, 0.2, 0.1):
        bodies, inertia, e0, _, dt = torque_free_bodies(device, dt_omega, scalar)
        steps = round(200.0 / dt_omega)  # the same time span, 200 rad of the fastest body
        q_hist, w_hist = bodies.run(steps, dt, record=True)
        energy, _ = rigid_body_invariants(q_hist, w_hist, inertia)
        errors.append(np.abs(energy - e0).max(axis=0) / e0)
    errors = np.array(errors)
    ratios = errors[:-1] / errors[1:]
    assert np.all((ratios > 3.0) & (ratios < 5.0)), (errors, ratios)


# -------------------------------------------------------------------------------------------------
# Diagnostics
# -------------------------------------------------------------------------------------------------


def test_kinetic_energy_and_momentum_kernels(device, scalar):
    rng = np.random.default_rng(5)
    n = 6
    x = rng.normal(size=(n, 3))
    q = Rotation.random(n, random_state=6).as_quat()
    v = rng.normal(size=(n, 3))
    w = rng.normal(size=(n, 3))
    inv_mass = rng.uniform(0.5, 2.0, size=n)
    inertia = rng.uniform(0.5, 2.0, size=(n, 3))
    flags = np.array([BODY_FREE, BODY_FREE, BODY_FIXED, BODY_KINEMATIC, BODY_FREE, BODY_FREE])
    inv_mass[2:4] = 0.0
    bodies = Bodies(device, x, q, v, w, inv_mass, inertia, flags, scalar=scalar)
    # The reference in float64 from the state as stored (float32 or float64).
    pose, v_s, w_s = bodies.numpy_state()
    inv_mass_s = bodies.body_inv_mass.numpy().astype(np.float64)
    m = 1.0 / np.where(inv_mass_s > 0.0, inv_mass_s, 1.0)
    free = flags == BODY_FREE
    eps = bodies.eps

    e_rot, spin = rigid_body_invariants(pose, w_s, bodies.body_inertia.numpy().astype(np.float64))
    e_lin_ref = np.where(free, 0.5 * m * np.sum(v_s * v_s, axis=1), 0.0)
    e_ang_ref = np.where(free, e_rot, 0.0)
    e_lin, e_ang = kinetic_energy(*bodies.model(), *bodies.state())
    # A few roundings of a few operations each: 16 eps (1e-6 in float32).
    np.testing.assert_allclose(e_lin.numpy(), e_lin_ref, rtol=16.0 * eps)
    np.testing.assert_allclose(e_ang.numpy(), e_ang_ref, rtol=16.0 * eps)

    p_ref = np.where(free[:, None], m[:, None] * v_s, 0.0)
    l_ref = np.where(free[:, None], np.cross(pose[:, :3], p_ref) + spin, 0.0)
    linear, angular = momentum(*bodies.model(), *bodies.state())
    scale = np.abs(l_ref).max()
    np.testing.assert_allclose(linear.numpy(), p_ref, rtol=16.0 * eps, atol=16.0 * eps * np.abs(p_ref).max())
    np.testing.assert_allclose(angular.numpy(), l_ref, rtol=0, atol=64.0 * eps * scale)


def test_check_finite_names_the_first_bad_body(device):
    n = 8
    bodies = Bodies(device, np.zeros((n, 3)), IDENTITY, 0.0, 0.0, 1.0, (1.0, 1.0, 1.0), BODY_FREE)
    flag, first = check_finite(*bodies.state())
    assert flag.numpy()[0] == 0 and first.numpy()[0] == NO_BODY

    # A NaN torque on body 5 and an infinite velocity on body 6 poison them through a step.
    t = np.zeros((n, 3), dtype=np.float32)
    t[5, 1] = np.nan
    bodies.body_t = wp.array(t, dtype=wp.vec3, device=device)
    v = np.zeros((n, 3), dtype=np.float32)
    v[6, 0] = np.inf
    bodies.body_v = wp.array(v, dtype=wp.vec3, device=device)
    bodies.step(1.0e-3)
    check_finite(*bodies.state(), flag=flag, first_body=first)
    assert flag.numpy()[0] == 1 and first.numpy()[0] == 5

    # The given arrays are sticky until reset; each state array is checked.
    reset_finite_check(flag, first)
    assert flag.numpy()[0] == 0 and first.numpy()[0] == NO_BODY
    for name, index, component in (("body_q", 3, 6), ("body_q", 2, 0), ("body_w", 7, 2)):
        clean = Bodies(device, np.zeros((n, 3)), IDENTITY, 0.0, 0.0, 1.0, (1.0, 1.0, 1.0), BODY_FREE)
        a = getattr(clean, name).numpy().copy()
        a[index, component] = np.nan
        setattr(clean, name, wp.array(a, dtype=getattr(clean, name).dtype, device=device))
        flag, first = check_finite(*clean.state())
        assert flag.numpy()[0] == 1 and first.numpy()[0] == index, name
