"""A data set of bodies that share one mesh topology (the avatars of Gillies et al. 2004, section 2).

PCA needs every body as the same vector ``(x0, y0, z0, x1, ...)`` with vertex ``i`` at the same place on every
body, i.e. one topology. :class:`BodyDataset` stacks the vertices ``(N, V, 3)`` of such bodies with their
shared faces. It comes from random anny adults (:meth:`BodyDataset.from_anny`, realistic ranges documented
in :mod:`torchgarment.body.anny_phenotype`) or from user meshes (:meth:`BodyDataset.from_meshes`), whose
faces must be identical; a mismatch raises :class:`~torchgarment.errors.MeshError` naming the first
offending mesh.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from torchgarment.errors import InputError, MeshError
from torchgarment.io.atomic import atomic_path
from torchgarment.io.payload import load_payload

if TYPE_CHECKING:
    from torchgarment.body.anny_phenotype import PhenotypeRanges
    from torchgarment.body.body import Body

FORMAT = "torchgarment.body_dataset/1"
"""Format tag stored in saved data sets."""


@dataclass
class BodyDataset:
    """Bodies of one topology.

    Attributes:
        vertices: (N, V, 3) positions in metres, +Y up.
        faces: (F, 3) long faces shared by every body.
        params: one dict per body (e.g. the anny phenotype), JSON-ready; may be empty dicts.
        source: where the bodies come from (``"anny"``, ``"meshes"``, ...).
        topology: name of the shared topology (e.g. ``"anny-noeyes-notongue"``), or ``""``.
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    params: list[dict] = field(default_factory=list)
    source: str = ""
    topology: str = ""

    def __post_init__(self) -> None:
        v, f = self.vertices, self.faces
        if not isinstance(v, torch.Tensor) or v.ndim != 3 or v.shape[2] != 3 or v.shape[0] < 1 \
                or not v.is_floating_point():
            raise MeshError(f"dataset vertices must be a floating (N, V, 3) tensor with N >= 1, got "
                            f"{getattr(v, 'shape', type(v).__name__)}")
        if not isinstance(f, torch.Tensor) or f.ndim != 2 or f.shape[1] != 3 or f.dtype != torch.long:
            raise MeshError("dataset faces must be a long (F, 3) tensor, got "
                            f"{getattr(f, 'shape', type(f).__name__)}")
        if f.numel() and (int(f.min()) < 0 or int(f.max()) >= v.shape[1]):
            raise MeshError(f"dataset faces index vertices outside [0, {v.shape[1]})")
        if not bool(torch.isfinite(v).all()):
            raise MeshError("dataset vertices contain NaN or Inf")
        if not self.params:
            self.params = [{} for _ in range(v.shape[0])]
        if len(self.params) != v.shape[0]:
            raise InputError(f"{len(self.params)} params for {v.shape[0]} bodies")

    def __len__(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[1])

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "BodyDataset":
        """A copy on ``device`` with vertices cast to ``dtype``."""
        return BodyDataset(self.vertices.to(device=device, dtype=dtype), self.faces.to(device=device),
                           [dict(p) for p in self.params], self.source, self.topology)

    def subset(self, index: slice | list[int] | torch.Tensor) -> "BodyDataset":
        """The bodies at ``index`` (a slice, list or tensor of indices)."""
        if isinstance(index, slice):
            ids = list(range(len(self)))[index]
        else:
            ids = [int(i) for i in (index.tolist() if isinstance(index, torch.Tensor) else index)]
        if not ids:
            raise InputError("empty subset of a body dataset")
        return BodyDataset(self.vertices[ids], self.faces, [dict(self.params[i]) for i in ids], self.source,
                           self.topology)

    def body(self, i: int) -> Body:
        """Body ``i`` as a plain :class:`~torchgarment.body.body.Body` (mesh only)."""
        from torchgarment.body.body import Body

        return Body(vertices=self.vertices[i], faces=self.faces, params=dict(self.params[i]))

    def check_topology(self, vertices: torch.Tensor, faces: torch.Tensor | None = None,
                       what: str = "body") -> None:
        """Raise :class:`MeshError` unless a mesh has this data set's topology.

        Args:
            vertices: (V, 3) or (B, V, 3) positions.
            faces: the mesh's faces, compared with the data set's when given.
            what: name of the mesh in the message.
        """
        if vertices.ndim not in (2, 3) or vertices.shape[-1] != 3:
            raise MeshError(f"{what}: vertices must be (V, 3) or (B, V, 3), got {tuple(vertices.shape)}")
        if vertices.shape[-2] != self.num_vertices:
            raise MeshError(f"{what} has {vertices.shape[-2]} vertices but the body model's topology "
                            f"({self.topology or self.source or 'dataset'}) has {self.num_vertices}: bodies "
                            f"must share one topology (same vertices in the same order)")
        if faces is not None and (faces.shape != self.faces.shape
                                  or not torch.equal(faces.to(self.faces.device).long(), self.faces)):
            raise MeshError(f"{what} has {self.num_vertices} vertices but different faces from the body "
                            "model's topology: bodies must share one topology (same faces, same vertex "
                            "order)")

    @classmethod
    def from_anny(cls, n: int, seed: int = 0, ranges: PhenotypeRanges | None = None, batch_size: int = 64,
                  dtype: torch.dtype = torch.float64,
                  device: torch.device | str | None = None) -> "BodyDataset":
        """``n`` random adult anny bodies (see :func:`torchgarment.body.anny_phenotype.sample_phenotypes`).

        Args:
            n: number of bodies. seed: sampling seed. ranges: a ``PhenotypeRanges`` (default: adult women).
            batch_size: bodies per anny forward pass. dtype, device: of the vertices.

        Returns:
            the data set; ``params[i]`` is body i's phenotype (with ``age_years`` and ``stature``).
        """
        from torchgarment.body.anny_body import TOPOLOGY, load_anny_model
        from torchgarment.body.anny_phenotype import sample_phenotypes, vertices_from_phenotypes

        phenotypes = sample_phenotypes(n, seed=seed, ranges=ranges, batch_size=batch_size)
        vertices = vertices_from_phenotypes(phenotypes, batch_size=batch_size)
        faces = load_anny_model().faces.clone().long()
        return cls(vertices.to(device=device, dtype=dtype), faces.to(device=device), phenotypes, "anny",
                   TOPOLOGY)

    @classmethod
    def from_meshes(cls, meshes: list, dtype: torch.dtype = torch.float64,
                    device: torch.device | str | None = None, topology: str = "") -> "BodyDataset":
        """A data set from meshes of one topology.

        Args:
            meshes: mesh file paths (OBJ, PLY, ...; read with :func:`torchgarment.io.mesh.load_mesh` semantics
                via :func:`torchgarment.body.load.load_body`), :class:`Body` objects or ``(vertices, faces)``
                pairs; all must have the same faces.
            dtype, device: of the vertices. topology: a name for the shared topology.

        Raises:
            MeshError: an empty list, or a mesh whose vertex count or faces differ from the first one's.
        """
        if not meshes:
            raise MeshError("no meshes given for the body dataset")
        verts, faces0, params = [], None, []
        for i, m in enumerate(meshes):
            name = str(m) if isinstance(m, (str, os.PathLike)) else f"mesh {i}"
            if isinstance(m, (str, os.PathLike)):
                from torchgarment.body.load import load_body

                if not Path(m).is_file():
                    raise InputError(f"body mesh {m} does not exist")
                b = load_body(m, dtype=torch.float64)
                v, f = b.vertices, b.faces.long()
                params.append({"path": str(m)})
            elif hasattr(m, "vertices") and hasattr(m, "faces"):
                v, f = torch.as_tensor(m.vertices, dtype=torch.float64), torch.as_tensor(m.faces).long()
                params.append(dict(getattr(m, "params", {}) or {}))
            else:
                try:
                    v, f = m
                except (TypeError, ValueError):
                    raise InputError(f"{name}: expected a path, a Body or a (vertices, faces) pair") from None
                v, f = torch.as_tensor(v, dtype=torch.float64), torch.as_tensor(f).long()
                params.append({})
            if v.ndim != 2 or v.shape[1] != 3:
                raise MeshError(f"{name}: vertices must be (V, 3), got {tuple(v.shape)}")
            if faces0 is None:
                faces0 = f.cpu()
            elif v.shape[0] != verts[0].shape[0]:
                raise MeshError(f"{name} has {v.shape[0]} vertices but the first mesh has "
                                f"{verts[0].shape[0]}: a body dataset needs one topology (same vertices in "
                                "the same order)")
            elif f.shape != faces0.shape or not torch.equal(f.cpu(), faces0):
                raise MeshError(f"{name} has the same vertex count as the first mesh but different faces: a "
                                f"body dataset needs one topology (same faces, same vertex order)")
            verts.append(v.cpu())
        return cls(torch.stack(verts).to(device=device, dtype=dtype), faces0.to(device=device), params,
                   "meshes",
                   topology)

    def measure(self, progress: bool = True) -> list[dict[str, float]]:
        """Height and girths of every body (:func:`torchgarment.body.measure.measure_body`, about 0.4 s
        each)."""
        from tqdm import tqdm

        from torchgarment.body.measure import measure_body

        out = []
        for i in tqdm(range(len(self)), desc="measure bodies", disable=not progress, leave=False):
            out.append(measure_body(self.vertices[i].detach().cpu().double(), self.faces.cpu()).to_dict())
        return out

    def save(self, path: str | os.PathLike) -> None:
        """Write the data set to one ``.pt`` file (atomically; float tensors as stored)."""
        payload = {"format": FORMAT, "vertices": self.vertices.detach().cpu(), "faces": self.faces.cpu(),
                   "params": self.params, "source": self.source, "topology": self.topology,
                   "saved": time.strftime("%Y-%m-%dT%H:%M:%S")}
        with atomic_path(path) as tmp:
            torch.save(payload, tmp)

    @classmethod
    def load(cls, path: str | os.PathLike, dtype: torch.dtype | None = None,
             device: torch.device | str | None = None) -> "BodyDataset":
        """Read a data set written by :meth:`save`.

        Raises:
            InputError: missing file or not a body data set.
        """
        payload = load_payload(path, FORMAT, "body dataset")
        ds = cls(payload["vertices"], payload["faces"].long(), list(payload["params"]), payload["source"],
                 payload["topology"])
        return ds.to(device=device, dtype=dtype)
