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
  :class:`PreconditionedGD`, :class:`LBFGS`, :class:`GaussNewton`, :class:`FixedPoint`;
* the differentiable problem on the simulator's autograd Function: :class:`AdjustProblem`;
* grading a size run (:mod:`torchgarment.adjust.grade`): :func:`grade` and its :class:`GradeResult`,
  :func:`base_drape_settings` (the base drape every size shares);
* fit preservation (:mod:`torchgarment.adjust.fit`): :func:`measure_fit`, :class:`LineFit`, :func:`fit_rows`,
  :func:`construction_lines`, :class:`FitScale` (how the kept fit scales with the body's height).

The command line is :mod:`torchgarment.adjust.cli` and its demo :mod:`torchgarment.adjust.demo` (both in the
command layer, not re-exported); the acceptance-study measurements are in
:mod:`torchgarment.adjust.acceptance`.
"""

from torchgarment.adjust.costs import DistanceCost, PositionalCost, SmoothnessCost, StretchingCost
from torchgarment.adjust.fit import FitScale, LineFit, construction_lines, fit_rows, measure_fit
from torchgarment.adjust.grade import GradeResult, grade
from torchgarment.adjust.inexact import AdjustProblem
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
    base_drape_settings,
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
    "AdjustProblem",
    "FitScale",
    "GradeResult",
    "LineFit",
    "base_drape_settings",
    "construction_lines",
    "fit_rows",
    "grade",
    "measure_fit",
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
