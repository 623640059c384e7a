"""File input and output: atomic writes, meshes, skeleton graphs, skin weights.

Re-exports the atomic writers :func:`atomic_open` and :func:`atomic_path`; mesh files are read and written by
:mod:`torchgarment.io.mesh`, skeleton graphs and skin weights by :mod:`torchgarment.io.skeleton`, staged
output folders by :mod:`torchgarment.io.staging` (imported from their modules so that this package stays
light).
"""

from torchgarment.io.atomic import atomic_open, atomic_path

__all__ = ["atomic_open", "atomic_path"]
