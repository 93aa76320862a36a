"""Time integration of the rigid bodies: a symplectic kick-drift step for translation and rotation.

State (one entry per body; float32, or float64 in the "mixed" and "float64" precisions of
:mod:`polydem.kernels.precision`): ``body_q`` transform (centroid position [m], unit quaternion
xyzw from the body frame, i.e. the principal axes, to the world), ``body_v`` linear velocity [m/s],
``body_w`` angular velocity in world axes [rad/s]. The force stage accumulates ``body_f`` [N] and
``body_t`` (torque about the centroid, world axes) [N m]; gravity is added here.

One step of length ``dt`` for a free body (``body_flags == BODY_FREE``):

Translation, symplectic Euler::

    v <- v + dt (f / m + g)
    x <- x + dt v

Rotation, kick then drift. With R the rotation of q, I the diagonal principal inertia and
pi = I R^T w the angular momentum in body axes (so L = R pi in world axes):

1. kick: pi <- I R^T w + dt R^T tau (the world momentum L gains dt tau);
2. drift: the free rigid body H = sum_k pi_k^2 / (2 I_k) is split into the three terms
   H_k = pi_k^2 / (2 I_k). The flow of H_k for a time h is exact and elementary: a rotation about
   body axis k by the angle theta = h pi_k / I_k (pi_k itself is constant along it), which turns
   the orientation R <- R Rot_k(theta) and the body momentum pi <- Rot_k(theta)^T pi. The drift is
   the symmetric (Strang) composition

       H_1 for dt/2, H_2 for dt/2, H_3 for dt, H_2 for dt/2, H_1 for dt/2

   (Dullweber, Leimkuhler and McLachlan, J. Chem. Phys. 107, 5840 (1997); the rotational part of
   NO_SQUISH by Miller et al. 2002 is the same splitting written with quaternions);
3. w <- R I^-1 pi with the new R.

Every sub-step is an exact rotation, so the world angular momentum L = R pi is unchanged by the
drift and |pi| = |L| is unchanged by every sub-step: a torque-free body keeps L exactly in exact
arithmetic (here: up to rounding), and the gyroscopic term of Euler's equations is
contained in the drift without any iteration. The splitting is symmetric, hence second order for
the free rigid body: it exactly conserves a modified energy H + O(dt^2), so the energy error of a
torque-free body stays bounded at O((|w| dt)^2) relative without drift over long runs. The map
is symplectic and time reversible.

Order with forces: kick-drift is symplectic Euler. Read with the velocities as mid-step values
(v_{n+1/2}, L_{n+1/2}) it is the Stormer-Verlet / leapfrog scheme, second order for positions
and orientations; read synchronously it is first order, e.g. a free fall gives
x_n = x_0 + t v_0 + g t^2 / 2 + g t dt / 2.

Rounding details (float32; the same code runs in float64, see :func:`make_integrator`). Rounding
along a smooth trajectory is correlated from step to step, so an error of 1e-7 relative made the
same way every step would add up linearly (1e-3 after 10^4 steps). Two places did that and are
treated:

* the cosine and sine of each sub-rotation angle are rounded, so they turn pi by a matrix whose
  scale is 1 only to rounding, nearly the same scale every step for a steady spin. The drift
  therefore restores |pi| to its value before the sub-steps (the exact flow keeps it);
* the state stores w, not pi, and the map pi -> w = R I^-1 pi -> I R^T w is the identity only to
  rounding (1/I_k, |q| = 1 to rounding). The new w gets one correction, computed with the very
  function that rebuilds pi at the start of the next step, so the round trip returns pi to
  rounding of w itself.

What remains is unbiased: a torque-free body keeps |L| and L to about 3e-7 * sqrt(steps)
relative (a random walk of a few float32 units per step; BENCHMARKS.md, "Design measurements",
has the drift with and without the two treatments). The five sub-rotations are composed
into one quaternion applied to q once, and q is renormalised every step.

A principal moment I_k = 0 locks the rotation about that axis (I_k^-1 is taken as 0).

Fixed bodies (``BODY_FIXED``) keep their state unchanged. Kinematic bodies (``BODY_KINEMATIC``) keep
their prescribed v and w; their position advances by v dt and their orientation by the exact
rotation exp(w dt) (about world axes), and forces and gravity are ignored. A kinematic body with a
pivot p (a part of a drum) turns about it instead: x <- p + exp(w dt)(x - p), v = w x (x - p).

After the integration the step counts itself and checks its state on the device (finite; each
body's fastest point against its speed limit); a settling run measures the free bodies' energies and
largest speed here too.

Layout of this file: ``@wp.func`` helpers, the kernels, then the plain launch functions.
"""

