"""The precisions of the simulator ("float32", "mixed", "float64"): far from the origin, float64
end to end, the broad phase's float32 input, and the choices offered."""

import numpy as np
import pytest
import warp as wp

import polydem
from polydem.scene import Scene
from polydem.shapes import ConvexShape

EPS32 = 2.0**-24
EDGE = 0.1  # [m]
DROP = 0.2  # centre height above the floor at the start [m]
DURATION = 0.5  # [s]
SAMPLES = 50


def drop_scene(z0, precision, floor="plane", walls=True):
    """A 0.1 m cube (its centre 0.2 m up) over a floor at height z0: a plane wall, or a fixed
    1 x 1 x 0.1 m slab (the pair path)."""
    scene = Scene(gravity=(0.0, 0.0, -9.81), dt="auto", name="drop", precision=precision)
    scene.add_material("steel", density=7800.0, law="hertz", k=1.0e8, restitution=0.5, friction=0.3)
    scene.add_shape("cube", ConvexShape.box(EDGE, name="cube"))
    if walls and floor == "plane":
        scene.add_plane((0.0, 0.0, z0), (0.0, 0.0, 1.0), "steel")
    elif walls:
        scene.add_shape("slab", ConvexShape.box(1.0, 1.0, 0.1, name="slab"))
        scene.add_body("slab", "steel", position=(0.0, 0.0, z0 - 0.05), kind="fixed")
    scene.add_body("cube", "steel", position=(0.0, 0.0, z0 + DROP))
    return scene


def trajectory(device, z0, precision, floor="plane"):
    """(steps, the cube's centre relative to the floor at SAMPLES times over DURATION (SAMPLES, 3))."""
    sim = polydem.Simulation(drop_scene(z0, precision, floor), device=device)
    per = int(round(DURATION / sim.dt)) // SAMPLES
    out = []
    for _ in range(SAMPLES):
        sim.step(per)
        out.append(sim.state()["body_position"][-1] - (0.0, 0.0, z0))
    return per * SAMPLES, np.array(out)


_AT_ORIGIN = {}


def at_origin(device, precision, floor):
    key = (device, precision, floor)
    if key not in _AT_ORIGIN:
        _AT_ORIGIN[key] = trajectory(device, 0.0, precision, floor)
    return _AT_ORIGIN[key]


# A cube far from the origin falls, bounces and comes to rest as one at the origin: the mixed
# precision clips each contact in float32 about body A (or about the body at a wall) and keeps
# the poses in float64; float64 does everything in float64. The tolerance, 1e-7 m (1e-6 of the
# edge, 5e-5 of the deepest penetration, 2e-3 m), is far above what the float64 rounding of
# coordinates of 1e4 m (1.8e-12 m) leaves after 4500 steps and two impacts (1e-11 m in mixed,
# 1e-9 m in float64 with a slab floor on the CPU) and far below float32's error.
FAR_TOLERANCE = 1.0e-7


@pytest.mark.parametrize("floor", ["plane", "slab"])
@pytest.mark.parametrize("z0", [1.0e3, 1.0e4])
@pytest.mark.parametrize("precision", ["mixed", "float64"])
def test_far_from_origin_moves_as_at_origin(device, precision, z0, floor):
    """Before (float32 only): the same drop 1e4 m from the origin ends 0.07 m (plane) or 0.12 m
    (slab) above the floor instead of 0.05 m and is off by up to 0.15 m on the way (each step's
    displacement is below the float32 spacing of 1e-3 m while the cube is slow); at 1e3 m it is off
    by 5e-3 m. Now, in "mixed" and "float64", the trajectory relative to the floor is the one at
    the origin to 1e-7 m."""
    steps, near = at_origin(device, precision, floor)
    _, far = trajectory(device, z0, precision, floor)
    assert near[:, 2].min() < 0.5 * EDGE  # it reached the floor ...
    assert abs(near[-1, 2] - 0.5 * EDGE) < 1.0e-3  # ... and rests on it
    np.testing.assert_allclose(far, near, rtol=0.0, atol=FAR_TOLERANCE)


