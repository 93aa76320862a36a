"""The three simulation fronts provide what ``polydem run`` and its recorders ask of them (src/polydem/fronts.py).

Checked on the classes, without building one: a method by its parameters (those of the protocol, by name
and kind, in order; any more must have defaults), a data member as a property, a class attribute, or an
annotation in the class body that the class also assigns (``self.name = ...``).
"""

import ast
import inspect
import textwrap
from typing import Generic, Protocol

import pytest

from polydem.distributed import DistributedSimulation
from polydem.distributed.root import RootSimulation
from polydem.fronts import Front, RunFront
from polydem.simulation import Simulation


def protocol_members(protocol: type) -> dict[str, object]:
    """Name -> the protocol's declaration (a function, a property, or None for an annotated attribute),
    over the protocol and the protocols it extends (the nearest declaration wins)."""
    members: dict[str, object] = {}
    for base in reversed(protocol.__mro__):
        if base in (object, Generic, Protocol):
            continue
        for name in vars(base).get("__annotations__", {}):
            members[name] = None
        for name, value in vars(base).items():
            if not name.startswith("_") and (inspect.isfunction(value) or isinstance(value, property)):
                members[name] = value
    return members


def assigned_on_self(cls: type) -> set[str]:
    """The attributes the class's own methods assign on ``self`` (of it and its bases)."""
    names = set()
    for klass in cls.__mro__[:-1]:
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
                if isinstance(node.value, ast.Name) and node.value.id == "self":
                    names.add(node.attr)
    return names


def _parameters_fit(declared: object, given: object) -> bool:
    """Whether the method ``given`` takes the parameters of ``declared`` and needs no more."""
    want = list(inspect.signature(declared).parameters.values())[1:]  # after self
    have = list(inspect.signature(given).parameters.values())[1:]
    if len(have) < len(want):
        return False
    for w, h in zip(want, have, strict=False):
        if w.name != h.name or w.kind != h.kind:
            return False
    optional = (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)
    return all(h.default is not inspect.Parameter.empty or h.kind in optional for h in have[len(want) :])


def missing_members(cls: type, protocol: type) -> list[str]:
    """The members of ``protocol`` that ``cls`` lacks, or has with other parameters."""
    annotations = {}
    for klass in reversed(cls.__mro__):
        annotations.update(vars(klass).get("__annotations__", {}))
    assigned = assigned_on_self(cls)
    missing = []
    for name, declared in protocol_members(protocol).items():
        have = inspect.getattr_static(cls, name, None)
        if inspect.isfunction(declared):
            if not inspect.isfunction(have) or not _parameters_fit(declared, have):
                missing.append(name)
        elif have is None and not (name in annotations and name in assigned):
            missing.append(name)
    return missing


FRONTS = {Front: (Simulation, DistributedSimulation, RootSimulation), RunFront: (Simulation, RootSimulation)}


@pytest.mark.parametrize(
    ("protocol", "cls"), [(p, c) for p, classes in FRONTS.items() for c in classes], ids=lambda x: x.__name__
)
def test_each_front_provides_every_member(protocol, cls):
    assert missing_members(cls, protocol) == []


def test_the_run_front_is_what_the_command_and_recorders_use():
    members = set(protocol_members(RunFront))
    assert {"step", "state", "contacts", "energy", "settle_measures", "steps_done", "time", "dt"} <= members
    assert {"model", "current_state", "current_contacts", "restore_from_arrays", "restore_last_good"} <= members
    assert {"contact_average_steps", "start_contact_average", "contact_average"} <= members
    assert set(protocol_members(Front)) < members


def test_a_front_missing_a_member_or_a_parameter_fails():
    class Partial:
        scene: object
        device: object
        dt: float  # declared, never assigned
        num_bodies = 3
        steps_done: int
        time: float

        def __init__(self):
            self.scene = self.device = None
            self.steps_done, self.time = 0, 0.0

        def step(self, count=1):  # the protocol's parameter is n
            pass

        def state(self):
            return {}

        def contacts(self):
            return {}

        def energy(self, bodies):  # an extra parameter without a default
            return {}

    assert missing_members(Partial, Front) == ["dt", "step", "energy", "settle_measures"]
    assert missing_members(Simulation, Front) == []