import functools
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, Protocol

import warp as wp
from polydem.kernels.structs import bodies_struct, body_model_struct, filled

BODY_FREE = wp.constant(0)
BODY_FIXED = wp.constant(1)
BODY_KINEMATIC = wp.constant(2)


class BodyModel(Protocol):
    """What the integration, the check and the settle measures read of a model (:class:`polydem.model.Model`):
    the bodies' static arrays in their struct (``bodies``, :func:`polydem.kernels.structs.body_model_struct`:
    flags, inverse masses, principal inertias, bounding radii [m], pivots), and the gravity (three numbers
    [m/s^2])."""

    bodies: Any
    gravity: Iterable[float]


class BodyMotion(Protocol):
    """The bodies' arrays in their struct (``bodies``, :func:`polydem.kernels.structs.bodies_struct`: poses,
    velocities, forces and torques; :class:`polydem.state.State`)."""

    bodies: Any


@dataclass(frozen=True)
class Integrator:
    """The integrator's functions and kernels in one scalar (``wp.float32`` or ``wp.float64``)."""

    scalar: Any
    vec3: Any
    quat: Any
    transform: Any
    BodyModel: Any
    Bodies: Any
    body_momentum: Any
    angular_velocity: Any
    body_kinetic_energy: Any
    free_body_step: Any
    integrate_body: Any
    integrate_bodies_kernel: Any
    kinetic_energy_kernel: Any


