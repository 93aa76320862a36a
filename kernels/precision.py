"""The precisions of the simulator: which scalar each part of a step computes in.

``[simulation] precision`` (and ``polydem run --precision``) chooses one of:

* ``"float32"``: everything in float32.
* ``"mixed"``: the state (poses, velocities, forces and torques per body, dissipated energy), the
  integrator, the gather of the pair forces and the wall offsets in float64; the overlap geometry
  and the contact response in float32, in a frame centred on body A of the pair (or on the body at a
  wall), so their rounding is relative to the bodies' size, not to their distance from the origin.
* ``"float64"``: everything in float64.

The broad phase runs in float32 in every mode (Warp's BVH is float32): in the float64 modes it gets
float32 copies of the centres with radii grown by the rounding of that cast (:mod:`polydem.contacts`).
"""

import warp as wp

PRECISIONS = ("float32", "mixed", "float64")


def scalars(precision):
    """``(state scalar, contact scalar)`` of a precision: the scalar of the body state and the
    integrator, and that of the pair geometry, the contact response and the contact history."""
    if precision == "float32":
        return wp.float32, wp.float32
    if precision == "mixed":
        return wp.float64, wp.float32
    if precision == "float64":
        return wp.float64, wp.float64
    raise ValueError(f"unknown precision {precision!r}; expected one of {', '.join(PRECISIONS)}")


def numpy_dtype(scalar):
    """The numpy dtype of a Warp scalar (``wp.float32`` or ``wp.float64``)."""
    import numpy as np

    return np.float64 if scalar == wp.float64 else np.float32
