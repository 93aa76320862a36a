"""The measurements of polydem.analysis on synthetic data of known answer."""

import numpy as np
import pytest

from polydem.analysis import angle_of_repose, discharge_rate, fit_beverloo


def test_discharge_rate_of_a_steady_flow_with_start_and_end():
    t = np.linspace(0.0, 2.0, 201)
    # Nothing for 0.3 s, then 250 grains/s with noise, then the hopper empties at 1000 grains.
    m = np.clip(250.0 * (t - 0.3), 0.0, 1000.0) + np.random.default_rng(0).normal(0, 2.0, t.size)
    m = np.maximum.accumulate(np.clip(m, 0, None))
    r = discharge_rate(t, m)
    assert r.slope == pytest.approx(250.0, rel=0.01)
    assert 0.0 < r.stderr < 2.0 and r.t0 > 0.3 and r.t1 < 0.3 + 1000 / 250


def test_discharge_rate_says_what_is_wrong():
    with pytest.raises(ValueError, match="nothing was discharged"):
        discharge_rate([0, 1, 2], [0, 0, 0])
    with pytest.raises(ValueError, match="sample more often"):
        discharge_rate([0, 1, 2], [0, 5, 10])


@pytest.mark.parametrize("n", [2.5, 2.2])
def test_beverloo_fit_recovers_exponent_and_k(n):
    d = 0.01
    D = np.array([0.05, 0.06, 0.07, 0.09, 0.11])
    W = 3.0 * (D - 1.4 * d) ** n * (1.0 + np.random.default_rng(1).normal(0, 1e-3, D.size))
    fixed = fit_beverloo(D, W, d, n=n)
    assert fixed.k == pytest.approx(1.4, abs=0.02) and fixed.C == pytest.approx(3.0, rel=0.05)
    free = fit_beverloo(D, W, d)
    assert free.n == pytest.approx(n, abs=0.05) and free.k == pytest.approx(1.4, abs=0.1)
    assert free.n_err > 0.0 and free.rms_relative_residual < 2e-3


def test_beverloo_fit_needs_four_orifices_for_the_exponent():
    with pytest.raises(ValueError, match="at least 4"):
        fit_beverloo([0.05, 0.06, 0.07], [1.0, 2.0, 3.0], 0.01)


@pytest.mark.parametrize("angle", [22.0, 30.0, 38.0])
def test_angle_of_repose_of_a_synthetic_cone(angle):
    """Grains filling a cone of known slope (and a few rolled away): the measured angle is it."""
    rng = np.random.default_rng(2)
    g = 0.01
    height = 0.15
    foot = height / np.tan(np.radians(angle))
    pts = []
    for x in np.arange(-foot, foot, g):
        for y in np.arange(-foot, foot, g):
            r = np.hypot(x, y)
            top = height - r * np.tan(np.radians(angle))
            for z in np.arange(0.5 * g, top, g):
                pts.append((x + rng.uniform(-0.3, 0.3) * g, y + rng.uniform(-0.3, 0.3) * g, z))
    pts += [(foot * 1.5, 0.0, 0.5 * g), (0.0, -foot * 1.6, 0.5 * g)]
    res = angle_of_repose(np.array(pts), grain_size=g)
    assert res.angle_deg == pytest.approx(angle, abs=1.5)
    assert res.foot_radius == pytest.approx(foot, rel=0.1)
