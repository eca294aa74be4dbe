"""The noise of a unit's step means, as model discovery weighs and tests with it.

One :class:`NoiseModel` per discovery: the step-mean sigma of every (repetition, step,
channel), each repetition's serial correlation (:class:`SerialNoise`: a wandering bias) and
the pure-error dof its estimation costs. It is estimated from the repetitions' scatter
(:meth:`NoiseModel.from_residuals`, the pooling rule of the replayed tables,
:func:`calib_core.discovery.replay.pool_step_noise`) or taken from a description measured
elsewhere (:meth:`NoiseModel.from_description`: a :class:`NoiseDescription`, e.g. from a
long static recording, costs the tests no dof). The corrections the tests make for noise
that is not white and spherical live here too: the Satterthwaite factor of unequal or
correlated steps (:func:`dof_inflation`), Box's epsilon (:func:`sphericity_epsilon`) and
the dof an estimated variance costs (:func:`variance_dof_cost`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import special

from calib_core.discovery.design import UnitGrid
from calib_core.discovery.replay import (
    MIN_POOL_DOF,
    NOISE_COLUMNS,
    NoiseEstimate,
    pool_step_noise,
)
from calib_core.effects import CHANNELS
from calib_core.errors import DesignError

# a triad's summed lag-1 correlation of the pure error, in standard errors of white noise,
# above which its steps are modelled as serially correlated (one-sided, 0.13 % per triad):
# the gate keeps two noisy correlations from switching the serial model on for units with
# white noise only (docs/model-discovery.md, "Design choices")
SERIAL_MIN_Z = 3.0


@dataclass(frozen=True)
class SerialNoise:
    """Noise of the step means of one repetition, per channel, as white noise plus a bias
    that wanders as a first-order Gauss-Markov process (the bias instability of a MEMS
    sensor, time constant tens of seconds, several steps long): correlation between two
    steps ``lam * exp(-|dt| / tau)``. ``lam`` 0: independent steps."""

    lam: np.ndarray  # (6,) share of the step-mean variance that wanders
    tau_s: np.ndarray  # (6,) its time constant

    @property
    def correlated(self) -> bool:
        return bool(np.any(self.lam > 0))


def serial_noise(z: np.ndarray, real: np.ndarray, t: np.ndarray) -> SerialNoise:
    """Estimate :class:`SerialNoise` from the normalised residual z (R, n, 6) of a model,
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
    median_dt = float(np.median(dt)) if dt.size else 0.0
    step_s = median_dt if median_dt > 0 else 1.0
    n = max(float(real.sum(axis=1).mean()), 2.0)
    lam, tau = np.zeros(6), np.ones(6)
    lag = np.arange(1, int(n))
    lag_weight = 1.0 - lag / n
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
        var_mean = total / n * (1.0 + 2.0 * lam * np.sum(lag_weight * phi[:, None] ** lag, axis=1))
    return SerialNoise(lam, tau)


# lags of the leftover serial correlation counted by dof_inflation (the steps a first-order
# wander of 20 s spans after whitening: its leftover correlation is gone by then)
_INFLATION_LAGS = 5


def dof_inflation(dev: np.ndarray) -> float:
    """Satterthwaite factor (>= 1) by which the effective degrees of freedom of a sum of
    squares of noise with covariance M fall below its count: n tr(M^2) / tr(M)^2, estimated
    from the repetitions' deviations ``dev`` (R, n) (each step's mean over the repetitions
    removed, so R - 1 dof per step). Unequal step variances (v_i, whose square is corrected
    for its own estimation noise: E v^2 = m^2 (R + 1) / (R - 1)) and the serial correlation
    left after whitening (lags 1.._INFLATION_LAGS, 1 + 2 sum rho_k^2) both make the sums
    spread more than the F distribution of the nominal dof assumes."""
    return float(dof_inflations(dev[None])[0])


def dof_inflations(dev: np.ndarray) -> np.ndarray:
    """:func:`dof_inflation` of each of a stack of deviations ``dev`` (C, R, n), (C,)."""
    _, R, n = dev.shape
    sq = dev**2
    v = np.sum(sq, axis=1) / (R - 1)  # (C, n)
    c0 = np.sum(sq, axis=(1, 2))
    rho2 = np.zeros(len(dev))
    with np.errstate(divide="ignore", invalid="ignore"):  # a silent block: 1 below
        for k in range(1, min(_INFLATION_LAGS, n - 1) + 1):
            rho2 = rho2 + (np.sum(dev[:, :, k:] * dev[:, :, :-k], axis=(1, 2)) / c0) ** 2
        hetero = n * np.sum(v**2, axis=1) * (R - 1) / (R + 1) / np.sum(v, axis=1) ** 2
    return np.where(np.any(v > 0, axis=1), np.maximum(hetero, 1.0) * (1.0 + 2.0 * rho2), 1.0)


def variance_dof_cost(dof: float, white_share: float) -> float:
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


