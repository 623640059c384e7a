"""Quasistatic garment simulation: energy terms, scenes that compose them, solvers (``torchgarment.sim.solvers``)
and IPC contact (``torchgarment.sim.contact``, imported on demand since it needs ipctk)."""

from torchgarment.sim.scene import Effect, Material, Scene, SimModel

__all__ = ["Effect", "Material", "Scene", "SimModel"]
