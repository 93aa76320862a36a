"""Tests of polydem.shapes.ConvexShape (CPU only, no Warp)."""

import math
import re
import subprocess
import sys
import time
import warnings

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from polydem.shapes import MAX_FACE_VERTICES, MAX_FACES, ConvexShape

SQRT5 = math.sqrt(5.0)


def same_point_sets(a, b, atol):
    """True when every point of a has a point of b within atol and vice versa (and the counts match)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.shape != b.shape:
        return False
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    return bool(d.min(axis=1).max() <= atol and d.min(axis=0).max() <= atol)


def polygon_area_vectors(shape):
    out = []
    for loop in shape.faces:
        p = shape.vertices[loop]
        out.append(0.5 * np.cross(p, np.roll(p, -1, axis=0)).sum(axis=0))
    return np.array(out)


def body_inertia_tensor(shape):
    """Inertia tensor per unit density about the origin, integrated independently by trimesh."""
    props = trimesh.triangles.mass_properties(shape.vertices[shape.to_trimesh().faces], density=1.0)
    return np.asarray(props.center_mass), np.asarray(props.inertia), props.volume


GENERATORS = {
    "cube": lambda: ConvexShape.box(1.0),
    "box": lambda: ConvexShape.box(0.3, 1.7, 0.9),
    "tetrahedron": lambda: ConvexShape.tetrahedron(0.7),
    "octahedron": lambda: ConvexShape.octahedron(1.3),
    "dodecahedron": lambda: ConvexShape.dodecahedron(0.4),
    "icosahedron": lambda: ConvexShape.icosahedron(2.0),
    "prism3": lambda: ConvexShape.prism(3, radius=0.2, height=2.0),
    "prism7": lambda: ConvexShape.prism(7),
    "prism64": lambda: ConvexShape.prism(64, radius=1.0, height=0.1),
    "rock": lambda: ConvexShape.rock(),
    "rock_elongated": lambda: ConvexShape.rock(40, size=0.05, seed=7, elongation=(3.0, 1.0, 0.5)),
    "sphere1": lambda: ConvexShape.sphere(1),
    "sphere2": lambda: ConvexShape.sphere(2, radius=3.0),
}


@pytest.fixture(params=sorted(GENERATORS), scope="module")
def shape(request):
    return GENERATORS[request.param]()


# ---------------------------------------------------------------------- invariants of every shape


def test_faces_are_ccw_and_planar(shape):
    scale = shape.radius
    area_vecs = polygon_area_vectors(shape)
    areas = np.linalg.norm(area_vecs, axis=1)
    assert np.all(areas > 0)
    # The loop's area vector points along the outward normal (CCW seen from outside).
    np.testing.assert_allclose(area_vecs / areas[:, None], shape.face_normals, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(shape.face_normals, axis=1), 1.0, atol=1e-14)
    for f, loop in enumerate(shape.faces):
        assert loop.dtype == np.int64 and len(loop) >= 3
        assert len(set(loop.tolist())) == len(loop)
        dist = shape.vertices[loop] @ shape.face_normals[f] - shape.face_offsets[f]
        assert np.abs(dist).max() <= max(shape.tolerance, 1e-13 * scale)
    assert np.all(shape.face_offsets > 0)


def test_convex_and_closed(shape):
    scale = shape.radius
    heights = shape.vertices @ shape.face_normals.T - shape.face_offsets
    assert heights.max() <= 1e-13 * scale
    # Closed surface: the area vectors of all faces cancel.
    assert np.linalg.norm(polygon_area_vectors(shape).sum(axis=0)) <= 1e-13 * scale**2
    # Every directed edge appears once and its reverse once (consistently oriented 2-manifold).
    edges = [(int(a), int(b)) for loop in shape.faces for a, b in zip(loop, np.roll(loop, -1), strict=True)]
    assert len(set(edges)) == len(edges)
    assert set(edges) == {(b, a) for a, b in edges}
    assert shape.num_vertices - len(edges) // 2 + shape.num_faces == 2


def test_one_plane_per_face_and_only_hull_vertices(shape):
    n = shape.face_normals
    cos = n @ n.T
    np.fill_diagonal(cos, -1.0)
    assert cos.max() < 1.0 - 1e-9
    used = np.unique(np.concatenate(shape.faces))
    np.testing.assert_array_equal(used, np.arange(shape.num_vertices))
    assert len(ConvexHull(shape.vertices).vertices) == shape.num_vertices
    assert shape.max_face_vertices == max(len(f) for f in shape.faces)


def test_body_frame_and_derived_data(shape):
    centre, tensor, volume = body_inertia_tensor(shape)
    scale = shape.radius
    assert np.linalg.norm(centre) <= 1e-12 * scale
    np.testing.assert_allclose(volume, shape.volume, rtol=1e-12)
    # Principal axes: the tensor is diagonal in the body frame, with sorted moments.
    np.testing.assert_allclose(tensor, np.diag(shape.inertia), atol=1e-12 * shape.inertia.max())
    assert np.all(np.diff(shape.inertia) >= -1e-12 * shape.inertia.max())
    rot = shape.input_rotation
    np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    np.testing.assert_array_equal(shape.input_transform[3], [0, 0, 0, 1])
    assert shape.radius == pytest.approx(np.linalg.norm(shape.vertices, axis=1).max())
    for f, loop in enumerate(shape.faces):
        p = shape.vertices[loop]
        np.testing.assert_allclose(shape.face_centers[f], p.mean(axis=0), atol=1e-15 * scale)
        assert shape.face_radii[f] == pytest.approx(np.linalg.norm(p - shape.face_centers[f], axis=1).max())


def test_to_trimesh(shape):
    mesh = shape.to_trimesh()
    assert isinstance(mesh, trimesh.Trimesh)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.is_convex
    assert len(mesh.faces) == sum(len(f) - 2 for f in shape.faces)
    assert mesh.volume == pytest.approx(shape.volume, rel=1e-12)
    np.testing.assert_array_equal(mesh.vertices, shape.vertices)


def test_arrays_are_read_only(shape):
    with pytest.raises(ValueError, match="read-only"):
        shape.vertices[0, 0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        shape.faces[0][0] = 0
    with pytest.raises(ValueError, match="read-only"):
        shape.input_translation[0] = 1.0


# ---------------------------------------------------------------------- specific shapes


def test_cube():
    s = 0.2
    cube = ConvexShape.box(s)
    assert cube.name == "box"
    assert cube.num_vertices == 8 and cube.num_faces == 6
    assert all(len(f) == 4 for f in cube.faces) and cube.max_face_vertices == 4
    assert cube.volume == pytest.approx(s**3, rel=1e-14)
    # I = m (a^2 + b^2) / 12 with m = volume (unit density) = s^5 / 6.
    np.testing.assert_allclose(cube.inertia, s**5 / 6.0, rtol=1e-12)
    np.testing.assert_allclose(cube.vertices.mean(axis=0), 0.0, atol=1e-16)
    np.testing.assert_allclose(np.sort(cube.face_offsets), s / 2, rtol=1e-14)
    np.testing.assert_allclose(cube.face_radii, s / math.sqrt(2.0), rtol=1e-14)
    assert cube.radius == pytest.approx(s * math.sqrt(3.0) / 2.0)
    # A symmetric shape keeps the input axes.
    np.testing.assert_allclose(cube.input_transform, np.eye(4), atol=1e-15)


def test_box_principal_axes_sorted_and_round_trip():
    a, b, c = 1.0, 3.0, 2.0
    box = ConvexShape.box(a, b, c)
    m = a * b * c
    expected = sorted([m * (b * b + c * c) / 12, m * (a * a + c * c) / 12, m * (a * a + b * b) / 12])
    np.testing.assert_allclose(box.inertia, expected, rtol=1e-12)
    # The smallest moment is about the longest edge (input y), so body x runs along input y.
    np.testing.assert_allclose(np.abs(box.input_rotation[:, 0]), [0, 1, 0], atol=1e-14)
    np.testing.assert_allclose(np.ptp(box.vertices, axis=0), [b, c, a], rtol=1e-14)
    corners = np.array([[x, y, z] for x in (-a / 2, a / 2) for y in (-b / 2, b / 2) for z in (-c / 2, c / 2)])
    assert same_point_sets(box.to_input_frame(box.vertices), corners, 1e-14)
    homogeneous = np.column_stack([box.vertices, np.ones(8)]) @ box.input_transform.T
    assert same_point_sets(homogeneous[:, :3], corners, 1e-14)


def test_box_needs_one_or_three_lengths():
    with pytest.raises(ValueError, match="one edge length for a cube or all three"):
        ConvexShape.box(1.0, 2.0)


@pytest.mark.parametrize(
    ("factory", "n_faces", "face_size", "volume"),
    [
        (ConvexShape.tetrahedron, 4, 3, lambda a: a**3 / (6.0 * math.sqrt(2.0))),
        (ConvexShape.octahedron, 8, 3, lambda a: math.sqrt(2.0) / 3.0 * a**3),
        (ConvexShape.dodecahedron, 12, 5, lambda a: (15.0 + 7.0 * SQRT5) / 4.0 * a**3),
        (ConvexShape.icosahedron, 20, 3, lambda a: 5.0 * (3.0 + SQRT5) / 12.0 * a**3),
    ],
)
@pytest.mark.parametrize("edge", [1.0, 0.013])
def test_platonic_solids(factory, n_faces, face_size, volume, edge):
    shape = factory(edge)
    assert shape.num_faces == n_faces
    assert all(len(f) == face_size for f in shape.faces)
    assert shape.volume == pytest.approx(volume(edge), rel=1e-12)
    # Regular polyhedra have isotropic inertia and equal face offsets; every edge has length `edge`.
    np.testing.assert_allclose(shape.inertia, shape.inertia[0], rtol=1e-10)
    np.testing.assert_allclose(shape.face_offsets, shape.face_offsets[0], rtol=1e-12)
    for loop in shape.faces:
        p = shape.vertices[loop]
        np.testing.assert_allclose(np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1), edge, rtol=1e-12)


@pytest.mark.parametrize("n", [3, 4, 5, 8, 64])
def test_prism(n):
    r, h = 0.4, 1.5
    prism = ConvexShape.prism(n, radius=r, height=h)
    assert prism.num_faces == n + 2
    assert prism.num_vertices == 2 * n
    sizes = sorted(len(f) for f in prism.faces)
    assert sizes == sorted([4] * n + [n, n])
    assert prism.volume == pytest.approx(0.5 * n * r * r * math.sin(2 * math.pi / n) * h, rel=1e-12)


def test_rock_deterministic_and_seeded():
    a = ConvexShape.rock(n_points=25, seed=3)
    b = ConvexShape.rock(n_points=25, seed=3)
    c = ConvexShape.rock(n_points=25, seed=4)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    assert [f.tolist() for f in a.faces] == [f.tolist() for f in b.faces]
    np.testing.assert_array_equal(a.input_transform, b.input_transform)
    assert a.volume != c.volume
    assert a.num_vertices == 25 and c.num_vertices == 25


@pytest.mark.parametrize("n_points", [4, 12, 100])
def test_rock_keeps_all_points_as_vertices(n_points):
    rock = ConvexShape.rock(n_points=n_points, seed=11, roughness=0.6)
    assert rock.num_vertices == n_points


def test_rock_size_and_elongation():
    rock = ConvexShape.rock(60, size=2.0, seed=1, elongation=(4.0, 1.0, 1.0))
    extent = np.ptp(rock.vertices, axis=0)
    assert extent.max() <= 2.0 + 1e-12
    # Body x follows the long axis: the elongation survives the principal-axis rotation.
    assert extent[0] > 2.5 * extent[2]


@pytest.mark.parametrize(("subdivisions", "n_faces"), [(0, 20), (1, 80), (2, 320), (3, 1280)])
def test_sphere(subdivisions, n_faces):
    sphere = ConvexShape.sphere(subdivisions, radius=0.25)
    assert sphere.num_faces == n_faces
    assert sphere.max_face_vertices == 3
    np.testing.assert_allclose(np.linalg.norm(sphere.vertices, axis=1), 0.25, rtol=1e-12)
    assert sphere.volume < 4.0 / 3.0 * math.pi * 0.25**3


# ---------------------------------------------------------------------- from_points and friends


def test_from_points_rotated_translated_box():
    rot = Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix()
    t = np.array([10.0, -4.0, 2.5])
    dims = np.array([0.5, 2.0, 1.0])
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * dims / 2
    rng = np.random.default_rng(5)
    interior = (rng.random((50, 3)) - 0.5) * dims * 0.9
    points = np.vstack([corners, interior]) @ rot.T + t
    shape = ConvexShape.from_points(points, name="tilted")
    assert shape.name == "tilted"
    assert shape.num_vertices == 8 and shape.num_faces == 6
    assert shape.volume == pytest.approx(np.prod(dims), rel=1e-12)
    np.testing.assert_allclose(shape.inertia, ConvexShape.box(*dims).inertia, rtol=1e-10)
    np.testing.assert_allclose(shape.input_translation, t, atol=1e-12)
    assert same_point_sets(shape.to_input_frame(shape.vertices), corners @ rot.T + t, 1e-12)
    # Body axes are the box axes up to order and sign: the rotation relates them.
    np.testing.assert_allclose(np.abs(rot.T @ shape.input_rotation).max(axis=0), 1.0, atol=1e-10)


def test_redundant_and_nearly_redundant_points_are_removed():
    grid = np.array([[x, y, z] for x in (-1, 0, 1) for y in (-1, 0, 1) for z in (-1, 0, 1)], dtype=float)
    shape = ConvexShape.from_points(grid)
    assert shape.num_vertices == 8 and shape.num_faces == 6
    # Edge midpoints and face centres pushed out by 1e-12 (well inside the 1e-9 tolerance) are
    # collinear/coplanar for practical purposes and must not split faces or edges.
    rng = np.random.default_rng(2)
    noisy = grid + rng.normal(scale=1e-12, size=grid.shape)
    shape = ConvexShape.from_points(noisy)
    assert shape.num_vertices == 8 and shape.num_faces == 6
    assert shape.max_face_vertices == 4
    # A bump of 1e-6 is real geometry at the default tolerance: the top face becomes 4 triangles.
    corners = grid[np.abs(grid).min(axis=1) == 1]
    bumped = ConvexShape.from_points(np.vstack([corners, [0.0, 0.0, 1.0 + 1e-6]]))
    assert bumped.num_vertices == 9 and bumped.num_faces == 9
    # ... and noise at a larger tolerance.
    merged = ConvexShape.from_points(np.vstack([corners, [0.0, 0.0, 1.0 + 1e-6]]), tol=1e-5)
    assert merged.num_vertices == 8 and merged.num_faces == 6


def assert_valid(shape, points):
    """Geometric invariants, and the volume within the tolerance of the exact hull of ``points``."""
    heights = shape.vertices @ shape.face_normals.T - shape.face_offsets
    assert heights.max() <= shape.tolerance
    for f, loop in enumerate(shape.faces):
        assert np.abs(heights[loop, f]).max() <= shape.tolerance
    np.testing.assert_allclose(
        polygon_area_vectors(shape) / np.linalg.norm(polygon_area_vectors(shape), axis=1)[:, None],
        shape.face_normals,
        atol=1e-9,
    )
    edges = [(int(a), int(b)) for loop in shape.faces for a, b in zip(loop, np.roll(loop, -1), strict=True)]
    assert len(set(edges)) == len(edges) and set(edges) == {(b, a) for a, b in edges}
    assert shape.num_vertices - len(edges) // 2 + shape.num_faces == 2
    mesh = shape.to_trimesh()
    assert abs(ConvexHull(points).volume - shape.volume) <= shape.tolerance * mesh.area


def test_near_duplicate_corner_does_not_cut_the_corner():
    # A point 1e-5 from a corner and 2e-10 off its edge (within the merge distance, but far from a
    # duplicate): either it or the corner may go, never both.
    dodeca = ConvexShape.dodecahedron(1.0)
    v = dodeca.vertices
    loop = dodeca.faces[0]
    corner, nxt = v[loop[0]], v[loop[1]]
    direction = (nxt - corner) / np.linalg.norm(nxt - corner)
    extra = corner + 1e-5 * direction + 2e-10 * dodeca.face_normals[0]
    points = np.vstack([v, extra])
    shape = ConvexShape.from_points(points)
    assert shape.num_vertices == 20 and shape.num_faces == 12
    assert_valid(shape, points)


@pytest.mark.parametrize("seed", range(5))
def test_noisy_faces(seed):
    # Many points on the faces of a box with noise comparable to the merge distance: the faces may
    # stay split, but the result must be a consistent convex polyhedron close to the exact hull.
    rng = np.random.default_rng(seed)
    n = 400
    p = rng.random((n, 3)) - 0.5
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.sign(p[np.arange(n), axis]) * 0.5
    p = np.vstack([p, ConvexShape.box(1.0).vertices])
    p += rng.normal(scale=2e-9, size=p.shape)
    p = p @ Rotation.random(random_state=seed).as_matrix().T + [3.0, -1.0, 2.0]
    shape = ConvexShape.from_points(p)
    assert_valid(shape, p)
    merged = ConvexShape.from_points(p, tol=1e-6)
    assert_valid(merged, p)
    assert merged.num_faces == 6 and merged.num_vertices == 8


@pytest.mark.parametrize("tol", [1e-9, 1e-4])
def test_thin_plate_is_not_flattened(tol):
    rng = np.random.default_rng(3)
    p = rng.normal(size=(300, 3)) * [1.0, 1.0, 1e-5]
    shape = ConvexShape.from_points(p, tol=tol)
    assert_valid(shape, p)
    assert shape.volume == pytest.approx(ConvexHull(p).volume, rel=1e-2)


def test_dense_sphere_cloud_float32():
    rng = np.random.default_rng(4)
    p = rng.normal(size=(1000, 3))
    p = (p / np.linalg.norm(p, axis=1, keepdims=True) + 50.0).astype(np.float32).astype(np.float64)
    for tol in (1e-12, 1e-9, 1e-6):
        shape = ConvexShape.from_points(p, tol=tol)
        assert_valid(shape, p)


def test_far_from_origin():
    rot = Rotation.from_euler("zyx", [0.4, 0.2, -0.7]).as_matrix()
    box = ConvexShape.box(1.0, 2.0, 3.0)
    points = box.vertices @ rot.T + [1e5, -2e5, 3e5]
    shape = ConvexShape.from_points(points)
    assert shape.num_faces == 6
    assert shape.volume == pytest.approx(6.0, rel=1e-9)
    np.testing.assert_allclose(shape.input_translation, [1e5, -2e5, 3e5], rtol=1e-15)


def test_scaled():
    rock = ConvexShape.rock(seed=2)
    big = rock.scaled(2.5)
    assert big is not rock and big.name == rock.name
    np.testing.assert_allclose(big.vertices, 2.5 * rock.vertices)
    assert big.volume == pytest.approx(2.5**3 * rock.volume)
    np.testing.assert_allclose(big.inertia, 2.5**5 * rock.inertia)
    np.testing.assert_allclose(big.face_offsets, 2.5 * rock.face_offsets)
    np.testing.assert_allclose(big.face_radii, 2.5 * rock.face_radii)
    np.testing.assert_array_equal(big.face_normals, rock.face_normals)
    assert big.radius == pytest.approx(2.5 * rock.radius)
    np.testing.assert_array_equal(big.input_rotation, rock.input_rotation)
    np.testing.assert_allclose(big.input_translation, 2.5 * rock.input_translation)
    # Same as rebuilding from the scaled input points.
    rebuilt = ConvexShape.from_points(2.5 * rock.to_input_frame(rock.vertices))
    assert rebuilt.volume == pytest.approx(big.volume, rel=1e-12)
    np.testing.assert_allclose(rebuilt.input_transform, big.input_transform, atol=1e-12)
    with pytest.raises(ValueError, match="factor must be positive"):
        rock.scaled(0.0)


def test_repr():
    text = repr(ConvexShape.box(1.0, name="brick"))
    assert text.startswith("ConvexShape(") and "'brick'" in text and "faces=6" in text and "vertices=8" in text


# ---------------------------------------------------------------------- meshes and files


def test_from_mesh_convex_no_warning():
    mesh = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        shape = ConvexShape.from_mesh(mesh, name="slab")
    assert shape.name == "slab" and shape.num_faces == 6
    assert shape.volume == pytest.approx(1.0)


def test_from_mesh_non_convex_warns_and_uses_hull():
    l_shape = _l_mesh()
    assert l_shape.is_watertight
    assert l_shape.volume == pytest.approx(3.0)
    with pytest.warns(UserWarning, match="not convex") as record:
        shape = ConvexShape.from_mesh(l_shape)
    message = str(record[0].message)
    assert "mesh volume 3 m^3" in message
    assert "convex hull volume 3.5 m^3" in message
    assert "relative difference 14.286%" in message
    assert shape.volume == pytest.approx(3.5)
    assert shape.num_faces == 7


def test_from_mesh_box_with_dent_warns():
    mesh = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    mesh = mesh.subdivide()
    top = np.isclose(mesh.vertices[:, 2], 0.5) & np.all(np.isclose(mesh.vertices[:, :2], 0.0), axis=1)
    assert top.sum() == 1
    mesh.vertices[top, 2] = 0.3
    with pytest.warns(UserWarning, match=r"mesh volume .* convex hull volume 1 m\^3 \(relative difference"):
        shape = ConvexShape.from_mesh(mesh, name="dented")
    assert shape.volume == pytest.approx(1.0)
    assert shape.num_faces == 6


def test_from_mesh_open_surface_warns():
    mesh = trimesh.creation.icosphere(subdivisions=1)
    mesh.update_faces(np.arange(len(mesh.faces)) != 0)
    with pytest.warns(UserWarning, match="not watertight"):
        shape = ConvexShape.from_mesh(mesh)
    assert shape.num_faces == 80


def test_from_mesh_rejects_other_types():
    with pytest.raises(TypeError, match="trimesh.Trimesh"):
        ConvexShape.from_mesh(np.zeros((4, 3)))


@pytest.mark.parametrize("ext", ["obj", "stl", "ply"])
def test_from_file_round_trip(tmp_path, ext):
    original = ConvexShape.box(0.5, 1.0, 2.0)
    path = tmp_path / f"brick.{ext}"
    original.to_trimesh().export(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loaded = ConvexShape.from_file(path)
    assert loaded.name == "brick"
    assert loaded.num_faces == 6 and loaded.num_vertices == 8
    assert loaded.volume == pytest.approx(original.volume, rel=1e-12)
    np.testing.assert_allclose(loaded.inertia, original.inertia, rtol=1e-10)
    assert same_point_sets(loaded.to_input_frame(loaded.vertices), original.vertices, 1e-12)


def test_from_file_float32_needs_larger_tolerance(tmp_path):
    # STL stores float32: a rotated dodecahedron's pentagons are then flat only to ~1e-7, so they
    # merge at tol=1e-6 but stay split into triangles at the default 1e-9.
    rot = Rotation.from_euler("xyz", [0.1, 0.7, -0.4]).as_matrix()
    mesh = ConvexShape.dodecahedron(1.0).to_trimesh()
    mesh.apply_transform(np.block([[rot, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]))
    path = tmp_path / "dodeca.stl"
    mesh.export(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        strict = ConvexShape.from_file(path)
        loose = ConvexShape.from_file(path, name="d12", tol=1e-6)
    assert strict.num_faces > 12
    assert loose.num_faces == 12 and loose.name == "d12"
    assert all(len(f) == 5 for f in loose.faces)
    assert loose.volume == pytest.approx((15.0 + 7.0 * SQRT5) / 4.0, rel=1e-6)
    deviation = max(
        np.abs(loose.vertices[f] @ n - d).max()
        for f, n, d in zip(loose.faces, loose.face_normals, loose.face_offsets, strict=True)
    )
    assert deviation <= min(loose.tolerance, 1e-6 * loose.radius)


def test_from_file_missing(tmp_path):
    path = tmp_path / "nope.obj"
    with pytest.raises(FileNotFoundError, match=re.escape(str(path))):
        ConvexShape.from_file(path)


def _box_bytes(ext):
    data = trimesh.creation.box(extents=(1.0, 2.0, 3.0)).export(file_type=ext)
    return data.encode() if isinstance(data, str) else data


def _noise(seed):
    return np.random.default_rng(seed).integers(0, 256, 500, dtype=np.uint8).tobytes()


_PLY_HEAD = b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\n"
_FORMAT = r"cannot read mesh file .*unknown mesh format '\.xyzq'; use an \.obj, \.stl or \.ply"


@pytest.mark.parametrize(
    ("name", "content", "reason"),
    [
        ("empty.obj", b"", "holds no vertices"),
        ("text.obj", b"hello\nnot a mesh\n", "holds no vertices"),
        ("junk.stl", b"\x00\x01 not an stl", r"cannot read mesh file .*not a valid STL file \(it has \d+ bytes"),
        ("shape.xyzq", b"1 2 3\n", _FORMAT),
        # Issue 9: random bytes and truncated files gave "No module named 'charset_normalizer'".
        ("noise.obj", _noise(0), r"not a valid OBJ file \(binary data at byte \d+"),
        ("noise.stl", _noise(1), r"not a valid STL file \(as binary STL it declares \d+ triangles"),
        ("noise.ply", _PLY_HEAD + bytes(50), r"not a valid PLY file \("),
        ("half.stl", _box_bytes("stl")[:342], r"declares 12 triangles \(684 bytes\) but has 342 bytes"),
        ("half.ply", _box_bytes("ply")[:300], r"not a valid PLY file \("),
        ("latin1.stl", b"solid \xe9\xff\n", r"not a valid STL file"),
    ],
)
def test_from_file_unreadable(tmp_path, name, content, reason):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(ValueError, match=reason) as info:
        ConvexShape.from_file(path)
    message = str(info.value)
    assert str(path) in message and "\n" not in message
    assert "charset_normalizer" not in message and "No module" not in message
    if "cannot read" in message and "unknown mesh format" not in message:
        assert "re-export it as OBJ, STL or PLY" in message  # the fix


_TET_FACES = "f 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nv nan 0.5 0.5\n" + _TET_FACES, "line 5: vertex 5 'v nan 0.5 0.5'"),
        ("# box\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 inf\n" + _TET_FACES, "line 5: vertex 4 'v 1 1 inf'"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1e999\n" + _TET_FACES, "line 4: vertex 4 'v 0 0 1e999'"),
    ],
)
def test_from_file_obj_with_non_finite_vertex_names_the_line(tmp_path, text, where):
    """Issue 9: a vertex "v nan 0.5 0.5" (unused by any face) was dropped silently and the shape accepted."""
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(ValueError, match="non-finite coordinate") as info:
        ConvexShape.from_file(path)
    message = str(info.value)
    assert f"mesh file '{path}', {where}" in message
    assert "give finite x y z numbers, or remove the vertex and the faces that use it" in message


def test_from_file_obj_vertex_without_three_numbers(tmp_path):
    path = tmp_path / "short.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1\nv 0 0 1\nf 1 2 4\n")
    with pytest.raises(ValueError, match=r"line 3: vertex 3 'v 0 1' does not hold three numbers x y z; fix the line"):
        ConvexShape.from_file(path)


@pytest.mark.parametrize("ext", ["stl", "ply"])
def test_from_file_binary_with_non_finite_vertex(tmp_path, ext):
    mesh = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    vertices = mesh.vertices.copy()
    vertices[3] = [np.nan, 0.0, 0.0]
    path = tmp_path / f"bad.{ext}"
    trimesh.Trimesh(vertices, mesh.faces, process=False).export(path)
    with pytest.raises(ValueError, match=r"vertex \d+ \(counting from 0\) has non-finite coordinates") as info:
        ConvexShape.from_file(path)
    assert str(path) in str(info.value) and "remove them and the faces that use them" in str(info.value)


def test_from_file_latin1_obj_comment_reads(tmp_path):
    path = tmp_path / "accent.obj"
    path.write_bytes(b"# caf\xe9\n" + _box_bytes("obj"))  # not UTF-8: read as Latin-1
    assert ConvexShape.from_file(path).volume == pytest.approx(6.0)


def test_from_file_directory(tmp_path):
    with pytest.raises(ValueError, match="not a regular file"):
        ConvexShape.from_file(tmp_path)


def test_from_file_flat_mesh(tmp_path):
    path = tmp_path / "flat.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 2 4 3\n")
    with pytest.raises(ValueError, match="coplanar"):
        ConvexShape.from_file(path)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "at least 4 points are needed for a 3D convex hull, got 3"),
        ("v 0 0 0\nv 1 0 0\nv 2 0 0\nv 3 0 0\nf 1 2 3\nf 2 3 4\n", "collinear"),
        # zero volume: the apex merges into a base corner (within trimesh's merge distance of 1e-8)
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1e-12\n" + _TET_FACES, "at least 4 points .*got 3; add points"),
    ],
)
def test_from_file_degenerate_meshes(tmp_path, text, match):
    path = tmp_path / "degenerate.obj"
    path.write_text(text)
    with pytest.raises(ValueError, match=match):
        ConvexShape.from_file(path)


def test_shape_size_limits_are_checked_before_building():
    """Issue 9: prism n = 100000 and rock n_points = 100000 took minutes; the kernels take at most
    MAX_FACES faces of MAX_FACE_VERTICES vertices."""
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=r"prism: n must be at most 1024 \(the most vertices of a face.*smaller n"):
        ConvexShape.prism(100_000)
    with pytest.raises(ValueError, match=r"rock: n_points must be at most 10242 \(a hull of at most 20480 faces\)"):
        ConvexShape.rock(100_000)
    rng = np.random.default_rng(0)
    cloud = rng.normal(size=(50_000, 3))
    cloud /= np.linalg.norm(cloud, axis=1, keepdims=True)  # every point is a hull vertex
    with pytest.raises(ValueError, match=r"50000 vertices, so at least 25002 faces: more than the 20480 .*simplify"):
        ConvexShape.from_points(cloud)
    assert time.perf_counter() - t0 < 5.0
    assert (MAX_FACES, MAX_FACE_VERTICES) == (20480, 1024)
    assert ConvexShape.prism(MAX_FACE_VERTICES).num_faces == MAX_FACE_VERTICES + 2  # the limit itself builds


def test_importing_the_scene_module_does_not_import_trimesh_or_scipy_spatial():
    code = "import sys, polydem.scene; print(sorted(m for m in ('trimesh', 'scipy.spatial') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


# ---------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    ("points", "match"),
    [
        (np.zeros((5, 2)), r"shape \(n, 3\).*got shape \(5, 2\)"),
        (np.zeros(12), r"shape \(n, 3\).*got shape \(12,\)"),
        ([["a", "b", "c"]] * 4, "numeric array"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0], [0, 0, 1], [np.inf, 1, 1]]), r"2 row\(s\) \[2, 4\]"),
        (np.eye(3), "at least 4 points.*got 3"),
        (np.ones((6, 3)), "identical"),
        (np.outer(np.arange(5.0), [1.0, 2.0, 3.0]), "collinear"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1e-12]]), "coplanar.*add at least one point off"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, 1e-6, 0], [0, 0, 1e-6]]), "volume .* below 1e-12"),
    ],
)
def test_invalid_points(points, match):
    with pytest.raises(ValueError, match=match):
        ConvexShape.from_points(points)


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: ConvexShape.box(-1.0), "box: sx must be positive"),
        (lambda: ConvexShape.box(1.0, 0.0, 1.0), "box: sy must be positive"),
        (lambda: ConvexShape.box(1.0, 1.0, float("nan")), "box: sz must be positive and finite"),
        (lambda: ConvexShape.box("big"), "box: sx must be a positive number"),
        (lambda: ConvexShape.tetrahedron(0.0), "tetrahedron: edge must be positive"),
        (lambda: ConvexShape.octahedron(-2.0), "octahedron: edge must be positive"),
        (lambda: ConvexShape.dodecahedron(float("inf")), "dodecahedron: edge must be positive"),
        (lambda: ConvexShape.icosahedron(0), "icosahedron: edge must be positive"),
        (lambda: ConvexShape.prism(2), "prism: n must be an integer >= 3, got 2"),
        (lambda: ConvexShape.prism(4.5), "prism: n must be an integer >= 3"),
        (lambda: ConvexShape.prism(5, radius=-1.0), "prism: radius must be positive"),
        (lambda: ConvexShape.prism(5, height=0.0), "prism: height must be positive"),
        (lambda: ConvexShape.rock(n_points=3), "rock: n_points must be an integer >= 4"),
        (lambda: ConvexShape.rock(size=0.0), "rock: size must be positive"),
        (lambda: ConvexShape.rock(elongation=(1.0, 0.0, 1.0)), "rock: elongation must be three positive"),
        (lambda: ConvexShape.rock(elongation=(1.0, 2.0)), "rock: elongation must be three positive"),
        (lambda: ConvexShape.rock(roughness=1.0), r"rock: roughness must be in \[0, 1\)"),
        (lambda: ConvexShape.sphere(-1), "sphere: subdivisions must be an integer >= 0"),
        (lambda: ConvexShape.sphere(6), "sphere: subdivisions must be <= 5"),
        (lambda: ConvexShape.sphere(1, radius=0.0), "sphere: radius must be positive"),
        (lambda: ConvexShape.from_points(np.eye(4)[:, :3], tol=-1.0), r"tol must be a relative tolerance"),
    ],
)
def test_invalid_arguments(call, match):
    with pytest.raises(ValueError, match=match):
        call()


# ---------------------------------------------------------------------- helpers


def _l_mesh():
    """Watertight L-shaped prism: a 2 x 1 x 1 block with a unit cube on one end (volume 3, hull 3.5)."""
    profile = np.array([[-1.0, -0.5], [1.0, -0.5], [1.0, 0.5], [0.0, 0.5], [0.0, 1.5], [-1.0, 1.5]])  # (x, z)
    vertices = np.array([[x, y, z] for y in (-0.5, 0.5) for x, z in profile])
    caps = [(3, 4, 5), (3, 5, 0), (3, 0, 1), (3, 1, 2)]  # fan from the reflex corner
    faces = list(caps) + [(c[0] + 6, c[2] + 6, c[1] + 6) for c in caps]
    for i in range(6):
        j = (i + 1) % 6
        faces += [(i, i + 6, j), (j, i + 6, j + 6)]
    mesh = trimesh.Trimesh(vertices, faces, process=True)
    mesh.fix_normals()
    return mesh
