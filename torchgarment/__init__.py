"""torchgarment: differentiable garment fitting in PyTorch.

Public entry points are re-exported lazily so that ``import torchgarment`` stays cheap (anny, ipctk and
libigl are only imported when used).
"""

from torchgarment.errors import InputError, MeshError, PatternError, TorchGarmentError

__version__ = "0.1.0"

__all__ = ["InputError", "MeshError", "PatternError", "TorchGarmentError", "__version__"]
