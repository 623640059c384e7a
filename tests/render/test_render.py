"""Tests of the software renderer: coverage, depth order, colours, back faces, PNG output, errors."""

from __future__ import annotations

import time

import matplotlib
import numpy as np
import pytest
import torch
import trimesh
from PIL import Image

from torchgarment.errors import InputError
from torchgarment.render import (
    FigureLayout,
    MeshLayer,
    RenderStyle,
    ScalarLocation,
    View,
    fit_camera,
    rasterize,
    render_image,
    render_views,
)

# Ambient light only: pixels show the unlit base colour exactly.
FLAT = RenderStyle(ambient=1.0, key=0.0, fill=0.0, supersample=1)


def _covered(img: np.ndarray) -> np.ndarray:
    return (img != 255).any(axis=2)


def _cube() -> tuple[np.ndarray, np.ndarray]:
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    return np.asarray(box.vertices), np.asarray(box.faces)


def _sphere(center=(0.0, 0.0, 0.0), radius=1.0) -> tuple[np.ndarray, np.ndarray]:
    s = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    return np.asarray(s.vertices) + np.asarray(center), np.asarray(s.faces)


def test_cube_covers_expected_fraction():
    v, f = _cube()
    img = render_image([MeshLayer(v, f)], View.FRONT, size=(200, 200), style=RenderStyle(supersample=1))
    assert img.shape == (200, 200, 3) and img.dtype == np.uint8
    # The unit cube fills the image minus a 5 % margin on each side: 180 x 180 pixels.
    assert abs(_covered(img).mean() - 0.81) < 0.005


@pytest.mark.parametrize("view", list(View))
def test_sphere_covers_disc(view):
    v, f = _sphere()
    img = render_image([MeshLayer(v, f)], view, size=(200, 160), style=RenderStyle(supersample=1))
    assert img.shape == (160, 200, 3)
    radius_px = 0.5 * 160 * 0.9
    expected = np.pi * radius_px**2 / (200 * 160)
    assert abs(_covered(img).mean() - expected) / expected < 0.02
    # The disc is centred.
    rows, cols = np.nonzero(_covered(img))
    assert abs(rows.mean() - 79.5) < 1.0 and abs(cols.mean() - 99.5) < 1.0


def test_subdivided_square_has_no_cracks():
    """A square cut into many small triangles covers exactly the pixels of the same square in 2 triangles."""
    n = 37
    g = np.linspace(0.0, 1.0, n + 1)
    x, y = np.meshgrid(g, g)
    rng = np.random.default_rng(0)
    jitter = rng.uniform(-0.3, 0.3, (n + 1, n + 1, 2)) / n
    jitter[[0, -1], :, :] = 0.0
    jitter[:, [0, -1], :] = 0.0
    v = np.stack([x + jitter[..., 0], y + jitter[..., 1], np.zeros_like(x)], axis=-1).reshape(-1, 3)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    f = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    two = (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float), np.array([[0, 1, 3], [0, 3, 2]]))
    cam = fit_camera(v, View.FRONT, (301, 257), margin=0.1)
    fine = render_image([MeshLayer(v, f)], View.FRONT, (301, 257), style=FLAT, camera=cam)
    coarse = render_image([MeshLayer(*two)], View.FRONT, (301, 257), style=FLAT, camera=cam)
    assert _covered(coarse).sum() > 200 * 200
    np.testing.assert_array_equal(_covered(fine), _covered(coarse))


def test_depth_order_front_and_back():
    red = MeshLayer(*_sphere((0.0, 0.0, 1.5), 0.5), color=(1.0, 0.0, 0.0))
    blue = MeshLayer(*_sphere((0.0, 0.0, -1.5), 0.5), color=(0.0, 0.0, 1.0))
    for layers in ([red, blue], [blue, red]):  # drawing order must not matter
        front = render_image(layers, View.FRONT, size=(64, 64))
        back = render_image(layers, View.BACK, size=(64, 64))
        cf, cb = front[32, 32].astype(int), back[32, 32].astype(int)
        assert cf[0] > 150 and cf[2] < 30, cf
        assert cb[2] > 150 and cb[0] < 30, cb
    # From the side the spheres sit next to each other: red (+Z) on the left when looking from +X.
    side = render_image([red, blue], View.SIDE, size=(128, 64), style=FLAT)
    left, right = side[32, :64].astype(int), side[32, 64:].astype(int)
    is_red = lambda px: (px[:, 0] == 255) & (px[:, 2] == 0)  # noqa: E731
    is_blue = lambda px: (px[:, 2] == 255) & (px[:, 0] == 0)  # noqa: E731
    assert is_red(left).sum() > 20 and is_blue(left).sum() == 0
    assert is_blue(right).sum() > 20 and is_red(right).sum() == 0


