"""Intersection-free garment retargeting (Huang et al. 2025): move a 3D garment from one body or avatar to
another without the garment crossing the target.

Re-exported here:

* the pipeline (:mod:`torchgarment.retarget.pipeline`): :func:`retarget` and :func:`retarget_layers` (several
  garment layers, inner first), :func:`layer_problem`, :class:`RetargetSettings` (with :class:`FitTarget`, the
  gap the fit pulls the garment to), :class:`RetargetResult`, :class:`RetargetError` and :func:`check_result`
  (the final intersection and distance check);
* problems (:mod:`torchgarment.retarget.inputs`): :class:`RetargetProblem`, built by
  :func:`problem_from_arrays` (tensors), :func:`problem_from_bodies` (two rigged bodies) or
  :func:`load_problem` (files), with :class:`Similarity` (the normalization to the working frame);
* Step 1 (:mod:`torchgarment.retarget.shrink`): :func:`shrink_avatar` and :class:`ShrunkAvatar`;
* test avatars (:mod:`torchgarment.retarget.avatars`): :func:`list_avatars`, :func:`make_avatar`,
  :class:`TestAvatar`, :func:`edit_by_bones`, :func:`toy_case` and :class:`ToyCase`.

The command line is :mod:`torchgarment.retarget.cli`.
"""

from torchgarment.retarget.avatars import (
    TestAvatar,
    ToyCase,
    edit_by_bones,
    list_avatars,
    make_avatar,
    toy_case,
)
from torchgarment.retarget.inputs import (
    RetargetProblem,
    Similarity,
    load_problem,
    problem_from_arrays,
    problem_from_bodies,
)
from torchgarment.retarget.pipeline import (
    FitTarget,
    RetargetError,
    RetargetResult,
    RetargetSettings,
    check_result,
    layer_problem,
    retarget,
    retarget_layers,
)
from torchgarment.retarget.shrink import ShrunkAvatar, shrink_avatar

__all__ = [
    "FitTarget",
    "RetargetError",
    "RetargetProblem",
    "RetargetResult",
    "RetargetSettings",
    "ShrunkAvatar",
    "Similarity",
    "TestAvatar",
    "ToyCase",
    "check_result",
    "edit_by_bones",
    "layer_problem",
    "list_avatars",
    "load_problem",
    "make_avatar",
    "problem_from_arrays",
    "problem_from_bodies",
    "retarget",
    "retarget_layers",
    "shrink_avatar",
    "toy_case",
]
