"""The significance tests of model discovery, as functions of the joint model's fits.

Every test compares what a fit leaves with the repetitions' scatter of the same steps (the
pure error) and keeps its false-alarm rate when that noise is neither white nor spherical
(:mod:`calib_core.discovery.noise`):

- **lack of fit** (:meth:`Significance.lack_of_fit`, per channel
  :meth:`Significance.channel_lack_of_fit`): the residual's mean over the repetitions
  against their scatter, both projected on the directions the model leaves free
  (:meth:`Significance.projected_lack_of_fit`), F with Satterthwaite dof;
- **a term set added** to a model (:meth:`Significance.group_test`): the drop of the
  weighted residual sum of squares against the pure error, F(p, dof_pure);
- **targeted** (:meth:`Significance.targeted_test`): the affine model's mean residual on a
  term set's joint directions against the repetitions' scatter along them;
- **between repetitions** (:meth:`Significance.between_repetition_test`): the part of a
  term set that differs between the repetitions against their scatter about their mean.

A test is kept per (kind, terms[, threshold]): selection and the report ask for it again.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from scipy import stats

from calib_core.discovery.fit import JointModel
from calib_core.discovery.identifiability import orthonormal_bases_by_shape, orthonormal_basis
from calib_core.discovery.noise import dof_inflations, sphericity_epsilon
from calib_core.discovery.results import FTest, f_test
from calib_core.effects import CHANNELS
from calib_core.linalg import lstsq_min_norm

# a term column's part that differs between the repetitions, relative to the column, below
# which the between-repetition test does not run (the recorded temperature's noise alone
# makes a few parts in 1e3)
REP_VARYING_MIN = 0.05


def nested_f_test(
    ss_small: float,
    rank_small: int,
    ss_big: float,
    rank_big: int,
    ss_noise: float,
    dof_noise: float,
    threshold: float,
) -> FTest:
    """F test of the columns a bigger model adds to a nested smaller one: the drop of the
    weighted residual sum of squares over the rank it adds, against a noise sum of squares
    (the repetitions' pure error on a turntable; the bigger model's residual on static
    poses) over its dof."""
    return f_test(ss_small - ss_big, rank_big - rank_small, ss_noise, dof_noise, threshold)


def significant_parameters(theta: np.ndarray, stderr: np.ndarray, alpha: float) -> np.ndarray:
    """Which parameters of a term are individually significant: |theta| / stderr above the
    normal quantile of ``alpha`` two-sided, Bonferroni over the term's parameters (an
    undetermined or zero standard error is never significant)."""
    t = np.abs(theta) / np.where(np.isfinite(stderr) & (stderr > 0), stderr, np.inf)
    return t > stats.norm.isf(alpha / (2 * max(theta.size, 1)))


class TargetedParts(NamedTuple):
    blocks: list[np.ndarray]  # per channel (R, p_c): the repetitions' deviations, denominator
    joint_ss: float  # R |mean residual|^2 on the terms' joint directions, numerator
    joint_dof: int  # the joint directions
    joint_deviations: np.ndarray  # (R, joint_dof) the repetitions' deviations along them


class AffineChannel(NamedTuple):
    """One channel on the affine model, what the targeted, between-repetition and
    lack-of-fit tests of every candidate share."""

    A: np.ndarray  # (R, n, k) the bias-removed design
    Ub: np.ndarray  # (n, q) orthonormal basis of the affine model's mean columns
    rbar: np.ndarray  # (n,) mean residual over the repetitions
    dev: np.ndarray  # (R, n) the repetitions' deviations from it
    A_mean: np.ndarray  # (n, k) the design's mean over the repetitions
    rbar_free: np.ndarray  # (n,) rbar with the affine model's columns projected out


class Significance:
    """The tests of one :class:`JointModel`, each a function of its fits, kept once asked."""

    def __init__(self, model: JointModel):
        self.model = model
        self._tests: dict[tuple, Any] = {}  # by (kind, terms[, threshold])

    def lack_of_fit(self, names: tuple[str, ...], threshold: float) -> FTest:
        key = ("all", tuple(sorted(names)), threshold)
        if key not in self._tests:  # a function of the fit: selection and report ask again
            self._tests[key] = self._lack_of_fit(names, threshold)
        return self._tests[key]

    def _lack_of_fit(self, names: tuple[str, ...], threshold: float) -> FTest:
        if self.model.g.balanced:
            ss_lof, dof, ss_pure, dof_pure, inflation = self.projected_lack_of_fit(names).T
            # the channels' sums are independent: their Satterthwaite dof add
            return f_test(
                float(ss_lof.sum()),
                float(np.sum(dof / inflation)),
                float(ss_pure.sum()),
                float(np.sum(dof_pure / inflation)),
                threshold,
            )
        f = self.model.fit(names)
        dof_res = 6 * self.model.rows_channel - sum(self.model.base_rank) - f.rank
        ps, pd_ = self.model.pure(names)
        pss, pdof = ps.sum(), int(pd_.sum())
        return f_test(f.ss - pss, dof_res - pdof, pss, pdof, threshold)

    def channel_lack_of_fit(self, names: tuple[str, ...], threshold: float) -> dict[str, FTest]:
        key = ("channel", tuple(sorted(names)), threshold)
        if key not in self._tests:
            self._tests[key] = self._channel_lack_of_fit(names, threshold)
        return dict(self._tests[key])  # the tests are frozen; the dict is the caller's

    def _channel_lack_of_fit(self, names: tuple[str, ...], threshold: float) -> dict[str, FTest]:
        if self.model.g.balanced:
            parts = self.projected_lack_of_fit(names)
            return {
                CHANNELS[c]: f_test(ss, dof / infl, ssp, dofp / infl, threshold)
                for c, (ss, dof, ssp, dofp, infl) in enumerate(parts.tolist())
            }
        f = self.model.fit(names)
        ps, pd_ = self.model.pure(names)
        cols = self.model.g.cols(tuple(sorted(names)))
        out = {}
        for c in range(6):
            n_params = int(self.model.g.live_mask[c, cols].sum())
            dof_res = self.model.rows_channel - self.model.base_rank[c] - min(n_params, f.rank)
            out[CHANNELS[c]] = f_test(
                float(f.ss_channel[c]) - ps[c], dof_res - int(pd_[c]), ps[c], int(pd_[c]), threshold
            )
        return out

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
        :func:`dof_inflation` (the dof to test with are dof / inflation).
        Balanced grids only (every repetition the same steps)."""
        key = ("projected", tuple(sorted(names)))
        if key in self._tests:
            return self._tests[key]
        g, R = self.model.g, self.model.g.R
        f = self.model.fit(names)
        hits = g.hits(tuple(sorted(names)))
        out = np.zeros((6, 5))
        devs = np.zeros((6, R, g.n))
        for c in range(6):
            local = 3 + hits[c]
            if local.size:
                A, wb = self.model.bias_removed(c)  # (R, n, k), (R, n)
                resid = A @ f.v[c]  # (R, n)
                X = np.concatenate([A[..., :3], A[..., local], wb[..., None]], axis=-1).mean(axis=0)
                Ub = orthonormal_basis(X)
                rbar = resid.mean(axis=0)
                e = rbar - Ub @ (Ub.T @ rbar)
                dev = resid - rbar
            else:  # the affine model's columns alone, and its fit: the channel has no term column
                aff = self._affine_channel(c)
                Ub, e, dev = aff.Ub, aff.rbar_free, aff.dev
            dev = dev - (dev @ Ub) @ Ub.T
            devs[c] = dev
            dof = Ub.shape[0] - Ub.shape[1]
            dof_pure = (R - 1) * dof - self.model.noise.params[c]
            out[c, :4] = (R * float(e @ e), dof, float(np.sum(dev**2)), dof_pure)
        out[:, 4] = dof_inflations(devs)
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
        direction. The numerator takes the joint directions, not the per-channel ones: the
        leakage columns carry almost none of the effect, and testing them would spend dof
        (p 9 instead of 3 for the accelerometer nonlinearity, 18 instead of 6 for the
        thermal scale drift) for no noncentrality (docs/model-discovery.md gives the power
        and false-alarm figures). Unbalanced grids: :meth:`group_test`."""
        if not self.model.g.balanced:
            return self.group_test((), names, threshold)
        parts = self._targeted_parts(tuple(names))
        if not parts.joint_dof or not parts.blocks:
            return f_test(0.0, 0.0, 0.0, 0.0, threshold)
        # F(p, dof) holds when the noise is spherical in the directions of each sum; a
        # channel noisier than another along them, or a wander left along a slow one, makes
        # a sum spread like fewer dof (Box's epsilon, each sum its own)
        den = sum(float(np.sum(d**2)) for d in parts.blocks)
        dof = (self.model.g.R - 1) * sum(d.shape[1] for d in parts.blocks)
        e_num = sphericity_epsilon([parts.joint_deviations])
        e_den = sphericity_epsilon(parts.blocks)
        # F = (joint_ss / p) / (den / dof) against F(e_num p, e_den dof): each sum scaled by
        # its own epsilon so that f_test's ratio of mean squares stays that F
        return f_test(e_num * parts.joint_ss, e_num * parts.joint_dof, e_den * den, e_den * dof, threshold)

    def _targeted_parts(self, names: tuple[str, ...]) -> TargetedParts:
        """The sums of :meth:`targeted_test` on the affine model's residual: per channel the
        terms act on, the repetitions' deviations (R, p_c) in an orthonormal basis of the
        terms' columns that the channel's affine model does not span (``blocks``); on the
        terms' joint directions (the channels stacked), R |mean residual|^2, their number
        and the repetitions' deviations along them."""
        key = ("targeted", tuple(sorted(names)))
        if key in self._tests:  # selection and the report ask again at other thresholds
            return self._tests[key]
        g, R = self.model.g, self.model.g.R
        cols = g.cols(tuple(sorted(names)))
        index = np.zeros(g.P + 2, np.intp)  # each of the terms' global columns: its place in cols
        index[cols] = np.arange(len(cols))
        hits = g.hits(tuple(sorted(names)))
        chans = [c for c in range(6) if hits[c].size]
        affs = {c: self._affine_channel(c) for c in chans}
        # channels with as many term columns and affine directions: one batched product and
        # SVD each (the same numbers as channel by channel)
        shapes: dict[tuple[int, int], list[int]] = {}
        for c in chans:
            shapes.setdefault((hits[c].size, affs[c].Ub.shape[1]), []).append(c)
        Xts, Uts = {}, {}
        for same in shapes.values():
            Xt = np.array([affs[c].A_mean[:, 3 + hits[c]] for c in same])  # (m, n, h)
            Ub = np.array([affs[c].Ub for c in same])  # (m, n, q)
            size = np.sqrt(np.add.reduce(Xt * Xt, axis=-2)).max(axis=-1)  # (m,) the largest column norm
            Xt = Xt - Ub @ (Ub.swapaxes(-1, -2) @ Xt)
            U, s, _ = np.linalg.svd(Xt, full_matrices=False)
            for j, c in enumerate(same):
                Xts[c] = Xt[j]
                Uts[c] = U[j][
                    :, s[j] > float(size[j]) * 1e-8
                ]  # what the affine model spans is not the terms'
        blocks, means, devs = [], [], []
        n = g.n
        joint = np.zeros((len(chans) * n, len(cols)))  # the channels' term columns stacked
        for i, c in enumerate(chans):
            Xt, Ut, dev = Xts[c], Uts[c], affs[c].dev
            if Ut.shape[1]:
                blocks.append(dev @ Ut)
            joint[i * n : (i + 1) * n, index[g.colmap[c][hits[c]]]] = Xt
            means.append(affs[c].rbar_free)
            devs.append(dev)  # along the joint directions, which the affine model's miss
        Uj = orthonormal_basis(joint) if chans else np.zeros((0, 0))
        mean = np.concatenate(means) if means else np.zeros(0)
        out = TargetedParts(
            blocks,
            R * float(np.sum((Uj.T @ mean) ** 2)) if Uj.size else 0.0,
            int(Uj.shape[1]),
            np.concatenate(devs, axis=1) @ Uj if Uj.size else np.zeros((R, 0)),
        )
        self._tests[key] = out
        return out

    def _affine_channel(self, c: int) -> AffineChannel:
        """Channel ``c`` on the affine model (:class:`AffineChannel`; kept, every channel at
        once)."""
        key = ("affine channels",)
        out = self._tests.get(key)
        if out is None:
            A, wb = self.model.bias_removed_design()
            X = np.concatenate([A[..., :3], wb[..., None]], axis=-1).mean(axis=1)
            bases = orthonormal_bases_by_shape(dict(enumerate(X)))
            v = self.model.fit(()).v
            out = []
            for ch in range(6):
                Ub = bases[ch]
                resid = A[ch] @ v[ch]
                rbar = resid.mean(axis=0)
                out.append(
                    AffineChannel(
                        A[ch], Ub, rbar, resid - rbar, A[ch].mean(axis=0), rbar - Ub @ (Ub.T @ rbar)
                    )
                )
            self._tests[key] = out
        return out[c]

    def _varying_columns(self) -> np.ndarray:
        """(6, k - 4) which term columns of each channel differ between the repetitions by
        ``REP_VARYING_MIN`` of their size (kept). Whether a column differs is a question
        about the physical column, not about the weights (each repetition's own step
        sigmas). The squared spread about the repetitions' mean is the squared size less R
        times the mean's square (no deviations formed): its rounding, ~eps of the squared
        size, is far below the threshold's share of it."""
        key = ("varying columns",)
        out = self._tests.get(key)
        if out is None:
            M = self.model.Mc[..., 3:-1]
            size2 = np.einsum("crnk,crnk->ck", M, M)
            total = M.sum(axis=1)  # (6, n, k - 4) the repetitions' sum
            spread2 = size2 - np.einsum("cnk,cnk->ck", total, total) / M.shape[1]
            out = self._tests[key] = spread2 > REP_VARYING_MIN**2 * size2
        return out

    def _between_channel(self, c: int) -> tuple[np.ndarray, np.ndarray]:
        """Channel ``c``'s term columns as the between-repetition test takes them (kept,
        every channel at once): their deviations from the repetitions' mean (R, n, k - 3)
        and which of them vary (:meth:`_varying_columns`)."""
        key = ("between channels",)
        out = self._tests.get(key)
        if out is None:
            T = self.model.bias_removed_design()[0][..., 3:-1]
            out = self._tests[key] = T - T.mean(axis=1, keepdims=True)
        return out[c], self._varying_columns()[c]

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
        parameters, :attr:`NoiseModel.params`). ``None`` when no column of the terms differs
        between the repetitions by ``REP_VARYING_MIN`` of its size (nothing to test: the
        test would take a share of alpha for no power). Balanced grids only."""
        if not self.model.g.balanced:
            return None
        key = ("between", tuple(sorted(names)))
        if key not in self._tests:
            self._tests[key] = self._between_repetition_sums(names)
        sums = self._tests[key]
        return None if sums is None else f_test(*sums, threshold)

    def _between_repetition_sums(self, names: tuple[str, ...]) -> tuple[float, int, float, int] | None:
        g, R = self.model.g, self.model.g.R
        hits = g.hits(tuple(sorted(names)))
        varying_columns = self._varying_columns()
        if not varying_columns.any() or not any(varying_columns[c][hits[c]].any() for c in range(6)):
            return None  # no column of the terms differs between the repetitions
        ss_num = ss_den = 0.0
        dof_num = dof_den = 0
        for c in range(6):
            local = 3 + hits[c]
            if not local.size:
                continue
            # the scale factors are shared by the repetitions: a repetition's own scale
            # (what a temperature offset between repetitions makes) stays in its deviation
            dev = self._affine_channel(c).dev
            D_all, varying_all = self._between_channel(c)
            D = D_all[..., local - 3]
            varying = varying_all[local - 3]
            ss_c = float(np.sum(dev**2))
            dof_c = (R - 1) * (int(g.real.sum()) // R - 1) - int(round(float(self.model.noise.params[c])))
            if varying.any():
                Z = D[..., varying].reshape(-1, int(varying.sum()))
                _, rank, fitted = lstsq_min_norm(Z, dev.reshape(-1))
                explained = float(np.sum(fitted**2))
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
        a, b = self.model.fit(current), self.model.fit(full)
        ps, pd_ = self.model.pure(full)
        return nested_f_test(a.ss, a.rank, b.ss, b.rank, ps.sum(), int(pd_.sum()), threshold)
