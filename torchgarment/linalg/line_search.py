"""Armijo backtracking line search."""

from __future__ import annotations

import math
from typing import Callable


def armijo_backtracking(
    f: Callable[[float], float], f0: float, slope: float, alpha0: float, *, armijo_c: float, backtrack: float,
    max_backtracks: int, slack: float = 0.0, min_alpha: float = 0.0,
) -> tuple[float, float, bool]:
    """The first step ``alpha`` of ``alpha0, alpha0 b, alpha0 b^2, ...`` with sufficient decrease
    ``f(alpha) <= f0 + armijo_c * alpha * slope + slack``.

    Args:
        f: the objective at step ``alpha`` (the caller moves its state there); a NaN or infinite value rejects
            the step.
        f0: the objective at ``alpha = 0``. slope: its directional derivative along the step (< 0 for
            descent).
        alpha0: the first trial step (already capped by any step bound: a trust length, a barrier's
            ``max_step``, a collision-free step).
        armijo_c: sufficient-decrease constant in (0, 1).
        backtrack: factor ``b`` in (0, 1) applied to ``alpha`` after a rejected trial.
        max_backtracks: trials at most.
        slack: absolute tolerance added to the right-hand side (round-off of ``f`` near a minimum).
        min_alpha: no step below this is tried (0: the trials end only after ``max_backtracks``).

    Returns:
        ``(alpha, f(alpha), True)`` for the accepted step; else ``(alpha, f(alpha), False)`` for the last
        tried step (``(alpha0, f0, False)`` when none was tried). The caller restores its state after a
        failure.
    """
    alpha, last, value = alpha0, alpha0, f0
    for trial in range(max_backtracks):
        if trial:
            alpha *= backtrack
        if alpha < min_alpha:
            break
        last, value = alpha, float(f(alpha))
        if math.isfinite(value) and value <= f0 + armijo_c * alpha * slope + slack:
            return alpha, value, True
    return last, value, False
