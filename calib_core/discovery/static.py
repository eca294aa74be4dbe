"""Model discovery on recordings without turntable references (static poses moved by hand).

The turntable discovery (:mod:`calib_core.discovery.turntable`) compares every step with a known
reference. A hand-made session (Ferraris, IMU-TK field calibration) has no reference except
what physics fixes at rest, so the *measured* quantities are the static poses' mean raw
outputs (:func:`calib_core.models.field.static_detection.static_pose_means`,
``FieldCalibrationResult.pose_means``, :func:`calib_core.models.ferraris.section_pose_means`) and
the baseline model is the calibration the recording's own method produced. At a static pose:

* **gyro** reference: rate 0. The Earth rate (0.0042 deg/s at most, direction unknown here)
  is ignored: it is a quarter of the smallest residual reported on the real recordings and,
  being constant in the earth frame, it would show as an orientation-dependent rate (a
  g-sensitivity-like pattern of at most 0.004 deg/s), not as a time drift.
  Testable residual: the calibrated rate ``w_k`` (deg/s), three channels per pose.
* **accelerometer** reference: the calibrated specific force has magnitude 1 g. Its
  direction ``u_k`` comes from the calibrated accelerometer itself, so only the magnitude is
  a reference: the testable residual is ``|f_k| - 1`` (g), one row per pose.

Each pose becomes a :class:`calib_core.effects.MotionContext` (``w = 0``, ``f = u_k`` with
|f| = 1 g, ``temp_c`` NaN, ``t`` = the pose's mid time), and every catalogue term's own
``regressors(ctx)`` give its design columns: on gyro rows the term's gyro channels; on the
magnitude row the projection ``u_k . E_accel`` (a small error ``e`` on f changes |f| by
``u . e``).

Base model (refitted jointly with the terms, by least squares on the poses): the parameters
of the calibration that static poses determine,

* gyro: a free bias per axis (static poses cannot see the gyro scale), plus the gyro parts
  of the terms the baseline calibration already carries (e.g. Ferraris's g-sensitivity);
* accelerometer: the linearised affine freedom seen by the magnitude, ``u_i u_j`` (symmetric
  scale/misalignment, 6) and ``u_i`` (bias, 3), plus the baseline terms' accel parts.

Every term is fitted and tested per sensor *block* (gyro rows, magnitude rows): the two have
different units and noise, so one F test across both would weigh them arbitrarily. A term
whose block columns vanish on static poses (``w = 0``: lever arm, rate nonlinearity and
asymmetry) or lie in the span of the base model (e.g. the accelerometer nonlinearity on
six axis-aligned poses, where ``u_i^3 = u_i``) is *not testable on this recording*, never
"absent".

The tests, the selection rule and the finding type are the turntable discovery's: the
nested F test (:func:`calib_core.discovery.significance.nested_f_test`), the parameters'
significance (:func:`calib_core.discovery.significance.significant_parameters`), the
selection (:func:`calib_core.discovery.policy.select_terms`) on a
:class:`calib_core.discovery.fit.HeldOutScore`, and
:class:`calib_core.discovery.results.EffectFinding`; terms act through the sensing
geometry of the calibration's own gains.

Test: nested-model F test within the block, ``F = (dRSS / p) / (RSS_1 / (N - r_1))``, rows
weighted by ``1 / sqrt(white^2 + tau_c^2)``: the white noise of a pose mean (within-pose
sample std through K over sqrt(count)) plus the pose-to-pose noise ``tau_c`` of each channel
(bias instability, placement) estimated from the residual of the baseline, then once more
from the chosen model. Threshold alpha / (number of testable term-block candidates)
(Bonferroni). Forward selection per block, as in the turntable discovery; a term is kept
only if it also lowers the held-out RMS. Terms the baseline already carries are checked the
other way round (``baseline_checks``: F test and held-out gain of keeping them).

Held-out score: poses are not independent in time (bias instability, drift), so whole
blocks of ``block_size`` consecutive poses are left out in turn; the model is fitted on the
rest and predicts the held-out poses' residuals (physical units: deg/s, mg). ``gain`` =
held-out RMS without the term / with it, on the channels the term acts on.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd
from scipy import stats

from calib_core.calibration import Calibration
from calib_core.discovery.fit import HeldOutScore
from calib_core.discovery.policy import select_terms
from calib_core.discovery.results import DEFAULT_ALPHA, EffectFinding, FTest, jsonable
from calib_core.discovery.significance import nested_f_test, significant_parameters
from calib_core.effects import CHANNELS, MotionContext, SensingGeometry, catalogue, get_effect
from calib_core.errors import DesignError
from calib_core.linalg import lstsq_pinv

EARTH_RATE_DPS = 360.0 / 86164.1  # 0.00418 deg/s, ignored (see the module docstring)
BASE_RCOND = 3e-2  # base columns are O(1) unit-vector products: directions below this are noise
GAIN_RTOL = 1e-3  # a term column must keep this fraction of its norm off the base span
BLOCKS = ("gyro", "accel")
BLOCK_UNITS = {"gyro": "deg/s", "accel": "mg"}
BLOCK_SCALE = {"gyro": 1.0, "accel": 1e3}  # physical residual -> reported unit


@dataclass(frozen=True)
class StaticPoses:
    """Mean raw outputs of the static poses of one recording (time order)."""

    names: tuple[str, ...]
    t_mid: np.ndarray  # (n,) s
    G: np.ndarray  # (n, 3) raw gyro means
    A: np.ndarray  # (n, 3) raw accel means
    G_std: np.ndarray  # (n, 3) within-pose sample std (raw)
    A_std: np.ndarray
    count: np.ndarray  # (n,) samples per pose

    @classmethod
    def from_pose_means(cls, df: pd.DataFrame) -> StaticPoses:
        need = ["t_mid", "count"] + [c for ch in CHANNELS for c in (ch, f"{ch}_std")]
        missing = [c for c in need if c not in df.columns]
        if missing:
            raise ValueError(f"pose table lacks columns {missing}")
        df = df.sort_values("t_mid", kind="stable")
        col = lambda names: df[list(names)].to_numpy(float)  # noqa: E731
        names = df["pose"].astype(str) if "pose" in df.columns else pd.Series(range(len(df))).astype(str)
        return cls(
            tuple(names),
            df["t_mid"].to_numpy(float),
            col(CHANNELS[:3]),
            col(CHANNELS[3:]),
            col([f"{c}_std" for c in CHANNELS[:3]]),
            col([f"{c}_std" for c in CHANNELS[3:]]),
            df["count"].to_numpy(float),
        )

    def __len__(self) -> int:
        return len(self.t_mid)

    def take(self, order: np.ndarray) -> StaticPoses:
        """The same poses with rows reordered (for permutation controls)."""
        return StaticPoses(
            tuple(np.asarray(self.names)[order]),
            self.t_mid[order],
            self.G[order],
            self.A[order],
            self.G_std[order],
            self.A_std[order],
            self.count[order],
        )


@dataclass
class _Block:
    """Rows of one sensor block: y (physical residual), weight, pose index, channel."""

    name: str
    y: np.ndarray
    weight: np.ndarray
    pose: np.ndarray
    channel: np.ndarray  # 0..5
    base: np.ndarray  # (N, q) base design


@dataclass
class StaticDiagnosis:
    recording: str
    n_poses: int
    alpha: float
    block_size: int
    misfit: bool
    unexplained: bool
    effects: list[EffectFinding]
    candidates: list[EffectFinding]  # every testable term-block, tested alone on the baseline
    not_testable: list[dict[str, str]]
    blocks: dict[str, dict[str, Any]]  # per block: rms before/after, white noise, chi2 tests
    baseline_terms: tuple[str, ...]
    # each term the baseline calibration carries, tested as if it were a candidate: does the
    # recording support it? (F test and held-out gain of keeping it vs dropping it)
    baseline_checks: list[EffectFinding] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return jsonable(
            {
                "recording": self.recording,
                "n_poses": self.n_poses,
                "alpha": self.alpha,
                "block_size": self.block_size,
                "misfit": self.misfit,
                "unexplained": self.unexplained,
                "effects": [e.to_dict() for e in self.effects],
                "candidates": [e.to_dict() for e in self.candidates],
                "not_testable": self.not_testable,
                "blocks": self.blocks,
                "baseline_terms": list(self.baseline_terms),
                "baseline_checks": [e.to_dict() for e in self.baseline_checks],
                "earth_rate_ignored_dps": EARTH_RATE_DPS,
            }
        )


# -- measured quantities and contexts ----------------------------------------------------
def pose_residuals(cal: Calibration, poses: StaticPoses) -> tuple[np.ndarray, np.ndarray, MotionContext]:
    """Calibrated rate at each pose (deg/s; reference 0), |f| - 1 (g) and the poses'
    MotionContext (w = 0, f = calibrated direction with |f| = 1 g, t = mid time)."""
    w, f = cal.apply(poses.G, poses.A, t=poses.t_mid)
    mag = np.linalg.norm(f, axis=1)
    if not np.all(mag > 0.5) or not np.all(mag < 1.5):
        raise DesignError(
            "E_STATIC_POSES",
            f"calibrated |f| at the poses spans {mag.min():.3g}.."
            f"{mag.max():.3g} g: not static poses under this calibration",
        )
    u = f / mag[:, None]
    ctx = MotionContext.from_refs(np.zeros_like(u), u, t=poses.t_mid, g_local=cal.g_local)
    return w, mag - 1.0, ctx


def _white_sigma(cal: Calibration, poses: StaticPoses, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.maximum(poses.count, 1.0)[:, None]
    sg = np.sqrt((poses.G_std**2) @ (cal.K_g.T**2)) / np.sqrt(n)
    sa = np.sqrt((poses.A_std**2) @ (cal.K_a.T**2)) / np.sqrt(n)
    s_mag = np.sqrt(np.sum((u * sa) ** 2, axis=1))  # |f| = u . f to first order
    return sg, s_mag


def _term_columns(
    name: str, ctx: MotionContext, u: np.ndarray, geometry: SensingGeometry
) -> dict[str, np.ndarray]:
    """Design columns of a catalogue term per block: gyro (3n, p) rows pose-major, channel
    minor; accel (n, p) magnitude rows. Sign: the residual is +E theta (sensed = true + E)."""
    E = get_effect(name).regressors(ctx, geometry)  # (n, 6, p)
    n, _, p = E.shape
    return {"gyro": E[:, :3, :].reshape(3 * n, p), "accel": np.einsum("ni,nip->np", u, E[:, 3:, :])}


class _StaticDiscovery:
    def __init__(
        self,
        cal: Calibration,
        poses: StaticPoses,
        alpha: float,
        block_size: int,
        candidates: list[str] | None,
        noise_terms: dict[str, tuple[str, ...]] | None = None,
    ):
        if len(poses) < 5:
            raise DesignError("E_STATIC_POSES", f"{len(poses)} static poses: need at least 5")
        self.cal, self.poses, self.alpha = cal, poses, alpha
        w, dmag, ctx = pose_residuals(cal, poses)
        self.ctx, self.u = ctx, ctx.f
        n = len(poses)
        sg, s_mag = _white_sigma(cal, poses, self.u)
        self.baseline_terms = tuple(tv.name for tv in cal.terms)
        base_extra = {b: [] for b in BLOCKS}
        for name in self.baseline_terms:
            cols = _term_columns(name, ctx, self.u, cal.geometry)
            for b in BLOCKS:
                live = np.abs(cols[b]).sum(axis=0) > 0
                if live.any():
                    base_extra[b].append(cols[b][:, live])
        gyro_base = np.kron(np.ones((n, 1)), np.eye(3))  # one bias per axis
        uu = np.column_stack([self.u[:, i] * self.u[:, j] for i in range(3) for j in range(i, 3)])
        accel_base = np.hstack([uu, self.u])
        self.blocks = {
            "gyro": _Block(
                "gyro",
                w.reshape(-1),
                1.0 / np.maximum(sg.reshape(-1), 1e-300),
                np.repeat(np.arange(n), 3),
                np.tile(np.arange(3), n),
                np.hstack([gyro_base] + base_extra["gyro"]),
            ),
            "accel": _Block(
                "accel",
                dmag,
                1.0 / np.maximum(s_mag, 1e-300),
                np.arange(n),
                np.full(n, -1),
                np.hstack([accel_base] + base_extra["accel"]),
            ),
        }
        # held-out folds: blocks of consecutive poses (time order)
        order = np.argsort(poses.t_mid, kind="stable")
        self.fold_of = np.empty(n, int)
        self.fold_of[order] = np.arange(n) // max(int(block_size), 1)
        # effects of the sensors only: a recording without references has no heading or
        # location, so the Earth rate's direction in each pose is unknown (it is part of the
        # gyro bias the base model fits per pose block)
        self.names = (
            sorted(n for n, cls in catalogue().items() if cls.sensor_effect)
            if candidates is None
            else list(candidates)
        )
        self.cols = {nm: _term_columns(nm, ctx, self.u, cal.geometry) for nm in self.names}
        self.sigma_white = {"gyro": sg, "accel": s_mag}
        self._cache: dict = {}
        self.tau = {
            b: self._set_noise(b, tuple(noise_terms.get(b, ())) if noise_terms else ()) for b in BLOCKS
        }

    def _set_noise(self, block: str, names: tuple[str, ...]) -> np.ndarray:
        """Row weights 1/sqrt(white^2 + tau_c^2): tau_c, the pose-to-pose noise of channel c
        that the within-pose white noise misses (bias instability, placement), from the
        residual of an unweighted fit of ``names``. With the baseline (no term) the misfit
        counts as noise: conservative, and the white-only weights would let a pose with many
        samples (e.g. the initial rest) dominate the time-dependent terms."""
        blk = self.blocks[block]
        white = self.sigma_white[block].reshape(-1)
        blk.weight = np.ones(len(blk.y))
        self._cache.clear()
        coef, _, _, rank, X, _ = self.fit(block, names)
        res = blk.y - X @ coef
        dof_frac = max(len(blk.y) - rank, 1) / len(blk.y)
        tau = {}
        for c in np.unique(blk.channel):
            m = blk.channel == c
            tau[c] = float(np.sqrt(max(np.mean(res[m] ** 2) / dof_frac - np.mean(white[m] ** 2), 0.0)))
        sigma = np.sqrt(white**2 + np.array([tau[c] for c in blk.channel]) ** 2)
        blk.weight = 1.0 / np.maximum(sigma, 1e-300)
        self._cache.clear()
        return np.array([tau[c] for c in sorted(tau)])

    # the design of a model: base + chosen term columns (live parameters only)
    def live_params(self, name: str, block: str) -> np.ndarray:
        return np.flatnonzero(np.abs(self.cols[name][block]).sum(axis=0) > 0)

    def design(self, block: str, names: tuple[str, ...]) -> np.ndarray:
        blk = self.blocks[block]
        parts = [blk.base] + [self.cols[n][block][:, self.live_params(n, block)] for n in names]
        return np.hstack(parts)

    def base_basis(self, block: str, rows: np.ndarray | None = None) -> np.ndarray:
        """Orthonormal basis of the base design's determined directions (weighted rows)."""
        blk = self.blocks[block]
        rows = np.arange(len(blk.y)) if rows is None else rows
        X = blk.base[rows] * blk.weight[rows, None]
        Xs = blk.base[rows]  # unweighted, for the rank tolerance on O(1) columns
        _, s, Vt = np.linalg.svd(Xs, full_matrices=False)
        keep = s > BASE_RCOND * s[0]
        Xr = X @ Vt[keep].T
        Q, _ = np.linalg.qr(Xr)
        return Q

    def rank_gained(self, block: str, name: str) -> int:
        blk = self.blocks[block]
        live = self.live_params(name, block)
        if live.size == 0:
            return 0
        Q = self.base_basis(block)
        Z = self.cols[name][block][:, live] * blk.weight[:, None]
        Zp = Z - Q @ (Q.T @ Z)
        scale = np.linalg.norm(Z, axis=0)
        s = np.linalg.svd(Zp / np.where(scale > 0, scale, 1.0), compute_uv=False)
        return int(np.sum(s > GAIN_RTOL))

    def fit(self, block: str, names: tuple[str, ...], rows: np.ndarray | None = None):
        """Weighted least squares of base + terms on ``rows``: (coef, cov-unscaled, rss, rank,
        design). Base directions below the tolerance are dropped (reduced base)."""
        key = (block, tuple(sorted(names)), None if rows is None else rows.tobytes())
        if key in self._cache:
            return self._cache[key]
        blk = self.blocks[block]
        rows = np.arange(len(blk.y)) if rows is None else rows
        _, s, Vt = np.linalg.svd(blk.base[rows], full_matrices=False)
        V = Vt[s > BASE_RCOND * s[0]].T  # base reduced to determined directions
        Zs = [self.cols[n][block][:, self.live_params(n, block)] for n in sorted(names)]
        X = np.hstack([blk.base @ V] + Zs)
        Xw = X[rows] * blk.weight[rows, None]
        yw = blk.y[rows] * blk.weight[rows]
        coef, rank, sol = lstsq_pinv(Xw, yw, rcond=1e-8, live_rtol=0.0)
        r = yw - Xw @ coef
        out = (coef, sol.cov_pinv, float(r @ r), rank, X, V.shape[1])
        self._cache[key] = out
        return out

    def f_test(self, block: str, current: tuple[str, ...], name: str, threshold: float) -> FTest:
        blk = self.blocks[block]
        _, _, rss0, r0, _, _ = self.fit(block, current)
        _, _, rss1, r1, _, _ = self.fit(block, current + (name,))
        return nested_f_test(rss0, r0, rss1, r1, rss1, len(blk.y) - r1, threshold)

    def channels_of(self, block: str, names: tuple[str, ...]) -> np.ndarray:
        """Rows the terms act on (gyro: their channels; accel: all magnitude rows)."""
        blk = self.blocks[block]
        if block == "accel" or not names:
            return np.ones(len(blk.y), bool)
        touched = np.zeros(len(blk.y), bool)
        for n in names:
            touched |= np.abs(self.cols[n][block][:, self.live_params(n, block)]).sum(axis=1) > 0
        chans = np.unique(blk.channel[touched])
        return np.isin(blk.channel, chans)

    def heldout(self, block: str, names: tuple[str, ...]) -> np.ndarray:
        """Held-out physical residual per row (each fold of consecutive poses left out)."""
        key = ("heldout", block, tuple(sorted(names)))
        if key in self._cache:
            return self._cache[key]
        blk = self.blocks[block]
        out = np.full(len(blk.y), np.nan)
        fold = self.fold_of[blk.pose]
        for k in np.unique(fold):
            train = np.flatnonzero(fold != k)
            test = np.flatnonzero(fold == k)
            coef, _, _, _, X, _ = self.fit(block, names, train)
            out[test] = blk.y[test] - X[test] @ coef
        self._cache[key] = out
        return out

    def heldout_rms(self, block: str, names: tuple[str, ...], mask: np.ndarray) -> float:
        z = self.heldout(block, names)[mask]
        return float(BLOCK_SCALE[block] * np.sqrt(np.nanmean(z**2)))

    def heldout_score(self, block: str, without: tuple[str, ...], with_: tuple[str, ...], mask: np.ndarray):
        """Held-out rms (the block's unit) without and with the terms ``with_`` adds, on the
        rows ``mask``: every row counts (the poses excite a term alike)."""
        n = int(mask.sum())
        return HeldOutScore(
            self.heldout_rms(block, without, mask), self.heldout_rms(block, with_, mask), n, n
        )

    def finding(self, block: str, chosen: tuple[str, ...], name: str, threshold: float) -> EffectFinding:
        others = tuple(n for n in chosen if n != name)
        full = others + (name,)
        coef, cov, rss, rank, _, q = self.fit(block, full)
        s2 = rss / max(len(self.blocks[block].y) - rank, 1)
        off = q + sum(self.live_params(n, block).size for n in sorted(full) if n < name)
        live = self.live_params(name, block)
        term = get_effect(name)
        theta = coef[off : off + live.size]
        se = np.sqrt(np.maximum(np.diag(cov)[off : off + live.size], 0.0) * s2)
        mask = self.channels_of(block, (name,))
        sig = significant_parameters(theta, se, self.alpha)
        axes = {CHANNELS[int(term.param_sensor()[j])][1] for j in live[sig]}
        if not axes:
            axes = {CHANNELS[c][1] for c in np.unique(self.blocks[block].channel[mask]) if c >= 0}
        return EffectFinding(
            name=name,
            block=block,
            axes=tuple(sorted(axes)),
            estimate={term.param_names[j]: float(v) for j, v in zip(live, theta)},
            stderr={term.param_names[j]: float(v) for j, v in zip(live, se)},
            units={term.param_names[j]: term.param_units[j] for j in live},
            evidence=self.f_test(block, others, name, threshold),
            heldout_rms_before=(score := self.heldout_score(block, others, full, mask)).before,
            heldout_rms_after=score.after,
            heldout_unit=BLOCK_UNITS[block],
        )


