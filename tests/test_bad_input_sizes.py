"""Absurd sizes, scales, speeds and counts in a scene file (issue 24): each is refused by `polydem validate` in
one line, exit code 2, naming the key and what to give instead.

Before, each of these crashed with a raw Python or numpy error (a traceback: ZeroDivisionError, OverflowError,
qhull's RuntimeError or ValueError), printed a qhull report over many lines, passed with numpy's overflow
warnings on stderr, or named a key other than the one given.
"""

import pytest
import trimesh
from cli_helpers import run, write_scene

# A steel cube over a plane; each case adds to it or replaces a value in it.
CUBE = """\
[simulation]
name = "cube"
dt = "auto"
steps = 20

[materials.steel]
density = 7800.0
law = "hertz"
k = 1.0e10
restitution = 0.5
friction = 0.3

[shapes.cube]
type = "box"
size = 0.1

[[bodies]]
shape = "cube"
material = "steel"
position = [0.0, 0.0, 0.2]

[[walls]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
material = "steel"

[output]
usd = false
pictures = false
"""


def _shape(spec: str) -> str:
    """A shape ``s`` and a body of it away from the cube."""
    return f'\n[shapes.s]\n{spec}\n\n[[bodies]]\nshape = "s"\nmaterial = "steel"\nposition = [3.0, 0.0, 1.0]\n'


def _wall(spec: str) -> str:
    return f'\n[[walls]]\nmaterial = "steel"\n{spec}\n'


def _emitter(spec: str) -> str:
    return (
        '\n[[emitters]]\nshape = "cube"\nmaterial = "steel"\ncount = 5\n'
        f"region = {{min = [50.0, 0.0, 0.0], max = [51.0, 1.0, 1.0]}}\n{spec}\n"
    )


_BOX = 'type = "box"\ncenter = [5.0, 0.0, 1.0]\n'
_DRUM = 'type = "drum"\ncenter = [10.0, 0.0, 1.0]\naxis = [0.0, 1.0, 0.0]\n'
_TRIANGLE = 'type = "mesh"\nvertices = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]\ntriangles = [[0, 1, 2]]\n'
_BIG = "1" + "0" * 400  # an integer past the floats, which TOML takes

