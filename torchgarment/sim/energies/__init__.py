"""Simulation energy terms (each an :class:`~torchgarment.sim.energies.base.EnergyTerm`), SI units.

* :class:`PlanarSprings` - in-panel springs with rest lengths from the pattern (Wang et al. 2018, Eq. 5).
* :class:`SewingSprings` - zero-rest-length seam springs (Eq. 5, sewing case).
* :class:`QuadraticBending` - Bergou et al. 2006 cotangent hinge bending, also across seams.
* :class:`Gravity` - lumped vertex masses from the rest areas.
* :class:`Pins` - sticking springs to targets (pins, belts).
* :class:`BodyBarrier` - ``-mu sum log phi`` on a body SDF (Eq. 4), with ``max_step`` and
  ``project_feasible``.
"""

from torchgarment.sim.energies.barrier import DEFAULT_BARRIER_DHAT, DEFAULT_BARRIER_MU, BodyBarrier
from torchgarment.sim.energies.base import EnergyTerm, HessianBlocks
from torchgarment.sim.energies.bend import DEFAULT_BEND_STIFFNESS, QuadraticBending
from torchgarment.sim.energies.gravity import DEFAULT_DENSITY, STANDARD_GRAVITY, Gravity, vertex_masses
from torchgarment.sim.energies.pins import DEFAULT_PIN_STIFFNESS, Pins
from torchgarment.sim.energies.sew import DEFAULT_SEW_STIFFNESS, SewingSprings
from torchgarment.sim.energies.stretch import DEFAULT_STRETCH_STIFFNESS, PairOperator, PlanarSprings

__all__ = [
    "DEFAULT_BARRIER_DHAT",
    "DEFAULT_BARRIER_MU",
    "DEFAULT_BEND_STIFFNESS",
    "DEFAULT_DENSITY",
    "DEFAULT_PIN_STIFFNESS",
    "DEFAULT_SEW_STIFFNESS",
    "DEFAULT_STRETCH_STIFFNESS",
    "STANDARD_GRAVITY",
    "BodyBarrier",
    "EnergyTerm",
    "Gravity",
    "HessianBlocks",
    "PairOperator",
    "Pins",
    "PlanarSprings",
    "QuadraticBending",
    "SewingSprings",
    "vertex_masses",
]
