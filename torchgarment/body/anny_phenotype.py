"""Anny bodies straight from phenotype parameters: random realistic adults in one forward pass each.

:func:`~torchgarment.body.anny_body.body_from_measurements` fits anny to tape measurements (5-50 s per body);
a data set of hundreds of bodies (the data-driven fitting of Gillies et al. 2004) instead samples anny's
phenotype parameters directly and evaluates the model once per batch (measured: 0.06 s per body for
sampling with the stature solve, 0.01-0.02 s per body for the vertices, on an idle 2-core CPU).
Bodies are in the frame of the fitted ones: +Y up, front +Z, metres, feet at ``y = 0``, the root (pelvis)
joint on the Y axis, topology :data:`~torchgarment.body.anny_body.TOPOLOGY` (13,348 vertices).

Sampling (:func:`sample_phenotypes`, all draws independent):

* ``gender`` uniform in :attr:`PhenotypeRanges.gender` (anny: 0 male, 1 female).
* ``age``: years uniform in :attr:`PhenotypeRanges.age_years`, mapped to anny's age (piecewise linear between
  MakeHuman's anchors: 11 years at 1/3, 25 years at 2/3, 90 years at 1).
* stature: normal with the mean and standard deviation of the US adult population, truncated at
  :attr:`PhenotypeRanges.stature_clip` standard deviations; anny's ``height`` phenotype is solved for it by
  batched secant iterations (the stature is monotonic in that parameter).
* ``weight``, ``muscle``, ``proportions``, ``cupsize``, ``firmness`` and the race mix uniform in their ranges.
* girths: anny's phenotypes alone give adult waists of at most about 83 cm, well below the US adult mean
  (NHANES: about 98 cm for women), so a shared "girth factor" drives the MakeHuman local changes
  ``measure-<girth>-circ-incr`` (see :attr:`PhenotypeRanges.girth` and :data:`GIRTH_GAINS`).

Where the ranges come from: the stature means and standard deviations are those of adults aged 20 and over
in NHANES 2015-2018 (C. D. Fryar, M. D. Carroll, Q. Gu, J. Afful, C. L. Ogden, "Anthropometric reference data
for children and adults: United States, 2015-2018", National Center for Health Statistics, Vital Health Stat
3(46), 2021): women mean 161.3 cm, men 175.3 cm; the standard deviations (about 7 cm for both) follow from
the published 5th-95th percentile spread (about 23 cm) of the same tables. The girth acceptance ranges
(:data:`GIRTH_RANGES`) bracket the 5th-95th percentiles of the same report (adult waist circumference about
75-125 cm for women, 80-130 cm for men) and of the US Army's ANSUR II survey (C. C. Gordon et al., "2012
Anthropometric Survey of U.S. Army Personnel", NATICK/TR-15/007, 2014) for chest and buttock (hip) girths,
widened by a few centimetres. (These figures are quoted from the cited reports as remembered when this module
was written; they could not be re-checked against the reports in the offline environment it was built in, so
treat them as approximate and check them before relying on the exact values.) The ``weight`` range and the
girth factor were chosen by measuring the sampled bodies (:func:`torchgarment.body.measure.measure_body`).
Measured on 40 default (female) samples, seed 1: stature mean 159.5 cm (5th-95th percentile 148.6-169.0), bust
93.7 (82.7-105.7), waist 75.6 (65.6-85.5), hips 104.0 (93.3-116.6) cm; 39 of 40 inside :data:`GIRTH_RANGES`
(one waist of 59.8 cm). Limitation: the statures match NHANES, but the girths span roughly the US Misses size
chart (sizes 6-20) rather than the whole US population (NHANES mean adult female waist about 98 cm): anny's
phenotypes and MakeHuman local changes within their range do not reach the largest waists with a plausible
shape. Bodies can be checked with :func:`check_realistic`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import torch

from torchgarment.body.anny_body import (
    _PHENOTYPES,
    DEFAULT_PHENOTYPE,
    LOCAL_CHANGE_RANGE,
    LOCAL_CHANGES,
    TOPOLOGY,
    _rig,
    _to_y_up,
    anny_version,
    load_anny_model,
)
from torchgarment.body.body import Body
from torchgarment.errors import InputError
from torchgarment.options import OptionEnum

if TYPE_CHECKING:
    import anny

PHENOTYPE_NAMES: tuple[str, ...] = _PHENOTYPES
"""Anny's phenotype labels (``phenotypes="all"``), in the model's order."""

AGE_ANCHORS_YEARS = ((11.0, 1.0 / 3.0), (25.0, 2.0 / 3.0), (90.0, 1.0))
"""(years, anny age) anchors of MakeHuman's child, young and old targets (anny interpolates linearly)."""

