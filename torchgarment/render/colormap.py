"""Mapping scalar fields to colours through matplotlib colormaps."""

from __future__ import annotations

from dataclasses import dataclass

import matplotlib
import matplotlib.colors as mcolors
import numpy as np

from torchgarment.errors import InputError


@dataclass(frozen=True)
class ScalarColors:
    """A colormap with its normalisation; maps scalars to RGB in [0, 1].

    Attributes:
        cmap: matplotlib colormap name.
        vmin: value drawn with the first colour (clipped below).
        vmax: value drawn with the last colour (clipped above).
        log: logarithmic scale (vmin > 0 required).
        label: colourbar label.
    """

    cmap: str
    vmin: float
    vmax: float
    log: bool = False
    label: str | None = None

    def norm(self) -> mcolors.Normalize:
        """The matplotlib normalisation (clipped)."""
        if self.log:
            return mcolors.LogNorm(vmin=self.vmin, vmax=self.vmax, clip=True)
        return mcolors.Normalize(vmin=self.vmin, vmax=self.vmax, clip=True)

    def colormap(self) -> mcolors.Colormap:
        """The matplotlib colormap object."""
        return matplotlib.colormaps[self.cmap]

    def __call__(self, values: np.ndarray) -> np.ndarray:
        """Map (N,) scalars to (N, 3) RGB in [0, 1]."""
        values = np.asarray(values, dtype=np.float64)
        if self.log:
            values = np.maximum(values, self.vmin)
        t = np.asarray(self.norm()(values), dtype=np.float64)
        return np.asarray(self.colormap()(t), dtype=np.float64)[..., :3]


def make_scalar_colors(
    scalars: np.ndarray,
    cmap: str,
    vmin: float | None,
    vmax: float | None,
    log: bool,
    label: str | None,
) -> ScalarColors:
    """Build a :class:`ScalarColors`, taking missing limits from the data.

    Args:
        scalars: (N,) finite values (N >= 1).
        cmap: matplotlib colormap name.
        vmin: lower limit, or None for the data minimum (the smallest positive value when ``log``).
        vmax: upper limit, or None for the data maximum.
        log: logarithmic scale.
        label: colourbar label.

    Returns:
        The colour mapping.
    """
    if cmap not in matplotlib.colormaps:
        raise InputError(f"unknown matplotlib colormap {cmap!r}")
    values = np.asarray(scalars, dtype=np.float64).ravel()
    if log:
        values = values[values > 0]
        if values.size == 0 and (vmin is None or vmax is None):
            raise InputError("log scale needs positive scalars or explicit positive vmin/vmax")
    lo = float(values.min()) if vmin is None else float(vmin)
    hi = float(values.max()) if vmax is None else float(vmax)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise InputError(f"colour limits must be finite, got vmin={lo}, vmax={hi}")
    if log and lo <= 0:
        raise InputError(f"log scale needs vmin > 0, got {lo}")
    if hi < lo:
        raise InputError(f"vmax ({hi}) is smaller than vmin ({lo})")
    if hi == lo:
        # A constant field: widen symmetrically so the colour is the middle of the map.
        pad = abs(lo) * 0.5 if lo != 0 else 0.5
        lo, hi = (lo / 2.0, lo * 2.0) if log else (lo - pad, hi + pad)
    return ScalarColors(cmap=cmap, vmin=lo, vmax=hi, log=log, label=label)
