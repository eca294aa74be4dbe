"""The joint fit of model discovery: one unit's repetitions, every catalogue term's columns,
one weighted least squares over every step of both sensors.

The model, per channel c (gx gy gz in deg/s, ax ay az in g):

    ref_c(step) = K_c . raw(step) + b_c(rep) - sum_T E_T,c(step) theta_T

K is shared by the repetitions; each repetition has its own biases b; every catalogue term
T adds its regressors E_T (:mod:`calib_core.discovery.design`). Weighted by the noise model
(:mod:`calib_core.discovery.noise`) and whitened for its serial correlation, each channel's
bias-removed design is factorised once per repetition and per leave-one-repetition-out
fold; every fit of a term subset (:class:`JointFit`), its pure error, the held-out
residuals and the calibrations it stands for are then products of small triangular
matrices (:class:`JointModel`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from calib_core.calibration import Calibration, TermValue
from calib_core.discovery.design import Layout, UnitGrid, protocol_layout
from calib_core.discovery.measured_noise import MeasuredNoise
from calib_core.discovery.noise import NoiseModel, prewhiten
from calib_core.discovery.results import EXCITED_SHARE
from calib_core.effects import CHANNELS, SensingGeometry, catalogue, get_effect
from calib_core.errors import DesignError
from calib_core.linalg import (
    PinvSolution,
    lstsq_pinv,
    lstsq_pinv_stack,
    pinv_solutions,
    pinv_theta,
    qr_r,
    qr_r_columns,
)
from calib_core.steps import StepMeans


def centre(M: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Columns M (..., R, n, k) minus their w^2-weighted mean per repetition (the
    repetition's bias fitted: Frisch-Waugh-Lovell for the per-repetition bias columns), and
    the means (..., R, k)."""
    w2 = w**2
    mu = np.einsum("...n,...nk->...k", w2, M) / w2.sum(axis=-1)[..., None]
    return M - mu[..., None, :], mu


@dataclass
class JointFit:
    names: list[str]
    theta: np.ndarray
    rank: int
    ss: float  # weighted residual sum of squares
    K: np.ndarray  # (6, 3)
    v: np.ndarray  # (6, k) per channel: [-K_c, -theta on its live term columns, 0..., 1]
    ss_channel: np.ndarray | None  # (6,) weighted residual sum of squares (fold of all reps)
    pure_channel: np.ndarray | None  # (6,) its pure-error part
    solution: PinvSolution | None = field(default=None, repr=False)

    @property
    def cov(self) -> np.ndarray:
        """Of theta, in units of the weighted residual variance (1 if sigma is right); built
        on first use: the term tests need only theta and the rank."""
        if self.solution is None:
            return np.zeros((0, 0))
        return self.solution.cov


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


class HeldOutScore(NamedTuple):
    before: float  # held-out rms without the item, sigma
    after: float  # with it
    steps: int  # step means counted
    steps_total: int  # step means on its channels

    @property
    def gain(self) -> float:
        return self.before / self.after if self.after > 0 else float("inf")


