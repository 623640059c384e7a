"""File input and output: atomic writes, meshes, skeleton graphs, skin weights."""

from torchgarment.io.atomic import atomic_open, atomic_path

__all__ = ["atomic_open", "atomic_path"]
