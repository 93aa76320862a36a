"""Triangle-mesh walls against slow, obviously right references: a plane, fixed convex bodies, finite differences."""

import itertools

import numpy as np
import pytest
import trimesh
import warp as wp

import polydem
from polydem import ConvexShape, Scene, SceneError, Simulation
from polydem.meshwall import MeshWallError, build_cells
from polydem.quaternions import quat_to_matrix

CUBE = 0.02


def floor_grid(n, size=1.0, jitter=0.0, seed=0):
    """A square floor z = 0 of 2 n^2 triangles facing +z; inner vertices moved by up to ``jitter`` cells."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    x, y = np.meshgrid(xs, xs, indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    inner = (np.abs(v[:, 0]) < size / 2 - 1e-12) & (np.abs(v[:, 1]) < size / 2 - 1e-12)
    v[inner, :2] += np.random.default_rng(seed).uniform(-jitter, jitter, (inner.sum(), 2)) * size / n
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])
    return v, f


def base_scene(precision="float64", law="hertz", friction=0.0, restitution=1.0, gravity=(0.0, 0.0, -9.81)):
    sc = Scene(gravity=gravity, dt="auto", precision=precision)
    k = 1.0e8 if law == "hertz" else 1.0e6
    sc.add_material("m", density=2500.0, k=k, restitution=restitution, friction=friction, law=law)
    sc.add_shape("cube", ConvexShape.box(CUBE))
    sc.add_shape("rock", ConvexShape.rock(20, 0.03, seed=3))
    return sc


def add_grains(sc, centres, seed, depth=(1e-4, 2e-3), down=(0.0, 0.0, 1.0)):
    """Grains of random orientation whose lowest point along -``down`` lies ``depth`` below the centre's plane."""
    rng = np.random.default_rng(seed)
    down = np.asarray(down, dtype=float)
    for k, c in enumerate(centres):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        name = "cube" if k % 2 == 0 else "rock"
        low = lowest(sc.shapes[name], q, down)
        sc.add_body(name, "m", position=np.asarray(c) + down * (-low - rng.uniform(*depth)), orientation=q)


def lowest(shape, q, d):
    """The least extent of ``shape`` at input-frame orientation ``q`` along direction ``d``."""
    return (shape.to_input_frame(shape.vertices) @ quat_to_matrix(q).T @ d).min()


def pressed(shape, q, point, d, depth):
    """The position that puts the vertex of ``shape`` (orientation ``q``) furthest along -``d`` at
    ``point - depth d``."""
    v = shape.to_input_frame(shape.vertices) @ quat_to_matrix(q).T
    return np.asarray(point) - depth * np.asarray(d) - v[np.argmin(v @ d)]


def contacts_by_body(sim, wall_rows=True):
    c = sim.contacts()
    keep = c["body_b"] < 0 if wall_rows else c["body_b"] >= 0
    order = np.argsort(c["body_a"][keep], kind="stable")
    return {k: v[keep][order] for k, v in c.items()}


def first_forces(sim):
    sim.step(1)  # the forces of the first step are those at the initial state
    st = sim.current_state
    return st.body_f.numpy().astype(np.float64), st.body_t.numpy().astype(np.float64)


def grid_centres(n=6, spacing=0.12, z=0.0):
    return [
        (spacing * (i - (n - 1) / 2) + 0.01 * j, spacing * (j - (n - 1) / 2) + 0.007 * i, z)
        for i in range(n)
        for j in range(n)
    ]


@pytest.mark.parametrize("precision", ["float64", "mixed"])
def test_flat_mesh_of_many_triangles_acts_as_one_plane(device, precision):
    """Grains pressed into a floor of 2 triangles, of 2,048 jittered triangles (a cell each, and joined into
    one), and a plane wall: the same overlap, force, torque and energy per grain, to rounding."""
    results = {}
    for kind in ("plane", "2", "2048", "2048/tri"):
        sc = base_scene(precision)
        if kind == "plane":
            sc.add_plane((0, 0, 0), (0, 0, 1), "m")
        else:
            sc.add_mesh_wall(floor_grid(1) if kind == "2" else floor_grid(32, jitter=0.3), "m")
        add_grains(sc, grid_centres(), seed=1)
        sim = Simulation(sc, device=device, join_flat_cells=kind != "2048/tri")
        c = contacts_by_body(sim)
        e = sim.energy()["contact"]
        results[kind] = (c, e, *first_forces(sim))
    c0, e0, f0, t0 = results["plane"]
    assert len(c0["volume"]) == 36
    tol = 1e-11 if precision == "float64" else 1e-4
    for kind in ("2", "2048", "2048/tri"):
        c, e, f, t = results[kind]
        np.testing.assert_array_equal(c["body_a"], c0["body_a"])
        np.testing.assert_allclose(c["volume"], c0["volume"], rtol=tol)
        np.testing.assert_allclose(c["normal_force"], c0["normal_force"], rtol=tol)
        np.testing.assert_allclose(c["normal"], c0["normal"], atol=tol)
        np.testing.assert_allclose(c["depth"], c0["depth"], rtol=tol, atol=1e-9 if precision == "mixed" else 0.0)
        assert e == pytest.approx(e0, rel=tol)
        np.testing.assert_allclose(f, f0, atol=tol * np.abs(f0).max())
        np.testing.assert_allclose(t, t0, atol=tol * np.abs(t0).max())