@functools.cache
def make_integrator(scalar) -> Integrator:
    """The helpers and kernels of this module, with every float in ``scalar``."""
    vec3 = wp.types.vector(3, scalar)
    quat = wp.types.quaternion(scalar)
    transform = wp.types.transformation(scalar)
    BodyModel = body_model_struct(scalar)
    Bodies = bodies_struct(scalar)

    # -----------------------------------------------------------------------------------------
    # Helpers

    @wp.func
    def quat_exp(v: vec3):
        # Unit quaternion of the rotation vector v (angle |v| [rad] about v / |v|), smooth at v = 0.
        theta = wp.length(v)
        half = scalar(0.5) * theta
        # sin(half) / theta by its series below 1e-3, where the truncation error is ~1e-14.
        s = scalar(0.5) * (scalar(1.0) - half * half / scalar(6.0))
        if half >= scalar(1.0e-3):
            s = wp.sin(half) / theta
        return quat(v[0] * s, v[1] * s, v[2] * s, wp.cos(half))

    @wp.func
    def safe_inv(x: scalar):
        # 1 / x for x > 0, else 0 (a zero principal moment locks rotation about that axis).
        r = scalar(0.0)
        if x > scalar(0.0):
            r = scalar(1.0) / x
        return r

    @wp.func
    def principal_rotation(axis: int, h: scalar, pi: vec3, inv_inertia: vec3, dq: quat):
        # Exact flow for time h of H_axis = pi_axis^2 / (2 I_axis): the body turns about its principal
        # axis `axis` by theta = h pi_axis / I_axis. Returns the body momentum Rot(theta)^T pi and the
        # accumulated body-frame rotation dq * Rot(theta).
        b = (axis + 1) % 3
        c = (axis + 2) % 3
        theta = h * pi[axis] * inv_inertia[axis]
        sh = wp.sin(scalar(0.5) * theta)
        ch = wp.cos(scalar(0.5) * theta)
        # cos and sin of theta from the half angle: the same rotation as the quaternion below.
        cs = scalar(1.0) - scalar(2.0) * sh * sh
        sn = scalar(2.0) * sh * ch
        out = pi
        out[b] = cs * pi[b] + sn * pi[c]
        out[c] = cs * pi[c] - sn * pi[b]
        r = quat(scalar(0.0), scalar(0.0), scalar(0.0), ch)
        r[axis] = sh
        return out, dq * r

    @wp.func
    def free_rotor_drift(pi: vec3, inv_inertia: vec3, dt: scalar):
        # Strang splitting 1(dt/2) 2(dt/2) 3(dt) 2(dt/2) 1(dt/2) of the free rigid body. Returns the new
        # body momentum and the body-frame rotation dq of the step (new R = R * rot(dq)).
        norm = wp.length(pi)
        dq = wp.quat_identity(dtype=scalar)
        half = scalar(0.5) * dt
        pi, dq = principal_rotation(0, half, pi, inv_inertia, dq)
        pi, dq = principal_rotation(1, half, pi, inv_inertia, dq)
        pi, dq = principal_rotation(2, dt, pi, inv_inertia, dq)
        pi, dq = principal_rotation(1, half, pi, inv_inertia, dq)
        pi, dq = principal_rotation(0, half, pi, inv_inertia, dq)
        # The exact flow keeps |pi|: remove the scale error of the rounded sub-rotations (module docstring).
        n = wp.length(pi)
        if n > scalar(0.0):
            pi = pi + pi * ((norm - n) / n)
        return pi, dq

    @wp.func
    def body_momentum(q: quat, inertia: vec3, w: vec3):
        # pi = I R^T w: angular momentum in body axes of the world angular velocity w.
        return wp.cw_mul(inertia, wp.quat_rotate_inv(q, w))

    @wp.func
    def angular_velocity(q: quat, inertia: vec3, inv_inertia: vec3, pi: vec3):
        # w = R I^-1 pi, corrected once so that body_momentum(q, inertia, w) reproduces pi to rounding:
        # the state stores w, and the next step rebuilds pi from it with body_momentum.
        w = wp.quat_rotate(q, wp.cw_mul(inv_inertia, pi))
        err = pi - body_momentum(q, inertia, w)
        return w + wp.quat_rotate(q, wp.cw_mul(inv_inertia, err))

    @wp.func
    def free_body_step(model: BodyModel, gravity: vec3, dt: scalar, i: int, tf: transform, v: vec3, w: vec3, f: vec3,
                       t: vec3):  # fmt: skip
        # Free body i's pose and velocities after a step under force f and torque t: (pose, velocity, angular
        # velocity). The integrate kernel's, and a decomposed run's for the bodies it sends before the step ends.
        x = wp.transform_get_translation(tf)
        q = wp.transform_get_rotation(tf)
        # Translation: symplectic Euler.
        v_new = v + (f * model.inv_mass[i] + gravity) * dt
        x_new = x + v_new * dt

        # Rotation: kick the body-frame momentum, then drift the free rotor.
        inertia = model.inertia[i]
        inv_inertia = vec3(safe_inv(inertia[0]), safe_inv(inertia[1]), safe_inv(inertia[2]))
        pi = body_momentum(q, inertia, w) + wp.quat_rotate_inv(q, t * dt)
        pi, dq = free_rotor_drift(pi, inv_inertia, dt)
        q_new = wp.normalize(q * dq)
        w_new = angular_velocity(q_new, inertia, inv_inertia, pi)
        return transform(x_new, q_new), v_new, w_new

    # -----------------------------------------------------------------------------------------
    # Kernels

    @wp.func
    def integrate_body(model: BodyModel, gravity: vec3, dt: scalar, bodies: Bodies, i: int):
        # In place: the pose and velocities of body i (from its force and torque).
        flag = model.flags[i]
        if flag == BODY_FIXED:
            return
        tf = bodies.q[i]
        x = wp.transform_get_translation(tf)
        q = wp.transform_get_rotation(tf)
        v = bodies.v[i]
        w = bodies.w[i]

        if flag == BODY_KINEMATIC:
            dq = quat_exp(w * dt)
            q_new = wp.normalize(dq * q)
            x_new = x + v * dt
            v_new = v
            if model.has_pivot != 0:
                p = model.pivot[i]
                if wp.isfinite(p[0] + p[1] + p[2]):
                    # A part of a drum turns about its pivot: its centre goes round, not along a tangent.
                    x_new = p + wp.quat_rotate(dq, x - p)
                    v_new = wp.cross(w, x_new - p)
            bodies.q[i] = transform(x_new, q_new)
            bodies.v[i] = v_new
            return

        tf_new, v_new, w_new = free_body_step(model, gravity, dt, i, tf, v, w, bodies.f[i], bodies.t[i])
        bodies.v[i] = v_new
        bodies.q[i] = tf_new
        bodies.w[i] = w_new

    @wp.kernel(enable_backward=False, module="unique")
    def integrate_bodies_kernel(model: BodyModel, gravity: vec3, dt: scalar, bodies: Bodies):
        # One thread a body.
        integrate_body(model, gravity, dt, bodies, wp.tid())

    @wp.func
    def body_kinetic_energy(inv_mass: scalar, inertia: vec3, q: transform, v: vec3, w: vec3):
        # Translational and rotational kinetic energy [J] of a body of inverse mass > 0 (w in world
        # axes, the inertia about the principal axes of its frame).
        wb = wp.quat_rotate_inv(wp.transform_get_rotation(q), w)
        return scalar(0.5) * wp.dot(v, v) / inv_mass, scalar(0.5) * wp.dot(wb, wp.cw_mul(inertia, wb))

    @wp.kernel(enable_backward=False, module="unique")
    def kinetic_energy_kernel(
        model: BodyModel, bodies: Bodies, energy_lin: wp.array(dtype=scalar), energy_ang: wp.array(dtype=scalar)
    ):
        i = wp.tid()
        e_lin = scalar(0.0)
        e_ang = scalar(0.0)
        inv_mass = model.inv_mass[i]
        if model.flags[i] == BODY_FREE and inv_mass > scalar(0.0):
            e_lin, e_ang = body_kinetic_energy(inv_mass, model.inertia[i], bodies.q[i], bodies.v[i], bodies.w[i])
        energy_lin[i] = e_lin
        energy_ang[i] = e_ang

    return Integrator(
        scalar=scalar,
        vec3=vec3,
        quat=quat,
        transform=transform,
        BodyModel=BodyModel,
        Bodies=Bodies,
        body_momentum=body_momentum,
        angular_velocity=angular_velocity,
        body_kinetic_energy=body_kinetic_energy,
        free_body_step=free_body_step,
        integrate_body=integrate_body,
        integrate_bodies_kernel=integrate_bodies_kernel,
        kinetic_energy_kernel=kinetic_energy_kernel,
    )


