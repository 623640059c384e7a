"""Offline step of Gillies et al. 2004: a clothing basis parallel to the PCA body basis.

One garment mesh (a pattern meshed once, so every result shares its topology) is draped with the simulator
(:func:`torchgarment.sim.drape.drape`) on the mean body and on the bodies ``mean +- c sigma_i component_i``
for each kept component ``i < k`` (2k + 1 drapes). The paper subtracts the mean garment from the garment
fitted to each example body and normalizes; here the weight of the example body along component ``i`` is
``+-h_i`` with ``h_i = c sigma_i`` (metres), so the garment displacement per unit weight is

* ``"linear"`` (the paper's linear model): ``G_i = (g_i+ - g_i-) / (2 h_i)`` (central difference), garment
  ``= g_0 + sum_i w_i G_i``; exact at the mean body, second-order accurate in between;
* ``"piecewise"``: ``G_i+ = (g_i+ - g_0) / h_i`` for ``w_i > 0`` and ``G_i- = (g_0 - g_i-) / h_i`` for
  ``w_i < 0``; garment ``= g_0 + sum_i max(w_i, 0) G_i+ + min(w_i, 0) G_i-``, which reproduces every one of
  the 2k + 1 basis drapes exactly (still two einsums online).

Placement of the fixed pattern around each body (the library drafts a pattern *for* one body and places
its panels from that body's measurements): the garment mesh is placed once for the reference (mean) body,
and for another body its placed positions are scaled about the floor and the Y axis, ``y' = y H_b / H_0``
(stature ratio: the library's heights are proportional to stature) and ``(x', z') = (x, z) D_b / D_0`` with
``D = max(bust, underbust, waist, hips) / (2 pi)`` (the library's panel-depth rule, so panels keep their
clearance from a larger body). Measurements come from :func:`torchgarment.body.measure.measure_body`. The
rest shape (panel coordinates ``p``) is never changed: the simulator sees the same garment on every body.

Support: a pattern with a support (a skirt's waistband, :attr:`SewingPattern.support`) keeps it in the
basis (:attr:`ClothingBasis.support`, a :class:`~torchgarment.sim.support.SupportLoop`), and every drape of
the basis, and every refine of a fit, holds it at that body's waist as a single drape does, so the garment
does not slide down by centimetres with small waist changes (``DrapeSettings(support=False)`` lets it hang by
its tension).

Regression (``BasisSettings(fit="regression")``, issue 15): a drape has several equilibria (the folds of a
skirt sit elsewhere around the body after a tiny body change), so each of Gillies' 2k + 1 example drapes is
one sample of them, and the blend carries that sample's folds, scaled by the customer's weights, into every
prediction. Instead, the garment is draped cold on N training bodies (the body model's own, passed as
``bodies``; the same protocol as a single drape) and the linear model ``g = g_0 + sum_i w_i G_i`` is fitted
to them by least squares: its prediction is the drapes' conditional mean given the weights, which is what
minimizes the expected distance to a drape of the customer. A garment with a support is fitted relative to
each body's waist plane (:func:`~torchgarment.sim.support.waist_height`: its y minus that height), because
the band hangs there and that level is not linear in the body; the fit then needs the customer's waist plane
(:meth:`~torchgarment.datadriven.online.OnlineFitter.anchors`). The fitted model is stored as a
:class:`ClothingBasis` whose ``plus`` / ``minus`` are the model's garments at ``+-c sigma_i`` (symmetric, so
both interpolations give the same linear model) and whose ``mean`` is the model at the mean body. The
continuation does not apply (every training drape is cold).

Caching: every drape is saved as it finishes under ``<cache>/<key>/<sample>.pt`` (atomic writes), so an
interrupted build resumes where it stopped, and a build for a larger k reuses the drapes of a smaller one;
the key hashes the PCA model (:meth:`BodyPCA.fingerprint`), the garment mesh, ``c``, the drape settings,
the placement rule and the support. Default cache: ``$TORCHGARMENT_CACHE/clothing_basis``.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from torchgarment.errors import InputError
from torchgarment.io.atomic import atomic_path
from torchgarment.io.payload import load_payload
from torchgarment.options import OptionEnum
from torchgarment.sim.drape import DrapeSettings
from torchgarment.sim.support import SupportLoop
from torchgarment.structures.garment_mesh import GarmentMesh

if TYPE_CHECKING:
    from torchgarment.body import Body
    from torchgarment.datadriven.pca import BodyPCA
    from torchgarment.pattern.spec import SewingPattern
    from torchgarment.sdf import BodySDF
    from torchgarment.sim.drape import DrapeResult

FORMAT = "torchgarment.clothing_basis/1"
PLACEMENT_VERSION = "1"
"""Version of the placement rule (part of the cache key)."""


class BasisFit(OptionEnum):
    """How a clothing basis is made from drapes (see the module docstring)."""

    EXAMPLES = "examples"
    """Gillies et al.: drapes of the mean body and of the example bodies ``mean +- c sigma_i component_i``."""
    REGRESSION = "regression"
    """A least-squares linear model of the cold drapes of N training bodies (``build_basis(bodies=...)``)."""


class Interpolation(OptionEnum):
    """How the basis drapes turn into per-weight garment displacements (see the module docstring)."""

    LINEAR = "linear"
    PIECEWISE = "piecewise"


@dataclass
class BasisSettings:
    """Settings of :func:`build_basis`.

    Attributes:
        k: number of PCA components to fit clothes for; None: the smallest k reaching ``variance``.
        variance: variance target used when ``k`` is None (e.g. 0.95, 0.99).
        c: the example bodies sit at ``+-c`` standard deviations along each component.
        drape: simulator settings of every basis drape (``edge_length`` meshes a pattern).
        continuation: drape each example body from the mean body's drape carried onto it in body-relative
            coordinates (:mod:`torchgarment.datadriven.relative`; sewing skipped), so that every basis drape
            sits on the mean drape's equilibrium branch (a hem has several); False: each drape starts from
            the placed panels, as Gillies et al. (examples only).
        fit: ``"examples"`` (Gillies: 2k + 1 example drapes) or ``"regression"`` (least squares over the cold
            drapes of training bodies; see the module docstring).
    """

    k: int | None = None
    variance: float = 0.95
    c: float = 1.0
    drape: DrapeSettings = field(default_factory=DrapeSettings)
    continuation: bool = True
    fit: BasisFit | str = BasisFit.EXAMPLES

    def __post_init__(self) -> None:
        """Validate at construction (and on ``dataclasses.replace``)."""
        self.validate()

    def validate(self) -> None:
        self.fit = BasisFit.resolve(self.fit)
        if not (isinstance(self.c, (int, float)) and math.isfinite(self.c) and 0 < self.c <= 4):
            raise InputError(f"BasisSettings.c must be in (0, 4] standard deviations, got {self.c!r}")
        if self.k is not None and (not isinstance(self.k, int) or self.k < 0):
            raise InputError(f"BasisSettings.k must be a non-negative integer or None, got {self.k!r}")
        if not 0 < self.variance <= 1:
            raise InputError(f"BasisSettings.variance must be in (0, 1], got {self.variance}")
        self.drape.validate()


@dataclass
class BodyFrame:
    """What the placement rule needs of a body: stature ``height`` and panel depth ``depth`` (metres)."""

    height: float
    depth: float

    @classmethod
    def of(cls, vertices: torch.Tensor, faces: torch.Tensor) -> "BodyFrame":
        """Measure a body (:func:`measure_body`; about 0.4 s)."""
        from torchgarment.body.measure import measure_body

        m = measure_body(vertices.detach().cpu().double(), faces.cpu()).to_dict()
        return cls(m["height"], max(m["bust"], m["underbust"], m["waist"], m["hips"]) / (2.0 * math.pi))


def place_for_body(x: torch.Tensor, reference: BodyFrame, body: BodyFrame) -> torch.Tensor:
    """(V, 3) garment positions placed for ``reference`` re-placed for ``body`` (see the module docstring)."""
    sy = body.height / reference.height
    sxz = body.depth / reference.depth
    scale = torch.tensor([sxz, sy, sxz], dtype=x.dtype, device=x.device)
    return x * scale


def mesh_hash(mesh: GarmentMesh) -> str:
    """SHA-256 of a garment mesh's placed positions, rest positions, faces and seams (float64/int64)."""
    h = hashlib.sha256()
    for t in (mesh.x.double(), mesh.p.double() if mesh.p is not None else torch.zeros(0), mesh.faces.long(),
              mesh.seam_pairs.long(),
              mesh.panel_ids.long() if mesh.panel_ids is not None else torch.zeros(0)):
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    h.update(json.dumps(list(mesh.panel_names)).encode())
    return h.hexdigest()


