"""Principal component analysis of a body data set, in torch (Gillies et al. 2004, section 2).

Every body is the vector ``x = (x0, y0, z0, x1, ...)`` of length ``3V``. With the mean ``m`` and the centred
data matrix ``X - m`` (N x 3V), the thin SVD ``X - m = U S Wt`` gives the principal components (the rows of
``Wt``, orthonormal, ordered by decreasing variance) and the explained variances ``S**2 / (N - 1)``
(m**2). A body's weights are the dot products of ``x - m`` with the kept components (metres; the paper's
projection), and ``m + sum_i w_i c_i`` reconstructs it. ``k`` for a variance target (0.95, 0.99) is the
smallest number of components whose variances sum to that fraction of the total.

The model is stored with at most ``N - 1`` components (the rank of the centred data); directions whose
singular value is below ``10 sqrt(eps)`` of the largest (numerically zero variance) are dropped. Its
:meth:`BodyPCA. fingerprint` (a SHA-256 of the mean, components and faces) keys the clothing-basis cache.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchgarment.errors import InputError, MeshError
from torchgarment.io.atomic import atomic_path
from torchgarment.io.payload import load_payload

if TYPE_CHECKING:
    from torchgarment.datadriven.dataset import BodyDataset

FORMAT = "torchgarment.body_pca/1"


@dataclass
class BodyPCA:
    """A PCA body model.

    Attributes:
        mean: (V, 3) mean body, metres.
        components: (K, V, 3) orthonormal principal components (as flat vectors of length 3V), by decreasing
            variance.
        variances: (K,) explained variance of each component, m**2 (eigenvalues of the covariance).
        total_variance: sum of the variances of all components of the data (m**2), for the ratios.
        faces: (F, 3) long faces of the shared topology.
        num_bodies: N, the number of training bodies.
        topology: name of the topology ("" if unknown).
    """

    mean: torch.Tensor
    components: torch.Tensor
    variances: torch.Tensor
    total_variance: float
    faces: torch.Tensor
    num_bodies: int
    topology: str = ""

    @classmethod
    def fit(cls, dataset: BodyDataset, max_components: int | None = None) -> "BodyPCA":
        """PCA of a :class:`~torchgarment.datadriven.dataset.BodyDataset`.

        Args:
            dataset: N >= 2 bodies of one topology (device and dtype of the model follow the data set's).
            max_components: keep at most this many components (default: all N - 1).

        Raises:
            InputError: fewer than two bodies or a bad ``max_components``.
        """
        v = dataset.vertices
        n, nv = int(v.shape[0]), int(v.shape[1])
        if n < 2:
            raise InputError(f"PCA needs at least 2 bodies, got {n}")
        x = v.reshape(n, 3 * nv)
        mean = x.mean(dim=0)
        xc = x - mean
        # thin SVD of the N x 3V matrix through the N x N Gram matrix (N << 3V): X X^T = U S^2 U^T
        gram = xc @ xc.T
        evals, u = torch.linalg.eigh(gram)
        order = torch.argsort(evals, descending=True)
        evals, u = evals[order].clamp_min(0.0), u[:, order]
        rank = n - 1
        if max_components is not None:
            if not isinstance(max_components, int) or max_components < 1:
                raise InputError(f"max_components must be a positive integer, got {max_components!r}")
            rank = min(rank, max_components)
        s = evals[:rank].sqrt()
        # singular values below sqrt(eps) of the largest are round-off of the Gram route (rank-deficient data)
        tiny = 10.0 * torch.finfo(s.dtype).eps ** 0.5
        keep = s > s[0] * tiny if rank else s > 0
        s, u = s[keep], u[:, :rank][:, keep]
        comps = (u.T @ xc) / s[:, None]
        # re-orthonormalize (Gram-route rounding) with a QR that keeps the order and signs
        q, r = torch.linalg.qr(comps.T)
        comps = (q * torch.sign(torch.diagonal(r))[None, :]).T
        # deterministic signs: the largest-magnitude entry of every component is positive
        idx = comps.abs().argmax(dim=1)
        signs = torch.sign(comps.gather(1, idx[:, None])).squeeze(1)
        comps = comps * signs[:, None]
        variances = s**2 / (n - 1)
        total = float(evals.sum() / (n - 1))
        return cls(mean.reshape(nv, 3), comps.reshape(-1, nv, 3), variances, total, dataset.faces.clone(), n,
                   getattr(dataset, "topology", ""))

    # ----------------------------------------------------------------------------------------- properties
    @property
    def num_components(self) -> int:
        return int(self.components.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.mean.shape[0])

    @property
    def device(self) -> torch.device:
        return self.mean.device

    @property
    def dtype(self) -> torch.dtype:
        return self.mean.dtype

    @property
    def sigmas(self) -> torch.Tensor:
        """(K,) standard deviation of the weights along every component, metres."""
        return self.variances.sqrt()

    @property
    def explained_variance_ratio(self) -> torch.Tensor:
        """(K,) fraction of the total variance explained by every component."""
        return self.variances / self.total_variance

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "BodyPCA":
        """A copy on ``device`` with float tensors cast to ``dtype``."""
        return BodyPCA(self.mean.to(device=device, dtype=dtype),
                       self.components.to(device=device, dtype=dtype),
                       self.variances.to(device=device, dtype=dtype), self.total_variance,
                       self.faces.to(device=device), self.num_bodies, self.topology)

    def k_for_variance(self, target: float) -> int:
        """Smallest k whose components explain at least ``target`` (in (0, 1]) of the total variance.

        Raises:
            InputError: target outside (0, 1].
        """
        if not (0.0 < float(target) <= 1.0):
            raise InputError(f"variance target must be in (0, 1], got {target}")
        cum = torch.cumsum(self.explained_variance_ratio, dim=0)
        hit = (cum >= float(target) - 1e-12).nonzero()
        return int(hit[0]) + 1 if hit.numel() else self.num_components

    def _k(self, k: int | None) -> int:
        if k is None:
            return self.num_components
        if not isinstance(k, (int, np.integer)) or not 0 <= int(k) <= self.num_components:
            raise InputError(f"k must be an integer in [0, {self.num_components}], got {k!r}")
        return int(k)

    # ------------------------------------------------------------------------------------- projection
    def check_vertices(self, vertices: torch.Tensor, what: str = "body") -> torch.Tensor:
        """``vertices`` as (B, V, 3) on the model's device/dtype; :class:`MeshError` for another topology."""
        if not isinstance(vertices, torch.Tensor):
            vertices = torch.as_tensor(np.asarray(vertices))
        if vertices.ndim not in (2, 3) or vertices.shape[-1] != 3:
            raise MeshError(f"{what}: vertices must be (V, 3) or (B, V, 3), got {tuple(vertices.shape)}")
        if vertices.shape[-2] != self.num_vertices:
            raise MeshError(f"{what} has {vertices.shape[-2]} vertices but the body model's topology "
                            f"({self.topology or 'PCA'}) has {self.num_vertices}: the body must have the "
                            "model's topology (same vertices in the same order)")
        v = vertices if vertices.ndim == 3 else vertices[None]
        return v.to(device=self.device, dtype=self.dtype)

    def project(self, vertices: torch.Tensor, k: int | None = None) -> torch.Tensor:
        """Weights of bodies on the first ``k`` components (the paper's projection).

        Args:
            vertices: (V, 3) or (B, V, 3) positions, metres, in the model's topology.
            k: number of components (default all).

        Returns:
            (k,) or (B, k) weights, metres.
        """
        k = self._k(k)
        v = self.check_vertices(vertices)
        d = (v - self.mean).reshape(v.shape[0], -1)
        w = d @ self.components[:k].reshape(k, 3 * self.num_vertices).T
        return w if vertices.ndim == 3 else w[0]

    def reconstruct(self, weights: torch.Tensor) -> torch.Tensor:
        """Bodies ``mean + sum_i w_i c_i`` from (k,) or (B, k) weights (k <= K): (V, 3) or (B, V, 3)."""
        w = torch.as_tensor(weights, device=self.device, dtype=self.dtype)
        if w.ndim not in (1, 2) or w.shape[-1] > self.num_components:
            raise InputError(f"weights must be (k,) or (B, k) with k <= {self.num_components}, got "
                             f"{tuple(w.shape)}")
        k = w.shape[-1]
        w2 = w if w.ndim == 2 else w[None]
        flat = w2 @ self.components[:k].reshape(k, 3 * self.num_vertices)
        out = self.mean + flat.reshape(-1, self.num_vertices, 3)
        return out if w.ndim == 2 else out[0]

    def reconstruction_error(self, vertices: torch.Tensor, k: int | None = None) -> dict[str, torch.Tensor]:
        """Per-body vertex error of the rank-``k`` reconstruction.

        Returns:
            ``{"mean": (B,), "max": (B,), "rms": (B,)}`` vertex distances in metres.
        """
        v = self.check_vertices(vertices)
        rec = self.reconstruct(self.project(v, k))
        d = torch.linalg.vector_norm(rec - v, dim=-1)
        return {"mean": d.mean(dim=1), "max": d.amax(dim=1), "rms": d.square().mean(dim=1).sqrt()}

    def sample_body(self, i: int, c: float) -> torch.Tensor:
        """(V, 3) body at ``mean + c sigma_i component_i`` (the examples of the clothing basis)."""
        if not 0 <= i < self.num_components:
            raise InputError(f"component {i} is outside [0, {self.num_components})")
        return self.mean + float(c) * self.sigmas[i] * self.components[i]

    # --------------------------------------------------------------------------------------- storage
    def fingerprint(self) -> str:
        """SHA-256 (hex) of the mean, components and faces in float64/int64 (device independent)."""
        h = hashlib.sha256()
        for t in (self.mean.double(), self.components.double(), self.variances.double()):
            h.update(t.detach().cpu().contiguous().numpy().tobytes())
        h.update(self.faces.long().cpu().contiguous().numpy().tobytes())
        return h.hexdigest()

    def save(self, path: str | os.PathLike) -> None:
        """Write the model to one ``.pt`` file atomically."""
        payload = {"format": FORMAT, "mean": self.mean.detach().cpu(),
                   "components": self.components.detach().cpu(),
                   "variances": self.variances.detach().cpu(), "total_variance": self.total_variance,
                   "faces": self.faces.cpu(), "num_bodies": self.num_bodies, "topology": self.topology}
        with atomic_path(path) as tmp:
            torch.save(payload, tmp)

    @classmethod
    def load(cls, path: str | os.PathLike, dtype: torch.dtype | None = None,
             device: torch.device | str | None = None) -> "BodyPCA":
        """Read a model written by :meth:`save`; :class:`InputError` if missing or not a PCA model."""
        p = load_payload(path, FORMAT, "PCA body model")
        model = cls(p["mean"], p["components"], p["variances"], float(p["total_variance"]), p["faces"].long(),
                    int(p["num_bodies"]), str(p["topology"]))
        return model.to(device=device, dtype=dtype)
