"""Flat contacts: a body lying on a face of another, tilted 1e-9 to 1e-2 rad and 1e-10 to 1e-3 of its size
deep, in float32 (the geometry of the default "mixed") against float64, and a cube on the grid lines of a
triangulated floor.

Before the pair-local frame was turned onto the contact face (kernels/geometry.py), a rock, a tetrahedron or a
mesh-wall cell lying flat had its faces rounded off their own planes by units of the body's size, as far as
the depth of a resting contact: S_A came out 120 times off for a rock on a mesh-wall cell and 13 times for a
tetrahedron on a tetrahedron, and a cube across a grid line of a floor had the whole force turned sideways
(10 of 30 poses, up to 1e34 times the normal force) by one enclosed sliver cell's fallback.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import polydem
from polydem import ConvexShape, Scene, Simulation

EPS32 = 2.0**-24


def cell(legs=0.05, thickness=0.17):
    """A mesh-wall cell: a right triangle extruded down by the wall's thickness."""
    tri = np.array([[0.0, 0.0], [legs, 0.0], [0.0, legs]])
    return ConvexShape.from_points(np.vstack([np.c_[tri, np.zeros(3)], np.c_[tri, -thickness * np.ones(3)]]))


SHAPES = {
    "cube": lambda: ConvexShape.box(0.1),
    "cell": cell,
    "pillar": lambda: ConvexShape.box(0.05, 0.05, 0.17),
    "tet": lambda: ConvexShape.tetrahedron(0.12),
    "rock": lambda: ConvexShape.rock(20, 0.1, seed=3),
    "hull": lambda: ConvexShape.sphere(1, 0.06),
}