def affine_fit(g: UnitGrid, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """K rows and physical residual (R, n, 6) of the affine model (own biases per
    repetition) weighted by w (R, n, 6)."""
    wc = np.moveaxis(w, -1, 0)  # (6, R, n)
    Mc, _ = centre(g.M[..., [0, 1, 2, -1]], wc)
    if not g.real.all():  # padding rows
        Mc[:, ~g.real] = 0.0
    Rf = qr_r((wc[..., None] * Mc).reshape(6, -1, 4))
    try:
        K = np.linalg.solve(Rf[:, :3, :3], Rf[:, :3, 3:])[..., 0]  # (6, 3)
    except np.linalg.LinAlgError:
        check_rank(g, w)  # says which channel cannot be determined
        raise
    resid = Mc[..., 3] - np.einsum("crnk,ck->crn", Mc[..., :3], K)
    return K, np.moveaxis(resid, 0, -1)


def check_rank(g: UnitGrid, weight: np.ndarray) -> None:
    """The affine model (K row + a bias per repetition) must be determined on every
    channel and fold: numpy's matrix_rank test on the weighted design, whose singular
    values are those of the repetitions' R factors placed block by block. Skipped when
    every fold's design is far from losing rank (:func:`_surely_full_rank`): the test
    could not fail."""
    R = g.R
    eps = np.finfo(float).eps
    w = np.moveaxis(weight, -1, 0)[..., None]  # (6, R, n, 1)
    D = np.concatenate([w * g.M[..., :3], w], axis=-1)  # (6, R, n, 4): [w raw | w]
    if _surely_full_rank(D):
        return
    R4 = qr_r(D)  # (6, R, 4, 4)
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


def joint_model(
    sessions: list[StepMeans],
    geometry: SensingGeometry | None = None,
    noise_fit: tuple[np.ndarray, np.ndarray] | None = None,
    measured: MeasuredNoise | None = None,
) -> JointModel:
    """The joint model of one unit's repetitions (at least 2, one unit). ``geometry``: the
    sensing geometry the terms act through (default: that of the affine fit's K).
    ``noise_fit`` = (K rows (6, 3), physical residual (R, n, 6) on the grid) of the model
    whose residuals estimate the noise (:meth:`JointModel.noise_model`); default: the affine
    model weighted by the within-step scatter alone. ``measured``: a noise measured
    independently of the repetitions (:mod:`calib_core.discovery.measured_noise`), which the
    tests then use instead of the noise estimated from the repetitions' scatter."""
    if len(sessions) < 2:
        raise DesignError(
            "E_DISCOVERY_REPS",
            "model discovery needs at least 2 repetitions of the unit: the "
            "step-to-step noise is estimated from their scatter",
        )
    units = {(sm.key.lot, sm.key.unit) for sm in sessions}
    if len(units) != 1:
        raise ValueError(f"sessions of several units: {sorted(units)}")
    sessions = sorted(sessions, key=lambda s: s.key.rep)
    names = sorted(catalogue())
    # one layout for every grid of this unit (its motion contexts keep the term columns)
    lay = protocol_layout(sessions)
    # the affine fit needs no term columns: they are built once the geometry is known
    g = UnitGrid.build(sessions, names if geometry is not None else [], geometry, layout=lay)
    if noise_fit is None:
        # affine fit weighted by within-step scatter only, to get K and residuals
        white = g.white_sigma(np.tile(np.eye(3), (2, 1)))
        w0 = np.where(g.real[..., None], 1.0 / np.maximum(white, 1e-300), 0.0)
        noise_fit = affine_fit(g, w0)
    if geometry is None:  # the terms act through the affine fit's sensing geometry
        K = noise_fit[0]
        geometry = SensingGeometry.from_gains(K[:3], K[3:])
        g = UnitGrid.build(sessions, names, geometry, layout=lay, outputs=(g.raw, g.std, g.count))
    # the noise measured elsewhere, or from the data: within-step scatter through K +
    # repetition scatter
    if measured is not None:
        noise = NoiseModel.from_description(
            g, noise_fit[0], measured.description(g, sessions[0].sample_rate_hz)
        )
    else:
        noise = NoiseModel.from_residuals(g, *noise_fit)
    return JointModel(sessions, names, lay, g, geometry, noise)


class JointModel:
    """One unit's joint model, factorised once: every fit of any term subset on any
    leave-one-repetition-out fold (:meth:`fit` -> :class:`JointFit`), each repetition's
    biases, the pure error of a fit (:meth:`pure`), the held-out residuals and scores, and
    the calibrations a fit stands for. Built by :func:`joint_model`."""

    def __init__(
        self,
        sessions: list[StepMeans],
        names: list[str],
        lay: Layout,
        grid: UnitGrid,
        geometry: SensingGeometry,
        noise: NoiseModel,
    ):
        self.sessions = sessions
        self.names = names
        self.layout = lay
        self.g = grid
        self.geometry = geometry
        self.noise = noise
        self.sigma = noise.sigma
        self.weight = noise.weight
        self.serial = noise.serial
        self._linv: dict[bytes, np.ndarray] = {}  # the whitening of each repetition's step times
        check_rank(self.g, self.weight)  # before anything solves with the affine part
        # which columns the steps determine needs the fold of all repetitions alone
        self._prepare()
        self._first_fold()
        self.undetermined = self._undetermined()
        if any(self.g.live_mask[:, k].any() for k in self.undetermined):
            # fitted as 0: rebuild the terms' columns without them (a column no step excites
            # is in no channel's columns already: the grid would be the same)
            dropped = frozenset(self.undetermined)
            self.g = UnitGrid.build(
                self.sessions,
                self.names,
                geometry,
                dropped,
                self.layout,
                self.g.regressors,
                (self.g.raw, self.g.std, self.g.count),
            )
            self._prepare()
            self.term_svds, self._term_solutions = {}, {}  # of the factor before the rebuild
        self._complete()
        self._fits: dict[tuple, JointFit] = {}
        self._heldout: dict[tuple, np.ndarray] = {}

    def _undetermined(self) -> dict[int, str]:
        """Term columns (global) the steps cannot determine, with the reason: no step
        excites the parameter, or its standard error with the term alone on the base model
        exceeds the term's ``max_useful_stderr`` (the protocol cannot tell a realistic value
        from 0)."""
        g, P = self.g, self.g.P
        Rg = self.Rg0[:P, :P]
        per_term: dict[str, dict[int, str]] = {}
        checked = []  # (term, its excited columns) for the standard-error test
        for name in self.names:
            a, b = g.offset[name]
            live = g.live_mask[:, a:b].any(axis=0)
            per_term[name] = {a + int(k): "no step excites it" for k in np.flatnonzero(~live)}
            cols = a + np.flatnonzero(live)
            if cols.size:
                checked.append((name, cols))
        # each term alone on the base model: the covariance of its parameters
        solutions = pinv_solutions([Rg[:, cols] for _, cols in checked])
        # the SVD of a term's columns scaled to unit length, for identifiability's (the same
        # matrix when every column is live): (its columns, s, Vt)
        self.term_svds = {
            name: (cols, sol.s, sol.Vt)
            for (name, cols), sol in zip(checked, solutions)
            if sol.live.all() and len(cols) <= P
        }
        # each term alone on the fold of all repetitions: the same design as its fit's
        self._term_solutions = {tuple(cols.tolist()): sol for (_, cols), sol in zip(checked, solutions)}
        for (name, cols), sol in zip(checked, solutions):
            term, a, out = get_effect(name), g.offset[name][0], per_term[name]
            se = np.sqrt(np.diag(sol.cov))
            flagged = ~(se <= term.max_useful_stderr)  # NaN (not separable) or too large
            for k, v in zip(cols[flagged].tolist(), se[flagged].tolist()):
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
        return {k: why for name in self.names for k, why in per_term[name].items()}

    def _prepare(self) -> None:
        """Per channel c, the weighted bias-removed design A_c = [raw_c | live terms | y],
        whitened, and its R factor per repetition."""
        g = self.g
        w = np.moveaxis(self.weight, -1, 0)  # (6, R, n)
        Mc, self.mu = centre(g.M, w)  # (6, R, n, k), (6, R, k)
        if not g.real.all():  # padding rows
            Mc[:, ~g.real] = 0.0
        self.Mc = Mc
        A_raw = w[..., None] * Mc
        A = prewhiten(A_raw, self.serial, g.real, g.t, self._linv)
        self.A = A
        self.A_seen = A_raw
        # each repetition's bias column, weighted and whitened as the rows (the lack-of-fit
        # test removes it per repetition)
        self.A_bias = prewhiten(np.where(g.real, w, 0.0)[..., None], self.serial, g.real, g.t, self._linv)[
            ..., 0
        ]
        # each channel's columns that are not 0 by construction: [raw | its live terms | y]
        k = A.shape[-1]
        self.columns = [list(range(3 + len(L))) + [k - 1] for L in g.live]
        self.Rrep = qr_r(A)  # (6, R, k, k)
        self.__dict__.pop("_bias_removed", None)
        self.__dict__.pop("_fold0", None)

    def _first_fold(self) -> None:
        """The fold of all repetitions alone (it stacks every repetition's factor) and its
        term factor (``Rg0`` (P+1, P+1)): what :meth:`_undetermined` needs. Kept for
        :meth:`_complete` unless the design is rebuilt (:meth:`_prepare` drops them)."""
        R, k = self.g.R, self.Rrep.shape[-1]
        Rf0 = qr_r(self.Rrep.reshape(6, 1, R * k, k))
        self.Rg0 = self._term_factor(Rf0)[0]
        self.__dict__["_fold0"] = (Rf0, self.Rg0)

    def _complete(self) -> None:
        """After :meth:`_prepare`: the R factor of the fold of all repetitions (``Rf0``) and
        its term factor (``Rg0``: the factor of every term column with the affine model
        projected out), of the pure-error part, and each fold leaving one repetition out
        (fold h: every repetition but h) factorised on the affine model's columns alone (what
        the held-out fits without terms use); the folds' factors of every column on first
        use (:meth:`fold_factors`, :meth:`fold_term_factors`): only fits with terms on a
        fold need them."""
        g, R = self.g, self.g.R
        A, A_raw = self.A, self.A_seen
        k = A.shape[-1]
        # the held-out score is the residual a user sees, residual / sigma, not whitened: a
        # slow effect (thermal drift) matters by its size, not by how far it is from the wander
        self.Rrep_seen = self.Rrep if A is A_raw else qr_r(A_raw)
        fold0 = self.__dict__.pop("_fold0", None)  # the same design: fold 0 is factorised
        self.Rf0 = qr_r(self.Rrep.reshape(6, 1, R * k, k)) if fold0 is None else fold0[0]  # (6, 1, k, k)
        # K_c = R_base^-1 (R_base,y - R_base,terms theta)
        self.K_solve0 = np.linalg.solve(self.Rf0[:, 0, :3, :3], self.Rf0[:, 0, :3, 3:])  # (6, 3, k - 3)
        affine = self._folds(self.Rrep[..., [0, 1, 2, k - 1]])  # (6, R, 4, 4)
        self.K_affine_folds = np.linalg.solve(affine[..., :3, :3], affine[..., :3, 3:])[..., 0]  # (6, R, 3)
        e, _, self.pure_dof = g.two_way(A)
        self.Rpure = qr_r_columns(e, self.columns)  # (6, k, k)
        # [R_terms c; 0 sqrt(ss_perp)] of the fold of all repetitions
        self.Rg0 = self._term_factor(self.Rf0)[0] if fold0 is None else fold0[1]
        self.__dict__.pop("_fold_factors", None)
        self.__dict__.pop("_fold_term_factors", None)
        self.rows_channel = int(g.real.sum())
        self.base_rank = [3 + R] * 6

    def _folds(self, Rrep: np.ndarray) -> np.ndarray:
        """R factors (6, R, m, m) of the folds leaving one repetition out, from each
        repetition's factor ``Rrep`` (6, R, k, m): fold h stacks them with h's rows 0."""
        R, k, m = Rrep.shape[1:]
        folds = np.broadcast_to(Rrep[:, None], (6, R, R, k, m)).copy()
        folds[:, np.arange(R), np.arange(R)] = 0.0
        return qr_r(folds.reshape(6, R, R * k, m))

    def fold_factors(self) -> tuple[np.ndarray, np.ndarray]:
        """Each fold leaving one repetition out on every column: its R factor (6, R, k, k)
        and R_base^-1 [R_base,terms | R_base,y] (6, R, 3, k - 3), built on first use."""
        out = self.__dict__.get("_fold_factors")
        if out is None:
            Rf = self._folds(self.Rrep)
            out = self.__dict__["_fold_factors"] = (Rf, np.linalg.solve(Rf[..., :3, :3], Rf[..., :3, 3:]))
        return out

    def fold_term_factors(self) -> np.ndarray:
        """(R, P+1, P+1) :attr:`Rg0` of each fold leaving one repetition out, built on first
        use."""
        out = self.__dict__.get("_fold_term_factors")
        if out is None:
            out = self.__dict__["_fold_term_factors"] = self._term_factor(self.fold_factors()[0])
        return out

    def _term_factor(self, Rf: np.ndarray) -> np.ndarray:
        """The affine model projected out: the trailing block of each fold's factor ``Rf``
        (6, folds, k, k), every channel's term columns put back in their global place (P + 1:
        padding, dropped), factorised per fold."""
        g, P = self.g, self.g.P
        n_folds, k = Rf.shape[1], Rf.shape[-1]
        T = np.zeros((n_folds, 6, k - 3, P + 2))
        for c in range(6):
            T[:, c][..., np.append(g.colmap[c], P)] = Rf[c, :, 3:, 3:]
        return qr_r(T.reshape(n_folds, 6 * (k - 3), P + 2)[..., : P + 1])

    # -- fits -----------------------------------------------------------------------------
    def fit(self, names: tuple[str, ...], fold: int | None = None) -> JointFit:
        key = (tuple(sorted(names)), fold)
        if key not in self._fits:
            self._fits[key] = self._fit(key[0], fold)
        return self._fits[key]

    def _fit(self, names: tuple[str, ...], fold: int | None) -> JointFit:
        g, P = self.g, self.g.P
        Rg = self.Rg0 if fold is None else self.fold_term_factors()[fold]
        c_all = Rg[:P, P]
        ss_perp = float(Rg[P, P] ** 2)
        cols = g.cols(names)
        solution = None
        if cols.size:
            R_S = Rg[:P, cols]
            known = self._term_solutions.get(tuple(cols.tolist())) if fold is None else None
            if known is not None:  # a term alone: factorised by _undetermined
                theta, rank = pinv_theta(known, c_all)
                solution = known
            else:
                theta, rank, solution = lstsq_pinv(R_S, c_all)
            d = c_all - R_S @ theta
            ss = float(d @ d) + ss_perp
        else:
            theta, rank = np.zeros(0), 0
            ss = float(c_all @ c_all) + ss_perp
        theta_ext = np.zeros(P + 2)
        theta_ext[cols] = theta
        tc = theta_ext[g.colmap]  # (6, k - 4) each channel's term coefficients
        # affine coefficients by back-substitution on the fold's factor of each channel
        KS = self.K_solve0 if fold is None else self.fold_factors()[1][:, fold]  # (6, 3, k - 3)
        K = KS[..., -1] - np.einsum("cij,cj->ci", KS[..., :-1], tc)
        v = np.empty((6, tc.shape[1] + 4))  # (6, k) [-K, -tc, 1]
        np.negative(K, out=v[:, :3])
        np.negative(tc, out=v[:, 3:-1])
        v[:, -1] = 1.0
        ss_c = pure_c = None
        if fold is None:
            ss_c = (np.einsum("cij,cj->ci", self.Rf0[:, 0], v) ** 2).sum(axis=1)
            pure_c = (np.einsum("cij,cj->ci", self.Rpure, v) ** 2).sum(axis=1)
        return JointFit(
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

    def biases(self, f: JointFit) -> np.ndarray:
        """Each repetition's biases (R, 6) under a fit of all repetitions: the weighted mean
        of what the fit leaves on the repetition."""
        return np.einsum("crk,ck->rc", self.mu, f.v)

    def noise_model(self, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """(K rows (6, 3), physical residual (R, n, 6)) of the fit of ``names``: what a
        noise model re-estimated around that fit takes (:meth:`NoiseModel.from_residuals`)."""
        f = self.fit(names)
        return f.K, np.einsum("crnk,ck->rnc", self.Mc, f.v)

    # -- public results of the fits, for presentation --------------------------------------
    @property
    def real(self) -> np.ndarray:
        """(R, n) which cells of the (repetition, step) grid are steps (False: padding)."""
        return self.g.real

    @property
    def steps(self) -> np.ndarray:
        """(R, n) step ids (-1 on padding)."""
        return self.g.step

    @property
    def contexts(self) -> list:
        """Each repetition's motion context (:class:`calib_core.effects.MotionContext`)."""
        return self.layout.ctx

    def residual(self, names: tuple[str, ...]) -> np.ndarray:
        """(R, n, 6) physical residual of the fit of ``names`` on every step, each
        repetition's own biases removed (deg/s, g; 0 on padding)."""
        return np.einsum("crnk,ck->rnc", self.Mc, self.fit(tuple(names)).v)

    def fitted_effect(self, names: tuple[str, ...], item: tuple[str, ...]) -> np.ndarray:
        """(R, n, 6) what the terms ``item`` contribute to the fit of ``names`` (which holds
        them): the residual with their coefficients set to 0 minus the fit's residual."""
        f = self.fit(tuple(names))
        v2 = f.v.copy()
        cols = set(self.g.cols(tuple(sorted(item))).tolist())
        for c in range(6):
            for j, col in enumerate(self.g.colmap[c]):
                if int(col) in cols:
                    v2[c, 3 + j] = 0.0
        return np.einsum("crnk,ck->rnc", self.Mc, v2) - np.einsum("crnk,ck->rnc", self.Mc, f.v)

    def pure(self, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        """Pure-error sum of squares and dof per channel of a model's weighted residual: its
        repetition-to-repetition scatter of the same step (dof net of the noise model's
        parameters, :attr:`NoiseModel.params`). Computed per model because the noise reaches the
        residual through that model's own K."""
        f = self.fit(names)
        dof = int(self.pure_dof.sum()) - np.round(self.noise.params)
        return f.pure_channel, dof.astype(np.int64)

    def _heldout_v(self, names: tuple[str, ...]) -> np.ndarray:
        """(6, R, k) each fold's coefficient vector [-K | -terms | 1] of channel c, fold h
        (repetitions but h): repetition h's rows times it are its held-out residual (its own
        biases fitted on itself); the R folds' fits are solved together."""
        key = ("v",) + tuple(sorted(names))
        if key not in self._heldout:
            g, P, R = self.g, self.g.P, self.g.R
            cols = g.cols(key[1:])
            theta_ext = np.zeros((R, P + 2))
            if cols.size:
                Rg = self.fold_term_factors()  # (R, P+1, P+1) the folds leaving one repetition out
                theta_ext[:, cols] = lstsq_pinv_stack(Rg[:, :P][:, :, cols], Rg[:, :P, P])
            tc = theta_ext[:, g.colmap]  # (R, 6, k - 4)
            if cols.size:
                KS = self.fold_factors()[1]  # (6, R, 3, k - 3)
                K = KS[..., -1] - np.einsum("chij,hcj->chi", KS[..., :-1], tc)  # (6, R, 3)
            else:  # the affine model alone
                K = self.K_affine_folds
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
    ) -> HeldOutScore:
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
            return HeldOutScore(
                float(np.sqrt(np.sum(zo**2) / total)), float(np.sqrt(np.sum(zf**2) / total)), total, total
            )
        order = np.argsort(d2)[::-1]
        m = min(int(np.searchsorted(np.cumsum(d2[order]), EXCITED_SHARE * tot)) + 1, total)
        rows = order[:m]
        return HeldOutScore(
            float(np.sqrt(np.mean(zo[rows] ** 2))), float(np.sqrt(np.mean(zf[rows] ** 2))), m, total
        )

    def heldout_rms(self, names: tuple[str, ...], channels: tuple[int, ...] | None = None) -> float:
        ss = self.heldout_ss(names)
        ch = list(range(6)) if channels is None else list(channels)
        n_rows = self.rows_channel * len(ch)
        return float(np.sqrt(ss[ch].sum() / n_rows))

    def bias_removed(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """Channel ``c``'s whitened design (R, n, k) with each repetition's own bias removed
        from every column, and the whitened bias column (R, n) (:meth:`bias_removed_design`)."""
        A, wb = self.bias_removed_design()
        return A[c], wb[c]

    def bias_removed_design(self) -> tuple[np.ndarray, np.ndarray]:
        """Every channel's whitened design (6, R, n, k) with each repetition's own bias
        removed from every column, and the whitened bias columns (6, R, n) (read-only, kept:
        asked by every test)."""
        out = self.__dict__.get("_bias_removed")
        if out is None:
            A, wb = self.A, self.A_bias
            coef = (
                np.einsum("crn,crnk->crk", wb, A)
                / np.maximum(np.einsum("crn,crn->cr", wb, wb), 1e-300)[..., None]
            )
            out = (A - wb[..., None] * coef[:, :, None, :], wb)
            for x in out:
                x.setflags(write=False)
            self.__dict__["_bias_removed"] = out
        return out

    def variance_scale(self, names: tuple[str, ...]) -> float:
        """Variance factor of the weighted residual: the pure-error mean square."""
        ps, pd_ = self.pure(names)
        return float(ps.sum() / max(pd_.sum(), 1))

    def calibrations(self, names: tuple[str, ...]) -> list[Calibration]:
        f = self.fit(names)
        scale = self.variance_scale(names)
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
