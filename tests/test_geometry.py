"""The Warp geometry and response functions called directly, against the float64 reference.

test_contact.py reaches the same functions through polydem.overlap(); here small kernels call
pair_geometry (both orders of the bodies), plane_geometry (the wall path) and respond (the
contact law and its damping branch) one by one.
"""

import functools

import numpy as np
import pytest
import warp as wp
from polydem.kernels.geometry import make_geometry, make_primitives
from polydem.kernels.response import make_response
from reference_geometry import reference_overlap
from scipy.spatial.transform import Rotation

from polydem import ContactLaw, ConvexShape
from polydem.shapeset import ShapeSet

F64 = wp.float64
VEC3 = wp.types.vector(3, F64)
TRANSFORM = wp.types.transformation(F64)


@functools.cache
def pair_kernel(max_poly, max_faces):
    geom = make_geometry(F64, max_poly, max_faces)
    pair_geometry = geom.pair_geometry

    @wp.kernel(enable_backward=False, module="unique")
    def kernel(
        shapes: geom.shapes,
        shape_a: int,
        shape_b: int,
        pose_a: wp.array(dtype=TRANSFORM),
        pose_b: wp.array(dtype=TRANSFORM),
        out: wp.array2d(dtype=VEC3),
        volume: wp.array(dtype=F64),
    ):
        i = wp.tid()
        vol, vol_c, s_a, m_a, s_b, m_b, fb_a, overflow = pair_geometry(shapes, shape_a, shape_b, pose_a[i], pose_b[i])
        volume[i] = vol
        out[i, 0] = vol_c
        out[i, 1] = s_a
        out[i, 2] = m_a
        out[i, 3] = s_b
        out[i, 4] = m_b

    return kernel


@functools.cache
def wall_kernel():
    prim = make_primitives(F64)
    plane_geometry = prim.plane_geometry

    @wp.kernel(enable_backward=False, module="unique")
    def kernel(
        shapes: prim.shapes,
        poses: wp.array(dtype=TRANSFORM),
        normal: VEC3,
        offset: F64,
        out: wp.array2d(dtype=VEC3),
        volume: wp.array(dtype=F64),
    ):
        i = wp.tid()
        vol, vol_c, s_a, m_a, fb = plane_geometry(shapes, 0, poses[i], normal, offset)
        volume[i] = vol
        out[i, 0] = vol_c
        out[i, 1] = s_a
        out[i, 2] = m_a

    return kernel


def world(shape, pose):
    return Rotation.from_quat(pose[3:]).apply(np.array(shape.vertices)) + pose[:3]


def random_poses(rng, n, spread):
    q = Rotation.random(n, random_state=int(rng.integers(1 << 30))).as_quat()
    return np.hstack([rng.normal(size=(n, 3)) * spread, q])


def run_pairs(shapes, sa, sb, pa, pb):
    n = len(pa)
    dev = shapes.device
    out = wp.zeros((n, 5), dtype=VEC3, device=dev)
    volume = wp.zeros(n, dtype=F64, device=dev)
    wp.launch(
        pair_kernel(shapes.max_poly_bound, shapes.max_faces),
        dim=n,
        inputs=[*shapes.kernel_args(), sa, sb, wp.array(pa, dtype=TRANSFORM, device=dev)],
        outputs=[wp.array(pb, dtype=TRANSFORM, device=dev), out, volume],
        device=dev,
    )
    return volume.numpy(), out.numpy()