GIRTH_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "female": {"height": (1.40, 1.85), "bust": (0.75, 1.40), "waist": (0.60, 1.35), "hips": (0.82, 1.45)},
    "male": {"height": (1.52, 1.98), "bust": (0.82, 1.40), "waist": (0.65, 1.40), "hips": (0.82, 1.35)},
}
"""Realistic adult ranges (metres, wider than the 5th-95th percentiles of NHANES 2015-2018 and ANSUR II; see
the module docstring) used by :func:`check_realistic`."""


LOCAL_CHANGE_NAMES: tuple[str, ...] = tuple(LOCAL_CHANGES.values())
"""Labels of the MakeHuman local changes a phenotype dict may also set (anny_body's girth changes)."""

GIRTH_GAINS: dict[str, float] = {"bust": 0.5, "underbust": 0.5, "waist": 1.2, "hips": 0.8, "thigh": 0.8,
                                 "upper_arm": 0.8}
"""Local change per unit of the shared girth factor, per girth (waist grows fastest, as in heavier adults)."""


class Population(OptionEnum):
    """Which adults :class:`PhenotypeRanges` describes."""

    FEMALE = "female"
    MALE = "male"

    @classmethod
    def aliases(cls) -> dict[str, str]:
        return {"women": "female", "men": "male", "f": "female", "m": "male"}