def sphericity_epsilon(blocks: list[np.ndarray]) -> float:
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
    # each block's tr(S^) and |S^|^2, the blocks of one shape in one batched product
    by_shape: dict[tuple[int, ...], list[int]] = {}
    for i, d in enumerate(blocks):
        by_shape.setdefault(d.shape, []).append(i)
    traces, squares = np.zeros(len(blocks)), np.zeros(len(blocks))
    for at in by_shape.values():
        D = np.array([blocks[i] for i in at])
        S = D.swapaxes(-1, -2) @ D / n
        traces[at] = S.trace(axis1=-2, axis2=-1)
        squares[at] = (S * S).sum(axis=(-2, -1))
    t1, t2, t1sq = [], 0.0, 0.0
    for tr, a in zip(traces.tolist(), squares.tolist()):
        b = tr**2
        t2_c = n * (n * a - b) / ((n - 1) * (n + 2))
        t1.append(tr)
        t2 += t2_c
        t1sq += b - 2.0 * t2_c / n
    t1sq += sum(t1) ** 2 - sum(x * x for x in t1)  # the channels' cross products
    if t2 <= 0.0:
        return 1.0
    return float(np.clip(t1sq / (p * t2), 1.0 / p, 1.0))


def prewhiten(
    A: np.ndarray, noise: SerialNoise, real: np.ndarray, t: np.ndarray, cache: dict | None = None
) -> np.ndarray:
    """Rows (6, R, n, k) of each repetition whitened for the serial correlation of
    :class:`SerialNoise` (generalised least squares: L^-1 with L L^T the correlation of the
    repetition's steps): the tests, fits and held-out scores then treat the wander of the
    bias as the noise it is, not as a lack of fit common to the repetitions. White rows keep
    unit variance."""
    if not noise.correlated:
        return A
    out = np.zeros_like(A)
    lam = noise.lam[:, None, None]
    tau = noise.tau_s[:, None, None]
    # repetitions on the same step times share L^-1; ``cache``: kept by the caller for its
    # next rows whitened with the same noise
    done: dict[bytes, np.ndarray] = {} if cache is None else cache
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


@dataclass(frozen=True)
class NoiseDescription:
    """A unit's step-mean noise as a table, whoever measured it: per channel and test group
    (rows of ``NOISE_COLUMNS``: channel, group, dof, step_sd, white_sd, instability_sd) and
    the serial correlation of its wandering bias. ``estimated`` says whether it was
    estimated from the same repetitions the tests then use (its parameters cost them dof) or
    measured independently (e.g. an Allan variance of a long static recording: no cost).
    ``white_from_rows``: each step's white part is its group's ``white_sd`` (a measured model
    knows the step mean's white-like variance from its processes, a periodic line or a
    quantization averaged as they are) rather than the within-step scatter measured on the
    unit (which counts them at their per-sample variance)."""

    rows: tuple[tuple, ...]
    serial: SerialNoise
    estimated: bool = False
    white_from_rows: bool = False