def test_pair_geometry_both_orders_against_reference(device):
    """The small body first and the large one first: the clipping runs in the larger body's frame
    either way, and each order matches the reference and the other order with A and B swapped."""
    small = ConvexShape.rock(n_points=18, size=0.8, seed=21)
    large = ConvexShape.rock(n_points=30, size=1.5, seed=22)
    assert small.radius < large.radius
    shapes = ShapeSet([small, large], device=device, precision="float64")
    rng = np.random.default_rng(3)
    pa = random_poses(rng, 24, 0.1)
    pb = random_poses(rng, 24, 0.6)
    vol_ab, ab = run_pairs(shapes, 0, 1, pa, pb)
    vol_ba, ba = run_pairs(shapes, 1, 0, pb, pa)
    scale = 2.0 * large.radius
    touching = 0
    for i in range(len(pa)):
        ref = reference_overlap(world(small, pa[i]), world(large, pb[i]))
        touching += ref["volume"] > 0.0
        xa = pa[i, :3]
        assert abs(vol_ab[i] - ref["volume"]) < 1e-9 * scale**3
        np.testing.assert_allclose(ab[i, 1], ref["area_vector"], atol=1e-9 * scale**2)
        np.testing.assert_allclose(ab[i, 3], ref["area_vector_b"], atol=1e-9 * scale**2)
        np.testing.assert_allclose(ab[i, 2] + np.cross(xa, ab[i, 1]), ref["moment"], atol=1e-9 * scale**3)
        if ref["volume"] > 0.0:
            np.testing.assert_allclose(ab[i, 0], ref["volume"] * (ref["centroid"] - xa), atol=1e-9 * scale**4)
        # Swapped: B's quantities of one order are A's of the other (moments about the other centre).
        r = pb[i, :3] - xa
        assert abs(vol_ba[i] - vol_ab[i]) < 1e-12 * scale**3
        np.testing.assert_allclose(ba[i, 1], ab[i, 3], atol=1e-12 * scale**2)
        np.testing.assert_allclose(ba[i, 3], ab[i, 1], atol=1e-12 * scale**2)
        np.testing.assert_allclose(ba[i, 2] + np.cross(r, ba[i, 1]), ab[i, 4], atol=1e-12 * scale**3)
    assert touching >= 12


def half_space_box(normal, offset, size=40.0):
    """Vertices of a box that stands for the half-space n.x <= offset near the origin."""
    normal = np.asarray(normal, dtype=np.float64)
    rot = Rotation.align_vectors([normal], [[0.0, 0.0, 1.0]])[0]
    corners = np.array([[x, y, z] for x in (-size, size) for y in (-size, size) for z in (-2 * size, 0.0)])
    return rot.apply(corners) + offset * normal


@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.3, -0.5, 0.8)])
def test_plane_geometry_against_reference(device, normal):
    """The wall path: one body against a half-space, every quantity against the reference."""
    body = ConvexShape.rock(n_points=24, size=1.0, seed=31)
    shapes = ShapeSet([body], device=device, precision="float64")
    n = np.asarray(normal) / np.linalg.norm(normal)
    offset = 0.2
    rng = np.random.default_rng(6)
    poses = random_poses(rng, 16, 0.0)
    poses[:, :3] = (offset + rng.uniform(-0.6, 0.6, size=(16, 1))) * n + rng.normal(size=(16, 3)) * 0.3
    dev = shapes.device
    out = wp.zeros((len(poses), 3), dtype=VEC3, device=dev)
    volume = wp.zeros(len(poses), dtype=F64, device=dev)
    wp.launch(
        wall_kernel(),
        dim=len(poses),
        inputs=[*shapes.kernel_args(), wp.array(poses, dtype=TRANSFORM, device=dev), VEC3(*n), F64(offset)],
        outputs=[out, volume],
        device=dev,
    )
    volume = volume.numpy()
    out = out.numpy()
    wall = half_space_box(n, offset)
    touching = 0
    for i, p in enumerate(poses):
        ref = reference_overlap(world(body, p), wall)
        touching += 0.0 < ref["volume"] < body.volume * (1.0 - 1e-9)
        xa = p[:3]
        assert abs(volume[i] - ref["volume"]) < 1e-10
        np.testing.assert_allclose(out[i, 1], ref["area_vector"], atol=1e-10)
        np.testing.assert_allclose(out[i, 2] + np.cross(xa, out[i, 1]), ref["moment"], atol=1e-9)
        if ref["volume"] > 0.0:
            np.testing.assert_allclose(out[i, 0], ref["volume"] * (ref["centroid"] - xa), atol=1e-10)
    assert touching >= 8


