"""Static interval detection from the data itself, and static-pose means.

The statistic is IMU-TK's (Tedaldi et al. 2014, sec. IV-A): for every sample the magnitude of
the per-axis variance in a centred window of ``window`` samples,

    s(t) = sqrt(var_w(x)^2 + var_w(y)^2 + var_w(z)^2)          [input unit^2]

A sample is static where ``s < threshold``. The threshold is ``multiplier * noise_floor`` where
the noise floor is taken from the data, never tuned per file:

* ``floor_from="initial"``: the same variance magnitude over the initial static period
  (Tedaldi's choice; the recording must start at rest for ``init_samples`` samples);
* ``floor_from="quantile"``: a low quantile of ``s`` itself (the quietest windows), for
  recordings that do not start with a known rest period.

Everything is returned (statistic, floor, threshold, intervals) so a report can plot it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd


@dataclass(frozen=True)
class StaticDetection:
    """Result of :func:`detect_static`. Intervals are sample indices ``[start, end)``."""

    statistic: np.ndarray  # (n,) windowed variance magnitude, NaN within window/2 of the ends
    threshold: float  # same unit as statistic
    noise_floor: float
    multiplier: float
    window: int  # samples
    floor_from: str  # "initial" | "quantile"
    intervals: tuple[tuple[int, int], ...]
    unit: str = ""  # unit of the statistic, e.g. "LSB^2" or "g^2"

    @property
    def mask(self) -> np.ndarray:
        m = np.zeros(len(self.statistic), bool)
        for a, b in self.intervals:
            m[a:b] = True
        return m

    def __len__(self) -> int:
        return len(self.intervals)


def moving_variance_magnitude(x: np.ndarray, window: int = 101) -> np.ndarray:
    """``s(t)`` above, O(n) with cumulative sums (centred on the data mean to keep precision
    on raw counts near 32768). The first and last ``window // 2`` samples are NaN."""
    x = np.asarray(x, float)
    n = len(x)
    h = window // 2
    out = np.full(n, np.nan)
    if n < window:
        return out
    xc = x - x.mean(axis=0)
    c1 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(xc, axis=0)])
    c2 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(xc**2, axis=0)])
    w = 2 * h + 1
    s1 = c1[w:] - c1[:-w]
    s2 = c2[w:] - c2[:-w]
    var = np.maximum(s2 / w - (s1 / w) ** 2, 0.0) * w / (w - 1)  # unbiased, as IMU-TK
    out[h : n - h] = np.sqrt((var**2).sum(axis=1))
    return out


def runs_of(mask: np.ndarray) -> list[tuple[int, int]]:
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def detect_static(
    x: np.ndarray,
    window: int = 101,
    multiplier: float = 6.0,
    init_samples: int | None = None,
    quantile: float = 0.05,
    min_samples: int | None = None,
    unit: str = "",
) -> StaticDetection:
    """Static intervals of a 3-axis signal (normally the accelerometer).

    ``init_samples`` given: noise floor = variance magnitude of ``x[:init_samples]`` (Tedaldi);
    otherwise the ``quantile`` of the statistic. Runs shorter than ``min_samples`` (default:
    the window) are dropped."""
    x = np.asarray(x, float)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"x must be (n, 3), got {x.shape}")
    stat = moving_variance_magnitude(x, window)
    if init_samples:
        if init_samples < 3 or init_samples > len(x):
            raise ValueError(f"init_samples={init_samples} outside 3..{len(x)}")
        floor = float(np.linalg.norm(np.var(x[:init_samples], axis=0, ddof=1)))
        floor_from = "initial"
    else:
        finite = stat[np.isfinite(stat)]
        if finite.size == 0:
            raise ValueError(f"recording shorter than the window ({len(x)} < {window} samples)")
        floor = float(np.quantile(finite, quantile))
        floor_from = "quantile"
    threshold = multiplier * floor
    min_samples = window if min_samples is None else min_samples
    static = np.isfinite(stat) & (stat < threshold)
    intervals = tuple((a, b) for a, b in runs_of(static) if b - a >= min_samples)
    return StaticDetection(
        stat, threshold, floor, float(multiplier), int(window), floor_from, intervals, unit
    )


def central_samples(intervals, n_samples: int) -> list[tuple[int, int]]:
    """The central ``n_samples`` of each interval (IMU-TK's ``extractIntervalsSamples``);
    intervals shorter than that are dropped."""
    out = []
    for a, b in intervals:
        if b - a >= n_samples:
            mid = (a + b) // 2
            s = mid - n_samples // 2
            out.append((s, s + n_samples))
    return out


