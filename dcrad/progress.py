"""A one-line progress bar on stderr: residual towards the tolerance, rays/s, ETA."""

from __future__ import annotations

import math
import sys
import time

__all__ = ["ProgressBar"]


def _fmt_time(s: float) -> str:
    if not math.isfinite(s):
        return "--:--"
    s = int(round(s))
    return f"{s // 60:02d}:{s % 60:02d}" if s < 3600 else f"{s // 3600}h{(s % 3600) // 60:02d}"


class ProgressBar:
    """Draws ``[#####-----] 52% residual 3.1e-02 -> 1.0e-02 | 2.3 Mrays/s | ETA 00:04``.

    The fraction is log(residual) / log(tol): progress in orders of magnitude.
    Redraws at most every ``interval`` seconds; silent when ``stream`` is not a tty
    unless ``force`` is set.
    """

    def __init__(self, tol: float, stream=None, interval: float = 0.2, width: int = 24, force: bool = False):
        self.tol = max(tol, 1e-300)
        self.stream = stream or sys.stderr
        self.interval = interval
        self.width = width
        self.enabled = force or getattr(self.stream, "isatty", lambda: False)()
        self._last = 0.0

    def line(self, residual: float, rays: int, elapsed: float, eta: float) -> str:
        if residual <= 0:
            frac = 1.0
        else:
            frac = min(1.0, max(0.0, math.log(residual) / math.log(self.tol))) if self.tol < 1 else 1.0
        done = int(round(frac * self.width))
        rate = rays / elapsed / 1e6 if elapsed > 0 else 0.0
        return (
            f"[{'#' * done}{'-' * (self.width - done)}] {100 * frac:3.0f}% "
            f"residual {residual:.2e} -> {self.tol:.1e} | {rate:.2f} Mrays/s | "
            f"{_fmt_time(elapsed)} elapsed | ETA {_fmt_time(eta)}"
        )

    def update(self, residual: float, rays: int, elapsed: float, eta: float, final: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not final and now - self._last < self.interval:
            return
        self._last = now
        self.stream.write("\r" + self.line(residual, rays, elapsed, eta))
        if final:
            self.stream.write("\n")
        self.stream.flush()
