"""Scene files: the TOML schema, reading a file into a Scene and writing a Scene back as a dict."""

from __future__ import annotations

import math
import tomllib
from os import PathLike
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from polydem.scene.bodies import KINDS, quat_from_axis_angle
from polydem.scene.errors import SceneError
from polydem.scene.output import Output
from polydem.scene.shape_specs import build_shape
from polydem.scene.values import (
    check_keys,
    read_boolean,
    read_choice,
    read_number,
    read_rows,
    read_string,
    read_table,
    read_vector,
    typename,
)

if TYPE_CHECKING:
    from polydem.scene.description import Scene

_SIM_KEYS = (
    "name",
    "description",
    "dt",
    "gravity",
    "steps",
    "duration",
    "device",
    "precision",
    "until_settled",
    "settle",
)
_TOP_KEYS = ("simulation", "materials", "shapes", "bodies", "walls", "emitters", "output")
_BODY_KEYS = (
    "shape",
    "material",
    "position",
    "orientation",
    "rotation",
    "velocity",
    "angular_velocity",
    "kind",
    "pivot",
)
_WALL_KEYS = {
    "plane": ("type", "point", "normal", "material"),
    "box": ("type", "center", "inner_size", "material", "wall_thickness", "open_top"),
    "drum": ("type", "center", "axis", "radius", "length", "material", "omega", "rpm", "sides", "thickness", "caps"),
    "mesh": (
        "type",
        "file",
        "vertices",
        "triangles",
        "material",
        "scale",
        "rotation",
        "orientation",
        "position",
        "flip_normals",
        "thickness",
        "velocity",
        "angular_velocity",
        "pivot",
    ),
}
_WALL_REQUIRED = {
    "plane": ("point", "normal", "material"),
    "box": ("center", "inner_size", "material"),
    "drum": ("center", "axis", "radius", "length", "material"),
    "mesh": ("material",),
}
_EMITTER_KEYS = (
    "shape",
    "weights",
    "material",
    "count",
    "region",
    "orientation",
    "seed",
    "velocity",
    "velocity_jitter",
    "scale",
    "scale_range",
    "scale_lognormal",
    "scale_bins",
    "kind",
    "spacing",
    "jitter",
    "fill",
)
_EMITTER_HINTS = {
    "shape": "a shape name, a list of names, or a table of weights such as {cube = 2, rock = 1}",
    "material": "a material name",
    "count": "number of bodies, an integer >= 1",
    "region": "the box to fill: region = {min = [x0, y0, z0], max = [x1, y1, z1]} in m",
}


def load_toml(cls: type[Scene], path: str | PathLike, validate: bool) -> Scene:
    """:meth:`Scene.from_toml`: read the file, then :func:`load_dict`."""
    path = Path(path)
    if not path.exists():
        raise SceneError(f"scene file not found (looked for '{path.absolute()}'); check the path", None, path)
    if not path.is_file():
        raise SceneError("scene path is not a file; give the path of a .toml scene file", None, path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"invalid TOML syntax: {exc}", None, path) from exc
    except UnicodeDecodeError as exc:
        raise SceneError(f"the file is not UTF-8 text: {exc}", None, path) from exc
    except OSError as exc:
        raise SceneError(f"cannot read the scene file: {exc}", None, path) from exc
    return load_dict(cls, data, path, path.parent, validate)


def load_dict(cls: type[Scene], data: dict, file, base_dir, validate: bool) -> Scene:
    """:meth:`Scene.from_dict`: a scene built section by section through the Scene's own methods."""
    try:
        return _build(cls, data, file, Path.cwd() if base_dir is None else Path(base_dir), validate)
    except SceneError as err:
        if err.file is None:
            err.file = file
        raise


