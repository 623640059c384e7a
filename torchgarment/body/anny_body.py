"""Human bodies from the ``anny`` parametric model, fitted to tape measurements.

The anny model (NAVER, Apache-2.0; MakeHuman topology) is loaded with the ``anny-noeyes-notongue`` topology:
without eyes and tongue the triangulated body is one closed, consistently wound genus-0 surface (checked
with trimesh: watertight, winding-consistent, Euler number 2), as measuring and collision code need. Anny is
Z-up with the front (toes) towards -Y and the body's left at +X (Blender's convention); bodies here are +Y up
with the front towards +Z and the left at +X (``(x, y, z) -> (x, z, -y)``, a proper rotation, so face winding
stays outward), metres, feet at ``y = 0`` and the root (pelvis) joint on the Y axis (x = z = 0), so that
garments placed around the Y axis sit around the torso. The pose is anny's rest pose (an A-pose).

Fitting (:func:`fit_anny`): the model is loaded with all phenotypes (``phenotypes="all"``, which adds the
breast phenotypes ``cupsize`` and ``firmness`` and the race mix). ``age`` is fixed to the "young adult" anchor
(2/3), ``firmness`` and the race mix to anny's neutral 0.5, and ``gender`` to a guess from the shape of the
request (the bust-underbust and hips-waist drops). The free parameters are the phenotypes ``height``,
``weight``, ``muscle``, ``proportions`` and ``cupsize`` (the bust-underbust drop of a large bust comes from a
real, larger breast rather than from stretching the chest with a local change) and, for every requested girth,
the matching MakeHuman local change ``measure-<girth>-circ-incr`` in [-1.5, 1.5]. The residuals are the body's
*own* measurements (:mod:`torchgarment.body.measure`: ``body_height`` and ``section_girths``, both
differentiable) minus the request, with the tape planes found afresh
(:func:`~torchgarment.body.measure.find_section_planes`) for every evaluated body, i.e. exactly what
:func:`~torchgarment.body.measure.measure_body` reports. They are minimised by projected Levenberg-Marquardt.
The Jacobian is the autograd Jacobian with the planes fixed plus, once the largest error is below 2 cm, the
effect of the planes moving with the shape (girth slope along each plane normal times the plane motion per
parameter, by finite differences of the landmark search): without it the fit alternates between plane sets,
because e.g. a larger breast moves its own fold, and with it the underbust tape, down. A weak prior pulls the
local changes to 0 (the one direction the residuals leave free is weight vs. local changes). The fit stops
when every measurement is within ``FitSettings.tolerance`` or after ``FitSettings.stall_rounds`` rounds
without progress; a run that misses the tolerance is repeated by continuation (the request reached in
``FitSettings.continuation`` stages from the start body's own measurements, each stage warm-started from the
last, which keeps the tape planes on one branch when the shape changes a lot, e.g. a bust graded without its
underbust). The best body found is kept, so a fit never ends farther from the request than its start. A final
:func:`measure_body` check within ``FitSettings.accept`` decides whether the request was reached
(:func:`body_from_measurements`); ``body --closest`` keeps the closest body otherwise.

Reach, measured (``python scripts/body_fit_acceptance.py``): the three GarmentCode mean bodies' YAML
measurements, each with bust, underbust, waist and hips moved by +-5.08 and +-10.16 cm, and with bust, waist
and hips moved by +-5.08 cm with the underbust kept: 21 of 21 within 3 mm (see the README for the figures).

Loading: anny builds its model data from the MakeHuman target files on first use and caches it under
``~/.cache/anny`` (``$ANNY_CACHE_DIR``). Measured on this project's machine: about 220 s cold (no anny cache),
0.6 s warm; the loaded model is also kept in memory for the process (:func:`load_anny_model`).
Fitted bodies are cached on disk (:mod:`torchgarment.body.cache`).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import asdict, dataclass
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np
import torch

from torchgarment.body import cache as body_cache
from torchgarment.body.body import Body
from torchgarment.body.measure import (
    SectionPlane,
    body_height,
    find_section_planes,
    measure_body,
    section_girths,
)
from torchgarment.body.skeleton import Skeleton
from torchgarment.errors import InputError

if TYPE_CHECKING:
    import anny

FIT_VERSION = "6"
"""Version of the fitting code; part of the cache key. Bump it whenever fitted bodies would change."""

TOPOLOGY = "anny-noeyes-notongue"
"""Anny topology: triangulated MakeHuman body without eyes and tongue (a closed manifold)."""

LOCAL_CHANGES: dict[str, str] = {
    "bust": "measure-bust-circ-incr",
    "underbust": "measure-underbust-circ-incr",
    "waist": "measure-waist-circ-incr",
    "hips": "measure-hips-circ-incr",
    "thigh": "measure-thigh-circ-incr",
    "upper_arm": "measure-upperarm-circ-incr",
    "neck": "measure-neck-circ-incr",
    "wrist": "measure-wrist-circ-incr",
}
"""Girth name -> the anny (MakeHuman) local change fitted for it."""

REQUIRED = ("height", "bust", "waist", "hips")
"""Measurements every request must give."""

RANGES: dict[str, tuple[float, float]] = {
    "height": (1.30, 2.10),
    "bust": (0.65, 1.60),
    "underbust": (0.55, 1.45),
    "waist": (0.50, 1.60),
    "hips": (0.70, 1.70),
    "thigh": (0.38, 0.95),
    "upper_arm": (0.20, 0.55),
    "neck": (0.27, 0.50),
    "wrist": (0.13, 0.22),
}
"""Accepted range of every measurement, metres (adult humans; wider than the 1st-99th percentiles)."""

ADULT_AGE = 2.0 / 3.0
"""Anny ``age`` of the MakeHuman "young" (25 years) targets."""

_PHENOTYPES = (
    "gender", "age", "muscle", "weight", "height", "proportions", "cupsize", "firmness", "african", "asian",
    "caucasian"
)
"""Anny's phenotype labels with ``phenotypes="all"``, in the model's order."""

_FREE = ("height", "weight", "muscle", "proportions", "cupsize")
"""Fitted phenotypes, in the order of the first entries of the parameter vector."""

NUM_PHENO_FREE = len(_FREE)

DEFAULT_PHENOTYPE: dict[str, float] = {
    "age": ADULT_AGE,
    "muscle": 0.5,
    "weight": 0.5,
    "height": 0.5,
    "proportions": 0.5,
    "cupsize": 0.5,
    "firmness": 0.5,
    "african": 0.5,
    "asian": 0.5,
    "caucasian": 0.5,
}
"""Start values of the phenotypes (``gender`` comes from :func:`guess_gender`); anny's neutral 0.5 except the
adult age. Equal race values give anny's mixed average."""

