"""Scene files: reading a file into a Scene and writing a Scene back as a dict, table by table as each
table's declaration says (:mod:`.schema`; the tables are declared beside the code that uses them)."""

from __future__ import annotations

import tomllib
from os import PathLike
from pathlib import Path

import numpy as np

from polydem.scene.bodies import BODY, KINDS
from polydem.scene.emitters import EMITTER
from polydem.scene.errors import SceneError
from polydem.scene.materials import MATERIAL
from polydem.scene.motions import MOTION
from polydem.scene.output import Output
from polydem.scene.schema import Key, Table
from polydem.scene.settings import SIMULATION, write_settings
from polydem.scene.shape_specs import build_shape
from polydem.scene.values import read_choice, read_rows, read_table, typename
from polydem.scene.walls import MESH, WALL_TYPES

SCENE = Table(
    "a scene file",
    tuple(
        Key(name, "any")
        for name in ("simulation", "materials", "motions", "shapes", "bodies", "walls", "emitters", "output")
    ),
)
"""The sections of a scene file."""


def load_toml(cls: type, path: str | PathLike, validate: bool):
    """:meth:`Scene.from_toml`: read the file, then :func:`load_dict`; ``cls`` is the Scene class."""
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


def load_dict(cls: type, data: dict, file, base_dir, validate: bool):
    """:meth:`Scene.from_dict`: a scene built section by section through the Scene's own methods."""
    try:
        return _build(cls, data, file, Path.cwd() if base_dir is None else Path(base_dir), validate)
    except SceneError as err:
        if err.file is None:
            err.file = file
        raise


def _build(cls, data, file, base_dir: Path, validate):
    read_table(data, None, file, what="a table of scene sections")
    SCENE.check(data, "", file)
    scene = _read_simulation(cls, data, file)
    _read_materials(scene, data, file)
    _read_motions(scene, data, file)
    _read_shapes(scene, data, file, base_dir)
    _read_bodies(scene, data, file)
    _read_walls(scene, data, file, base_dir)
    _read_emitters(scene, data, file)
    if "output" in data:
        scene.output = Output.from_dict(data["output"], file)
    if validate:
        scene.validate()
    return scene


def _read_simulation(cls, data, file):
    sim = read_table(data.get("simulation", {}), "simulation", file, what="a [simulation] table")
    SIMULATION.check(sim, "simulation", file)
    settle = sim.get("settle")
    if "until_settled" in sim:
        until = SIMULATION["until_settled"].read(sim["until_settled"], "simulation.until_settled", file)
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
    settings = SIMULATION.arguments(sim, "simulation", file, skip=("until_settled", "settle", "name"))
    return cls(**settings, name=name, settle=settle, file=file)


def _read_materials(scene, data, file):
    materials = read_table(
        data.get("materials", {}), "materials", file, what="tables [materials.NAME], one per material"
    )
    for name, props in materials.items():
        props = read_table(
            props,
            f"materials.{name}",
            file,
            what=f"a table [materials.{name}] with {', '.join(MATERIAL.required)}",
        )
        scene.add_material(name, **props)


def _read_motions(scene, data, file):
    motions = read_table(data.get("motions", {}), "motions", file, what="tables [motions.NAME], one per motion")
    for name, props in motions.items():
        props = read_table(props, f"motions.{name}", file, what=f"a table [motions.{name}]")
        MOTION.check(props, f"motions.{name}", file)
        try:
            scene.add_motion(name, **props)
        except SceneError as err:
            err.file = file
            raise


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
        BODY.check(body, key, file)
        _orientation_or_rotation(body, key, file)
        if "pivot" in body and "velocity" in body:
            raise SceneError(
                "a body turning about a pivot gets its velocity from angular_velocity x (centroid - pivot); "
                "give either velocity or pivot, not both",
                f"{key}.velocity",
                file,
            )
        scene.add_body(**BODY.arguments(body, key, file), key=key)


