"""Bodies: meshes with skeletons, anny human bodies, measuring, kinematics and skinning."""

from torchgarment.body.body import Body
from torchgarment.body.skeleton import Skeleton

__all__ = ["Body", "Skeleton"]