class NoiseModel:
    """The noise discovery weighs, whitens and tests with, on one unit's grid: ``sigma``
    (R, n, 6) of every step mean (1 on padding), ``weight`` 1 / sigma (0 on padding),
    ``serial`` (:class:`SerialNoise`), ``rows`` (per channel and test group, as
    ``NOISE_COLUMNS``), ``estimate`` (the same as a :class:`NoiseEstimate`) and ``params``
    (the pure-error dof per channel its estimation costs)."""

    def __init__(
        self,
        grid: UnitGrid,
        K: np.ndarray,
        rows: list[tuple],
        sigma: np.ndarray,
        serial: SerialNoise,
        estimated: bool,
    ):
        self.grid = grid
        self.K = K  # the gain rows the within-step scatter reaches the step means through
        self.rows = rows
        self.sigma = sigma
        self.weight = np.where(grid.real[..., None], 1.0 / sigma, 0.0)
        self.serial = serial
        self.estimated = estimated

    @classmethod
    def from_residuals(cls, grid: UnitGrid, K: np.ndarray, resid: np.ndarray) -> NoiseModel:
        """Estimated from a model's physical residual ``resid`` (R, n, 6) and its gain rows
        ``K`` (6, 3): within-step scatter through K plus the repetitions' scatter of the same
        step, pooled per channel and test group (the replayed tables' rule, same numbers);
        the serial correlation from the residual normalised by that sigma."""
        g = grid
        white = g.white_sigma(K)
        ng = len(g.groups)
        e, grp, dof = g.two_way(resid)
        ss = np.zeros((6, ng))
        w2 = np.zeros((6, ng))
        for gi in range(ng):  # per test group: a handful
            ss[:, gi] = np.sum(e[grp == gi] ** 2, axis=0)
            w2[:, gi] = np.mean(white[g.gcode == gi] ** 2, axis=0)
        rows, inst = [], np.zeros((6, ng))
        dofs = dof.tolist()
        wsd = np.sqrt(w2).tolist()  # correctly rounded, as math.sqrt
        for c, (ch, ss_c) in enumerate(zip(CHANNELS, ss.tolist())):
            for gi, (gname, d, step_sd, w, x) in enumerate(pool_step_noise(g.groups, dofs, ss_c, wsd[c])):
                inst[c, gi] = x
                rows.append((ch, gname, d, step_sd, w, inst[c, gi]))  # np.float64, as before
        sigma = cls._sigma(g, white, inst)
        weight = np.where(g.real[..., None], 1.0 / sigma, 0.0)
        return cls(g, K, rows, sigma, serial_noise(resid * weight, g.real, g.t), True)

    @classmethod
    def from_description(cls, grid: UnitGrid, K: np.ndarray, description: NoiseDescription) -> NoiseModel:
        """A noise measured elsewhere: each step's sigma is its within-step scatter through
        ``K`` (or, ``description.white_from_rows``, the described white sd of its channel
        and test group) plus the described instability of its channel and test group (0 for
        a group the description lacks)."""
        g = grid
        lut = {(r[0], r[1]): float(r[5]) for r in description.rows}
        inst = np.array([[lut.get((ch, gn), 0.0) for gn in g.groups] for ch in CHANNELS], float)
        if description.white_from_rows:
            wlut = {(r[0], r[1]): float(r[4]) for r in description.rows}
            wg = np.array([[wlut.get((ch, gn), 0.0) for gn in g.groups] for ch in CHANNELS], float)
            white = np.where(g.real[..., None], wg.T[np.maximum(g.gcode, 0)], 0.0)
        else:
            white = g.white_sigma(K)
        sigma = cls._sigma(g, white, inst)
        out = cls(g, K, list(description.rows), sigma, description.serial, description.estimated)
        out.white_from_rows = description.white_from_rows
        return out

    @staticmethod
    def _sigma(g: UnitGrid, white: np.ndarray, inst: np.ndarray) -> np.ndarray:
        inst_row = np.where(g.real[..., None], inst.T[np.maximum(g.gcode, 0)], 0.0)
        sigma = np.sqrt(white**2 + np.nan_to_num(inst_row) ** 2)
        if not np.all(sigma[g.real] > 0):
            raise DesignError("E_DISCOVERY_NOISE", "zero noise estimate on some steps")
        sigma[~g.real] = 1.0
        return sigma

    def description(self) -> NoiseDescription:
        return NoiseDescription(
            tuple(self.rows), self.serial, self.estimated, getattr(self, "white_from_rows", False)
        )

    @property
    def estimate(self) -> NoiseEstimate:
        """The rows as the replayed tables' :class:`NoiseEstimate` (built on first use)."""
        if "_estimate" not in self.__dict__:
            self.__dict__["_estimate"] = NoiseEstimate.from_records(
                [dict(zip(NOISE_COLUMNS, r)) for r in self.rows], from_repetitions=True
            )
        return self.__dict__["_estimate"]

    @property
    def params(self) -> np.ndarray:
        """Pure-error dof (6,) that the noise model fitted to the repetitions' scatter costs,
        per channel (0 for a noise measured independently). The model is fitted to the pure
        error that the tests then divide by, so that pure error is smaller than an
        independent sample of the noise would be. Each step-mean variance (one per test
        group with enough dof of its own, one pooled for the groups that borrow it) costs
        :func:`variance_dof_cost`: 2 when the wander dominates the step (an estimated
        inverse weight: E[1 / q] = d / (d - 2)), 0 when the known white part does. On a
        triad with serial noise, its share ``lam`` costs 2 as well (the wander's variance is
        the inverse weight of the slow directions) and its time constant, shared by the
        triad, a third of a parameter per channel. Counted so, the lack-of-fit F of clean
        units has the F distribution's mean (docs/model-discovery.md gives the figures)."""
        if "_params" in self.__dict__:  # asked by every test of every term set
            return self.__dict__["_params"]
        if not self.estimated:
            out = np.zeros(6)
            out.setflags(write=False)
            self.__dict__["_params"] = out
            return out
        cost = np.zeros(6)
        pooled: dict[int, list[float]] = {}
        dof_c = np.zeros(6)  # each channel's pooled dof: what a borrowed variance has
        for row in self.rows:
            dof_c[CHANNELS.index(row[0])] += row[2]
        for ch, _group, d, step_sd, wsd, *_ in self.rows:
            c = CHANNELS.index(ch)
            share = wsd**2 / step_sd**2 if step_sd > 0 else 1.0
            if d >= MIN_POOL_DOF:
                cost[c] += variance_dof_cost(d, share)
            else:  # the borrowed pooled variance: counted once, at the borrowers' white share
                pooled.setdefault(c, []).append(share)
        for c, shares in pooled.items():
            cost[c] += variance_dof_cost(dof_c[c], float(np.mean(shares)))
        # the wander's share is a variance too (the inverse of the slow directions' weight):
        # 2, as an estimated step variance; its time constant, shared by the triad, a third
        serial = np.where(self.serial.lam > 0, 2.0 + 1.0 / 3.0, 0.0)  # its triads only
        out = cost + serial
        out.setflags(write=False)
        self.__dict__["_params"] = out
        return out
