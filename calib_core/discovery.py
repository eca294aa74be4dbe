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

Weights are 1/sigma of each step mean, estimated from the data (:mod:`calib_core.replay`):
within-step scatter plus the step-to-step scatter seen across repetitions.

Tests (alpha is the family-wise false-alarm rate per unit, default 1%):

- **misfit** (lack of fit): the residual of the model is split into *pure error* (what is
  left after a free value per step and per repetition, i.e. the repetition-to-repetition
  scatter) and *lack of fit* (the rest). F = (SS_lof/dof_lof) / (SS_pure/dof_pure) against
  F(dof_lof, dof_pure). A systematic error common to the repetitions inflates SS_lof only.
- **a term** T added to the current set S: F = (dSS/p) / (SS_pure/dof_pure) against
  F(p, dof_pure) (p = rank gained), at alpha / (number of candidate terms) (Bonferroni over
  the catalogue), *and* its leave-one-repetition-out held-out rms must drop (gain > 1).
- forward selection adds the most significant eligible term and repeats; a backward pass
  drops any chosen term no longer significant given the others.
- a chosen term must fix at least one channel it acts on that misfit at baseline
  (per-channel lack-of-fit test at alpha/6); a term that leaves all of them misfit only
  soaks up part of something else and is reported as a *partial* candidate, not an effect.
- **misfit**: the baseline lack-of-fit test rejects, or a term was significant (a
  targeted test is more powerful than the omnibus one).
- **unexplained**: the lack-of-fit test still rejects after selection, or a partial term was
  set aside.

Held-out score: each repetition in turn is held out, the model is fitted on the others,
the held-out repetition is predicted (its own biases fitted, as at turn-on) and its residual
normalised by sigma; rms over all folds. ``gain`` = rms without the term / rms with it, over
the channels the term acts on.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from calib_core.calibration import Calibration, TermValue
from calib_core.effects import CHANNELS, MotionContext, catalogue, get_effect
from calib_core.errors import DesignError
from calib_core.replay import (NoiseEstimate, estimate_noise_arrays, noise_sigma, replay_unit,
                               test_group, two_way_residual, white_sigma)
from calib_core.steps import StepMeans
from calib_core.results import to_jsonable

DEFAULT_ALPHA = 0.01
_RCOND = 1e-10


# -- the stacked data of one unit -------------------------------------------------------
@dataclass
class UnitStack:
    """All repetitions of a unit in long form: one row per (repetition, step, channel)."""

    sessions: list[StepMeans]
    rep_index: np.ndarray  # (N,) 0..R-1
    channel: np.ndarray  # (N,) 0..5
    step: np.ndarray  # (N,) step id
    group: np.ndarray  # (N,) test group (noise pooling)
    y: np.ndarray  # (N,) reference of the channel
    raw: np.ndarray  # (N, 3) raw outputs of the channel's sensor
    contexts: list[MotionContext]

    @property
    def n_reps(self) -> int:
        return len(self.sessions)

    @classmethod
    def build(cls, sessions: list[StepMeans]) -> "UnitStack":
        rep_index, channel, step, group, y, raw, ctxs = [], [], [], [], [], [], []
        for r, sm in enumerate(sessions):
            n = len(sm)
            rep_index.append(np.full(6 * n, r))
            channel.append(np.tile(np.arange(6), n))
            step.append(np.repeat(sm.step.astype(np.int64), 6))
            group.append(np.repeat([test_group(t) for t in sm.test], 6))
            y.append(np.hstack([sm.w_ref, sm.f_ref]).ravel())
            rr = np.empty((n, 6, 3))
            rr[:, :3, :] = sm.gyro[:, None, :]
            rr[:, 3:, :] = sm.accel[:, None, :]
            raw.append(rr.reshape(6 * n, 3))
            ctxs.append(MotionContext.from_refs(sm.w_ref, sm.f_ref, temp_c=sm.temp_c,
                                                t=sm.t_mid, g_local=sm.g_local))
        return cls(sessions=list(sessions), rep_index=np.concatenate(rep_index),
                   channel=np.concatenate(channel), step=np.concatenate(step),
                   group=np.concatenate(group).astype(str), y=np.concatenate(y),
                   raw=np.concatenate(raw), contexts=ctxs)

    def regressors(self, name: str) -> np.ndarray:
        """Design columns of a term, (N, p): minus its regressors (ref = ... - E theta)."""
        term = get_effect(name)
        return -np.concatenate([term.regressors(c).reshape(len(c) * 6, term.n_params)
                                for c in self.contexts])

    def white_sigma(self, K: np.ndarray) -> np.ndarray:
        """Within-step scatter through the 6x3 gain rows K (gyro rows then accel rows)."""
        out = []
        for sm in self.sessions:
            cal = Calibration(K_g=K[:3], w0=np.zeros(3), K_a=K[3:], f0=np.zeros(3))
            out.append(white_sigma(cal, sm).ravel())
        return np.concatenate(out)


