"""Bodies: meshes with skeletons, anny human bodies, measuring, kinematics and skinning.

Re-exports :class:`Body` (mesh, skeleton, skin weights, landmarks; ``Body.from_size`` fits an anny body to a
chart row), :class:`Skeleton`, :func:`measure_body` with its :class:`BodyMeasurements`, and the size chart's
:func:`chart_row` and :func:`list_sizes`.
"""

from torchgarment.body.body import Body
from torchgarment.body.measure import BodyMeasurements, measure_body
from torchgarment.body.size_chart import chart_row, list_sizes
from torchgarment.body.skeleton import Skeleton

__all__ = ["Body", "BodyMeasurements", "Skeleton", "chart_row", "list_sizes", "measure_body"]
