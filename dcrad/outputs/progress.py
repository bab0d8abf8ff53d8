"""A one-line progress bar on stderr: the estimated error towards the target, rays/s, ETA."""

from __future__ import annotations

import math
import sys
import time

__all__ = ["ProgressBar", "error_text", "progress_fraction"]


def _fmt_time(s: float) -> str:
    if not math.isfinite(s):
        return "--:--"
    s = int(round(s))
    return f"{s // 60:02d}:{s % 60:02d}" if s < 3600 else f"{s // 3600}h{(s % 3600) // 60:02d}"


def _pct(x) -> str:
    return f"{100 * x:.2f}%" if x is not None and math.isfinite(x) else "--"


def error_text(rms_refl, noise_refl=None, bias_refl=None, accuracy: float = 0.0) -> str:
    """``est. error 3.10% -> 2% of reflected (noise 2.50%, bias 1.80%)``: the live estimate."""
    target = f" -> {100 * accuracy:g}%" if accuracy > 0 else ""
    parts = f" (noise {_pct(noise_refl)}, bias {_pct(bias_refl)})" if noise_refl is not None else ""
    return f"est. error {_pct(rms_refl)}{target} of reflected{parts}"


def progress_fraction(residual: float, tol: float, error=None, accuracy: float = 0.0, first_error=None) -> float:
    """Progress in orders of magnitude: of the estimated error from its first value to the
    accuracy target when there is one, else of the residual to the tolerance."""
    if accuracy > 0 and error is not None and math.isfinite(error):
        if error <= accuracy:
            return 1.0
        start = first_error if first_error is not None and math.isfinite(first_error) else 1.0
        start = max(start, error, accuracy * 1.0001)
        return min(1.0, max(0.0, math.log(start / error) / math.log(start / accuracy)))
    if residual <= 0:
        return 1.0
    tol = max(tol, 1e-300)
    return min(1.0, max(0.0, math.log(residual) / math.log(tol))) if tol < 1 else 1.0


class ProgressBar:
    """Draws ``[#####-----] 52% est. error 3.10% -> 2% of reflected (...) | residual 3.1e-02 | 2.3 Mrays/s | ETA``.

    With an accuracy target the fraction is the estimated error's way from its
    first value to the target, in orders of magnitude; without one it is
    log(residual) / log(tol).  Redraws at most every ``interval`` seconds; silent
    when ``stream`` is not a tty unless ``force`` is set.
    """

    def __init__(self, tol: float, stream=None, interval: float = 0.2, width: int = 24, force: bool = False,
                 accuracy: float = 0.0):
        self.tol = max(tol, 1e-300)
        self.accuracy = accuracy
        self.stream = stream or sys.stderr
        self.interval = interval
        self.width = width
        self.enabled = force or getattr(self.stream, "isatty", lambda: False)()
        self._last = 0.0
        self._first_error = None

    def line(self, residual: float, rays: int, elapsed: float, eta: float, estimate=None) -> str:
        err = getattr(estimate, "rms_refl", None)
        if err is not None and math.isfinite(err) and self._first_error is None:
            self._first_error = err
        frac = progress_fraction(residual, self.tol, err, self.accuracy, self._first_error)
        done = int(round(frac * self.width))
        rate = rays / elapsed / 1e6 if elapsed > 0 else 0.0
        if estimate is not None:
            what = (f"{error_text(err, estimate.noise_refl, estimate.bias_refl, self.accuracy)} | "
                    f"residual {residual:.2e}")
        else:
            what = f"residual {residual:.2e} -> {self.tol:.1e}"
        return (
            f"[{'#' * done}{'-' * (self.width - done)}] {100 * frac:3.0f}% {what} | {rate:.2f} Mrays/s | "
            f"{_fmt_time(elapsed)} elapsed | ETA {_fmt_time(eta)}"
        )

    def update(self, residual: float, rays: int, elapsed: float, eta: float, final: bool = False,
               estimate=None) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not final and now - self._last < self.interval:
            return
        self._last = now
        self.stream.write("\r" + self.line(residual, rays, elapsed, eta, estimate))
        if final:
            self.stream.write("\n")
        self.stream.flush()
