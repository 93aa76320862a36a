"""Contact response: from the overlap geometry of a contact to its normal, point and wrench.

One function, :func:`respond` (built by :func:`make_response`), turns the overlap of a contact
(V, V times the centroid, S_A, M_A and the fallback area vector, see
:mod:`polydem.kernels.geometry`) into the wrench of the energy model; the pair kernel, the wall
contacts and the diagnostics of :mod:`polydem.kernels.forces` all call it, and so do the batch
kernels at the end of this file, which :func:`polydem.overlap` and :func:`polydem.contact_forces`
launch.

Normal and contact point (:func:`contact_frame`): the normal is S_A / |S_A|, from A into B; the
contact point is where the central axis of the wrench (S_A, M_A) meets the plane through the
overlap's centroid normal to it.

Enclosed pairs. When one body lies (almost) wholly inside the other, or two identical bodies sit
on top of each other, S_A vanishes with the gradient of V. The geometry then (|S_A| <
ENCLOSED_RATIO V^(2/3)) returns a fallback area vector, which takes the place of S_A: the
direction of least penetration (the face normal, of either body, along which the shorter
translation separates them; for a grain inside a plate, out through the nearest face) times the
projected area of the smaller body along it, 1/2 sum |n.n_f| A_f. Just before a body sinks
wholly in through a face, |S_A| is that face's area, which is the projected area along its
normal: the force W'(V) |S| goes on without a jump. A body wholly inside a wall is pushed along
the wall's normal with its projected area. The moment is that of the push applied at the
overlap's centroid. Callers without a fallback (a zero vector) get the older push along the line
of centres with the effective area V^(2/3), and a thin sliver (V below ENCLOSED_MIN_VOLUME
r_min^3) with a vanishing S_A gets no force.

The contact law and the damping are described in :mod:`polydem.kernels.forces`.
"""

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np
import warp as wp
from polydem.kernels.geometry import ENCLOSED_RATIO
from polydem.kernels.laws import LAW_SPECS, LAWS, TOE_MIN_RESTITUTION, TOE_OMEGA_DT, Law
from polydem.kernels.structs import arrays, filled, make_struct

# A pair whose |S_A| falls below ENCLOSED_RATIO V^(2/3) is "enclosed": one body (nearly) inside
# the other, or two identical bodies on top of each other. The gradient of V vanishes there.
# Without a fallback area vector from the geometry, only when the overlap is a real share of the
# smaller body (V > this times r_min^3): a sliver has no gradient either, and no force.
ENCLOSED_MIN_VOLUME = 1.0e-3

# The friction spring's twist channel (respond): the lever of the twist, as a fraction of the radius
# sqrt(|S_A| / pi) of a disc of the contact's area: 2/3, Coulomb's friction torque over a disc under
# a uniform pressure, mu F_n (2/3) R.
TWIST_LEVER = 2.0 / 3.0
# The rocking damping of a contact (respond) is at most this fraction of mu F_n R, R = sqrt(|S_A| / pi).
ROLL_FRACTION = 0.1
# The tangential dashpots of all a body's contacts, taken explicitly, may change the velocity at its farthest
# point by at most this fraction of it in one step (the body's damping load, polydem.kernels.forces): past
# 1 an explicit dashpot reverses the motion it damps, and two bodies that damp each other's relative motion
# count twice. A grain held by many contacts at a long step otherwise rings at the step's period forever
# (a pile at 4 dt_rec never came to rest: BENCHMARKS.md section 21).
DAMPING_SHARE = 0.5

# What contact_frame found: a regular contact, an enclosed pair (pushed along the fallback area
# vector) or a sliver (no force).
REGULAR = 0
ENCLOSED = 1
SLIVER = 2


@dataclass(frozen=True)
class Frame:
    """:func:`contact_frame` and :func:`centre_line` of one precision."""

    scalar: Any
    vec3: Any
    centre_line: Any  # (r_ab) -> the unit vector from A's centre to B's
    contact_frame: Any  # (V, V centroid, S_A, M_A, fallback, r_ab, r_min) -> (kind, normal, point, S, M, |S|)