# The float32 helpers, for callers that build their own float32 kernels (the tests do).
body_momentum = make_integrator(wp.float32).body_momentum


# ---------------------------------------------------------------------------------------------
# After the step: its count and its check; the measures of a settling run


@functools.cache
def make_check_body(scalar):
    """The check of one body's state in ``scalar`` (a ``wp.func``): see :func:`make_check_state_kernel`."""

    @wp.func
    def check_body(
        model: body_model_struct(scalar),
        body_speed_limit: wp.array(dtype=float),
        step_now: int,
        bodies: bodies_struct(scalar),
        i: int,
        bad_step: wp.array(dtype=int),
        body_peak_speed: wp.array(dtype=float),
        too_fast: wp.array(dtype=int),
    ):
        speed = float(wp.length(bodies.v[i]) + wp.length(bodies.w[i]) * scalar(model.radius[i]))
        # One thread per body: a plain running maximum, no atomics.
        if speed > body_peak_speed[i]:
            body_peak_speed[i] = speed
        if speed > body_speed_limit[i]:
            wp.atomic_max(too_fast, 0, 1)
        q = bodies.q[i]
        p = wp.transform_get_translation(q)
        r = wp.transform_get_rotation(q)
        v = bodies.v[i]
        w = bodies.w[i]
        total = p[0] + p[1] + p[2] + r[0] + r[1] + r[2] + r[3] + v[0] + v[1] + v[2] + w[0] + w[1] + w[2]
        if not wp.isfinite(total):
            wp.atomic_min(bad_step, 0, step_now)

    return check_body