def _build(cls, data, file, base_dir: Path, validate) -> Scene:
    read_table(data, None, file, what="a table of scene sections")
    check_keys(data, _TOP_KEYS, "", file)
    scene = _read_simulation(cls, data, file)
    _read_materials(scene, data, file)
    _read_shapes(scene, data, file, base_dir)
    _read_bodies(scene, data, file)
    _read_walls(scene, data, file, base_dir)
    _read_emitters(scene, data, file)
    if "output" in data:
        scene.output = Output.from_dict(data["output"], file)
    if validate:
        scene.validate()
    return scene


def _read_simulation(cls, data, file) -> Scene:
    sim = read_table(data.get("simulation", {}), "simulation", file, what="a [simulation] table")
    check_keys(sim, _SIM_KEYS, "simulation", file)
    settle = sim.get("settle")
    if "until_settled" in sim:
        until = read_boolean(sim["until_settled"], "simulation.until_settled", file)
        if not until and settle is not None:
            raise SceneError(
                "until_settled = false with a [simulation.settle] table: set until_settled = true, or leave the "
                "table out to run the whole duration",
                "simulation.until_settled",
                file,
            )
        settle = (settle if settle is not None else True) if until else None
    stem = Path(file).stem if file is not None else "scene"
    name = sim.get("name", stem)
    if isinstance(name, str) and not name.strip():
        # A blank name would head every line of the run's output with ": " and name no folder.
        raise SceneError(
            f"the name is empty: it heads the run's output and names its default folder (polydem_out/NAME/); "
            f"give a name, or leave name out to use the file's ({stem!r})",
            "simulation.name",
            file,
        )
    return cls(
        gravity=sim.get("gravity", (0.0, 0.0, -9.81)),
        dt=sim.get("dt", "auto"),
        name=name,
        steps=sim.get("steps"),
        duration=sim.get("duration"),
        description=sim.get("description", ""),
        file=file,
        device=sim.get("device"),
        precision=sim.get("precision", "mixed"),
        settle=settle,
    )


def _read_materials(scene, data, file):
    materials = read_table(
        data.get("materials", {}), "materials", file, what="tables [materials.NAME], one per material"
    )
    for name, props in materials.items():
        props = read_table(
            props,
            f"materials.{name}",
            file,
            what=f"a table [materials.{name}] with density, law, k, restitution, friction",
        )
        scene.add_material(name, **props)


def _read_shapes(scene, data, file, base_dir: Path):
    shapes = read_table(data.get("shapes", {}), "shapes", file, what="tables [shapes.NAME], one per shape")
    for name, spec in shapes.items():
        shape, spec = build_shape(name, spec, f"shapes.{name}", file, base_dir)
        scene.add_shape(name, shape, spec=spec)


def _read_bodies(scene, data, file):
    bodies = data.get("bodies", [])
    if not isinstance(bodies, list):
        raise SceneError(f"expected an array of tables [[bodies]], got {typename(bodies)}", "bodies", file)
    for j, body in enumerate(bodies):
        key = f"bodies[{j}]"
        body = read_table(body, key, file, what="a [[bodies]] table")
        check_keys(body, _BODY_KEYS, key, file, required=("shape", "material", "position"))
        if "orientation" in body and "rotation" in body:
            raise SceneError(
                "give either orientation (quaternion) or rotation (axis and angle), not both",
                f"{key}.rotation",
                file,
            )
        orientation = body.get("orientation", (0.0, 0.0, 0.0, 1.0))
        if "rotation" in body:
            orientation = read_rotation(body["rotation"], f"{key}.rotation", file)
        if "pivot" in body and "velocity" in body:
            raise SceneError(
                "a body turning about a pivot gets its velocity from angular_velocity x (centroid - pivot); "
                "give either velocity or pivot, not both",
                f"{key}.velocity",
                file,
            )
        scene.add_body(
            body["shape"],
            body["material"],
            position=body["position"],
            orientation=orientation,
            velocity=body.get("velocity", (0.0, 0.0, 0.0)),
            angular_velocity=body.get("angular_velocity", (0.0, 0.0, 0.0)),
            kind=body.get("kind", "free"),
            pivot=body.get("pivot"),
            key=key,
        )