def _orientation_or_rotation(table, key, file):
    if "orientation" in table and "rotation" in table:
        raise SceneError(
            "give either orientation (quaternion) or rotation (axis and angle), not both", f"{key}.rotation", file
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
        kind = read_choice(wall["type"], WALL_TYPES, f"{key}.type", file, what="wall type")
        table = WALL_TYPES[kind]
        table.check(wall, key, file, context=f" for type = {kind!r}")
        if kind == "mesh":
            mesh = _mesh(wall, key, file)
            _orientation_or_rotation(wall, key, file)
            args = table.arguments(wall, key, file, skip=("type", "file", "vertices", "triangles"))
            scene.add_mesh_wall(mesh, **args, key=key, base_dir=base_dir)
            continue
        args = table.arguments(wall, key, file, skip=("type",))
        add = {"plane": scene.add_plane, "box": scene.add_box_container, "drum": scene.add_drum}[kind]
        add(**args, key=key)


def _mesh(wall, key, file):
    """A mesh wall's mesh: its file's path, or its (vertices, triangles)."""
    if ("file" in wall) == ("vertices" in wall or "triangles" in wall):
        raise SceneError(
            "give the mesh either as file = 'wall.stl' or as vertices = [[x, y, z], ...] with "
            "triangles = [[i, j, k], ...]",
            f"{key}.file",
            file,
        )
    if "file" in wall:
        return MESH["file"].read(wall["file"], f"{key}.file", file)
    for name in ("vertices", "triangles"):
        if name not in wall:
            raise SceneError(f"missing required key {name!r} (the mesh's {name})", f"{key}.{name}", file)
    vertices = read_rows(wall["vertices"], 3, f"{key}.vertices", file)
    return vertices, read_rows(wall["triangles"], 3, f"{key}.triangles", file)


def _read_emitters(scene, data, file):
    emitters = data.get("emitters", [])
    if not isinstance(emitters, list):
        raise SceneError(f"expected an array of tables [[emitters]], got {typename(emitters)}", "emitters", file)
    for j, emitter in enumerate(emitters):
        key = f"emitters[{j}]"
        emitter = read_table(emitter, key, file, what="an [[emitters]] table")
        EMITTER.check(emitter, key, file)
        scene.emit(**EMITTER.arguments(emitter, key, file), key=key)


def scene_dict(scene) -> dict:
    """:meth:`Scene.to_dict`: the scene as the nested dict of a scene file, from its public attributes."""
    sim = write_settings(scene)
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
        **({"motions": {name: m.to_dict() for name, m in scene.motions.items()}} if scene.motions else {}),
        "shapes": shapes,
        "bodies": _body_tables(scene),
        "walls": [p.to_dict() for p in scene.planes] + [w.to_dict() for w in scene.mesh_walls],
        "output": scene.output.to_dict(),
    }


def _body_tables(scene) -> list[dict]:
    """A ``[[bodies]]`` table per body, as :data:`BODY` writes it from the columns of the scene's arrays."""
    pos, q_user = scene.input_poses()
    pivots = scene.body_pivot
    pivoted = (~np.isnan(pivots).any(axis=1)).tolist()
    shape_names, material_names = scene.shape_names, scene.material_names
    # A body turning about a pivot has a derived velocity: it is written with the pivot instead.
    columns = {
        "shape": [shape_names[s] for s in scene.body_shape.tolist()],
        "material": [material_names[m] for m in scene.body_material.tolist()],
        "position": pos.tolist(),
        "orientation": q_user.tolist(),
        "velocity": [None if p else v for p, v in zip(pivoted, scene.body_velocity.tolist(), strict=True)],
        "angular_velocity": scene.body_angular_velocity.tolist(),
        "kind": [KINDS[k] for k in scene.body_kind.tolist()],
        "pivot": [v if p else None for p, v in zip(pivoted, pivots.tolist(), strict=True)],
        "motion": [scene.body_motion.get(i) for i in range(scene.num_bodies)],
    }
    return BODY.write_rows(columns)
