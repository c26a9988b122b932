"""Progress bars of the iterative solvers that show the way to their stopping rule.

An ADMM solve stops when its residuals fall to their tolerances, long before its iteration limit
(LBC: about 750 of 20,000 iterations on the data set's cages), so a bar whose total is the limit
shows 4% done at the end and an ETA 25 times too long. :class:`ToleranceProgress` shows instead
how far, on a log scale, the worst residual has come from its first value towards its tolerance:
ADMM's residuals fall roughly geometrically, so the bar moves at about a steady pace and its ETA
is an estimate of the time to convergence. With a zero tolerance (run to the iteration limit) the
bar counts iterations towards the limit.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

__all__ = ["ToleranceProgress", "fraction_to_tolerance"]


def fraction_to_tolerance(first: float, current: float, tolerance: float) -> float:
    """How far ``current`` has come from ``first`` towards ``tolerance`` on a log scale, in
    ``[0, 1]`` (1 once ``current <= tolerance``); 0 for a tolerance of 0 or a non-finite residual.

    Examples:
        >>> fraction_to_tolerance(1.0, 1e-3, 1e-6), fraction_to_tolerance(1.0, 1e-7, 1e-6)
        (0.5, 1.0)
    """
    if not math.isfinite(current):
        return 0.0
    if current <= tolerance:
        return 1.0
    if tolerance <= 0 or not math.isfinite(first) or first <= tolerance:
        return 0.0
    return min(1.0, max(0.0, math.log(first / current) / math.log(first / tolerance)))


class ToleranceProgress:
    """A tqdm bar towards a stopping rule ``residual_k <= tolerance_k`` for every ``k``.

    Args:
        desc: the bar's label.
        max_iter: the iteration limit.
        names: the residuals' names, shown with their ratio to the tolerance (``1x`` stops).
        tolerances: their tolerances; any of them 0 means "run to ``max_iter``" (the bar counts
            iterations).
    """

    def __init__(self, desc: str, max_iter: int, names: Sequence[str], tolerances: Sequence[float]) -> None:
        from tqdm.auto import tqdm

        self.names, self.tolerances = list(names), [float(t) for t in tolerances]
        self.to_limit = any(t <= 0 for t in self.tolerances)
        self.first: list[float] | None = None
        if self.to_limit:
            self.bar: Any = tqdm(total=max_iter, desc=f"{desc} (to max_iter)", unit="it", leave=False)
        else:
            fmt = "{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}{postfix}"
            self.bar = tqdm(total=100, desc=f"{desc}, log residual to tolerance", bar_format=fmt, leave=False)

    def update(self, iteration: int, residuals: Sequence[float]) -> None:
        """Show the state after ``iteration`` with these residuals."""
        ratios = {
            n: (f"{r / t:.2g}x tol" if t > 0 else f"{r:.2g}")
            for n, r, t in zip(self.names, residuals, self.tolerances, strict=True)
        }
        if self.to_limit:
            self.bar.n = iteration
        else:
            now = [max(float(r), t) for r, t in zip(residuals, self.tolerances, strict=True)]
            # the first finite value of each residual is where its way starts
            self.first = (
                now
                if self.first is None
                else [f if math.isfinite(f) else n for f, n in zip(self.first, now, strict=True)]
            )
            frac = min(
                fraction_to_tolerance(f, float(r), t)
                for f, r, t in zip(self.first, residuals, self.tolerances, strict=True)
            )
            self.bar.n = int(100 * frac)
        self.bar.set_postfix(OrderedDict([("it", iteration), *ratios.items()]), refresh=False)
        self.bar.refresh()

    def close(self) -> None:
        """Close the bar."""
        self.bar.close()
