"""Sewing-pattern adjustment (Wang et al. 2018): change a pattern so its garment fits a target body as the
original fits the base body.

Re-exported here:

* the pipeline (:mod:`torchgarment.adjust.pipeline`): :func:`adjust` (drape, transfer, initialize, optimize in
  one call), its steps :func:`prepare` and :func:`optimize`, their :class:`AdjustSettings`,
  :class:`AdjustSetup` and :class:`AdjustResult`, and :func:`pattern_from_mesh` (the pattern through adjusted
  rest positions);
* the objective: :class:`AdjustObjective` with its :class:`CostWeights`, the costs (:class:`DistanceCost`,
  :class:`SmoothnessCost`, :class:`StretchingCost`, :class:`PositionalCost`) and regularizers
  (:class:`FixingRegularizer`, :class:`BoundaryCurvatureRegularizer`, :class:`SeamLengthRegularizer`), all
  ``nn.Module``\\ s;
* :class:`BoundaryParametrization` (boundary vertices -> rest positions) and :func:`transfer_deformation`
  (the base drape carried to the target body);
* the optimizers (``torch.optim.Optimizer``\\ s): :func:`make_optimizer`, :class:`OptimizerKind`,
  :class:`PreconditionedGD`, :class:`LBFGS`, :class:`GaussNewton`, :class:`FixedPoint`.

The command line is :mod:`torchgarment.adjust.cli` and its demo :mod:`torchgarment.adjust.demo` (both in the
command layer, not re-exported); the acceptance-study measurements are in
:mod:`torchgarment.adjust.acceptance`.
"""

from torchgarment.adjust.costs import DistanceCost, PositionalCost, SmoothnessCost, StretchingCost
from torchgarment.adjust.objective import AdjustObjective, CostWeights
from torchgarment.adjust.optimizers import (
    LBFGS,
    FixedPoint,
    GaussNewton,
    OptimizerKind,
    PreconditionedGD,
    make_optimizer,
)
from torchgarment.adjust.parametrization import BoundaryParametrization
from torchgarment.adjust.pipeline import (
    AdjustResult,
    AdjustSettings,
    AdjustSetup,
    adjust,
    optimize,
    pattern_from_mesh,
    prepare,
)
from torchgarment.adjust.regularizers import (
    BoundaryCurvatureRegularizer,
    FixingRegularizer,
    SeamLengthRegularizer,
)
from torchgarment.adjust.transfer import transfer_deformation

__all__ = [
    "LBFGS",
    "AdjustObjective",
    "AdjustResult",
    "AdjustSettings",
    "AdjustSetup",
    "BoundaryCurvatureRegularizer",
    "BoundaryParametrization",
    "CostWeights",
    "DistanceCost",
    "FixedPoint",
    "FixingRegularizer",
    "GaussNewton",
    "OptimizerKind",
    "PositionalCost",
    "PreconditionedGD",
    "SeamLengthRegularizer",
    "SmoothnessCost",
    "StretchingCost",
    "adjust",
    "make_optimizer",
    "optimize",
    "pattern_from_mesh",
    "prepare",
    "transfer_deformation",
]
