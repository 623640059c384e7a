"""Bodies: meshes with skeletons, anny human bodies, measuring, kinematics and skinning."""

from torchgarment.body.body import Body
from torchgarment.body.measure import BodyMeasurements, measure_body
from torchgarment.body.skeleton import Skeleton

__all__ = ["Body", "BodyMeasurements", "Skeleton", "measure_body"]