@dataclass(frozen=True)
class PhenotypeRanges:
    """Sampling ranges of :func:`sample_phenotypes` (see the module docstring for the sources).

    Attributes:
        population: female or male adults (chooses :data:`GIRTH_RANGES` in :func:`check_realistic`).
        gender: anny gender range (0 male, 1 female).
        age_years: age range in years (adults).
        stature_mean, stature_sd: mean and standard deviation of the stature, metres.
        stature_clip: the stature normal is truncated at this many standard deviations.
        weight, muscle, proportions, cupsize, firmness: anny phenotype ranges in [0, 1].
        race: range of each of anny's race weights (african, asian, caucasian).
        girth: range of the shared girth factor ``u``: the MakeHuman local change of girth ``g`` is
            ``u * GIRTH_GAINS[g]`` plus uniform noise in ``[-girth_noise, girth_noise]``, clamped to anny's
            local-change range (anny's phenotypes alone stop at waists of about 83 cm, below the US mean).
        girth_noise: half-width of the per-girth noise.
    """

    population: Population = Population.FEMALE
    gender: tuple[float, float] = (0.9, 1.0)
    age_years: tuple[float, float] = (25.0, 65.0)
    stature_mean: float = 1.613
    stature_sd: float = 0.070
    stature_clip: float = 2.0
    weight: tuple[float, float] = (0.3, 0.9)
    muscle: tuple[float, float] = (0.3, 0.7)
    proportions: tuple[float, float] = (0.3, 0.7)
    cupsize: tuple[float, float] = (0.3, 0.8)
    firmness: tuple[float, float] = (0.3, 0.7)
    race: tuple[float, float] = (0.0, 1.0)
    girth: tuple[float, float] = (-0.3, 1.2)
    girth_noise: float = 0.2

    @classmethod
    def female(cls) -> "PhenotypeRanges":
        """US adult women (NHANES 2015-2018 stature 161.3 cm)."""
        return cls()

    @classmethod
    def male(cls) -> "PhenotypeRanges":
        """US adult men (NHANES 2015-2018 stature 175.3 cm); cup size is irrelevant for male bodies."""
        return cls(population=Population.MALE, gender=(0.0, 0.1), stature_mean=1.753, stature_sd=0.072,
                   cupsize=(0.4, 0.6))

    @classmethod
    def for_population(cls, population: Population | str) -> "PhenotypeRanges":
        """The default ranges of ``"female"`` or ``"male"`` adults."""
        return cls.male() if Population.resolve(population) is Population.MALE else cls.female()

    def __post_init__(self) -> None:
        """Validate at construction (and on ``dataclasses.replace``)."""
        self.validate()

    def validate(self) -> None:
        """Raise :class:`InputError` for empty, reversed or out-of-range intervals."""
        for name in ("gender", "weight", "muscle", "proportions", "cupsize", "firmness", "race"):
            lo, hi = getattr(self, name)
            if not (0.0 <= lo <= hi <= 1.0):
                raise InputError(f"PhenotypeRanges.{name} must satisfy 0 <= lo <= hi <= 1, got {(lo, hi)}")
        lo, hi = self.age_years
        if not (AGE_ANCHORS_YEARS[0][0] <= lo <= hi <= AGE_ANCHORS_YEARS[-1][0]):
            raise InputError(f"PhenotypeRanges.age_years must lie in [11, 90] years, got {(lo, hi)}")
        if not (LOCAL_CHANGE_RANGE[0] <= self.girth[0] <= self.girth[1] <= LOCAL_CHANGE_RANGE[1]
                and 0.0 <= self.girth_noise <= 1.0):
            raise InputError(f"PhenotypeRanges.girth must be an interval in {LOCAL_CHANGE_RANGE} and "
                             f"girth_noise in [0, 1], got {self.girth} and {self.girth_noise}")
        if not (0.8 < self.stature_mean < 2.3 and 0.0 <= self.stature_sd < 0.3 and self.stature_clip >= 0):
            raise InputError("PhenotypeRanges: stature_mean must be in (0.8, 2.3) m, stature_sd in [0, 0.3) "
                             "m and stature_clip >= 0")


def age_from_years(years: torch.Tensor) -> torch.Tensor:
    """Anny ``age`` parameter of an age in years (linear between MakeHuman's anchors), any shape."""
    (y0, a0), (y1, a1), (y2, a2) = AGE_ANCHORS_YEARS
    young = a0 + (years - y0) * (a1 - a0) / (y1 - y0)
    old = a1 + (years - y1) * (a2 - a1) / (y2 - y1)
    return torch.where(years < y1, young, old)