@functools.cache
def make_check_state_kernel(scalar):
    """The check of a state in ``scalar``: finiteness, and each body's peak speed against its limit."""
    check_body = make_check_body(scalar)

    @wp.kernel(enable_backward=False, module="unique")
    def check_state_kernel(
        # Model
        model: body_model_struct(scalar),
        body_speed_limit: wp.array(dtype=float),
        # State in
        step: wp.array(dtype=int),
        bodies: bodies_struct(scalar),
        # Out
        bad_step: wp.array(dtype=int),
        body_peak_speed: wp.array(dtype=float),
        too_fast: wp.array(dtype=int),
    ):
        """Records (atomic min) the first step at which a body's state is not finite, each body's
        largest speed of its fastest point (|v| + |w| r), and whether one went above its speed limit."""
        check_body(model, body_speed_limit, step[0], bodies, wp.tid(), bad_step, body_peak_speed, too_fast)

    return check_state_kernel


@functools.cache
def make_integrate_check_kernel(scalar):
    """The integration and the check of a step in one kernel (a launch less a step; the same bits as
    integrate_bodies_kernel, the step's count, then check_state_kernel): for a step with nothing between them (no
    motion driving bodies). The check records the step as the count will be, ``step[0] + 1``."""
    ig = make_integrator(scalar)
    check_body = make_check_body(scalar)

    @wp.kernel(enable_backward=False, module="unique")
    def integrate_check_kernel(
        # Model
        model: body_model_struct(scalar),
        gravity: ig.vec3,
        dt: scalar,
        body_speed_limit: wp.array(dtype=float),
        # State in/out
        bodies: bodies_struct(scalar),
        step: wp.array(dtype=int),
        # Out
        bad_step: wp.array(dtype=int),
        body_peak_speed: wp.array(dtype=float),
        too_fast: wp.array(dtype=int),
    ):
        i = wp.tid()
        ig.integrate_body(model, gravity, dt, bodies, i)
        check_body(model, body_speed_limit, step[0] + 1, bodies, i, bad_step, body_peak_speed, too_fast)

    return integrate_check_kernel


@functools.cache
def make_settle_measures_kernel(scalar):
    """Per free body, in float64: kinetic and gravitational energy; the largest speed of a fastest point."""
    ig = make_integrator(scalar)

    @wp.kernel(enable_backward=False, module="unique")
    def settle_measures_kernel(
        # Model
        model: ig.BodyModel,
        gravity: wp.vec3d,
        # State in
        bodies: ig.Bodies,
        # Out
        body_kinetic: wp.array(dtype=wp.float64),
        body_gravity: wp.array(dtype=wp.float64),
        largest_speed: wp.array(dtype=wp.float64),
    ):
        """Zero for fixed, kinematic and infinite-mass bodies (driven from outside the pile); the
        speeds go into one running maximum (atomic: a maximum does not depend on the order)."""
        i = wp.tid()
        inv_mass = model.inv_mass[i]
        body_kinetic[i] = wp.float64(0.0)
        body_gravity[i] = wp.float64(0.0)
        if model.flags[i] == 0 and inv_mass > scalar(0.0):
            v = bodies.v[i]
            w = bodies.w[i]
            speed = wp.float64(wp.length(v)) + wp.float64(wp.length(w)) * wp.float64(model.radius[i])
            wp.atomic_max(largest_speed, 0, speed)
            q = bodies.q[i]
            e_lin, e_ang = ig.body_kinetic_energy(inv_mass, model.inertia[i], q, v, w)
            body_kinetic[i] = wp.float64(e_lin + e_ang)
            x = wp.transform_get_translation(q)
            mass = wp.float64(1.0) / wp.float64(inv_mass)
            h = wp.float64(x[0]) * gravity[0] + wp.float64(x[1]) * gravity[1] + wp.float64(x[2]) * gravity[2]
            body_gravity[i] = -mass * h

    return settle_measures_kernel


@wp.kernel(enable_backward=False)
def advance_step_kernel(step: wp.array(dtype=int)):
    step[0] = step[0] + 1


# ---------------------------------------------------------------------------------------------
# Launch functions
# ---------------------------------------------------------------------------------------------


def _device(device, array):
    return array.device if device is None else wp.get_device(device)


def _pose_scalar(body_q):
    # The scalar of the poses (float32 or float64 transforms): that of the state's kernels.
    return wp.float64 if wp.types.types_equal(body_q.dtype, wp.transformd) else wp.float32


