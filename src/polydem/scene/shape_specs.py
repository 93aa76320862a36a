"""Shapes from the ``[shapes.NAME]`` tables of a scene file, and the specs of scaled shapes."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from polydem.compound import MAX_PARTS
from polydem.scene.errors import SceneError
from polydem.scene.schema import LENGTH, LENGTH_WHY, REQUIRED, Key, Table, read_rotation
from polydem.scene.values import (
    F32_HIGH,
    F32_LOW,
    RADIUS_HIGH,
    RADIUS_LOW,
    is_number,
    read_table,
    read_vector,
    typename,
)
from polydem.shapes import MAX_FACE_VERTICES, MAX_FACES, ConvexShape

SHAPE_TYPES = (
    "box",
    "tetrahedron",
    "octahedron",
    "dodecahedron",
    "icosahedron",
    "prism",
    "rock",
    "sphere",
    "mesh",
    "points",
    "compound",
)
"""Shape ``type`` values of a scene file's ``[shapes.NAME]`` tables."""

_PLATONIC = ("tetrahedron", "octahedron", "dodecahedron", "icosahedron")

# Keys that several types share. A key in metres ("m") is a length that scaled_spec scales.
_TYPE = Key("type", "choice", choices=SHAPE_TYPES, what="shape type", default=REQUIRED)
_SIZE_HINT = "edge length(s) in m: size = 0.1 for a cube or size = [sx, sy, sz]; for rock the largest diameter in m"
_RADIUS = Key("radius", unit="m", range=LENGTH, why=LENGTH_WHY, default=REQUIRED, hint="circumscribed radius in m")
_SEED = Key("seed", "integer", range=">= 0", hint="random seed, an integer >= 0", about="")
_SCALE = Key("scale", range="> 0", hint="factor applied to the file's coordinates, e.g. 0.001 for mm")
_FILE = Key(
    "file",
    "string",
    what="a file path string",
    default=REQUIRED,
    hint="mesh file (OBJ, STL, PLY) relative to the scene file, e.g. file = 'meshes/rock.obj'",
)
_TOL = Key("tol", range="[0, 1e-3]", why=" (a relative tolerance; use ~1e-6 for STL files)")
_POINTS_HINT = "array of [x, y, z] points in m"


def _table(kind, *keys) -> Table:
    return Table(f"[shapes.NAME] type = {kind!r}", (_TYPE, *keys))


SHAPES = {
    "box": _table("box", Key("size", unit="m", range=LENGTH, why=LENGTH_WHY, default=REQUIRED, hint=_SIZE_HINT)),
    **{
        kind: _table(
            kind,
            Key(
                "edge",
                unit="m",
                range=LENGTH,
                why=LENGTH_WHY,
                default=REQUIRED,
                hint="edge length in m, e.g. edge = 0.1",
            ),
        )
        for kind in _PLATONIC
    },
    "prism": _table(
        "prism",
        Key(
            "n",
            "integer",
            range=f"[3, {MAX_FACE_VERTICES}]",
            default=REQUIRED,
            hint=f"number of sides of the base polygon, an integer from 3 to {MAX_FACE_VERTICES}",
            about=f"the contact kernels take faces of at most {MAX_FACE_VERTICES} vertices; use a smaller n",
        ),
        _RADIUS,
        Key("height", unit="m", range=LENGTH, why=LENGTH_WHY, default=REQUIRED, hint="prism height in m"),
    ),
    "rock": _table(
        "rock",
        Key(
            "n_points",
            "integer",
            range=f"[4, {MAX_FACES // 2 + 2}]",
            default=REQUIRED,
            hint=f"number of hull vertices, an integer from 4 to {MAX_FACES // 2 + 2}",
            about=f"its hull has 2 n_points - 4 faces, and the contact kernels take at most {MAX_FACES}",
        ),
        Key("size", unit="m", range=LENGTH, why=LENGTH_WHY, default=REQUIRED, hint=_SIZE_HINT),
        replace(_SEED, default=0),
        Key("elongation", "vector", label="[ex, ey, ez]"),
        Key("roughness", range="[0, 1)"),
    ),
    "sphere": _table(
        "sphere",
        Key(
            "subdivisions",
            "integer",
            range="[0, 5]",
            default=REQUIRED,
            hint="icosphere subdivision level, 0 to 5",
            about="",
        ),
        _RADIUS,
    ),
    "mesh": _table("mesh", _FILE, _SCALE, _TOL),
    "points": _table("points", Key("points", "any", unit="m", default=REQUIRED, hint=_POINTS_HINT), _TOL),
    "compound": _table(
        "compound",
        Key(
            "parts",
            "any",
            hint="array of convex shape tables, each with a 'type', its keys, and position = [x, y, z] and "
            "rotation = {axis = [ax, ay, az], degrees = angle} (or orientation = [x, y, z, w]) placing it in the grain",
        ),
        replace(_FILE, default=None),
        Key(
            "decompose",
            "choice",
            choices=("coacd", "components"),
            what="decomposition",
            default="coacd",
            hint="how to cut the mesh file into convex parts: 'coacd' (CoACD) or 'components' (the hull of each "
            "connected piece)",
        ),
        Key(
            "threshold",
            range="(0, 1]",
            hint="CoACD's concavity threshold, in (0, 1], e.g. 0.05 (smaller: more, finer parts)",
            about="",
        ),
        Key(
            "max_parts",
            "integer",
            range=f"[1, {MAX_PARTS}]",
            hint="the most convex parts CoACD may make, e.g. 16",
            about="",
        ),
        _SEED,
        _SCALE,
    ),
}
"""Each shape type's ``[shapes.NAME]`` table: the parameters of its :class:`ConvexShape` constructor."""