@functools.cache
def make_damping(scalar) -> tuple[Any, Any]:
    """``damping_factor(e)``, twice the damping ratio that restitution e gives a linear oscillator (a ``wp.func`` in
    ``scalar``), and a kernel filling a table of it, ``damping_factor_kernel(e, out)``: the tangential dashpot's
    factor of each material pair, computed once where the model is built by the expression :func:`make_response`'s
    ``dashpot`` uses, so that a dashpot from the table has the same bits as one from e (the gather reads the
    table: a logarithm and a square root less a contact)."""

    @wp.func
    def damping_factor(e: scalar):
        ln_e = wp.log(wp.max(e, scalar(1.0e-6)))
        zeta = -ln_e / wp.sqrt(ln_e * ln_e + scalar(9.8696044))
        return scalar(2.0) * zeta

    @wp.kernel(enable_backward=False, module="unique")
    def damping_factor_kernel(e: wp.array(dtype=scalar), out: wp.array(dtype=scalar)):
        i = wp.tid()
        out[i] = damping_factor(e[i])

    return damping_factor, damping_factor_kernel


def fill_damping_factors(e: wp.array, out: wp.array) -> None:
    """``out`` (M*M,) the damping factor of each entry of ``e`` (:func:`make_damping`), on their device."""
    wp.launch(make_damping(e.dtype)[1], dim=e.shape[0], inputs=[e], outputs=[out], device=e.device)


@dataclass(frozen=True)
class Response:
    """The contact law's :func:`kept_energy` and :func:`respond` of one precision, law, friction setting
    and purpose (the law's other functions are theirs alone)."""

    scalar: Any
    law: str
    friction: bool
    diagnostics: bool
    frame: Frame
    kept_energy: Any  # (turn, k, m, e, dt, area, r_min, inv_mass) -> what an opening contact kept [J]
    dashpot: Any  # (kt, e, inv_mass) -> the tangential dashpot's coefficient [N s/m]
    dashpot_factored: Any  # (damping_factor(e), kt, inv_mass) -> the same, from the material table's factor
    respond: Any  # (overlap, motion, material, history, step) -> (force, torque, xi, turn, energy, lost, n, ...)


@functools.cache
def make_frame(scalar) -> Frame:
    """The contact normal, the enclosed push and the contact point (module docstring)."""
    vec3 = wp.types.vector(3, scalar)

    @wp.func
    def centre_line(r_ab: vec3):
        # Unit vector from A's centre to B's; +z when they coincide.
        line = vec3(scalar(0.0), scalar(0.0), scalar(1.0))
        dist = wp.length(r_ab)
        if dist > scalar(0.0):
            line = r_ab / dist
        return line

    @wp.func
    def contact_frame(
        volume: scalar, first_moment: vec3, area: vec3, moment: vec3, fallback: vec3, r_ab: vec3, r_min: scalar
    ):
        """Kind (REGULAR, ENCLOSED or SLIVER), unit normal, contact point, effective S_A and M_A,
        and |S_A| of an overlap V > 0 (V * centroid, S_A, M_A about x_A; all relative to x_A).
        ``fallback`` is the geometry's fallback area vector (zero unless enclosed), ``r_ab`` is
        x_B - x_A, ``r_min`` the smaller bounding radius.

        Enclosure is decided here, on the S_A and V given, not on whether a fallback came: a mesh wall
        or a compound grain sums the geometry of many cells or parts, and one of them may be an
        enclosed sliver (a face within rounding of a cell's side) whose fallback, as large as the
        body's projected area, must not turn a regular contact's force sideways."""
        c = first_moment / volume
        s = area
        mom = moment
        s_norm = wp.length(s)
        kind = int(REGULAR)
        v23 = wp.pow(volume, scalar(2.0) / scalar(3.0))
        if s_norm < scalar(ENCLOSED_RATIO) * v23:
            fb_norm = wp.length(fallback)
            if fb_norm > scalar(0.0):
                # Enclosed: push along the direction of least penetration (module docstring).
                s = fallback
                mom = wp.cross(c, s)
                s_norm = fb_norm
                kind = int(ENCLOSED)
            else:
                line = centre_line(r_ab)
                if volume <= scalar(ENCLOSED_MIN_VOLUME) * r_min * r_min * r_min:
                    # A sliver without a gradient: no force.
                    return int(SLIVER), line, c, s, mom, s_norm
                # No fallback given: push along the line of centres.
                s = v23 * line
                mom = wp.cross(c, s)
                s_norm = v23
                kind = int(ENCLOSED)
        n = s / s_norm
        axis = wp.cross(s, mom) / (s_norm * s_norm)
        point = axis + wp.dot(c - axis, n) * n
        return kind, n, point, s, mom, s_norm

    return Frame(scalar=scalar, vec3=vec3, centre_line=centre_line, contact_frame=contact_frame)