def rotation_onto(a, b):
    """A rotation matrix taking the unit vector a onto the unit vector b."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-12:
        if c > 0.0:
            return np.eye(3)
        p = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(p) < 1e-6:
            p = np.cross(a, [0.0, 1.0, 0.0])
        return Rotation.from_rotvec(np.pi * p / np.linalg.norm(p)).as_matrix()
    return Rotation.from_rotvec(v / np.linalg.norm(v) * np.arctan2(np.linalg.norm(v), c)).as_matrix()


def lying_poses(a, b, n, rng):
    """Body-frame poses of ``a`` lying on a random face of ``b`` by a random face of its own: turned about the
    normal, tilted 1e-9 to 1e-2 rad, its lowest point 1e-10 to 1e-3 of its size below the face's plane, its
    centre up to its size off a random point of the face, the pair at a random pose within 0.5 m of the
    origin."""
    pa, pb = [], []
    size = a.volume ** (1.0 / 3.0)
    for _ in range(n):
        fb, fa = rng.integers(len(b.faces)), rng.integers(len(a.faces))
        nb = b.face_normals[fb]
        r = rotation_onto(a.face_normals[fa], -nb)
        r = Rotation.from_rotvec(nb * rng.uniform(0.0, 2.0 * np.pi)).as_matrix() @ r
        axis = np.cross(nb, rng.normal(size=3))
        r = Rotation.from_rotvec(axis / np.linalg.norm(axis) * 10 ** rng.uniform(-9, -2)).as_matrix() @ r
        face = b.vertices[b.faces[fb]]
        side = np.cross(nb, rng.normal(size=3))
        x = rng.dirichlet(np.ones(len(face))) @ face + side * rng.uniform(0.0, size) / np.linalg.norm(side)
        low = (a.vertices @ r.T @ nb).min()
        x += nb * (nb @ face[0] - low - nb @ x - size * 10 ** rng.uniform(-10, -3))
        g = Rotation.random(random_state=rng.integers(1 << 30)).as_matrix()
        off = rng.uniform(-0.5, 0.5, 3)
        pa.append(np.r_[g @ x + off, Rotation.from_matrix(g @ r).as_quat()])
        pb.append(np.r_[off, Rotation.from_matrix(g).as_quat()])
    return np.array(pa), np.array(pb)


PAIRS = [("cube", "cell"), ("cube", "tet"), ("tet", "tet"), ("tet", "cube"), ("rock", "cell"), ("rock", "tet"),
         ("rock", "rock"), ("hull", "cell"), ("hull", "tet"), ("cube", "pillar")]  # fmt: skip


@pytest.mark.parametrize("names", PAIRS, ids=["-on-".join(p) for p in PAIRS])
def test_float32_flat_contacts_match_float64(device, names):
    """V, S_A, M_A and S_A + S_B of float32 clipping (what "mixed" uses) against float64, over 80 lying poses.

    Face contacts (|S_A| above 1e-3 r_min^2): S_A and M_A within 2e-5 relative, S_A + S_B within 4e-5 of |S_A|,
    V within 8 units of float32 rounding of r_min |S_A| (measured after the change: 6.8e-6, 6.8e-6, 1.2e-5, 1;
    before: up to 120, 120, 120 and 1e5). Every touching pose, corner slivers included: S_A and S_A + S_B
    within 64 and 128 units of rounding of r_min sqrt|S_A| (measured 13 and 31; before 2e8 and 6e8)."""
    a, b = SHAPES[names[0]](), SHAPES[names[1]]()
    pa, pb = lying_poses(a, b, 80, np.random.default_rng(sum(map(ord, "".join(names)))))
    r32 = polydem.overlap(a, pa, b, pb, frame="body", device=device, precision="float32")
    r64 = polydem.overlap(a, pa, b, pb, frame="body", device=device, precision="float64")
    rmin = min(a.radius, b.radius)
    touch = r64.volume > 0.0
    assert touch.sum() >= 15  # rocks on rocks touch least often: a face of one on a far face of the other
    s64 = np.linalg.norm(r64.area_vector, axis=1)
    face = touch & (s64 > 1e-3 * rmin**2)
    assert face.sum() >= 10
    ds = np.linalg.norm(r32.area_vector - r64.area_vector, axis=1)
    dm = np.linalg.norm(r32.moment - r64.moment, axis=1)
    closure = np.linalg.norm(r32.area_vector + r32.area_vector_b, axis=1)
    dv = np.abs(r32.volume - r64.volume)
    assert (ds[face] / s64[face]).max() < 2e-5
    assert (dm[face] / np.linalg.norm(r64.moment[face], axis=1)).max() < 2e-5
    assert (closure[face] / s64[face]).max() < 4e-5
    assert (dv[face] / (EPS32 * rmin * s64[face])).max() < 8.0
    unit = EPS32 * rmin * np.sqrt(s64[touch])
    assert (ds[touch] / unit).max() < 64.0
    assert (closure[touch] / unit).max() < 128.0


def grid_floor(n=20, size=2.0):
    """A flat floor of n x n squares, each cut into two triangles along a diagonal; the top at z = 0."""
    xs = np.linspace(-size / 2, size / 2, n + 1)
    vertices = np.array([[x, y, 0.0] for y in xs for x in xs])
    triangles = []
    for j in range(n):
        for i in range(n):
            a = j * (n + 1) + i
            triangles += [[a, a + 1, a + n + 2], [a, a + n + 2, a + n + 1]]
    return vertices, np.array(triangles)


def cube_on_floor(precision, position, rotation, velocity=(0.0, 0.0, 0.0)):
    scene = Scene(gravity=(0, 0, -9.81), dt="auto", precision=precision)
    scene.add_material("steel", density=7800.0, law="hertz", k=1e10, restitution=0.3, friction=0.3)
    scene.add_shape("cube", ConvexShape.box(0.1))
    q = tuple(Rotation.from_matrix(rotation).as_quat())
    scene.add_body("cube", "steel", position=position, orientation=q, velocity=velocity)
    scene.add_mesh_wall(grid_floor(), "steel")
    return scene


@pytest.mark.parametrize("cells", ["triangles", "joined"])
@pytest.mark.parametrize("precision", ["mixed", "float64"])
def test_face_on_a_grid_line_pushes_up(device, precision, cells):
    """A cube whose side face lies within 1e-8 m of a grid line of a triangulated floor, turned by up to 1e-6
    rad, 1e-9 to 1e-5 m deep: the force is the floor's normal force, sideways at most 1e-3 of it in mixed and
    1e-9 in float64 (measured 6e-5 and 1e-14). Before, one cell cut to an enclosed sliver by the grid line
    gave its fallback, the cube's whole projected area sideways, to the sum over the cells: in mixed 10 of
    these 16 poses pushed the cube sideways, up to 1e34 times the normal force. With one cell per triangle (as
    on a curved mesh, or a float32 file's floor) and with the floor's cells joined into one."""
    rng = np.random.default_rng(3)
    cube = ConvexShape.box(0.1)
    worst = 0.0
    for _ in range(16):
        rv = rng.normal(size=3)
        r = Rotation.from_rotvec(rv / np.linalg.norm(rv) * 10 ** rng.uniform(-10, -6)).as_matrix()
        low = (cube.vertices @ r.T)[:, 2].min()
        dx = rng.choice([0.0, rng.uniform(-1e-8, 1e-8)])
        position = (0.05 + dx, rng.uniform(-0.04, 0.04), -low - 10 ** rng.uniform(-9, -5))
        sim = Simulation(cube_on_floor(precision, position, r), device, join_flat_cells=cells == "joined")
        sim.step(1)
        c = sim.contacts()
        f = (-c["normal_force"][:, None] * c["normal"] + c["tangential_force"]).sum(axis=0)
        assert f[2] > 0.0
        worst = max(worst, float(np.linalg.norm(f[:2]) / f[2]))
    assert worst < (1e-3 if precision == "mixed" else 1e-9), worst


@pytest.mark.parametrize("cells", ["triangles", "joined"])
@pytest.mark.parametrize("precision", ["mixed", "float64"])
def test_cube_slides_across_grid_lines_without_spikes(device, precision, cells):
    """A steel cube sliding at 1 m/s over a triangulated floor, its face crossing a grid line and the cells'
    diagonals: the floor's vertical push stays within 1e-2 (mixed) and 1e-3 (float64) of the weight in every
    step (the issue measured spikes of 26-42 times the weight in mixed); one cell per triangle, and joined."""
    scene = cube_on_floor(precision, (-0.052, 0.03, 0.05), np.eye(3), velocity=(1.0, 0.0, 0.0))
    sim = Simulation(scene, device, join_flat_cells=cells == "joined")
    weight = 7800.0 * 0.1**3 * 9.81
    sim.step(int(0.005 / sim.dt))  # settle onto the floor while sliding
    push = []
    for _ in range(40):
        sim.step(25)
        c = sim.contacts()
        push.append(float((-c["normal_force"][:, None] * c["normal"] + c["tangential_force"]).sum(axis=0)[2]))
    x = sim.state()["body_position"][0, 0]
    assert x > -0.047  # both faces across x have crossed a grid line (x = -0.1 and 0)
    spread = np.abs(np.array(push) / weight - 1.0).max()
    assert spread < (1e-2 if precision == "mixed" else 1e-3), spread


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_face_in_a_compound_cut_plane_gets_the_union_force(device, precision):
    """A cube cut in two along z = 0 (a compound of two half boxes) against a box whose top face lies in
    that cut plane: the overlap of the two unions is that of the uncut cube, and so must be V, S_A and M_A.
    The cut face of the lower half coincides with the box's top face (the same outward normal): half and half,
    as for any coincident face, left S_A with half of that region (-0.05 d instead of -0.1 d along z); the
    box's face is the union's boundary there and takes it all."""
    from polydem import CompoundShape

    halves = [ConvexShape.box(0.1, 0.1, 0.05).placed(np.eye(3), (0.0, 0.0, z)) for z in (0.025, -0.025)]
    cut = CompoundShape(halves)
    whole = ConvexShape.box(0.1)
    box = ConvexShape.box(0.1)
    rng = np.random.default_rng(5)
    n = 12
    pa = np.tile([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], (n, 1))
    depth = rng.uniform(0.002, 0.03, n)
    pb = np.column_stack([0.1 - depth, rng.uniform(-0.03, 0.03, n), np.full(n, -0.05), np.tile([0, 0, 0, 1.0], (n, 1))])
    pb[0, 1] = 0.0  # one pose with the faces' edges in line as well
    got = polydem.overlap(cut, pa, box, pb, device=device, precision=precision)
    want = polydem.overlap(whole, pa, box, pb, device=device, precision="float64")
    tol = 1e-6 if precision == "float32" else 1e-12
    np.testing.assert_allclose(got.volume, want.volume, rtol=tol)
    np.testing.assert_allclose(got.area_vector, want.area_vector, atol=tol * 0.01)
    np.testing.assert_allclose(got.moment, want.moment, atol=tol * 0.01 * 0.1)
    np.testing.assert_allclose(got.area_vector_b, want.area_vector_b, atol=tol * 0.01)
    # The region in the cut plane, d by the overlap along y, is all in S_A (along -z: A's bottom face).
    np.testing.assert_allclose(got.area_vector[:, 2], -depth * (0.1 - np.abs(pb[:, 1])), rtol=tol * 10)