def _framed(model: anny.Anny, coeffs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, V, 3) Y-up vertices in the body frame and the (B, 3) offsets subtracted (root on Y, feet at 0)."""
    with torch.no_grad():
        rest = model.get_rest_model(coeffs)
        v = _to_y_up(model.get_rest_vertices(coeffs))
        heads = _to_y_up(rest["rest_bone_heads"])
    labels = list(model.bone_labels)
    root = heads[:, labels.index("root") if "root" in labels else 0]
    offset = torch.stack([root[:, 0], v[..., 1].amin(dim=1), root[:, 2]], dim=1)
    return v - offset[:, None], offset


def _as_matrix(phenotypes: list[dict]) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, P) phenotype and (B, L) local-change matrices (float64) from dicts; missing phenotypes take anny's
    neutral 0.5 (gender too) and the adult age, missing local changes 0."""
    if isinstance(phenotypes, dict):
        phenotypes = [phenotypes]
    if not phenotypes:
        raise InputError("no phenotypes given")
    rows, lc_rows = [], []
    for ph in phenotypes:
        if not isinstance(ph, dict):
            raise InputError(f"a phenotype must be a dict of anny parameters, got {type(ph).__name__}")
        unknown = sorted(set(ph) - set(PHENOTYPE_NAMES) - set(LOCAL_CHANGE_NAMES))
        if unknown:
            raise InputError(f"unknown anny parameter(s) {unknown}; accepted: {', '.join(PHENOTYPE_NAMES)} "
                             f"and the local changes {', '.join(LOCAL_CHANGE_NAMES)}")
        full = dict(DEFAULT_PHENOTYPE, gender=0.5)
        full.update(ph)
        row, lc_row = [], []
        for name in PHENOTYPE_NAMES + LOCAL_CHANGE_NAMES:
            try:
                value = float(full.get(name, 0.0))
            except (TypeError, ValueError):
                raise InputError(f"anny parameter {name!r} must be a number, got {full[name]!r}") from None
            lo, hi = (-1.0 / 3.0, 1.0) if name == "age" else (0.0, 1.0)
            if name in LOCAL_CHANGE_NAMES:
                lo, hi = LOCAL_CHANGE_RANGE
            if not (math.isfinite(value) and lo <= value <= hi):
                raise InputError(f"anny parameter {name}={value!r} is outside [{lo:.3g}, {hi:.3g}]")
            (row if name in PHENOTYPE_NAMES else lc_row).append(value)
        rows.append(row)
        lc_rows.append(lc_row)
    return (torch.tensor(rows, dtype=torch.float64),
            torch.tensor(lc_rows, dtype=torch.float64).reshape(len(rows), -1))


def _coefficients(model: anny.Anny, pheno: torch.Tensor, lc: torch.Tensor | None = None) -> torch.Tensor:
    """Blend-shape coefficients of a (B, P) phenotype batch with (B, L) local changes (in
    :data:`LOCAL_CHANGE_NAMES` order; None: none)."""
    full = pheno.new_zeros(pheno.shape[0], len(model.local_change_labels))
    if lc is not None and lc.shape[1]:
        labels = list(model.local_change_labels)
        full[:, [labels.index(n) for n in LOCAL_CHANGE_NAMES]] = lc
    return model._get_phenotype_blendshape_coefficients(pheno, full, pheno.new_zeros(pheno.shape[0], 0))


def vertices_from_phenotypes(phenotypes: list[dict], batch_size: int = 32) -> torch.Tensor:
    """Rest vertices of anny bodies, one forward pass per batch.

    Args:
        phenotypes: N dicts of anny phenotype values (names :data:`PHENOTYPE_NAMES`; missing ones default to
            anny's neutral 0.5 and the adult age 2/3, gender 0.5).
        batch_size: bodies per forward pass.

    Returns:
        (N, V, 3) float64 CPU vertices in metres, +Y up, feet at y = 0, root joint on the Y axis.

    Raises:
        InputError: unknown names or values out of range.
    """
    if isinstance(phenotypes, dict):
        phenotypes = [phenotypes]
    pheno, lc = _as_matrix([_strip(ph) if isinstance(ph, dict) else ph for ph in phenotypes])
    model = load_anny_model()
    out = [_framed(model, _coefficients(model, pheno[i:i + batch_size], lc[i:i + batch_size]))[0]
           for i in range(0, len(pheno), batch_size)]
    return torch.cat(out)


def _solve_stature(model: anny.Anny, pheno: torch.Tensor, lc: torch.Tensor, target: torch.Tensor,
                   iterations: int = 8) -> torch.Tensor:
    """Batched secant on the ``height`` phenotype column so that the stature (max y - min y) hits
    ``target``."""
    hi_index = PHENOTYPE_NAMES.index("height")

    def stature(t: torch.Tensor) -> torch.Tensor:
        p = pheno.clone()
        p[:, hi_index] = t
        with torch.no_grad():
            v = _to_y_up(model.get_rest_vertices(_coefficients(model, p, lc)))
        return v[..., 1].amax(dim=1) - v[..., 1].amin(dim=1)

    t0, t1 = torch.full_like(target, 0.2), torch.full_like(target, 0.8)
    h0, h1 = stature(t0), stature(t1)
    for _ in range(iterations):
        if float((h1 - target).abs().max()) < 1e-4:
            break
        slope = (h1 - h0) / torch.where((t1 - t0).abs() > 1e-12, t1 - t0, torch.full_like(t1, 1e-12))
        t_new = (t1 + (target - h1) / torch.where(slope.abs() > 1e-9, slope, torch.full_like(slope, 1e-9)))
        t_new = t_new.clamp(0.0, 1.0)
        t0, h0, t1 = t1, h1, t_new
        h1 = stature(t1)
    return t1


