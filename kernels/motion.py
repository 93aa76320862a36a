"""Prescribed motions of containers: vibration and taps (issue 26).

A motion moves a set of kinematic bodies (a container's slabs) together along a unit ``axis`` by a
displacement ``d(t)`` taken from the step counter on the device, so that a captured CUDA graph
replays it without the host. Each cycle of the motion is one period of

    d(s) = A (1 - cos(w s)),   v(s) = A w sin(w s),   a(s) = A w^2 cos(w s),   0 <= s < 2 pi / w,

which starts and ends at rest in place (the velocity is continuous, the container returns to where
it was), lifts by 2 A at mid-cycle and reaches the peak acceleration ``A w^2 = Gamma g`` at its ends
(upwards) and its middle (downwards: the grains leave the floor there where Gamma > 1). Cycles start
every ``period`` seconds from ``start``: a period of one cycle is a continuous vibration, a longer one
a train of taps with the container at rest between them; ``count`` cycles in all (0: no end).

The pose is set from d(t) each step (never summed from velocities, so nothing drifts over 1e6 steps)
and the velocity from v(t), which the contact forces use for the wall's relative velocity.
"""

import math

import warp as wp

__all__ = ["cycle_displacement", "launch_drive_bodies", "make_motion_kernels"]


@wp.func
def cycle_displacement(
    t: wp.float64, amplitude: wp.float64, omega: wp.float64, start: wp.float64, period: wp.float64, count: int
):
    # (d, v) of the motion at time t: the cycle under way, or rest before, between and after the cycles.
    zero = wp.float64(0.0)
    tau = t - start
    if tau < zero:
        return wp.vec2d(zero, zero)
    k = wp.floor(tau / period)
    if count > 0 and k >= wp.float64(count):
        return wp.vec2d(zero, zero)
    s = tau - k * period
    if s * omega >= wp.float64(2.0 * math.pi):
        return wp.vec2d(zero, zero)
    phase = omega * s
    return wp.vec2d(amplitude * (wp.float64(1.0) - wp.cos(phase)), amplitude * omega * wp.sin(phase))


def make_motion_kernels(scalar):
    """The drive kernel for poses in ``scalar`` (wp.float32 or wp.float64): each driven
    row with the index of its motion (-1: not driven) and its position at rest."""
    vec3 = wp.types.vector(3, scalar)
    transform = wp.types.transformation(scalar)

    @wp.kernel(enable_backward=False)
    def drive_kernel(
        # Model
        row_motion: wp.array(dtype=int),
        row_rest: wp.array(dtype=wp.vec3d),
        motion_axis: wp.array(dtype=wp.vec3d),
        motion_amplitude: wp.array(dtype=wp.float64),
        motion_omega: wp.array(dtype=wp.float64),
        motion_start: wp.array(dtype=wp.float64),
        motion_period: wp.array(dtype=wp.float64),
        motion_count: wp.array(dtype=int),
        # State in
        step_count: wp.array(dtype=int),
        step_offset: int,
        dt: wp.float64,
        # Out
        row_q: wp.array(dtype=transform),
        row_v: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        m = row_motion[i]
        if m < 0:
            return
        t = wp.float64(step_count[0] + step_offset) * dt
        dv = cycle_displacement(t, motion_amplitude[m], motion_omega[m], motion_start[m], motion_period[m],
                                motion_count[m])  # fmt: skip
        u = motion_axis[m]
        x = row_rest[i] + u * dv[0]
        row_q[i] = transform(vec3(scalar(x[0]), scalar(x[1]), scalar(x[2])), wp.transform_get_rotation(row_q[i]))
        v = u * dv[1]
        row_v[i] = vec3(scalar(v[0]), scalar(v[1]), scalar(v[2]))

    return drive_kernel


_KERNELS = {}


def _kernels(scalar):
    key = wp.types.type_repr(scalar)
    if key not in _KERNELS:
        _KERNELS[key] = make_motion_kernels(scalar)
    return _KERNELS[key]


def _scalar_of(q):
    return wp.float64 if wp.types.types_equal(q.dtype, wp.transformd) else wp.float32


def launch_drive_bodies(motions, body_motion, body_rest, step_count, step_offset, dt, body_q, body_v, device=None):
    """Set the pose and velocity of each driven body (``body_motion`` >= 0) from its motion at time
    ``(step_count[0] + step_offset) * dt``. ``motions``: the six motion arrays (axis, amplitude, omega,
    start, period, count); ``body_rest``: (N,) vec3d the body's position at rest [m]."""
    kernel = _kernels(_scalar_of(body_q))
    wp.launch(kernel, dim=len(body_motion), inputs=[body_motion, body_rest, *motions, step_count, int(step_offset),
              float(dt)], outputs=[body_q, body_v], device=device)  # fmt: skip