MAX_WEIGHT = 0.9
"""Upper bound of the fitted ``weight`` phenotype (the heaviest anny bodies have a belly that overhangs the
hips); larger girths come from the local changes instead."""

LOCAL_CHANGE_RANGE = (-1.5, 1.5)
"""Bounds of the fitted local changes (MakeHuman's sliders span [-1, 1]; the targets are linear offsets, and a
mild extrapolation to +-1.5 reaches the whole size chart, e.g. its small underbusts)."""


@dataclass(frozen=True)
class FitSettings:
    """Settings of :func:`fit_anny`.

    Attributes:
        tolerance: stop when every measurement (height and girths, re-measured with fresh planes) is within
            this many metres of the request (the landmark search has about 1 mm of jitter, so much less is
            wasted time).
        max_rounds: maximum number of Levenberg-Marquardt iterations (each re-finds the planes of every
            trial).
        prior: weight (metres per unit) of the prior pulling local changes to 0.
        accept: a fit whose final error exceeds this many metres raises InputError.
        max_step: largest change of any parameter in one step (a trust region: the tape planes move with the
            shape, so long steps computed with fixed planes overshoot).
        plane_motion_below: once the largest error is below this (metres), the Jacobian also models how the
            tape planes move with the shape (finite differences of the landmark search, one per parameter).
        fd_step: parameter step of those finite differences.
        continuation: stages of the continuation tried when the direct fit misses ``tolerance`` (1: none).
        stall_rounds: a run stops when its largest error has not improved by 1 % for this many rounds.
    """

    tolerance: float = 1e-3
    max_rounds: int = 30
    prior: float = 2e-4
    accept: float = 3e-3
    max_step: float = 0.15
    plane_motion_below: float = 0.02
    fd_step: float = 1e-3
    continuation: int = 4
    stall_rounds: int = 6

    def __post_init__(self) -> None:
        """Raise :class:`InputError` for non-positive or non-finite values."""
        for name in ("tolerance", "prior", "accept", "max_step", "plane_motion_below", "fd_step"):
            v = getattr(self, name)
            number = isinstance(v, (int, float)) and math.isfinite(v)
            if not (number and (v > 0 or (name == "prior" and v == 0))):
                raise InputError(f"FitSettings.{name} must be a positive number, got {v!r}")
        for name in ("continuation", "stall_rounds"):
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise InputError(f"FitSettings.{name} must be an integer >= 1, got {v!r}")
        if not (isinstance(self.max_rounds, int) and self.max_rounds >= 1):
            raise InputError(f"FitSettings.max_rounds must be an integer >= 1, got {self.max_rounds!r}")


