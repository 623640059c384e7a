"""Skeleton: joint positions and a bone graph.

A skeleton is a tree (or forest) of joints. ``bones`` lists (parent, child) joint index pairs. The OBJ edge
graph convention of the reference code of Huang et al. 2025 is used for files: ``v`` lines are joints,
``l`` lines are bones.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


@dataclass
class Skeleton:
    """Joints and bones of a body.

    Attributes:
        joints: (J, 3) joint positions in metres.
        bones: (B, 2) long tensor of (parent, child) joint indices.
        names: optional joint names, length J.
    """

    joints: torch.Tensor
    bones: torch.Tensor
    names: list[str] = field(default_factory=list)

    @property
    def num_joints(self) -> int:
        return int(self.joints.shape[0])

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "Skeleton":
        """Return a copy on ``device`` with float tensors cast to ``dtype``."""
        return Skeleton(self.joints.to(device=device, dtype=dtype), self.bones.to(device=device),
                        list(self.names))