def test_cube_sliding_across_many_triangles_as_on_a_plane(device):
    """A spinning cube sliding frictionless across 2 and 2,048 triangles (a cell each, and joined) follows the
    plane-wall run."""
    runs = {}
    for kind in ("plane", "2", "2048", "2048/tri"):
        sc = base_scene("float64")
        if kind == "plane":
            sc.add_plane((0, 0, 0), (0, 0, 1), "m")
        else:
            sc.add_mesh_wall(floor_grid(1) if kind == "2" else floor_grid(32, jitter=0.3), "m")
        sc.add_body("cube", "m", position=(0.0123, 0.0371, 0.5 * CUBE - 6.0e-8), velocity=(2.0, 0.7, 0.0),
                    angular_velocity=(0.0, 0.0, 4.0))  # fmt: skip
        sim = Simulation(sc, device=device, join_flat_cells=kind != "2048/tri")
        rows = []
        for _ in range(6):
            sim.step(300)
            c = contacts_by_body(sim)
            st = sim.state()
            rows.append([c["normal_force"].sum(), c["volume"].sum(), sim.energy()["total"], *st["body_position"][0]])
        runs[kind] = np.array(rows)
    ref = runs["plane"]
    assert np.all(ref[:, 0] > 0.0)  # in contact at every sample
    assert ref[-1, 3] - ref[0, 3] > 0.1  # it crossed many triangles (of 0.03 m)
    for kind in ("2", "2048", "2048/tri"):
        np.testing.assert_allclose(runs[kind][:, :3], ref[:, :3], rtol=1e-7)
        np.testing.assert_allclose(runs[kind][:, 3:], ref[:, 3:], atol=1e-10)


def box_mesh(size, center):
    """A closed box, each face of 8 triangles (joined into one cell by default)."""
    m = trimesh.creation.box(extents=size).subdivide()
    m.apply_translation(center)
    return m


def test_closed_box_mesh_equals_a_fixed_box_body_at_edges_and_corners(device):
    """Grains over the convex edges and corners of a closed box mesh (a cell per triangle, and each face's
    eight joined) meet the same solid as a fixed convex box body: the overlaps and forces agree to rounding."""
    size, centre = np.array([0.3, 0.24, 0.16]), np.array([0.0, 0.0, -0.08])
    rng = np.random.default_rng(4)
    # The 8 corners and a point on each of the 12 edges, each grain pressed in along the outward
    # diagonal there.
    points, dirs = [], []
    for sign in np.array(np.meshgrid([-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0])).reshape(3, -1).T:
        points.append(centre + sign * size / 2)
        dirs.append(sign / np.sqrt(3.0))
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        for s1 in (-1.0, 1.0):
            for s2 in (-1.0, 1.0):
                sign = np.zeros(3)
                sign[others] = s1, s2
                p = centre + sign * size / 2
                p[axis] = centre[axis] + rng.uniform(-0.15, 0.15) * size[axis]
                points.append(p)
                dirs.append(sign / np.sqrt(2.0))
    results = {}
    for kind in ("body", "mesh", "mesh/tri"):
        for law in ("hertz", "linear"):
            sc = base_scene("float64", law=law)
            rng_g = np.random.default_rng(9)
            for p, d in zip(points, dirs, strict=True):
                q = rng_g.normal(size=4)
                q /= np.linalg.norm(q)
                pos = pressed(sc.shapes["cube"], q, p, d, rng_g.uniform(2e-4, 2e-3))
                sc.add_body("cube", "m", position=pos, orientation=q)
            if kind == "body":
                sc.add_shape("box", ConvexShape.box(*size))
                sc.add_body("box", "m", position=centre, kind="fixed")
            else:
                sc.add_mesh_wall(box_mesh(size, centre), "m", thickness=0.08)
            sim = Simulation(sc, device=device, join_flat_cells=kind != "mesh/tri")
            c = contacts_by_body(sim, wall_rows=(kind != "body"))
            results[kind, law] = (c, sim.energy()["contact"], *first_forces(sim))
    for kind, law in itertools.product(("mesh", "mesh/tri"), ("hertz", "linear")):
        (cb, eb, fb, tb), (cm, em, fm, tm) = results["body", law], results[kind, law]
        assert len(cb["volume"]) == len(points)
        np.testing.assert_array_equal(cm["body_a"], cb["body_a"])
        np.testing.assert_allclose(cm["volume"], cb["volume"], rtol=1e-10)
        np.testing.assert_allclose(cm["normal"], cb["normal"], atol=1e-10)
        np.testing.assert_allclose(cm["point"], cb["point"], atol=1e-12)
        assert em == pytest.approx(eb, rel=1e-10)
        n = len(points)
        np.testing.assert_allclose(fm[:n], fb[:n], atol=1e-10 * np.abs(fb).max())
        np.testing.assert_allclose(tm[:n], tb[:n], atol=1e-10 * np.abs(tb).max())


