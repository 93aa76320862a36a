"""polydem: GPU discrete element simulation of rigid convex polyhedra with NVIDIA Warp.

Contacts follow the energy-based volume model of Feng, Han and Owen: the contact energy is a
function W(V) of the overlap volume V of two polyhedra, and forces and torques are its exact
gradients, computed by clipping the two hulls against each other.
"""

import importlib

# Names are imported on first use, so that `polydem --help`, `polydem validate` and `polydem info`
# start without importing Warp (a third of a second) or trimesh.
_EXPORTS = {
    "ContactForces": "polydem.batch",
    "ContactLaw": "polydem.batch",
    "OverlapResult": "polydem.batch",
    "contact_forces": "polydem.batch",
    "overlap": "polydem.batch",
    "Body": "polydem.scene",
    "Material": "polydem.scene",
    "PlaneWall": "polydem.scene",
    "Scene": "polydem.scene",
    "SceneError": "polydem.scene",
    "pair_material": "polydem.scene",
    "ConvexShape": "polydem.shapes",
    "CompoundShape": "polydem.compound",
    "SettleCriterion": "polydem.settle",
    "SettleResult": "polydem.settle",
    "Simulation": "polydem.simulation",
    "SimulationError": "polydem.simulation",
    "SimulationWarning": "polydem.simulation",
}


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'polydem' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(_EXPORTS))


__version__ = "0.1.0"

__all__ = [
    "ConvexShape",
    "CompoundShape",
    "Scene",
    "SceneError",
    "Material",
    "Body",
    "PlaneWall",
    "pair_material",
    "Simulation",
    "SimulationError",
    "SettleCriterion",
    "SettleResult",
    "SimulationWarning",
    "ContactLaw",
    "ContactForces",
    "OverlapResult",
    "contact_forces",
    "overlap",
    "__version__",
]