@functools.cache
def response_kernel(law):
    resp = make_response(F64, law, friction=False)
    respond = resp.respond
    zero3 = wp.constant(VEC3(0.0, 0.0, 0.0))

    @wp.kernel(enable_backward=False, module="unique")
    def kernel(
        volume: wp.array(dtype=F64),
        turn: wp.array(dtype=F64),
        dvdt: wp.array(dtype=F64),
        k: F64,
        m: F64,
        e: F64,
        force: wp.array(dtype=VEC3),
        turn_out: wp.array(dtype=F64),
        energy: wp.array(dtype=F64),
        lost: wp.array(dtype=F64),
    ):
        i = wp.tid()
        v = volume[i]
        # A flat contact: S_A along +z with |S_A| = 1, A moving into B at dV/dt.
        s = VEC3(F64(0.0), F64(0.0), F64(1.0))
        vel = VEC3(F64(0.0), F64(0.0), dvdt[i])
        zero = F64(0.0)
        # face_area 0: no resolved toe, so the branches are those of the law itself.
        f, t, xi, tn, en, dl, n, point, fn, ft = respond(
            v, v * VEC3(F64(0.0), F64(0.0), F64(0.5)), s, zero3, zero3, VEC3(F64(0.0), F64(0.0), F64(1.0)),
            vel, zero3, zero3, zero3,
            k, m, e, zero, zero,
            zero3, turn[i],
            F64(1.0e-4), F64(1.0e-4), F64(1.0), F64(0.0), F64(1.0), F64(1.0),
        )  # fmt: skip
        force[i] = f
        turn_out[i] = tn
        energy[i] = en
        lost[i] = dl

    return kernel


@pytest.mark.parametrize("law", [ContactLaw("linear", 1e6), ContactLaw("hertz", 1e7), ContactLaw("power", 1e8, 2.5)])
def test_respond_branches_against_the_law(device, law):
    """Loading: force -W'(V) S_A, energy W(V), the turning volume follows V. Unloading below the
    turning volume V_t: pressure W'(u) at u = V_t - (V_t - V) / e^2, energy (1 - e^2) W(V_t) +
    e^2 W(u). Reloading from below V_t: back on W, the loop's area booked as dissipated."""
    e = 0.6
    e2 = e * e
    vt = 1e-3
    v = np.array([2e-4, 1e-3, 9e-4, 8e-4, 6e-4, 5e-4])
    turn = np.array([0.0, 1e-3, vt, vt, vt, vt])
    dvdt = np.array([1.0, 1.0, -1.0, -1.0, -1.0, 1.0])  # loading, loading, unloading x3, reloading
    dev = wp.get_device(device)
    n = len(v)
    force = wp.zeros(n, dtype=VEC3, device=dev)
    turn_out = wp.zeros(n, dtype=F64, device=dev)
    energy = wp.zeros(n, dtype=F64, device=dev)
    lost = wp.zeros(n, dtype=F64, device=dev)
    wp.launch(
        response_kernel(law.kind),
        dim=n,
        inputs=[
            wp.array(v, dtype=F64, device=dev),
            wp.array(turn, dtype=F64, device=dev),
            wp.array(dvdt, dtype=F64, device=dev),
            F64(law.k),
            F64(law.exponent),
            F64(e),
        ],
        outputs=[force, turn_out, energy, lost],
        device=dev,
    )
    fz = force.numpy()[:, 2]
    turn_out = turn_out.numpy()
    energy = energy.numpy()
    lost = lost.numpy()
    u = np.maximum(vt - (vt - v) / e2, 0.0)
    loading = dvdt > 0.0
    expected_f = np.where(loading, -law.derivative(v), -np.where(u > 0.0, law.derivative(u), 0.0))
    expected_e = np.where(loading, law.energy(v), (1.0 - e2) * law.energy(vt) + e2 * law.energy(u))
    np.testing.assert_allclose(fz, expected_f, rtol=1e-12)
    np.testing.assert_allclose(energy, expected_e, rtol=1e-12)
    np.testing.assert_array_equal(turn_out, np.where(loading, v, turn))
    reload_loss = (1.0 - e2) * law.energy(vt) + e2 * law.energy(u[-1]) - law.energy(v[-1])
    np.testing.assert_allclose(lost, [0, 0, 0, 0, 0, reload_loss], rtol=1e-12, atol=0.0)
    assert reload_loss > 0.0