PLACEMENT = Table(
    "a compound's part",
    (
        Key("position", "vector", unit="m", label="[x, y, z]"),
        Key("orientation", "vector", size=4, label="[x, y, z, w]"),
        Key("rotation", "rotation", attr="orientation"),
    ),
)
"""What a part of a compound shape takes beyond its type's keys: its place in the grain."""


def build_shape(
    name: str, spec: dict, key: str, file, base_dir: Path, *, part: bool = False
) -> tuple[ConvexShape, dict]:
    """Build a shape from a ``[shapes.NAME]`` table; returns it and the normalised spec. ``part``: the
    table is a part of a compound shape (convex, with its placement in the grain)."""
    spec = read_table(spec, key, file, what=f"a table [shapes.{name}] with a 'type' key")
    if "type" not in spec:
        raise SceneError(f"missing required key 'type' (one of {', '.join(SHAPE_TYPES)})", f"{key}.type", file)
    kind = _TYPE.read(spec["type"], f"{key}.type", file)
    if part and kind == "compound":
        raise SceneError(
            "a part of a compound shape must be convex: give a convex type, not 'compound'", f"{key}.type", file
        )
    SHAPES[kind].check(spec, key, file, context=f" for type = {kind!r}", extra=PLACEMENT.names if part else ())
    r = _Spec(spec, key, file, name, base_dir, {"type": kind})
    try:
        shape = _BUILDERS[kind](r)
    except SceneError:
        raise
    except (ValueError, OSError, ArithmeticError, RuntimeError) as exc:
        # Geometry rejected by ConvexShape (degenerate, unreadable file) or whose hull qhull could not make;
        # qhull's report goes on over many lines of its options, its first line says what failed.
        why = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
        raise SceneError(f"cannot build the {kind} shape: {why}", key, file) from exc
    if part:
        shape = _place_part(r, shape)
    return shape, r.out


def _place_part(r: _Spec, shape: ConvexShape) -> ConvexShape:
    from polydem.compound import place

    spec, key, file = r.spec, r.key, r.file
    if "orientation" in spec and "rotation" in spec:
        raise SceneError(
            "give either orientation (quaternion) or rotation (axis and angle), not both", f"{key}.rotation", file
        )
    q = np.array([0.0, 0.0, 0.0, 1.0])
    if "rotation" in spec:
        q = read_rotation(spec["rotation"], f"{key}.rotation", file)
        r.out["orientation"] = q.tolist()
    elif "orientation" in spec:
        q = PLACEMENT["orientation"].read(spec["orientation"], f"{key}.orientation", file)
        if abs(np.linalg.norm(q) - 1.0) > 1e-6:
            raise SceneError(
                f"orientation {q.tolist()} is not a unit quaternion (norm {np.linalg.norm(q):.9g}); give "
                "rotation = {axis = [ax, ay, az], degrees = angle} instead",
                f"{key}.orientation",
                file,
            )
        r.out["orientation"] = q.tolist()
    p = np.zeros(3)
    if "position" in spec:
        p = PLACEMENT["position"].read(spec["position"], f"{key}.position", file)
        r.out["position"] = p.tolist()
    return place(shape, p, q)