def _settings_description(settings: DrapeSettings) -> dict:
    return json.loads(json.dumps(asdict(settings), default=str, sort_keys=True))


def basis_cache_dir() -> Path:
    """Default folder of clothing bases: ``$TORCHGARMENT_CACHE/clothing_basis`` or
    ``~/.cache/torchgarment/...``."""
    from torchgarment.body.cache import cache_root

    return cache_root() / "clothing_basis"


@dataclass
class ClothingBasis:
    """A garment fitted to the PCA example bodies.

    Attributes:
        mean: (Vg, 3) garment draped on the mean body, metres.
        plus, minus: (k, Vg, 3) garments draped on ``mean +- c sigma_i component_i``.
        steps: (k,) weight offsets ``h_i = c sigma_i`` of those bodies, metres.
        garment: the garment mesh (topology, rest shape and seams; ``x`` = the mean-body drape).
        pca_fingerprint: :meth:`BodyPCA.fingerprint` of the body model the basis belongs to.
        key: cache key. name: garment name.
        metrics: per drape (``"mean"``, ``"plus_i"``, ``"minus_i"``): the drape's metrics (converged, ok,
            min_sdf_mm, seconds, ...).
        support: the garment's support loop (a skirt's waistband), held at each example body's waist in its
            drape (and in a refine), or None (the garment hangs by its tension).
        fit: how it was made (:class:`BasisFit` value). A regression basis of a garment with a support is
            fitted relative to the waist plane and must be fitted with the customers' ``anchors``
            (:attr:`needs_anchor`).
    """

    mean: torch.Tensor
    plus: torch.Tensor
    minus: torch.Tensor
    steps: torch.Tensor
    garment: GarmentMesh
    pca_fingerprint: str
    key: str = ""
    name: str = ""
    metrics: dict = field(default_factory=dict)
    support: SupportLoop | None = None
    fit: str = BasisFit.EXAMPLES.value

    @property
    def needs_anchor(self) -> bool:
        """True when the blend is relative to the waist plane: an online fit must move it there
        (:meth:`~torchgarment.datadriven.online.OnlineFitter.anchors`)."""
        return self.fit == BasisFit.REGRESSION.value and self.support is not None

    @property
    def k(self) -> int:
        return int(self.steps.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.mean.shape[0])

    def example_bodies(self, pca: BodyPCA) -> tuple[torch.Tensor, torch.Tensor]:
        """(k, V, 3) bodies of :attr:`plus` and of :attr:`minus` (``pca.sample_body(i, +-c)`` with ``c`` from
        :attr:`steps`), float64 CPU."""
        pca64 = pca.to(device="cpu", dtype=torch.float64)
        c = (self.steps.detach().cpu().double() / pca64.sigmas[: self.k]).tolist()
        if not c:
            empty = pca64.mean.new_zeros(0, *pca64.mean.shape)
            return empty, empty
        return (torch.stack([pca64.sample_body(i, c[i]) for i in range(self.k)]),
                torch.stack([pca64.sample_body(i, -c[i]) for i in range(self.k)]))

    def deltas(self, interpolation: Interpolation | str = Interpolation.PIECEWISE,
               k: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Garment displacement per unit weight for positive and negative weights, each (k, Vg, 3).

        For ``"linear"`` both are the central difference ``(g+ - g-) / (2 h)``.
        """
        k = self.k if k is None else int(k)
        if not 0 <= k <= self.k:
            raise InputError(f"the clothing basis has {self.k} components, asked for {k}")
        h = self.steps[:k, None, None]
        if Interpolation.resolve(interpolation) is Interpolation.LINEAR:
            g = (self.plus[:k] - self.minus[:k]) / (2.0 * h)
            return g, g
        return (self.plus[:k] - self.mean) / h, (self.mean - self.minus[:k]) / h

    def evaluate(self, weights: torch.Tensor, interpolation: Interpolation | str = Interpolation.PIECEWISE
                 ) -> torch.Tensor:
        """Garment(s) for (k',) or (B, k') weights, k' <= k (a reference implementation; batched use:
        :class:`torchgarment.datadriven.online.OnlineFitter`). Returns (Vg, 3) or (B, Vg, 3)."""
        w = torch.as_tensor(weights, dtype=self.mean.dtype, device=self.mean.device)
        w2 = w if w.ndim == 2 else w[None]
        gp, gm = self.deltas(interpolation, w2.shape[1])
        out = self.mean + torch.einsum("bk,kvc->bvc", w2.clamp_min(0.0), gp) \
            + torch.einsum("bk,kvc->bvc", w2.clamp_max(0.0), gm)
        return out if w.ndim == 2 else out[0]

    def to(self, device: torch.device | str | None = None,
           dtype: torch.dtype | None = None) -> "ClothingBasis":
        def cast(t: torch.Tensor) -> torch.Tensor:
            return t.to(device=device, dtype=dtype)

        return replace(self, mean=cast(self.mean), plus=cast(self.plus), minus=cast(self.minus),
                       steps=cast(self.steps),
                       garment=self.garment.to(device=device, dtype=dtype))

    def save(self, path: str | os.PathLike) -> None:
        """Write the basis to one ``.pt`` file atomically."""
        g = self.garment
        payload = {
            "format": FORMAT, "mean": self.mean.cpu(), "plus": self.plus.cpu(), "minus": self.minus.cpu(),
            "steps": self.steps.cpu(), "pca_fingerprint": self.pca_fingerprint, "key": self.key,
            "name": self.name,
            "metrics_json": json.dumps(self.metrics, default=str),
            "support": None if self.support is None else self.support.to_dict(), "fit": self.fit,
            "garment": {"x": g.x.cpu(), "faces": g.faces.cpu(), "p": None if g.p is None else g.p.cpu(),
                        "panel_ids": None if g.panel_ids is None else g.panel_ids.cpu(),
                        "panel_names": list(g.panel_names), "seam_pairs": g.seam_pairs.cpu()},
        }
        with atomic_path(path) as tmp:
            torch.save(payload, tmp)

    @classmethod
    def load(cls, path: str | os.PathLike, dtype: torch.dtype | None = None,
             device: torch.device | str | None = None) -> "ClothingBasis":
        """Read a basis written by :meth:`save`; :class:`InputError` if missing or of another format."""
        p = load_payload(path, FORMAT, "clothing basis")
        gd = p["garment"]
        garment = GarmentMesh(gd["x"], gd["faces"], p=gd["p"], panel_ids=gd["panel_ids"],
                              panel_names=gd["panel_names"], seam_pairs=gd["seam_pairs"])
        basis = cls(p["mean"], p["plus"], p["minus"], p["steps"], garment, p["pca_fingerprint"], p["key"],
                    p["name"], json.loads(p["metrics_json"]), SupportLoop.from_dict(p.get("support")),
                    p.get("fit", BasisFit.EXAMPLES.value))
        return basis.to(device=device, dtype=dtype)


def _as_garment_mesh(garment: SewingPattern | GarmentMesh, settings: DrapeSettings) -> GarmentMesh:
    if isinstance(garment, GarmentMesh):
        return garment.to(dtype=torch.float64, device="cpu")
    from torchgarment.pattern.spec import SewingPattern

    if isinstance(garment, SewingPattern):
        from torchgarment.pattern.meshing import mesh_pattern

        return mesh_pattern(garment, settings.edge_length, dtype=torch.float64)
    raise InputError(f"a clothing basis needs a SewingPattern or a GarmentMesh, got {type(garment).__name__}")


def basis_key(pca: BodyPCA, mesh: GarmentMesh, settings: BasisSettings,
              support: SupportLoop | None = None, bodies: torch.Tensor | None = None) -> str:
    """Cache key of a basis: hash of the body model, garment, c, drape settings, placement rule and the
    support held in the drapes (and, for ``fit="regression"``, of the training ``bodies``).

    ``k`` is not part of it: the drapes along component ``i`` do not depend on how many components are kept,
    so a basis for a larger k reuses those of a smaller one (the assembled basis is ``basis_k<k>.pt``).
    """
    desc = {"format": FORMAT, "pca": pca.fingerprint(), "garment": mesh_hash(mesh), "c": float(settings.c),
            "drape": _settings_description(settings.drape), "placement": PLACEMENT_VERSION}
    if BasisFit.resolve(settings.fit) is BasisFit.REGRESSION:  # training bodies, not examples
        if bodies is None:
            raise InputError("the key of a regression clothing basis needs its training bodies (bodies=...)")
        desc["fit"] = "regression"
        desc["bodies"] = hashlib.sha256(bodies.detach().cpu().double().numpy().tobytes()).hexdigest()
    elif settings.continuation:  # (absent from the key of the cold bases built before it existed)
        desc["continuation"] = True
    if support is not None and settings.drape.support:  # (absent from the keys of unsupported bases)
        desc["support"] = [support.name, support.indices.tolist()]
    return hashlib.sha256(json.dumps(desc, sort_keys=True).encode()).hexdigest()[:24]


def sample_names(k: int) -> list[str]:
    """Names of the 2k + 1 basis drapes, in build order."""
    return ["mean"] + [f"{s}_{i}" for i in range(k) for s in ("plus", "minus")]


def drape_on_body(mesh: GarmentMesh, vertices: torch.Tensor, faces: torch.Tensor, reference: BodyFrame,
                  settings: DrapeSettings, frame: BodyFrame | None = None,
                  start: torch.Tensor | None = None, support: SupportLoop | None = None) -> DrapeResult:
    """Drape the garment (placed for ``reference``) on one body after re-placing it (:func:`place_for_body`),
    or, with ``start``, settle it from those positions (:func:`refine`: sewing skipped). Every drape of a
    clothing basis goes through here.

    Args:
        mesh: garment mesh, positions placed for the reference body.
        vertices: (V, 3) body vertices, metres. faces: (F, 3) body faces.
        reference: frame of the body the garment is placed for.
        settings: drape settings. frame: the body's frame if already measured.
        start: (Vg, 3) sewn garment positions to start from (a continuation), or None.
        support: the garment's support loop (:attr:`ClothingBasis.support`), held at the body's waist.

    Returns:
        the :class:`~torchgarment.sim.drape.DrapeResult`.
    """
    from torchgarment.body.body import Body
    from torchgarment.sim.drape import drape

    body = Body(vertices=vertices.detach().cpu().double(), faces=faces.cpu().long())
    if start is not None:
        return refine(mesh, start, body, settings, support=support)
    frame = frame if frame is not None else BodyFrame.of(vertices, faces)
    placed = mesh.with_positions(place_for_body(mesh.x, reference, frame))
    return drape(placed, body, settings=settings, support=support)


def refine(mesh: GarmentMesh, x: torch.Tensor, body: Body, settings: DrapeSettings,
           iterations: int | None = None, sdf: BodySDF | None = None,
           support: SupportLoop | None = None, support_reference: torch.Tensor | None = None) -> DrapeResult:
    """Warm-started simulation: the PCA prediction ``x`` as the initial state of the quasistatic solve.

    The garment (already sewn: the sewing stage is skipped) settles on ``body`` with the drape's physics and
    tolerance for at most ``iterations`` solver iterations (None: the drape's own budget), a continuum between
    the millisecond PCA guess (0 iterations) and a full drape.

    Args:
        mesh: the basis garment (:attr:`ClothingBasis.garment`: rest pattern ``p``, seams).
        x: (V, 3) its predicted positions on ``body``, metres.
        body: the customer's body (vertices and faces). settings: the basis's drape settings.
        iterations: settle budget (>= 0). sdf: the body's SDF when already built (else built and cached).
        support: the garment's support loop (:attr:`ClothingBasis.support`), held at the body's waist.
        support_reference: (V, 3) the garment placed for ``body`` (e.g. :func:`place_for_body` of a placed or
            mean-body garment): the support's targets take their rotation about the body from it, as a cold
            drape's do, not from the prediction ``x`` (whose rotation error a converged settle would keep);
            None: from ``x``.

    Returns:
        The :class:`~torchgarment.sim.drape.DrapeResult` (``metrics["converged"]`` tells whether the budget
        was enough).
    """
    from torchgarment.sim.drape import drape

    if iterations is not None and not (isinstance(iterations, int) and iterations >= 0):
        raise InputError(f"refine iterations must be an integer >= 0, got {iterations!r}")
    st = replace(settings, sew_max_iterations=0,
                 max_iterations=settings.max_iterations if iterations is None else iterations)
    return drape(mesh.with_positions(x.detach().to(mesh.x)), body, settings=st, sdf=sdf, support=support,
                 support_reference=support_reference)


def build_basis(
    pca: BodyPCA,
    garment: SewingPattern | GarmentMesh,
    settings: BasisSettings | None = None,
    *,
    name: str = "",
    cache_dir: str | os.PathLike | None = None,
    progress: bool = True,
    bodies: torch.Tensor | None = None,
) -> ClothingBasis:
    """Fit a garment to the PCA example bodies (or, for ``fit="regression"``, to training bodies) with the
    simulator (resumable, cached).

    Args:
        pca: the :class:`~torchgarment.datadriven.pca.BodyPCA` body model.
        garment: a :class:`SewingPattern` (meshed at ``settings.drape.edge_length``) or a sewn
            :class:`GarmentMesh`, placed around the mean body (e.g. drafted from its measurements).
        settings: k (or a variance target), c, drape settings and the fit.
        name: garment name stored in the basis.
        cache_dir: root of the cache (default :func:`basis_cache_dir`).
        progress: tqdm bar over the drapes.
        bodies: (N, V, 3) training bodies in the model's topology, metres: needed by ``fit="regression"``
            (N >= k + 2; e.g. the dataset the model was fitted on), refused otherwise.

    Returns:
        the :class:`ClothingBasis` (also written to ``<cache>/<key>/basis_k<k>.pt``).

    Raises:
        InputError: bad settings, a garment that is not a pattern/mesh, k larger than the model's, or
            training bodies missing, too few or given to an examples basis.
        MeshError: training bodies of another topology.
    """
    from tqdm import tqdm

    from torchgarment.body.frames import attach, decode, encode

    settings = replace(settings) if settings is not None else BasisSettings()
    settings.validate()
    mesh = _as_garment_mesh(garment, settings.drape)
    k = pca.k_for_variance(settings.variance) if settings.k is None else settings.k
    if k > pca.num_components:
        raise InputError(f"the body model has {pca.num_components} components, asked for k={k}")
    regression = settings.fit is BasisFit.REGRESSION
    if regression:
        if bodies is None:
            raise InputError("a regression clothing basis needs the training bodies (bodies=...)")
        bodies = pca.check_vertices(torch.as_tensor(bodies), "training body").detach().cpu().double()
        if bodies.shape[0] < k + 2:
            raise InputError(f"a regression clothing basis of k={k} needs at least {k + 2} training bodies, "
                             f"got {bodies.shape[0]}")
    elif bodies is not None:
        raise InputError("training bodies are for BasisSettings(fit='regression'); an examples basis drapes "
                         "the PCA's example bodies")
    support = (SupportLoop.of(garment, mesh)
               if settings.drape.support and not isinstance(garment, GarmentMesh) else None)
    key = basis_key(pca, mesh, settings, support, bodies)
    folder = Path(cache_dir) if cache_dir is not None else basis_cache_dir()
    folder = folder / key
    final = folder / f"basis_k{k}.pt"
    if final.is_file():
        return ClothingBasis.load(final)
    pca64 = pca.to(device="cpu", dtype=torch.float64)
    faces = pca64.faces
    reference = BodyFrame.of(pca64.mean, faces)
    names = [f"body_{i:04d}" for i in range(bodies.shape[0])] if regression else sample_names(k)
    results: dict[str, torch.Tensor] = {}
    metrics: dict[str, dict] = {}
    kind = ", regression" if regression else ""
    bar = tqdm(names, desc=f"clothing basis {name or 'garment'} (k={k}{kind})", disable=not progress)
    tri = None  # attachment triangles of the continuation
    for n_sample, sample in enumerate(bar):
        path = folder / f"{sample}.pt"
        if path.is_file():
            entry = torch.load(path, map_location="cpu", weights_only=True)
            results[sample], metrics[sample] = entry["x"], json.loads(entry["metrics_json"])
            continue
        if regression:
            verts = bodies[n_sample]
        elif sample == "mean":
            verts = pca64.mean
        else:
            sign, i = sample.split("_")
            verts = pca64.sample_body(int(i), settings.c if sign == "plus" else -settings.c)
        t0 = time.perf_counter()
        start = None
        if sample != "mean" and settings.continuation and not regression:  # the mean drape carried over
            if tri is None:
                tri = attach(results["mean"], pca64.mean, faces.long())
            start = decode(encode(results["mean"], pca64.mean, faces.long(), tri), verts, faces.long(), tri)
        result = drape_on_body(mesh, verts, faces, reference, settings.drape, start=start, support=support)
        m = {key_: result.metrics[key_]
             for key_ in ("vertices", "iterations", "converged", "ok", "min_sdf_mm",
                                                    "inside_vertices", "max_seam_gap_mm", "residual")}
        if regression and support is not None:
            from torchgarment.sim.support import waist_height

            m["waist_y_m"] = waist_height(verts, faces.long())
        m["seconds"] = time.perf_counter() - t0
        bar.set_postfix(last=f"{sample} {m['seconds']:.0f}s {'ok' if m['ok'] else 'NOT ok'}", refresh=False)
        with atomic_path(path) as tmp:
            torch.save({"x": result.x.detach().cpu().double(), "metrics_json": json.dumps(m)}, tmp)
        results[sample], metrics[sample] = result.x.detach().cpu().double(), m
    if regression:
        mean, plus, minus, steps = _regression_model(pca64, bodies, k, settings.c,
                                                     torch.stack([results[n] for n in names]),
                                                     [metrics[n].get("waist_y_m") for n in names],
                                                     support is not None)
    else:
        mean = results["mean"]
        plus = (torch.stack([results[f"plus_{i}"] for i in range(k)]) if k
                else torch.zeros(0, mesh.num_vertices, 3, dtype=torch.float64))
        minus = torch.stack([results[f"minus_{i}"] for i in range(k)]) if k else torch.zeros_like(plus)
        steps = settings.c * pca64.sigmas[:k].clone()
    basis = ClothingBasis(mean, plus, minus, steps, mesh.with_positions(mean), pca64.fingerprint(), key, name,
                          metrics, support, settings.fit.value)
    basis.save(final)
    return basis


_MEAN_WAIST: dict[str, float] = {}


def mean_waist_height(pca: BodyPCA) -> float:
    """Waist-plane height (metres) of the body model's mean body
    (:func:`~torchgarment.sim.support.waist_height`), measured once per model (cached by
    :meth:`BodyPCA.fingerprint`; 0.25 s to measure)."""
    from torchgarment.sim.support import waist_height

    fp = pca.fingerprint()
    if fp not in _MEAN_WAIST:
        _MEAN_WAIST[fp] = waist_height(pca.mean.detach().cpu().double(), pca.faces.long().cpu())
    return _MEAN_WAIST[fp]


def _regression_model(pca: BodyPCA, bodies: torch.Tensor, k: int, c: float, drapes: torch.Tensor,
                      waists: list[float | None], anchored: bool
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Least-squares linear model of training drapes (see the module docstring), as a basis's
    ``(mean, plus, minus, steps)``.

    Args:
        pca: the body model (float64, CPU). bodies: (N, V, 3) training bodies. k: components.
        c: the stored ``plus`` / ``minus`` sit at ``+-c sigma_i``. drapes: (N, Vg, 3) their drapes, metres.
        waists: (N,) the bodies' waist-plane heights (metres; used when ``anchored``).
        anchored: fit the drapes relative to their bodies' waist planes (a garment with a support).
    """
    n = drapes.shape[0]
    z = drapes.clone()
    y0 = 0.0
    if anchored:
        z[:, :, 1] -= torch.tensor(waists, dtype=z.dtype)[:, None]
        y0 = mean_waist_height(pca)
    sig = pca.sigmas[:k]
    w = pca.project(bodies, k) / sig if k else bodies.new_zeros(n, 0)  # (N, k), in standard deviations
    features = torch.cat([w.new_ones(n, 1), w], dim=1)  # (N, k + 1)
    coef = torch.linalg.lstsq(features, z.reshape(n, -1)).solution.reshape(k + 1, -1, 3)  # per sigma
    mean = coef[0].clone()
    mean[:, 1] += y0
    plus, minus = mean + c * coef[1:], mean - c * coef[1:]
    return mean, plus, minus, c * sig.clone()