def _select(d: _StaticDiscovery, testable: list[tuple[str, str]], threshold: float) -> dict[str, list[str]]:
    """Forward selection per block by the turntable's rule
    (:func:`calib_core.discovery.policy.select_terms`, the threshold fixed at
    ``threshold``): the most significant term that also lowers the held-out RMS on its
    channels, until none is left."""
    chosen: dict[str, list[str]] = {}
    n_tests = max(len(testable), 1)
    for b in BLOCKS:

        def heldout(current: tuple[str, ...], n: str, b: str = b) -> HeldOutScore:
            return d.heldout_score(b, current, current + (n,), d.channels_of(b, (n,)))

        def test(current: tuple[str, ...], n: str, _thr: float, b: str = b) -> FTest:
            return d.f_test(b, current, n, threshold)

        chosen[b] = select_terms(
            [n for bb, n in testable if bb == b],
            test,
            heldout,
            threshold * n_tests,
            backward=False,
            bonferroni_over=n_tests,
        )
    return chosen


def _lag1(res: np.ndarray, blk: _Block, t_mid: np.ndarray) -> float:
    """Lag-1 autocorrelation of the residual between consecutive poses (per channel, pooled):
    near 0 for independent pose errors, near 1 for a slow drift no term captured."""
    num = den = 0.0
    for c in np.unique(blk.channel):
        r = res[blk.channel == c][np.argsort(t_mid[blk.pose[blk.channel == c]], kind="stable")]
        r = r - r.mean()
        num += float(r[1:] @ r[:-1])
        den += float(r @ r)
    return num / den if den > 0 else float("nan")