# name: (what replaces what in CUBE, what is added to it, the key named, words of the message)
CASES = {
    # Before: ZeroDivisionError in the loads check (|g| overflowed to inf).
    "gravity 1e300": (("steps = 20", "steps = 20\ngravity = [1e300, 0.0, -9.81]"), "", "simulation.gravity",
                      "beyond the accelerations a run computes with"),
    # Before: qhull's RuntimeError (1e300) and ZeroDivisionError (1e-300) building the shape.
    "box size 1e300": (("size = 0.1", "size = 1e300"), "", "shapes.cube.size", "must be <= 3.4e+32 m"),
    "box size 1e-300": (("size = 0.1", "size = 1e-300"), "", "shapes.cube.size", "must be >= 1.18e-32 m"),
    "box sizes 1e300": (("size = 0.1", "size = [1e300, 1e300, 1e300]"), "", "shapes.cube.size",
                        "each component must be <= 3.4e+32 m"),
    "tetrahedron edge 1e-300": ((), _shape('type = "tetrahedron"\nedge = 1e-300'), "shapes.s.edge",
                                "must be >= 1.18e-32 m"),
    "octahedron edge 1e300": ((), _shape('type = "octahedron"\nedge = 1e300'), "shapes.s.edge", "must be <= 3.4e+32 m"),
    # Before: exit 2, but qhull's report over 16 lines.
    "dodecahedron edge 1e300": ((), _shape('type = "dodecahedron"\nedge = 1e300'), "shapes.s.edge",
                                "a shape needs a bounding radius from 1e-08 to 1.4e+08 m"),
    "icosahedron edge 1e-300": ((), _shape('type = "icosahedron"\nedge = 1e-300'), "shapes.s.edge",
                                "must be >= 1.18e-32 m"),
    "rock size 1e-300": ((), _shape('type = "rock"\nn_points = 12\nsize = 1e-300'), "shapes.s.size",
                         "must be >= 1.18e-32 m"),
    "sphere radius 1e300": ((), _shape('type = "sphere"\nsubdivisions = 1\nradius = 1e300'), "shapes.s.radius",
                            "must be <= 3.4e+32 m"),
    "compound part 1e300": ((), _shape('type = "compound"\nparts = [{type = "box", size = 1e300}]'),
                            "shapes.s.parts[0].size", "must be <= 3.4e+32 m"),
    # Before: ValueError ("points are (nearly) coplanar") building a slab.
    "container wall_thickness 1e9": ((), _wall(_BOX + "inner_size = [1.0, 1.0, 1.0]\nwall_thickness = 1e9"),
                                     "walls[1].wall_thickness", "give a wall_thickness from 1e-06 to 1e+06 m"),
    "container inner_size 1e9": ((), _wall(_BOX + "inner_size = [1e9, 1.0, 1.0]"), "walls[1].inner_size",
                                 "give inner sizes within a factor of 1e+06 of each other"),
    "drum radius 1e9": ((), _wall(_DRUM + "radius = 1e9\nlength = 0.3\nrpm = 10.0\nthickness = 0.05"),
                        "walls[1].radius", "give a radius from 3e-07 to 5e+04 m"),
    "drum length 1e30": ((), _wall(_DRUM + "radius = 0.5\nlength = 1e30\nrpm = 10.0\nthickness = 0.05"),
                         "walls[1].length", "give a length from 5e-07 to 5e+04 m"),
    "drum thickness 1e-300": ((), _wall(_DRUM + "radius = 0.5\nlength = 0.3\nrpm = 10.0\nthickness = 1e-300"),
                              "walls[1].thickness", "must be >= 1.18e-32 m"),
    # Before: OverflowError scaling the shape (factor^5).
    "emitter scale 1e300": ((), _emitter("scale = 1e300"), "emitters[0].scale",
                            "give size factors from 1.2e-07 to 1.57e+09"),
    "emitter scale_range 1e300": ((), _emitter("scale_range = [1e300, 1e300]"), "emitters[0].scale_range",
                                  "too large for the simulator's float32 arithmetic"),
    "emitter scale_lognormal 1e300": ((), _emitter("scale_lognormal = {mean = 1e300, sigma = 0.2}"),
                                      "emitters[0].scale_lognormal", "give size factors from"),
    # Before: exit 0, with numpy's "overflow encountered" warnings on stderr.
    "body velocity 1e300": (("position = [0.0, 0.0, 0.2]", "position = [0.0, 0.0, 0.2]\nvelocity = [1e300, 0.0, 0.0]"),
                            "", "bodies[0].velocity", "each component must be in [-3.4e+32, 3.4e+32]"),
    "body angular_velocity 1e300": (
        ("position = [0.0, 0.0, 0.2]", "position = [0.0, 0.0, 0.2]\nangular_velocity = [0.0, 1e300, 0.0]"),
        "", "bodies[0].angular_velocity", "each component must be in [-3.4e+32, 3.4e+32]"),
    "pivot 1e300": ((), '\n[[bodies]]\nshape = "cube"\nmaterial = "steel"\nposition = [2.0, 0.0, 0.5]\n'
                        'kind = "kinematic"\nangular_velocity = [0.0, 0.0, 1.0]\npivot = [1e300, 0.0, 0.4]\n',
                    "bodies[1].pivot", "give a pivot and a position nearer each other"),
    "drum rpm 1e300": ((), _wall(_DRUM + "radius = 0.5\nlength = 0.3\nrpm = 1e300"), "walls[1].rpm",
                       "must be in [-3.4e+32, 3.4e+32]"),
    "mesh wall velocity 1e300": ((), _wall(_TRIANGLE + "position = [30.0, 0.0, 0.0]\nvelocity = [1e300, 0.0, 0.0]"),
                                 "walls[1].velocity", "each component must be in [-3.4e+32, 3.4e+32]"),
    "emitter velocity_jitter 1e300": ((), _emitter("velocity_jitter = 1e300"), "emitters[0].velocity_jitter",
                                      "must be <= 3.4e+32"),
    # Before: OverflowError ("int too large to convert to float").
    "density 1e400": (("density = 7800.0", f"density = {_BIG}"), "", "materials.steel.density",
                      "expected a finite number, got 1e+400"),
    "steps 1e400": (("steps = 20", f"steps = {_BIG}"), "", "simulation.steps",
                    "must be an integer <= 2147483647, got 1e+400"),
    "position 1e400": (("position = [0.0, 0.0, 0.2]", f"position = [{_BIG}, 0.0, 0.2]"), "", "bodies[0].position",
                       "got integer 1e+400"),
    "emitter count 1e400": ((), _emitter("").replace("count = 5", f"count = {_BIG}"), "emitters[0].count",
                            "count = 1e+400 would make 1e+400 bodies"),
    # Before: one line, but naming walls[1] (or walls[1].file) and no fix.
    "mesh wall scale 1e300": ((), _wall(_TRIANGLE + "position = [30.0, 0.0, 0.0]\nscale = 1e300\nthickness = 0.1"),
                              "walls[1].scale", "give the mesh file's unit in m"),
    "mesh wall pivot 1e300": ((), _wall(_TRIANGLE + "position = [30.0, 0.0, 0.0]\npivot = [1e300, 0.0, 0.0]"),
                              "walls[1].pivot", "give a pivot nearer the wall"),
    "mesh wall position 1e30": ((), _wall(_TRIANGLE + "position = [1e30, 0.0, 0.0]"), "walls[1].position",
                                "place the scene nearer the origin"),
    # Before: one line, but "the region is 1e+30 m along x, too small for one body" (an int64 overflow).
    "emitter region 1e30": ((), _emitter("").replace("max = [51.0, 1.0, 1.0]", "max = [1e30, 1.0, 1.0]"),
                            "emitters[0].region", "far more than 5 bodies need"),
}  # fmt: skip


