"""The design of one unit's model discovery: its repetitions on a (repetition, step) grid,
with every catalogue term's columns through the unit's sensing geometry.

What depends on the protocol alone (steps, tests, references, motion) is the
:class:`Layout`, the same for every unit measured with that protocol; the :class:`UnitGrid`
adds the unit's outputs and the terms' columns.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib_core.discovery.replay import test_group, two_way_residual
from calib_core.effects import MotionContext, SensingGeometry, get_effect
from calib_core.effects.base import ACCEL, GYRO
from calib_core.steps import StepMeans


# -- one unit on a (repetition, step) grid ----------------------------------------------
# Why this layout: every quantity discovery needs (fits of any term subset on any
# leave-one-repetition-out fold, per-channel residual sums of squares, pure error, held-out
# residuals) is a quadratic form in a small coefficient vector v_c = [-K_c, -theta, 1] over
# the channel's weighted, bias-removed design A_c = w (M_c - weighted mean per repetition).
# Factorising A_c once per (channel, repetition) block (R factors, k x k with k ~ 10) turns
# all of them into products of small triangular matrices: nothing per row after the set-up.
@dataclass
class UnitGrid:
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
        layout: Layout | None = None,
        regressors: list[np.ndarray] | None = None,
        outputs: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> UnitGrid:
        """The unit's grid with the terms' columns through ``geometry`` (default: the
        nominal one); ``dropped`` term columns (undetermined parameters) are left at 0.
        ``layout``: the sessions' :func:`protocol_layout` when the caller already has it;
        ``regressors``: the terms' columns of a grid of the same sessions, terms and
        geometry (:attr:`regressors`), not computed again. Without ``names`` the grid has
        the affine model's columns alone (what the affine fit and the rank test use).
        ``outputs``: (raw, std, count) of a grid of the same sessions, shared (not built
        again)."""
        lay = layout if layout is not None else protocol_layout(sessions)
        R, n = lay.real.shape
        if outputs is not None:
            raw, std, count = outputs
        else:
            raw = np.zeros((R, n, 6, 3))
            std = np.zeros((R, n, 6, 3))
            count = np.ones((R, n))
            for r, sm in enumerate(sessions):
                m = len(sm)
                raw[r, :m, :3], raw[r, :m, 3:] = sm.gyro[:, None, :], sm.accel[:, None, :]
                std[r, :m, :3], std[r, :m, 3:] = sm.gyro_std[:, None, :], sm.accel_std[:, None, :]
                count[r, :m] = np.maximum(np.asarray(sm.count, float), 1.0)
        offset, live, live_mask, M, colmap, Zs = term_design(lay, names, geometry, dropped, regressors)
        M[..., :3] = np.moveaxis(raw, 2, 0)
        grid = cls(
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
        grid.__dict__["_regressors"] = Zs
        return grid

    @property
    def regressors(self) -> list[np.ndarray]:
        """Per repetition (n_r, 6, P): minus every term's regressors through the grid's
        geometry, before undetermined columns are dropped (read-only)."""
        return self.__dict__["_regressors"]

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

    def hits(self, names: tuple[str, ...]) -> tuple[np.ndarray, ...]:
        """Per channel, which of its term columns (positions in M's term block) belong to the
        terms ``names`` (kept per grid, read-only)."""
        cache = self.__dict__.setdefault("_hits", {})
        out = cache.get(names)
        if out is None:
            member = np.zeros(self.P + 2, bool)  # colmap's P + 1 (padding) is never a member
            member[self.cols(names)] = True
            mask = member[self.colmap]  # (6, k - 4)
            at = np.nonzero(mask)[1]  # every channel's positions, channel by channel
            at.setflags(write=False)
            ends = np.cumsum(mask.sum(axis=1)).tolist()
            out = tuple(at[a:b] for a, b in zip([0] + ends[:-1], ends))
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
            e = X - X.mean(axis=-3, keepdims=True)
            e -= (rep_mean - grand)[..., g].swapaxes(-1, -2)
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
class Layout:
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
    cache: dict = field(default_factory=dict, compare=False, repr=False)  # derived once


def protocol_layout(sessions: list[StepMeans]) -> Layout:
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


def _build_layout(sessions: list[StepMeans]) -> Layout:
    R = len(sessions)
    lens = [len(sm) for sm in sessions]
    n = max(lens)
    real = np.zeros((R, n), bool)
    step = np.full((R, n), -1, np.int64)
    y = np.zeros((R, n, 6))
    t = np.zeros((R, n))
    tests, ctxs = [], []
    last: tuple[list, tuple] | None = None  # the previous repetition's test names and codes
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
        names = _test_names(sm).tolist()
        if last is None or last[0] != names:  # repetitions of one protocol: the same names
            u = sorted(set(names))  # np.unique's order (code points), by a dict: a few distinct names
            at = {t: i for i, t in enumerate(u)}
            last = (names, (u, np.array([at[t] for t in names], np.int64)))
        tests.append(last[1])
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
    return Layout(real, step, gcode, groups, y, balanced, t, ctxs)


def _joint_context(lay: Layout) -> MotionContext | None:
    """The repetitions' motion contexts as one (their rows stacked), when they share the
    session-level values (g, latitude, table heading) and every per-row field; None
    otherwise. Kept on the layout."""
    if "joint" in lay.cache:
        return lay.cache["joint"]
    ctxs = lay.ctx
    c0 = ctxs[0]
    same = all(
        c.g_local == c0.g_local
        and c.latitude_deg == c0.latitude_deg
        and c.table_heading_deg == c0.table_heading_deg
        and (c.heading_deg is None) == (c0.heading_deg is None)
        and (c.turned_deg is None) == (c0.turned_deg is None)
        for c in ctxs
    )
    out = None
    if same and len(ctxs) > 1:

        def cat(name):
            v = getattr(c0, name)
            return None if v is None else np.concatenate([getattr(c, name) for c in ctxs])

        out = MotionContext(
            w=cat("w"),
            f=cat("f"),
            dwdt=cat("dwdt"),
            temp_c=cat("temp_c"),
            t=cat("t"),
            g_local=c0.g_local,
            heading_deg=cat("heading_deg"),
            latitude_deg=c0.latitude_deg,
            table_heading_deg=c0.table_heading_deg,
            turned_deg=cat("turned_deg"),
        )
    lay.cache["joint"] = out
    return out


def _body_regressors(terms: list, ctx: MotionContext, geometry: SensingGeometry, P: int) -> np.ndarray:
    """Minus every term's regressors (n, 6, P) through the sensing geometry
    (ref = K raw + b - E theta), laid out channel by channel in memory (a (6, n, P) array
    seen as (n, 6, P)): each channel's columns are one block. Each term's sensor errors go
    through its triads' inverse (:meth:`SensingGeometry.to_body`; by minus the inverse:
    negation is exact) one triad at a time (a term's rows are laid out sensor by sensor:
    :func:`calib_core.effects.base.sensor_zeros`); a triad the term leaves at 0 is 0."""
    Z = np.empty((6, len(ctx), P))
    minus_inv = ((GYRO, -geometry.inverse("gyro")), (ACCEL, -geometry.inverse("accel")))
    at = 0
    for t in terms:
        E = np.asarray(t.sensor_regressors(ctx, geometry), float).transpose(1, 0, 2)  # (6, n, p)
        for triad, A in minus_inv:
            block = Z[triad, :, at : at + t.n_params]
            if E[triad].any():
                block[...] = np.einsum("ij,jnp->inp", A, E[triad])
            else:
                block[...] = 0.0
        at += t.n_params
    return Z.transpose(1, 0, 2)


def term_design(
    lay: Layout,
    names: list[str],
    geometry: SensingGeometry | None,
    dropped: frozenset[int],
    regressors: list[np.ndarray] | None = None,
):
    """The terms' columns of one unit: every term's regressors through the unit's sensing
    geometry (or ``regressors``, computed before), per channel only the columns not
    identically 0 on it (``live``), laid out as M (6, R, n, k) = [raw (filled by the
    caller) | live term columns | 0 | y]; and the regressors, per repetition."""
    terms = [get_effect(nm) for nm in names]
    offset, off = {}, 0
    for nm, t in zip(names, terms):
        offset[nm] = (off, off + t.n_params)
        off += t.n_params
    P = off
    R, n = lay.real.shape
    every_row = None  # every repetition's regressors in one array, when built in one call
    if regressors is None:
        regressors = []
        joint = _joint_context(lay)
        # every repetition's rows in one call per term when the repetitions share the
        # session-level context (the terms act row by row); else one call per repetition
        g = SensingGeometry.identity() if geometry is None else geometry
        for ctx in [joint] if joint is not None else lay.ctx:
            regressors.append(_body_regressors(terms, ctx, g, P))
        if joint is not None:
            ends = np.cumsum([len(c) for c in lay.ctx])[:-1]
            every_row = regressors[0]
            regressors = np.split(every_row, ends)
        for Z in regressors:
            Z.setflags(write=False)
    Zs, live_mask = [], np.zeros((6, P), bool)
    same_length = all(len(Z) == n for Z in regressors)
    if every_row is not None and not dropped and same_length:
        # each repetition's column sums of |Z| channel by channel, in one pass over the
        # (6, R n, P) memory (a sum of magnitudes is 0 only when every entry is)
        Zs = regressors
        sums = np.abs(every_row.transpose(1, 0, 2).reshape(6, R, n, P)).sum(axis=2)
        live_mask = (sums > 0).any(axis=1)
    else:
        for Z in regressors:
            if dropped:
                Z = Z.copy()
                Z[..., sorted(dropped)] = 0.0
            Zs.append(Z)
            live_mask |= np.abs(Z).sum(axis=0) > 0
    live = [np.flatnonzero(m) for m in live_mask]
    k = 3 + max(len(L) for L in live) + 1
    M = np.zeros((6, R, n, k))
    colmap = np.full((6, k - 4), P + 1)  # global term column of each, P + 1 = none
    M[..., -1] = np.moveaxis(lay.y, 2, 0)
    if every_row is not None and not dropped and same_length:
        Zg = every_row.reshape(R, n, 6, P)  # the repetitions' rows already side by side
    elif same_length:
        Zg = np.stack(Zs)  # (R, n, 6, P) every repetition's rows on the grid
    else:  # padding rows stay 0
        Zg = np.zeros((R, n, 6, P))
        for r, Z in enumerate(Zs):
            Zg[r, : len(Z)] = Z
    for c in range(6):
        L = live[c]
        colmap[c, : len(L)] = L
        M[c, :, :, 3 : 3 + len(L)] = Zg[:, :, c, L]
    return offset, live, live_mask, M, colmap, regressors