def static_pose_means(
    t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, intervals, names=None, trim: int = 0
) -> pd.DataFrame:
    """One row per static pose: name, start, end (sample indices, end exclusive), count,
    t_mid [s], mean and sample std of the raw gyro (gx..gz) and accel (ax..az).

    The handover to model discovery on real recordings: raw outputs per pose in the
    recording's units, with their spread and time, so a replay/residual analysis can be run
    without re-reading samples. ``trim`` samples are dropped at each end of every pose."""
    t = np.asarray(t, float)
    G = np.asarray(gyro, float)
    A = np.asarray(accel, float)
    rows = []
    for k, (a, b) in enumerate(intervals):
        a2, b2 = a + trim, b - trim
        if b2 - a2 < 2:
            continue
        g, f = G[a2:b2], A[a2:b2]
        row = {
            "pose": names[k] if names is not None else k,
            "start": a2,
            "end": b2,
            "count": b2 - a2,
            "t_mid": float(0.5 * (t[a2] + t[b2 - 1])),
        }
        for i, c in enumerate(("gx", "gy", "gz")):
            row[c] = g[:, i].mean()
            row[f"{c}_std"] = g[:, i].std(ddof=1)
        for i, c in enumerate(("ax", "ay", "az")):
            row[c] = f[:, i].mean()
            row[f"{c}_std"] = f[:, i].std(ddof=1)
        rows.append(row)
    return pd.DataFrame(rows)


# --- hand-held poses ------------------------------------------------------------------------
@dataclass(frozen=True)
class Pose:
    """One static pose, sample indices ``[start, end)``. ``gyro_quiet``: the gyro statistic
    is at its noise floor too (no residual rotation), so the pose's mean raw gyro is a bias
    observation; a pose held by hand often turns slowly (<1 deg/s) while the accelerometer
    is at rest, and is then used for |f| and the gravity direction but not for the bias."""

    start: int
    end: int
    gyro_quiet: bool
    accel_ratio: float  # median accel statistic / accel noise floor
    gyro_ratio: float  # 90th percentile of the gyro statistic / gyro noise floor

    @property
    def mid(self) -> int:
        return (self.start + self.end) // 2

    def __len__(self) -> int:
        return self.end - self.start


@dataclass(frozen=True)
class RejectedPose:
    start: int
    end: int
    reason: str


@dataclass(frozen=True)
class PoseDetection:
    """Static poses of a hand-held recording (:func:`detect_poses`)."""

    poses: tuple[Pose, ...]
    rejected: tuple[RejectedPose, ...]
    window: int  # samples of the variance window
    min_samples: int  # shortest pose accepted
    rate_hz: float  # median sample rate of the recording
    accel_floor: float  # statistic units (raw unit^2)
    gyro_floor: float
    multiplier: float
    floor_from: str  # "initial" | "quantile"
    accel_statistic: np.ndarray
    gyro_statistic: np.ndarray

    def intervals(self) -> list[tuple[int, int]]:
        return [(p.start, p.end) for p in self.poses]

    def __len__(self) -> int:
        return len(self.poses)


def odd_window(rate_hz: float, window_s: float) -> int:
    """Samples in a centred window of ``window_s`` seconds: the nearest count, made odd by
    adding one if needed (at least 5)."""
    n = round(window_s * rate_hz)
    return max(5, n if n % 2 else n + 1)