def crease_mesh(length=0.2, width=0.2, n=4):
    """An L-shaped open mesh: a floor z = 0 (x in [0, length]) facing +z meeting a wall x = 0
    (z in [0, length]) facing +x along the y axis: a concave crease (a 90 degree valley)."""
    v, f = floor_grid(n, size=1.0)
    v = v * [length, width, 1.0] + [length / 2, 0.0, 0.0]
    wall = v[:, [2, 1, 0]].copy()  # x <-> z: the floor turned up into the plane x = 0
    wall_f = f[:, ::-1] + len(v)  # the swap mirrors it: re-orient to face +x
    return np.concatenate([v, wall]), np.concatenate([f, wall_f])


def test_grain_in_a_concave_crease_meets_the_solid_once(device):
    """Grains pressed into both faces of a 90 degree crease: the overlap is that of the L-shaped
    solid, counted once where the two faces' solids meet; checked against two fixed boxes that
    partition the solid (linear law: the wrench of the sum is the sum of the wrenches)."""
    h = 0.05
    rng = np.random.default_rng(5)
    centres = []
    for k in range(7):
        y = -0.09 + 0.03 * k
        centres.append((rng.uniform(0.0, 0.004), y, rng.uniform(0.0, 0.004)))
    results = {}
    for kind in ("boxes", "mesh"):
        for law in ("hertz", "linear"):
            sc = base_scene("float64", law=law)
            rng_g = np.random.default_rng(6)
            for c in centres:
                q = rng_g.normal(size=4)
                q /= np.linalg.norm(q)
                # The lowest vertex 1.5 mm below the floor, the one nearest the wall 1 mm into it.
                pos = np.array([-lowest(sc.shapes["cube"], q, [1.0, 0.0, 0.0]) - 1e-3, c[1], 0.0])
                pos[2] = -lowest(sc.shapes["cube"], q, [0.0, 0.0, 1.0]) - 1.5e-3
                sc.add_body("cube", "m", position=pos, orientation=q)
            if kind == "boxes":
                sc.add_shape("floor", ConvexShape.box(0.2 + h, 0.2, h))
                sc.add_shape("wall", ConvexShape.box(h, 0.2, 0.2))
                sc.add_body("floor", "m", position=(0.1 - h / 2, 0.0, -h / 2), kind="fixed")
                sc.add_body("wall", "m", position=(-h / 2, 0.0, 0.1), kind="fixed")
            else:
                sc.add_mesh_wall(crease_mesh(), "m", thickness=h)
            sim = Simulation(sc, device=device)
            c = sim.contacts()
            results[kind, law] = (c, *first_forces(sim))
    n = len(centres)
    cb, fb, tb = results["boxes", "linear"]
    cm, fm, tm = results["mesh", "linear"]
    both = np.bincount(cb["body_a"], minlength=n)[:n]
    assert np.sum(both == 2) >= n // 2  # most grains reach behind both faces
    vb = np.bincount(cb["body_a"], weights=cb["volume"], minlength=n)[:n]
    vm = np.bincount(cm["body_a"], weights=cm["volume"], minlength=n)[:n]
    np.testing.assert_allclose(vm, vb, rtol=1e-10)
    np.testing.assert_allclose(fm[:n], fb[:n], atol=1e-10 * np.abs(fb).max())
    np.testing.assert_allclose(tm[:n], tb[:n], atol=1e-10 * np.abs(tb).max())
    # Hertz: one contact per grain with the summed volume (the boxes give two, one per box).
    ch = results["mesh", "hertz"][0]
    assert len(ch["volume"]) == n
    np.testing.assert_allclose(np.sort(ch["volume"]), np.sort(vb), rtol=1e-10)


@pytest.mark.parametrize("where", ["crease", "edge"])
def test_mesh_force_is_the_gradient_of_the_overlap(device, where):
    """Central differences of the overlap volume along x, y, z against the force -k S_A of the linear law."""
    delta = 1e-6
    if where == "crease":
        # d points out of the solid (as at the edge below), so the cube reaches 1 mm into the crease,
        # behind both faces; it pointed in and buried the cube 2.4 cm deep, which validation now refuses.
        mesh, d, p0 = crease_mesh(width=0.8), np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0), np.array([0.0, 0.01, 0.0])
    else:
        mesh, d, p0 = (
            box_mesh([0.2, 0.9, 0.1], [0.0, 0.0, -0.05]),
            np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0),
            np.array([0.1, 0.013, 0.0]),
        )
    q = np.array([0.2, -0.4, 0.3, 0.8])
    q /= np.linalg.norm(q)
    base = pressed(ConvexShape.box(CUBE), q, p0, d, 1e-3)
    offsets = [np.zeros(3)] + [s * delta * e for e in np.eye(3) for s in (1.0, -1.0)]
    sc = base_scene("float64", law="linear", gravity=(0.0, 0.0, 0.0))
    for k, off in enumerate(offsets):
        sc.add_body("cube", "m", position=base + off + [0.0, 0.06 * k, 0.0], orientation=q)
    sc.add_mesh_wall(mesh, "m", thickness=0.05)
    sim = Simulation(sc, device=device)
    c = contacts_by_body(sim)
    vol = np.bincount(c["body_a"], weights=c["volume"], minlength=len(offsets))
    f, _ = first_forces(sim)
    g = np.array([(vol[1 + 2 * a] - vol[2 + 2 * a]) / (2 * delta) for a in range(3)])
    s_a = -f[0] / 1.0e6
    np.testing.assert_allclose(g, s_a, atol=1e-4 * np.linalg.norm(s_a))