@functools.cache
def make_law_funcs(scalar) -> dict:
    """Each :class:`~polydem.kernels.laws.Law`'s own W'(V) [Pa] and W(V) [J] as a pair of ``@wp.func``
    ``(volume, k, m)`` of one precision, without the resolved toe (``law_derivative`` and ``law_energy``
    of :func:`make_response` add it); their host twins are in :data:`polydem.kernels.laws.LAW_SPECS`."""

    @wp.func
    def linear_derivative(volume: scalar, k: scalar, m: scalar):
        return k

    @wp.func
    def linear_energy(volume: scalar, k: scalar, m: scalar):
        return k * volume

    @wp.func
    def hertz_derivative(volume: scalar, k: scalar, m: scalar):
        return k * wp.sqrt(volume)

    @wp.func
    def hertz_energy(volume: scalar, k: scalar, m: scalar):
        return (scalar(2.0) / scalar(3.0)) * k * volume * wp.sqrt(volume)

    @wp.func
    def power_derivative(volume: scalar, k: scalar, m: scalar):
        return k * wp.pow(volume, m - scalar(1.0))

    @wp.func
    def power_energy(volume: scalar, k: scalar, m: scalar):
        return k * wp.pow(volume, m) / m

    return {
        Law.LINEAR: (linear_derivative, linear_energy),
        Law.HERTZ: (hertz_derivative, hertz_energy),
        Law.POWER: (power_derivative, power_energy),
    }


