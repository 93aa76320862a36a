"""The contact laws W(V) of the overlap volume V, each declared once.

:class:`Law` names them (a ``str`` enum: ``Law.HERTZ == "hertz"``, so scene files, ``Material.law``
and messages keep their strings) and :data:`LAW_SPECS` holds one :class:`LawSpec` per law: its
formula, the unit of k, the exponent of V, W and W' on the host, whether it has the resolved toe and
the stiffness of a face resting under a load (the time step's resting rule). The kernels' factory
(:func:`polydem.kernels.response.make_response`) keys each law's pair of ``@wp.func`` (W' and W) by
:class:`Law` and takes the toe from here; the scene package (:mod:`polydem.scene.materials`,
:mod:`~polydem.scene.checks`, :mod:`~polydem.scene.depth`) and the batch API
(:class:`polydem.batch.ContactLaw`) read the rest.

Pure Python and numpy, no Warp: it lives with the kernels (shipped as ``polydem.kernels.laws``) so
that the kernels import nothing from the host package, and the scene package, which must not import
Warp, can still import it (``polydem.kernels`` itself imports nothing).

Every law is of the family W = k V^m / m, with its own m (linear 1, hertz 1.5) or the power law's
given one; each writes it with its own operations (hertz with a square root, as the kernel does), and
the resolved toe, the float32 checks and the closed forms of the resting depth use the exponent m.

To add a law: a member of :class:`Law` and its row (its :class:`LawSpec`) in ``_LAW_ROWS`` here, and its W'
and W as ``@wp.func`` in the table of :func:`polydem.kernels.response.make_law_funcs`;
``tests/test_laws.py`` then checks W' against W and the kernel against the host.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

# The resolved toe of the laws stiffer than linear at V = 0 (kernels/response.py, toe_volume, and its host
# twin scene/depth.py, toe_volume): a face contact is at most as stiff as a frequency of TOE_OMEGA_DT / dt
# against the pair's translational mass, on the unloading branch (1 / e^2 stiffer than the loading one), dt the
# larger of the run's step and the scene's recommended one (Model.toe_dt): the law is the same at every shorter step.
# Symplectic Euler is stable below 2; a face contact of one degree of freedom rests for every restitution
# up to 1.5.
TOE_OMEGA_DT = 1.0
# toe_volume takes e at least this: V_c grows as e^-4 (e enters a logarithm), and e = 0 has none.
TOE_MIN_RESTITUTION = 1.0e-3


class Law(enum.StrEnum):
    """The contact laws, by the name a scene file gives them."""

    LINEAR = "linear"
    HERTZ = "hertz"
    POWER = "power"


@dataclass(frozen=True)
class LawSpec:
    """What the host knows of one contact law.

    Attributes:
        law: its :class:`Law`.
        formula: W(V), for messages and documentation.
        unit: the unit of its stiffness k.
        fixed_exponent: the law's m in W = k V^m / m, or None where the material gives m (>= 1).
        toe: whether the law is stiffer than linear at V = 0 for m < 2, so that the simulator continues
            it below a toe volume V_c as the resolved toe (kernels/response.py, toe_volume).
        energy: ``energy(V, k, m)``, W [J]; numpy arrays broadcast (V >= 0).
        derivative: ``derivative(V, k, m)``, W'(V) [Pa], the pressure on the area vector; the same.
        resting_stiffness: ``resting_stiffness(k, m, area, weight)``, the tangent normal stiffness
            dF/dd [N/m] of a face of ``area`` [m^2] (V = area d) resting on the law alone under
            ``weight`` [N], at the depth where W'(area d) area = weight; NaN where the law has no
            resting depth on a face. ``k`` is a float64 array; call it under ``np.errstate(all="ignore")``.
    """

    law: Law
    formula: str
    unit: str
    fixed_exponent: float | None
    toe: bool
    energy: Callable
    derivative: Callable
    resting_stiffness: Callable

    def exponent(self, m):
        """The m of W = k V^m / m: the law's own, else the material's ``m``."""
        return m if self.fixed_exponent is None else self.fixed_exponent

    def has_toe(self, m) -> bool:
        """Whether the simulator's toe bounds a resting face's stiffness W''(V) A^2, which under this law
        and exponent grows without bound as V -> 0 (1 < m < 2); then a body resting on a face needs no
        shorter step than the law's elsewhere."""
        return self.toe and 1.0 < float(self.exponent(m)) < 2.0


def _no_resting_face(k, m, area, weight):
    # The force of a face, W'(A d) A, does not grow with its depth: no depth carries a given weight.
    return np.full(np.shape(k), np.nan)


def _linear_energy(volume, k, m):
    return k * volume


def _linear_derivative(volume, k, m):
    return k * np.ones_like(volume)


def _hertz_energy(volume, k, m):
    return (2.0 / 3.0) * k * volume * np.sqrt(volume)


def _hertz_derivative(volume, k, m):
    return k * np.sqrt(volume)


def _hertz_resting_stiffness(k, m, area, weight):
    # W' = k sqrt(A d): the weight rests at d = (F / (k A^1.5))^2, and dF/dd = F / (2 d).
    depth = (weight / (k * area**1.5)) ** 2
    return weight / (2.0 * depth)


def _power_energy(volume, k, m):
    return k * volume**m / m


def _power_derivative(volume, k, m):
    return k * volume ** (m - 1.0)


def _power_resting_stiffness(k, m, area, weight):
    # W' = k (A d)^(m - 1): A d = (F / (k A))^(1 / (m - 1)), and dF/dd = (m - 1) F / d.
    if m > 1.0:
        depth = (weight / (k * area)) ** (1.0 / (np.float64(m) - 1.0)) / area
        return (np.float64(m) - 1.0) * weight / depth
    return _no_resting_face(k, m, area, weight)


# One row per law, the fields of LawSpec in order: law, formula, unit of k, fixed exponent, toe, W, W', and
# the stiffness of a face resting under a load.
_LAW_ROWS = (
    (Law.LINEAR, "W = k V", "Pa", 1.0, False, _linear_energy, _linear_derivative, _no_resting_face),
    (Law.HERTZ, "W = 2/3 k V^1.5", "J/m^4.5", 1.5, True, _hertz_energy, _hertz_derivative, _hertz_resting_stiffness),
    (Law.POWER, "W = k V^m / m", "J/m^(3m)", None, True, _power_energy, _power_derivative, _power_resting_stiffness),
)
LAW_SPECS: dict[Law, LawSpec] = {row[0]: LawSpec(*row) for row in _LAW_ROWS}
"""Every :class:`Law`'s :class:`LawSpec`; a plain name indexes it too (``LAW_SPECS["hertz"]``)."""

LAWS = tuple(law.value for law in Law)
"""The laws' names, in the order messages list them."""

LAW_UNITS = {law.value: spec.unit for law, spec in LAW_SPECS.items()}
"""The unit of each law's stiffness k, for messages."""

# The laws whose m the material gives (the power law), for messages about m.
FREE_EXPONENT_LAWS = tuple(law.value for law, spec in LAW_SPECS.items() if spec.fixed_exponent is None)