@dataclass
class AnnyFit:
    """Result of :func:`fit_anny`.

    Attributes:
        phenotype: anny phenotype values by name.
        local_changes: anny local change values by label.
        measured: the fitted body's measurements (``measure_body``), metres.
        max_error: largest absolute difference between ``measured`` and the request, metres.
        rounds: plane searches done; steps: LM steps taken; seconds: wall time of the fit.
        history: largest error (metres) measured with fresh planes at the start of every round.
    """

    phenotype: dict[str, float]
    local_changes: dict[str, float]
    measured: dict[str, float]
    max_error: float
    rounds: int
    steps: int
    seconds: float
    history: list[float]


@functools.lru_cache(maxsize=1)
def load_anny_model() -> anny.Anny:
    """The anny model used for bodies (loaded once per process; anny caches its data on disk).

    Returns:
        ``anny.Anny`` in float64 on the CPU, topology :data:`TOPOLOGY`, local changes :data:`LOCAL_CHANGES`.
    """
    anny = _import_anny_quietly()
    return anny.Anny(topology=TOPOLOGY, local_changes=list(LOCAL_CHANGES.values()), phenotypes="all")


def _import_anny_quietly() -> ModuleType:
    """Import anny without the banner and the CUDA-driver line its NVIDIA Warp dependency prints at import
    (:mod:`torchgarment.warp_runtime`: Warp initialized quietly, stderr muted during the import only).
    Exceptions raised by the import propagate unchanged."""
    import sys

    if "anny" in sys.modules:
        return sys.modules["anny"]
    from torchgarment.warp_runtime import import_warp, muted_stderr

    import_warp()
    with muted_stderr():
        import anny
    return anny


def anny_version() -> str:
    """Installed anny version (part of the cache key), read from the package's metadata so that a cache hit
    never imports anny and warp (about 2 s); from the module itself for an anny without metadata (a source
    tree on ``sys.path``)."""
    from importlib import metadata

    try:
        return metadata.version("anny")
    except metadata.PackageNotFoundError:
        return str(_import_anny_quietly().__version__)


def validate_measurements(measurements: dict) -> dict[str, float]:
    """Check a measurement request.

    Args:
        measurements: name -> metres; names from :data:`RANGES`, those of :data:`REQUIRED` mandatory.

    Returns:
        The request as plain floats, in the canonical order.

    Raises:
        InputError: unknown or missing names, non-finite or out-of-range values, or underbust >= bust.
    """
    unknown = sorted(set(measurements) - set(RANGES))
    if unknown:
        raise InputError(f"unknown body measurement(s) {unknown}; accepted: {', '.join(RANGES)}")
    missing = [k for k in REQUIRED if k not in measurements]
    if missing:
        raise InputError(f"missing body measurement(s) {missing}; required: {', '.join(REQUIRED)}")
    out: dict[str, float] = {}
    for name, (lo, hi) in RANGES.items():
        if name not in measurements:
            continue
        try:
            if isinstance(measurements[name], bool):  # JSON true would read as 1.0 m
                raise TypeError
            value = float(measurements[name])
        except (TypeError, ValueError):
            raise InputError(f"body measurement {name!r} must be a number (metres), got "
                             f"{measurements[name]!r}")
        if not math.isfinite(value) or not lo <= value <= hi:
            raise InputError(f"body measurement {name}={value!r} m is outside the realistic range [{lo}, "
                             f"{hi}] m")
        out[name] = value
    if "underbust" in out and out["underbust"] >= out["bust"]:
        raise InputError(f"underbust ({out['underbust']:.3f} m) must be smaller than bust ({out['bust']:.3f} "
                         "m)")
    return out