@functools.cache
def make_response(scalar, law: str, friction: bool, diagnostics: bool = False) -> Response:
    """:func:`respond` for one contact law (a name of :data:`polydem.kernels.laws.LAWS`), with or without friction.

    ``diagnostics`` builds the variant that reports a contact without stepping it (the turning
    volume stays as it is).
    """
    if law not in LAWS:
        raise ValueError(f"unknown contact law {law!r}")
    frame = make_frame(scalar)
    vec3 = frame.vec3
    contact_frame = frame.contact_frame
    zero3 = wp.constant(vec3(scalar(0.0), scalar(0.0), scalar(0.0)))
    own_derivative, own_energy = make_law_funcs(scalar)[law]

    # The resolved toe (module docstring of polydem.kernels.forces): below V_c a law stiffer than
    # linear at V = 0 (1 < m < 2, the hertz law among them) continues as W'(V) = a V + b V^2, with W'
    # and W'' continuous at V_c, so that a face contact is never stiffer than the step resolves.
    toe_law = LAW_SPECS[law].toe

    @wp.func
    def toe_volume(k: scalar, m: scalar, e: scalar, dt: scalar, area: scalar, r_min: scalar, inv_mass: scalar):
        """V_c [m^3] of the resolved toe: the normal stiffness W''(0) A^2 of a face of area ``area`` (the
        smaller of the two bodies' largest faces), taken 1/e^2 stiffer on the unloading branch, meets the
        pair's translational mass (1 / ``inv_mass``) at a frequency of TOE_OMEGA_DT / dt, dt the larger of the
        run's step and the scene's recommended one (``Model.toe_dt``): below the recommended step a toe that
        followed the run's (V_c ~ dt^4) made every refinement of dt another law; above it the run's step keeps
        a face at rest resolved (BENCHMARKS.md section 25). A constant of the pair, so that W stays a function
        of V alone and the step's energy books stay exact; at most the smaller bounding cube r_min^3. 0 (no
        toe) for a law without a singular stiffness, without a step (the batch API) or without mass."""
        vc = scalar(0.0)
        if wp.static(toe_law):
            if (
                m < scalar(2.0)
                and dt > scalar(0.0)
                and inv_mass > scalar(0.0)
                and k > scalar(0.0)
                and area > scalar(0.0)
            ):
                # (3 - m) k V_c^(m - 2) area^2 dt^2 inv_mass / e^2 = TOE_OMEGA_DT^2, in logs (float32 range)
                ln_x = (
                    wp.log((scalar(3.0) - m) * k)
                    + scalar(2.0) * wp.log(area * dt)
                    + wp.log(inv_mass)
                    - scalar(2.0) * wp.log(wp.max(e, scalar(TOE_MIN_RESTITUTION)) * scalar(TOE_OMEGA_DT))
                )
                # Never beyond the smaller body's bounding cube: past it the toe would be the law.
                vc = wp.exp(wp.min(ln_x / (scalar(2.0) - m), scalar(3.0) * wp.log(r_min)))
        return vc

    @wp.func
    def law_derivative(volume: scalar, k: scalar, m: scalar, vc: scalar):
        # W'(V) [Pa]: the law's, or below V_c (a law with the toe) a V + b V^2 with
        # a = (3 - m) k V_c^(m - 2), b = (m - 2) k V_c^(m - 3)
        if wp.static(toe_law):
            if volume < vc:
                x = volume / vc
                return k * wp.pow(vc, m - scalar(1.0)) * x * ((scalar(3.0) - m) + (m - scalar(2.0)) * x)
        return own_derivative(volume, k, m)

    @wp.func
    def law_energy(volume: scalar, k: scalar, m: scalar, vc: scalar):
        # W(V) [J]
        if wp.static(not toe_law):
            return own_energy(volume, k, m)
        else:
            if volume < vc:
                x = volume / vc
                return (
                    k * wp.pow(vc, m) * x * x * ((scalar(3.0) - m) / scalar(2.0) + (m - scalar(2.0)) / scalar(3.0) * x)
                )
            # The law's W, less what the toe stores below V_c than the law does: continuous at V_c.
            offset = scalar(0.0)
            if vc > scalar(0.0):
                offset = k * wp.pow(vc, m) * ((scalar(5.0) - m) / scalar(6.0) - scalar(1.0) / m)
            return own_energy(volume, k, m) + offset

    @wp.func
    def kept_energy(
        turn: scalar, k: scalar, m: scalar, e: scalar, toe_dt: scalar, area: scalar, r_min: scalar, inv_mass: scalar
    ):
        # (1 - e^2) W(turn) [J]: what the last impact of a contact that opens never gave back, dissipated
        # as it opens (its force may have ended before, at u = 0). Arguments as for toe_volume.
        vc = toe_volume(k, m, e, toe_dt, area, r_min, inv_mass)
        return (scalar(1.0) - e * e) * law_energy(turn, k, m, vc)

    damping_factor = make_damping(scalar)[0]

    @wp.func
    def dashpot(kt: scalar, e: scalar, inv_mass: scalar):
        # The tangential dashpot [N s/m]: the damping ratio that e gives a linear oscillator, on the spring kt
        # and the pair's translational mass (1 / inv_mass); none without a mass.
        ct = scalar(0.0)
        if inv_mass > scalar(0.0):
            ct = damping_factor(e) * wp.sqrt(kt / wp.max(inv_mass, scalar(1.0e-30)))
        return ct

    @wp.func
    def dashpot_factored(factor: scalar, kt: scalar, inv_mass: scalar):
        # dashpot(kt, e, inv_mass) from factor = damping_factor(e) (the material table's): the same bits
        ct = scalar(0.0)
        if inv_mass > scalar(0.0):
            ct = factor * wp.sqrt(kt / wp.max(inv_mass, scalar(1.0e-30)))
        return ct

    @wp.func
    def elastic_volume(volume: scalar, turn: scalar, e2: scalar):
        # u on the unloading branch from the turning volume: du = dV / e^2, u(turn) = turn.
        return turn - (turn - volume) / e2

    @wp.func
    def branch_pressure(volume: scalar, turn: scalar, k: scalar, m: scalar, e2: scalar, vc: scalar):
        # dE/dV on the branch of (V, turn) [Pa]: W'(V) loading, W'(u) unloading, 0 once u <= 0.
        if volume >= turn:
            return law_derivative(volume, k, m, vc)
        u = elastic_volume(volume, turn, e2)
        if u > scalar(0.0):
            return law_derivative(u, k, m, vc)
        return scalar(0.0)

    @wp.func
    def branch_energy(volume: scalar, turn: scalar, k: scalar, m: scalar, e2: scalar, vc: scalar):
        # E(V; turn) [J]: W(V) loading; unloading, (1 - e^2) W(turn) + e^2 W(u) (what is left to
        # return plus what will never come back), so that -dE/dV is the branch's pressure.
        en = scalar(0.0)
        if volume >= turn:
            en = law_energy(volume, k, m, vc)
        else:
            en = (scalar(1.0) - e2) * law_energy(turn, k, m, vc)
            u = elastic_volume(volume, turn, e2)
            if u > scalar(0.0):
                en += e2 * law_energy(u, k, m, vc)
        return en

    @wp.func
    def respond(
        # Overlap (positions relative to x_A)
        volume: scalar,
        first_moment: vec3,
        area: vec3,
        moment: vec3,
        fallback: vec3,
        r_ab: vec3,
        # Motion
        v_a: vec3,
        w_a: vec3,
        v_b: vec3,
        w_b: vec3,
        # Material
        k: scalar,
        m: scalar,
        e: scalar,
        mu: scalar,
        kt: scalar,
        # History
        xi: vec3,
        turn: scalar,
        # Step
        dt: scalar,
        toe_dt: scalar,
        r_min: scalar,
        face_area: scalar,
        inv_mass: scalar,
        damping_scale: scalar,
    ):
        """Wrench on A from the overlap (V, V * centroid, S_A, M_A about x_A; all relative to x_A).

        ``fallback`` is the geometry's fallback area vector (the push of an enclosed pair, zero
        otherwise), ``r_ab`` is x_B - x_A; ``dt`` the run's step and ``toe_dt`` the step whose toe the law
        takes (toe_volume); ``turn`` the pair's
        turning volume (0 for a new contact; unused for e = 1); ``damping_scale`` (<= 1) scales the tangential
        dashpot where the bodies' damping loads exceed DAMPING_SHARE (1 elsewhere). Returns (force on A, torque on A
        about x_A, new spring xi, new turning volume, stored energy, energy dissipated this step,
        unit normal, contact point relative to x_A, normal force magnitude, tangential force).
        """
        e2 = e * e
        vc = toe_volume(k, m, e, toe_dt, face_area, r_min, inv_mass)
        if e2 >= scalar(1.0):
            turn = scalar(0.0)
        kind, n, point, s, mom, s_norm = contact_frame(volume, first_moment, area, moment, fallback, r_ab, r_min)
        if kind == SLIVER:
            lost0 = scalar(0.0)
            if wp.static(friction):
                lost0 = scalar(0.5) * kt * wp.dot(xi, xi)
            en0 = branch_energy(volume, turn, k, m, e2, vc)
            return zero3, zero3, zero3, turn, en0, lost0, n, point, scalar(0.0), zero3

        dvdt = wp.dot(s, v_a - v_b) + wp.dot(mom, w_a) + wp.dot(wp.cross(r_ab, s) - mom, w_b)
        lost = scalar(0.0)
        turn_new = turn
        if wp.static(not diagnostics):
            # Growing, or past the turning volume: the loading branch, whose turning volume follows V.
            # Reloading from below the turning volume drops the part of E(V; turn) that the loading
            # branch does not hold: the hysteresis loop's area, dissipated.
            if e2 < scalar(1.0) and (dvdt >= scalar(0.0) or volume >= turn):
                turn_new = volume
                if volume < turn:
                    lost = branch_energy(volume, turn, k, m, e2, vc) - law_energy(volume, k, m, vc)
        wd = branch_pressure(volume, turn_new, k, m, e2, vc)
        fn = wd * s_norm
        force = -wd * s
        torque = -wd * mom
        energy = branch_energy(volume, turn_new, k, m, e2, vc)
        ft = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        xi_new = vec3(scalar(0.0), scalar(0.0), scalar(0.0))
        if wp.static(friction):
            v_rel = v_a + wp.cross(w_a, point) - v_b - wp.cross(w_b, point - r_ab)
            # The spring has three channels: two tangential, and along n the twist, the rim of a disc
            # of the contact's area (radius r_t, 2/3 of which is the lever of Coulomb's friction over
            # a disc) turned by the relative spin about n. Without it a face contact has no grip on a
            # grain that spins about the contact's normal, and a settled pile keeps turning.
            r_t = scalar(TWIST_LEVER) * wp.sqrt(s_norm / scalar(3.14159265358979))
            w_n = wp.dot(w_a - w_b, n)
            vt = v_rel - wp.dot(v_rel, n) * n + (w_n * r_t) * n
            # Turn the spring's tangential part into the current tangent plane, keeping its whole length
            # (and its energy); the twist stays along n.
            l0 = wp.length(xi)
            tw = wp.dot(xi, n)
            xt = xi - tw * n
            l1 = wp.length(xt)
            if l1 > scalar(0.0):
                xt = xt * (wp.sqrt(wp.max(l0 * l0 - tw * tw, scalar(0.0))) / l1)
            xt = xt + tw * n
            # The spring at the current poses: the last step moved the bodies by vt dt (symplectic
            # Euler: x_n = x_(n-1) + v_n dt). Like the normal force it is a function of the poses.
            xt = xt + vt * dt
            # A tangential dashpot with the damping ratio of e keeps a sticking contact from ringing
            # (an undamped spring rings, slips at each swing and lets a block creep down a slope).
            ct = dashpot(kt, e, inv_mass) * damping_scale
            ft = -kt * xt - ct * vt
            cap = mu * fn
            ft_norm = wp.length(ft)
            # The dashpot's work, what of the force is not the spring's, times vt dt: it opposes vt.
            damped = ct * wp.dot(vt, vt) * dt
            if ft_norm > cap:
                ft = ft * (cap / ft_norm)
                # Sliding: the spring keeps its direction xt and slips to the length whose force is
                # the cap (never longer than xt). Re-pointing it along the capped total force, which
                # the dashpot turns towards vt, booked the turn of an unchanged length as slip.
                l_max = wp.length(xt)
                xi_new = xt
                if kt * l_max > cap:
                    xi_new = xt * (cap / (kt * l_max))
                # (>= 0: the cap only hits the dashpot's share where kt xt . vt > -ct |vt|^2 / 2.)
                damped = -wp.dot(ft + kt * xi_new, vt) * dt
            else:
                xi_new = xt
            # Dissipated: the dashpot's work and the slip xt - xi_new at the spring's force averaged
            # over the step (kt |xi| before it, kt |xi_new| after: exact where the spring lets go as
            # the cap falls and where it slides at a constant cap; where the cap changes while it
            # slides, a residue of first order in dt). Both >= 0, and a sticking contact books only
            # its dashpot: its spring is a potential that the step integrates like the normal force.
            # Booking instead the work of this step's force, -ft.vt dt, less the change of the
            # spring's energy pairs this step's force with the last step's displacement: it books
            # kt |vt|^2 dt^2 / 2 too much every step a contact sticks, an error of first order in dt.
            plastic = scalar(0.5) * kt * (l0 + wp.length(xi_new)) * wp.length(xt - xi_new)
            lost += plastic + damped
            # The contact's energy: the spring, and the slip's loss until the step books it.
            energy += scalar(0.5) * kt * wp.dot(xi_new, xi_new) + plastic
            # The twist channel's force acts at the rim: a couple about n of that force times r_t.
            f_tw = wp.dot(ft, n)
            ft = ft - f_tw * n
            force += ft
            torque += wp.cross(point, ft) + (f_tw * r_t) * n
            # Rocking damping: the tangential dashpot spread over the contact's disc resists the relative
            # rotation about tangential axes with ct R^2 / 4, capped at ROLL_FRACTION mu F_n R. The volume
            # law gives a face no stiffness against a small tilt (V does not change), so a grain rocking or
            # wobbling on a face (rolling round its rim, V constant) lost nothing and a pile kept moving.
            r_c = wp.sqrt(s_norm / scalar(3.14159265358979))
            w_rel = w_a - w_b
            w_t = w_rel - wp.dot(w_rel, n) * n
            tr = -(scalar(0.25) * ct * r_c * r_c) * w_t
            tr_norm = wp.length(tr)
            cap_r = scalar(ROLL_FRACTION) * cap * r_c
            if tr_norm > cap_r:
                tr = tr * (cap_r / tr_norm)
            torque += tr
            lost -= wp.dot(tr, w_t) * dt
        return force, torque, xi_new, turn_new, energy, lost, n, point, fn, ft

    return Response(scalar, law, friction, diagnostics, frame, kept_energy, dashpot, dashpot_factored, respond)


