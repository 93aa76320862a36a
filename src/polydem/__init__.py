"""polydem: GPU discrete element simulation of rigid convex polyhedra with NVIDIA Warp.

Contacts follow the energy-based volume model of Feng, Han and Owen: the contact energy is a
function W(V) of the overlap volume V of two polyhedra, and forces and torques are its exact
gradients, computed by clipping the two hulls against each other.
"""

from polydem.contact import ContactForces, ContactLaw, OverlapResult, contact_forces, overlap
from polydem.scene import Body, Material, PlaneWall, Scene, SceneError, pair_material
from polydem.shapes import ConvexShape
from polydem.simulation import Simulation, SimulationError

__version__ = "0.1.0"

__all__ = [
    "ConvexShape",
    "Scene",
    "SceneError",
    "Material",
    "Body",
    "PlaneWall",
    "pair_material",
    "Simulation",
    "SimulationError",
    "ContactLaw",
    "ContactForces",
    "OverlapResult",
    "contact_forces",
    "overlap",
    "__version__",
]
