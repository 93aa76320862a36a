"""The scene file's declarations (polydem.scene.schema, issue 25): each table declared once, and the
loader, the Python signatures, the messages and the write-back agree with it.

Host-only: no Warp kernels run here.
"""

import dataclasses
import inspect

import numpy as np
import pytest

from polydem.scene import Output, Scene, SceneError
from polydem.scene.bodies import BODY
from polydem.scene.emitters import EMITTER
from polydem.scene.materials import MATERIAL, Material
from polydem.scene.output import CHECKPOINT, OUTPUT
from polydem.scene.schema import REQUIRED, Bound, Key, Table
from polydem.scene.settings import SETTING_NAMES, SETTLE, SIMULATION
from polydem.scene.walls import BOX, DRUM, MESH, PLANE

# (declaration, the Python call a file's table goes to, the keys the loader does not pass to it by name)
CALLS = [
    (SIMULATION, Scene.__init__, ("until_settled",)),
    (BODY, Scene.add_body, ("rotation",)),
    (PLANE, Scene.add_plane, ("type",)),
    (BOX, Scene.add_box_container, ("type",)),
    (DRUM, Scene.add_drum, ("type",)),
    (MESH, Scene.add_mesh_wall, ("type", "file", "vertices", "triangles", "rotation")),
    (EMITTER, Scene.emit, ()),
]


@pytest.mark.parametrize("table, call, skipped", CALLS, ids=[t.name for t, _, _ in CALLS])
def test_every_key_is_an_argument_with_the_declared_default(table, call, skipped):
    params = inspect.signature(call).parameters
    for key in table.keys:
        if key.name in skipped:
            continue
        assert key.attr in params, f"{table.name}: {key.name} is not an argument of {call.__qualname__}"
        given = params[key.attr].default
        if key.required:
            continue  # a required key may still have a default in Python (add_body's position)
        assert given is not inspect.Parameter.empty and np.array_equal(given, key.default), (table.name, key.name)


@pytest.mark.parametrize(
    "record, tables", [(Material, (MATERIAL,)), (Output, (OUTPUT, CHECKPOINT))], ids=["Material", "Output"]
)
def test_every_key_is_a_field_of_its_record_with_the_declared_default(record, tables):
    fields = {f.name: f for f in dataclasses.fields(record)}
    for table in tables:
        for key in table.keys:
            if key.name == "checkpoint":  # a sub-table: its own declaration, CHECKPOINT
                continue
            assert key.attr in fields, (table.name, key.name)
            if not key.required:
                assert fields[key.attr].default == key.default, (table.name, key.name)


def test_the_settings_are_the_simulation_keys():
    assert set(SETTING_NAMES) == {k.attr for k in SIMULATION.keys} - {"until_settled"}


def test_the_settle_defaults_are_the_criterions():
    from polydem.settle import SettleCriterion

    defaults = SettleCriterion()
    for key in SETTLE.keys:
        assert getattr(defaults, key.attr) == key.default, key.name


def test_ranges_give_their_messages():
    k = Key("x", range="> 0 and < 1", hint="a fraction")
    assert k.read(0.5, "t.x") == 0.5
    with pytest.raises(SceneError, match=r"^t.x: must be positive \(> 0\), got 0 \(a fraction\)$"):
        k.read(0, "t.x")
    with pytest.raises(SceneError, match=r"^t.x: must be < 1, got 1 \(a fraction\)$"):
        k.read(1, "t.x")
    k = Key("x", range="(0, 1]", why=" (a reason)", hint="a fraction")
    for bad in (0.0, 1.5):
        with pytest.raises(SceneError, match=r"^t.x: must be in \(0, 1\] \(a reason\), got [0-9.]+$"):
            k.read(bad, "t.x")
    n = Key("n", "integer", range="[3, 24]", hint="sides")
    with pytest.raises(SceneError, match=r"must be an integer <= 24, got 25 \(sides\)"):
        n.read(25, "t.n")
    assert n.read(3.0, "t.n") == 3
    with pytest.raises(ValueError, match="is not like"):
        Key("x", range="between 0 and 1")
    assert Bound.parse(">= 0").sign == "nonneg" and Bound.parse("> 0").sign == "positive"


def test_a_table_refuses_unknown_keys_and_reports_missing_ones():
    table = Table("t", (Key("alpha", default=REQUIRED, hint="the first"), Key("beta")))
    with pytest.raises(SceneError, match=r"unknown key 'alpah'; did you mean 'alpha'\? Valid keys: alpha, beta$"):
        table.check({"alpah": 1}, "t")
    with pytest.raises(SceneError, match=r"^t.alpha: missing required key 'alpha' \(the first\)$"):
        table.check({"beta": 1}, "t")
    with pytest.raises(ValueError, match="declared twice"):
        Table("t", (Key("a"), Key("a")))