def detect_poses(
    t: np.ndarray,
    gyro: np.ndarray,
    accel: np.ndarray,
    init_s: float | None = None,
    window_s: float = 0.25,
    min_pose_s: float = 1.0,
    multiplier: float = 3.0,
    loose_multiplier: float = 10.0,
    quiet_multiplier: float = 2.0,
    turn_multiplier: float = 1000.0,
    quantile: float = 0.05,
) -> PoseDetection:
    """Static poses of a recording moved by hand, with every threshold from the data.

    The window (``window_s``) and the shortest pose (``min_pose_s``) are in seconds and
    converted with the recording's own median sample rate, so a 50 Hz and a 1 kHz logger get
    the same poses. Noise floors of the accelerometer and gyro statistics
    (:func:`moving_variance_magnitude`): their median over the initial rest (``init_s``
    seconds) or, without one, their ``quantile`` over the whole recording (the quietest
    windows). A pose is a run where the accel statistic is below ``multiplier`` x floor for
    at least ``min_pose_s`` (runs apart by at most two windows, with the statistic below
    ``loose_multiplier`` x floor in between, are one pose). A pose is ``gyro_quiet`` (a bias
    observation) when the 90th percentile of its gyro statistic is below ``quiet_multiplier``
    x the gyro floor: stricter than the accelerometer's test, because a hand's slow wobble
    moves a pose's mean rate by tens of counts while its variance grows only 2-3x, and a turn
    about the vertical, invisible to the accelerometer, must not enter a bias. Rejected and listed:
    runs below ``loose_multiplier`` x floor that
    hold no pose (residual motion), and quiet runs shorter than ``min_pose_s``."""
    t = np.asarray(t, float)
    G = np.asarray(gyro, float)
    A = np.asarray(accel, float)
    if len(t) < 10:
        raise ValueError(f"recording of {len(t)} samples is too short")
    rate = float(1.0 / np.median(np.diff(t)))
    window = odd_window(rate, window_s)
    min_samples = max(window, int(np.ceil(min_pose_s * rate)))
    s_a = moving_variance_magnitude(A, window)
    s_g = moving_variance_magnitude(G, window)
    if init_s:
        n0 = int(np.searchsorted(t, t[0] + init_s))
        ref = np.zeros(len(t), bool)
        ref[:n0] = True
        ref &= np.isfinite(s_a)
        if ref.sum() < window:
            raise ValueError(f"initial rest of {init_s} s holds fewer than {window} samples")
        floor_a, floor_g, floor_from = float(np.median(s_a[ref])), float(np.median(s_g[ref])), "initial"
    else:
        fa, fg = s_a[np.isfinite(s_a)], s_g[np.isfinite(s_g)]
        if fa.size == 0:
            raise ValueError(f"recording shorter than the window ({len(t)} < {window} samples)")
        floor_a, floor_g, floor_from = (
            float(np.quantile(fa, quantile)),
            float(np.quantile(fg, quantile)),
            "quantile",
        )
    floor_a, floor_g = max(floor_a, 1e-300), max(floor_g, 1e-300)
    finite = np.isfinite(s_a)
    # a turn about the vertical leaves the accelerometer at rest: the gyro cuts the pose there
    turning = np.isfinite(s_g) & (s_g > turn_multiplier * floor_g)
    strict = []
    for a, b in runs_of(finite & (s_a < multiplier * floor_a) & ~turning):
        # a twitch of the hand inside one pose does not split it: a disturbance of d samples
        # lifts the windowed statistic for d + window - 1 samples, so gaps up to two windows
        # are twitches shorter than a window
        if (
            strict
            and a - strict[-1][1] <= 2 * window
            and np.all(s_a[strict[-1][1] : a] < loose_multiplier * floor_a)
        ):
            strict[-1] = (strict[-1][0], b)
        else:
            strict.append((a, b))
    poses = []
    for a, b in strict:
        if b - a >= min_samples:
            ra = float(np.median(s_a[a:b]) / floor_a)
            rg = float(np.quantile(s_g[a:b], 0.9) / floor_g)  # a turn in a tenth of it shows
            poses.append(Pose(a, b, rg < quiet_multiplier, ra, rg))
    rejected = []
    for a, b in runs_of(finite & (s_a < loose_multiplier * floor_a)):
        if b - a < min_samples or any(p.start < b and p.end > a for p in poses):
            continue
        rejected.append(
            RejectedPose(
                a, b, f"residual motion: accel variance {np.median(s_a[a:b]) / floor_a:.1f} x noise floor"
            )
        )
    for a, b in strict:
        if window <= b - a < min_samples:
            rejected.append(RejectedPose(a, b, f"too short: {(b - a) / rate:.2f} s < {min_pose_s:g} s"))
    rejected.sort(key=lambda r: r.start)
    return PoseDetection(
        tuple(poses),
        tuple(rejected),
        window,
        min_samples,
        rate,
        floor_a,
        floor_g,
        float(multiplier),
        floor_from,
        s_a,
        s_g,
    )


def clipped_samples(x: np.ndarray, full_scale: float | None = None, min_repeats: int = 2) -> np.ndarray:
    """Samples where any axis sits at the sensor's limit (a saturated gyro in a fast hand
    move): ``|x| >= full_scale`` when the limit is known (e.g. 32767 counts for an int16
    output), else, per axis, the recording's largest or smallest value when it occurs at
    least ``min_repeats`` times (a clipped output repeats its limit; a real peak does not)."""
    x = np.asarray(x, float)
    if full_scale is not None:
        return np.any(np.abs(x) >= full_scale, axis=1)
    out = np.zeros(len(x), bool)
    for i in range(x.shape[1]):
        col = x[:, i]
        for extreme in (col.max(), col.min()):
            hit = col == extreme
            if hit.sum() >= min_repeats:
                out |= hit
    return out