def test_face_scalars_map_to_colormap():
    # Two separate unit squares side by side, facing the viewer (+Z); face scalars 0, 0, 1, 1.
    v = np.array(
        [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0], [3, 0, 0], [3, 1, 0], [2, 1, 0]], dtype=float
    )
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    scalars = np.array([0.0, 0.0, 2.0, 2.0])
    layer = MeshLayer(v, f, scalars=scalars, scalar_on=ScalarLocation.FACE, cmap="plasma")
    img = render_image([layer], View.FRONT, size=(300, 100), style=FLAT)
    cmap = matplotlib.colormaps["plasma"]
    lo = np.rint(np.asarray(cmap(0.0)[:3]) * 255)
    hi = np.rint(np.asarray(cmap(1.0)[:3]) * 255)
    np.testing.assert_allclose(img[50, 50], lo, atol=1)
    np.testing.assert_allclose(img[50, 250], hi, atol=1)
    np.testing.assert_array_equal(img[50, 150], [255, 255, 255])  # the gap between the squares

    # Explicit limits and a log scale: 10 sits in the middle of [1, 100].
    scalars = [10.0, 10.0, 1000.0, 1000.0]
    layer = MeshLayer(v, f, scalars=scalars, scalar_on="face", vmin=1.0, vmax=100.0, log=True)
    img = render_image([layer], View.FRONT, size=(300, 100), style=FLAT)
    viridis = matplotlib.colormaps["viridis"]
    np.testing.assert_allclose(img[50, 50], np.rint(np.asarray(viridis(0.5)[:3]) * 255), atol=2)
    np.testing.assert_allclose(img[50, 250], np.rint(np.asarray(viridis(1.0)[:3]) * 255), atol=1)


def test_vertex_scalars_are_interpolated():
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    layer = MeshLayer(v, f, scalars=v[:, 0], cmap="gray")  # value = x
    img = render_image([layer], View.FRONT, size=(201, 201), style=FLAT)
    row = img[100, 20:181, 0].astype(float)
    expected = np.rint(np.linspace(0.0, 1.0, 181)[10:171] * 255)  # pixel centres across the 181-px square
    assert np.abs(row - expected).max() <= 3
    assert np.all(np.diff(row) >= 0)


def test_back_faces_are_darker():
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    tri = MeshLayer(corners, np.array([[0, 1, 2]]), color=(0.2, 0.6, 1.0))
    style = RenderStyle(ambient=1.0, key=0.0, fill=0.0, supersample=1, back_face=0.5)
    front = render_image([tri], View.FRONT, size=(100, 100), style=style)
    back = render_image([tri], View.BACK, size=(100, 100), style=style)
    np.testing.assert_allclose(front[70, 30], np.rint(np.array([0.2, 0.6, 1.0]) * 255), atol=1)
    np.testing.assert_allclose(back[70, 70], np.rint(np.array([0.1, 0.3, 0.5]) * 255), atol=1)


def test_lambert_shading_darkens_oblique_faces():
    v, f = _sphere()
    img = render_image([MeshLayer(v, f, color=(1.0, 1.0, 1.0))], View.FRONT, size=(100, 100))
    centre = img[50, 50].astype(float).mean()
    rim = img[50, 94].astype(float).mean()  # near the right silhouette, facing sideways
    assert centre > rim + 20


def test_torch_and_numpy_inputs_agree():
    v, f = _sphere()
    a = render_image([MeshLayer(v, f, color=(0.3, 0.5, 0.7))], View.SIDE, size=(64, 48))
    b = render_image(
        [MeshLayer(torch.tensor(v, dtype=torch.float64), torch.tensor(f), color=(0.3, 0.5, 0.7))],
        View.SIDE,
        size=(64, 48),
    )
    np.testing.assert_array_equal(a, b)