def test_float64_run_matches_float32_to_float32_accuracy(device):
    """The drop with its bounces in float64 against float32: a float32 run rounds the positions once
    a step (2^-24 of 0.2 m), so after n steps the two stay within n 2^-24 0.2 m (5e-5 m after 4500
    steps; 1.3e-5 m measured at the largest, after the second impact); and they do differ, by more
    than one float32 rounding, so the float64 run is not float32 in disguise."""
    steps, f32 = at_origin(device, "float32", "plane")
    _, f64 = at_origin(device, "float64", "plane")
    diff = np.abs(f64 - f32).max()
    assert diff < steps * EPS32 * DROP
    assert diff > EPS32 * DROP


def test_float64_free_fall_matches_closed_form(device):
    """Symplectic Euler from x_0, v_0 gives x_n = x_0 + t v_0 + g t^2 / 2 + g t dt / 2 exactly in
    exact arithmetic; float64 keeps that to 1e-12 relative (measured 1e-14; float32 is off by 9e-6)."""
    scene = drop_scene(0.0, "float64", walls=False)
    scene.dt = 5.0e-4
    sim = polydem.Simulation(scene, device=device)
    x0 = sim.state()["body_position"][0]
    v0 = np.array([1.0, -0.5, 2.0])
    wp.copy(sim.current_state.body_v, wp.array(v0[None, :], dtype=wp.vec3d, device=sim.device))
    n = 1000
    sim.step(n)
    t, g = n * scene.dt, np.asarray(scene.gravity)
    exact = x0 + t * v0 + 0.5 * g * t * t + 0.5 * g * t * scene.dt
    got = sim.state()["body_position"][0]
    np.testing.assert_allclose(got, exact, rtol=1.0e-12, atol=1.0e-12 * np.abs(exact).max())
    assert wp.types.types_equal(sim.current_state.body_q.dtype, wp.transformd)


def test_dtypes_per_precision(device):
    """State, model and pair arrays carry the dtype each mode documents; the readers give float64."""
    expect = {
        "float32": (wp.float32, wp.float32),
        "mixed": (wp.float64, wp.float32),
        "float64": (wp.float64, wp.float64),
    }
    for precision, (s, c) in expect.items():
        sim = polydem.Simulation(drop_scene(0.0, precision, "slab"), device=device)
        st, m, pairs = sim.current_state, sim.model, sim.current_contacts
        assert st.body_q.dtype == wp.types.transformation(s) and st.body_v.dtype == wp.types.vector(3, s)
        assert st.body_dissipated.dtype == s and st.wall_turn.dtype == c
        assert m.body_inv_mass.dtype == s and m.plane_offset.dtype == s and m.material_k.dtype == c
        assert pairs.pair_turn.dtype == c and pairs.pair_force.dtype == wp.types.vector(3, c)
        assert sim.state()["body_position"].dtype == np.float64
        assert isinstance(sim.energy()["total"], float)


def test_broadphase_finds_far_pairs_whose_float32_centres_round_apart(device):
    """Two cubes 1e4 m from the origin whose bounding spheres overlap by 1e-5 m in float64, with no
    skin, are a candidate pair although their float32 centres (spacing 1e-3 m there) round 6e-4 m
    apart (before: only float32 poses reached the broad phase; now float64 poses reach it through
    float32_input_kernel, which grows the radii by the rounding)."""
    from polydem.kernels.broadphase import BroadPhase, float32_input_kernel

    r = 0.5 * np.sqrt(3.0) * EDGE
    x = np.array([[1.0e4 + 0.0003, 0.0, 0.0], [1.0e4 + 0.0003 + 2.0 * r - 1.0e-5, 0.0, 0.0]])
    gap32 = float(np.float32(x[1, 0]) - np.float32(x[0, 0]))
    assert gap32 > 2.0 * np.float32(r)  # rounded, the spheres no longer touch
    q = np.hstack([x, np.tile([0.0, 0.0, 0.0, 1.0], (2, 1))])
    body_q = wp.array(q, dtype=wp.transformd, device=device)
    radius = wp.array(np.full(2, r, dtype=np.float32), dtype=float, device=device)
    q32 = wp.zeros(2, dtype=wp.transform, device=device)
    r32 = wp.zeros(2, dtype=float, device=device)
    wp.launch(float32_input_kernel, dim=2, inputs=[radius, body_q], outputs=[q32, r32], device=device)
    flags = wp.zeros(2, dtype=int, device=device)
    bp = BroadPhase(2, device, skin=0.0)
    bp.build(q32, r32, flags)
    a, b, _ = bp.pairs_numpy()
    assert list(zip(a.tolist(), b.tolist(), strict=True)) == [(0, 1)]