# ---------------------------------------------------------------------------------------------
# Batch kernels for polydem.overlap and polydem.contact_forces: the same functions, one thread
# per pair.


@functools.cache
def batch_struct(scalar):
    """The ``wp.struct`` of N overlaps that both batch kernels read: V, V times the centroid, S_A, M_A and
    the fallback area vector (about and relative to x_A), and r_ab = x_B - x_A; one precision."""
    vec3 = wp.types.vector(3, scalar)
    members = arrays(volume=scalar, volume_moment=vec3, area_a=vec3, moment_a=vec3, fallback_a=vec3, r_ab=vec3)
    return make_struct("BatchOverlaps", **members)


@functools.cache
def batch_out_struct(scalar):
    """The ``wp.struct`` of what the batch kernels write per overlap, in one precision: the ``kind``
    (-1 without overlap, REGULAR, ENCLOSED, SLIVER), unit ``normal`` and contact ``point`` of
    :func:`make_frame_kernel`; the ``force`` and ``torque_a`` on A and the ``energy`` of
    :func:`make_force_kernel` (each kernel writes its own; the others may be left empty)."""
    vec3 = wp.types.vector(3, scalar)
    return make_struct(
        "BatchContacts", **arrays(kind=int, normal=vec3, point=vec3, force=vec3, torque_a=vec3, energy=scalar)
    )