def test_wireframe_and_outline_draw_dark_pixels():
    v, f = _sphere()
    plain = render_image([MeshLayer(v, f)], View.FRONT, size=(120, 120))
    wire = render_image([MeshLayer(v, f)], View.FRONT, size=(120, 120), style=RenderStyle(wireframe=True))
    outline = render_image([MeshLayer(v, f)], View.FRONT, size=(120, 120), style=RenderStyle(outline=True))
    assert (wire.astype(int).sum(2) < plain.astype(int).sum(2) - 30).mean() > 0.05
    darker = outline.astype(int).sum(2) < plain.astype(int).sum(2) - 30
    rows, cols = np.nonzero(darker)
    radius = np.hypot(rows + 0.5 - 60, cols + 0.5 - 60)
    assert darker.sum() > 2 * np.pi * 54  # a closed ring around the silhouette (radius 54 px) ...
    assert radius.min() > 0.9 * 54 and radius.max() < 56  # ... and nothing inside


def test_render_views_writes_png(tmp_path):
    body = MeshLayer(*_sphere((0.0, 0.0, 0.0), 0.3))
    cloth_v, cloth_f = _cube()
    cloth = MeshLayer(cloth_v * [0.8, 0.3, 0.8], cloth_f, scalars=cloth_v[:, 1], label="height (m)")
    out = tmp_path / "sub" / "fit.png"
    written = render_views([body, cloth], out, size=(120, 160), title="test")
    assert written == out and out.is_file()
    assert [p.name for p in out.parent.iterdir()] == ["fit.png"]  # no temporary files left
    layout = FigureLayout((120, 160), 3, 1, True)
    assert layout.size == (3 * 120 + 110, 160 + 30 + 36)
    with Image.open(out) as im:
        assert im.format == "PNG"
        assert im.size == layout.size

    # No scalars, no title, two views: no colourbar band.
    out2 = tmp_path / "plain.png"
    render_views([body], out2, views=(View.FRONT, View.SIDE), size=(100, 80))
    with Image.open(out2) as im:
        assert im.size == FigureLayout((100, 80), 2, 0, False).size == (200, 110)


def test_views_share_one_scale():
    v = np.array([[0, 0, 0], [0.2, 0, 0], [0, 1.0, 0], [0, 0, 0.6]], float)
    views = (View.FRONT, View.SIDE, View.BACK)
    scales = {fit_camera(v, w, (100, 100), views_for_scale=views).scale for w in views}
    assert len(scales) == 1
    assert scales.pop() == pytest.approx(90.0)


def test_bad_input_raises(tmp_path):
    v, f = _cube()
    with pytest.raises(InputError, match="empty"):
        render_image([], View.FRONT)
    with pytest.raises(InputError, match="empty"):
        render_views([], tmp_path / "x.png")
    bad = v.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="NaN"):
        render_image([MeshLayer(bad, f)], View.FRONT, size=(32, 32))
    with pytest.raises(InputError, match="NaN"):
        render_views([MeshLayer(bad, f)], tmp_path / "x.png")
    with pytest.raises(InputError, match="indices"):
        render_image([MeshLayer(v, f + 100)], View.FRONT, size=(32, 32))
    with pytest.raises(InputError, match="scalars"):
        render_image([MeshLayer(v, f, scalars=np.zeros(5))], View.FRONT, size=(32, 32))
    with pytest.raises(InputError, match="scalar_on"):
        render_image([MeshLayer(v, f, scalars=np.zeros(8), scalar_on="edge")], View.FRONT, size=(32, 32))
    with pytest.raises(InputError, match="color"):
        render_image([MeshLayer(v, f, color=(2.0, 0.0, 0.0))], View.FRONT, size=(32, 32))
    with pytest.raises(InputError, match="colormap"):
        render_image([MeshLayer(v, f, scalars=np.zeros(8), cmap="nope")], View.FRONT, size=(32, 32))
    cam = fit_camera(v, View.FRONT, (32, 32))
    with pytest.raises(InputError, match="camera"):
        render_image([MeshLayer(v, f)], View.BACK, size=(32, 32), camera=cam)
    with pytest.raises(InputError, match="camera"):
        render_image([MeshLayer(v, f)], View.FRONT, size=(64, 32), camera=cam)
    with pytest.raises(InputError, match="png"):
        render_views([MeshLayer(v, f)], tmp_path / "x.jpg")
    assert list(tmp_path.iterdir()) == []