def _read_walls(scene, data, file, base_dir=None):
    walls = data.get("walls", [])
    if not isinstance(walls, list):
        raise SceneError(f"expected an array of tables [[walls]], got {typename(walls)}", "walls", file)
    for j, wall in enumerate(walls):
        key = f"walls[{j}]"
        wall = read_table(wall, key, file, what="a [[walls]] table")
        if "type" not in wall:
            raise SceneError("missing required key 'type' ('plane', 'box', 'drum' or 'mesh')", f"{key}.type", file)
        kind = read_choice(wall["type"], _WALL_KEYS, f"{key}.type", file, what="wall type")
        check_keys(wall, _WALL_KEYS[kind], key, file, required=_WALL_REQUIRED[kind], context=f" for type = {kind!r}")
        if kind == "plane":
            scene.add_plane(wall["point"], wall["normal"], wall["material"], key=key)
        elif kind == "mesh":
            _read_mesh_wall(scene, wall, key, file, base_dir)
        elif kind == "box":
            scene.add_box_container(
                wall["center"],
                wall["inner_size"],
                wall["material"],
                wall_thickness=wall.get("wall_thickness"),
                open_top=wall.get("open_top", True),
                key=key,
            )
        else:
            scene.add_drum(
                wall["center"],
                wall["axis"],
                wall["radius"],
                wall["length"],
                wall["material"],
                omega=wall.get("omega"),
                rpm=wall.get("rpm"),
                sides=wall.get("sides", 24),
                thickness=wall.get("thickness"),
                caps=wall.get("caps", True),
                key=key,
            )


def _read_mesh_wall(scene, wall, key, file, base_dir):
    if ("file" in wall) == ("vertices" in wall or "triangles" in wall):
        raise SceneError(
            "give the mesh either as file = 'wall.stl' or as vertices = [[x, y, z], ...] with "
            "triangles = [[i, j, k], ...]",
            f"{key}.file",
            file,
        )
    if "file" in wall:
        mesh = read_string(wall["file"], f"{key}.file", file, what="a file path string")
    else:
        for name in ("vertices", "triangles"):
            if name not in wall:
                raise SceneError(f"missing required key {name!r} (the mesh's {name})", f"{key}.{name}", file)
        mesh = (
            read_rows(wall["vertices"], 3, f"{key}.vertices", file),
            read_rows(wall["triangles"], 3, f"{key}.triangles", file),
        )
    if "orientation" in wall and "rotation" in wall:
        raise SceneError(
            "give either orientation (quaternion) or rotation (axis and angle), not both", f"{key}.rotation", file
        )
    orientation = wall.get("orientation")
    if "rotation" in wall:
        orientation = read_rotation(wall["rotation"], f"{key}.rotation", file)
    scene.add_mesh_wall(
        mesh,
        wall["material"],
        scale=wall.get("scale", 1.0),
        orientation=orientation,
        position=wall.get("position", (0.0, 0.0, 0.0)),
        velocity=wall.get("velocity", (0.0, 0.0, 0.0)),
        angular_velocity=wall.get("angular_velocity", (0.0, 0.0, 0.0)),
        pivot=wall.get("pivot"),
        thickness=wall.get("thickness"),
        flip_normals=wall.get("flip_normals", False),
        key=key,
        base_dir=base_dir,
    )


def _read_emitters(scene, data, file):
    emitters = data.get("emitters", [])
    if not isinstance(emitters, list):
        raise SceneError(f"expected an array of tables [[emitters]], got {typename(emitters)}", "emitters", file)
    for j, emitter in enumerate(emitters):
        key = f"emitters[{j}]"
        emitter = read_table(emitter, key, file, what="an [[emitters]] table")
        check_keys(
            emitter,
            _EMITTER_KEYS,
            key,
            file,
            required=("shape", "material", "count", "region"),
            hints=_EMITTER_HINTS,
        )
        scene.emit(**emitter, key=key)


