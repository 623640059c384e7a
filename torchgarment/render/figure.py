"""Compose several views of a scene, titles and colourbars into one PNG (matplotlib, Agg, no display)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import matplotlib.cm
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from torchgarment.errors import InputError
from torchgarment.io.atomic import atomic_path
from torchgarment.render.colormap import ScalarColors
from torchgarment.render.image import RenderStyle, check_size, render_prepared, scene_points
from torchgarment.render.layers import MeshLayer, prepare_layers
from torchgarment.render.views import View, fit_camera

_DPI = 100


@dataclass(frozen=True)
class FigureLayout:
    """Pixel layout of the figure written by :func:`render_views`.

    Attributes:
        panel: (width, height) of each view in pixels.
        num_views: number of views, side by side.
        num_colorbars: number of colourbars, right of the views.
        has_title: whether a title band sits above the view labels.
        label_band: height of the band with the view names, pixels.
        title_band: height of the title band, pixels.
        colorbar_band: width taken by each colourbar with its ticks and label, pixels.
    """

    panel: tuple[int, int]
    num_views: int
    num_colorbars: int
    has_title: bool
    label_band: int = 30
    title_band: int = 36
    colorbar_band: int = 110

    @property
    def header(self) -> int:
        """Height above the views, pixels."""
        return self.label_band + (self.title_band if self.has_title else 0)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the whole PNG in pixels."""
        w, h = self.panel
        return self.num_views * w + self.num_colorbars * self.colorbar_band, h + self.header


def render_views(
    layers: list[MeshLayer],
    path: str | os.PathLike,
    views: tuple[View, ...] = (View.FRONT, View.SIDE, View.BACK),
    size: tuple[int, int] = (512, 768),
    title: str | None = None,
    *,
    style: RenderStyle = RenderStyle(),
) -> Path:
    """Render the scene from several views side by side and write a PNG atomically.

    All views share one scale (pixels per metre). Each scalar-coloured layer with a distinct colour mapping
    gets a colourbar on the right. The PNG measures :attr:`FigureLayout.size` pixels: ``len(views) * W +
    110 * num_colorbars`` wide and ``H + 30`` high (``+ 36`` more with a title).

    Args:
        layers: meshes to draw (at least one).
        path: destination ``.png`` file; parent folders are created.
        views: the views, left to right (at least one).
        size: (width, height) of each view in pixels.
        title: optional title above the views.
        style: lighting and drawing options.

    Returns:
        The path written.

    Raises:
        InputError: empty scene or views, malformed meshes, a path that does not end in ``.png``.
    """
    path = Path(path)
    if path.suffix.lower() != ".png":
        raise InputError(f"render_views writes PNG files; {path} does not end in .png")
    views = tuple(View(v) for v in views)
    if len(views) == 0:
        raise InputError("render_views needs at least one view")
    prepared = prepare_layers(layers)
    width, height = check_size(size)
    points = scene_points(prepared)
    images = []
    for v in views:
        cam = fit_camera(points, v, (width, height), style.margin, views_for_scale=views)
        images.append(render_prepared(prepared, cam, style))

    bars: list[ScalarColors] = []
    for p in prepared:
        if p.colors is not None and p.colors not in bars:
            bars.append(p.colors)
    layout = FigureLayout((width, height), len(views), len(bars), title is not None)
    fig = _compose(images, views, bars, layout, title, style)
    with atomic_path(path) as tmp:
        FigureCanvasAgg(fig)
        fig.savefig(tmp, dpi=_DPI, format="png", facecolor=fig.get_facecolor())
    return path


def _compose(
    images: list[np.ndarray],
    views: tuple[View, ...],
    bars: list[ScalarColors],
    layout: FigureLayout,
    title: str | None,
    style: RenderStyle,
) -> Figure:
    total_w, total_h = layout.size
    w, h = layout.panel
    fig = Figure(figsize=(total_w / _DPI, total_h / _DPI), dpi=_DPI, facecolor=style.background)

    def rect(x: float, y_top: float, rw: float, rh: float) -> list[float]:
        """Figure-fraction rectangle from a pixel box measured from the top-left corner."""
        return [x / total_w, 1.0 - (y_top + rh) / total_h, rw / total_w, rh / total_h]

    for i, (img, v) in enumerate(zip(images, views)):
        ax = fig.add_axes(rect(i * w, layout.header, w, h))
        ax.imshow(img, interpolation="nearest", aspect="auto")
        ax.set_axis_off()
        fig.text(
            (i * w + 0.5 * w) / total_w,
            1.0 - (layout.header - 0.5 * layout.label_band) / total_h,
            v.value,
            ha="center",
            va="center",
            fontsize=12,
            color="0.25",
        )
    if title is not None:
        fig.text(0.5, 1.0 - 0.5 * layout.title_band / total_h, title, ha="center", va="center", fontsize=14)

    bar_h = 0.7 * h
    for j, sc in enumerate(bars):
        x0 = layout.num_views * w + j * layout.colorbar_band + 14
        cax = fig.add_axes(rect(x0, layout.header + 0.5 * (h - bar_h), 16, bar_h))
        mappable = matplotlib.cm.ScalarMappable(norm=sc.norm(), cmap=sc.colormap())
        cb = fig.colorbar(mappable, cax=cax)
        cb.ax.tick_params(labelsize=9)
        if sc.label:
            cb.set_label(sc.label, fontsize=10)
    return fig