def diagnose_static(
    cal: Calibration,
    pose_means: pd.DataFrame | StaticPoses,
    recording: str,
    alpha: float = DEFAULT_ALPHA,
    block_size: int = 4,
    candidates: list[str] | None = None,
) -> StaticDiagnosis:
    """Model discovery on the static poses of a recording without references.

    ``cal`` is the calibration the recording's method produced (its terms are part of the
    baseline and refitted with it); ``pose_means`` one row per static pose (see
    :func:`calib_core.models.field.static_detection.static_pose_means`); ``alpha`` the family-wise
    false-alarm rate of the recording; ``block_size`` consecutive poses left out together
    in the held-out score; ``candidates`` defaults to the whole catalogue."""
    poses = pose_means if isinstance(pose_means, StaticPoses) else StaticPoses.from_pose_means(pose_means)
    d = _StaticDiscovery(cal, poses, alpha, block_size, candidates)
    not_testable, testable = [], []
    for name in d.names:
        if name in d.baseline_terms:
            not_testable.append(
                {
                    "name": name,
                    "reason": "already in the baseline calibration "
                    "(its parameters are refitted as part of the base model)",
                }
            )
            continue
        live = {b: d.live_params(name, b).size for b in BLOCKS}
        if not any(live.values()):
            not_testable.append(
                {
                    "name": name,
                    "reason": "zero regressors on static poses (w = 0, "
                    "dw/dt = 0): the recording cannot show it",
                }
            )
            continue
        gained = {b: d.rank_gained(b, name) for b in BLOCKS if live[b]}
        for b in BLOCKS:
            if live[b] and gained[b] == 0:
                not_testable.append(
                    {
                        "name": name,
                        "block": b,
                        "reason": "its columns lie in the "
                        "span of the calibration's own parameters on these poses",
                    }
                )
            elif live[b]:
                testable.append((b, name))
    threshold = alpha / max(len(testable), 1)
    chosen = _select(d, testable, threshold)
    if any(chosen.values()):
        # the baseline's misfit was counted as noise (conservative); with the chosen model
        # the pose-to-pose noise is smaller: weigh again with it and select once more
        d = _StaticDiscovery(
            cal, poses, alpha, block_size, candidates, noise_terms={b: tuple(v) for b, v in chosen.items()}
        )
        chosen = _select(d, testable, threshold)
    candidates_f = [d.finding(b, (), n, threshold) for b, n in testable]
    effects = [d.finding(b, tuple(chosen[b]), n, threshold) for b in BLOCKS for n in chosen[b]]
    blocks = {}
    unexplained = False
    for b in BLOCKS:
        blk = d.blocks[b]
        white = d.sigma_white[b].reshape(-1)
        n_rows = len(blk.y)
        sc = BLOCK_SCALE[b]
        out = {
            "unit": BLOCK_UNITS[b],
            "rows": n_rows,
            "chosen": list(chosen[b]),
            "baseline_rms": float(sc * np.sqrt(np.mean(blk.y**2))),
            "white_noise_rms": float(sc * np.sqrt(np.mean(white**2))),
            "pose_noise_tau": [float(sc * v) for v in d.tau[b]],
        }
        for tag, names in (("before", ()), ("after", tuple(chosen[b]))):
            coef, _, _, rank, X, _ = d.fit(b, names)
            res = blk.y - X @ coef
            dof = n_rows - rank
            chi2 = float(np.sum((res / white) ** 2))
            out[f"dof_{tag}"] = dof
            out[f"refit_rms_{tag}"] = float(sc * np.sqrt(np.mean(res**2)))
            out[f"heldout_rms_{tag}"] = d.heldout_rms(b, names, np.ones(n_rows, bool))
            # residual vs the white noise of a pose mean alone (no pose-to-pose noise)
            out[f"rms_over_white_{tag}"] = float(np.sqrt(chi2 / dof)) if dof > 0 else float("nan")
            out[f"chi2_white_p_{tag}"] = float(stats.chi2.sf(chi2, dof)) if dof > 0 else float("nan")
            out[f"lag1_autocorr_{tag}"] = _lag1(res, blk, poses.t_mid)
        if out["dof_after"] > 0 and out["chi2_white_p_after"] < alpha / len(BLOCKS):
            unexplained = True
        blocks[b] = out
    checks = []
    for name in d.baseline_terms:
        without = replace(cal, terms=tuple(tv for tv in cal.terms if tv.name != name))
        d0 = _StaticDiscovery(without, poses, alpha, block_size, [name])
        for b in BLOCKS:
            if d0.live_params(name, b).size and d0.rank_gained(b, name):
                checks.append(d0.finding(b, (), name, alpha))
    return StaticDiagnosis(
        recording=recording,
        n_poses=len(poses),
        alpha=alpha,
        block_size=block_size,
        misfit=bool(effects) or unexplained,
        unexplained=unexplained,
        effects=effects,
        candidates=candidates_f,
        not_testable=not_testable,
        blocks=blocks,
        baseline_terms=d.baseline_terms,
        baseline_checks=checks,
    )
