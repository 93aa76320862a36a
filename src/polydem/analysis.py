"""Measurements on granular flows and piles: discharge rates, Beverloo's law, the angle of repose.

Plain numpy (and scipy for the free-exponent fit); the benchmarks that run the scenes
(``benchmarks/hopper_discharge.py``, ``benchmarks/repose.py``) call these, and the tests check them
on synthetic data of known answer. Arguments that are not finite real numbers of the shape asked
for (NaN, ragged or empty arrays, times that do not increase) raise a ValueError naming the
argument, before any fit.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


def _numbers(name: str, values, ndim: int | None = 1) -> np.ndarray:
    """``values`` as a float64 array of finite real numbers with ``ndim`` dimensions (None: any);
    ValueError naming ``name`` otherwise."""
    try:
        a = np.asarray(values)
    except ValueError:  # ragged nesting
        raise ValueError(f"{name} must be an array of numbers, got a ragged sequence") from None
    if a.dtype == object or not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
        raise ValueError(f"{name} must be an array of numbers, got {type(values).__name__} of {a.dtype}")
    if np.iscomplexobj(a):
        raise ValueError(f"{name} must be real numbers, got complex ones")
    a = a.astype(np.float64)
    if ndim is not None and a.ndim != ndim:
        raise ValueError(f"{name} must be a {ndim}-D array, got shape {a.shape}")
    bad = np.flatnonzero(~np.isfinite(a.reshape(-1)))
    if len(bad):
        raise ValueError(f"{name} must be finite, got {a.reshape(-1)[bad[0]]} at flat index {int(bad[0])}")
    return a


def _number(name: str, value, positive: bool = False) -> float:
    """``value`` as a finite float (> 0 with ``positive``); ValueError naming ``name`` otherwise."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not np.isfinite(v) or (positive and v <= 0.0):
        raise ValueError(f"{name} must be a finite number{' > 0' if positive else ''}, got {value!r}")
    return v


@dataclass
class Rate:
    """A steady rate fitted to a cumulative record: ``slope`` [units/s] with its standard error,
    over the window ``t0``..``t1`` [s] (``points`` samples)."""

    slope: float
    stderr: float
    t0: float
    t1: float
    points: int

    def to_dict(self):
        return asdict(self)


def discharge_rate(times, discharged, lo: float = 0.2, hi: float = 0.7) -> Rate:
    """The steady discharge rate of a cumulative record (mass or count that has left, against time).

    The window is where the record lies between ``lo`` and ``hi`` of its final value: past the
    start-up (the orifice's first arch, the column still falling in) and before the hopper runs
    low. A least-squares line over the samples in it gives the rate and its standard error.
    Raises ValueError when fewer than 3 samples fall in the window (run longer, sample more often).
    """
    t = _numbers("times", times, None)
    m = _numbers("discharged", discharged, None)
    if t.shape != m.shape or t.ndim != 1:
        raise ValueError(f"times and discharged must be 1-D of one length, got {t.shape} and {m.shape}")
    if len(t) < 3:
        raise ValueError(f"need at least 3 samples of the discharged amount to fit a rate, got {len(t)}")
    if np.any(np.diff(t) <= 0.0):
        k = int(np.flatnonzero(np.diff(t) <= 0.0)[0])
        raise ValueError(f"times must increase from sample to sample, got {t[k]} then {t[k + 1]} at index {k + 1}")
    lo, hi = _number("lo", lo), _number("hi", hi)
    if not 0.0 <= lo < hi <= 1.0:
        raise ValueError(f"need 0 <= lo < hi <= 1, got lo = {lo}, hi = {hi}")
    final = m[-1] if len(m) else 0.0
    if final <= 0.0:
        raise ValueError("nothing was discharged: the orifice jammed or the run was too short")
    sel = np.flatnonzero((m >= lo * final) & (m <= hi * final))
    if len(sel) < 3:
        raise ValueError(
            f"only {len(sel)} samples between {lo:g} and {hi:g} of the discharged amount; sample more often"
        )
    tt, mm = t[sel], m[sel]
    a = np.vstack([tt, np.ones_like(tt)]).T
    coef, res, *_ = np.linalg.lstsq(a, mm, rcond=None)
    resid = mm - a @ coef
    dof = max(len(tt) - 2, 1)
    s2 = float(resid @ resid) / dof
    var = s2 / float(np.sum((tt - tt.mean()) ** 2))
    return Rate(float(coef[0]), float(np.sqrt(var)), float(tt[0]), float(tt[-1]), len(tt))