@functools.cache
def toe_response_kernel():
    respond = make_response(F64, "hertz", friction=False).respond
    zero3 = wp.constant(VEC3(0.0, 0.0, 0.0))

    @wp.kernel(enable_backward=False, module="unique")
    def kernel(
        volume: wp.array(dtype=F64),
        k: F64,
        dt: F64,
        toe_dt: F64,
        face_area: F64,
        inv_mass: F64,
        pressure: wp.array(dtype=F64),
        energy: wp.array(dtype=F64),
    ):
        i = wp.tid()
        v = volume[i]
        s = VEC3(F64(0.0), F64(0.0), F64(1.0))  # |S_A| = 1: the force is the pressure
        zero = F64(0.0)
        f, t, xi, tn, en, dl, n, point, fn, ft = respond(
            v, v * VEC3(F64(0.0), F64(0.0), F64(0.5)), s, zero3, zero3, VEC3(F64(0.0), F64(0.0), F64(1.0)),
            zero3, zero3, zero3, zero3,
            k, F64(1.5), F64(1.0), zero, zero,
            zero3, zero,
            dt, toe_dt, F64(1.0), face_area, inv_mass, F64(1.0),
        )  # fmt: skip
        pressure[i] = -f[2]
        energy[i] = en

    return kernel


def test_the_resolved_toe_is_the_gradient_of_its_energy_and_the_host_twins(device):
    """The hertz law with its resolved toe, in float64, across V_c: the pressure the kernel applies is dW/dV of
    the energy it books (central differences, to 1e-7), W' and W are continuous at V_c, V_c is the toe of
    ``toe_dt`` (not of the run's ``dt``) and the pressure is what the host twin (scene.depth.Law) says. A toe
    pressure off by 1e-4 of itself passed every other test."""
    from polydem.scene import depth

    k, dt, toe_dt, area, inv_mass = 1.0e9, 1.0e-6, 4.0e-6, 1.0e-4, 2.0 / 0.0025
    vc = depth.toe_volume("hertz", k, None, 1.0, toe_dt, area, 1.0, inv_mass)
    assert 0.0 < vc < 1.0 and vc != depth.toe_volume("hertz", k, None, 1.0, dt, area, 1.0, inv_mass)
    x = np.array([0.05, 0.3, 0.7, 0.999, 1.001, 2.0, 10.0])
    h = 1e-5 * vc
    v = np.concatenate([x * vc - h, x * vc, x * vc + h])
    dev = wp.get_device(device)
    pressure = wp.zeros(len(v), dtype=F64, device=dev)
    energy = wp.zeros(len(v), dtype=F64, device=dev)
    inputs = [wp.array(v, dtype=F64, device=dev), F64(k), F64(dt), F64(toe_dt), F64(area), F64(inv_mass)]
    wp.launch(toe_response_kernel(), dim=len(v), inputs=inputs, outputs=[pressure, energy], device=dev)
    p = pressure.numpy().reshape(3, -1)
    en = energy.numpy().reshape(3, -1)
    np.testing.assert_allclose(p[1], (en[2] - en[0]) / (2.0 * h), rtol=1e-7)
    law = depth.Law("hertz", k, vc=vc)
    np.testing.assert_allclose(p[1], [law.derivative(vi) for vi in x * vc], rtol=1e-12)
    # continuous across V_c: the two sides of x = 1 +- 1e-3 differ by the slope times 2e-3 V_c only (1e-3, 3e-3)
    assert abs(p[1][4] - p[1][3]) < 2e-3 * p[1][3] and abs(en[1][4] - en[1][3]) < 5e-3 * en[1][3]
