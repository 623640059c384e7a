"""Where a garment's support sticks and how stiffly: the targets and stiffness of its sticking springs.

The support (:attr:`~torchgarment.pattern.spec.SewingPattern.support`, e.g. a skirt's waistband) is held by
the existing sticking energy, :class:`~torchgarment.sim.energies.pins.Pins` (``Effect.PINS``, Wang 2018's
``F(x)``). This module decides its targets and stiffness:

* **Base drape target** (:func:`waist_band_targets`): the band's loop sits in the horizontal plane of the
  body's waist (:func:`~torchgarment.body.measure.find_section_planes`, the minimum torso girth), on the
  convex hull of the body's section there (the tape measure's path) offset outwards by
  ``d = (L - L_hull) / (2 pi)`` so that the loop keeps its own rest length ``L`` (the offset of a convex curve
  by ``d`` is ``2 pi d`` longer); a band shorter than ``L_hull + 2 pi min_clearance`` is stretched around the
  hull at ``min_clearance``. The band's vertices are spaced along that curve by their rest arc length, in the
  band's own direction around the body, at the rotation (phase) that best matches their positions after the
  sewing stage (least squares in the horizontal plane, 4,096 phases): the band is put on, not twisted.
* **Stiffness** (:func:`support_stiffness`): from physics, not tuned: the band holds the garment's whole
  weight ``W`` with a mean displacement of ``sag``: ``k = W / (P sag)`` per pin for ``P`` pinned vertices
  (N/m). The default sag (``DrapeSettings.support_sag``) is 0.5 mm, half the 1 mm a waistband may give, so the
  unevenly loaded pins stay within 1 mm. The total stiffness ``P k = W / sag`` does not depend on the mesh
  resolution.
* **Report** (:func:`support_metrics`): the force the pins exert and their largest displacement.

A mesh without its pattern (a clothing basis keeps only the mesh) carries its support as a
:class:`SupportLoop` (:meth:`SupportLoop.of` the pattern and its mesh).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchgarment.errors import InputError

if TYPE_CHECKING:
    from torchgarment.body.measure import SectionPlane
    from torchgarment.pattern.spec import SewingPattern
    from torchgarment.structures.garment_mesh import GarmentMesh

DEFAULT_SUPPORT_SAG = 5.0e-4
"""Mean displacement (m) of the support pins if they alone carried the garment's weight (sets k)."""

MIN_CLEARANCE = 1.0e-3
"""Smallest outward offset (m) of the band's target loop from the convex hull of the body's waist section."""

PHASES = 4096
"""Number of rotations tried when placing the band's vertices along the target loop."""


@dataclass(frozen=True)
class SupportLoop:
    """A garment mesh's support loop, for draping the mesh without its pattern.

    Attributes:
        indices: (P,) long mesh vertices of the loop, in loop order.
        arc: (P,) float64 their rest arc length along the loop from its first vertex, metres.
        length: the loop's rest length, metres.
        name: the support as ``PANEL:EDGE,...`` (for reports).
    """

    indices: torch.Tensor
    arc: torch.Tensor
    length: float
    name: str

    @classmethod
    def of(cls, pattern: SewingPattern, mesh: GarmentMesh) -> SupportLoop | None:
        """The support of ``pattern`` on ``mesh`` (made from it by ``mesh_pattern``), or None without one."""
        from torchgarment.pattern.support import format_support, support_vertices

        if not pattern.support:
            return None
        idx, arc, length = support_vertices(pattern, mesh)
        return cls(idx, arc, float(length), format_support(pattern.support))

    def to_dict(self) -> dict:
        """Plain data (tensors on the CPU) for ``torch.save``; :meth:`from_dict` reads it back."""
        return {"indices": self.indices.cpu(), "arc": self.arc.cpu(), "length": self.length,
                "name": self.name}

    @classmethod
    def from_dict(cls, d: dict | None) -> SupportLoop | None:
        if d is None:
            return None
        return cls(d["indices"].long(), d["arc"].double(), float(d["length"]), str(d["name"]))


def support_stiffness(weight: float, count: int, sag: float = DEFAULT_SUPPORT_SAG) -> float:
    """Pin spring constant ``k = W / (P sag)`` in N/m (see the module docstring).

    Args:
        weight: the garment's weight ``W`` in newtons (> 0).
        count: number ``P`` of pinned vertices (>= 1).
        sag: mean displacement in metres under the full weight (> 0).

    Raises:
        InputError: a non-positive argument.
    """
    if not (weight > 0 and count >= 1 and sag > 0):
        raise InputError(f"support stiffness needs weight > 0, count >= 1 and sag > 0, got {weight}, "
                         f"{count}, {sag}")
    return float(weight) / (int(count) * float(sag))


def _waist_plane(vertices: torch.Tensor, faces: torch.Tensor) -> SectionPlane:
    """The tape measure's waist plane (:func:`~torchgarment.body.measure.find_section_planes`)."""
    from torchgarment.body.measure import find_section_planes

    return find_section_planes(vertices, faces, names=("waist",))["waist"]


def waist_height(vertices: torch.Tensor, faces: torch.Tensor) -> float:
    """Height (metres, +Y) of the body's waist plane, where :func:`waist_band_targets` puts a band: the
    minimum torso girth's level, a landmark that can move by centimetres between similar bodies (a flat
    minimum). About 0.1 s for an anny body on one slow core (the landmark search: about 200 horizontal
    cuts, most of them batched).

    Args:
        vertices: (B, 3) body vertices in metres (+Y up). faces: (G, 3) long body triangles.
    """
    return float(_waist_plane(vertices, faces).point[1])