# -- weighted least squares with the base model projected out (Frisch-Waugh-Lovell) -------
class _Fold:
    """The base model (K rows + per-repetition biases, per channel) fitted on the training
    rows; term columns are fitted after projecting the base out, channel by channel."""

    def __init__(self, st: UnitStack, weight: np.ndarray, held_out: int | None):
        self.st, self.w, self.held_out = st, weight, held_out
        train = np.ones(len(st.y), bool) if held_out is None else st.rep_index != held_out
        self.reps = [r for r in range(st.n_reps) if r != held_out]
        self.idx, self.Q, self.R, self.rank = [], [], [], []
        for c in range(6):
            idx = np.flatnonzero(train & (st.channel == c))
            X = self._base_design(idx) * weight[idx, None]
            Q, R = np.linalg.qr(X)
            self.idx.append(idx)
            self.Q.append(Q)
            self.R.append(R)
            self.rank.append(int(np.linalg.matrix_rank(X)))
            if self.rank[-1] < X.shape[1]:
                raise DesignError("E_DISCOVERY_RANK",
                                  f"channel {CHANNELS[c]}: the steps cannot determine the "
                                  f"affine model (rank {self.rank[-1]} < {X.shape[1]})",
                                  (CHANNELS[c],))
        self.rows = np.concatenate(self.idx)
        self.y_res = self._project_out(st.y[:, None])[:, 0]

    def _base_design(self, idx: np.ndarray) -> np.ndarray:
        onehot = (self.st.rep_index[idx, None] == np.array(self.reps)[None, :]).astype(float)
        return np.hstack([self.st.raw[idx], onehot])

    def _project_out(self, cols: np.ndarray) -> np.ndarray:
        out = []
        for idx, Q in zip(self.idx, self.Q):
            a = cols[idx] * self.w[idx, None]
            out.append(a - Q @ (Q.T @ a))
        return np.concatenate(out)

    def _all_terms(self, Zs: dict[str, np.ndarray]) -> None:
        """One QR of every catalogue column with the base projected out: any subset of
        terms is then fitted on the small triangular factor (exactly, no normal equations):
        min |y - Z_S theta|^2 = min |Q^T y - R_S theta|^2 + |y - Q Q^T y|^2."""
        if hasattr(self, "_R_all"):
            return
        names = sorted(Zs)
        self._offset, off = {}, 0
        for n in names:
            self._offset[n] = (off, off + Zs[n].shape[1])
            off += Zs[n].shape[1]
        self._Z_all = self._project_out(np.hstack([Zs[n] for n in names]))
        Q, self._R_all = np.linalg.qr(self._Z_all)
        self._c_all = Q.T @ self.y_res
        self._ss_perp = float(max(self.y_res @ self.y_res - self._c_all @ self._c_all, 0.0))

    def _cols(self, names: list[str]) -> np.ndarray:
        return np.concatenate([np.arange(*self._offset[n]) for n in names])

    @property
    def base_rank(self) -> int:
        return int(sum(self.rank))

    def fit(self, names: list[str], Zs: dict[str, np.ndarray], residual: bool = False
            ) -> "_FitResult":
        if names:
            self._all_terms(Zs)
            cols = self._cols(names)
            R_S = self._R_all[:, cols]
            theta, cov, rank = _lstsq_cov(R_S, self._c_all)
            d = self._c_all - R_S @ theta
            ss = float(d @ d) + self._ss_perp
        else:
            theta, cov, rank = np.zeros(0), np.zeros((0, 0)), 0
            ss = float(self.y_res @ self.y_res)
        z = None
        if residual:  # weighted residual in the stack's row order (NaN off the training rows)
            z = np.full(len(self.st.y), np.nan)
            z[self.rows] = self.y_res - (self._Z_all[:, self._cols(names)] @ theta
                                         if names else 0.0)
        # base coefficients by back-substitution: beta_c = R^-1 Q^T (y_w - Z_w theta)
        Zfull = np.hstack([Zs[n] for n in names]) if names else np.zeros((len(self.st.y), 0))
        target = self.st.y - Zfull @ theta
        K = np.zeros((6, 3))
        b = np.zeros((self.st.n_reps, 6))
        for c, (idx, Q, R) in enumerate(zip(self.idx, self.Q, self.R)):
            beta = np.linalg.solve(R, Q.T @ (target[idx] * self.w[idx]))
            K[c] = beta[:3]
            b[self.reps, c] = beta[3:]
        return _FitResult(names=list(names), theta=theta, cov=cov, rank=rank, ss=ss, z=z,
                          K=K, b=b)

    def heldout_z(self, fit: "_FitResult", Zs: dict[str, np.ndarray]) -> np.ndarray:
        """Normalised residual of the held-out repetition, its biases fitted on itself."""
        st, h = self.st, self.held_out
        rows = np.flatnonzero(st.rep_index == h)
        pred = np.einsum("ij,ij->i", st.raw[rows], fit.K[st.channel[rows]])
        if fit.names:
            pred = pred + np.hstack([Zs[n][rows] for n in fit.names]) @ fit.theta
        w = self.w[rows]
        z = (st.y[rows] - pred) * w
        ch = st.channel[rows]
        for c in range(6):
            m = ch == c
            z[m] -= w[m] * (z[m] @ w[m]) / (w[m] @ w[m])
        return z