def _compound(r: _Spec):
    from polydem.compound import CompoundShape, CompoundShapeError

    spec, key, file = r.spec, r.key, r.file
    if ("parts" in spec) == ("file" in spec):
        raise SceneError(
            "a compound shape needs either parts = [...] (convex shape tables) or file = '...' with decompose = "
            "'coacd' or 'components', not both or neither",
            key,
            file,
        )
    try:
        if "parts" in spec:
            for k in ("decompose", "threshold", "max_parts", "seed", "scale"):
                if k in spec:
                    raise SceneError(f"{k!r} applies to a mesh file; parts are given as they are", f"{key}.{k}", file)
            parts_in = spec["parts"]
            if not isinstance(parts_in, list) or not parts_in:
                raise SceneError(
                    f"expected a non-empty array of part tables, got {typename(parts_in)}", f"{key}.parts", file
                )
            if len(parts_in) > MAX_PARTS:
                raise SceneError(f"at most {MAX_PARTS} parts, got {len(parts_in)}", f"{key}.parts", file)
            parts, specs = [], []
            for k, p in enumerate(parts_in):
                part, out = build_shape(f"{r.name}[{k}]", p, f"{key}.parts[{k}]", file, r.base_dir, part=True)
                parts.append(part)
                specs.append(out)
            r.out["parts"] = specs
            return CompoundShape(parts, name=r.name)
        path = _mesh_path(r)
        r.out["file"] = str(path.resolve())
        method = r.out["decompose"] = r.get("decompose")
        opts = {}
        for k in ("threshold", "max_parts", "seed"):
            if k in spec:
                opts[k] = r.out[k] = r.get(k)
        from polydem.shapes import load_mesh

        mesh = load_mesh(path)
        if "scale" in spec:
            r.out["scale"] = r.get("scale")
            _check_scale(r, 0.5 * float(np.linalg.norm(np.ptp(mesh.vertices, axis=0))), r.out["scale"])
            mesh.apply_scale(r.out["scale"])
        return CompoundShape.from_mesh(mesh, name=r.name, decompose=method, **opts)
    except CompoundShapeError as exc:
        raise SceneError(f"cannot build the compound shape: {exc}", key, file) from None


def _mesh_path(r: _Spec) -> Path:
    spec, key, file, base_dir = r.spec, r.key, r.file, r.base_dir
    rel = _FILE.read(spec["file"], f"{key}.file", file)
    path = Path(rel).expanduser()
    if not path.is_absolute():
        path = base_dir / path
    if not path.is_file():
        what = "is not a file" if path.exists() else "not found"
        raise SceneError(
            f"mesh file {rel!r} {what} (looked for '{path}'; relative paths are taken from the folder of the "
            f"scene file, '{base_dir}')",
            f"{key}.file",
            file,
        )
    return path


@dataclass
class _Spec:
    """A ``[shapes.NAME]`` table being read: its readers name the key; ``out`` is the normalised spec."""

    spec: dict
    key: str
    file: object
    name: str
    base_dir: Path
    out: dict

    def get(self, k):
        """The checked value of key ``k`` as its type's table declares it (its default when not given)."""
        key = SHAPES[self.out["type"]][k]
        return key.read(self.spec[k], f"{self.key}.{k}", self.file) if k in self.spec else key.default

    def tol(self):
        return {"tol": self.get("tol")} if "tol" in self.spec else {}


def _box(r: _Spec) -> ConvexShape:
    size = r.spec["size"]
    if is_number(size):
        s = [r.get("size")] * 3
    else:
        s = read_vector(size, 3, f"{r.key}.size", r.file, label="[sx, sy, sz]").tolist()
        if min(s) <= 0.0:
            raise SceneError(f"box edge lengths must be positive, got {s}", f"{r.key}.size", r.file)
        for x in s:
            SHAPES["box"]["size"].within(x, f"{r.key}.size", r.file, each=np.array(s))
    r.out["size"] = s
    return ConvexShape.box(*s, name=r.name)


def _platonic(r: _Spec) -> ConvexShape:
    r.out["edge"] = r.get("edge")
    return getattr(ConvexShape, r.out["type"])(r.out["edge"], name=r.name)


