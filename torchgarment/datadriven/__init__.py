"""Data-driven garment fitting (Gillies et al. 2004): a PCA body model, a clothing basis draped offline on
its example bodies, and an online fit that interpolates the basis for a new body in milliseconds.

Re-exported here:

* bodies: :class:`BodyDataset` (anny body samples) and :class:`BodyPCA` (the PCA body model);
* the clothing basis (:mod:`torchgarment.datadriven.basis`): :func:`build_basis` with :class:`BasisSettings`
  (:class:`BasisFit`: Gillies' example drapes or a regression over training drapes) and
  :class:`Interpolation`, the resulting :class:`ClothingBasis`, :class:`BodyFrame` with
  :func:`place_for_body` (placing a garment for a body), :func:`drape_on_body` and :func:`basis_cache_dir`;
* the online fit (:mod:`torchgarment.datadriven.online`): :class:`OnlineFitter`, :func:`push_out` with its
  :class:`PushOutResult` (vertices inside the body pushed out, exact distances) and :func:`refine` (the
  prediction settled by the simulator for a few iterations).

The command line (``torchgarment pca build`` / ``pca fit``) is :mod:`torchgarment.datadriven.cli`.
"""

from torchgarment.datadriven.basis import (
    BasisFit,
    BasisSettings,
    BodyFrame,
    ClothingBasis,
    Interpolation,
    basis_cache_dir,
    build_basis,
    drape_on_body,
    place_for_body,
)
from torchgarment.datadriven.dataset import BodyDataset
from torchgarment.datadriven.online import OnlineFitter, PushOutResult, push_out, refine
from torchgarment.datadriven.pca import BodyPCA

__all__ = [
    "BasisFit",
    "BasisSettings",
    "BodyDataset",
    "BodyFrame",
    "BodyPCA",
    "ClothingBasis",
    "Interpolation",
    "OnlineFitter",
    "PushOutResult",
    "basis_cache_dir",
    "build_basis",
    "drape_on_body",
    "place_for_body",
    "push_out",
    "refine",
]
