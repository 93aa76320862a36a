"""Recorder stage: one frame of the bodies as the output files store it, made on the device (issue 27).

A frame of a USD file is float32 positions in file units, unit float32 (or half) quaternions xyzw and,
optionally, float32 velocities in file units per second of playback and angular velocities in degrees per
second of playback. Converting the state on the host (``Simulation.state()``, float64 copies, then float32
copies, then the file's arrays) held a frame several times over in host memory: about 250 bytes a body against
the 20-60 the file keeps, which at 1e8 bodies is 25 GB for one frame. Here the device writes the file's arrays
directly, so that the host sees each of them once, one at a time.

The arithmetic is the host path's, in the same order and precisions: positions and velocities scaled in float64
and rounded to float32; the quaternion rounded to float32, divided by its float32 norm and turned to the sign
nearest the previous frame's (so that interpolation between frames turns the short way).
"""

import functools

import warp as wp

__all__ = ["launch_frame", "make_frame_kernel"]


@functools.cache
def make_frame_kernel(scalar):
    """The frame kernel for a state of scalar type ``scalar`` (wp.float32 or wp.float64)."""
    transform = wp.types.transformation(scalar)
    vec3 = wp.types.vector(3, scalar)

    @wp.kernel(enable_backward=False, module="unique")
    def frame_kernel(
        # State in
        body_q: wp.array(dtype=transform),
        body_v: wp.array(dtype=vec3),
        body_w: wp.array(dtype=vec3),
        # Settings
        scale: wp.float64,
        velocity_scale: wp.float64,
        angular_scale: wp.float64,
        with_velocities: int,
        align: int,
        # In: the previous frame's quaternions (the caller copies this frame's there once it is written)
        previous: wp.array(dtype=wp.vec4f),
        # Out
        position: wp.array(dtype=wp.vec3f),
        orientation: wp.array(dtype=wp.vec4f),
        velocity: wp.array(dtype=wp.vec3f),
        angular_velocity: wp.array(dtype=wp.vec3f),
    ):
        i = wp.tid()
        x = wp.transform_get_translation(body_q[i])
        position[i] = wp.vec3f(
            wp.float32(wp.float64(x[0]) * scale),
            wp.float32(wp.float64(x[1]) * scale),
            wp.float32(wp.float64(x[2]) * scale),
        )
        r = wp.transform_get_rotation(body_q[i])
        q = wp.vec4f(wp.float32(r[0]), wp.float32(r[1]), wp.float32(r[2]), wp.float32(r[3]))
        norm = wp.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        if norm > wp.float32(0.0):
            q = q / norm
        if align != 0:
            p = previous[i]
            if q[0] * p[0] + q[1] * p[1] + q[2] * p[2] + q[3] * p[3] < wp.float32(0.0):
                q = -q
        orientation[i] = q
        if with_velocities != 0:
            v = body_v[i]
            w = body_w[i]
            velocity[i] = wp.vec3f(
                wp.float32(wp.float64(v[0]) * velocity_scale),
                wp.float32(wp.float64(v[1]) * velocity_scale),
                wp.float32(wp.float64(v[2]) * velocity_scale),
            )
            angular_velocity[i] = wp.vec3f(
                wp.float32(wp.float64(w[0]) * angular_scale),
                wp.float32(wp.float64(w[1]) * angular_scale),
                wp.float32(wp.float64(w[2]) * angular_scale),
            )

    return frame_kernel


def launch_frame(state, scalar, frame, *, scale, velocity_scale, angular_scale, with_velocities, align):
    """Write one frame of ``state`` (its ``body_q``, ``body_v``, ``body_w``) into ``frame``'s arrays
    (``previous``, ``position``, ``orientation``, ``velocity``, ``angular_velocity``; the last two may be
    one-element placeholders without velocities). ``align``: turn each quaternion to the sign nearest
    ``frame.previous`` (False for a file's first frame); ``frame.previous`` is read only."""
    n = frame.position.shape[0]
    wp.launch(
        make_frame_kernel(scalar),
        dim=n,
        inputs=[
            state.body_q,
            state.body_v,
            state.body_w,
            float(scale),
            float(velocity_scale),
            float(angular_scale),
            int(bool(with_velocities)),
            int(bool(align)),
            frame.previous,
        ],  # fmt: skip
        outputs=[frame.position, frame.orientation, frame.velocity, frame.angular_velocity],
        device=frame.position.device,
    )
