"""Run logging shared by the pipelines: TensorBoard scalars and a tqdm progress bar.

:class:`RunLogger` writes scalars with a ``torch.utils.tensorboard.SummaryWriter`` when given a folder and
shows a tqdm bar on stderr when asked; both are optional, so a pipeline logs unconditionally and the caller
decides.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from pathlib import Path


class RunLogger:
    """TensorBoard scalars (when ``log_dir``) and a tqdm bar on stderr (when ``progress``).

    Args:
        log_dir: TensorBoard folder, or None (no scalars).
        progress: show a progress bar.
        desc: the bar's label.
        total: the bar's total (None: open-ended). initial: its starting count (a resumed run).
    """

    def __init__(
        self,
        log_dir: str | Path | None,
        progress: bool,
        desc: str,
        total: int | None = None,
        initial: int = 0,
    ) -> None:
        self.writer = None
        if log_dir is not None:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(log_dir=str(log_dir))
        self.bar = None
        if progress:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=initial, desc=desc, unit="it", file=sys.stderr, leave=False)

    def scalars(self, values: Mapping[str, float], step: int, prefix: str = "") -> None:
        """Write each value as the TensorBoard scalar ``prefix + name`` at ``step`` (no-op without a
        folder)."""
        if self.writer is not None:
            for name, v in values.items():
                self.writer.add_scalar(f"{prefix}{name}", v, step)

    def advance(self, postfix: Mapping[str, object] | None = None, n: int = 1) -> None:
        """Advance the bar by ``n`` and show ``postfix`` (no-op without a bar)."""
        if self.bar is not None:
            self.bar.update(n)
            if postfix:
                self.bar.set_postfix(postfix, refresh=False)

    def close(self) -> None:
        """Flush and close the writer and the bar."""
        if self.writer is not None:
            self.writer.flush()
            self.writer.close()
        if self.bar is not None:
            self.bar.close()
