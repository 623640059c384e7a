"""Quasistatic garment simulation: energy terms, scenes that compose them, solvers, the differentiable solve
and draping.

Re-exported here:

* scenes (:mod:`torchgarment.sim.scene`): :class:`Scene` (declares the :class:`Effect`\\ s and the
  :class:`Material`) and the :class:`SimModel` it builds;
* draping (:mod:`torchgarment.sim.drape`): :func:`drape` with :class:`DrapeSettings`, :class:`DrapeResult`
  and :class:`DrapeStage`, the seam and stretch measures :func:`seam_gaps`, :func:`max_seam_gap` and
  :func:`vertex_stretch_ratio`, and :class:`SupportLoop` (a mesh's support, :mod:`torchgarment.sim.support`);
* solvers (:mod:`torchgarment.sim.solvers`): :func:`solve` with :class:`SolveSettings`, :class:`SolverKind`,
  :class:`Preconditioner` and the returned :class:`SolveInfo`;
* the differentiable solve (:mod:`torchgarment.sim.diff`): :class:`DifferentiableSolver` (an ``nn.Module``),
  the autograd Function :class:`QuasistaticSolve`, :class:`BackwardMode`, :class:`AdjointLinearSolver`,
  :class:`AdjointHessian`, :class:`NonConvergenceError` and :class:`NonConvergenceWarning`;
* energy terms (:mod:`torchgarment.sim.energies`): :class:`EnergyTerm`, :class:`HessianBlocks`,
  :class:`PlanarSprings`, :class:`SewingSprings`, :class:`QuadraticBending`, :class:`Gravity`, :class:`Pins`,
  :class:`BodyBarrier`;
* IPC contact (:mod:`torchgarment.sim.contact`, needs ipctk): :class:`SelfContact` and
  :class:`BodyMeshContact`, imported on first use of these names.

``torchgarment.sim.drape`` is the function :func:`drape`; import the module's other names from it
(``from torchgarment.sim.drape import DrapeSettings``) or from here. The command line is
:mod:`torchgarment.sim.drape_cli`.
"""

from typing import TYPE_CHECKING

from torchgarment.sim.diff import (
    AdjointHessian,
    AdjointLinearSolver,
    BackwardMode,
    DifferentiableSolver,
    NonConvergenceError,
    NonConvergenceWarning,
    QuasistaticSolve,
)
from torchgarment.sim.drape import (
    DrapeResult,
    DrapeSettings,
    DrapeStage,
    drape,
    max_seam_gap,
    seam_gaps,
    vertex_stretch_ratio,
)
from torchgarment.sim.energies import (
    BodyBarrier,
    EnergyTerm,
    Gravity,
    HessianBlocks,
    Pins,
    PlanarSprings,
    QuadraticBending,
    SewingSprings,
)
from torchgarment.sim.scene import Effect, Material, Scene, SimModel
from torchgarment.sim.solvers import Preconditioner, SolveInfo, SolverKind, SolveSettings, solve
from torchgarment.sim.support import SupportLoop

if TYPE_CHECKING:
    from torchgarment.sim.contact import BodyMeshContact, SelfContact

_CONTACT = ("BodyMeshContact", "SelfContact")


def __getattr__(name: str) -> type:
    """Import the IPC contact classes (and ipctk) on first use."""
    if name in _CONTACT:
        from torchgarment.sim import contact

        return getattr(contact, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "AdjointHessian",
    "AdjointLinearSolver",
    "BackwardMode",
    "BodyBarrier",
    "BodyMeshContact",
    "DifferentiableSolver",
    "DrapeResult",
    "DrapeSettings",
    "DrapeStage",
    "Effect",
    "EnergyTerm",
    "Gravity",
    "HessianBlocks",
    "Material",
    "NonConvergenceError",
    "NonConvergenceWarning",
    "Pins",
    "PlanarSprings",
    "Preconditioner",
    "QuadraticBending",
    "QuasistaticSolve",
    "Scene",
    "SelfContact",
    "SewingSprings",
    "SimModel",
    "SolveInfo",
    "SolveSettings",
    "SolverKind",
    "SupportLoop",
    "drape",
    "max_seam_gap",
    "seam_gaps",
    "solve",
    "vertex_stretch_ratio",
]