def _waist_hull(vertices: torch.Tensor, faces: torch.Tensor) -> tuple[float, np.ndarray]:
    """Height of the waist plane and the convex hull (H, 2) of the torso section there, (x, z), CCW."""
    from scipy.spatial import ConvexHull

    # the tape measure's own section (the loop its waist girth is measured on)
    from torchgarment.body.measure import section_loop

    plane = _waist_plane(vertices, faces)
    p = plane.point.detach().cpu().double().numpy()
    loop = section_loop(vertices, faces, plane)
    if loop is None:
        raise InputError("the body's waist plane does not cut the body")
    xz = loop.points[:, [0, 2]]
    hull = xz[ConvexHull(xz).vertices]
    return float(p[1]), hull


def _offset_curve(hull: np.ndarray, d: float, samples: int = 4096) -> np.ndarray:
    """Boundary (samples, 2) of the Minkowski sum of a convex CCW polygon (H, 2) and a disk of radius d,
    sampled by outward normal angle (CCW)."""
    t = np.linspace(0.0, 2.0 * math.pi, samples, endpoint=False)
    nrm = np.stack([np.cos(t), np.sin(t)], axis=1)
    j = np.argmax(nrm @ hull.T, axis=1)
    return hull[j] + d * nrm


def _closed_arclength(c: np.ndarray) -> tuple[np.ndarray, float]:
    seg = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)
    return np.concatenate([[0.0], np.cumsum(seg)[:-1]]), float(seg.sum())


def waist_band_targets(vertices: torch.Tensor, faces: torch.Tensor, x_band: torch.Tensor, s: torch.Tensor,
                       length: float, *, min_clearance: float = MIN_CLEARANCE) -> tuple[torch.Tensor, dict]:
    """Targets of a band's vertices at the body's waist (see the module docstring).

    Args:
        vertices: (B, 3) body vertices in metres (+Y up). faces: (G, 3) long body triangles.
        x_band: (P, 3) the band's vertices in loop order (e.g. after the sewing stage), metres.
        s: (P,) their rest arc length along the loop from its first vertex, metres, non-decreasing.
        length: the loop's rest length ``L`` in metres.
        min_clearance: smallest offset of the loop from the section's convex hull, metres.

    Returns:
        ``(targets, info)``: (P, 3) targets (dtype and device of ``x_band``) and JSON-ready numbers:
        ``waist_y_m`` (plane height), ``hull_girth_m``, ``band_length_m``, ``offset_mm``, ``stretch`` (target
        loop length / L, 1 unless the band is too short).
    """
    y, hull = _waist_hull(vertices, faces)
    _, l_hull = _closed_arclength(hull)
    d = max((length - l_hull) / (2.0 * math.pi), min_clearance)
    curve = _offset_curve(hull, d)
    u_curve, l_curve = _closed_arclength(curve)
    xb = x_band.detach().cpu().double().numpy()[:, [0, 2]]
    area = 0.5 * float(np.sum(xb[:, 0] * np.roll(xb[:, 1], -1) - xb[:, 1] * np.roll(xb[:, 0], -1)))
    u = s.detach().cpu().double().numpy() * (l_curve / length) * (1.0 if area >= 0 else -1.0)
    up = np.concatenate([u_curve, [l_curve]])
    cp = np.concatenate([curve, curve[:1]], axis=0)

    def at(w: np.ndarray) -> np.ndarray:
        w = np.mod(w, l_curve)
        return np.stack([np.interp(w, up, cp[:, 0]), np.interp(w, up, cp[:, 1])], axis=-1)

    phases = np.linspace(0.0, l_curve, PHASES, endpoint=False)
    pts = at(u[None, :] + phases[:, None])  # (PHASES, P, 2)
    cost = ((pts - xb[None]) ** 2).sum(axis=(1, 2))
    best = pts[int(np.argmin(cost))]
    tgt = np.stack([best[:, 0], np.full(len(best), y), best[:, 1]], axis=1)
    info = {"waist_y_m": y, "hull_girth_m": l_hull, "band_length_m": float(length), "offset_mm": 1e3 * d,
            "stretch": l_curve / float(length)}
    return torch.as_tensor(tgt, dtype=x_band.dtype, device=x_band.device), info


def support_metrics(x: torch.Tensor, indices: torch.Tensor, targets: torch.Tensor, stiffness: float) -> dict:
    """What the support pins do at positions ``x`` (V, 3).

    Returns:
        JSON-ready: ``support_force_n`` = ``|sum_i k (t_i - x_i)|``, the magnitude of the net force the pins
        exert on the garment (N; about the weight they carry); ``support_force_sum_n`` = ``sum_i |k (t_i -
        x_i)|`` (N; also counts forces that cancel around the loop, e.g. a band pulled in by a tight waist);
        ``support_max_displacement_mm`` = ``max_i |x_i - t_i|``; ``support_mean_displacement_mm``;
        ``support_vertices``; ``support_stiffness_n_per_m`` (``k`` per pin).
    """
    d = (x.detach()[indices] - targets.detach().to(x.dtype)).double()
    dist = torch.linalg.vector_norm(d, dim=1)
    return {"support_force_n": float(stiffness * torch.linalg.vector_norm(d.sum(dim=0))),
            "support_force_sum_n": float(stiffness * dist.sum()),
            "support_max_displacement_mm": 1e3 * float(dist.max()) if dist.numel() else 0.0,
            "support_mean_displacement_mm": 1e3 * float(dist.mean()) if dist.numel() else 0.0,
            "support_vertices": int(indices.numel()),
            "support_stiffness_n_per_m": float(stiffness)}


__all__ = ["DEFAULT_SUPPORT_SAG", "MIN_CLEARANCE", "support_metrics", "support_stiffness",
           "waist_band_targets", "waist_height"]