def sample_phenotypes(n: int, seed: int = 0, ranges: PhenotypeRanges | None = None,
                      batch_size: int = 64) -> list[dict[str, float]]:
    """Sample ``n`` realistic adult anny phenotypes (see the module docstring).

    Args:
        n: number of bodies (>= 1).
        seed: seed of the torch generator (same seed, same bodies).
        ranges: sampling ranges; default :meth:`PhenotypeRanges.female`.
        batch_size: bodies per forward pass of the stature solve.

    Returns:
        ``n`` dicts with every name of :data:`PHENOTYPE_NAMES` (floats in anny's units) plus ``"age_years"``
        and ``"stature"`` (the sampled stature in metres, reached within 0.1 mm unless clamped at anny's
        height range). Pass them to :func:`body_from_phenotype` or :func:`vertices_from_phenotypes` (the two
        extra keys are ignored there).

    Raises:
        InputError: ``n < 1`` or bad ranges.
    """
    ranges = ranges if ranges is not None else PhenotypeRanges.female()
    ranges.validate()
    if not isinstance(n, int) or n < 1:
        raise InputError(f"number of bodies must be a positive integer, got {n!r}")
    g = torch.Generator().manual_seed(int(seed))

    def uniform(lo_hi: tuple[float, float], size: int = n) -> torch.Tensor:
        lo, hi = lo_hi
        return lo + (hi - lo) * torch.rand(size, generator=g, dtype=torch.float64)

    years = uniform(ranges.age_years)
    z = torch.randn(n, generator=g, dtype=torch.float64).clamp(-ranges.stature_clip, ranges.stature_clip)
    stature = ranges.stature_mean + ranges.stature_sd * z
    cols = {
        "gender": uniform(ranges.gender),
        "age": age_from_years(years),
        "muscle": uniform(ranges.muscle),
        "weight": uniform(ranges.weight),
        "height": torch.full((n,), 0.5, dtype=torch.float64),
        "proportions": uniform(ranges.proportions),
        "cupsize": uniform(ranges.cupsize),
        "firmness": uniform(ranges.firmness),
        "african": uniform(ranges.race),
        "asian": uniform(ranges.race),
        "caucasian": uniform(ranges.race),
    }
    pheno = torch.stack([cols[k] for k in PHENOTYPE_NAMES], dim=1)
    girth = uniform(ranges.girth)
    noise = ranges.girth_noise * (2.0 * torch.rand(n, len(GIRTH_GAINS), generator=g, dtype=torch.float64)
                                  - 1.0)
    gains = torch.tensor(list(GIRTH_GAINS.values()), dtype=torch.float64)
    lc = (girth[:, None] * gains + noise).clamp(*LOCAL_CHANGE_RANGE)
    lc_full = torch.zeros(n, len(LOCAL_CHANGE_NAMES), dtype=torch.float64)
    lc_full[:, [LOCAL_CHANGE_NAMES.index(LOCAL_CHANGES[k]) for k in GIRTH_GAINS]] = lc
    model = load_anny_model()
    hi = PHENOTYPE_NAMES.index("height")
    for i in range(0, n, batch_size):
        sl = slice(i, i + batch_size)
        pheno[sl, hi] = _solve_stature(model, pheno[sl], lc_full[sl], stature[sl])
    return [
        {**{k: float(pheno[b, j]) for j, k in enumerate(PHENOTYPE_NAMES)},
         **{k: float(lc_full[b, j]) for j, k in enumerate(LOCAL_CHANGE_NAMES)},
         "age_years": float(years[b]), "stature": float(stature[b])}
        for b in range(n)
    ]