def test_rasterize_reports_barycentrics():
    xy = np.array([[10.0, 10.0], [90.0, 10.0], [10.0, 90.0]])
    frags = rasterize(xy, np.zeros(3), np.array([[0, 1, 2]]), 100, 100)
    r, c = 30, 50  # pixel centre (50.5, 30.5)
    b = frags.bary[r, c]
    np.testing.assert_allclose(b @ xy, [50.5, 30.5], atol=1e-9)
    assert frags.face[r, c] == 0 and frags.face[95, 95] == -1 and np.isinf(frags.depth[95, 95])
    assert abs(frags.mask.sum() - 0.5 * 80 * 80) < 80


def test_body_render_time(garmentcode_dir, tmp_path):
    mesh = trimesh.load(garmentcode_dir / "bodies" / "mean_female.obj", process=False)
    layer = MeshLayer(np.asarray(mesh.vertices), np.asarray(mesh.faces))
    render_image([layer], View.FRONT, size=(80, 80))  # warm-up
    timings = {}
    for ss in (1, 2):
        t0 = time.perf_counter()
        img = render_image([layer], View.FRONT, size=(800, 800), style=RenderStyle(supersample=ss))
        timings[ss] = time.perf_counter() - t0
        cover = _covered(img).mean()
        assert 0.08 < cover < 0.3
    print(
        f"\nmean_female ({len(mesh.faces)} faces) 800x800 FRONT: "
        f"{timings[1]:.3f} s (supersample 1), {timings[2]:.3f} s (supersample 2)"
    )


def test_rasterize_is_independent_of_chunking():
    """Large triangles cut into row bands and small chunks give the same buffers as one pass."""
    xy = np.array([[5.3, 3.1], [990.2, 40.7], [300.5, 1190.9], [900.0, 1000.0], [-50.0, 600.0]])
    depth = np.array([0.0, 1.0, 2.0, 0.5, -1.0])
    faces = np.array([[0, 1, 2], [1, 3, 2], [4, 0, 3]])
    one = rasterize(xy, depth, faces, 1000, 1200, chunk_pixels=10**8)
    many = rasterize(xy, depth, faces, 1000, 1200, chunk_pixels=777)
    assert one.mask.mean() > 0.5
    np.testing.assert_array_equal(one.face, many.face)
    np.testing.assert_allclose(one.bary, many.bary, atol=1e-12)
    np.testing.assert_allclose(one.depth[one.mask], many.depth[one.mask], atol=1e-12)


def test_contact_sheet_tiles_pictures_and_marks_missing_ones(tmp_path):
    from torchgarment.render import contact_sheet

    for i, colour in enumerate([(255, 0, 0), (0, 0, 255)]):
        Image.new("RGB", (900, 300), colour).save(tmp_path / f"r{i}.png")
    tiles = [(tmp_path / "r0.png", "red job"), (None, "failed job"), (tmp_path / "r1.png", "blue job")]
    out = contact_sheet(tiles, tmp_path / "sheet.png", columns=2, tile_size=(300, 100), title="three jobs")
    img = np.asarray(Image.open(out).convert("RGB")).astype(int)
    assert img.shape[1] == 2 * 306 + 6 and img.shape[0] > 2 * 100
    h = img.shape[0]
    # a thumbnail is the picture scaled into its cell (aspect kept), a missing picture a grey cell
    assert (img[: h // 2, :306] == [255, 0, 0]).all(axis=2).sum() > 0.8 * 300 * 100
    assert (img[: h // 2, 306:] == [215, 215, 215]).all(axis=2).sum() > 0.8 * 300 * 100
    assert (img[h // 2:, :306] == [0, 0, 255]).all(axis=2).sum() > 0.8 * 300 * 100
    assert not list(tmp_path.glob(".*"))  # written atomically