def guess_gender(measurements: dict[str, float]) -> float:
    """Anny ``gender`` (0 male, 1 female) guessed from the relative hips-waist and bust-underbust drops.

    Typical women have ``(hips - waist) / hips`` about 0.2-0.3 and ``(bust - underbust) / bust`` about
    0.12-0.18; typical men about 0.05-0.1 and 0.05-0.08. Each drop is mapped linearly onto [0, 1] between
    those values and the available ones are averaged.
    """
    m = measurements
    scores = [((m["hips"] - m["waist"]) / m["hips"] - 0.08) / 0.12]
    if "underbust" in m:
        scores.append(((m["bust"] - m["underbust"]) / m["bust"] - 0.06) / 0.06)
    return float(np.clip(np.mean(scores), 0.0, 1.0))


def _to_y_up(v: torch.Tensor) -> torch.Tensor:
    """Anny (Z up, front -Y) to ours (Y up, front +Z): (x, y, z) -> (x, z, -y), a rotation. Shape (..., 3)."""
    return torch.stack([v[..., 0], v[..., 2], -v[..., 1]], dim=-1)


class _Shape:
    """Differentiable map from the free parameters to Y-up rest vertices (V, 3), float64 CPU.

    The parameter vector is ``[height, weight, muscle, proportions, cupsize, local changes of girths]``.
    """

    def __init__(self, model: anny.Anny, phenotype: dict[str, float], girths: list[str]) -> None:
        self.model = model
        if tuple(model.phenotype_labels) != _PHENOTYPES:
            raise InputError(f"unexpected anny phenotype labels {list(model.phenotype_labels)}")
        self.base_pheno = torch.tensor([phenotype[k] for k in _PHENOTYPES], dtype=torch.float64)
        self.free_index = torch.tensor([_PHENOTYPES.index(k) for k in _FREE], dtype=torch.long)
        labels = list(model.local_change_labels)
        self.lc_index = torch.tensor([labels.index(LOCAL_CHANGES[g]) for g in girths], dtype=torch.long)
        self.num_lc = len(labels)
        self.girths = girths
        upper = {"weight": MAX_WEIGHT}
        self.lower = torch.tensor([0.0] * NUM_PHENO_FREE + [LOCAL_CHANGE_RANGE[0]] * len(girths),
                                  dtype=torch.float64)
        self.upper = torch.tensor(
            [upper.get(k, 1.0) for k in _FREE] + [LOCAL_CHANGE_RANGE[1]] * len(girths), dtype=torch.float64
        )

    def initial(self) -> torch.Tensor:
        """Start point: the base phenotype's free values, no local changes."""
        return torch.cat([self.base_pheno[self.free_index], self.base_pheno.new_zeros(len(self.girths))])

    def split(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        pheno = self.base_pheno.to(x.dtype).index_put((self.free_index,), x[:NUM_PHENO_FREE])
        lc = torch.zeros(self.num_lc, dtype=x.dtype).index_put((self.lc_index,), x[NUM_PHENO_FREE:])
        return pheno, lc

    def coefficients(self, x: torch.Tensor) -> torch.Tensor:
        pheno, lc = self.split(x)
        return self.model._get_phenotype_blendshape_coefficients(pheno[None], lc[None], pheno.new_zeros(1, 0))

    def vertices(self, x: torch.Tensor) -> torch.Tensor:
        return _to_y_up(self.model.get_rest_vertices(self.coefficients(x))[0])


def _solve_height(shape: _Shape, x: torch.Tensor, target: float) -> torch.Tensor:
    """Secant iterations on the phenotype height so that the body height matches ``target`` (in place on
    x)."""
    with torch.no_grad():

        def h(t: float) -> float:
            y = x.clone()
            y[0] = t
            return float(body_height(shape.vertices(y)))

        t0, t1 = 0.3, 0.7
        h0, h1 = h(t0), h(t1)
        for _ in range(6):
            if abs(h1 - target) < 1e-5 or h1 == h0:
                break
            t0, t1, h0 = t1, t1 + (target - h1) * (t1 - t0) / (h1 - h0), h1
            h1 = h(t1)
        x[0] = float(np.clip(t1, 0.0, 1.0))
    return x


def _plane_offsets(planes: dict[str, SectionPlane], names: tuple[str, ...]) -> torch.Tensor:
    """(G,) signed offset of each plane along its normal (``point . normal``), metres."""
    return torch.stack([(planes[n].point * planes[n].normal).sum() for n in names]).to(torch.float64)


def _plane_motion(
    shape: "_Shape", faces: torch.Tensor, names: tuple[str, ...], x: torch.Tensor, offsets: torch.Tensor,
    h: float
) -> torch.Tensor:
    """(G, P) derivative of the plane offsets (``point . normal`` of freshly found planes) with respect to the
    parameters, by one-sided finite differences of step ``h`` (backwards at an upper bound)."""
    out = torch.zeros(len(names), x.numel(), dtype=torch.float64)
    for k in range(x.numel()):
        d = -h if float(x[k]) + h > float(shape.upper[k]) else h
        y = x.clone()
        y[k] += d
        with torch.no_grad():
            v = shape.vertices(y)
        out[:, k] = (_plane_offsets(find_section_planes(v, faces, names=names), names) - offsets) / d
    return out


def _girth_slopes(vertices: torch.Tensor, faces: torch.Tensor, planes: dict[str, SectionPlane],
                  eps: float = 1e-3) -> torch.Tensor:
    """(G,) derivative of each girth with respect to moving its plane along the normal (central differences
    over +-eps metres), in the order of ``planes``."""
    shifted = {}
    for n, p in planes.items():
        for sign in (1.0, -1.0):
            shifted[f"{n}{sign:+}"] = SectionPlane(n, p.point + sign * eps * p.normal, p.normal, p.seed)
    g = section_girths(vertices, faces, shifted)
    return torch.stack([(g[f"{n}+1.0"] - g[f"{n}-1.0"]) / (2 * eps) for n in planes])


def _bounded_step(
    jtj: torch.Tensor, jtr: torch.Tensor, mu: float, x: torch.Tensor, lower: torch.Tensor, upper: torch.Tensor
) -> torch.Tensor:
    """Damped Gauss-Newton step (P,) with an active set: parameters at a bound that the step would push
    outwards are frozen and the step is solved again for the others."""
    free = torch.ones_like(x, dtype=torch.bool)
    step = torch.zeros_like(x)
    for _ in range(x.numel()):
        idx = free.nonzero().squeeze(1)
        a = jtj[idx][:, idx]
        a = a + torch.diag(mu * (torch.diag(a) + 1e-12))
        step = torch.zeros_like(x)
        step[idx] = -torch.linalg.solve(a, jtr[idx])
        blocked = free & (((x <= lower) & (step < 0)) | ((x >= upper) & (step > 0)))
        if not bool(blocked.any()):
            break
        free &= ~blocked
        if not bool(free.any()):
            return torch.zeros_like(x)
    return step


@dataclass
class _Solve:
    """One Levenberg-Marquardt run of :func:`_least_squares`: the best parameters found (P,), their largest
    measurement error (metres, fresh planes), plane searches (rounds), trial steps, and the largest error at
    the start of every round."""

    x: torch.Tensor
    max_error: float
    rounds: int
    steps: int
    history: list[float]


def _least_squares(shape: "_Shape", faces: torch.Tensor, girths: list[str], target: torch.Tensor,
                   x: torch.Tensor, prior_w: torch.Tensor, x_prior: torch.Tensor,
                   settings: FitSettings) -> _Solve:
    """Projected Levenberg-Marquardt on the body's own measurements minus ``target`` (height then girths,
    metres), from ``x`` (P,), with the prior ``prior_w * (x - x_prior)``; see the module docstring."""

    def residual(xv: torch.Tensor, planes: dict[str, SectionPlane]) -> torch.Tensor:
        v = shape.vertices(xv)
        g = section_girths(v, faces, planes)
        meas = torch.stack([body_height(v)] + [g[n] for n in girths])
        return torch.cat([meas - target, prior_w * (xv - x_prior)])

    n_meas = 1 + len(girths)
    names = tuple(girths)
    steps = 0
    rounds = 0
    history: list[float] = []

    def evaluate(xv: torch.Tensor) -> tuple[dict[str, SectionPlane], torch.Tensor, torch.Tensor]:
        """(fresh planes, their offsets (G,), true residual) of the body at xv: what measure_body reports."""
        with torch.no_grad():
            v = shape.vertices(xv)
        fresh = find_section_planes(v, faces, names=names)
        with torch.no_grad():
            r = residual(xv, fresh)
        return fresh, _plane_offsets(fresh, names), r

    planes, offsets, r = evaluate(x)
    best, progress_round = (math.inf, x.clone()), 0
    mu = 1e-3
    motion: torch.Tensor | None = None  # (G, P) plane motion per parameter, once close to the goal
    fresh_motion = False
    while True:
        rounds += 1
        max_err = float(r[:n_meas].abs().max())
        history.append(max_err)
        if max_err < 0.99 * best[0]:
            progress_round = rounds
        if max_err < best[0]:
            best = (max_err, x.clone())
        if max_err <= settings.tolerance or rounds > settings.max_rounds:
            break
        if rounds - progress_round >= settings.stall_rounds:
            break  # under 1 % of progress: let the caller try the continuation
        # Jacobian of the true residual: the shape change with the planes fixed (autograd) plus, close to the
        # goal, the girth change caused by the tape planes moving with the shape (girth slope along each plane
        # normal x plane motion per parameter, by finite differences of the landmark search)
        jac = torch.autograd.functional.jacobian(lambda xv: residual(xv, planes), x).clone()
        if max_err < settings.plane_motion_below:
            # the plane motion changes slowly with the shape: re-estimated only after a failed iteration
            fresh_motion = motion is None
            if fresh_motion:
                motion = _plane_motion(shape, faces, names, x, offsets, settings.fd_step)
            with torch.no_grad():
                slopes = _girth_slopes(shape.vertices(x), faces, planes)
            jac[1:n_meas] += slopes[:, None] * motion
        jtj, jtr, cost = jac.T @ jac, jac.T @ r, float(r @ r)
        improved = False
        for _ in range(8):
            step = _bounded_step(jtj, jtr, mu, x, shape.lower, shape.upper)
            step = step * min(1.0, settings.max_step / max(float(step.abs().max()), 1e-30))
            x_new = torch.minimum(torch.maximum(x + step, shape.lower), shape.upper)
            try:
                planes_new, offsets_new, r_new = evaluate(x_new)
            except InputError:  # a trial body whose landmarks cannot be found (not a fit): a failed step
                planes_new = None
            steps += 1
            if planes_new is not None and float(r_new @ r_new) < cost:
                x, planes, offsets, r = x_new, planes_new, offsets_new, r_new
                mu = max(mu / 3.0, 1e-7)
                improved = True
                break
            mu *= 4.0
        if not improved:
            if motion is None or fresh_motion:
                break
            motion, mu = None, 1e-3  # retry with a fresh plane-motion estimate
    return _Solve(best[1], best[0], rounds, steps, history)


def fit_anny(measurements: dict[str, float],
             settings: FitSettings = FitSettings()) -> tuple[AnnyFit, torch.Tensor]:
    """Fit anny's phenotype and local changes to tape measurements.

    The fit runs from anny's average body at the requested height. When that run ends farther than
    ``settings.tolerance`` from the request, the fit is repeated by continuation: the request is reached in
    ``settings.continuation`` equal stages from the start body's own measurements, each stage started from the
    previous one's result, so that the tape planes (which jump where the shape changes a lot, e.g. a larger
    bust-underbust drop moves the underbust fold) stay on one branch. The better of the two results is kept.

    Args:
        measurements: validated request (see :func:`validate_measurements`), metres.
        settings: tolerances and iteration limits.

    Returns:
        The fit (the closest body found, whether or not within ``settings.accept``: see
        :func:`body_from_measurements`) and the fitted Y-up rest vertices (V, 3), float64, not yet recentred.
    """
    t_start = time.perf_counter()
    model = load_anny_model()
    faces = model.faces
    girths = [g for g in LOCAL_CHANGES if g in measurements]
    phenotype = dict(DEFAULT_PHENOTYPE, gender=guess_gender(measurements))
    shape = _Shape(model, phenotype, girths)
    target = torch.tensor([measurements["height"]] + [measurements[g] for g in girths], dtype=torch.float64)
    x0 = _solve_height(shape, shape.initial(), measurements["height"])
    # prior weights (metres of residual per unit of parameter): none on height, weak on the body-wide
    # phenotypes, the full prior on local changes
    prior_w = torch.tensor(
        [0.0, 0.1 * settings.prior, 0.5 * settings.prior, 0.5 * settings.prior, 0.1 * settings.prior]
        + [settings.prior] * len(girths),
        dtype=torch.float64,
    )
    solve = _least_squares(shape, faces, girths, target, x0, prior_w, x0, settings)
    rounds, steps, history = solve.rounds, solve.steps, list(solve.history)
    if solve.max_error > settings.tolerance and settings.continuation > 1:
        with torch.no_grad():
            v0 = shape.vertices(x0)
        g0 = section_girths(v0, faces, find_section_planes(v0, faces, names=tuple(girths)))
        start = torch.stack([body_height(v0)] + [g0[n] for n in girths]).to(torch.float64)
        x = x0
        for k in range(1, settings.continuation + 1):
            stage = start + (k / settings.continuation) * (target - start)
            staged = _least_squares(shape, faces, girths, stage, x, prior_w, x0, settings)
            x = staged.x
            rounds, steps, history = rounds + staged.rounds, steps + staged.steps, history + staged.history
        if staged.max_error < solve.max_error:
            solve = staged
    x = solve.x
    with torch.no_grad():
        v = shape.vertices(x)
    measured = measure_body(v, faces).to_dict()
    max_err = max(abs(measured[k] - val) for k, val in measurements.items())
    pheno, lc = shape.split(x)
    fit = AnnyFit(
        phenotype={k: float(pheno[i]) for i, k in enumerate(_PHENOTYPES)},
        local_changes={label: float(lc[i]) for i, label in enumerate(model.local_change_labels)},
        measured=measured,
        max_error=max_err,
        rounds=rounds,
        steps=steps,
        seconds=time.perf_counter() - t_start,
        history=history,
    )
    return fit, v


def reach_errors(requested: dict[str, float], measured: dict[str, float]) -> dict[str, float]:
    """Per-measurement error of a fitted body, measured minus requested, millimetres (rounded to 0.1)."""
    return {k: round(1000.0 * (measured[k] - val), 1) for k, val in requested.items()}


def _rig(model: anny.Anny, x_coeffs: torch.Tensor, offset: torch.Tensor) -> tuple[Skeleton, torch.Tensor]:
    """Skeleton (joints = bone heads, bones = parent links) and (J, V) skin weights of a fitted body.

    Joints carrying no skin weight and having no weighted descendant (the eye bones of the eyeless topology)
    are dropped; their weight (zero) is not redistributed.
    """
    with torch.no_grad():
        heads = _to_y_up(model.get_rest_model(x_coeffs)["rest_bone_heads"][0]) - offset
    labels = list(model.bone_labels)
    parents = list(model.bone_parents)
    num_v = model.template_vertices.shape[0]
    dense = torch.zeros(num_v, len(labels), dtype=torch.float64)
    dense.scatter_add_(1, model.vertex_bone_indices.long(), model.vertex_bone_weights.to(torch.float64))
    keep = (dense.sum(dim=0) > 0).tolist()
    for j in reversed(range(len(labels))):  # bones are topologically ordered: children after parents
        if keep[j] and parents[j] >= 0:
            keep[parents[j]] = True
    kept = [j for j in range(len(labels)) if keep[j]]
    new_index = {old: new for new, old in enumerate(kept)}
    bones = [(new_index[parents[j]], new_index[j]) for j in kept if parents[j] >= 0]
    skeleton = Skeleton(
        joints=heads[kept].clone(),
        bones=torch.tensor(bones, dtype=torch.long).reshape(-1, 2),
        names=[labels[j] for j in kept],
    )
    weights = dense[:, kept].T.contiguous()
    return skeleton, weights / weights.sum(dim=0, keepdim=True)


def _generate(measurements: dict[str, float], settings: FitSettings) -> dict:
    """Fit and assemble a body as a cache payload (float64 CPU tensors and plain data)."""
    model = load_anny_model()
    fit, v = fit_anny(measurements, settings)
    shape = _Shape(model, fit.phenotype, list(LOCAL_CHANGES))
    x = shape.initial()
    x[NUM_PHENO_FREE:] = torch.tensor([fit.local_changes[LOCAL_CHANGES[g]] for g in LOCAL_CHANGES])
    skeleton, weights = _rig(model, shape.coefficients(x).detach(), torch.zeros(3, dtype=v.dtype))
    # Body frame: feet at y = 0 and the root (pelvis) joint on the Y axis, so that garments placed around
    # the Y axis sit around the torso (a bounding-box centre would be pulled forward by the toes).
    root = skeleton.joints[skeleton.names.index("root") if "root" in skeleton.names else 0]
    offset = torch.stack([root[0], v[:, 1].min(), root[2]])
    vertices = v - offset
    skeleton = Skeleton(joints=skeleton.joints - offset, bones=skeleton.bones, names=skeleton.names)
    planes = find_section_planes(vertices, model.faces)
    landmarks = {name: p.seed.to(torch.float64) for name, p in planes.items()}
    landmarks["crown"] = vertices[int(torch.argmax(vertices[:, 1]))].clone()
    return {
        "vertices": vertices.detach().clone(),
        "faces": model.faces.clone().long(),
        "joints": skeleton.joints,
        "bones": skeleton.bones,
        "joint_names": list(skeleton.names),
        "skin_weights": weights,
        "landmark_names": list(landmarks),
        "landmarks": torch.stack(list(landmarks.values())),
        "params": {
            "generator": "anny",
            "anny_version": anny_version(),
            "fit_version": FIT_VERSION,
            "topology": TOPOLOGY,
            "requested": dict(measurements),
            "measured": fit.measured,
            "max_error": fit.max_error,
            "phenotype": fit.phenotype,
            "local_changes": fit.local_changes,
            "fit_seconds": fit.seconds,
            "fit_rounds": fit.rounds,
            "fit_steps": fit.steps,
        },
    }


def cache_description(measurements: dict[str, float], settings: FitSettings = FitSettings()) -> dict:
    """What a fitted body depends on (hashed into its cache key)."""
    return {
        "kind": "anny_body",
        "measurements": dict(sorted(measurements.items())),
        "anny_version": anny_version(),
        "fit_version": FIT_VERSION,
        "topology": TOPOLOGY,
        "settings": asdict(settings),
    }


def body_from_measurements(
    measurements: dict[str, float],
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
    cache: bool = True,
    settings: FitSettings = FitSettings(),
    closest: bool = False,
) -> Body:
    """An anny body whose own measurements match the request.

    Args:
        measurements: metres; ``height``, ``bust``, ``waist``, ``hips`` required; ``underbust``, ``thigh``,
            ``upper_arm``, ``neck``, ``wrist`` optional (see :data:`RANGES`).
        dtype: float dtype of the returned tensors.
        device: device of the returned tensors (fitting runs on the CPU).
        cache: read and write the disk cache (:mod:`torchgarment.body.cache`).
        settings: fit settings.
        closest: return the closest body the model reaches even when it misses the request by more than
            ``settings.accept`` (``params["reach_errors"]`` then tells by how much); otherwise such a request
            raises.

    Returns:
        A :class:`Body`: closed manifold mesh (V = 13,348 vertices), +Y up, metres, feet at y = 0, centred in
        x and z; skeleton of anny's bone heads (joint names kept); (J, V) skin weights; landmarks at the girth
        section seeds (``"bust"``, ...) and the ``"crown"``; ``params`` with the request, the measured values,
        the fitted anny parameters and the fit's timing, ``reach_errors`` (mm, measured minus requested) and
        ``reached`` (all within ``settings.accept``). ``params["cache_hit"]`` tells whether it came from
        the cache.

    Raises:
        InputError: bad names or values, or (without ``closest``) a request the model cannot reach.
    """
    request = validate_measurements(measurements)
    key = body_cache.cache_key(cache_description(request, settings))
    payload = body_cache.load_entry(key) if cache else None
    hit = payload is not None
    if payload is None:
        payload = _generate(request, settings)
        if cache:
            body_cache.store_entry(key, payload)
    params = dict(payload["params"])
    # the cache holds the closest body found; whether it is close enough is decided on every load
    errors = reach_errors(request, params["measured"])
    reached = max(abs(e) for e in errors.values()) <= 1000.0 * settings.accept
    if not (reached or closest):
        raise InputError(
            f"anny cannot reach these measurements within {1000 * settings.accept:.0f} mm (errors in mm: "
            f"{errors}); they may be an unusual combination: check them, or pass --closest for the closest "
            "body"
        )
    params["reach_errors"], params["reached"] = errors, reached
    params["cache_hit"] = hit
    params["cache_key"] = key
    body = Body(
        vertices=payload["vertices"],
        faces=payload["faces"],
        skeleton=Skeleton(payload["joints"], payload["bones"], list(payload["joint_names"])),
        skin_weights=payload["skin_weights"],
        landmarks={n: payload["landmarks"][i] for i, n in enumerate(payload["landmark_names"])},
        params=params,
    )
    return body.to(device=device, dtype=dtype)