def test_true_and_false_stand_for_what_the_key_declares():
    usd = OUTPUT["usd"]
    assert usd.from_file(True) == "trajectory.usd" and usd.from_file(False) is None
    assert usd.to_file(None) is False
    assert OUTPUT["pictures"].to_file(()) is REQUIRED  # left out: a file without pictures renders the last frame
    assert Output.from_dict({"usd": True, "summary": False, "pictures": True}) == Output(
        usd="trajectory.usd", summary=None, pictures="last"
    )


def test_every_table_round_trips_through_to_dict(tmp_path):
    data = {
        "simulation": {
            "name": "all",
            "description": "every table",
            "dt": 1e-5,
            "gravity": [0, 0, -9.81],
            "duration": 0.01,
            "device": "cpu",
            "precision": "float64",
            "settle": {"kinetic_fraction": False, "max_speed": 0.01, "hold": 0.1},
        },
        "materials": {
            "steel": {"density": 7800.0, "law": "power", "m": 2.0, "k": 1e9, "restitution": 0.5, "friction": 0.3},
            "glass": {"density": 2500.0, "law": "power", "m": 2.0, "k": 5e8, "restitution": 0.9, "friction": 0.2},
        },
        "shapes": {"cube": {"type": "box", "size": 0.1}, "tet": {"type": "tetrahedron", "edge": 0.1}},
        "bodies": [
            {"shape": "cube", "material": "steel", "position": [0, 0, 0.2], "velocity": [0, 0, 1]},
            {"shape": "tet", "material": "glass", "position": [1, 0, 0.2], "kind": "kinematic", "pivot": [1, 0, 0]},
        ],
        "walls": [
            {"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 2], "material": "steel"},
            {
                "type": "mesh",
                "vertices": [[5, 0, 0], [6, 0, 0], [5, 1, 0]],
                "triangles": [[0, 1, 2]],
                "material": "steel",
                "thickness": 0.1,
                "angular_velocity": [0, 0, 1],
            },
        ],
        "emitters": [
            {
                "shape": "cube",
                "material": "steel",
                "count": 4,
                "region": {"min": [10, 0, 0], "max": [11, 1, 1]},
                "scale_range": [0.5, 1.0],
            }
        ],
        "output": {"usd": True, "fps": 30, "pictures": [2, 0], "vtk": True, "checkpoint": {"seconds": 0.005}},
    }
    scene = Scene.from_dict(data, validate=False)
    written = scene.to_dict()
    again = Scene.from_dict(written, validate=False)
    assert again.to_dict() == written
    sim = written["simulation"]
    assert sim["settle"] == {"kinetic_fraction": False, "speed_fraction": 3e-4, "max_speed": 0.01, "hold": 0.1}
    assert written["materials"]["steel"] == {**data["materials"]["steel"]}
    assert written["output"] == {
        "usd": "trajectory.usd",
        "fps": 30.0,
        "summary": "summary.json",
        "pictures": [0, 2],
        "vtk": True,
        "checkpoint": {"seconds": 0.005, "path": "checkpoints"},
    }
    bodies = written["bodies"]
    assert "pivot" not in bodies[0] and "velocity" not in bodies[1] and bodies[1]["pivot"] == [1.0, 0.0, 0.0]
    assert written["walls"][0]["normal"] == [0.0, 0.0, 1.0]
    assert "velocity" not in written["walls"][1] and written["walls"][1]["angular_velocity"] == [0.0, 0.0, 1.0]


def test_rows_are_written_by_each_keys_rule():
    plain = Table("t", (Key("a"), Key("b", "vector"), Key("c", write="never")))
    assert plain.write_rows({"a": [1.0, None], "b": [[0.0, 1.0, 2.0], None]}) == [{"a": 1.0, "b": [0.0, 1.0, 2.0]}, {}]
    ruled = Table("t", (Key("a"), Key("b", default=0.0, write="changed"), Key("u", "string", on="x.usd", off=None)))
    rows = ruled.write_rows({"a": [1.0, None], "b": [0.0, 2.0], "u": ["y.usd", None]})
    assert rows == [{"a": 1.0, "u": "y.usd"}, {"b": 2.0, "u": False}]
    assert rows == [ruled.write({"a": 1.0, "b": 0.0, "u": "y.usd"}), ruled.write({"a": None, "b": 2.0, "u": None})]
