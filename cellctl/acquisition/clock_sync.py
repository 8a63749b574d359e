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
from scipy.spatial import ConvexHull, QhullError

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
        min_drift_span_s: below this window span the drift is held at 0 and only the offset is fitted:
            over a short span the envelope's slope is dominated by how the minimum latency wanders
            (milliseconds on a loaded host), while 50 ppm of drift adds only 1 ms over 20 s.
        min_pairs: no fit before this many pairs.
        spike_ms: a pair more than this above the envelope counts as a latency spike in the report.
        step_ms, step_confirm_s: a device clock that jumps *back* (reset, resynchronised) leaves
            every new pair more than ``step_ms`` above the fit, and the lower envelope would keep
            the old pairs for the whole window. When every pair stays that far above for
            ``step_confirm_s`` of device time (longer than a host's latency burst) the pairs before
            are forgotten and the fit restarts from the pairs after the step. A jump *ahead* needs
            nothing: its pairs lie below the envelope, which the next refit follows. Off (0) by
            default: on a host so loaded that a whole second of messages arrives late it restarts
            the fit from a handful of lagging pairs, which costs more than it saves.
    """

    window_s: float = 120.0
    bin_s: float = 0.2
    refit_interval_s: float = 2.0
    max_drift_ppm: float = 200.0
    min_drift_span_s: float = 20.0
    min_pairs: int = 4
    spike_ms: float = 2.0
    step_ms: float = 0.0
    step_confirm_s: float = 1.0

    def __post_init__(self) -> None:
        if self.min_drift_span_s < 0:
            raise ClockSyncError(
                f"ClockSyncConfig.min_drift_span_s must be >= 0, got {self.min_drift_span_s}"
            )
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
        offset_ns: envelope offset at the reference, ns, relative to ``host_ref_ns`` (the report's
            ``host_minus_device_ms`` is the whole offset, the link's minimum latency included).
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
        # host minus device time at the reference point: the clock offset plus the minimum latency
        d["host_minus_device_ms"] = (self.host_ref_ns - self.src_ref_us * 1000 + self.offset_ns) * 1e-6
        return d


def lower_hull(s: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Indices of the lower convex hull of points ``(s, d)``, in increasing ``s``.

    Args:
        s: (n,) float, strictly increasing.
        d: (n,) float.

    Returns:
        (k,) int indices from the first point to the last (qhull; collinear points are left out).
    """
    n = len(s)
    if n <= 2:
        return np.arange(n, dtype=np.int64)
    try:
        hull = ConvexHull(np.column_stack([s, d]))
    except QhullError:  # all points on one line: its end points are the hull
        return np.array([0, n - 1], dtype=np.int64)
    v = hull.vertices  # counter-clockwise: from the leftmost point the walk runs along the bottom
    v = np.roll(v, -int(np.argmin(s[v])))
    right = int(np.argmax(s[v]))
    return v[: right + 1].astype(np.int64)


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
    if abs(b) > max_slope:  # (max_slope 0 fits the offset alone)
        b = float(np.clip(b, -max_slope, max_slope))
    a = float(np.min(d - b * s))  # keep every point on or above the line
    return a, b


class ClockSync:
    """Online offset + drift estimator for one device clock.

    Feed pairs with :meth:`add` as messages arrive (device stamp of the newest exposure in a message,
    host receive time of that message); read :attr:`fit` or map stamps with :meth:`to_host_ns`.

    Pairs are reduced on arrival to the lowest one per ``bin_s`` of device time (only those can be on
    the lower envelope), so memory and refit cost depend on the window length, not on the message
    rate. The last ``report_pairs`` raw pairs are kept for the jitter figures of the quality report.

    Args:
        config: window, binning, refit cadence and bounds.
        name: which clock ("sensor", "controller"), for logs and reports.
        report_pairs: raw pairs kept for the quality report.
    """

    def __init__(
        self, config: ClockSyncConfig | None = None, name: str = "clock", report_pairs: int = 4096
    ) -> None:
        self.config = config or ClockSyncConfig()
        self.name = name
        self._report_pairs = report_pairs
        self._bin_us = max(int(self.config.bin_s * 1e6), 1)
        self._origin: tuple[int, int] | None = None  # (src_us, host_ns) of the first pair
        # per bin of device time: id, device time of its lowest pair (us from origin), its d (ns), count
        self._bin_id = np.empty(0, dtype=np.int64)
        self._bin_s = np.empty(0, dtype=np.int64)
        self._bin_d = np.empty(0, dtype=np.int64)
        self._bin_n = np.empty(0, dtype=np.int64)
        self._recent_s = np.empty(0, dtype=np.int64)
        self._recent_d = np.empty(0, dtype=np.int64)
        self._newest_s = 0
        self._fit: ClockFit | None = None
        self._last_fit_s: int | None = None
        self._n_fits = 0
        # the run of new pairs off the fit on one side: side (+1 above, -1 below, 0 none), start, count
        self._step_side = 0
        self._step_from_s = 0
        self._run_s = np.empty(0, dtype=np.int64)
        self._run_d = np.empty(0, dtype=np.int64)
        self.steps = 0

    @property
    def fit(self) -> ClockFit | None:
        """The current fit, or None before ``min_pairs`` pairs."""
        return self._fit

    @property
    def n_pairs(self) -> int:
        """Pairs that fell into the bins still in the window."""
        return int(self._bin_n.sum())

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
        if self._origin is None:
            self._origin = (int(src[0]), int(host[0]))
        s = src - self._origin[0]
        d = (host - self._origin[1]) - s * 1000  # exact integers: host minus device time, ns
        if self._fit is not None and self.config.step_ms > 0:
            k = self._track_step(s, d, (host - self._fit.to_host_ns(src)) * 1e-6)
            s, d = s[k:], d[k:]
        self._merge_bins(s, d)
        self._recent_s = np.concatenate([self._recent_s, s])[-self._report_pairs :]
        self._recent_d = np.concatenate([self._recent_d, d])[-self._report_pairs :]
        self._newest_s = max(self._newest_s, int(s.max()))
        cutoff_bin = (self._newest_s - int(self.config.window_s * 1e6)) // self._bin_us
        if self._bin_id[0] < cutoff_bin:
            k = int(np.searchsorted(self._bin_id, cutoff_bin))
            self._bin_id, self._bin_s = self._bin_id[k:], self._bin_s[k:]
            self._bin_d, self._bin_n = self._bin_d[k:], self._bin_n[k:]
        due = (
            self._last_fit_s is None
            or self._newest_s - self._last_fit_s >= self.config.refit_interval_s * 1e6
        )
        if not due or self.n_pairs < self.config.min_pairs:
            return None
        self._fit = self._refit()
        self._last_fit_s = self._newest_s
        return self._fit

    def _track_step(self, s: np.ndarray, d: np.ndarray, above_ms: np.ndarray) -> int:
        """Follow the run of pairs far above the fit; on a confirmed step, forget every pair
        from before it (they describe the clock as it was, and after a backward step their device
        times overlap the new ones) and keep the run's. Returns the index of the first pair of
        ``s`` / ``d`` that still belongs in the window (0 unless a step began in this batch)."""
        cfg = self.config
        side = (above_ms > cfg.step_ms).astype(np.int64)
        last = int(side[-1])
        if last == 0:
            self._step_side, self._run_s, self._run_d = 0, s[:0], d[:0]
            return 0
        other = np.flatnonzero(side != last)
        k = int(other[-1]) + 1 if other.size else 0
        if k > 0 or self._step_side != last:
            self._step_side, self._step_from_s = last, int(s[k])
            self._run_s, self._run_d = s[:0], d[:0]
        run_s, run_d = self._run_s, self._run_d  # the run's pairs from earlier batches
        n = len(run_s) + len(side) - k
        confirmed = n >= cfg.min_pairs and int(s[-1]) - self._step_from_s >= cfg.step_confirm_s * 1e6
        if not confirmed:
            self._run_s, self._run_d = np.concatenate([run_s, s[k:]]), np.concatenate([run_d, d[k:]])
            return 0
        empty = np.empty(0, dtype=np.int64)
        self._bin_id, self._bin_s, self._bin_d, self._bin_n = empty, empty, empty, empty
        self._recent_s, self._recent_d = empty, empty
        self._newest_s = int(max(s.max(), run_s.max() if len(run_s) else s.max()))
        if len(run_s):
            self._merge_bins(run_s, run_d)
            self._recent_s, self._recent_d = run_s[-self._report_pairs :], run_d[-self._report_pairs :]
        self._last_fit_s = None  # refit as soon as the pairs after the step suffice
        self.steps += 1
        log.warning(
            "clock_step", clock=self.name, step_ms=round(float(np.median(above_ms[k:])), 3),
            at_device_s=round(self._step_from_s * 1e-6, 3), pairs=n,
        )  # fmt: skip
        self._step_side, self._run_s, self._run_d = 0, s[:0], d[:0]
        return k

    def _merge_bins(self, s: np.ndarray, d: np.ndarray) -> None:
        b = s // self._bin_us
        n = np.ones(len(b), dtype=np.int64)
        append = not len(self._bin_id) or b.min() > self._bin_id[-1]
        if not append:
            # late pairs touch existing bins: merge everything (rare: pairs arrive in device order)
            b = np.concatenate([self._bin_id, b])
            s = np.concatenate([self._bin_s, s])
            d = np.concatenate([self._bin_d, d])
            n = np.concatenate([self._bin_n, n])
        order = np.lexsort((d, b))
        bs = b[order]
        first = np.concatenate([[True], bs[1:] != bs[:-1]])
        counts = np.add.reduceat(n[order], np.flatnonzero(first))
        pick = order[first]  # the lowest pair of every bin
        if append:
            self._bin_id = np.concatenate([self._bin_id, b[pick]])
            self._bin_s = np.concatenate([self._bin_s, s[pick]])
            self._bin_d = np.concatenate([self._bin_d, d[pick]])
            self._bin_n = np.concatenate([self._bin_n, counts])
        else:
            self._bin_id, self._bin_s, self._bin_d, self._bin_n = b[pick], s[pick], d[pick], counts

    def _refit(self) -> ClockFit:
        cfg = self.config
        assert self._origin is not None
        s0, d0 = int(self._bin_s[0]), int(self._bin_d[0])
        s_s = (self._bin_s - s0).astype(np.float64) * 1e-6
        d_rel = (self._bin_d - d0).astype(np.float64)
        uniq = np.concatenate([[True], np.diff(s_s) > 0])  # bins finer than 1 us could share a time
        span_s = float(s_s[-1])
        max_slope = cfg.max_drift_ppm * 1e3 if span_s >= cfg.min_drift_span_s else 0.0
        a_ns, b_ns_per_s = fit_lower_envelope(s_s[uniq], d_rel[uniq], max_slope)
        rs = (self._recent_s - s0).astype(np.float64) * 1e-6
        above_ms = ((self._recent_d - d0).astype(np.float64) - (a_ns + b_ns_per_s * rs)) * 1e-6
        # both quantiles from one partial sort (the same values as two separate percentile calls)
        p50_ms, p95_ms = np.percentile(above_ms, [50, 95])
        return_fit = ClockFit(
            src_ref_us=self._origin[0] + s0,
            host_ref_ns=self._origin[1] + s0 * 1000 + d0,
            offset_ns=a_ns,
            drift_ppm=b_ns_per_s * 1e-3,
            n_pairs=self.n_pairs,
            span_s=float(self._bin_s[-1] - s0) * 1e-6,
            jitter_p50_ms=float(p50_ms),
            jitter_p95_ms=float(p95_ms),
            jitter_max_ms=float(above_ms.max()),
            spike_fraction=float(np.mean(above_ms > cfg.spike_ms)),
            fit_index=self._n_fits,
        )
        self._n_fits += 1
        return return_fit

    def refit_now(self) -> ClockFit | None:
        """Fit over every pair in the window now (e.g. once at the end of a scan); None if too few."""
        if self.n_pairs < self.config.min_pairs:
            return None
        self._fit = self._refit()
        self._last_fit_s = self._newest_s
        return self._fit

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
        line: a fixed line ``(f0, t0_us, intercept_us, us_per_frame)`` (from :meth:`line` over a
            whole scan) to use instead of the running regression.
    """

    def __init__(self, window: int = 4000, line: tuple[int, int, float, float] | None = None) -> None:
        if window < 2:
            raise ClockSyncError(f"FrameTimeline window must be >= 2, got {window}")
        self.window = window
        self._f = np.empty(0, dtype=np.int64)
        self._t_us = np.empty(0, dtype=np.int64)
        self._fixed = line

    def line(self) -> tuple[int, int, float, float] | None:
        """The regression over the frames in the window: ``(f0, t0_us, intercept_us, us_per_frame)``."""
        if len(self._f) < 2 or self._f[-1] == self._f[0]:
            return None
        f0, t0 = int(self._f[0]), int(self._t_us[0])
        x = (self._f - f0).astype(np.float64)
        y = (self._t_us - t0).astype(np.float64)
        xm, ym = x.mean(), y.mean()
        slope = float(np.dot(x - xm, y - ym) / np.dot(x - xm, x - xm))
        return f0, t0, float(ym - slope * xm), slope

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
        if self._fixed is None:
            self._f = np.concatenate([self._f, f])[-self.window :]
            self._t_us = np.concatenate([self._t_us, t])[-self.window :]
        line = self._fixed or self.line()
        if line is None:
            return t.copy()
        f0, t0, icpt, slope = line
        return t0 + np.rint(icpt + slope * (f - f0).astype(np.float64)).astype(np.int64)
