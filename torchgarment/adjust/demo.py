"""A short pattern-adjustment demo for ``torchgarment demo``: a library garment from one chart size to
another.

Coarse by default (5 cm triangle edges, 10 mm SDF voxels, 16 pgd iterations with an exact check every 8) so
that it runs in a few minutes on 2 CPU cores. The outputs are those of ``torchgarment adjust``
(:func:`torchgarment.adjust.cli.write_outputs`), TensorBoard scalars under ``out_dir/logs``.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from torchgarment.errors import InputError


def run_adjust_demo(
    out_dir: Path,
    *,
    base_size: str = "12",
    target_size: str = "20",
    garment: str = "straight_skirt",
    edge_length: float = 0.05,
    iterations: int = 16,
    voxel_size: float = 0.01,
    progress: bool = True,
    device: torch.device | str | None = None,
) -> dict:
    """Adjust ``garment`` drafted for chart size ``base_size`` to the chart body of ``target_size``.

    Args:
        out_dir: output folder (staged: filled only when the run succeeds): ``pattern.json``, ``pattern.svg``,
            ``pattern.dxf``, ``garment_base.obj``, ``garment_target.obj``, ``target_before.png``,
            ``target_after.png``, ``overlay.png``, ``metrics.json`` and TensorBoard ``logs/``.
        base_size, target_size: chart sizes (``torchgarment.body.size_chart.list_sizes()``).
        garment: a library garment (``torchgarment.pattern.library.list_garments()``).
        edge_length: triangle edge length in metres.
        iterations: outer pgd iterations.
        voxel_size: body SDF voxel size in metres.
        progress: tqdm bar on stderr.
        device: computation device (default CPU).

    Returns:
        The adjustment's metrics (as ``metrics.json``) plus ``garment``, ``base_size``, ``target_size`` and
        ``out_dir``.

    Raises:
        InputError: unknown size or garment, non-positive ``edge_length``/``voxel_size``, negative
            ``iterations``.
    """
    from torchgarment.adjust.cli import write_outputs
    from torchgarment.adjust.pipeline import AdjustSettings, adjust
    from torchgarment.body import Body
    from torchgarment.body.size_chart import chart_row, list_sizes
    from torchgarment.io.staging import staged_output
    from torchgarment.pattern.library import draft, list_garments

    for what, size in (("base_size", base_size), ("target_size", target_size)):
        if str(size) not in list_sizes():
            raise InputError(f"{what} {size!r} is not a chart size ({', '.join(list_sizes())})")
    if garment not in list_garments():
        raise InputError(f"garment {garment!r} is not a library garment ({', '.join(list_garments())})")
    if not (edge_length > 0 and voxel_size > 0 and math.isfinite(edge_length) and math.isfinite(voxel_size)):
        raise InputError(f"edge_length and voxel_size must be positive, got {edge_length} and {voxel_size}")
    if iterations < 0:
        raise InputError(f"iterations must be >= 0, got {iterations}")
    out = Path(out_dir)
    settings = AdjustSettings(edge_length=edge_length, voxel_size=voxel_size, iterations=iterations,
                              exact_interval=max(1, min(8, iterations)))
    base_body, target_body = Body.from_size(str(base_size)), Body.from_size(str(target_size))
    if device is not None and torch.device(device).type != "cpu":
        base_body, target_body = base_body.to(device), target_body.to(device)
    pattern = draft(garment, chart_row(str(base_size)))
    result = adjust(pattern, base_body, target_body, settings, log_dir=out / "logs", progress=progress,
                    device=device)
    title = f"{pattern.name}: size {base_size} -> size {target_size}"
    with staged_output(out) as stage:
        write_outputs(result, stage, base_body, target_body, title)
    metrics = dict(result.metrics)
    metrics.update(garment=garment, base_size=str(base_size), target_size=str(target_size), out_dir=str(out))
    return metrics