def _solid_depth(mesh, pts):
    """Depth of points in the solid behind ``mesh``'s faces (negative: in front), by name."""
    name, m = mesh
    if name in ("box", "icosphere"):  # convex, solid inside
        return -np.max(pts @ m.face_normals.T - np.sum(m.face_normals * m.triangles[:, 0], axis=1), axis=1)
    if name == "container":  # the inside of a box is empty, the solid outside
        lo, hi = m.bounds
        inside = np.all((pts > lo) & (pts < hi), axis=1)
        out = np.maximum(lo - pts, pts - hi).max(axis=1)
        return np.where(inside, -np.min(np.minimum(pts - lo, hi - pts), axis=1), out)
    if name == "crease":  # behind the floor z = 0 (x > 0) or the wall x = 0 (z > 0)
        x, z = pts[:, 0], pts[:, 2]
        return np.where((x > 0) & (z > 0), -np.minimum(x, z), np.maximum(-x, -z))
    raise ValueError(name)


@pytest.mark.parametrize("name", ["box", "icosphere", "container", "crease"])
def test_cells_cover_the_solid_near_its_surface_once(name):
    """Points of the solid less than the thickness behind the surface lie in exactly one cell, at
    convex edges and corners (box, icosphere) and at concave ones (the inside of a box, a crease)."""
    if name == "box":
        m, h = trimesh.creation.box(extents=[0.3, 0.24, 0.16]), 0.08
    elif name == "icosphere":
        m, h = trimesh.creation.icosphere(subdivisions=2, radius=0.1), 0.03
    elif name == "container":
        m, h = trimesh.creation.box(extents=[0.3, 0.24, 0.16]), 0.05
        m.invert()
    else:
        v, f = crease_mesh(width=0.8)
        m, h = trimesh.Trimesh(v, f, process=False), 0.05
    cells = build_cells(m.vertices, m.faces, thickness=h)
    lo, hi = m.bounds
    pts = np.random.default_rng(0).uniform(lo - 1.5 * h, hi + 1.5 * h, (100_000, 3))
    if name == "crease":  # away from the open ends
        pts = pts[(np.abs(pts[:, 1]) < 0.35) & (pts[:, 0] < 0.15) & (pts[:, 2] < 0.15)]
    depth = _solid_depth((name, m), pts)
    count = np.zeros(len(pts), dtype=int)
    for c in cells.cells:
        count += np.all((pts - c.center) @ c.face_normals.T <= c.face_offsets + 1e-12, axis=1)
    near = (depth > 1e-9) & (depth < h - 1e-9)
    assert near.sum() > 2_000
    np.testing.assert_array_equal(count[near], 1)
    np.testing.assert_array_equal(count[depth < -1e-9], 0)


def test_inconsistent_winding_is_refused():
    v, f = floor_grid(2)
    f[0] = f[0][::-1]
    sc = base_scene()
    with pytest.raises(SceneError, match="wound the same way"):
        sc.add_mesh_wall((v, f), "m")


def test_mesh_wall_from_a_scene_file(tmp_path, device):
    v, f = floor_grid(4)
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "floor.stl")
    text = f"""
[simulation]
dt = "auto"
duration = 0.01
[materials.m]
density = 2500.0
law = "hertz"
k = 1.0e8
restitution = 0.5
friction = 0.5
[shapes.cube]
type = "box"
size = {CUBE}
[[bodies]]
shape = "cube"
material = "m"
position = [0.01, 0.02, 0.0099]
[[walls]]
type = "mesh"
file = "floor.stl"
material = "m"
scale = 0.5
rotation = {{axis = [0, 0, 1], degrees = 30}}
position = [0.0, 0.0, 0.0]
"""
    path = tmp_path / "scene.toml"
    path.write_text(text)
    sc = Scene.from_toml(path)
    assert len(sc.mesh_walls) == 1 and len(sc.mesh_walls[0].triangles) == 32
    assert np.abs(sc.mesh_walls[0].vertices[:, :2]).max() == pytest.approx(0.25 * np.sqrt(2.0) * np.cos(np.pi / 12))
    sim = Simulation(sc, device=device)
    c = contacts_by_body(sim)
    assert len(c["volume"]) == 1 and c["volume"][0] > 0.0
    again = Scene.from_dict(sc.to_dict())
    np.testing.assert_array_equal(again.mesh_walls[0].vertices, sc.mesh_walls[0].vertices)