@functools.cache
def make_frame_kernel(scalar):
    """Kernel: normal, contact point and kind of N overlaps (kind -1 where V <= 0)."""
    frame = make_frame(scalar)

    @wp.kernel(enable_backward=False, module="unique")
    def contact_frame_kernel(
        r_min: scalar, share_a: scalar, pairs: batch_struct(scalar), out: batch_out_struct(scalar)
    ):
        i = wp.tid()
        vol = pairs.volume[i]
        r_ab = pairs.r_ab[i]
        if vol <= scalar(0.0):
            # No overlap: the normal along the line of centres, the point on it where the
            # bounding spheres would meet in proportion to their radii.
            out.kind[i] = -1
            out.normal[i] = frame.centre_line(r_ab)
            out.point[i] = share_a * r_ab
            return
        kind, n, point, s, mom, s_norm = frame.contact_frame(
            vol, pairs.volume_moment[i], pairs.area_a[i], pairs.moment_a[i], pairs.fallback_a[i], r_ab, r_min
        )
        out.kind[i] = kind
        out.normal[i] = n
        out.point[i] = point

    return contact_frame_kernel


@functools.cache
def make_force_kernel(scalar, law: str):
    """Kernel: elastic wrench on A and energy of N overlaps under one contact law (no damping,
    no friction), with the smaller bounding radius of each pair (``pair_r_min``)."""
    resp = make_response(scalar, law, friction=False, diagnostics=True)
    zero3 = wp.constant(resp.frame.vec3(scalar(0.0), scalar(0.0), scalar(0.0)))

    @wp.kernel(enable_backward=False, module="unique")
    def contact_force_kernel(
        k: scalar,
        m: scalar,
        pairs: batch_struct(scalar),
        pair_r_min: wp.array(dtype=scalar),
        out: batch_out_struct(scalar),
    ):
        i = wp.tid()
        vol = pairs.volume[i]
        if vol <= scalar(0.0):
            out.force[i] = zero3
            out.torque_a[i] = zero3
            out.energy[i] = scalar(0.0)
            return
        zero = scalar(0.0)
        force, torque, xi, turn, energy, lost, n, point, fn, ft = resp.respond(
            vol, pairs.volume_moment[i], pairs.area_a[i], pairs.moment_a[i], pairs.fallback_a[i], pairs.r_ab[i],
            zero3, zero3, zero3, zero3,
            k, m, scalar(1.0), zero, zero,
            zero3, zero,
            zero, zero, pair_r_min[i], zero, zero, scalar(1.0),
        )  # fmt: skip
        out.force[i] = force
        out.torque_a[i] = torque
        out.energy[i] = energy

    return contact_force_kernel


