"""Online mapping of a device clock (sensor or controller) onto the host's monotonic clock.

The method (line-laser-and-sync.md section 3.3, Olson's passive synchronisation): every message
gives a pair ``(src_us, host_ns)``, the device's stamp and the host's receive time. Transport delay
is never negative, so ``d = host - src`` lies *above* ``offset + drift * t + min_latency``; latency
spikes only push points further up. We therefore fit the **lower envelope**: the line below every
pair that is closest to them overall. That line is a supporting line of the lower convex hull, and
minimising the summed gap ``sum(d_i - a - b s_i)`` picks the hull edge spanning the mean source
time (a linear programme whose optimum is on a hull vertex pair). Drift is bounded by
``max_drift_ppm`` so a short window cannot produce a wild slope.

The fit maps device time to "host time of the fastest possible arrival": true time plus the
link's minimum latency. The difference between the sensor's and the controller's minimum latencies
is a constant that the configured ``latency_ms`` (``cellctl calibrate time-offset``) removes.

The HD8's own clock is a 32-bit millisecond counter: :class:`CounterUnwrapper` makes it monotonic
across the wrap (every ~49.7 days, or mid-scan when it starts near the top) and
:class:`FrameTimeline` recovers sub-millisecond profile times from the counter by regressing it on
the frame index (the frame timer and the counter share the sensor's oscillator).

Everything here is deterministic in its inputs, so replaying the raw files reproduces every fit
bit for bit (:mod:`cellctl.acquisition.reassemble`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import structlog

__all__ = [
    "ClockFit",
    "ClockSync",
    "ClockSyncConfig",
    "ClockSyncError",
    "CounterUnwrapper",
    "FrameTimeline",
    "fit_lower_envelope",
    "lower_hull",
]

log = structlog.get_logger(__name__)

_U32 = 1 << 32
_HALF_U32 = 1 << 31


class ClockSyncError(ValueError):
    """Clock synchronisation cannot proceed: bad input arrays or no fit yet."""


@dataclass(frozen=True, slots=True)
class ClockSyncConfig:
    """Settings of one clock's online estimator.

    Attributes:
        window_s: pairs older than this (device time) are forgotten; long enough to see drift.
        bin_s: pairs are reduced to the lowest one per bin of device time before the hull (cost bound).
        refit_interval_s: the fit is recomputed at most this often (device time).
        max_drift_ppm: bound on |drift|; real quartz clocks stay within about 100 ppm.
        min_pairs: no fit before this many pairs.
        spike_ms: a pair more than this above the envelope counts as a latency spike in the report.
    """

    window_s: float = 120.0
    bin_s: float = 0.05
    refit_interval_s: float = 0.25
    max_drift_ppm: float = 500.0
    min_pairs: int = 4
    spike_ms: float = 2.0

    def __post_init__(self) -> None:
        for name in ("window_s", "bin_s", "refit_interval_s", "max_drift_ppm", "spike_ms"):
            if not getattr(self, name) > 0:
                raise ClockSyncError(f"ClockSyncConfig.{name} must be > 0, got {getattr(self, name)}")
        if self.min_pairs < 2:
            raise ClockSyncError(f"ClockSyncConfig.min_pairs must be >= 2, got {self.min_pairs}")


@dataclass(frozen=True, slots=True)
class ClockFit:
    """``host_ns = host_ref_ns + (src_us - src_ref_us) * 1000 + offset_ns + drift_ppm * 1e-3 * (src_us - src_ref_us)``.

    Attributes:
        src_ref_us: reference point on the device clock, us (integer, so no precision is lost).
        host_ref_ns: host time at the reference before the offset, ns.
        offset_ns: envelope offset at the reference, ns (includes the link's minimum latency).
        drift_ppm: device clock rate error seen from the host, parts per million.
        n_pairs: pairs in the window the fit used.
        span_s: device-time span of those pairs.
        jitter_p50_ms, jitter_p95_ms, jitter_max_ms: latency above the envelope (the spread of the
            pairs above the fitted line).
        spike_fraction: share of pairs more than ``spike_ms`` above the envelope.
        fit_index: 0 for the first fit of an estimator, then +1 per refit.
    """

    src_ref_us: int
    host_ref_ns: int
    offset_ns: float
    drift_ppm: float
    n_pairs: int
    span_s: float
    jitter_p50_ms: float
    jitter_p95_ms: float
    jitter_max_ms: float
    spike_fraction: float
    fit_index: int = 0

    def to_host_ns(self, src_us: np.ndarray) -> np.ndarray:
        """Map device times ``src_us`` (n,) int64 us to host times (n,) int64 ns."""
        ds_us = np.asarray(src_us, dtype=np.int64) - np.int64(self.src_ref_us)
        corr_ns = self.offset_ns + self.drift_ppm * 1e-3 * ds_us.astype(np.float64)
        return np.int64(self.host_ref_ns) + ds_us * 1000 + np.rint(corr_ns).astype(np.int64)

    def report(self) -> dict[str, float | int]:
        """The fit's quality as plain numbers (for logs, the job record and ``cellctl`` output)."""
        d = asdict(self)
        d["offset_ms"] = self.offset_ns * 1e-6
        return d


def lower_hull(s: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Indices of the lower convex hull of points ``(s, d)``, sorted by ``s`` (monotone chain).

    Args:
        s: (n,) float, strictly increasing.
        d: (n,) float.

    Returns:
        (k,) int indices, first and last point included.
    """
    hull: list[int] = []
    # Python loop over the (already binned, a few thousand) points; numpy has no incremental hull.
    for i in range(len(s)):
        while len(hull) >= 2:
            a, b = hull[-2], hull[-1]
            cross = (s[b] - s[a]) * (d[i] - d[a]) - (d[b] - d[a]) * (s[i] - s[a])
            if cross <= 0:
                hull.pop()
            else:
                break
        hull.append(i)
    return np.asarray(hull, dtype=np.int64)


def fit_lower_envelope(s: np.ndarray, d: np.ndarray, max_slope: float) -> tuple[float, float]:
    """Line ``d = a + b s`` below every point that minimises the summed gap to the points.

    Args:
        s: (n,) float, strictly increasing (e.g. device time, s).
        d: (n,) float (e.g. host minus device time, ns).
        max_slope: bound on ``|b|``.

    Returns:
        ``(a, b)``.
    """
    if len(s) == 1:
        return float(d[0]), 0.0
    h = lower_hull(s, d)
    s_mean = float(np.mean(s))
    hs, hd = s[h], d[h]
    # the supporting line at the mean abscissa is the hull edge spanning it
    k = int(np.clip(np.searchsorted(hs, s_mean, side="right") - 1, 0, len(h) - 2))
    b = float((hd[k + 1] - hd[k]) / (hs[k + 1] - hs[k]))
    if abs(b) > max_slope:
        b = float(np.clip(b, -max_slope, max_slope))
    a = float(np.min(d - b * s))  # keep every point on or above the line
    return a, b


class ClockSync:
    """Online offset + drift estimator for one device clock.

    Feed pairs with :meth:`add` as messages arrive (device stamp of the newest exposure in a message,
    host receive time of that message); read :attr:`fit` or map stamps with :meth:`to_host_ns`.

    Args:
        config: window, binning, refit cadence and bounds.
        name: which clock ("sensor", "controller"), for logs and reports.
    """

    def __init__(self, config: ClockSyncConfig | None = None, name: str = "clock") -> None:
        self.config = config or ClockSyncConfig()
        self.name = name
        self._src_us = np.empty(0, dtype=np.int64)
        self._host_ns = np.empty(0, dtype=np.int64)
        self._fit: ClockFit | None = None
        self._last_fit_src_us: int | None = None
        self._n_fits = 0

    @property
    def fit(self) -> ClockFit | None:
        """The current fit, or None before ``min_pairs`` pairs."""
        return self._fit

    @property
    def n_pairs(self) -> int:
        """Pairs currently in the window."""
        return int(self._src_us.shape[0])

    def add(self, src_us: np.ndarray, host_ns: np.ndarray) -> ClockFit | None:
        """Add pairs and refit if due. Returns the new fit when one was made, else None.

        Args:
            src_us: (n,) int device times, us.
            host_ns: (n,) int host receive times, ns (``time.monotonic_ns``).
        """
        src = np.atleast_1d(np.asarray(src_us, dtype=np.int64))
        host = np.atleast_1d(np.asarray(host_ns, dtype=np.int64))
        if src.shape != host.shape or src.ndim != 1:
            raise ClockSyncError(
                f"{self.name}: src_us {src.shape} and host_ns {host.shape} must be equal (n,)"
            )
        if src.size == 0:
            return None
        self._src_us = np.concatenate([self._src_us, src])
        self._host_ns = np.concatenate([self._host_ns, host])
        newest = int(self._src_us.max())
        cutoff = newest - int(self.config.window_s * 1e6)
        if self._src_us[0] < cutoff:
            keep = self._src_us >= cutoff
            self._src_us, self._host_ns = self._src_us[keep], self._host_ns[keep]
        due = (
            self._fit is None
            or self._last_fit_src_us is None
            or newest - self._last_fit_src_us >= self.config.refit_interval_s * 1e6
        )
        if not due or self.n_pairs < self.config.min_pairs:
            return None
        self._fit = self._refit()
        self._last_fit_src_us = newest
        return self._fit

    def _refit(self) -> ClockFit:
        cfg = self.config
        src_ref = int(self._src_us.min())
        host_ref = int(self._host_ns[np.argmin(self._src_us)])
        ds_us = self._src_us - src_ref
        d_ns = ((self._host_ns - host_ref) - ds_us * 1000).astype(np.float64)
        # lowest pair per bin of device time: hull cost stays bounded whatever the message rate
        bins = ds_us // max(int(cfg.bin_s * 1e6), 1)
        order = np.lexsort((d_ns, bins))
        b_sorted = bins[order]
        first = np.concatenate([[True], b_sorted[1:] != b_sorted[:-1]])
        pick = order[first]  # the minimum d of each bin, in increasing bin order
        s_s = ds_us[pick].astype(np.float64) * 1e-6
        d_bin = d_ns[pick]
        # several bins can share one device time only if bin_s < 1 us; keep s strictly increasing
        uniq = np.concatenate([[True], np.diff(s_s) > 0])
        a_ns, b_ns_per_s = fit_lower_envelope(s_s[uniq], d_bin[uniq], cfg.max_drift_ppm * 1e3)
        above_ms = (d_ns - (a_ns + b_ns_per_s * ds_us.astype(np.float64) * 1e-6)) * 1e-6
        span_s = float(ds_us.max()) * 1e-6
        fit = ClockFit(
            src_ref_us=src_ref,
            host_ref_ns=host_ref,
            offset_ns=a_ns,
            drift_ppm=b_ns_per_s * 1e-3,
            n_pairs=self.n_pairs,
            span_s=span_s,
            jitter_p50_ms=float(np.percentile(above_ms, 50)),
            jitter_p95_ms=float(np.percentile(above_ms, 95)),
            jitter_max_ms=float(above_ms.max()),
            spike_fraction=float(np.mean(above_ms > cfg.spike_ms)),
            fit_index=self._n_fits,
        )
        self._n_fits += 1
        return fit

    def to_host_ns(self, src_us: np.ndarray) -> np.ndarray:
        """Map device times (n,) int64 us to host times (n,) int64 ns with the current fit."""
        if self._fit is None:
            raise ClockSyncError(
                f"{self.name}: no clock fit yet ({self.n_pairs} pairs, need {self.config.min_pairs})"
            )
        return self._fit.to_host_ns(src_us)


class CounterUnwrapper:
    """Turns a wrapping 32-bit millisecond counter into a monotonic int64 count.

    A backwards step of more than half the range is a wrap; a smaller backwards step is a glitch and
    is passed through (it shows up in the fit's residuals, it does not add 49.7 days).
    """

    def __init__(self) -> None:
        self._last: int | None = None
        self._epochs = 0

    def unwrap(self, counter: np.ndarray) -> np.ndarray:
        """(n,) uint32 counter values, in arrival order -> (n,) int64 unwrapped values."""
        c = np.atleast_1d(np.asarray(counter)).astype(np.int64)
        if c.size == 0:
            return c
        if np.any((c < 0) | (c >= _U32)):
            raise ClockSyncError(f"counter values outside the 32-bit range: {c[(c < 0) | (c >= _U32)][:4]}")
        prev = np.concatenate([[c[0] if self._last is None else self._last], c[:-1]])
        step = c - prev
        wraps = np.cumsum((step < -_HALF_U32).astype(np.int64) - (step > _HALF_U32).astype(np.int64))
        out = c + (self._epochs + wraps) * _U32
        self._epochs += int(wraps[-1])
        self._last = int(c[-1])
        return out


class FrameTimeline:
    """Sub-millisecond profile times from a 1 ms counter: a least-squares line over the frame index.

    The HD8 counter truncates to whole milliseconds, but its frames come from a timer on the same
    oscillator, so ``t(frame) = t0 + period * frame`` holds in device time. Regressing the counter's
    mid-millisecond values on the frame index (over a sliding window) gives each profile a device time
    whose error is the regression's, not the counter's 1 ms step.

    Args:
        window: frames kept for the regression.
    """

    def __init__(self, window: int = 4000) -> None:
        if window < 2:
            raise ClockSyncError(f"FrameTimeline window must be >= 2, got {window}")
        self.window = window
        self._f = np.empty(0, dtype=np.int64)
        self._t_us = np.empty(0, dtype=np.int64)

    def times_us(self, frame_index: np.ndarray, counter_us: np.ndarray) -> np.ndarray:
        """Add profiles and return their regressed device times.

        Args:
            frame_index: (n,) int frame counter.
            counter_us: (n,) int64 unwrapped counter in us (ms value * 1000 + 500: mid-millisecond).

        Returns:
            (n,) int64 device times, us.
        """
        f = np.asarray(frame_index, dtype=np.int64)
        t = np.asarray(counter_us, dtype=np.int64)
        self._f = np.concatenate([self._f, f])[-self.window :]
        self._t_us = np.concatenate([self._t_us, t])[-self.window :]
        if len(self._f) < 2 or self._f[-1] == self._f[0]:
            return t.copy()
        f0, t0 = self._f[0], self._t_us[0]
        x = (self._f - f0).astype(np.float64)
        y = (self._t_us - t0).astype(np.float64)
        xm, ym = x.mean(), y.mean()
        slope = float(np.dot(x - xm, y - ym) / np.dot(x - xm, x - xm))
        icpt = ym - slope * xm
        return t0 + np.rint(icpt + slope * (f - f0).astype(np.float64)).astype(np.int64)
