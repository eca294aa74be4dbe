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
    c2 = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(xc ** 2, axis=0)])
    w = 2 * h + 1
    s1 = c1[w:] - c1[:-w]
    s2 = c2[w:] - c2[:-w]
    var = np.maximum(s2 / w - (s1 / w) ** 2, 0.0) * w / (w - 1)  # unbiased, as IMU-TK
    out[h:n - h] = np.sqrt((var ** 2).sum(axis=1))
    return out


def runs_of(mask: np.ndarray) -> list[tuple[int, int]]:
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1).tolist(), np.flatnonzero(d == -1).tolist()))


def detect_static(x: np.ndarray, window: int = 101, multiplier: float = 6.0,
                  init_samples: int | None = None, quantile: float = 0.05,
                  min_samples: int | None = None, unit: str = "") -> StaticDetection:
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
    return StaticDetection(stat, threshold, floor, float(multiplier), int(window), floor_from,
                           intervals, unit)


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


def static_pose_means(t: np.ndarray, gyro: np.ndarray, accel: np.ndarray, intervals,
                      names=None, trim: int = 0) -> pd.DataFrame:
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
        row = {"pose": names[k] if names is not None else k, "start": a2, "end": b2,
               "count": b2 - a2, "t_mid": float(0.5 * (t[a2] + t[b2 - 1]))}
        for i, c in enumerate(("gx", "gy", "gz")):
            row[c] = g[:, i].mean()
            row[f"{c}_std"] = g[:, i].std(ddof=1)
        for i, c in enumerate(("ax", "ay", "az")):
            row[c] = f[:, i].mean()
            row[f"{c}_std"] = f[:, i].std(ddof=1)
        rows.append(row)
    return pd.DataFrame(rows)
