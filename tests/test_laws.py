"""The contact laws of polydem.kernels.laws: each law's host W' is the slope of its W, its exponent is
the one of its W, its resting stiffness is the slope of a face's force, and the kernels' W' and W (what
polydem.contact_forces launches) are the host's."""

import math

import numpy as np
import pytest
from polydem.kernels.laws import LAW_SPECS, LAWS, Law

from polydem import ContactLaw, ConvexShape, contact_forces, overlap

# Every law, the power law at exponents below, at and above 2 (where the toe ends and the law stiffens).
CASES = [(law, None) for law in Law if LAW_SPECS[law].fixed_exponent is not None] + [
    (law, m) for law in Law if LAW_SPECS[law].fixed_exponent is None for m in (1.0, 1.25, 2.0, 3.5)
]
IDS = [law.value if m is None else f"{law.value}-{m}" for law, m in CASES]
K = 3.0e7


def exponent(law, m):
    return LAW_SPECS[law].exponent(m)


@pytest.mark.parametrize(("law", "m"), CASES, ids=IDS)
def test_derivative_is_the_slope_of_the_energy(law, m):
    spec = LAW_SPECS[law]
    mm = exponent(law, m)
    v = np.geomspace(1e-12, 1e-2, 21)
    h = 1e-4 * v
    slope = (spec.energy(v + h, K, mm) - spec.energy(v - h, K, mm)) / (2.0 * h)
    # Truncation (h/V)^2 and rounding 1e-16 V / h: far below a fault of 1e-4 in W' or W.
    np.testing.assert_allclose(spec.derivative(v, K, mm), slope, rtol=1e-7)
    assert spec.energy(0.0, K, mm) == 0.0


@pytest.mark.parametrize(("law", "m"), CASES, ids=IDS)
def test_exponent_is_the_one_of_the_energy(law, m):
    """The toe, the float32 checks and the depth's closed forms take W = k V^m / m with the law's m."""
    spec = LAW_SPECS[law]
    mm = exponent(law, m)
    v = np.geomspace(1e-9, 1e-3, 7)
    np.testing.assert_allclose(spec.energy(v, K, mm), K * v**mm / mm, rtol=1e-13)
    np.testing.assert_allclose(spec.derivative(v, K, mm), K * v ** (mm - 1.0), rtol=1e-13)


@pytest.mark.parametrize(("law", "m"), CASES, ids=IDS)
def test_resting_stiffness_is_the_slope_of_a_face_force(law, m):
    """The step's resting rule: a face of area A carries the weight F at the depth d where W'(A d) A = F,
    and its tangent stiffness there is dF/dd; NaN where no depth carries it (the force does not grow)."""
    spec = LAW_SPECS[law]
    mm = exponent(law, m)
    area, weight = 4.0e-4, 0.2
    k = np.array([K, 10.0 * K])
    got = spec.resting_stiffness(k, mm, area, weight)
    assert got.shape == k.shape
    if mm == 1.0:
        assert np.isnan(got).all()
        return
    for ki, stiffness in zip(k, got, strict=True):

        def force(d, ki=ki):
            return float(spec.derivative(area * d, ki, mm)) * area

        lo, hi = 1e-30, 1e30
        for _ in range(200):
            mid = math.sqrt(lo * hi)
            lo, hi = (mid, hi) if force(mid) < weight else (lo, mid)
        d = math.sqrt(lo * hi)
        slope = (force(d * (1 + 1e-5)) - force(d * (1 - 1e-5))) / (2e-5 * d)
        assert stiffness == pytest.approx(slope, rel=1e-7)


def test_laws_are_listed_in_the_order_of_the_enum():
    """Messages list the laws ("linear, hertz, power") and scene files name them by these strings."""
    assert LAWS == tuple(law.value for law in Law)
    assert [LAW_SPECS[name].law for name in LAWS] == list(Law)


@pytest.mark.parametrize("law", list(Law), ids=[law.value for law in Law])
def test_kernel_force_and_energy_are_the_host_laws(device, law):
    """Two unit cubes pressed face on face (V = d), shifted, and tilted corner first: the batch kernel's
    force is -W'(V) S_A and its energy W(V) with the host's W' and W, in float64, for every law."""
    cube = ConvexShape.box(1.0)
    tilt = np.array([0.1, 0.2, 0.0, 1.0]) / np.linalg.norm([0.1, 0.2, 0.0, 1.0])
    poses_b = np.array(
        [[0.0, 0.0, 1.0 - d, 0.0, 0.0, 0.0, 1.0] for d in (1e-6, 1e-4, 1e-2, 0.3)]
        + [[0.3, -0.2, 0.98, 0.0, 0.0, 0.0, 1.0], [0.1, 0.1, 1.05, *tilt]]
    )
    res = overlap(cube, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], cube, poses_b, device=device, precision="float64")
    assert (res.volume > 0.0).all() and not res.enclosed.any()
    spec = LAW_SPECS[law]
    for m in (1.0, 1.25, 2.0, 3.5) if spec.fixed_exponent is None else (None,):
        mm = exponent(law, m)
        f = contact_forces(res, ContactLaw(law, k=K, m=1.0 if m is None else m), device=device)
        expected = -spec.derivative(res.volume, K, mm)[:, None] * res.area_vector
        scale = np.linalg.norm(expected, axis=1, keepdims=True)
        np.testing.assert_allclose(f.force_a / scale, expected / scale, rtol=0.0, atol=1e-12)
        np.testing.assert_allclose(f.energy, spec.energy(res.volume, K, mm), rtol=1e-12)
