"""Model discovery: where the fitted model is wrong, which physical effect explains it, and
what extending the model buys on data it was not fitted to.

The model of a unit over R repetitions, per channel c (gx gy gz in deg/s, ax ay az in g):

    ref_c(step) = K_c . raw(step) + b_c(rep) - sum_T E_T,c(step) theta_T

K is shared by the repetitions; each repetition has its own biases b (turn-on
repeatability is not an effect); every catalogue term T (:func:`calib_core.effects.catalogue`)
adds its regressors E_T. All of it is linear, so the fit is one weighted least squares over
every step of both sensors (gyro channels during multiposition steps and accelerometer
channels during rotation steps included). Even-in-rate terms are visible because steps enter
one by one, not as the +/- differences of xu2016 (which cancel them).

Weights are 1/sigma of each step mean, estimated from the data (:mod:`calib_core.discovery.replay`):
within-step scatter plus the step-to-step scatter seen across repetitions.

Tests (alpha is the family-wise false-alarm rate per unit, default 1%):

- **misfit** (lack of fit): the residual of the model is split into *pure error* (the
  repetition-to-repetition scatter) and *lack of fit* (the mean over the repetitions the
  model does not explain), both projected on the directions the model leaves free
  (:meth:`_Discovery.projected_lack_of_fit`): F = (SS_lof/dof_lof) / (SS_pure/dof_pure)
  against F with Satterthwaite dof. A systematic error common to the repetitions inflates
  SS_lof only. "The unit misfits" is the union of the overall test (alpha / 4), the six
  channels' (alpha / 24 each) and every candidate's targeted test (its mean residual on the
  term's joint directions against the repetitions' scatter along every channel's copy of
  them, alpha / 2 over the candidates): at most alpha on a unit that fits.
- **a term** T added to the current set S: F = (dSS/p) / (SS_pure/dof_pure) against
  F(p, dof_pure) (p = rank gained), at alpha / 2 / (number of candidate terms) (Bonferroni
  over the catalogue), *and* its leave-one-repetition-out held-out rms must drop (gain > 1).
- forward selection adds the most significant eligible term and repeats; a backward pass
  drops any chosen term no longer significant given the others.
- a chosen term must fix at least one channel it acts on that misfit at baseline
  (per-channel lack-of-fit test at alpha/24), or, when no channel misfits, be what makes the
  unit misfit; a term that leaves all of them misfit only
  soaks up part of something else and is reported as a *partial* candidate, not an effect.
- **misfit**: the union test above rejects at baseline, or a term was chosen.
- **unexplained**: the lack-of-fit test still rejects after selection, or a partial term was
  set aside.

Held-out score: each repetition in turn is held out, the model is fitted on the others,
the held-out repetition is predicted (its own biases fitted, as at turn-on) and its residual
normalised by sigma; rms over all folds. ``gain`` = rms without the term / rms with it, over
the channels the term acts on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Any, NamedTuple

import numpy as np
import pandas as pd
from scipy import special, stats

from calib_core.calibration import Calibration, TermValue
from calib_core.discovery.identifiability import (
    Confounded,
    Identifiability,
    analyse,
    near_confounded,
    orthonormal_basis,
)
from calib_core.discovery.presentation import evidence_frame
from calib_core.discovery.replay import (
    MIN_POOL_DOF,
    NOISE_COLUMNS,
    NoiseEstimate,
    replay_unit,
    test_group,
    two_way_residual,
)
from calib_core.discovery.results import (
    DEFAULT_ALPHA,
    DEFAULT_MIN_GAIN,
    EXCITED_SHARE,
    ConfoundedFinding,
    EffectFinding,
    FTest,
    f_test,
    jsonable,
)
from calib_core.discovery.selection import stepwise
from calib_core.effects import CHANNELS, MotionContext, SensingGeometry, catalogue, get_effect
from calib_core.errors import DesignError
from calib_core.steps import StepMeans

_RCOND = 1e-10
# terms whose columns share a direction up to this sine of angle (the part of a column the
# others do not explain is below 5 % of it) are tested together: calib_core.discovery.identifiability
CONFOUNDING_TOL = 0.05
# a term column's part that differs between the repetitions, relative to the column, below
# which the between-repetition test does not run (the recorded temperature's noise alone
# makes a few parts in 1e3)
REP_VARYING_MIN = 0.05
# a triad's summed lag-1 correlation of the pure error, in standard errors of white noise,
# above which its steps are modelled as serially correlated (one-sided, 0.13 % per triad):
# without a gate the sign of two noisy correlations switched the model on for 44 % of
# units with white noise only
SERIAL_MIN_Z = 3.0


# -- one unit on a (repetition, step) grid ----------------------------------------------
# Why this layout: every quantity discovery needs (fits of any term subset on any
# leave-one-repetition-out fold, per-channel residual sums of squares, pure error, held-out
# residuals) is a quadratic form in a small coefficient vector v_c = [-K_c, -theta, 1] over
# the channel's weighted, bias-removed design A_c = w (M_c - weighted mean per repetition).
# Factorising A_c once per (channel, repetition) block (R factors, k x k with k ~ 10) turns
# all of them into products of small triangular matrices: nothing per row after the set-up.
@dataclass
class _UnitGrid:
    """Repetitions of a unit on a (repetition, step) grid, padded to the longest repetition
    (padding rows: ``real`` False, weight 0, in no sum)."""

    R: int
    n: int
    real: np.ndarray  # (R, n) bool
    step: np.ndarray  # (R, n) step id, -1 on padding
    gcode: np.ndarray  # (R, n) index into groups, -1 on padding
    groups: list[str]  # test groups (noise pooling), sorted
    y: np.ndarray  # (R, n, 6) references
    raw: np.ndarray  # (R, n, 6, 3) raw outputs of each channel's sensor
    std: np.ndarray  # (R, n, 6, 3) within-step std of each channel's sensor outputs
    count: np.ndarray  # (R, n) samples averaged (1 on padding)
    names: list[str]  # catalogue terms, sorted; the P term columns in this order
    offset: dict[str, tuple[int, int]]
    live: list[np.ndarray]  # per channel: term columns not identically 0 on it
    live_mask: np.ndarray  # (6, P) bool, the same
    balanced: bool  # every repetition has the same steps in the same order
    t: np.ndarray  # (R, n) step mid times, s (0 on padding)
    M: np.ndarray  # (6, R, n, k) per channel: [raw_c | live term columns | 0 | y_c]
    colmap: np.ndarray  # (6, k - 4) global term column of M's term columns (P + 1: padding)

    @classmethod
    def build(
        cls,
        sessions: list[StepMeans],
        names: list[str],
        geometry: SensingGeometry | None = None,
        dropped: frozenset[int] = frozenset(),
        layout: _Layout | None = None,
    ) -> _UnitGrid:
        """The unit's grid with the terms' columns through ``geometry`` (default: the
        nominal one); ``dropped`` term columns (undetermined parameters) are left at 0.
        ``layout``: the sessions' :func:`_layout` when the caller already has it."""
        lay = layout if layout is not None else _layout(sessions)
        R, n = lay.real.shape
        raw = np.zeros((R, n, 6, 3))
        std = np.zeros((R, n, 6, 3))
        count = np.ones((R, n))
        for r, sm in enumerate(sessions):
            m = len(sm)
            raw[r, :m, :3], raw[r, :m, 3:] = sm.gyro[:, None, :], sm.accel[:, None, :]
            std[r, :m, :3], std[r, :m, 3:] = sm.gyro_std[:, None, :], sm.accel_std[:, None, :]
            count[r, :m] = np.maximum(np.asarray(sm.count, float), 1.0)
        offset, live, live_mask, M, colmap = _term_design(lay, names, geometry, dropped)
        M[..., :3] = np.moveaxis(raw, 2, 0)
        return cls(
            R,
            n,
            lay.real,
            lay.step,
            lay.gcode,
            list(lay.groups),
            lay.y,
            raw,
            std,
            count,
            list(names),
            offset,
            live,
            live_mask,
            lay.balanced,
            lay.t,
            M,
            colmap,
        )

    @property
    def P(self) -> int:
        return self.live_mask.shape[1]

    def cols(self, names: tuple[str, ...]) -> np.ndarray:
        """Global term columns of the terms ``names``, in that order (read-only: kept per
        grid, asked for by every fit and test of the same term set)."""
        cache = self.__dict__.setdefault("_cols", {})
        out = cache.get(names)
        if out is None:
            out = (
                np.concatenate([np.arange(*self.offset[n]) for n in names])
                if names
                else np.zeros(0, np.int64)
            )
            out.setflags(write=False)
            cache[names] = out
        return out

    def white_sigma(self, K: np.ndarray) -> np.ndarray:
        """Within-step scatter of the step mean through the 6x3 gain rows K, (R, n, 6)
        (:func:`calib_core.discovery.replay.white_sigma` for every repetition at once)."""
        return np.sqrt(np.einsum("rnck,ck->rnc", self.std**2, K**2)) / np.sqrt(self.count)[..., None]

    def _balanced_groups(self) -> tuple[np.ndarray, ...]:
        """For :meth:`two_way` on a balanced grid (what depends on the steps alone, kept on
        the grid): each step's group g (n,), its one-hot matrix G (n, ng), the steps per
        group, every row's group (R n,) and the degrees of freedom per group."""
        out = self.__dict__.get("_balanced")
        if out is None:
            g = self.gcode[0]
            G = np.zeros((self.n, len(self.groups)))
            G[np.arange(self.n), g] = 1.0
            cnt = G.sum(axis=0)
            out = (g, G, cnt, np.tile(g, self.R), ((cnt - 1) * (self.R - 1)).astype(np.int64))
            for a in out:
                a.setflags(write=False)
            self.__dict__["_balanced"] = out
        return out

    # -- pure error: the two-way (step x repetition) residual within each test group ------
    def two_way(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Two-way residual of X (..., R, n, k) per test group (a value per step and per
        repetition removed, :func:`calib_core.discovery.replay.two_way_residual`), as rows (..., m, k),
        the group of each row (m,) and the degrees of freedom per group."""
        ng = len(self.groups)
        if self.balanced:  # double centring of every group's (step x repetition) table
            g, G, cnt, grp, dof = self._balanced_groups()
            rep_mean = (X.swapaxes(-1, -2) @ G) / cnt  # (..., R, k, ng)
            grand = rep_mean.mean(axis=-3, keepdims=True)
            e = X - X.mean(axis=-3, keepdims=True) - (rep_mean - grand)[..., g].swapaxes(-1, -2)
            return (e.reshape(X.shape[:-3] + (-1, X.shape[-1])), grp, dof.copy())
        lead = X.shape[:-3]
        Xf = X.reshape((-1,) + X.shape[-3:])
        out, grp, dof = [], None, np.zeros(ng, np.int64)
        r_idx = np.broadcast_to(np.arange(self.R)[:, None], self.real.shape)
        for Xi in Xf:  # one per channel at most
            rows, grp = [], []
            for gi in range(ng):
                m = self.gcode == gi
                e, d = two_way_residual(Xi[m], self.step[m], r_idx[m])
                rows.append(e)
                grp.append(np.full(len(e), gi))
                dof[gi] = d
            out.append(np.concatenate(rows))
            grp = np.concatenate(grp)
        e = np.stack(out).reshape(lead + (-1, X.shape[-1]))
        return e, grp, dof


@dataclass(frozen=True)
class _Layout:
    """What a unit's grid takes from its protocol alone (steps, tests, references, motion),
    not from the unit's outputs: the same for every unit measured with that protocol. Arrays
    are read-only (shared by those units)."""

    real: np.ndarray  # (R, n)
    step: np.ndarray
    gcode: np.ndarray
    groups: list[str]
    y: np.ndarray  # (R, n, 6)
    balanced: bool
    t: np.ndarray  # (R, n) step mid times
    ctx: list[MotionContext]  # per repetition


def _layout(sessions: list[StepMeans]) -> _Layout:
    """The grid's layout of these repetitions, read-only: built once per unit's discovery and
    shared by its grids. Not kept for the next unit: a process-wide cache of layouts keyed on
    the sessions' bytes hit only on simulated fleets, whose step mid-times are identical to the
    bit (docs/benchmarks.md)."""
    lay = _build_layout(sessions)
    for a in (lay.real, lay.step, lay.gcode, lay.y, lay.t):
        a.setflags(write=False)
    return lay


def _test_names(sm: StepMeans) -> np.ndarray:
    return np.asarray(sm.test).astype(str)


def _build_layout(sessions: list[StepMeans]) -> _Layout:
    R = len(sessions)
    lens = [len(sm) for sm in sessions]
    n = max(lens)
    real = np.zeros((R, n), bool)
    step = np.full((R, n), -1, np.int64)
    y = np.zeros((R, n, 6))
    t = np.zeros((R, n))
    tests, ctxs = [], []
    for r, sm in enumerate(sessions):
        m = len(sm)
        real[r, :m] = True
        step[r, :m] = sm.step.astype(np.int64)
        y[r, :m, :3], y[r, :m, 3:] = sm.w_ref, sm.f_ref
        t[r, :m] = np.asarray(sm.t_mid, float)
        ctxs.append(
            MotionContext.from_refs(
                sm.w_ref,
                sm.f_ref,
                temp_c=sm.temp_c,
                t=sm.t_mid,
                g_local=sm.g_local,
                heading_deg=sm.headings,
                latitude_deg=sm.latitude_deg,
                table_heading_deg=sm.table_heading_deg,
                turned_deg=sm.turned_deg(),
            )
        )
        tests.append(np.unique(_test_names(sm), return_inverse=True))
    # test groups: mapped per distinct test name, not per step
    groups = sorted({test_group(t) for u, _ in tests for t in u})
    gcode = np.full((R, n), -1, np.int64)
    for r, (u, inv) in enumerate(tests):
        gcode[r, : lens[r]] = np.array([groups.index(test_group(t)) for t in u])[inv]
    balanced = (
        len(set(lens)) == 1
        and all(np.array_equal(step[0], s) for s in step)
        and all(np.array_equal(gcode[0], g) for g in gcode)
        and len(np.unique(step[0])) == n
    )
    return _Layout(real, step, gcode, groups, y, balanced, t, ctxs)


def _term_design(lay: _Layout, names: list[str], geometry: SensingGeometry | None, dropped: frozenset[int]):
    """The terms' columns of one unit: every term's regressors through the unit's sensing
    geometry, per channel only the columns not identically 0 on it (``live``), laid out as
    M (6, R, n, k) = [raw (filled by the caller) | live term columns | 0 | y]."""
    terms = [get_effect(nm) for nm in names]
    offset, off = {}, 0
    for nm, t in zip(names, terms):
        offset[nm] = (off, off + t.n_params)
        off += t.n_params
    P = off
    R, n = lay.real.shape
    Zs, live_mask = [], np.zeros((6, P), bool)
    for ctx in lay.ctx:
        # minus the regressors: ref = K raw + b - E theta
        Z = -np.concatenate([t.regressors(ctx, geometry) for t in terms], axis=-1)
        if dropped:
            Z[..., sorted(dropped)] = 0.0
        Zs.append(Z)
        live_mask |= np.abs(Z).sum(axis=0) > 0
    live = [np.flatnonzero(m) for m in live_mask]
    k = 3 + max(len(L) for L in live) + 1
    M = np.zeros((6, R, n, k))
    colmap = np.full((6, k - 4), P + 1)  # global term column of each, P + 1 = none
    M[..., -1] = np.moveaxis(lay.y, 2, 0)
    for c in range(6):
        L = live[c]
        colmap[c, : len(L)] = L
        for r, Z in enumerate(Zs):
            M[c, r, : len(Z), 3 : 3 + len(L)] = Z[:, c, L]
    return offset, live, live_mask, M, colmap


@dataclass(frozen=True)
class _SerialNoise:
    """Noise of the step means of one repetition, per channel, as white noise plus a bias
    that wanders as a first-order Gauss-Markov process (the bias instability of a MEMS
    sensor, time constant tens of seconds, several steps long): correlation between two
    steps ``lam * exp(-|dt| / tau)``. ``lam`` 0: independent steps."""

    lam: np.ndarray  # (6,) share of the step-mean variance that wanders
    tau_s: np.ndarray  # (6,) its time constant

    @property
    def correlated(self) -> bool:
        return bool(np.any(self.lam > 0))


def _serial_noise(z: np.ndarray, real: np.ndarray, t: np.ndarray) -> _SerialNoise:
    """Estimate :class:`_SerialNoise` from the normalised residual z (R, n, 6) of a model,
    with every step's mean over the repetitions (any systematic error) and every
    repetition's mean (its turn-on bias) removed. Lag-1 and lag-2 correlations between
    consecutive steps give the decay per step (r2 / r1, pooled over a sensor triad) and the
    wandering share (r1 / decay); ``t`` (R, n) step times give the time constant. A triad
    whose summed lag-1 correlation is within ``SERIAL_MIN_Z`` standard errors of white
    noise is left white."""
    m = real[..., None].astype(float)
    z = z * m
    z = (z - z.sum(axis=0) / np.maximum(m.sum(axis=0), 1.0)) * m
    z = (z - z.sum(axis=1, keepdims=True) / np.maximum(m.sum(axis=1, keepdims=True), 1.0)) * m
    cnt = [max(int(real.sum()), 1)] + [max(int((real[:, k:] & real[:, :-k]).sum()), 1) for k in (1, 2)]
    c0 = np.sum(z**2, axis=(0, 1)) / cnt[0]
    c1 = np.sum(z[:, 1:] * z[:, :-1], axis=(0, 1)) / cnt[1]
    c2 = np.sum(z[:, 2:] * z[:, :-2], axis=(0, 1)) / cnt[2]
    dt = np.diff(t, axis=1)[real[:, 1:] & real[:, :-1]]
    step_s = float(np.median(dt)) if dt.size and np.median(dt) > 0 else 1.0
    n = max(float(real.sum(axis=1).mean()), 2.0)
    lam, tau = np.zeros(6), np.ones(6)
    lag = np.arange(1, int(n))
    var_mean = np.zeros(6)
    for _ in range(3):
        # removing each repetition's mean lowers every autocovariance by the variance of
        # that mean (about var / n (1 + 2 sum (1 - j/n) rho_j)): put it back
        r1 = np.where(c0 > 0, (c1 + var_mean) / np.where(c0 > 0, c0 + var_mean, 1.0), 0.0)
        r2 = np.where(c0 > 0, (c2 + var_mean) / np.where(c0 > 0, c0 + var_mean, 1.0), 0.0)
        for tri in (slice(0, 3), slice(3, 6)):
            s1, s2 = r1[tri].sum(), r2[tri].sum()
            if s1 <= SERIAL_MIN_Z * np.sqrt(3.0 / cnt[1]) or s2 <= 0:
                lam[tri] = 0.0
                continue
            decay = float(np.clip(s2 / s1, 0.05, 0.98))
            lam[tri] = np.clip(r1[tri] / decay, 0.0, 0.98)
            tau[tri] = -step_s / np.log(decay)
        phi = np.exp(-step_s / tau)
        total = c0 + var_mean
        var_mean = total / n * (1.0 + 2.0 * lam * np.array([np.sum((1.0 - lag / n) * p**lag) for p in phi]))
    return _SerialNoise(lam, tau)


# lags of the leftover serial correlation counted by _dof_inflation (the steps a first-order
# wander of 20 s spans after whitening: its leftover correlation is gone by then)
_INFLATION_LAGS = 5


def _dof_inflation(dev: np.ndarray) -> float:
    """Satterthwaite factor (>= 1) by which the effective degrees of freedom of a sum of
    squares of noise with covariance M fall below its count: n tr(M^2) / tr(M)^2, estimated
    from the repetitions' deviations ``dev`` (R, n) (each step's mean over the repetitions
    removed, so R - 1 dof per step). Unequal step variances (v_i, whose square is corrected
    for its own estimation noise: E v^2 = m^2 (R + 1) / (R - 1)) and the serial correlation
    left after whitening (lags 1.._INFLATION_LAGS, 1 + 2 sum rho_k^2) both make the sums
    spread more than the F distribution of the nominal dof assumes."""
    R, n = dev.shape
    v = np.sum(dev**2, axis=0) / (R - 1)
    if not np.any(v > 0):
        return 1.0
    hetero = n * np.sum(v**2) * (R - 1) / (R + 1) / np.sum(v) ** 2
    c0 = np.sum(dev**2)
    rho2 = sum(
        (np.sum(dev[:, k:] * dev[:, :-k]) / c0) ** 2 for k in range(1, min(_INFLATION_LAGS, n - 1) + 1)
    )
    return float(max(hetero, 1.0) * (1.0 + 2.0 * rho2))


def _variance_dof_cost(dof: float, white_share: float) -> float:
    """Pure-error dof (0..2) that one step-mean variance costs when it is estimated from
    ``dof`` dof of the pure error and then weights the rows that test against that pure
    error. The weight is 1 / max(s^2, w^2) (the within-step white part w^2 is known, only the
    excess over it is estimated; ``white_share`` = w^2 / s^2), so with q = s^2 / sigma^2 ~
    chi2_d / d and W the white share, a group's weighted pure error is d E[q / max(q, W)]
    and its weighted lack of fit scales as E[1 / max(q, W)]: the F's mean is right when the
    pure dof are d E[q / max(q, W)] / E[1 / max(q, W)], i.e. net of this cost. Estimated
    weights (W -> 0) cost 2, because E[1 / q] = d / (d - 2), not the 1 of a fitted
    parameter; a variance that is mostly the known white part (W >= 1) costs nothing.
    Both expectations in closed form: E[chi2_d; chi2_d < x] = d F_(d+2)(x) and
    E[1 / chi2_d; chi2_d >= x] = (1 - F_(d-2)(x)) / (d - 2)."""
    d = float(dof)
    if d <= 2.0:
        return 0.0
    W = max(float(white_share), 1e-12)
    x = d * W
    # scipy.special's chi-square functions: the distribution objects cost 50x more per call
    below = special.chdtr(d, x)
    ratio_mean = (1.0 - below) + special.chdtr(d + 2, x) / W  # E[q / max(q, W)]
    inv_mean = d / (d - 2) * special.chdtrc(d - 2, x) + below / W  # E[1 / max(q, W)]
    return float(np.clip(d * (1.0 - ratio_mean / inv_mean), 0.0, 2.0))


def _sphericity_epsilon(blocks: list[np.ndarray]) -> float:
    """Share (1/p .. 1) of its p degrees of freedom that a sum of squares over p directions
    keeps when its noise is not spherical in them: tr(S)^2 / (p tr(S^2)), S the noise
    covariance in those directions (Box's epsilon of repeated-measures analysis), estimated
    from the repetitions' deviations ``blocks`` [(R, p_c)] (each a channel's coordinates,
    the repetitions' mean removed; the channels independent, S block-diagonal). Few
    repetitions make the plain plug-in (Greenhouse-Geisser) far too small, so tr(S)^2 and
    tr(S^2) are each estimated without bias from the Wishart moments, as Huynh and Feldt
    did: with n = R - 1 and S^ = D'D / n, E tr(S^^2) = ((n + 1) tr S^2 + (tr S)^2) / n and
    E (tr S^)^2 = (tr S)^2 + 2 tr(S^2) / n."""
    if not blocks:  # the affine model spans the terms' columns: nothing to correct
        return 1.0
    n = blocks[0].shape[0] - 1
    p = sum(b.shape[1] for b in blocks)
    if n < 2 or p < 2:
        return 1.0
    t1, t2, t1sq = [], 0.0, 0.0
    for d in blocks:
        S = d.T @ d / n
        a, b = float(np.sum(S * S)), float(np.trace(S)) ** 2
        t2_c = n * (n * a - b) / ((n - 1) * (n + 2))
        t1.append(float(np.trace(S)))
        t2 += t2_c
        t1sq += b - 2.0 * t2_c / n
    t1sq += sum(t1) ** 2 - sum(x * x for x in t1)  # the channels' cross products
    if t2 <= 0.0:
        return 1.0
    return float(np.clip(t1sq / (p * t2), 1.0 / p, 1.0))


def _prewhiten(A: np.ndarray, noise: _SerialNoise, real: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Rows (6, R, n, k) of each repetition whitened for the serial correlation of
    :class:`_SerialNoise` (generalised least squares: L^-1 with L L^T the correlation of the
    repetition's steps): the tests, fits and held-out scores then treat the wander of the
    bias as the noise it is, not as a lack of fit common to the repetitions. White rows keep
    unit variance."""
    if not noise.correlated:
        return A
    out = np.zeros_like(A)
    lam = noise.lam[:, None, None]
    tau = noise.tau_s[:, None, None]
    done: dict[bytes, np.ndarray] = {}  # repetitions on the same step times share L^-1
    for r in range(A.shape[1]):
        rows = np.flatnonzero(real[r])
        tr = t[r, rows]
        key = tr.tobytes()
        Linv = done.get(key)
        if Linv is None:
            C = lam * np.exp(-np.abs(tr[:, None] - tr[None, :]) / tau)  # (6, m, m)
            C[:, np.arange(len(rows)), np.arange(len(rows))] = 1.0
            Linv = np.linalg.inv(np.linalg.cholesky(C))
            done[key] = Linv
        out[:, r, rows] = Linv @ A[:, r, rows]
    return out


def _qr_r(X: np.ndarray) -> np.ndarray:
    """R factor of each matrix of a stack, padded with zero rows to square."""
    Rf = np.linalg.qr(X, mode="r")
    k = X.shape[-1]
    if Rf.shape[-2] < k:
        pad = np.zeros(Rf.shape[:-2] + (k - Rf.shape[-2], k))
        Rf = np.concatenate([Rf, pad], axis=-2)
    return Rf


def _centre(M: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns M (..., R, n, k) minus their w^2-weighted mean per repetition (the
    repetition's bias fitted: Frisch-Waugh-Lovell for the per-repetition bias columns), and
    the means (..., R, k)."""
    w2 = w**2
    mu = np.einsum("...n,...nk->...k", w2, M) / w2.sum(axis=-1)[..., None]
    return M - mu[..., None, :], mu


@dataclass
class _FitResult:
    names: list[str]
    theta: np.ndarray
    rank: int
    ss: float  # weighted residual sum of squares
    K: np.ndarray  # (6, 3)
    v: np.ndarray  # (6, k) per channel: [-K_c, -theta on its live term columns, 0..., 1]
    ss_channel: np.ndarray | None  # (6,) weighted residual sum of squares (fold of all reps)
    pure_channel: np.ndarray | None  # (6,) its pure-error part
    solution: _LstsqSolution | None = field(default=None, repr=False)

    @property
    def cov(self) -> np.ndarray:
        """Of theta, in units of the weighted residual variance (1 if sigma is right); built
        on first use: the term tests need only theta and the rank."""
        if self.solution is None:
            return np.zeros((0, 0))
        return self.solution.cov


@dataclass
class _LstsqSolution:
    """What :func:`_lstsq` keeps of its SVD for the covariance."""

    Vt: np.ndarray
    inv_s: np.ndarray
    keep: np.ndarray
    live: np.ndarray
    scale: np.ndarray

    @property
    def cov(self) -> np.ndarray:
        if "_cov" not in self.__dict__:
            Vt, inv_s, keep, live, scale = self.Vt, self.inv_s, self.keep, self.live, self.scale
            cov = (Vt.T * inv_s**2) @ Vt / np.outer(scale, scale)
            # a parameter with a component along an undetermined direction is undetermined
            undetermined = (np.abs(Vt[~keep]) > 1e-6).any(axis=0) | ~live
            cov[undetermined, :] = np.nan
            cov[:, undetermined] = np.nan
            self.__dict__["_cov"] = cov
        return self.__dict__["_cov"]


def _lstsq(Z: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, int, _LstsqSolution]:
    """Least squares with column scaling (pseudo-inverse on directions the data do not
    determine): theta, rank, and the SVD's parts for the covariance."""
    norms = np.sqrt(np.add.reduce(Z * Z, axis=0))  # np.linalg.norm(Z, axis=0), its arithmetic
    live = norms > 1e-12 * max(norms.max(), 1e-300)
    scale = np.where(live, norms, 1.0)
    U, s, Vt = np.linalg.svd(Z / scale, full_matrices=False)  # Z is small (R factor) here
    keep = s > _RCOND**0.5 * s[0] if len(s) and s[0] > 0 else np.zeros(len(s), bool)
    keep &= s > 0
    rank = int(keep.sum())
    inv_s = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
    theta = (Vt.T * inv_s) @ (U.T @ y) / scale
    theta[~live] = 0.0  # a column that is all zero has no estimate
    return theta, rank, _LstsqSolution(Vt, inv_s, keep, live, scale)


def _lstsq_cov(Z: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Least squares with column scaling; covariance from the SVD (pseudo-inverse on
    directions the data do not determine, whose variance is reported as inf)."""
    theta, rank, solution = _lstsq(Z, y)
    return theta, solution.cov, rank


def _lstsq_theta_stack(Z: np.ndarray, y: np.ndarray) -> np.ndarray:
    """theta of :func:`_lstsq_cov` for a stack of problems, Z (B, m, p), y (B, m): one
    batched SVD for the held-out folds instead of one call each."""
    norms = np.linalg.norm(Z, axis=-2)  # (B, p)
    live = norms > 1e-12 * np.maximum(norms.max(axis=-1, keepdims=True), 1e-300)
    scale = np.where(live, norms, 1.0)
    U, s, Vt = np.linalg.svd(Z / scale[:, None, :], full_matrices=False)
    keep = (s > _RCOND**0.5 * s[:, :1]) & (s[:, :1] > 0) & (s > 0)
    inv_s = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
    uy = np.einsum("bmk,bm->bk", U, y)
    theta = np.einsum("bkp,bk->bp", Vt, inv_s * uy) / scale
    return np.where(live, theta, 0.0)


# smallest eigenvalue of a fold's Gram matrix, relative to its trace, above which its rank
# is certainly full by numpy's matrix_rank rule (which needs s_min > s_max max(M, N) eps,
# i.e. a ratio of ~1e-28 on the Gram): rounding in forming the Gram (~n eps) is far below
RANK_SURE_RATIO = 1e-8


@lru_cache(maxsize=16)
def _fold_columns(R: int) -> np.ndarray:
    """Per fold 1 + h (h < R), the columns of the full affine Gram it keeps: the three raw
    columns and every repetition's bias column but h's."""
    out = np.array(
        [[0, 1, 2] + [3 + r for r in range(R) if r != h] for h in range(R)], dtype=np.intp
    ).reshape(R, 2 + R)
    out.setflags(write=False)
    return out


def _surely_full_rank(D: np.ndarray) -> bool:
    """True when the weighted affine design of every channel and fold has full rank with a
    wide margin: ``D`` (6, R, n, 4) each repetition's rows ``[w raw | w]``; the design of a
    fold stacks its repetitions' rows with a bias column per repetition (fold 0: all, fold
    1 + h: all but h). Its Gram matrix minus ``RANK_SURE_RATIO`` times its trace must be
    positive definite (a Cholesky factorisation). False says nothing: the exact test runs."""
    C, R = D.shape[:2]
    G = D.swapaxes(-1, -2) @ D  # (6, R, 4, 4) per repetition
    # which repetitions each fold sums (a sum of the included ones: no cancellation)
    included = np.ones((R + 1, R))
    included[np.arange(1, R + 1), np.arange(R)] = 0.0
    full = np.zeros((C, R + 1, 3 + R, 3 + R))
    full[:, :, :3, :3] = np.einsum("fr,crij->cfij", included, G[:, :, :3, :3])
    for r in range(R):  # repetition r's bias column (dropped from fold 1 + r below)
        full[:, :, :3, 3 + r] = full[:, :, 3 + r, :3] = G[:, None, r, :3, 3]
        full[:, :, 3 + r, 3 + r] = G[:, None, r, 3, 3]
    # fold 1 + h without repetition h's bias row and column: the same matrices as deleting
    # them (np.delete), taken with one index array for all folds
    keep = _fold_columns(R)  # (R, 2 + R)
    held_out = full[:, 1 + np.arange(R)[:, None, None], keep[:, :, None], keep[:, None, :]]
    for A in (full[:, :1], held_out):
        tr = np.trace(A, axis1=-2, axis2=-1)
        if not (np.isfinite(tr).all() and (tr > 0).all()):
            return False
        shifted = A - (RANK_SURE_RATIO * tr)[..., None, None] * np.eye(A.shape[-1])
        try:
            np.linalg.cholesky(shifted)
        except np.linalg.LinAlgError:
            return False
    return True


# -- results --------------------------------------------------------------------------
@dataclass
class Diagnosis:
    """What :func:`diagnose_unit` found for one unit."""

    lot: str
    unit: str
    n_reps: int
    alpha: float
    misfit: bool
    unexplained: bool
    effects: list[EffectFinding]
    partial: list[EffectFinding]  # significant but leave their channels misfit: not chosen
    negligible: list[EffectFinding]  # significant, but the unit fits without them or their
    # held-out gain is below min_gain: not applied
    terms: tuple[TermValue, ...]
    lack_of_fit_before: FTest
    lack_of_fit_after: FTest
    channel_misfit_before: dict[str, FTest]
    channel_misfit_after: dict[str, FTest]
    noise: NoiseEstimate
    calibrations_before: list[Calibration]  # one per repetition (own biases)
    calibrations_after: list[Calibration]
    residuals_before: pd.DataFrame = field(repr=False)
    residuals_after: pd.DataFrame = field(repr=False)
    heldout_rms_baseline: float = float("nan")  # all channels, affine model
    heldout_rms_final: float = float("nan")  # all channels, chosen model
    min_gain: float = DEFAULT_MIN_GAIN
    # largest change of a sensing direction (rad) at each re-linearisation of the geometry
    relinearisations: list[float] = field(default_factory=list)
    # terms the steps cannot tell apart, significant together: applied, named by none
    confounded: list[ConfoundedFinding] = field(default_factory=list)
    confounded_set_aside: list[list[str]] = field(default_factory=list)  # partial/negligible
    advice: list[str] = field(default_factory=list)  # which steps would separate them
    # candidates whose targeted (or between-repetition) test on the affine model rejects
    # (part of "misfit"); those of them whose between-repetition test rejects
    misfit_terms: list[str] = field(default_factory=list)
    misfit_between: list[str] = field(default_factory=list)
    # the series behind each finding's figure (calib_core.discovery.presentation)
    evidence: pd.DataFrame = field(default_factory=pd.DataFrame, repr=False)

    @property
    def calibration(self) -> Calibration:
        """The unit's extended calibration (biases averaged over the repetitions)."""
        cals = self.calibrations_after
        return replace(
            cals[0], w0=np.mean([c.w0 for c in cals], axis=0), f0=np.mean([c.f0 for c in cals], axis=0)
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (non-finite numbers become None)."""
        return jsonable(
            {
                "unit": self.unit,
                "lot": self.lot,
                "n_reps": self.n_reps,
                "alpha": self.alpha,
                "misfit": self.misfit,
                "unexplained": self.unexplained,
                "effects": [e.to_dict() for e in self.effects],
                "partial": [e.to_dict() for e in self.partial],
                "negligible": [e.to_dict() for e in self.negligible],
                "min_gain": self.min_gain,
                "relinearisations": list(self.relinearisations),
                "confounded": [c.to_dict() for c in self.confounded],
                "confounded_set_aside": [list(g) for g in self.confounded_set_aside],
                "advice": list(self.advice),
                "misfit_terms": list(self.misfit_terms),
                "misfit_between": list(self.misfit_between),
                "lack_of_fit_before": self.lack_of_fit_before.to_dict(),
                "lack_of_fit_after": self.lack_of_fit_after.to_dict(),
                "misfit_channels_before": [c for c, t in self.channel_misfit_before.items() if t.rejects],
                "misfit_channels_after": [c for c, t in self.channel_misfit_after.items() if t.rejects],
                "heldout_rms_baseline": self.heldout_rms_baseline,
                "heldout_rms_final": self.heldout_rms_final,
                "noise": self.noise.records(),
            }
        )


# -- the procedure ----------------------------------------------------------------------


class _TargetedParts(NamedTuple):
    blocks: list[np.ndarray]  # per channel (R, p_c): the repetitions' deviations, denominator
    joint_ss: float  # R |mean residual|^2 on the terms' joint directions, numerator
    joint_dof: int  # the joint directions
    joint_deviations: np.ndarray  # (R, joint_dof) the repetitions' deviations along them


class _HeldOutScore(NamedTuple):
    before: float  # held-out rms without the item, sigma
    after: float  # with it
    steps: int  # step means counted
    steps_total: int  # step means on its channels

    @property
    def gain(self) -> float:
        return self.before / self.after if self.after > 0 else float("inf")


class _Discovery:
    def __init__(
        self,
        sessions: list[StepMeans],
        alpha: float,
        geometry: SensingGeometry | None = None,
        noise_model: tuple[np.ndarray, np.ndarray] | None = None,
        min_gain: float = DEFAULT_MIN_GAIN,
    ):
        """``geometry``: the sensing geometry the terms act through (default: that of the
        affine fit's K). ``noise_model`` = (K rows (6, 3), physical residual (R, n, 6) on the
        grid) of the model whose residuals estimate the noise; default: the affine model."""
        if len(sessions) < 2:
            raise DesignError(
                "E_DISCOVERY_REPS",
                "model discovery needs at least 2 repetitions of the unit: the "
                "step-to-step noise is estimated from their scatter",
            )
        units = {(sm.key.lot, sm.key.unit) for sm in sessions}
        if len(units) != 1:
            raise ValueError(f"sessions of several units: {sorted(units)}")
        self.sessions = sorted(sessions, key=lambda s: s.key.rep)
        self.alpha = alpha
        self.min_gain = float(min_gain)
        self.names = sorted(catalogue())
        # one layout for every grid of this unit (its motion contexts keep the term columns)
        self.layout = _layout(self.sessions)
        self.g = _UnitGrid.build(self.sessions, self.names, geometry, layout=self.layout)
        if noise_model is None:
            # affine fit weighted by within-step scatter only, to get K and residuals
            white = self.g.white_sigma(np.tile(np.eye(3), (2, 1)))
            w0 = np.where(self.g.real[..., None], 1.0 / np.maximum(white, 1e-300), 0.0)
            noise_model = self._affine_fit(w0)
        if geometry is None:  # the terms act through the affine fit's sensing geometry
            K = noise_model[0]
            geometry = SensingGeometry.from_gains(K[:3], K[3:])
            self.g = _UnitGrid.build(self.sessions, self.names, geometry, layout=self.layout)
        self.geometry = geometry
        # noise from the data: within-step scatter through K + repetition scatter
        self._noise_rows, self.sigma = self._noise(*noise_model)
        self.weight = np.where(self.g.real[..., None], 1.0 / self.sigma, 0.0)
        self.serial = _serial_noise(noise_model[1] * self.weight, self.g.real, self.g.t)
        self._factorise()
        self.undetermined = self._undetermined()
        if self.undetermined:  # fitted as 0: rebuild the terms' columns without them
            dropped = frozenset(self.undetermined)
            self.g = _UnitGrid.build(self.sessions, self.names, geometry, dropped, self.layout)
            self._factorise()
        self._fits: dict[tuple, _FitResult] = {}
        self._heldout: dict[tuple, np.ndarray] = {}
        self._tests: dict[tuple, Any] = {}  # lack-of-fit tests by (kind, terms, threshold)

    def _undetermined(self) -> dict[int, str]:
        """Term columns (global) the steps cannot determine, with the reason: no step
        excites the parameter, or its standard error with the term alone on the base model
        exceeds the term's ``max_useful_stderr`` (the protocol cannot tell a realistic value
        from 0)."""
        g, P = self.g, self.g.P
        out: dict[int, str] = {}
        Rg = self.Rg[0][:P, :P]
        for name in self.names:
            a, b = g.offset[name]
            term = get_effect(name)
            live = g.live_mask[:, a:b].any(axis=0)
            for k in np.flatnonzero(~live):
                out[a + int(k)] = "no step excites it"
            cols = a + np.flatnonzero(live)
            if not cols.size:
                continue
            _, _, sol = _lstsq(Rg[:, cols], np.zeros(P))
            se = np.sqrt(np.diag(sol.cov))
            for k, v in zip(cols, se):
                if not np.isfinite(v):
                    out[int(k)] = (
                        "not separable from the base model and the term's other parameters on these steps"
                    )
                elif v > term.max_useful_stderr:
                    unit = term.param_units[int(k) - a]
                    out[int(k)] = (
                        f"standard error {v:.3g} {unit} on these steps exceeds "
                        f"{term.max_useful_stderr:g} {unit}: too weakly excited "
                        f"({term.excited_by})"
                    )
        return out

    # -- set-up ---------------------------------------------------------------------------
    def _affine_fit(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """K rows and physical residual (R, n, 6) of the affine model (own biases per
        repetition) weighted by w (R, n, 6)."""
        g = self.g
        wc = np.moveaxis(w, -1, 0)  # (6, R, n)
        Mc, _ = _centre(g.M[..., [0, 1, 2, -1]], wc)
        Mc[:, ~g.real] = 0.0
        Rf = _qr_r((wc[..., None] * Mc).reshape(6, -1, 4))
        try:
            K = np.linalg.solve(Rf[:, :3, :3], Rf[:, :3, 3:])[..., 0]  # (6, 3)
        except np.linalg.LinAlgError:
            self._check_rank(w)  # says which channel cannot be determined
            raise
        resid = Mc[..., 3] - np.einsum("crnk,ck->crn", Mc[..., :3], K)
        return K, np.moveaxis(resid, 0, -1)

    def _noise(self, K: np.ndarray, resid: np.ndarray) -> tuple[list, np.ndarray]:
        """:func:`calib_core.discovery.replay.estimate_noise_arrays` and :func:`noise_sigma` on the
        grid (same pooling, same numbers)."""
        g = self.g
        white = g.white_sigma(K)
        ng = len(g.groups)
        e, grp, dof = g.two_way(resid)
        ss = np.zeros((6, ng))
        w2 = np.zeros((6, ng))
        for gi in range(ng):  # per test group: a handful
            ss[:, gi] = np.sum(e[grp == gi] ** 2, axis=0)
            w2[:, gi] = np.mean(white[g.gcode == gi] ** 2, axis=0)
        # per channel and group, in Python floats (the same operations as replay's pooling:
        # math.sqrt and np.sqrt are both the correctly rounded square root); the arrays are
        # converted once, not indexed one numpy scalar at a time
        rows, inst_c = [], []
        dofs = dof.tolist()
        pooled_dof = 0
        for d in dofs:
            pooled_dof += int(d)
        for ch, ss_c, w2_c in zip(CHANNELS, ss.tolist(), w2.tolist()):
            pooled_ss = 0.0
            for v in ss_c:
                pooled_ss += v
            pooled_var = pooled_ss / pooled_dof if pooled_dof else np.nan
            inst_g = []
            for gname, v, w2v, d in zip(g.groups, ss_c, w2_c, dofs):
                wsd = math.sqrt(w2v)
                var = v / int(d) if d >= MIN_POOL_DOF else pooled_var
                step_sd = math.sqrt(var) if math.isfinite(var) else wsd
                inst_g.append(math.sqrt(max(step_sd**2 - wsd**2, 0.0)))
                rows.append((ch, gname, int(d), step_sd, wsd))
            inst_c.append(inst_g)
        inst = np.array(inst_c, dtype=float).reshape(6, ng)
        rows = [r + (x,) for r, x in zip(rows, inst.ravel())]  # np.float64, as before
        inst_row = np.where(g.real[..., None], inst.T[np.maximum(g.gcode, 0)], 0.0)
        sigma = np.sqrt(white**2 + np.nan_to_num(inst_row) ** 2)
        if not np.all(sigma[g.real] > 0):
            raise DesignError("E_DISCOVERY_NOISE", "zero noise estimate on some steps")
        sigma[~g.real] = 1.0
        return rows, sigma

    @property
    def noise(self) -> NoiseEstimate:
        if not hasattr(self, "_noise_estimate"):
            self._noise_estimate = NoiseEstimate.from_records(
                [dict(zip(NOISE_COLUMNS, r)) for r in self._noise_rows], from_repetitions=True
            )
        return self._noise_estimate

    def _factorise(self) -> None:
        """Per channel c, the weighted bias-removed design A_c = [raw_c | live terms | y]:
        R factors per repetition (held-out residuals), per fold (repetitions but one;
        fold 0 = all, fold 1 + h leaves h out), of its pure-error part; per fold, the factor
        of every term column with the affine model projected out (fits of any subset)."""
        g, R, P = self.g, self.g.R, self.g.P
        self._check_rank(self.weight)  # before anything solves with the affine part
        w = np.moveaxis(self.weight, -1, 0)  # (6, R, n)
        Mc, self.mu = _centre(g.M, w)  # (6, R, n, k), (6, R, k)
        Mc[:, ~g.real] = 0.0
        self.Mc = Mc
        A_raw = w[..., None] * Mc
        A = _prewhiten(A_raw, self.serial, g.real, g.t)
        self.A = A
        # each repetition's bias column, weighted and whitened as the rows (the lack-of-fit
        # test removes it per repetition)
        self.A_bias = _prewhiten(np.where(g.real, w, 0.0)[..., None], self.serial, g.real, g.t)[..., 0]
        k = A.shape[-1]
        self.Rrep = _qr_r(A)  # (6, R, k, k)
        # the held-out score is the residual a user sees, residual / sigma, not whitened: a
        # slow effect (thermal drift) matters by its size, not by how far it is from the wander
        self.Rrep_seen = self.Rrep if A is A_raw else _qr_r(A_raw)
        self.A_seen = A_raw
        folds = np.broadcast_to(self.Rrep[:, None], (6, R + 1, R, k, k)).copy()
        folds[:, np.arange(1, R + 1), np.arange(R)] = 0.0
        self.Rf = _qr_r(folds.reshape(6, R + 1, R * k, k))  # (6, R+1, k, k)
        # K_c = R_base^-1 (R_base,y - R_base,terms theta): solved once per fold
        self.K_solve = np.linalg.solve(self.Rf[..., :3, :3], self.Rf[..., :3, 3:])
        e, _, self.pure_dof = g.two_way(A)
        self.Rpure = _qr_r(e)  # (6, k, k)
        # the affine model projected out: the trailing block of each fold's factor, every
        # channel's term columns put back in their global place (P + 1: padding, dropped)
        T = np.zeros((R + 1, 6, k - 3, P + 2))
        for c in range(6):
            T[:, c][..., np.append(g.colmap[c], P)] = self.Rf[c, :, 3:, 3:]
        S = T.reshape(R + 1, 6 * (k - 3), P + 2)[..., : P + 1]
        self.Rg = _qr_r(S)  # (R+1, P+1, P+1): [R_terms c; 0 sqrt(ss_perp)] per fold
        self.rows_channel = int(g.real.sum())
        self.base_rank = [3 + R] * 6

    def _check_rank(self, weight: np.ndarray) -> None:
        """The affine model (K row + a bias per repetition) must be determined on every
        channel and fold: numpy's matrix_rank test on the weighted design, whose singular
        values are those of the repetitions' R factors placed block by block. Skipped when
        every fold's design is far from losing rank (:func:`_surely_full_rank`): the test
        could not fail."""
        g, R = self.g, self.g.R
        eps = np.finfo(float).eps
        w = np.moveaxis(weight, -1, 0)[..., None]  # (6, R, n, 1)
        D = np.concatenate([w * g.M[..., :3], w], axis=-1)  # (6, R, n, 4): [w raw | w]
        if _surely_full_rank(D):
            return
        R4 = _qr_r(D)  # (6, R, 4, 4)
        Y = np.zeros((6, R + 1, R, 4, 3 + R))
        Y[..., :3] = R4[:, None, :, :, :3]
        for r in range(R):  # bias column of repetition r
            Y[:, :, r, :, 3 + r] = R4[:, None, r, :, 3]
        Y[:, np.arange(1, R + 1), np.arange(R)] = 0.0
        s = np.linalg.svd(Y.reshape(6, R + 1, 4 * R, 3 + R), compute_uv=False)
        rows = g.real.sum(axis=1)
        n_rows = np.array([rows.sum()] + [rows.sum() - rows[h] for h in range(R)])
        n_cols = np.array([3 + R] + [3 + R - 1] * R)
        tol = s.max(axis=-1) * np.maximum(n_rows, n_cols) * eps
        rank = (s > tol[..., None]).sum(axis=-1)  # (6, R+1)
        bad = np.argwhere((rank < n_cols).T)  # fold by fold, channel by channel
        if bad.size:
            f, c = bad[0]
            raise DesignError(
                "E_DISCOVERY_RANK",
                f"channel {CHANNELS[c]}: the steps cannot determine the "
                f"affine model (rank {int(rank[c, f])} < {int(n_cols[f])})",
                (CHANNELS[c],),
            )

    # -- fits -----------------------------------------------------------------------------
    def fit(self, names: tuple[str, ...], fold: int | None = None) -> _FitResult:
        key = (tuple(sorted(names)), fold)
        if key not in self._fits:
            self._fits[key] = self._fit(key[0], fold)
        return self._fits[key]

    def _fit(self, names: tuple[str, ...], fold: int | None) -> _FitResult:
        g, P = self.g, self.g.P
        fi = 0 if fold is None else 1 + fold
        Rg = self.Rg[fi]
        c_all = Rg[:P, P]
        ss_perp = float(Rg[P, P] ** 2)
        cols = g.cols(names)
        solution = None
        if cols.size:
            R_S = Rg[:P, cols]
            theta, rank, solution = _lstsq(R_S, c_all)
            d = c_all - R_S @ theta
            ss = float(d @ d) + ss_perp
        else:
            theta, rank = np.zeros(0), 0
            ss = float(c_all @ c_all) + ss_perp
        theta_ext = np.zeros(P + 2)
        theta_ext[cols] = theta
        tc = theta_ext[g.colmap]  # (6, k - 4) each channel's term coefficients
        # affine coefficients by back-substitution on the fold's factor of each channel
        KS = self.K_solve[:, fi]  # (6, 3, k - 3)
        K = KS[..., -1] - np.einsum("cij,cj->ci", KS[..., :-1], tc)
        v = np.concatenate([-K, -tc, np.ones((6, 1))], axis=1)  # (6, k)
        ss_c = pure_c = None
        if fold is None:
            ss_c = np.sum(np.einsum("cij,cj->ci", self.Rf[:, 0], v) ** 2, axis=1)
            pure_c = np.sum(np.einsum("cij,cj->ci", self.Rpure, v) ** 2, axis=1)
        return _FitResult(
            names=list(names),
            theta=theta,
            rank=rank,
            ss=ss,
            K=K,
            v=v,
            ss_channel=ss_c,
            pure_channel=pure_c,
            solution=solution,
        )

    def biases(self, f: _FitResult) -> np.ndarray:
        """Each repetition's biases (R, 6) under a fit of all repetitions: the weighted mean
        of what the fit leaves on the repetition."""
        return np.einsum("crk,ck->rc", self.mu, f.v)

    def noise_model(self, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        f = self.fit(names)
        return f.K, np.einsum("crnk,ck->rnc", self.Mc, f.v)

    @property
    def noise_params(self) -> np.ndarray:
        """Pure-error dof (6,) that the noise model fitted to the repetitions' scatter costs,
        per channel. The model is fitted to the pure error that the tests then divide by, so
        that pure error is smaller than an independent sample of the noise would be. Each
        step-mean variance (one per test group with enough dof of its own, one pooled for
        the groups that borrow it) costs :func:`_variance_dof_cost`: 2 when the wander
        dominates the step (an estimated inverse weight: E[1 / q] = d / (d - 2)), 0 when the
        known white part does. On a triad with serial noise, its share ``lam`` costs 2 as
        well (the wander's variance is the inverse weight of the slow directions) and its
        time constant, shared by the triad, a third of a parameter per channel. Counted so,
        the lack-of-fit F of clean units has the F distribution's mean (uncounted, 1.035 /
        1.019 / 1.007 on 3 / 5 / 10 repetitions; each variance counted 1, 1.0116 on 5)."""
        if "_noise_params" in self.__dict__:  # asked by every test of every term set
            return self.__dict__["_noise_params"]
        cost = np.zeros(6)
        pooled: dict[int, list[float]] = {}
        dof_c = np.zeros(6)  # each channel's pooled dof: what a borrowed variance has
        for row in self._noise_rows:
            dof_c[CHANNELS.index(row[0])] += row[2]
        for ch, _group, d, step_sd, wsd, *_ in self._noise_rows:
            c = CHANNELS.index(ch)
            share = wsd**2 / step_sd**2 if step_sd > 0 else 1.0
            if d >= MIN_POOL_DOF:
                cost[c] += _variance_dof_cost(d, share)
            else:  # the borrowed pooled variance: counted once, at the borrowers' white share
                pooled.setdefault(c, []).append(share)
        for c, shares in pooled.items():
            cost[c] += _variance_dof_cost(dof_c[c], float(np.mean(shares)))
        # the wander's share is a variance too (the inverse of the slow directions' weight):
        # 2, as an estimated step variance; its time constant, shared by the triad, a third
        serial = np.where(self.serial.lam > 0, 2.0 + 1.0 / 3.0, 0.0)  # its triads only
        out = cost + serial
        out.setflags(write=False)
        self.__dict__["_noise_params"] = out
        return out

    def pure(self, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Pure-error sum of squares and dof per channel of a model's weighted residual: its
        repetition-to-repetition scatter of the same step (dof net of the noise model's
        parameters, :attr:`noise_params`). Computed per model because the noise reaches the
        residual through that model's own K."""
        f = self.fit(names)
        dof = int(self.pure_dof.sum()) - np.round(self.noise_params)
        return f.pure_channel, dof.astype(np.int64)

    def _heldout_v(self, names: tuple[str, ...]) -> np.ndarray:
        """(6, R, k) each fold's coefficient vector [-K | -terms | 1] of channel c, fold h
        (repetitions but h): repetition h's rows times it are its held-out residual (its own
        biases fitted on itself); the R folds' fits are solved together."""
        key = ("v",) + tuple(sorted(names))
        if key not in self._heldout:
            g, P, R = self.g, self.g.P, self.g.R
            Rg = self.Rg[1:]  # (R, P+1, P+1) the folds leaving one repetition out
            cols = g.cols(key[1:])
            theta_ext = np.zeros((R, P + 2))
            if cols.size:
                theta_ext[:, cols] = _lstsq_theta_stack(Rg[:, :P][:, :, cols], Rg[:, :P, P])
            tc = theta_ext[:, g.colmap]  # (R, 6, k - 4)
            KS = self.K_solve[:, 1:]  # (6, R, 3, k - 3)
            K = KS[..., -1] - np.einsum("chij,hcj->chi", KS[..., :-1], tc)  # (6, R, 3)
            self._heldout[key] = np.concatenate([-K, -tc.transpose(1, 0, 2), np.ones((6, R, 1))], axis=-1)
        return self._heldout[key]

    def heldout_ss(self, names: tuple[str, ...]) -> np.ndarray:
        """Sum of squares of the held-out normalised residual per channel (each repetition
        predicted by the fold holding it out)."""
        key = tuple(sorted(names))
        if key not in self._heldout:
            # [:, h]: repetition h's R factor times fold h's coefficients
            z = np.einsum("chij,chj->chi", self.Rrep_seen, self._heldout_v(key))
            self._heldout[key] = np.sum(z**2, axis=(1, 2))
        return self._heldout[key]

    def heldout_rows(self, names: tuple[str, ...]) -> np.ndarray:
        """(6, R, n) held-out normalised residual of every step (0 on padding)."""
        key = ("rows",) + tuple(sorted(names))
        if key not in self._heldout:
            self._heldout[key] = np.einsum("chnj,chj->chn", self.A_seen, self._heldout_v(key[1:]))
        return self._heldout[key]

    def heldout_score(
        self, without: tuple[str, ...], with_: tuple[str, ...], channels: tuple[int, ...]
    ) -> _HeldOutScore:
        """Held-out rms without and with an item on ``channels``, counted on the steps that
        excite it: the fewest step means that carry EXCITED_SHARE of the squared change it
        makes to the held-out prediction. That change is the other repetitions' fit applied
        to the held-out steps' inputs: the steps are chosen by where the item acts, not by
        the held-out residual. An effect on every step is judged on nearly all of them."""
        ch = list(channels)
        zo = self.heldout_rows(without)[ch].ravel()
        zf = self.heldout_rows(with_)[ch].ravel()
        total = self.rows_channel * len(ch)
        d2 = (zo - zf) ** 2  # 0 on padding
        tot = float(d2.sum())
        if tot <= 0:
            return _HeldOutScore(
                float(np.sqrt(np.sum(zo**2) / total)), float(np.sqrt(np.sum(zf**2) / total)), total, total
            )
        order = np.argsort(d2)[::-1]
        m = min(int(np.searchsorted(np.cumsum(d2[order]), EXCITED_SHARE * tot)) + 1, total)
        rows = order[:m]
        return _HeldOutScore(
            float(np.sqrt(np.mean(zo[rows] ** 2))), float(np.sqrt(np.mean(zf[rows] ** 2))), m, total
        )

    def heldout_rms(self, names: tuple[str, ...], channels: tuple[int, ...] | None = None) -> float:
        ss = self.heldout_ss(names)
        ch = list(range(6)) if channels is None else list(channels)
        n_rows = self.rows_channel * len(ch)
        return float(np.sqrt(ss[ch].sum() / n_rows))

    # tests
    def lack_of_fit(self, names: tuple[str, ...], threshold: float) -> FTest:
        key = ("all", tuple(sorted(names)), threshold)
        if key not in self._tests:  # a function of the fit: selection and report ask again
            self._tests[key] = self._lack_of_fit(names, threshold)
        return self._tests[key]

    def _lack_of_fit(self, names: tuple[str, ...], threshold: float) -> FTest:
        if self.g.balanced:
            ss_lof, dof, ss_pure, dof_pure, inflation = self.projected_lack_of_fit(names).T
            # the channels' sums are independent: their Satterthwaite dof add
            return f_test(
                float(ss_lof.sum()),
                float(np.sum(dof / inflation)),
                float(ss_pure.sum()),
                float(np.sum(dof_pure / inflation)),
                threshold,
            )
        f = self.fit(names)
        dof_res = 6 * self.rows_channel - sum(self.base_rank) - f.rank
        ps, pd_ = self.pure(names)
        pss, pdof = ps.sum(), int(pd_.sum())
        return f_test(f.ss - pss, dof_res - pdof, pss, pdof, threshold)

    def channel_lack_of_fit(self, names: tuple[str, ...], threshold: float) -> dict[str, FTest]:
        key = ("channel", tuple(sorted(names)), threshold)
        if key not in self._tests:
            self._tests[key] = self._channel_lack_of_fit(names, threshold)
        return dict(self._tests[key])  # the tests are frozen; the dict is the caller's

    def _channel_lack_of_fit(self, names: tuple[str, ...], threshold: float) -> dict[str, FTest]:
        if self.g.balanced:
            parts = self.projected_lack_of_fit(names)
            return {
                CHANNELS[c]: f_test(ss, dof / infl, ssp, dofp / infl, threshold)
                for c, (ss, dof, ssp, dofp, infl) in enumerate(parts.tolist())
            }
        f = self.fit(names)
        ps, pd_ = self.pure(names)
        cols = self.g.cols(tuple(sorted(names)))
        out = {}
        for c in range(6):
            n_params = int(self.g.live_mask[c, cols].sum())
            dof_res = self.rows_channel - self.base_rank[c] - min(n_params, f.rank)
            out[CHANNELS[c]] = f_test(
                float(f.ss_channel[c]) - ps[c], dof_res - int(pd_[c]), ps[c], int(pd_[c]), threshold
            )
        return out

    def _bias_removed(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """Channel ``c``'s whitened design (R, n, k) with each repetition's own bias removed
        from every column, and the whitened bias column (R, n)."""
        A, wb = self.A[c], self.A_bias[c]
        coef = np.einsum("rn,rnk->rk", wb, A) / np.maximum(np.einsum("rn,rn->r", wb, wb), 1e-300)[:, None]
        return A - wb[..., None] * coef[:, None, :], wb

    def projected_lack_of_fit(self, names: tuple[str, ...]) -> np.ndarray:
        """Per channel (6, 5): (SS_lof, dof_lof, SS_pure, dof_pure, inflation) of the
        lack-of-fit test
        with the pure error *projected on the lack-of-fit space*.

        Each repetition's whitened residual r_h (its own bias removed) = systematic error s
        + noise e_h, the e_h independent between repetitions with any covariance M within
        one (what the serial-noise model leaves: a wander not quite Gauss-Markov, a sigma a
        little off on some steps). Q projects out the model's columns (mean over the
        repetitions). SS_lof = R |Q mean_h r_h|^2 has expectation tr(Q M) under no misfit,
        and so has SS_pure / (R - 1) with SS_pure = sum_h |Q (r_h - mean r)|^2: the ratio
        is calibrated whatever M is, where the pure error over every direction is not (a
        direction the model projects out may hold more or less noise than the average one).
        The model's columns are those of the channel, each term's coefficient free per
        channel (a little more freedom than the joint fit: conservative). Both sums are
        quadratic forms in the same noise: when M is not a multiple of the identity their
        spread is that of fewer degrees of freedom (Satterthwaite), see
        :func:`_dof_inflation` (the dof to test with are dof / inflation).
        Balanced grids only (every repetition the same steps)."""
        key = ("projected", tuple(sorted(names)))
        if key in self._tests:
            return self._tests[key]
        g, R = self.g, self.g.R
        cols = g.cols(tuple(sorted(names)))
        f = self.fit(names)
        out = np.zeros((6, 5))
        for c in range(6):
            A, wb = self._bias_removed(c)  # (R, n, k), (R, n)
            resid = A @ f.v[c]  # (R, n)
            local = 3 + np.flatnonzero(np.isin(g.colmap[c], cols))
            X = np.concatenate([A[..., :3], A[..., local], wb[..., None]], axis=-1).mean(axis=0)
            Ub = orthonormal_basis(X)
            rbar = resid.mean(axis=0)
            e = rbar - Ub @ (Ub.T @ rbar)
            dev = resid - rbar
            dev = dev - (dev @ Ub) @ Ub.T
            dof = Ub.shape[0] - Ub.shape[1]
            dof_pure = (R - 1) * dof - self.noise_params[c]
            out[c] = (R * float(e @ e), dof, float(np.sum(dev**2)), dof_pure, _dof_inflation(dev))
        self._tests[key] = out
        return out

    def targeted_test(self, names: tuple[str, ...], threshold: float) -> FTest:
        """F test of the terms ``names`` on the affine model, the pure error measured along
        the terms' own directions: the noise along a slow direction (a drift over the
        repetition) is what the repetitions show along it, not the average over every
        direction, so the test keeps its false-alarm rate when the whitening leaves some
        wander (the pure error of :meth:`group_test` pools every direction: more dof, but
        too small along slow ones).

        Numerator: the affine model's mean residual on the terms' *joint* directions, each
        parameter one column across the channels it acts on through the sensing geometry,
        as the joint fit has it (p of them). Denominator: the repetitions' scatter along
        every channel's own copy of the terms' columns (the per-channel directions, which
        span the joint ones: a sensor's column leaks into the other channels of its triad
        through the misalignment, so there are up to three times as many), (R - 1) per
        direction. Testing the per-channel directions in the numerator too spent dof on
        leakage columns that carry almost none of the effect (p 9 instead of 3 for the
        accelerometer nonlinearity, 18 instead of 6 for the thermal scale drift) and cost a
        third of the noncentrality it needs: a quarter of a realistic accelerometer
        nonlinearity rejected on 75 % of 40 physics units that way, 97.5 % this way, at the
        same false-alarm rate (0.45 % and 0.40 % of 2,000 clean units at the 0.5 % share).
        Unbalanced grids: :meth:`group_test`."""
        if not self.g.balanced:
            return self.group_test((), names, threshold)
        parts = self._targeted_parts(tuple(names))
        if not parts.joint_dof or not parts.blocks:
            return f_test(0.0, 0.0, 0.0, 0.0, threshold)
        # F(p, dof) holds when the noise is spherical in the directions of each sum; a
        # channel noisier than another along them, or a wander left along a slow one, makes
        # a sum spread like fewer dof (Box's epsilon, each sum its own)
        den = sum(float(np.sum(d**2)) for d in parts.blocks)
        dof = (self.g.R - 1) * sum(d.shape[1] for d in parts.blocks)
        e_num = _sphericity_epsilon([parts.joint_deviations])
        e_den = _sphericity_epsilon(parts.blocks)
        # F = (joint_ss / p) / (den / dof) against F(e_num p, e_den dof): each sum scaled by
        # its own epsilon so that f_test's ratio of mean squares stays that F
        return f_test(e_num * parts.joint_ss, e_num * parts.joint_dof, e_den * den, e_den * dof, threshold)

    def _targeted_parts(self, names: tuple[str, ...]) -> _TargetedParts:
        """The sums of :meth:`targeted_test` on the affine model's residual: per channel the
        terms act on, the repetitions' deviations (R, p_c) in an orthonormal basis of the
        terms' columns that the channel's affine model does not span (``blocks``); on the
        terms' joint directions (the channels stacked), R |mean residual|^2, their number
        and the repetitions' deviations along them."""
        key = ("targeted", tuple(sorted(names)))
        if key in self._tests:  # selection and the report ask again at other thresholds
            return self._tests[key]
        g, R = self.g, self.g.R
        cols = g.cols(tuple(sorted(names)))
        index = {int(k): j for j, k in enumerate(cols)}
        f = self.fit(())
        blocks, means, devs, joint = [], [], [], []
        for c in range(6):
            hit = np.flatnonzero(np.isin(g.colmap[c], cols))
            if not hit.size:
                continue
            A, wb = self._bias_removed(c)
            Ub = orthonormal_basis(np.concatenate([A[..., :3], wb[..., None]], axis=-1).mean(axis=0))
            resid = A @ f.v[c]
            rbar = resid.mean(axis=0)
            dev = resid - rbar
            Xt = A[..., 3 + hit].mean(axis=0)
            size = float(np.linalg.norm(Xt, axis=0).max())
            Xt = Xt - Ub @ (Ub.T @ Xt)
            U, s, _ = np.linalg.svd(Xt, full_matrices=False)
            Ut = U[:, s > size * 1e-8]  # what the affine model spans is not the terms'
            if Ut.shape[1]:
                blocks.append(dev @ Ut)
            J = np.zeros((Xt.shape[0], len(cols)))
            J[:, [index[int(k)] for k in g.colmap[c][hit]]] = Xt
            joint.append(J)
            means.append(rbar - Ub @ (Ub.T @ rbar))
            devs.append(dev)  # along the joint directions, which the affine model's miss
        Uj = orthonormal_basis(np.concatenate(joint)) if joint else np.zeros((0, 0))
        mean = np.concatenate(means) if means else np.zeros(0)
        out = _TargetedParts(
            blocks,
            R * float(np.sum((Uj.T @ mean) ** 2)) if Uj.size else 0.0,
            int(Uj.shape[1]),
            np.concatenate(devs, axis=1) @ Uj if Uj.size else np.zeros((R, 0)),
        )
        self._tests[key] = out
        return out

    def between_repetition_test(self, names: tuple[str, ...], threshold: float) -> FTest | None:
        """F test of the part of the terms ``names`` that differs between the repetitions,
        on the affine model: does it explain the repetitions' scatter about their mean?

        Why: the lack-of-fit tests and :meth:`targeted_test` compare the repetitions' mean
        with the model, and take their scatter as the noise. An effect driven by something
        that differs from one repetition to the next (the temperature of repetitions run
        back to back on one warm-up, or on days of different ambient: xu2016's k_g33 drift
        between repetitions) lands in that scatter, so those tests cannot see it, however
        large it is. Here each repetition's residual (its own bias removed) minus the
        repetitions' mean residual is regressed on the same deviation of the terms'
        columns; the rest of that scatter is the noise (its dof net of the noise model's
        parameters, :attr:`noise_params`). ``None`` when no column of the terms differs
        between the repetitions by ``REP_VARYING_MIN`` of its size (nothing to test: the
        test would take a share of alpha for no power). Balanced grids only."""
        if not self.g.balanced:
            return None
        key = ("between", tuple(sorted(names)))
        if key not in self._tests:
            self._tests[key] = self._between_repetition_sums(names)
        sums = self._tests[key]
        return None if sums is None else f_test(*sums, threshold)

    def _between_repetition_sums(self, names: tuple[str, ...]) -> tuple[float, int, float, int] | None:
        g, R = self.g, self.g.R
        cols = g.cols(tuple(sorted(names)))
        f = self.fit(())
        ss_num = ss_den = 0.0
        dof_num = dof_den = 0
        for c in range(6):
            local = 3 + np.flatnonzero(np.isin(g.colmap[c], cols))
            if not local.size:
                continue
            A, _ = self._bias_removed(c)
            # the scale factors are shared by the repetitions: a repetition's own scale
            # (what a temperature offset between repetitions makes) stays in its deviation
            resid = A @ f.v[c]
            dev = resid - resid.mean(axis=0)
            D = A[..., local] - A[..., local].mean(axis=0)
            # whether a column differs between the repetitions is a question about the
            # physical column, not about the weights (each repetition's own step sigmas)
            M = self.Mc[c][..., local]
            size = np.sqrt(np.sum(M**2, axis=(0, 1)))
            spread = np.sqrt(np.sum((M - M.mean(axis=0)) ** 2, axis=(0, 1)))
            varying = spread > REP_VARYING_MIN * np.maximum(size, 1e-300)
            ss_c = float(np.sum(dev**2))
            dof_c = (R - 1) * (int(g.real.sum()) // R - 1) - int(round(float(self.noise_params[c])))
            if varying.any():
                Z = D[..., varying].reshape(-1, int(varying.sum()))
                beta, *_ = np.linalg.lstsq(Z, dev.reshape(-1), rcond=None)
                rank = int(np.linalg.matrix_rank(Z))
                explained = float(np.sum((Z @ beta) ** 2))
                ss_num += explained
                dof_num += rank
                ss_den += ss_c - explained
                dof_den += dof_c - rank
        return (ss_num, dof_num, ss_den, dof_den) if dof_num else None

    def term_test(self, current: tuple[str, ...], name: str, threshold: float) -> FTest:
        return self.group_test(current, (name,), threshold)

    def group_test(self, current: tuple[str, ...], names: tuple[str, ...], threshold: float) -> FTest:
        """F test of the terms ``names`` together, added to ``current``."""
        full = tuple(current) + tuple(n for n in names if n not in current)
        a, b = self.fit(current), self.fit(full)
        ps, pd_ = self.pure(full)
        pss, pdof = ps.sum(), int(pd_.sum())
        return f_test(a.ss - b.ss, b.rank - a.rank, pss, pdof, threshold)

    # -- identifiability ------------------------------------------------------------------
    @property
    def identifiability(self) -> Identifiability:
        """Which terms the unit's steps cannot tell apart (:func:`identifiability.analyse`
        on the terms' columns with the affine model projected out, weighted and whitened as
        every fit here: the R factor of the full fold), undetermined columns left out."""
        if "_ident" not in self.__dict__:
            P = self.g.P
            Rg = self.Rg[0][:P, :P]
            terms, pnames = {}, {}
            for n in self.names:
                a, b = self.g.offset[n]
                keep = [k for k in range(a, b) if k not in self.undetermined and self.g.live_mask[:, k].any()]
                if keep:
                    terms[n] = Rg[:, keep]
                    pnames[n] = tuple(get_effect(n).param_names[k - a] for k in keep)
            self.__dict__["_ident"] = analyse(np.zeros((P, 0)), terms, pnames, CONFOUNDING_TOL)
        return self.__dict__["_ident"]

    @property
    def near_confounded(self) -> tuple[Confounded, ...]:
        """Pairs of terms near-collinear on the unit's steps but not confounded
        (:func:`identifiability.near_confounded` on the same columns as
        :attr:`identifiability`): the data decide them (:meth:`_settle_near_confounded`)."""
        if "_near" not in self.__dict__:
            P = self.g.P
            Rg = self.Rg[0][:P, :P]
            grouped = {n for grp in self.identifiability.groups() if len(grp) > 1 for n in grp}
            terms = {}
            for n in self.names:
                a, b = self.g.offset[n]
                keep = [k for k in range(a, b) if k not in self.undetermined and self.g.live_mask[:, k].any()]
                if keep and n not in grouped:
                    terms[n] = Rg[:, keep]
            self.__dict__["_near"] = near_confounded(terms, CONFOUNDING_TOL)
        return self.__dict__["_near"]

    def _settle_near_confounded(self, items: list[tuple[str, ...]]) -> list[tuple[str, ...]]:
        """A chosen term A with a near-confounded partner B (:attr:`near_confounded`) that
        alone would explain the data as well (B significant given the other chosen terms
        without A): A stays named when it is significant given B; B replaces it when B is
        significant given A and A not given B; when neither is significant given the other,
        the pair is one confounded item (the combined fit applied, no name picked). Tests
        at the terms' share of alpha (``term_alpha``) over the catalogue, as :meth:`_resolve`."""
        thr = self.term_alpha / len(self.names)
        out = list(items)
        for pair in self.near_confounded:
            names = tuple(n for i in out for n in i)
            a, b = pair.terms
            if (a in names) == (b in names) or (a,) not in out and (b,) not in out:
                continue  # both chosen (each significant given the other), or neither
            kept, rival = (a, b) if (a,) in out else (b, a)
            others = tuple(n for n in names if n != kept)
            if not self.term_test(others, rival, thr).rejects:
                continue  # the partner alone does not explain the data
            if self.term_test(others + (rival,), kept, thr).rejects:
                continue  # the chosen one is significant given its partner
            rival_given_kept = self.term_test(names, rival, thr).rejects
            out[out.index((kept,))] = (rival,) if rival_given_kept else tuple(sorted((kept, rival)))
        return out

    def test_groups(self) -> list[tuple[str, ...]]:
        """Candidates as tested: confounded terms together, the others alone."""
        ident = self.identifiability
        grouped = {n for g in ident.groups() for n in g}
        return sorted(ident.groups() + [(n,) for n in self.names if n not in grouped])

    def channels_of(self, name: str) -> tuple[int, ...]:
        a, b = self.g.offset[name]
        return tuple(int(c) for c in np.flatnonzero(self.g.live_mask[:, a:b].any(axis=1)))

    def sensor_channels(self, name: str) -> tuple[int, ...]:
        """The channels of the sensors the term's parameters act on (a term reaches the
        other channels of its triad only through misalignment)."""
        a, b = self.g.offset[name]
        live = self.g.live_mask[:, a:b].any(axis=0)
        return tuple(sorted({int(c) for c in get_effect(name).param_sensor()[live]}))

    # selection
    def select(self) -> tuple[list[str], list[str], list[str]]:
        """(chosen, partial, negligible) terms: stepwise selection (:func:`stepwise`) over
        the test groups (:meth:`test_groups`: terms the steps cannot tell apart enter
        together), each chosen group resolved (:meth:`_resolve`), then each chosen item must
        matter (:meth:`_verdict`); the worst that does not is set aside and the rest judged
        again. The items (a term, or a confounded group) are kept in ``self.items``."""
        groups = {"+".join(g): g for g in self.test_groups()}

        def flat(labels: tuple[str, ...]) -> tuple[str, ...]:
            return tuple(n for lab in labels for n in groups[lab])

        def test(current: tuple[str, ...], lab: str, threshold: float) -> FTest:
            return self.group_test(flat(current), groups[lab], threshold)

        def improves(current: tuple[str, ...], lab: str) -> bool:
            # the held-out score as the verdict counts it: on the channels the item acts on
            # significantly, on the steps it acts on. Counted on every channel it could act
            # on, the five parameters a one-sensor effect does not have are fitted noise:
            # a thermal scale drift of 19 ppm/degC on gyro z, its targeted test at p = 3e-8,
            # scored 0.9994 there (1.068 on its own channel) and was never chosen
            item, cur = groups[lab], flat(current)
            ch = self.item_channels(list(cur + item), item) or tuple(
                sorted({c for n in item for c in self.channels_of(n)})
            )
            return self._gain(cur, cur + item, ch) > 1.0

        labels = stepwise(list(groups), test, improves, self.term_alpha)
        chosen = self._settle_near_confounded(self._resolve([groups[lab] for lab in labels]))
        partial: list[tuple[str, ...]] = []
        negligible: list[tuple[str, ...]] = []
        while chosen:
            names = [n for item in chosen for n in item]
            verdicts = {item: self._verdict(names, item) for item in chosen}
            failing = [
                (kind != "partial", gain, item)
                for item, (kind, gain, _) in verdicts.items()
                if kind != "named"
            ]
            if not failing:
                break
            is_negligible, _, worst = min(failing)
            chosen.remove(worst)
            (negligible if is_negligible else partial).append(worst)
        self.items = {"chosen": chosen, "partial": partial, "negligible": negligible}
        return (
            [n for i in chosen for n in i],
            [n for i in partial for n in i],
            [n for i in negligible for n in i],
        )

    def _resolve(self, items: list[tuple[str, ...]]) -> list[tuple[str, ...]]:
        """A chosen group of confounded terms keeps the members the data single out: each
        member tested given everything else chosen (its group included), at alpha over the
        catalogue. Members that pass are named alone; when none does, the group stays one
        item (reported confounded, its combined fit applied)."""
        out: list[tuple[str, ...]] = []
        thr = self.term_alpha / len(self.names)
        names = [n for i in items for n in i]
        for item in items:
            if len(item) == 1:
                out.append(item)
                continue
            alone = [m for m in item if self.term_test(tuple(n for n in names if n != m), m, thr).rejects]
            if alone:
                names = [n for n in names if n not in item or n in alone]
                out += [(m,) for m in alone]
            else:
                out.append(item)
        return out

    # alpha, the false-alarm rate per unit, is shared by the tests that say "the unit
    # misfits" (Bonferroni): half by the lack-of-fit tests (the overall one alpha / 4, each
    # channel alpha / 24), half by the catalogue's targeted tests (alpha / 2 over the
    # candidates), which see a small effect along its own direction long before an omnibus
    # test over every direction does
    @property
    def lof_alpha(self) -> float:
        return self.alpha / 4

    @property
    def channel_alpha(self) -> float:
        return self.alpha / 24

    @property
    def term_alpha(self) -> float:
        return self.alpha / 2

    def misfit_channels(self) -> list[int]:
        """Channels whose lack of fit rejects at baseline (``channel_alpha`` each)."""
        before = self.channel_lack_of_fit((), self.channel_alpha)
        return [c for c in range(6) if before[CHANNELS[c]].rejects]

    def misfit_terms(self) -> list[str]:
        """Candidates (:meth:`test_groups`, joined by "+") whose targeted test on the affine
        model (:meth:`targeted_test`) or between-repetition test
        (:meth:`between_repetition_test`) rejects at ``term_alpha`` over the tests that run:
        the targeted part of "the unit misfits"."""
        return self._misfit_tests()[0]

    def misfit_between_terms(self) -> list[str]:
        """The candidates of :meth:`misfit_terms` whose between-repetition test rejects."""
        return self._misfit_tests()[1]

    def _misfit_tests(self) -> tuple[list[str], list[str]]:
        if "_misfit_terms" not in self.__dict__:
            groups = self.test_groups()
            # the between-repetition tests share the candidates' alpha only where they run
            varying = [g for g in groups if self.between_repetition_test(g, 1.0) is not None]
            thr = self.term_alpha / (len(groups) + len(varying))
            between = ["+".join(g) for g in varying if self.between_repetition_test(g, thr).rejects]
            self.__dict__["_misfit_terms"] = (
                ["+".join(g) for g in groups if self.targeted_test(g, thr).rejects or "+".join(g) in between],
                between,
            )
        return self.__dict__["_misfit_terms"]

    def unit_misfits(self) -> bool:
        """The union test: the overall or a channel's lack of fit, or a candidate's targeted
        test rejects; its false-alarm rate on a unit that fits is at most alpha."""
        return bool(
            self.lack_of_fit((), self.lof_alpha).rejects or self.misfit_channels() or self.misfit_terms()
        )

    def _verdict(self, chosen: list[str], name: str | tuple[str, ...]) -> tuple[str, float, tuple[int, ...]]:
        """("named" | "partial" | "negligible", held-out gain, channels it fixes) of a term
        or a confounded group. Named: the unit misfits, the term fixes a channel of its
        sensors that misfit at baseline (misfit without it, given the other chosen terms,
        and not with it) and its held-out gain on the channels it fixes is at least
        ``min_gain``. Partial: it acts on misfit channels and leaves them all misfit (it
        soaks up part of something else). A term whose presence is physics, not a defect
        (``named_when_significant``, the Earth rate), and any group holding one, is named
        once chosen when it improves the held-out score of its channels."""
        item = (name,) if isinstance(name, str) else tuple(name)
        others = tuple(x for x in chosen if x not in item)
        if any(get_effect(n).named_when_significant for n in item):
            ch = tuple(sorted({c for n in item for c in self.sensor_channels(n)}))
            gain = self._gain(others, tuple(chosen), ch)
            return ("named" if gain > 1.0 else "negligible"), gain, ch
        sensors = sorted({c for n in item for c in self.sensor_channels(n)})
        if not self.unit_misfits():
            return "negligible", 1.0, ()
        if not self.misfit_channels():
            # only the overall test or the targeted tests reject: the term must be what
            # makes the unit misfit (the overall test rejects without it and not with it,
            # or its own test given the other chosen terms rejects at the targeted tests'
            # threshold), and its gain counts on the sensors of its individually
            # significant parameters
            overall_fixed = (
                self.lack_of_fit(others, self.lof_alpha).rejects
                and not self.lack_of_fit(tuple(chosen), self.lof_alpha).rejects
            )
            targeted = any(set(item) & set(lab.split("+")) for lab in self.misfit_terms())
            if not (overall_fixed or targeted):
                return "negligible", 1.0, ()
            ch = self.item_channels(list(chosen), item) or tuple(sensors)
            if not ch:
                return "negligible", 1.0, ()
            gain = self._gain(others, tuple(chosen), ch)
            return ("named" if gain >= self.min_gain else "negligible"), gain, ch
        bad = [c for c in sensors if c in self.misfit_channels()]
        without = self.channel_lack_of_fit(others, self.channel_alpha) if bad else {}
        if not any(without[CHANNELS[c]].rejects for c in bad):
            # no channel of its sensors misfits, or the other chosen terms already fix every
            # one that did (two effects on one sensor): on its own sensors this term is
            # judged as when no channel misfits, by its own targeted or between-repetition
            # test (a drift between repetitions never makes a channel's lack of fit reject)
            if not any(set(item) & set(lab.split("+")) for lab in self.misfit_terms()):
                return "negligible", 1.0, ()
            ch = self.item_channels(list(chosen), item) or tuple(sensors)
            gain = self._gain(others, tuple(chosen), ch)
            return ("named" if gain >= self.min_gain else "negligible"), gain, ch
        with_ = self.channel_lack_of_fit(tuple(chosen), self.channel_alpha)
        fixed = tuple(c for c in bad if without[CHANNELS[c]].rejects and not with_[CHANNELS[c]].rejects)
        if not fixed:
            if all(with_[CHANNELS[c]].rejects for c in bad):
                return "partial", 1.0, ()
            return "negligible", 1.0, ()
        gain = self._gain(others, tuple(chosen), fixed)
        return ("named" if gain >= self.min_gain else "negligible"), gain, fixed

    def _gain(self, without: tuple[str, ...], with_: tuple[str, ...], channels: tuple[int, ...]) -> float:
        return self.heldout_score(without, with_, channels).gain

    def _param_t(self, chosen: list[str], name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(theta, stderr, |t| > the Bonferroni-corrected normal quantile) of the term's
        parameters in the fit of ``chosen`` (which holds ``name``)."""
        full = tuple(chosen)
        f = self.fit(full)
        k = self._theta_index(full, name)
        theta = f.theta[k]
        se = np.sqrt(np.diag(f.cov)[k] * self._scale(full))
        p = k.size
        t = np.abs(theta) / np.where(np.isfinite(se) & (se > 0), se, np.inf)
        sig = t > stats.norm.isf(self.alpha / (2 * p))
        if not sig.any() and np.isfinite(t).any() and np.nanmax(t) > 0:
            sig[int(np.nanargmax(t))] = True
        return theta, se, sig

    @staticmethod
    def _theta_index(full: tuple[str, ...], name: str) -> np.ndarray:
        """Indices of the term ``name``'s parameters in the coefficients of the fit of
        ``full`` (its terms in sorted order)."""
        names_sorted = sorted(full)
        off = sum(get_effect(m).n_params for m in names_sorted[: names_sorted.index(name)])
        return off + np.arange(get_effect(name).n_params)

    def significant_channels(self, chosen: list[str], name: str) -> tuple[int, ...]:
        """Channels of the sensors the term's individually significant parameters act on."""
        _, _, sig = self._param_t(chosen, name)
        return tuple(sorted({int(c) for c in get_effect(name).param_sensor()[sig]}))

    def item_channels(self, chosen: list[str], item: tuple[str, ...]) -> tuple[int, ...]:
        """Channels a term (:meth:`significant_channels`) or a confounded group acts on
        significantly. A group's members are near-collinear, so in their joint fit no single
        parameter need be significant while their sum on a sensor is: each sensor's
        parameters of the group are Wald-tested together (Bonferroni over the sensors), and
        the sensor with the largest statistic stands in when none passes."""
        if len(item) == 1:
            return self.significant_channels(chosen, item[0])
        full = tuple(chosen)
        f = self.fit(full)
        cov = f.cov * self._scale(full)
        idx = np.concatenate([self._theta_index(full, n) for n in item])
        sensor = np.concatenate([get_effect(n).param_sensor() for n in item])
        wald: dict[int, float] = {}
        for c in np.unique(sensor):
            k = idx[sensor == c]
            C = cov[np.ix_(k, k)]
            if not np.all(np.isfinite(C)):
                continue
            # the Wald statistic on the directions the covariance determines (one eigh)
            lam, V = np.linalg.eigh(C)
            keep = lam > 1e-10 * max(float(lam.max()), 0.0)
            if keep.any():
                z = V[:, keep].T @ f.theta[k]
                wald[int(c)] = float(stats.chi2.sf(np.sum(z**2 / lam[keep]), int(keep.sum())))
        if not wald:
            return ()
        hit = tuple(sorted(c for c, p in wald.items() if p < self.alpha / len(wald)))
        return hit or (min(wald, key=wald.get),)

    def finding(self, chosen: list[str], name: str, threshold: float) -> EffectFinding:
        others = tuple(x for x in chosen if x != name)
        full = tuple(others) + (name,)
        term = get_effect(name)
        p = term.n_params
        theta, se, sig = self._param_t(list(full), name)
        a = self.g.offset[name][0]
        undet = {term.param_names[k - a]: why for k, why in self.undetermined.items() if a <= k < a + p}
        _, _, fixed = self._verdict(list(full), name)
        ch = fixed or self.sensor_channels(name) or self.channels_of(name)
        sensor = term.param_sensor()
        axes = {CHANNELS[int(sensor[k])][1] for k in np.flatnonzero(sig)}

        def number(n: str, v: float) -> float | None:
            return None if n in undet or not np.isfinite(v) else float(v)

        return EffectFinding(
            name=name,
            axes=tuple(sorted(axes)),
            estimate={n: number(n, v) for n, v in zip(term.param_names, theta)},
            stderr={n: number(n, v) for n, v in zip(term.param_names, se)},
            units=dict(zip(term.param_names, term.param_units)),
            evidence=self.term_test(others, name, threshold),
            heldout_rms_before=(score := self.heldout_score(others, full, ch)).before,
            heldout_rms_after=score.after,
            heldout_steps=(score.steps, score.steps_total),
            channels=tuple(CHANNELS[c] for c in ch),
            undetermined=undet,
        )

    def confounded_finding(
        self,
        chosen: list[str],
        item: tuple[str, ...],
        threshold: float,
        separated_by: tuple[str, ...] | None = None,
    ) -> ConfoundedFinding:
        """A group the steps cannot tell apart, fitted together with ``chosen``."""
        full = list(chosen) + [n for n in item if n not in chosen]
        others = tuple(n for n in full if n not in item)
        # the channels its verdict judged it on (as a single term's finding), else all its sensors'
        _, _, fixed = self._verdict(full, tuple(item))
        ch = fixed or tuple(sorted({c for n in item for c in self.sensor_channels(n)}))
        sin = min(
            (
                c.sin_angle
                for c in self.identifiability.confounded + self.near_confounded
                if set(c.terms) & set(item)
            ),
            default=0.0,
        )
        # each member as if it were the whole explanation (with the other chosen terms): the
        # combined fit's split along the shared direction is arbitrary
        return ConfoundedFinding(
            terms=tuple(item),
            members=tuple(self.finding(list(others) + [n], n, threshold) for n in item),
            evidence=self.group_test(others, item, threshold),
            heldout_rms_before=(score := self.heldout_score(others, tuple(full), ch)).before,
            heldout_rms_after=score.after,
            heldout_steps=(score.steps, score.steps_total),
            channels=tuple(CHANNELS[c] for c in ch),
            sin_angle=float(sin),
            separated_by=tuple(separated_by or ()),
            separable=separated_by is None,
        )

    def _scale(self, names: tuple[str, ...]) -> float:
        """Variance factor of the weighted residual: the pure-error mean square."""
        ps, pd_ = self.pure(names)
        return float(ps.sum() / max(pd_.sum(), 1))

    def calibrations(self, names: tuple[str, ...]) -> list[Calibration]:
        f = self.fit(names)
        scale = self._scale(names)
        names_sorted = sorted(names)
        terms, off = [], 0
        for n in names_sorted:
            p = get_effect(n).n_params
            se = np.sqrt(np.diag(f.cov)[off : off + p] * scale)
            a = self.g.offset[n][0]
            names_p = get_effect(n).param_names
            undet = {names_p[k - a]: why for k, why in self.undetermined.items() if a <= k < a + p}
            theta = f.theta[off : off + p].copy()
            theta[~np.isfinite(theta)] = 0.0
            terms.append(TermValue(n, theta, se, undet))
            off += p
        b = self.biases(f)
        out = []
        for r, sm in enumerate(self.sessions):
            out.append(
                Calibration(
                    K_g=f.K[:3].copy(),
                    w0=b[r, :3].copy(),
                    K_a=f.K[3:].copy(),
                    f0=b[r, 3:].copy(),
                    gyro_unit=sm.gyro_unit,
                    accel_unit=sm.accel_unit,
                    terms=tuple(terms),
                    g_local=sm.g_local,
                    kind="turntable",
                    metadata={"source": "mimucal discovery joint fit", "rep": int(sm.key.rep)},
                )
            )
        return out


_BLAS_CONTROLLER: list = []  # threadpoolctl.ThreadpoolController, found once per process


def _single_thread_blas():
    """Many small factorisations: BLAS threads only cost synchronisation here (6x slower
    on a loaded 2-core machine). threadpoolctl is optional. The controller is built once:
    finding the loaded libraries (reading /proc/self/maps) cost ~5 ms per unit."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover
        import contextlib

        return contextlib.nullcontext()
    if not _BLAS_CONTROLLER:
        _BLAS_CONTROLLER.append(ThreadpoolController())
    return _BLAS_CONTROLLER[0].limit(limits=1, user_api="blas")


# re-linearisation of the bilinear model (K and the terms' geometry): stop when no sensing
# direction moves by more than this (rad; 1e-6 x 4 g of lever-arm acceleration is 0.004 mg,
# far below the 0.1 mg noise of a step mean), the chosen terms are the same and the noise
# estimate moved by less than 3 %; at most MAX_RELINEARISATIONS passes after the first
GEOMETRY_TOL = 1e-6
MAX_RELINEARISATIONS = 4


def diagnose_unit(
    step_means_by_rep: list[StepMeans],
    alpha: float = DEFAULT_ALPHA,
    tables: bool = True,
    min_gain: float = DEFAULT_MIN_GAIN,
) -> Diagnosis:
    """Diagnose one unit from its repetitions (see the module docstring for the tests).

    ``alpha`` is the family-wise false-alarm rate per unit; ``min_gain`` the held-out gain a
    term must reach on the channels it fixes to be named; ``tables=False`` skips the
    replayed residual tables (Monte Carlo speed)."""
    with _single_thread_blas():
        return _diagnose_unit(step_means_by_rep, alpha, tables, min_gain)


def _diagnose_unit(
    step_means_by_rep: list[StepMeans], alpha: float, tables: bool, min_gain: float
) -> Diagnosis:
    d = _Discovery(step_means_by_rep, alpha, min_gain=min_gain)
    chosen, partial, negligible = d.select()
    moves: list[float] = []
    while (chosen or partial or negligible) and len(moves) < MAX_RELINEARISATIONS:
        # the model is bilinear: the terms act through the geometry of K, and the affine
        # model's K is distorted by the effects it misses (and the noise reaches the
        # residual through K). Re-linearise around the model of every significant term (one
        # left partial or negligible on a poor geometry included) and select again.
        model = tuple(chosen + partial + negligible)
        K = d.fit(model).K
        geometry = SensingGeometry.from_gains(K[:3], K[3:])
        moves.append(geometry.distance(d.geometry))
        d2 = _Discovery(
            step_means_by_rep, alpha, geometry=geometry, noise_model=d.noise_model(model), min_gain=min_gain
        )
        noise_moved = float(np.max(np.abs(np.log(d2.sigma / d.sigma))))
        before = (sorted(chosen), sorted(partial), sorted(negligible))
        d = d2
        chosen, partial, negligible = d.select()
        if (
            moves[-1] < GEOMETRY_TOL
            and (sorted(chosen), sorted(partial), sorted(negligible)) == before
            and noise_moved < np.log(1.03)
        ):
            break
    lof_before = d.lack_of_fit((), d.lof_alpha)
    chosen_t = tuple(chosen)
    lof_after = d.lack_of_fit(chosen_t, d.lof_alpha)
    thr = d.term_alpha / len(d.names)
    items = d.items
    groups = [i for kind in ("chosen", "partial", "negligible") for i in items[kind] if len(i) > 1]
    effects = [d.finding(chosen, i[0], thr) for i in items["chosen"] if len(i) == 1]
    partial_f = [d.finding(chosen + [n], n, thr) for n in partial]
    negligible_f = [d.finding(chosen + [n], n, thr) for n in negligible]
    advice = _advice(d.sessions[0]) if groups or any(e.undetermined for e in effects) else []
    confounded = [
        d.confounded_finding(chosen, i, thr, _separated_by(advice, i)) for i in items["chosen"] if len(i) > 1
    ]
    cal_before = d.calibrations(())
    cal_after = d.calibrations(chosen_t)
    if tables:
        res_before = replay_unit(cal_before, d.sessions, d.noise)
        res_after = replay_unit(cal_after, d.sessions, d.noise)
    else:
        res_before = res_after = pd.DataFrame()
    sm0 = d.sessions[0]
    ch_before = d.channel_lack_of_fit((), d.channel_alpha)
    ch_after = d.channel_lack_of_fit(chosen_t, d.channel_alpha)
    diag = Diagnosis(
        lot=sm0.key.lot,
        unit=sm0.key.unit,
        n_reps=len(d.sessions),
        alpha=alpha,
        misfit=bool(d.unit_misfits() or chosen or partial),
        unexplained=bool(lof_after.rejects or partial or any(t.rejects for t in ch_after.values())),
        effects=effects,
        partial=partial_f,
        negligible=negligible_f,
        terms=cal_after[0].terms,
        lack_of_fit_before=lof_before,
        lack_of_fit_after=lof_after,
        channel_misfit_before=ch_before,
        channel_misfit_after=ch_after,
        noise=d.noise,
        calibrations_before=cal_before,
        calibrations_after=cal_after,
        residuals_before=res_before,
        residuals_after=res_after,
        heldout_rms_baseline=d.heldout_rms(()),
        heldout_rms_final=d.heldout_rms(chosen_t),
        min_gain=min_gain,
        relinearisations=moves,
        confounded=confounded,
        misfit_terms=list(d.misfit_terms()),
        misfit_between=list(d.misfit_between_terms()),
        confounded_set_aside=[list(i) for k in ("partial", "negligible") for i in items[k] if len(i) > 1],
        advice=[
            a.describe()
            for a in advice
            if a.terms
            and (
                any(set(a.terms) == set(i) or set(a.terms) <= set(i) for i in groups)
                or any(e.name in a.terms and e.undetermined for e in effects)
            )
        ],
    )
    try:
        diag.evidence = evidence_frame(d, diag, chosen, items)
    except Exception:  # pragma: no cover - figures never cost the unit its diagnosis
        diag.evidence = pd.DataFrame()
    return diag


_ADVICE_CACHE: dict[bytes, list] = {}


def _advice(sm: StepMeans) -> list:
    """:func:`calib_core.discovery.plan.advise` for the unit's protocol (the steps' motion and
    headings, nominal times and warm-up: the same for every unit of the protocol, kept)."""
    from calib_core.discovery.plan import advise

    key = b"".join(
        [
            np.asarray(sm.w_ref, float).tobytes(),
            np.asarray(sm.f_ref, float).tobytes(),
            sm.headings.tobytes(),
            sm.turned_deg().tobytes(),
            repr((sm.latitude_deg, sm.table_heading_deg)).encode(),
        ]
    )
    if key not in _ADVICE_CACHE:
        steps = pd.DataFrame(
            {
                "step": np.asarray(sm.step, np.int64),
                "test": np.asarray(sm.test).astype(str),
                **{f"w_ref_{a}": sm.w_ref[:, i] for i, a in enumerate("xyz")},
                **{f"f_ref_{a}": sm.f_ref[:, i] for i, a in enumerate("xyz")},
                "settle_s": np.zeros(len(sm)),
                "heading_deg": sm.headings,
                "turned0_deg": sm.turned_deg()[:, 0],
                "turned1_deg": sm.turned_deg()[:, 1],
            }
        )
        if len(_ADVICE_CACHE) >= 8:
            _ADVICE_CACHE.clear()
        _ADVICE_CACHE[key] = advise(
            steps, latitude_deg=sm.latitude_deg, table_heading_deg=sm.table_heading_deg
        )
    return _ADVICE_CACHE[key]


def _separated_by(advice: list, item: tuple[str, ...]) -> tuple[str, ...] | None:
    """The step sets that separate ``item`` (None: the protocol already sees a part of each
    member of its own, so no advice names it)."""
    for a in advice:
        if set(a.terms) & set(item) and len(a.terms) > 1:
            return tuple(a.separated_by)
    return None