def scene_dict(scene: Scene) -> dict:
    """:meth:`Scene.to_dict`: the scene as the nested dict of a scene file, from its public attributes."""
    sim = {"name": scene.name, "dt": scene.dt, "gravity": list(scene.gravity), "precision": scene.precision}
    if scene.description:
        sim["description"] = scene.description
    if scene.steps is not None:
        sim["steps"] = scene.steps
    if scene.duration is not None:
        sim["duration"] = scene.duration
    if scene.device is not None:
        sim["device"] = scene.device
    if scene.settle is not None:
        c = scene.settle
        table = {
            "kinetic_fraction": c.kinetic_fraction if c.kinetic_fraction is not None else False,
            "speed_fraction": c.speed_fraction if c.speed_fraction is not None else False,
            "hold": c.hold,
        }
        if c.max_speed is not None:
            table["max_speed"] = c.max_speed
        sim["settle"] = table
    shapes = {}
    for name, shape in scene.shapes.items():
        spec = scene.shape_spec(name)
        if spec is None and getattr(shape, "is_compound", False):
            # Each part as its points in the grain's input frame (where the parts were given).
            spec = {
                "type": "compound",
                "parts": [{"type": "points", "points": p.to_input_frame(p.vertices).tolist()} for p in shape.parts],
            }
        elif spec is None:
            spec = {"type": "points", "points": shape.to_input_frame(shape.vertices).tolist()}
        shapes[name] = spec
    return {
        "simulation": sim,
        "materials": {name: m.to_dict() for name, m in scene.materials.items()},
        "shapes": shapes,
        "bodies": _body_tables(scene),
        "walls": [p.to_dict() for p in scene.planes] + [w.to_dict() for w in scene.mesh_walls],
        "output": scene.output.to_dict(),
    }


def _body_tables(scene: Scene) -> list[dict]:
    pos, q_user = scene.input_poses()
    pivots = scene.body_pivot
    shape_names, material_names = scene.shape_names, scene.material_names
    has_pivot = ~np.isnan(pivots).any(axis=1)
    bodies = []
    for s, m, p, q, v, w, kind, pivoted, pivot in zip(
        scene.body_shape.tolist(),
        scene.body_material.tolist(),
        pos.tolist(),
        q_user.tolist(),
        scene.body_velocity.tolist(),
        scene.body_angular_velocity.tolist(),
        scene.body_kind.tolist(),
        has_pivot.tolist(),
        pivots.tolist(),
        strict=True,
    ):
        body = {
            "shape": shape_names[s],
            "material": material_names[m],
            "position": p,
            "orientation": q,
            "velocity": v,
            "angular_velocity": w,
            "kind": KINDS[kind],
        }
        if pivoted:
            del body["velocity"]
            body["pivot"] = pivot
        bodies.append(body)
    return bodies


def read_rotation(value, key, file) -> np.ndarray:
    """Quaternion of a ``rotation = {axis = [..], degrees = a}`` (or ``radians = a``) table."""
    value = read_table(value, key, file, what="a table {axis = [ax, ay, az], degrees = angle}")
    check_keys(value, ("axis", "degrees", "radians"), key, file, required=("axis",))
    if ("degrees" in value) == ("radians" in value):
        raise SceneError(
            "give the angle as exactly one of degrees or radians, e.g. rotation = {axis = [0, 1, 0], degrees = 20}",
            f"{key}.degrees",
            file,
        )
    axis = read_vector(value["axis"], 3, f"{key}.axis", file)
    if np.linalg.norm(axis) == 0.0:
        raise SceneError("rotation axis is zero; give a direction such as [0, 0, 1]", f"{key}.axis", file)
    if "degrees" in value:
        angle = math.radians(read_number(value["degrees"], f"{key}.degrees", file))
    else:
        angle = read_number(value["radians"], f"{key}.radians", file)
    return quat_from_axis_angle(axis, angle)
