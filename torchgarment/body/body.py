"""The :class:`Body` structure: a triangle mesh with an optional skeleton, landmarks and measurements."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from torchgarment.body.skeleton import Skeleton

if TYPE_CHECKING:  # pragma: no cover
    from torchgarment.body.measure import BodyMeasurements


@dataclass
class Body:
    """A body (human or not) as a triangle mesh in metres, +Y up.

    Attributes:
        vertices: (V, 3) positions in metres.
        faces: (F, 3) long vertex indices.
        skeleton: optional joints and bones.
        skin_weights: optional (J, V) linear-blend-skinning weights, columns sum to 1.
        landmarks: named points, each a (3,) tensor in metres.
        params: the parameters that generated the body (e.g. anny phenotype), for caching and provenance.
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    skeleton: Skeleton | None = None
    skin_weights: torch.Tensor | None = None
    landmarks: dict[str, torch.Tensor] = field(default_factory=dict)
    params: dict = field(default_factory=dict)
    _measurements: "BodyMeasurements | None" = field(default=None, repr=False, compare=False)

    @property
    def device(self) -> torch.device:
        return self.vertices.device

    @property
    def dtype(self) -> torch.dtype:
        return self.vertices.dtype

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "Body":
        """Return a copy with tensors moved to ``device`` and floats cast to ``dtype``."""
        return Body(
            vertices=self.vertices.to(device=device, dtype=dtype),
            faces=self.faces.to(device=device),
            skeleton=None if self.skeleton is None else self.skeleton.to(device, dtype),
            skin_weights=(None if self.skin_weights is None
                          else self.skin_weights.to(device=device, dtype=dtype)),
            landmarks={k: v.to(device=device, dtype=dtype) for k, v in self.landmarks.items()},
            params=dict(self.params),
        )

    def measurements(self) -> "BodyMeasurements":
        """Measure the body (height and girths, metres); computed once and cached."""
        if self._measurements is None:
            from torchgarment.body.measure import measure_body

            self._measurements = measure_body(self.vertices.detach(), self.faces)
        return self._measurements

    # Constructors live in their own modules; these are thin entry points.
    @classmethod
    def from_file(cls, path: str | os.PathLike, skeleton: Skeleton | str | os.PathLike | None = None,
                  skin_weights: torch.Tensor | str | os.PathLike | None = None, *,
                  dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> "Body":
        """Load any mesh file (OBJ, PLY, STL, GLB) as a body; see :func:`torchgarment.body.load.load_body`."""
        from torchgarment.body.load import load_body

        return load_body(path, skeleton=skeleton, skin_weights=skin_weights, dtype=dtype, device=device)

    @classmethod
    def from_measurements(cls, *, dtype: torch.dtype = torch.float64,
                          device: torch.device | str | None = None, cache: bool = True,
                          closest: bool = False, **measurements: float) -> "Body":
        """Fit an anny body to measurements in metres; see
        :func:`torchgarment.body.anny_body.body_from_measurements` (``closest``: keep the closest body when
        the request is out of the model's reach)."""
        from torchgarment.body.anny_body import body_from_measurements

        return body_from_measurements(measurements, dtype=dtype, device=device, cache=cache, closest=closest)

    @classmethod
    def from_size(cls, size: str, *, dtype: torch.dtype = torch.float64,
                  device: torch.device | str | None = None, cache: bool = True) -> "Body":
        """A body of a size of the built-in chart; see :mod:`torchgarment.body.size_chart`."""
        from torchgarment.body.size_chart import chart_row

        return cls.from_measurements(dtype=dtype, device=device, cache=cache, **chart_row(size))