def _integrator(body_q):
    return make_integrator(_pose_scalar(body_q))


def body_structs(
    body_inv_mass, body_inertia, body_flags, body_q, body_v, body_w, body_f=None, body_t=None, body_pivot=None
):
    """The structs (:func:`polydem.kernels.structs.body_model_struct`, :func:`~polydem.kernels.structs.bodies_struct`)
    of loose arrays, for the functions below that take them so (a Model and a State have theirs)."""
    scalar = _pose_scalar(body_q)
    has_pivot = int(body_pivot is not None)
    masses = {"inv_mass": body_inv_mass, "inertia": body_inertia, "flags": body_flags}
    model = filled(body_model_struct(scalar), **masses, pivot=body_pivot, has_pivot=has_pivot)
    return model, filled(bodies_struct(scalar), q=body_q, v=body_v, w=body_w, f=body_f, t=body_t)


def launch_integrate(*, model: BodyModel, state: BodyMotion, dt: float) -> None:
    """Advance every body of ``state`` by one step of length ``dt`` under its force and torque and the
    model's gravity, in place (the scheme: the module docstring). Capturable in a CUDA graph: a kinematic
    body with a pivot (``has_pivot``) turns about it; without pivots the null array is never read, so a
    step allocates nothing."""
    _integrate(model.bodies, model.gravity, dt, state.bodies, state.bodies.q.device)


def _integrate(model, gravity, dt, bodies, device):
    ig = _integrator(bodies.q)
    gravity = ig.vec3(*[ig.scalar(float(g)) for g in gravity])
    wp.launch(
        ig.integrate_bodies_kernel,
        dim=bodies.q.shape[0],
        inputs=[model, gravity, ig.scalar(float(dt)), bodies],
        device=device,
    )


def integrate_bodies(
    body_inv_mass,
    body_inertia,
    body_flags,
    gravity,
    body_q,
    body_v,
    body_w,
    body_f,
    body_t,
    dt,
    device=None,
    body_pivot=None,
):
    """Advance every body by one step of length ``dt``, updating the state in place (:func:`launch_integrate`
    on loose arrays).

    Args:
        body_inv_mass: ``(n,)`` inverse masses [1/kg] (0 for fixed and kinematic bodies).
        body_inertia: ``(n,)`` vec3 principal moments of inertia in the body frame [kg m^2].
        body_flags: ``(n,)`` int32, ``BODY_FREE`` (0), ``BODY_FIXED`` (1) or ``BODY_KINEMATIC`` (2).
        gravity: gravitational acceleration [m/s^2], a ``wp.vec3`` or three numbers.
        body_q: ``(n,)`` transform, centroid position [m] and unit quaternion xyzw (in/out).
        body_v: ``(n,)`` vec3 linear velocity [m/s] (in/out).
        body_w: ``(n,)`` vec3 angular velocity, world axes [rad/s] (in/out).
        body_f: ``(n,)`` vec3 total contact/external force without gravity [N].
        body_t: ``(n,)`` vec3 torque about the centroid, world axes [N m].
        dt: time step [s].
        device: Warp device; defaults to the device of ``body_q``.
        body_pivot: optional ``(n,)`` vec3 [m]: a kinematic body with a finite pivot turns about it
            (x <- p + R(w dt)(x - p), v = w x (x - p)) instead of moving along its velocity.

    The scheme (symplectic Euler for translation; momentum kick and Strang-split free-rotor
    drift for rotation) is described in the module docstring. Every float array is in the scalar of
    ``body_q`` (float32 or float64 transforms).
    """
    model, bodies = body_structs(
        body_inv_mass, body_inertia, body_flags, body_q, body_v, body_w, body_f, body_t, body_pivot
    )
    _integrate(model, gravity, dt, bodies, _device(device, body_q))


