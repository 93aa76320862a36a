"""Writes the triangle meshes of the mesh-wall scenes (hopper.toml, heap.toml, mixer.toml, tapped_cup.toml) into
this folder.

heap.toml uses the hopper with the 7 cm orifice as its funnel.

    python scenes/meshes/make_meshes.py

Every mesh faces the grains (its triangles counter-clockwise seen from them), so that the solid of
a mesh wall lies behind it. Lengths in metres. Deterministic: running it again writes the same files.

* ``hopper_D{mm}.stl``: a conical hopper of half-angle 30 degrees from the vertical with a
  cylindrical bin above it, radius 0.12 m, open at the top and at the orifice of diameter D at
  z = 0, for the orifice sizes of ``ORIFICES`` (in mm);
* ``drum.stl``: a closed cylinder of radius 0.15 m and length 0.15 m around the y axis, its normals
  pointing inwards (a container); ``baffles.stl``: four bars 3 cm high and 1.5 cm thick along its
  wall, closed boxes facing out (mixer.toml turns both);
* ``cup.stl``: a cylindrical cup of inner radius 0.06 m and height 0.2 m, its flat bottom at z = 0, open at the
  top, facing inwards (tapped_cup.toml taps it).
"""

from pathlib import Path

import numpy as np
import trimesh

HERE = Path(__file__).parent
ORIFICES = (50, 60, 70, 90)  # mm: 5 to 9 cube edges of 1 cm
# Around the axis: at 96 the cone's triangles near a 5 cm orifice are 1.6 mm wide, a sixth of a grain,
# and a grain there overlaps tens of cells (each one a clipping); at 32 they are 5 mm wide.
SEGMENTS = 32


def surface_of_revolution(profile, segments=SEGMENTS):
    """Triangles of the surface swept by the (r, z) ``profile`` (a polyline, at least two points)
    about the z axis, facing the axis (counter-clockwise seen from inside)."""
    profile = np.asarray(profile, dtype=np.float64)
    th = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    rings = [np.column_stack([r * np.cos(th), r * np.sin(th), np.full(segments, z)]) for r, z in profile]
    verts = np.concatenate(rings)
    faces = []
    k = np.arange(segments)
    for i in range(len(profile) - 1):
        a, b = i * segments + k, i * segments + (k + 1) % segments
        c, d = (i + 1) * segments + (k + 1) % segments, (i + 1) * segments + k
        faces += [np.column_stack([a, b, c]), np.column_stack([a, c, d])]
    mesh = trimesh.Trimesh(verts, np.concatenate(faces), process=False)
    inward = np.sum(mesh.face_normals[:, :2] * mesh.triangles_center[:, :2], axis=1)
    if np.mean(inward) > 0.0:
        mesh.invert()
    # A fresh mesh, so that the facet normals written to the STL follow the inverted winding.
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)


def hopper(orifice, radius=0.12, half_angle_deg=30.0, bin_height=0.25, rings=4):
    """Cone from the orifice (z = 0) up to ``radius``, then a vertical bin ``bin_height`` tall."""
    cone_height = (radius - orifice / 2) / np.tan(np.radians(half_angle_deg))
    cone = [(orifice / 2 + (radius - orifice / 2) * t, cone_height * t) for t in np.linspace(0.0, 1.0, rings + 1)]
    bin_ = [(radius, cone_height + bin_height * t) for t in np.linspace(0.0, 1.0, rings + 1)[1:]]
    return surface_of_revolution(cone + bin_)


def drum(radius=0.15, length=0.15):
    """A closed drum about the y axis, facing inwards (a container)."""
    shell = trimesh.creation.cylinder(radius=radius, height=length, sections=SEGMENTS)
    shell.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    shell.invert()
    return trimesh.Trimesh(shell.vertices, shell.faces, process=False)


def baffles(radius=0.15, length=0.15, count=4, height=0.03, width=0.015):
    """Bars along the drum's wall (closed boxes facing out), reaching ``height`` in from it."""
    bars = []
    for k in range(count):
        ang = 2.0 * np.pi * k / count
        box = trimesh.creation.box(extents=[height + 0.005, length - 0.002, width])
        box.apply_translation([radius - height / 2 + 0.0025, 0.0, 0.0])
        box.apply_transform(trimesh.transformations.rotation_matrix(ang, [0, 1, 0]))
        bars.append(box)
    return trimesh.util.concatenate(bars)


def cup(radius=0.06, height=0.2, step=0.01):
    """A cylindrical cup about the z axis, bottom at z = 0, open at the top, facing inwards; triangles about
    ``step`` in size (a long thin triangle has a large bounding sphere, which the emitters and the broad
    phase see)."""
    rings = np.arange(step, radius + 0.5 * step, step)
    profile = [(r, 0.0) for r in rings] + [(radius, z) for z in np.arange(step, height + 0.5 * step, step)]
    side = surface_of_revolution(profile)
    # The bottom's centre: a fan out to the first ring, wound as the annuli next to it.
    th = np.linspace(0.0, 2.0 * np.pi, SEGMENTS, endpoint=False)
    ring = np.column_stack([rings[0] * np.cos(th), rings[0] * np.sin(th), np.zeros(SEGMENTS)])
    k = np.arange(SEGMENTS)
    fan = trimesh.Trimesh(
        np.vstack([ring, [0.0, 0.0, 0.0]]),
        np.column_stack([np.full(SEGMENTS, SEGMENTS), k, (k + 1) % SEGMENTS]),
        process=False,
    )
    if np.sign(fan.face_normals[0, 2]) != np.sign(side.face_normals[side.triangles_center[:, 2] < 1e-12][0, 2]):
        fan.invert()
    mesh = trimesh.util.concatenate([side, fan])
    mesh.merge_vertices()
    if mesh.face_normals[mesh.triangles_center[:, 2] < 1e-12][:, 2].mean() < 0.0:
        mesh.invert()  # the bottom faces up, into the cup
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)


def main():
    for d_mm in ORIFICES:
        m = hopper(d_mm / 1000.0)
        m.export(HERE / f"hopper_D{d_mm}.stl")
        print(f"hopper_D{d_mm}.stl: {len(m.faces)} triangles")
    m = drum()
    m.export(HERE / "drum.stl")
    print(f"drum.stl: {len(m.faces)} triangles")
    m = baffles()
    m.export(HERE / "baffles.stl")
    print(f"baffles.stl: {len(m.faces)} triangles")
    m = cup()
    m.export(HERE / "cup.stl")
    print(f"cup.stl: {len(m.faces)} triangles")


if __name__ == "__main__":
    main()
