"""Headless PNG renders of bodies and garments with a numpy software rasterizer (no OpenGL, no display), and
:func:`contact_sheet` (many results' pictures as labelled thumbnails on one PNG).

Example::

    from torchgarment.render import MeshLayer, View, render_views

    render_views(
        [MeshLayer(body_v, body_f), MeshLayer(cloth_v, cloth_f, scalars=strain, label="strain")],
        "out/fit.png",
        title="fitted dress",
    )
"""

from torchgarment.render.colormap import ScalarColors
from torchgarment.render.figure import FigureLayout, render_views
from torchgarment.render.image import RenderStyle, render_image
from torchgarment.render.layers import DEFAULT_COLOR, MeshLayer, ScalarLocation
from torchgarment.render.raster import Fragments, rasterize
from torchgarment.render.sheet import contact_sheet
from torchgarment.render.views import OrthoCamera, View, fit_camera

__all__ = [
    "DEFAULT_COLOR",
    "FigureLayout",
    "Fragments",
    "MeshLayer",
    "OrthoCamera",
    "RenderStyle",
    "ScalarColors",
    "ScalarLocation",
    "View",
    "contact_sheet",
    "fit_camera",
    "rasterize",
    "render_image",
    "render_views",
]