@dataclass
class BeverlooFit:
    """W = C (D - k d)^n: ``C`` [kg/s / m^n], ``k`` [-], ``n`` [-], with standard errors (``*_err``;
    ``n_err`` is 0 when n was fixed), and the rms relative residual of the fit."""

    C: float
    k: float
    n: float
    C_err: float
    k_err: float
    n_err: float
    rms_relative_residual: float

    def to_dict(self):
        return asdict(self)


def _fixed_n(D, W, d, n):
    # W^(1/n) = C^(1/n) (D - k d): a straight line in D.
    y = W ** (1.0 / n)
    a = np.vstack([D, np.ones_like(D)]).T
    (slope, icpt), *_ = np.linalg.lstsq(a, y, rcond=None)
    k = -icpt / (slope * d)
    return slope**n, k


def fit_beverloo(D, W, d: float, n: float | None = None) -> BeverlooFit:
    """Fit Beverloo's law ``W = C (D - k d)^n`` to discharge rates ``W`` at orifice sizes ``D``.

    Beverloo, Leniger and van de Velde (1961) give n = 5/2 for a 3-D orifice. With ``n`` given,
    a straight-line fit of W^(1/n) against D gives C and k; with ``n = None`` the exponent is
    fitted too (scipy's least squares in W, started from the fixed-n fit), which needs at least 4
    orifices. ``d`` is the grain size the law's k is measured in.
    """
    D = _numbers("D", D, None)
    W = _numbers("W", W, None)
    if D.shape != W.shape or D.ndim != 1:
        raise ValueError(f"D and W must be 1-D of one length, got {D.shape} and {W.shape}")
    if np.any(W <= 0.0):
        raise ValueError("every rate must be positive (a jammed orifice has no rate: leave it out)")
    if np.any(D <= 0.0):
        raise ValueError(f"every orifice size D must be positive, got {float(D.min())}")
    d = _number("d (the grain size)", d, positive=True)
    if n is not None:
        n = _number("n (the exponent)", n, positive=True)
    need = 3 if n is not None else 4
    sizes = len(np.unique(D))
    if sizes < need:
        raise ValueError(
            f"need at least {need} different orifice sizes to fit {'C, k' if n else 'C, k and n'}, got {sizes}"
        )
    if n is not None:
        C, k = _fixed_n(D, W, d, n)
        pred = C * np.clip(D - k * d, 0.0, None) ** n
        resid = (W - pred) / W
        # Standard errors from the linearised fit's Jacobian.
        jac = np.column_stack([pred / C, -n * C * d * np.clip(D - k * d, 1e-300, None) ** (n - 1.0)])
        cov = _covariance(jac, W - pred, len(D) - 2)
        return BeverlooFit(C, k, n, float(np.sqrt(cov[0, 0])), float(np.sqrt(cov[1, 1])), 0.0,
                           float(np.sqrt(np.mean(resid**2))))  # fmt: skip
    from scipy.optimize import curve_fit

    def model(x, c, k, nn):
        return c * np.clip(x - k * d, 1e-12, None) ** nn

    C0, k0 = _fixed_n(D, W, d, 2.5)
    popt, pcov = curve_fit(model, D, W, p0=(C0, k0, 2.5), maxfev=20000)
    resid = (W - model(D, *popt)) / W
    err = np.sqrt(np.clip(np.diag(pcov), 0.0, None))
    return BeverlooFit(*map(float, popt), *map(float, err), float(np.sqrt(np.mean(resid**2))))


def _covariance(jac, resid, dof):
    s2 = float(resid @ resid) / max(dof, 1)
    try:
        return s2 * np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return np.full((jac.shape[1], jac.shape[1]), np.inf)


@dataclass
class ReposeAngle:
    """The angle of repose of a heap [degrees] from a line fitted to its surface over the flank,
    with the fit's standard error, the heap's axis (x, y) and its foot radius [m]."""

    angle_deg: float
    stderr_deg: float
    axis: tuple
    foot_radius: float
    height: float
    points: int

    def to_dict(self):
        return asdict(self)


