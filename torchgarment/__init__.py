"""torchgarment: differentiable garment fitting in PyTorch.

The package root re-exports the error classes (:class:`TorchGarmentError` and its :class:`InputError`,
:class:`MeshError`, :class:`PatternError`) and ``__version__`` only, so that ``import torchgarment`` stays
cheap (torch, scipy, anny, ipctk and libigl are imported by the subpackages that use them). Each subpackage
re-exports what users call: ``torchgarment.body``, ``.pattern``, ``.structures``, ``.sdf``, ``.sim``,
``.adjust``, ``.retarget``, ``.datadriven``, ``.render``, ``.io``.
"""

from torchgarment.errors import InputError, MeshError, PatternError, TorchGarmentError

__version__ = "0.1.0"

__all__ = ["InputError", "MeshError", "PatternError", "TorchGarmentError", "__version__"]
