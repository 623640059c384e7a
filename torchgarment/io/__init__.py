"""File input and output: atomic writes, meshes, staged output folders.

Re-exports the atomic writers :func:`atomic_open` and :func:`atomic_path`; mesh files are read and written by
:mod:`torchgarment.io.mesh`, staged output folders by :mod:`torchgarment.io.staging` (imported from their
modules so that this package stays light). Skeleton graphs and skin weights, which build body objects, are
read and written by :mod:`torchgarment.body.skeleton_io` (the body layer).
"""

from torchgarment.io.atomic import atomic_open, atomic_path

__all__ = ["atomic_open", "atomic_path"]