@pytest.mark.parametrize(
    "wall, message",
    [
        ({"file": "missing.stl"}, "not found"),
        ({"file": "floor.stl", "vertices": [[0, 0, 0]]}, "either as file"),
        ({"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]]}, "missing required key 'triangles'"),
        ({"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "triangles": [[0, 1, 5]]}, "outside its 3 vertices"),
        ({"vertices": [[0, 0, 0], [1, 0, 0], [2, 0, 0]], "triangles": [[0, 1, 2]]}, "no triangle of non-zero area"),
        ({"file": "floor.stl", "scale": 0}, "zero"),
        ({"file": "floor.stl", "thickness": -1}, "thickness"),
        ({"file": "floor.stl", "colour": 1}, "colour"),
    ],
)
def test_bad_mesh_walls_say_what_to_fix(tmp_path, wall, message):
    v, f = floor_grid(2)
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "floor.stl")
    data = {
        "simulation": {"dt": "auto"},
        "materials": {"m": {"density": 2500.0, "law": "hertz", "k": 1e8, "restitution": 0.5, "friction": 0.5}},
        "shapes": {"cube": {"type": "box", "size": CUBE}},
        "bodies": [{"shape": "cube", "material": "m", "position": [0, 0, 0.2]}],
        "walls": [{"type": "mesh", "material": "m", **wall}],
    }
    with pytest.raises(SceneError, match=message) as err:
        Scene.from_dict(data, base_dir=tmp_path)
    assert "walls[0]" in str(err.value)


def test_turning_mesh_wall_moves_as_a_rigid_body(device):
    """A mesh turning about a pivot and sliding: its pose after n steps is the closed-form one."""
    sc = base_scene("float64")
    sc.add_body("cube", "m", position=(5.0, 5.0, 5.0))
    v, f = floor_grid(2, size=0.2)
    w = np.array([0.0, 0.0, 2.0])
    vel = np.array([0.1, 0.0, 0.0])
    sc.add_mesh_wall((v, f), "m", pivot=(0.05, 0.0, 0.0), angular_velocity=w, velocity=vel)
    sim = Simulation(sc, device=device)
    sim.step(100)
    t = sim.time
    q = sim.current_state.mesh_q.numpy()[0]
    np.testing.assert_allclose(q[:3], [0.05 + 0.1 * t, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(q[3:], [0.0, 0.0, np.sin(t), np.cos(t)], atol=1e-12)


def test_cube_on_a_moving_belt_is_carried_along(device):
    """Friction with a translating mesh floor (a conveyor belt) brings a resting cube to its speed."""
    sc = base_scene("mixed", friction=0.5, restitution=0.5)
    v, f = floor_grid(4, size=4.0)
    sc.add_mesh_wall((v, f), "m", velocity=(0.2, 0.0, 0.0))
    sc.add_body("cube", "m", position=(0.0, 0.0, 0.5 * CUBE - 1e-6))
    sim = Simulation(sc, device=device)
    sim.step(int(0.2 / sim.dt))
    vx = sim.state()["body_velocity"][0, 0]
    assert vx == pytest.approx(0.2, rel=2e-3)


def test_checkpoint_keeps_the_mesh_pose(tmp_path, device):
    from polydem.checkpoint import load_checkpoint, save_checkpoint

    sc = base_scene("float64")
    sc.add_body("cube", "m", position=(0.0, 0.0, 0.5 * CUBE + 0.001))
    sc.add_mesh_wall(floor_grid(2, size=0.4), "m", angular_velocity=(0.0, 0.0, 1.0))
    sim = Simulation(sc, device=device)
    sim.step(50)
    save_checkpoint(sim, tmp_path / "c.npz")
    q = sim.current_state.mesh_q.numpy().copy()
    sim2 = Simulation(sc, device=device)
    load_checkpoint(sim2, tmp_path / "c.npz")
    np.testing.assert_array_equal(sim2.current_state.mesh_q.numpy(), q)
    sim.step(20)
    sim2.step(20)
    np.testing.assert_array_equal(sim2.state()["body_position"], sim.state()["body_position"])


def test_build_cells_rejects_a_bad_thickness():
    v, f = floor_grid(1)
    with pytest.raises(MeshWallError, match="thickness"):
        build_cells(v, f, thickness=0.0)


def test_public_api():
    assert hasattr(polydem.Scene, "add_mesh_wall")


def test_emitter_keeps_clear_of_mesh_walls(device):
    """Bodies emitted into a region that crosses a container mesh's walls start clear of them."""
    sc = base_scene("float64")
    box = trimesh.creation.box(extents=[0.2, 0.2, 0.2])
    box.apply_translation([0.0, 0.0, 0.1])
    sc.add_mesh_wall(box, "m", flip_normals=True, thickness=0.02)
    sc.emit(
        shape="cube", material="m", count=20, region={"min": [-0.15, -0.15, -0.05], "max": [0.15, 0.15, 0.25]}, seed=2
    )
    pos = sc.body_position
    assert len(pos) == 20
    assert np.all(np.abs(pos[:, :2]) < 0.1) and np.all((pos[:, 2] > 0.0) & (pos[:, 2] < 0.2))
    sim = Simulation(sc, device=device)
    assert len(contacts_by_body(sim)["volume"]) == 0


def cone_mesh(n=48, r_top=0.1, r_bottom=0.02, z_top=0.2, z_bottom=0.05):
    """An open conical hopper facing its axis, through a float32 STL file as a user would give it."""
    th = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    top = np.column_stack([r_top * np.cos(th), r_top * np.sin(th), np.full(n, z_top)])
    bottom = np.column_stack([r_bottom * np.cos(th), r_bottom * np.sin(th), np.full(n, z_bottom)])
    k = np.arange(n)
    a, b, c, d = k, (k + 1) % n, n + (k + 1) % n, n + k
    faces = np.concatenate([np.column_stack([a, c, b]), np.column_stack([a, d, c])])
    m = trimesh.Trimesh(np.vstack([top, bottom]), faces, process=False)
    if np.mean(np.sum(m.face_normals[:, :2] * m.triangles_center[:, :2], axis=1)) > 0.0:
        m.invert()  # face the axis: the grains are inside
    return trimesh.load(trimesh.util.wrap_as_stream(m.export(file_type="stl")), file_type="stl")


def test_float32_cone_has_one_wedge_per_crease():
    """A cone read from STL: its planar quads (bent by float32 rounding) count as flat, each of its
    48 creases gets one wedge cell, and no cell reaches beyond the solid's neighbourhood."""
    m = cone_mesh()
    cells = build_cells(m.vertices, m.faces, thickness=0.017)
    assert len(cells.cells) == 96 + 48
    assert max(c.radius for c in cells.cells) < 0.12


def test_grains_in_a_cone_keep_their_energy(device):
    """Elastic frictionless cubes dropped into a cone hopper: the energy balance closes."""
    sc = base_scene("float64")
    sc.add_mesh_wall(cone_mesh(), "m", thickness=0.017)
    for k in range(6):
        ang = 2 * np.pi * k / 6
        sc.add_body("cube", "m", position=(0.06 * np.cos(ang), 0.06 * np.sin(ang), 0.16 + 0.01 * k))
    sim = Simulation(sc, device=device)
    e0 = sim.energy()["total"]
    touched = 0
    for _ in range(8):
        sim.step(500)
        touched += int(np.sum(contacts_by_body(sim)["body_b"] < 0))
    assert touched > 0
    assert abs(sim.energy()["total"] - e0) < 2e-3 * abs(e0)


def test_checkpoint_of_another_mesh_is_refused(tmp_path, device):
    from polydem.checkpoint import CheckpointError, load_checkpoint, save_checkpoint

    sc = base_scene("float64")
    sc.add_body("cube", "m", position=(0.0, 0.0, 0.5 * CUBE + 0.001))
    sc.add_mesh_wall(floor_grid(2, size=0.4), "m")
    sim = Simulation(sc, device=device)
    sim.step(5)
    save_checkpoint(sim, tmp_path / "c.npz")
    other = base_scene("float64")
    other.add_body("cube", "m", position=(0.0, 0.0, 0.5 * CUBE + 0.001))
    other.add_mesh_wall(floor_grid(3, size=0.4), "m")
    with pytest.raises(CheckpointError, match=r"mesh_walls\[0\].triangles"):
        load_checkpoint(Simulation(other, device=device), tmp_path / "c.npz")


def candidate_scene(precision):
    """Cubes, rocks and L-shaped compound grains pressed into a jittered floor of 2,048 triangles and sliding on a
    shelf of 8 above it, and a slab over some 20 cells (hertz, friction 0.5, e = 0.5)."""
    from test_compound import H, l_partition

    sc = base_scene(precision, friction=0.5, restitution=0.5)
    sc.add_shape("L", l_partition())
    sc.add_mesh_wall(floor_grid(32, jitter=0.3), "m")
    v, f = floor_grid(2, size=0.3)
    sc.add_mesh_wall((v + (0.0, 0.0, 0.1), f), "m", thickness=0.02)  # a shelf of 8 triangles above the floor
    add_grains(sc, grid_centres(5, spacing=0.1), seed=4, depth=(1.0e-5, 1.0e-4))
    for k, c in enumerate(grid_centres(3, spacing=0.08, z=0.1 + 0.5 * H - 5.0e-5)):
        sc.add_body("L", "m", position=c, velocity=(0.3, 0.1 * k, 0.0))  # sliding on the shelf
    # A slab over some 20 cells: more than a thread keeps while it traverses (LISTED_IN_REGISTERS)
    sc.add_shape("slab", ConvexShape.box(0.12, 0.12, 0.02))
    sc.add_body("slab", "m", position=(0.35, 0.35, 0.01 - 5.0e-5), velocity=(0.1, 0.0, 0.0))
    return sc


@pytest.mark.parametrize("precision", ["mixed", "float32"])
def test_candidate_list_gives_the_walks_bits(device, precision):
    """The mesh-wall contacts through the (body, cell) candidate list (CUDA's default) against the walk, one
    thread per body (the CPU's): cubes, rocks and L-shaped compound grains pressed into a jittered floor of
    2,048 triangles and on a shelf of 8 above it (hertz, friction, e = 0.5), the list started with room for one
    candidate, so that the first steps overflow, grow it and are redone. The states, the contacts reported
    (the report variant), the energies (the diagnostics variant) and the loads: the same bits (the energy lost
    to 1e-6 on CUDA)."""
    from polydem.kernels.meshwall import LISTED_IN_REGISTERS, MeshCandidates

    runs = {}
    for listed in (False, True):
        # One cell per triangle: many cells a grain (joined, the floor is one)
        sim = Simulation(candidate_scene(precision), device=device, mesh_candidates=listed, join_flat_cells=False)
        if listed:
            sim.stepper.mesh_candidates = MeshCandidates(sim.num_bodies, 1, precision, sim.device)
        sim.step(400)
        st = sim.current_state
        arrays = {k: getattr(st, k).numpy() for k in ("body_q", "body_v", "body_w", "body_damping", "wall_turn")}
        runs[listed] = (sim, arrays, sim.contacts(), sim.energy())
    walk, listed = runs[False], runs[True]
    candidates = listed[0].stepper.mesh_candidates
    assert walk[0].stepper.mesh_candidates is None
    assert candidates.generation >= 1 and candidates.capacity >= candidates.needed() > 25  # it grew
    assert candidates.arrays["count"].numpy().max() > LISTED_IN_REGISTERS
    for k, a in walk[1].items():
        np.testing.assert_array_equal(listed[1][k], a, k)
    walls = walk[2]["body_b"] < 0
    assert np.count_nonzero(walls) > 25  # many grains on the walls, of three shapes
    for k, a in walk[2].items():
        np.testing.assert_array_equal(listed[2][k], a, k)
    energies = listed[3], walk[3]
    for k in ("kinetic", "contact", "gravity"):
        assert energies[0][k] == energies[1][k], k
    # The book of the energy lost: on CUDA the compiler may fuse a multiply-add of it differently in the walk's
    # kernel and the list's, and a body's book is float32 in these precisions (measured on an H200: 2e-9 and 6e-9
    # of it apart after 400 steps, the motion the same bits).
    rtol = 0.0 if wp.get_device(device).is_cpu else 1.0e-6
    np.testing.assert_allclose(energies[0]["dissipated"], energies[1]["dissipated"], rtol=rtol, atol=0.0)


def test_candidate_overflow_of_steps_outlives_a_report(device):
    """Steps run without a check (Simulation.advance, as a decomposed run does) overflow the candidate list; a
    report of the contacts before the caller's check grows the list for its own pass but still lets the check see
    the steps' overflow, and the list grows to at least what the first step listed (later steps of the chunk,
    with no mesh-wall force, may list fewer)."""
    from polydem.kernels.meshwall import MeshCandidates

    roomy = Simulation(candidate_scene("mixed"), device=device, mesh_candidates=True, join_flat_cells=False)
    roomy.step(1)
    first = roomy.stepper.mesh_candidates.needed()
    sim = Simulation(candidate_scene("mixed"), device=device, mesh_candidates=True, join_flat_cells=False)
    sim.stepper.mesh_candidates = MeshCandidates(sim.num_bodies, 1, "mixed", sim.device)
    sim.advance(20)
    assert sim.stepper.mesh_candidates.needed() >= first > 25
    sim.energy()  # the diagnostics pass: grows the list, lists all
    assert sim.stepper.buffers_overflowed()
    sim.stepper.grow_buffers()
    assert not sim.stepper.buffers_overflowed()
    assert sim.stepper.mesh_candidates.capacity >= 1.5 * first


def joined_scene(precision):
    """Cubes and rocks pressed into the floor and the wall of a crease (two flat patches of 32 triangles,
    a concave edge between them), over the floor's open edge, and into an L-shaped jittered floor (a flat
    patch not convex: its cells stay one per triangle); hertz, friction 0.5, e = 0.5."""
    sc = base_scene(precision, friction=0.5, restitution=0.5)
    sc.add_mesh_wall(crease_mesh(), "m", thickness=0.05)
    v, f = floor_grid(8, size=0.4, jitter=0.3)
    centroid = v[f].mean(axis=1)
    keep = ~((centroid[:, 0] > 0.0) & (centroid[:, 1] > 0.0))
    sc.add_mesh_wall((v + (0.0, 0.0, -0.3), f[keep]), "m", thickness=0.05)
    on_floor = [(x, y, 0.0) for x in (0.04, 0.11, 0.192) for y in (-0.06, 0.0, 0.05)]
    add_grains(sc, on_floor, seed=7, depth=(1.0e-5, 1.0e-3))
    on_wall = [(0.0, y, z) for y in (-0.05, 0.04) for z in (0.06, 0.13)]
    add_grains(sc, on_wall, seed=8, depth=(1.0e-5, 1.0e-3), down=(1.0, 0.0, 0.0))
    rng = np.random.default_rng(9)
    for y in (-0.07, 0.02, 0.08):  # in the crease, pressed into both faces
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        x = -lowest(sc.shapes["cube"], q, [1.0, 0.0, 0.0]) - 5.0e-4
        z = -lowest(sc.shapes["cube"], q, [0.0, 0.0, 1.0]) - 7.0e-4
        sc.add_body("cube", "m", position=(x, y, z), orientation=q)
    on_l = [(x, y, -0.3) for x, y in ((-0.1, -0.1), (0.1, -0.12), (-0.12, 0.1), (0.013, -0.011))]
    add_grains(sc, on_l, seed=10, depth=(1.0e-5, 1.0e-3))
    return sc


@pytest.mark.parametrize("precision", ["float64", "mixed"])
def test_joined_flat_cells_give_the_triangles_contacts(device, precision):
    """The cells of a flat patch joined into one (the default) against one cell per triangle: the crease's
    floor and wall each become one cell, the L-shaped floor keeps its cells; the contacts of the first step
    (overlap, force, normal, depth) to rounding, and 300 steps of bouncing, sliding grains (hertz, friction)
    alike to 1e-12 (float64) or 1e-6 (mixed) of their travel."""
    runs = {}
    for join in (False, True):
        sim = Simulation(joined_scene(precision), device=device, join_flat_cells=join)
        c = contacts_by_body(sim)
        f, t = first_forces(sim)
        start = sim.state()["body_position"].copy()
        sim.step(299)
        runs[join] = (sim, c, f, t, start, sim.state(), sim.energy())
    apart, joined = runs[False], runs[True]
    cells = [[mc.num_cells for mc in r[0].model.mesh_cells] for r in (apart, joined)]
    crease = len(build_cells(*crease_mesh(), thickness=0.05).cells)
    assert cells[0][0] == crease and cells[1][0] == crease - 64 + 2  # the floor and the wall: a cell each
    assert cells[1][1] == cells[0][1]  # the L: not convex, one cell per triangle
    c0, c1 = apart[1], joined[1]
    n = joined[0].num_bodies
    assert len(c0["volume"]) == n  # every grain touches a wall
    tol = 1e-11 if precision == "float64" else 1e-5  # measured: 1e-13, 5e-7
    np.testing.assert_array_equal(c1["body_a"], c0["body_a"])
    np.testing.assert_allclose(c1["volume"], c0["volume"], rtol=tol)
    np.testing.assert_allclose(c1["normal_force"], c0["normal_force"], rtol=tol)
    np.testing.assert_allclose(c1["normal"], c0["normal"], atol=tol)
    np.testing.assert_allclose(c1["depth"], c0["depth"], rtol=tol, atol=1e-9)
    for a, b in ((joined[2], apart[2]), (joined[3], apart[3])):
        np.testing.assert_allclose(a, b, atol=tol * np.abs(b).max())
    travel = np.linalg.norm(apart[5]["body_position"] - apart[4], axis=1)
    assert np.median(travel) > 2e-4  # pushed out, bouncing, sliding
    gap = np.linalg.norm(joined[5]["body_position"] - apart[5]["body_position"], axis=1)
    assert gap.max() <= (1e-12 if precision == "float64" else 1e-6) * travel.max()  # measured: 2e-15, 8e-8
    for k in ("kinetic", "contact", "dissipated"):
        assert joined[6][k] == pytest.approx(apart[6][k], rel=1e-9 if precision == "float64" else 1e-4), k


def _cell_count_at(cells, points):
    """How many of ``cells`` hold each of ``points`` (the mesh frame)."""
    planes, owner = cells.world_planes()
    out = planes[:, :3] @ points.T - planes[:, 3, None] > 1e-12  # (F, P): outside that face
    return cells.num_cells - np.add.reduceat(out, cells.cell_face_start[:-1], axis=0).astype(bool).sum(axis=0)


def _tilted(v, angle=0.4):
    c, s = np.cos(angle), np.sin(angle)
    return v @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]]).T


@pytest.mark.parametrize("name", ["jittered floor", "tilted floor", "box", "folded floor", "crease"])
def test_joined_cells_are_the_same_solid(name):
    """Joined cells against the cells of one triangle each, on their own: every face's corners lie on its plane
    and run counter-clockwise about its outward normal, every corner lies in its cell, and 40,000 points near
    the surface lie in as many cells either way. A floor folded over (a vertex dragged past its neighbours,
    whose cells overlap) does not join across the fold."""
    from polydem.meshmerge import join_flat_cells

    h = 0.05
    if name in ("jittered floor", "tilted floor", "folded floor"):
        v, f = floor_grid(8, size=0.4, jitter=0.3 if name != "folded floor" else 0.0)
        if name == "tilted floor":
            v = _tilted(v)
        if name == "folded floor":
            v[np.argmin(np.linalg.norm(v, axis=1)), 0] = 0.08  # past its neighbours at x = 0.05
    elif name == "box":
        m = box_mesh(np.array([0.3, 0.24, 0.16]), np.zeros(3))
        v, f = m.vertices, m.faces
    else:
        v, f = crease_mesh()
    cells = build_cells(v, f, thickness=h)
    joined = join_flat_cells(cells)
    if name != "folded floor":
        assert joined.num_cells < cells.num_cells
    planes, _ = joined.world_planes()
    for k, c in enumerate(joined.cells):
        corners = c.vertices + c.center
        for loop, normal, offset in zip(c.faces, c.face_normals, c.face_offsets, strict=True):
            pts = c.vertices[loop]
            assert np.abs(pts @ normal - offset).max() < 1e-12
            assert np.cross(pts, np.roll(pts, -1, axis=0)).sum(axis=0) @ normal > 0.0  # counter-clockwise
        own = planes[joined.cell_face_start[k] : joined.cell_face_start[k + 1]]
        assert (corners @ own[:, :3].T - own[:, 3]).max() < 1e-12
    lo, hi = cells.lower.min(axis=0), cells.upper.max(axis=0)
    pts = np.random.default_rng(3).uniform(lo, hi, (40_000, 3))
    before, after = _cell_count_at(cells, pts), _cell_count_at(joined, pts)
    assert np.count_nonzero(before) > 5_000
    np.testing.assert_array_equal(after, before)