def kinetic_energy(
    body_inv_mass,
    body_inertia,
    body_flags,
    body_q,
    body_v,
    body_w,
    energy_lin=None,
    energy_ang=None,
    device=None,
):
    """Per-body kinetic energy, translational m |v|^2 / 2 and rotational w . R I R^T w / 2 [J].

    Arguments as in :func:`integrate_bodies`; ``energy_lin`` and ``energy_ang`` are optional
    ``(n,)`` output arrays in the scalar of ``body_q`` (allocated when None). Fixed, kinematic and infinite-mass
    bodies are driven from outside the system and count 0.

    Returns:
        ``(energy_lin, energy_ang)``, two ``(n,)`` Warp arrays [J].
    """
    device = _device(device, body_q)
    ig = _integrator(body_q)
    n = body_q.shape[0]
    if energy_lin is None:
        energy_lin = wp.empty(n, dtype=ig.scalar, device=device)
    if energy_ang is None:
        energy_ang = wp.empty(n, dtype=ig.scalar, device=device)
    model, bodies = body_structs(body_inv_mass, body_inertia, body_flags, body_q, body_v, body_w)
    wp.launch(ig.kinetic_energy_kernel, dim=n, inputs=[model, bodies], outputs=[energy_lin, energy_ang], device=device)
    return energy_lin, energy_ang


def launch_count_step(step_count: wp.array) -> None:
    """Add one to ``step_count`` (1,) on the device: a captured step counts itself."""
    wp.launch(advance_step_kernel, dim=1, inputs=[step_count], device=step_count.device)


def launch_check_state(
    *,
    model: BodyModel,
    state: BodyMotion,
    step_count: wp.array,
    body_speed_limit: wp.array,
    bad_step: wp.array,
    body_peak_speed: wp.array,
    too_fast: wp.array,
) -> None:
    """Check the state after a step: ``bad_step`` (1,) lowered to ``step_count[0]`` where a body's state is
    not finite; ``body_peak_speed`` (N,) float32 raised to the speed of each body's fastest point
    (``|v| + |w| r``, r its bounding radius) [m/s]; ``too_fast`` (1,) set where one is above
    ``body_speed_limit``. The kernel is in the scalar of ``state.body_q``."""
    bodies = state.bodies
    wp.launch(
        make_check_state_kernel(_pose_scalar(bodies.q)),
        dim=bodies.q.shape[0],
        inputs=[model.bodies, body_speed_limit, step_count, bodies],
        outputs=[bad_step, body_peak_speed, too_fast],
        device=bodies.q.device,
    )


def launch_integrate_and_check(
    *,
    model: BodyModel,
    state: BodyMotion,
    dt: float,
    step_count: wp.array,
    body_speed_limit: wp.array,
    bad_step: wp.array,
    body_peak_speed: wp.array,
    too_fast: wp.array,
) -> None:
    """:func:`launch_integrate` and then :func:`launch_check_state` in one launch, the check taking the step as
    ``step_count[0] + 1`` (what :func:`launch_count_step`, launched after this, makes it): for a step that moves
    no body between the two (no motions). The same bits as the two launches."""
    bodies = state.bodies
    ig = _integrator(bodies.q)
    gravity = ig.vec3(*[ig.scalar(float(g)) for g in model.gravity])
    wp.launch(
        make_integrate_check_kernel(_pose_scalar(bodies.q)),
        dim=bodies.q.shape[0],
        inputs=[model.bodies, gravity, ig.scalar(float(dt)), body_speed_limit, bodies, step_count],
        outputs=[bad_step, body_peak_speed, too_fast],
        device=bodies.q.device,
    )


def launch_settle_measures(
    *,
    model: BodyModel,
    state: BodyMotion,
    body_kinetic: wp.array,
    body_gravity: wp.array,
    largest_speed: wp.array,
) -> None:
    """Per free body, in float64: its kinetic energy into ``body_kinetic`` (N,) and its gravitational
    energy ``-m g.x`` into ``body_gravity`` (N,) [J] (zero for the other bodies); ``largest_speed``
    (1,) raised to the speed of the fastest point of a free body [m/s]. The kernel is in the scalar of
    ``state.body_q``."""
    bodies = state.bodies
    wp.launch(
        make_settle_measures_kernel(_pose_scalar(bodies.q)),
        dim=bodies.q.shape[0],
        inputs=[model.bodies, wp.vec3d(*(float(g) for g in model.gravity)), bodies],
        outputs=[body_kinetic, body_gravity, largest_speed],
        device=bodies.q.device,
    )