@dataclass
class _FitResult:
    names: list[str]
    theta: np.ndarray
    cov: np.ndarray  # of theta, in units of the weighted residual variance (1 if sigma right)
    rank: int
    ss: float  # weighted residual sum of squares
    z: np.ndarray | None  # weighted residual per stack row (fold of all repetitions only)
    K: np.ndarray  # (6, 3)
    b: np.ndarray  # (R, 6)


def _lstsq_cov(Z: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Least squares with column scaling; covariance from the SVD (pseudo-inverse on
    directions the data do not determine, whose variance is reported as inf)."""
    norms = np.linalg.norm(Z, axis=0)
    live = norms > 1e-12 * max(norms.max(), 1e-300)
    scale = np.where(live, norms, 1.0)
    U, s, Vt = np.linalg.svd(Z / scale, full_matrices=False)  # Z is small (R factor) here
    keep = s > _RCOND ** 0.5 * s[0] if len(s) and s[0] > 0 else np.zeros(len(s), bool)
    keep &= s > 0
    rank = int(keep.sum())
    inv_s = np.where(keep, 1.0 / np.where(keep, s, 1.0), 0.0)
    theta = (Vt.T * inv_s) @ (U.T @ y) / scale
    cov = (Vt.T * inv_s ** 2) @ Vt / np.outer(scale, scale)
    # a parameter with a component along an undetermined direction is undetermined
    undetermined = (np.abs(Vt[~keep]) > 1e-6).any(axis=0) | ~live
    cov[undetermined, :] = np.nan
    cov[:, undetermined] = np.nan
    theta[undetermined] = np.where(live[undetermined], theta[undetermined], 0.0)
    return theta, cov, rank


# -- results --------------------------------------------------------------------------
@dataclass(frozen=True)
class FTest:
    statistic: float
    dof1: int
    dof2: int
    p_value: float
    threshold: float

    @property
    def rejects(self) -> bool:
        return bool(self.p_value < self.threshold)

    def to_dict(self) -> dict[str, Any]:
        return {"test": "F", "statistic": self.statistic, "dof1": self.dof1, "dof2": self.dof2,
                "p_value": self.p_value, "threshold": self.threshold}


def _f_test(ss_num: float, dof_num: int, ss_den: float, dof_den: int, threshold: float) -> FTest:
    if dof_num <= 0 or dof_den <= 0 or ss_den <= 0:
        return FTest(float("nan"), int(dof_num), int(dof_den), 1.0, threshold)
    F = (max(ss_num, 0.0) / dof_num) / (ss_den / dof_den)
    return FTest(float(F), int(dof_num), int(dof_den), float(stats.f.sf(F, dof_num, dof_den)),
                 threshold)


@dataclass(frozen=True)
class EffectFinding:
    """One chosen (or partial) catalogue term with its evidence and held-out gain."""

    name: str
    axes: tuple[str, ...]
    estimate: dict[str, float]
    stderr: dict[str, float]
    units: dict[str, str]
    evidence: FTest
    heldout_rms_before: float
    heldout_rms_after: float

    @property
    def gain(self) -> float:
        return self.heldout_rms_before / self.heldout_rms_after

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "axes": list(self.axes), "estimate": self.estimate,
                "stderr": self.stderr, "units": self.units, "evidence": self.evidence.to_dict(),
                "heldout_rms_before": self.heldout_rms_before,
                "heldout_rms_after": self.heldout_rms_after, "gain": self.gain}


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

    @property
    def calibration(self) -> Calibration:
        """The unit's extended calibration (biases averaged over the repetitions)."""
        cals = self.calibrations_after
        return replace(cals[0], w0=np.mean([c.w0 for c in cals], axis=0),
                       f0=np.mean([c.f0 for c in cals], axis=0))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (non-finite numbers become None)."""
        return _jsonable({
            "unit": self.unit, "lot": self.lot, "n_reps": self.n_reps, "alpha": self.alpha,
            "misfit": self.misfit, "unexplained": self.unexplained,
            "effects": [e.to_dict() for e in self.effects],
            "partial": [e.to_dict() for e in self.partial],
            "lack_of_fit_before": self.lack_of_fit_before.to_dict(),
            "lack_of_fit_after": self.lack_of_fit_after.to_dict(),
            "misfit_channels_before": [c for c, t in self.channel_misfit_before.items()
                                       if t.rejects],
            "misfit_channels_after": [c for c, t in self.channel_misfit_after.items()
                                      if t.rejects],
            "heldout_rms_baseline": self.heldout_rms_baseline,
            "heldout_rms_final": self.heldout_rms_final,
            "noise": self.noise.table.to_dict(orient="records"),
        })


_jsonable = to_jsonable  # one JSON conversion for the whole project


# -- the procedure ----------------------------------------------------------------------
class _Discovery:
    def __init__(self, sessions: list[StepMeans], alpha: float,
                 noise_model: tuple[np.ndarray, np.ndarray] | None = None):
        """``noise_model`` = (K rows (6, 3), physical residual per stack row) of the model
        whose residuals estimate the noise; default: the affine model."""
        if len(sessions) < 2:
            raise DesignError("E_DISCOVERY_REPS",
                              "model discovery needs at least 2 repetitions of the unit: the "
                              "step-to-step noise is estimated from their scatter")
        units = {(sm.key.lot, sm.key.unit) for sm in sessions}
        if len(units) != 1:
            raise ValueError(f"sessions of several units: {sorted(units)}")
        self.sessions = sorted(sessions, key=lambda s: s.key.rep)
        self.alpha = alpha
        self.st = UnitStack.build(self.sessions)
        self.names = sorted(catalogue())
        self.Zs = {n: self.st.regressors(n) for n in self.names}
        if noise_model is None:
            # affine fit weighted by within-step scatter only, to get K and residuals
            w0 = 1.0 / np.maximum(self.st.white_sigma(np.tile(np.eye(3), (2, 1))), 1e-300)
            fit0 = _Fold(self.st, w0, None).fit([], self.Zs, residual=True)
            noise_model = (fit0.K, fit0.z / w0)
        # noise from the data: within-step scatter through K + repetition scatter
        self.noise, self.sigma = self._noise(*noise_model)
        self.weight = 1.0 / self.sigma
        self.folds = {h: _Fold(self.st, self.weight, h) for h in [None, *range(self.st.n_reps)]}
        self._fits: dict[tuple, _FitResult] = {}
        self._heldout: dict[tuple, np.ndarray] = {}
        self._pure_cache: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def noise_model(self, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        f = self.fit(names)
        return f.K, f.z / self.weight

    def _noise(self, K: np.ndarray, resid: np.ndarray) -> tuple[NoiseEstimate, np.ndarray]:
        st = self.st
        names = np.array(CHANNELS)[st.channel]
        white = st.white_sigma(K)
        noise = estimate_noise_arrays(names, st.group, st.rep_index, st.step, resid, white)
        sigma = noise_sigma(noise, names, st.group, white)
        if not np.all(sigma > 0):
            raise DesignError("E_DISCOVERY_NOISE", "zero noise estimate on some steps")
        return noise, sigma

    def _pure_cells(self) -> list[tuple]:
        """Per channel and test group: rows, and how to take their two-way residual."""
        if not hasattr(self, "_cells"):
            st, self._cells = self.st, []
            for c in range(6):
                for g in np.unique(st.group):
                    rows = np.flatnonzero((st.channel == c) & (st.group == g))
                    if rows.size == 0:
                        continue
                    _, ci = np.unique(st.step[rows], return_inverse=True)
                    ri = st.rep_index[rows]
                    shape = (ci.max() + 1, st.n_reps)
                    balanced = rows.size == shape[0] * shape[1] and \
                        np.unique(ci * shape[1] + ri).size == rows.size
                    self._cells.append((c, rows, (ci, ri, shape) if balanced else None,
                                        st.step[rows], ri))
        return self._cells

    def pure(self, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Pure-error sum of squares and dof per channel of a model's weighted residual: its
        repetition-to-repetition scatter of the same step. Computed per model because the
        noise reaches the residual through that model's own K."""
        key = tuple(sorted(names))
        if key not in self._pure_cache:
            z = self.fit(key).z
            ss, dof = np.zeros(6), np.zeros(6, int)
            for c, rows, bal, step, rep in self._pure_cells():
                if bal is not None:  # double centring (same as two_way_residual, faster)
                    ci, ri, shape = bal
                    t = np.zeros(shape)
                    t[ci, ri] = z[rows]
                    e = t - t.mean(axis=1, keepdims=True) - t.mean(axis=0, keepdims=True) + t.mean()
                    ss[c] += float(np.sum(e * e))
                    dof[c] += (shape[0] - 1) * (shape[1] - 1)
                else:
                    e, d = two_way_residual(z[rows], step, rep)
                    ss[c] += e @ e
                    dof[c] += d
            self._pure_cache[key] = (ss, dof)
        return self._pure_cache[key]

    # cached fits
    def fit(self, names: tuple[str, ...], fold: int | None = None) -> _FitResult:
        key = (tuple(sorted(names)), fold)
        if key not in self._fits:
            self._fits[key] = self.folds[fold].fit(list(key[0]), self.Zs,
                                                   residual=fold is None)
        return self._fits[key]

    def heldout(self, names: tuple[str, ...]) -> np.ndarray:
        """Held-out normalised residual of every row (each row from the fold holding out
        its repetition)."""
        key = tuple(sorted(names))
        if key not in self._heldout:
            z = np.empty(len(self.st.y))
            for h in range(self.st.n_reps):
                rows = self.st.rep_index == h
                z[rows] = self.folds[h].heldout_z(self.fit(key, h), self.Zs)
            self._heldout[key] = z
        return self._heldout[key]

    def heldout_rms(self, names: tuple[str, ...], channels: tuple[int, ...] | None = None) -> float:
        z = self.heldout(names)
        if channels is not None:
            z = z[np.isin(self.st.channel, channels)]
        return float(np.sqrt(np.mean(z ** 2)))

    # tests
    def lack_of_fit(self, names: tuple[str, ...], threshold: float) -> FTest:
        f = self.fit(names)
        dof_res = len(self.st.y) - self.folds[None].base_rank - f.rank
        ps, pd_ = self.pure(names)
        pss, pdof = ps.sum(), int(pd_.sum())
        return _f_test(f.ss - pss, dof_res - pdof, pss, pdof, threshold)

    def channel_lack_of_fit(self, names: tuple[str, ...], threshold: float) -> dict[str, FTest]:
        f = self.fit(names)
        ps, pd_ = self.pure(names)
        out = {}
        for c in range(6):
            m = self.st.channel == c
            n_params = sum(int((np.abs(self.Zs[n][m]).sum(axis=0) > 0).sum()) for n in names)
            dof_res = int(m.sum()) - self.folds[None].rank[c] - min(n_params, f.rank)
            ss = float(np.nansum(f.z[m] ** 2))
            out[CHANNELS[c]] = _f_test(ss - ps[c], dof_res - int(pd_[c]), ps[c], int(pd_[c]),
                                       threshold)
        return out

    def term_test(self, current: tuple[str, ...], name: str, threshold: float) -> FTest:
        a, b = self.fit(current), self.fit(tuple(current) + (name,))
        ps, pd_ = self.pure(tuple(current) + (name,))
        pss, pdof = ps.sum(), int(pd_.sum())
        return _f_test(a.ss - b.ss, b.rank - a.rank, pss, pdof, threshold)

    def channels_of(self, name: str) -> tuple[int, ...]:
        touched = np.abs(self.Zs[name]).sum(axis=1) > 0
        return tuple(int(c) for c in np.unique(self.st.channel[touched]))

    # selection
    def select(self) -> tuple[list[str], list[str]]:
        chosen: list[str] = []
        while True:
            cands = [n for n in self.names if n not in chosen]
            if not cands:
                break
            thr = self.alpha / len(cands)
            best, best_score = None, None
            for n in cands:
                t = self.term_test(tuple(chosen), n, thr)
                if not t.rejects:
                    continue
                ch = self.channels_of(n)
                before = self.heldout_rms(tuple(chosen), ch)
                if self.heldout_rms(tuple(chosen) + (n,), ch) >= before:
                    continue
                # most significant first; p underflows for strong effects: then the larger
                # explained sum of squares wins
                score = (float(stats.f.logsf(t.statistic, t.dof1, t.dof2)),
                         -t.statistic * t.dof1)
                if best is None or score < best_score:
                    best, best_score = n, score
            if best is None:
                break
            chosen.append(best)
        # backward pass: drop terms no longer significant given the others
        changed = True
        while changed and len(chosen) > 1:
            changed = False
            thr = self.alpha / len(self.names)
            worst, worst_p = None, -1.0
            for n in chosen:
                rest = tuple(x for x in chosen if x != n)
                t = self.term_test(rest, n, thr)
                if not t.rejects and t.p_value > worst_p:
                    worst, worst_p = n, t.p_value
            if worst is not None:
                chosen.remove(worst)
                changed = True
        # a chosen term must fix a channel it acts on that misfit at baseline
        before = self.channel_lack_of_fit((), self.alpha / 6)
        partial: list[str] = []
        while True:
            after = self.channel_lack_of_fit(tuple(chosen), self.alpha / 6)
            drop = None
            for n in chosen:
                bad = [CHANNELS[c] for c in self.channels_of(n) if before[CHANNELS[c]].rejects]
                if bad and all(after[c].rejects for c in bad):
                    drop = n
                    break
            if drop is None:
                break
            chosen.remove(drop)
            partial.append(drop)
        return chosen, partial

    def finding(self, chosen: list[str], name: str, threshold: float) -> EffectFinding:
        others = tuple(x for x in chosen if x != name)
        full = tuple(others) + (name,)
        f = self.fit(full)
        names_sorted = sorted(full)
        off = sum(get_effect(n).n_params for n in names_sorted[:names_sorted.index(name)])
        term = get_effect(name)
        p = term.n_params
        theta = f.theta[off:off + p]
        se = np.sqrt(np.diag(f.cov)[off:off + p] * self._scale(full))
        ch = self.channels_of(name)
        t = np.abs(theta) / np.where(np.isfinite(se) & (se > 0), se, np.inf)
        crit = stats.norm.isf(self.alpha / (2 * p))
        sig = np.flatnonzero(t > crit)
        if sig.size == 0 and np.isfinite(t).any():
            sig = np.array([int(np.nanargmax(t))])
        axes = set()
        for k in sig:
            touched = np.abs(self.Zs[name][:, k]) > 0
            for c in np.unique(self.st.channel[touched]):
                axes.add(CHANNELS[c][1])
        return EffectFinding(
            name=name, axes=tuple(sorted(axes)),
            estimate={n: float(v) for n, v in zip(term.param_names, theta)},
            stderr={n: float(v) for n, v in zip(term.param_names, se)},
            units=dict(zip(term.param_names, term.param_units)),
            evidence=self.term_test(others, name, threshold),
            heldout_rms_before=self.heldout_rms(others, ch),
            heldout_rms_after=self.heldout_rms(full, ch))

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
            se = np.sqrt(np.diag(f.cov)[off:off + p] * scale)
            terms.append(TermValue(n, f.theta[off:off + p].copy(), se))
            off += p
        out = []
        for r, sm in enumerate(self.sessions):
            out.append(Calibration(
                K_g=f.K[:3].copy(), w0=f.b[r, :3].copy(), K_a=f.K[3:].copy(), f0=f.b[r, 3:].copy(),
                gyro_unit=sm.gyro_unit, accel_unit=sm.accel_unit, terms=tuple(terms),
                g_local=sm.g_local, kind="turntable",
                metadata={"source": "mimucal discovery joint fit", "rep": int(sm.key.rep)}))
        return out


def _single_thread_blas():
    """Many small factorisations: BLAS threads only cost synchronisation here (6x slower
    on a loaded 2-core machine). threadpoolctl is optional."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover
        import contextlib
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


def diagnose_unit(step_means_by_rep: list[StepMeans], alpha: float = DEFAULT_ALPHA,
                  tables: bool = True) -> Diagnosis:
    """Diagnose one unit from its repetitions (see the module docstring for the tests).

    ``alpha`` is the family-wise false-alarm rate per unit; ``tables=False`` skips the
    replayed residual tables (Monte Carlo speed)."""
    with _single_thread_blas():
        return _diagnose_unit(step_means_by_rep, alpha, tables)


def _diagnose_unit(step_means_by_rep: list[StepMeans], alpha: float, tables: bool
                   ) -> Diagnosis:
    d = _Discovery(step_means_by_rep, alpha)
    chosen, partial = d.select()
    if chosen:
        # the affine model's K is distorted by the effects it misses, and the noise reaches
        # the residual through K: estimate the noise again with the chosen model and, if it
        # moved (more than 3 % on some channel and test group), select again with it
        d2 = _Discovery(step_means_by_rep, alpha, noise_model=d.noise_model(tuple(chosen)))
        if np.max(np.abs(np.log(d2.sigma / d.sigma))) > np.log(1.03):
            d = d2
            chosen, partial = d.select()
    lof_before = d.lack_of_fit((), alpha)
    chosen_t = tuple(chosen)
    lof_after = d.lack_of_fit(chosen_t, alpha)
    effects = [d.finding(chosen, n, alpha / len(d.names)) for n in chosen]
    partial_f = [d.finding(chosen + [n], n, alpha / len(d.names)) for n in partial]
    cal_before = d.calibrations(())
    cal_after = d.calibrations(chosen_t)
    if tables:
        res_before = replay_unit(cal_before, d.sessions, d.noise)
        res_after = replay_unit(cal_after, d.sessions, d.noise)
    else:
        res_before = res_after = pd.DataFrame()
    sm0 = d.sessions[0]
    return Diagnosis(
        lot=sm0.key.lot, unit=sm0.key.unit, n_reps=len(d.sessions), alpha=alpha,
        misfit=bool(lof_before.rejects or chosen or partial),
        unexplained=bool(lof_after.rejects or partial),
        effects=effects, partial=partial_f, terms=cal_after[0].terms,
        lack_of_fit_before=lof_before, lack_of_fit_after=lof_after,
        channel_misfit_before=d.channel_lack_of_fit((), alpha / 6),
        channel_misfit_after=d.channel_lack_of_fit(chosen_t, alpha / 6),
        noise=d.noise, calibrations_before=cal_before, calibrations_after=cal_after,
        residuals_before=res_before, residuals_after=res_after,
        heldout_rms_baseline=d.heldout_rms(()), heldout_rms_final=d.heldout_rms(chosen_t))


# -- simulated units for validation (tests, docs) ---------------------------------------
# Noise of a MEMS unit as the validation lots use it: white noise per sample, bias
# instability between steps (3x the white noise of a 2.5 s step mean), turn-on repeatability.
REALISTIC_NOISE = dict(
    gyro_noise_dps=0.05, gyro_bias_instability_dps=0.01, gyro_bias_repeatability_dps=0.05,
    accel_noise_g=1e-3, accel_bias_instability_g=1e-4, accel_bias_repeatability_g=1e-3)

# Realistic size of each built-in effect (nominal magnitude; scale multiplies it). Only the
# simulator uses this table: selection never looks at effect names.
_FULL_SCALE = np.array([300.0, 300.0, 3600.0])


def hidden_effect(name: str, rng: np.random.Generator, scale: float = 1.0
                  ) -> tuple[np.ndarray, str]:
    """Parameters of a built-in effect at realistic magnitude on random axes, and a
    description. Magnitudes (scale=1):

    - lever_arm: one accelerometer, position 2-8 mm from the rotation centre, random direction;
    - gyro_scale_nonlinearity: one gyro axis, quadratic and cubic parts each 0.02-0.06 %
      of full scale at full scale (MEMS datasheets: 0.1 % FS), random signs;
    - gyro_scale_asymmetry: one gyro axis, 300-1000 ppm;
    - gyro_g_sensitivity: 1-3 random entries of G, 0.01-0.05 deg/s per g;
    - accel_scale_nonlinearity: one axis, 0.3-1 mg/g^2;
    - thermal_bias_drift: one channel, gyro 0.005-0.02 deg/s/degC or accel 0.05-0.2 mg/degC
      (needs a temperature profile in the truth).
    """
    sign = lambda: rng.choice([-1.0, 1.0])  # noqa: E731
    term = get_effect(name)
    theta = np.zeros(term.n_params)
    if name == "lever_arm":
        i = rng.integers(3)
        v = rng.normal(size=3)
        theta[3 * i:3 * i + 3] = v / np.linalg.norm(v) * rng.uniform(2, 8)
        what = f"accelerometer {'xyz'[i]}"
    elif name == "gyro_scale_nonlinearity":
        i = rng.integers(3)
        fs = _FULL_SCALE[i]
        u = fs / 1000.0
        theta[i] = sign() * rng.uniform(2e-4, 6e-4) * fs / u ** 2
        theta[3 + i] = sign() * rng.uniform(2e-4, 6e-4) * fs / u ** 3
        what = f"gyro {'xyz'[i]}"
    elif name == "gyro_scale_asymmetry":
        i = rng.integers(3)
        theta[i] = sign() * rng.uniform(300, 1000)
        what = f"gyro {'xyz'[i]}"
    elif name == "gyro_g_sensitivity":
        k = rng.choice(9, size=rng.integers(1, 4), replace=False)
        theta[k] = [sign() * rng.uniform(0.01, 0.05) for _ in k]
        what = "G" + ",".join(term.param_names[j][1:] for j in k)
    elif name == "accel_scale_nonlinearity":
        i = rng.integers(3)
        theta[i] = sign() * rng.uniform(0.3, 1.0)
        what = f"accelerometer {'xyz'[i]}"
    elif name == "thermal_bias_drift":
        c = rng.integers(6)
        theta[c] = sign() * (rng.uniform(0.005, 0.02) if c < 3 else rng.uniform(0.05, 0.2))
        what = f"channel {CHANNELS[c]}"
    else:
        raise KeyError(f"no realistic magnitude known for {name!r}")
    return theta * scale, what


def simulate_unit(truth, steps: pd.DataFrame, rng: np.random.Generator, n_reps: int = 5,
                  lot: str = "SIM", unit: str = "U000") -> tuple[list[StepMeans], list]:
    """Step means of ``n_reps`` repetitions of one unit (each with its own turn-on biases),
    and the per-repetition truths."""
    from calib_core.simulator import draw_repetition_truth, simulate_step_means
    from calib_core.steps import SessionKey

    sessions, truths = [], []
    for r in range(1, n_reps + 1):
        tr = draw_repetition_truth(truth, rng)
        truths.append(tr)
        sessions.append(simulate_step_means(tr, steps, rng, key=SessionKey(lot, unit, r)))
    return sessions, truths