def _prism(r: _Spec) -> ConvexShape:
    r.out.update(n=r.get("n"), radius=r.get("radius"), height=r.get("height"))
    return ConvexShape.prism(r.out["n"], r.out["radius"], r.out["height"], name=r.name)


def _rock(r: _Spec) -> ConvexShape:
    spec, key, file, out = r.spec, r.key, r.file, r.out
    out.update(n_points=r.get("n_points"), size=r.get("size"), seed=r.get("seed"))
    extra = {}
    if "elongation" in spec:
        el = r.get("elongation")
        if el.min() <= 0.0:
            raise SceneError(f"elongation factors must be positive, got {el.tolist()}", f"{key}.elongation", file)
        extra["elongation"] = el.tolist()
    if "roughness" in spec:
        extra["roughness"] = r.get("roughness")
    out.update(extra)
    return ConvexShape.rock(out["n_points"], out["size"], out["seed"], name=r.name, **extra)


def _sphere(r: _Spec) -> ConvexShape:
    r.out.update(subdivisions=r.get("subdivisions"), radius=r.get("radius"))
    return ConvexShape.sphere(r.out["subdivisions"], r.out["radius"], name=r.name)


def _mesh(r: _Spec) -> ConvexShape:
    path = _mesh_path(r)
    r.out["file"] = str(path.resolve())
    t = r.tol()
    r.out.update(t)
    shape = ConvexShape.from_file(path, name=r.name, **t)
    if "scale" in r.spec:
        r.out["scale"] = r.get("scale")
        _check_scale(r, shape.radius, r.out["scale"])
        shape = shape.scaled(r.out["scale"])
    return shape


def _check_scale(r: _Spec, radius: float, scale: float):
    """Refuse a mesh file's ``scale`` that takes the shape's bounding radius (``radius`` [m] unscaled) beyond
    the lengths of a run, where its volume and inertia are not even float64 numbers; the float32 check of
    the scene's validation names the narrower radii a run can resolve."""
    if F32_LOW <= radius * scale <= F32_HIGH:
        return
    raise SceneError(
        f"scale {scale:g} makes the shape's bounding radius {radius * scale:.3g} m, beyond the lengths a run holds "
        f"({F32_LOW:.3g} to {F32_HIGH:.3g} m, float32's range less a margin); a shape needs a bounding radius from "
        f"{RADIUS_LOW:.2g} to {RADIUS_HIGH:.2g} m: give a scale from {RADIUS_LOW / radius:.3g} to "
        f"{RADIUS_HIGH / radius:.3g} (the mesh file's unit in m: 0.001 for mm)",
        f"{r.key}.scale",
        r.file,
    )


def _points(r: _Spec) -> ConvexShape:
    pts = r.spec["points"]
    if not isinstance(pts, list | tuple | np.ndarray) or len(pts) < 4:
        raise SceneError(
            f"expected an array of at least 4 [x, y, z] points, got {typename(pts)}", f"{r.key}.points", r.file
        )
    rows = [read_vector(p, 3, f"{r.key}.points[{i}]", r.file) for i, p in enumerate(pts)]
    r.out["points"] = [row.tolist() for row in rows]
    t = r.tol()
    r.out.update(t)
    return ConvexShape.from_points(np.array(rows), name=r.name, **t)


_BUILDERS = {
    "box": _box,
    **dict.fromkeys(_PLATONIC, _platonic),
    "prism": _prism,
    "rock": _rock,
    "sphere": _sphere,
    "mesh": _mesh,
    "points": _points,
    "compound": _compound,
}


def scaled_spec(spec: dict | None, factor: float) -> dict | None:
    """The spec of a shape scaled by ``factor`` about its input origin, or None (then written as points)."""
    if spec is None:
        return None
    out = dict(spec)
    kind = spec["type"]
    if kind == "points":
        out["points"] = [[factor * x for x in p] for p in spec["points"]]
        return out
    if kind == "compound" and "parts" in spec:
        out["parts"] = []
        for p in spec["parts"]:
            q = scaled_spec(p, factor)
            if "position" in p:
                q["position"] = [factor * x for x in p["position"]]
            out["parts"].append(q)
        return out
    if kind in ("mesh", "compound"):  # a mesh file: its factor
        out["scale"] = factor * spec.get("scale", 1.0)
        return out
    for k in SHAPES[kind].keys:
        if k.unit == "m" and k.name in spec:
            value = spec[k.name]
            out[k.name] = [factor * x for x in value] if isinstance(value, list) else factor * value
    return out
