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

:class:`Precision` names them. Warp is imported only by the functions that need it, so that the scene
package, which must not import Warp, takes :class:`Precision` from here (``polydem.kernels`` itself
imports nothing), as it takes :class:`~polydem.kernels.laws.Law` from :mod:`polydem.kernels.laws`.
"""

from __future__ import annotations

import enum


class Precision(enum.StrEnum):
    """The precisions, by the name a scene file gives them (a ``str`` enum: ``Precision.MIXED == "mixed"``,
    so scene files, checkpoints, summaries and the kernels' factories keep their strings)."""

    FLOAT32 = "float32"
    MIXED = "mixed"
    FLOAT64 = "float64"

    @classmethod
    def _missing_(cls, value: object) -> Precision:
        raise ValueError(f"unknown precision {value!r}; expected one of {', '.join(PRECISIONS)}")


PRECISIONS = tuple(p.value for p in Precision)


def scalars(precision: str) -> tuple[type, type]:
    """``(state scalar, contact scalar)`` of a precision (a :class:`Precision` or its name): the scalar of
    the body state and the integrator, and that of the pair geometry, the contact response and the
    contact history."""
    import warp as wp

    p = Precision(precision)
    if p is Precision.FLOAT32:
        return wp.float32, wp.float32
    if p is Precision.MIXED:
        return wp.float64, wp.float32
    return wp.float64, wp.float64


def numpy_dtype(scalar: type) -> type:
    """The numpy dtype of a Warp scalar (``wp.float32`` or ``wp.float64``)."""
    import numpy as np
    import warp as wp

    return np.float64 if scalar == wp.float64 else np.float32