def _strip(phenotype: dict) -> dict:
    return {k: v for k, v in phenotype.items() if k not in ("age_years", "stature")}


def body_from_phenotype(
    phenotype: dict,
    dtype: torch.dtype = torch.float64,
    device: torch.device | str | None = None,
    landmarks: bool = False,
) -> Body:
    """An anny body from phenotype parameters, rigged like the fitted bodies.

    Args:
        phenotype: anny phenotype values by name (:data:`PHENOTYPE_NAMES`; missing ones default to 0.5 and the
            adult age 2/3; the extra keys ``age_years`` and ``stature`` of :func:`sample_phenotypes` are
            ignored).
        dtype: float dtype of the returned tensors. device: their device (generation runs on the CPU).
        landmarks: also find the girth section planes (:func:`~torchgarment.body.measure.find_section_planes`,
            about 0.4 s) and store their seeds and the ``"crown"`` as landmarks, as fitted bodies have.

    Returns:
        A :class:`Body` (V = 13,348 vertices, +Y up, metres, feet at y = 0, root joint on the Y axis) with
        anny's skeleton (bone heads) and (J, V) skin weights; ``params`` holds the phenotype.

    Raises:
        InputError: unknown names or out-of-range values.
    """
    pheno, lc = _as_matrix([_strip(phenotype)])
    model = load_anny_model()
    coeffs = _coefficients(model, pheno, lc)
    v, offset = _framed(model, coeffs)
    vertices = v[0]
    skeleton, weights = _rig(model, coeffs.detach(), offset[0])
    marks: dict[str, torch.Tensor] = {}
    if landmarks:
        from torchgarment.body.measure import find_section_planes

        planes = find_section_planes(vertices, model.faces)
        marks = {name: p.seed.to(torch.float64) for name, p in planes.items()}
        marks["crown"] = vertices[int(torch.argmax(vertices[:, 1]))].clone()
    params = {
        "generator": "anny-phenotype",
        "anny_version": anny_version(),
        "topology": TOPOLOGY,
        "phenotype": {k: float(pheno[0, j]) for j, k in enumerate(PHENOTYPE_NAMES)},
        "local_changes": {k: float(lc[0, j]) for j, k in enumerate(LOCAL_CHANGE_NAMES)},
    }
    body = Body(vertices=vertices.clone(), faces=model.faces.clone().long(), skeleton=skeleton,
                skin_weights=weights, landmarks=marks, params=params)
    return body.to(device=device, dtype=dtype)


def check_realistic(measurements: dict[str, float],
                    population: Population | str = Population.FEMALE) -> list[str]:
    """Names of the measurements outside :data:`GIRTH_RANGES` (empty list: realistic).

    Args:
        measurements: ``measure_body(...).to_dict()`` of a body (metres).
        population: ``"female"`` or ``"male"``.
    """
    bounds = GIRTH_RANGES[Population.resolve(population).value]
    return [k for k, (lo, hi) in bounds.items() if not lo <= float(measurements[k]) <= hi]


def ranges_description(ranges: PhenotypeRanges) -> dict:
    """JSON-ready description of the ranges (for provenance and cache keys)."""
    d = asdict(ranges)
    d["population"] = Population.resolve(ranges.population).value
    return d


__all__ = [
    "GIRTH_GAINS",
    "LOCAL_CHANGE_NAMES",
    "GIRTH_RANGES",
    "PHENOTYPE_NAMES",
    "PhenotypeRanges",
    "Population",
    "age_from_years",
    "body_from_phenotype",
    "check_realistic",
    "ranges_description",
    "sample_phenotypes",
    "vertices_from_phenotypes",
]