def batch_overlaps(
    scalar: Any,
    device: Any,
    *,
    volume: np.ndarray,
    first_moment: np.ndarray,
    area: np.ndarray,
    moment: np.ndarray,
    fallback: np.ndarray,
    r_ab: np.ndarray,
) -> Any:
    """The :func:`batch_struct` of N overlaps in ``scalar`` on ``device``, from numpy arrays relative to x_A:
    V (N,), V times the centroid, S_A, M_A, the fallback area vector and x_B - x_A (N, 3)."""
    vec3 = wp.types.vector(3, scalar)
    np_scalar = np.float32 if scalar == wp.float32 else np.float64
    pairs = batch_struct(scalar)()
    columns = dict(
        volume=volume, volume_moment=first_moment, area_a=area, moment_a=moment, fallback_a=fallback, r_ab=r_ab
    )
    for name, a in columns.items():
        a = np.ascontiguousarray(a, dtype=np_scalar)
        setattr(pairs, name, wp.array(a, dtype=vec3 if a.ndim == 2 else scalar, device=device))
    return pairs


def launch_contact_frame(pairs: Any, *, r_min: float, share_a: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Kind (-1 no overlap, REGULAR, ENCLOSED, SLIVER), normal and contact point (relative to x_A) of the
    overlaps ``pairs`` (:func:`batch_overlaps`), in their precision, as numpy arrays."""
    scalar = pairs.volume.dtype
    device = pairs.volume.device
    n = pairs.volume.shape[0]
    vec3 = wp.types.vector(3, scalar)
    kind = wp.zeros(n, dtype=int, device=device)
    normal = wp.zeros(n, dtype=vec3, device=device)
    point = wp.zeros(n, dtype=vec3, device=device)
    out = filled(batch_out_struct(scalar), kind=kind, normal=normal, point=point)
    wp.launch(make_frame_kernel(scalar), dim=n, inputs=[scalar(r_min), scalar(share_a), pairs, out], device=device)
    return kind.numpy(), normal.numpy().astype(np.float64), point.numpy().astype(np.float64)


def launch_contact_force(
    pairs: Any, *, law: str, k: float, m: float, r_min: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Force on A, torque on A about x_A and energy of the float64 overlaps ``pairs`` (:func:`batch_overlaps`)
    under a contact law (``r_min`` per pair), as numpy arrays."""
    scalar = wp.float64
    device = pairs.volume.device
    n = pairs.volume.shape[0]
    vec3 = wp.types.vector(3, scalar)
    r_min = wp.array(np.ascontiguousarray(r_min, dtype=np.float64), dtype=scalar, device=device)
    force = wp.zeros(n, dtype=vec3, device=device)
    torque = wp.zeros(n, dtype=vec3, device=device)
    energy = wp.zeros(n, dtype=scalar, device=device)
    out = filled(batch_out_struct(scalar), force=force, torque_a=torque, energy=energy)
    wp.launch(make_force_kernel(scalar, law), dim=n, inputs=[scalar(k), scalar(m), pairs, r_min, out], device=device)
    return force.numpy(), torque.numpy(), energy.numpy()