def angle_of_repose(positions, grain_size: float, floor: float = 0.0, axis=None, flank=(0.25, 0.75),
                    bins: int = 24) -> ReposeAngle:  # fmt: skip
    """The angle of repose of a conical heap from its grains' centres (N, 3) [m].

    Method: the heap's axis is the median of the grains' positions in plan (or ``axis``); the
    grains are binned in rings one ``grain_size`` wide around it; the surface height of a ring is
    the highest grain centre in it. The foot radius is where the surface first comes down to the
    floor, the first ring (past the highest) whose top lies below 1.5 grain sizes or that holds no
    grain: grains that bounced or rolled away beyond it do not count. A straight line through
    (r, height) over the flank, the rings between ``flank[0]`` and ``flank[1]`` of the foot radius
    (leaving out the rounded top and the toe), gives tan(angle) = -slope. The angle is that of the
    line through the surface grains' centres, parallel to the surface. ``bins`` caps the number of
    rings over the foot radius (wider rings for large heaps).
    """
    p = _numbers("positions", positions, None)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 20:
        raise ValueError(f"need (N, 3) grain positions with N >= 20, got shape {p.shape}")
    grain_size = _number("grain_size", grain_size, positive=True)
    floor = _number("floor", floor)
    if axis is None:
        xy = np.median(p[:, :2], axis=0)
    else:
        xy = _numbers("axis", axis)
        if xy.shape != (2,):
            raise ValueError(f"axis must be the heap's (x, y), got shape {xy.shape}")
    f0, f1 = (_number("flank", f) for f in flank) if np.shape(flank) == (2,) else (None, None)
    if f0 is None or not 0.0 <= f0 < f1 <= 1.0:
        raise ValueError(f"flank must be (start, end) fractions of the foot radius with 0 <= start < end <= 1, "
                         f"got {flank!r}")  # fmt: skip
    if isinstance(bins, bool) or not isinstance(bins, int | np.integer) or bins < 1:
        raise ValueError(f"bins must be a whole number >= 1, got {bins!r}")
    r = np.linalg.norm(p[:, :2] - xy, axis=1)
    z = p[:, 2] - floor
    width = grain_size
    if r.max() / width > 1e6:
        raise ValueError(
            f"grain_size {grain_size:g} m is too small for a heap {r.max():g} m wide (over a million rings): "
            "give the grains' size in metres"
        )
    n_rings = int(np.ceil(r.max() / width)) + 1
    ring = np.minimum((r / width).astype(np.int64), n_rings - 1)
    tops = np.full(n_rings, -np.inf)
    np.maximum.at(tops, ring, z)
    peak = int(np.argmax(tops))
    low = np.flatnonzero(tops[peak:] < 1.5 * grain_size)
    foot = (peak + (int(low[0]) if len(low) else n_rings - peak)) * width
    # Rings no narrower than a grain, at most ``bins`` over the foot radius.
    width = max(grain_size, foot / bins)
    edges = np.arange(0.0, foot + 0.5 * width, width)
    mids, heights = [], []
    for i in range(len(edges) - 1):
        sel = (r >= edges[i]) & (r < edges[i + 1])
        if sel.any():
            mids.append(0.5 * (edges[i] + edges[i + 1]))
            heights.append(float(z[sel].max()))
    mids, tops = np.array(mids), np.array(heights)
    use = (mids >= flank[0] * foot) & (mids <= flank[1] * foot)
    if use.sum() < 3:
        raise ValueError("fewer than 3 rings on the flank: the heap is too small for this many bins")
    a = np.vstack([mids[use], np.ones(use.sum())]).T
    coef, *_ = np.linalg.lstsq(a, tops[use], rcond=None)
    resid = tops[use] - a @ coef
    s2 = float(resid @ resid) / max(use.sum() - 2, 1)
    var = s2 / float(np.sum((mids[use] - mids[use].mean()) ** 2))
    slope = -coef[0]
    angle = float(np.degrees(np.arctan(slope)))
    err = float(np.degrees(np.sqrt(var) / (1.0 + slope**2)))
    return ReposeAngle(angle, err, (float(xy[0]), float(xy[1])), foot, float(z.max()), int(use.sum()))