def _refused(path, capsys, key, words):
    code, out, err = run(["validate", path], capsys)
    assert code == 2 and out == "", (code, out, err)
    assert err.count("\n") == 1 and err.startswith(f"polydem: error: {path}: {key}: "), err
    assert words in err, err


@pytest.mark.parametrize("case", list(CASES))
def test_absurd_value_is_refused_in_one_line(tmp_path, capsys, case):
    replace, extra, key, words = CASES[case]
    path = write_scene(tmp_path, CUBE + extra, "scene.toml", replace=[replace] if replace else ())
    _refused(path, capsys, key, words)


# Shapes from mesh files: a 1 m cube, and two for a compound cut into its connected pieces.
MESHES = {
    # Before: OverflowError scaling the shape.
    "mesh shape scale 1e300": ('type = "mesh"\nfile = "cube.stl"\nscale = 1e300', "shapes.s.scale",
                               "give a scale from 1.2e-08 to 1.57e+08"),
    # Before: ZeroDivisionError building a part's mass properties.
    "compound file scale 1e-300": ('type = "compound"\nfile = "two.stl"\ndecompose = "components"\nscale = 1e-300',
                                   "shapes.s.scale", "beyond the lengths a run holds"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(MESHES))
def test_absurd_mesh_scale_is_refused_in_one_line(tmp_path, capsys, case):
    spec, key, words = MESHES[case]
    cube = trimesh.creation.box((1.0, 1.0, 1.0))
    cube.export(tmp_path / "cube.stl")
    trimesh.util.concatenate([cube, cube.copy().apply_translation((2.0, 0.0, 0.0))]).export(tmp_path / "two.stl")
    path = write_scene(tmp_path, CUBE + _shape(spec), "scene.toml")
    _refused(path, capsys, key, words)
