"""Replay a calibration as a simulation of the protocol it was fitted on, and say how far the
measured step means are from what it predicts, in units of their own noise.

For every step of a session and every one of the six channels (gyro channels during
multiposition steps and accelerometer channels during rotation steps included), the
calibration predicts the raw step mean (:meth:`Calibration.predict_raw`); the residual is

    residual = K (measured_raw - predicted_raw)        [deg/s for gx gy gz, g for ax ay az]

i.e. the physical error the calibrated unit would show on that step. Its expected size is
estimated from the data, never assumed:

- ``sigma_white``: within-step sample scatter through K, ``|K_c * std| / sqrt(count)``;
- ``sigma_step``: the step-to-step scatter seen across repetitions. The same step's residual
  is compared between repetitions after removing each repetition's own offset (turn-on bias)
  and each step's common value (systematic model error, identical in every repetition):
  what remains is the noise of a step mean, bias instability between steps included. It is
  pooled per channel and test group; the part white noise does not explain is the
  instability, and ``sigma**2 = sigma_white**2 + instability**2``.

With a single repetition there is no repetition scatter: ``sigma`` falls back to
``sigma_white`` and :attr:`NoiseEstimate.from_repetitions` is False (a test on that alone
would cry wolf on any unit with bias instability; :mod:`calib_core.discovery` refuses it).
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from calib_core.calibration import Calibration
from calib_core.effects import CHANNELS
from calib_core.linalg import lstsq_min_norm
from calib_core.steps import StepMeans

CHANNEL_UNITS = ("deg/s",) * 3 + ("g",) * 3

# Steps whose noise is pooled together. Stationary steps are too few to pool on their own
# and have the same noise as slow multirate steps.
TEST_GROUP = {
    "stationary": "rate",
    "multirate": "rate",
    "multiposition": "position",
    "dynamic": "dynamic",
    "verification": "verification",
}
MIN_POOL_DOF = 8  # groups with fewer degrees of freedom borrow the channel's pooled value

REPLAY_COLUMNS = (
    "lot",
    "unit",
    "rep",
    "step",
    "test",
    "up_axis",
    "rate_dps",
    "angle_deg",
    "channel",
    "quantity_unit",
    "reference",
    "measured_raw",
    "predicted_raw",
    "residual",
    "sigma_white",
    "sigma",
)


def test_group(test: str) -> str:
    return TEST_GROUP.get(str(test), str(test))


def physical_residuals(cal: Calibration, sm: StepMeans) -> tuple[np.ndarray, np.ndarray]:
    """Residual (n, 6) in physical units and predicted raw (n, 6) of one session."""
    G_pred, A_pred = cal.predict_raw(sm.w_ref, sm.f_ref, temp_c=sm.temp_c, t=sm.t_mid)
    res_g = (sm.gyro - G_pred) @ cal.K_g.T
    res_a = (sm.accel - A_pred) @ cal.K_a.T
    return np.hstack([res_g, res_a]), np.hstack([G_pred, A_pred])


def white_sigma(cal: Calibration, sm: StepMeans) -> np.ndarray:
    """Within-step scatter of the step mean through K, (n, 6), channel noise independent."""
    n = np.maximum(np.asarray(sm.count, float), 1.0)[:, None]
    sg = np.sqrt((sm.gyro_std**2) @ (cal.K_g.T**2))
    sa = np.sqrt((sm.accel_std**2) @ (cal.K_a.T**2))
    return np.hstack([sg, sa]) / np.sqrt(n)


def replay_session(cal: Calibration, sm: StepMeans) -> pd.DataFrame:
    """Tidy residual table of one session (``sigma`` = ``sigma_white`` until
    :func:`attach_noise` adds the repetition scatter)."""
    res, pred = physical_residuals(cal, sm)
    sw = white_sigma(cal, sm)
    meas = np.hstack([sm.gyro, sm.accel])
    ref = np.hstack([sm.w_ref, sm.f_ref])
    n = len(sm)
    rows = {
        "lot": np.repeat(sm.key.lot, 6 * n),
        "unit": np.repeat(sm.key.unit, 6 * n),
        "rep": np.repeat(int(sm.key.rep), 6 * n),
        "step": np.repeat(sm.step.astype(np.int64), 6),
        "test": np.repeat(np.asarray(sm.test, str), 6),
        "up_axis": np.repeat(np.asarray(sm.up_axis, str), 6),
        "rate_dps": np.repeat(sm.rate_dps.astype(float), 6),
        "angle_deg": np.repeat(sm.angle_deg.astype(float), 6),
        "channel": np.tile(np.array(CHANNELS), n),
        "quantity_unit": np.tile(np.array(CHANNEL_UNITS), n),
        "reference": ref.ravel(),
        "measured_raw": meas.ravel(),
        "predicted_raw": pred.ravel(),
        "residual": res.ravel(),
        "sigma_white": sw.ravel(),
        "sigma": sw.ravel(),
    }
    return pd.DataFrame(rows, columns=list(REPLAY_COLUMNS))


NOISE_COLUMNS = ("channel", "group", "dof", "step_sd", "white_sd", "instability_sd")


class NoiseEstimate:
    """Noise of a step mean per channel and test group, estimated from the data.

    ``table`` columns: channel, group, dof (degrees of freedom of the repetition scatter),
    step_sd (pooled scatter of a step mean across repetitions, physical units), white_sd
    (rms within-step scatter through K), instability_sd (the excess, 0 if none).

    Built from a table or from its rows (:meth:`from_records`); the other form is made on
    first use: the nightly run only ever needs the rows (JSON), and a DataFrame round trip
    would cost more than the rows themselves.
    """

    def __init__(self, table: pd.DataFrame | None, from_repetitions: bool, records: list[dict] | None = None):
        if table is None and records is None:
            raise ValueError("NoiseEstimate needs a table or its records")
        self._table = table
        self._records = records
        self.from_repetitions = bool(from_repetitions)

    @classmethod
    def from_records(cls, records: list[dict], from_repetitions: bool) -> NoiseEstimate:
        return cls(None, from_repetitions, records)

    @property
    def table(self) -> pd.DataFrame:
        if self._table is None:
            self._table = pd.DataFrame({c: [r[c] for r in self._records] for c in NOISE_COLUMNS})
        return self._table

    def records(self) -> list[dict]:
        """One dict per row (what ``table.to_dict(orient="records")`` gives)."""
        if self._records is None:
            self._records = self.table.to_dict(orient="records")
        return [dict(r) for r in self._records]

    def step_sd_by_channel(self) -> dict[str, float]:
        """The typical noise of a step mean per channel: the median of its test groups'
        step_sd (physical units: deg/s for gyros, g for accelerometers)."""
        t = self.table
        return {str(ch): float(sub["step_sd"].median()) for ch, sub in t.groupby("channel", sort=False)}

    def __repr__(self) -> str:
        return f"NoiseEstimate(from_repetitions={self.from_repetitions}, rows={len(self.records())})"


def two_way_residual(values: np.ndarray, cell: np.ndarray, rep: np.ndarray) -> tuple[np.ndarray, int]:
    """Residual of ``value = cell effect + repetition effect + e`` and its degrees of freedom.

    Removing a value per cell (step) takes out any systematic model error, identical in
    every repetition; removing a value per repetition takes out its turn-on offset; what is
    left is the repetition-to-repetition scatter of a step mean (pure error). ``values`` is
    (n,) or (n, k): k columns are fitted at once (model discovery's design columns)."""
    X = np.asarray(values, float)
    flat = X.ndim == 1
    X = X[:, None] if flat else X
    ci, cell_idx = np.unique(cell, return_inverse=True)
    ri, rep_idx = np.unique(rep, return_inverse=True)
    n = len(X)
    if n == len(ci) * len(ri) and len(np.unique(cell_idx * len(ri) + rep_idx)) == n:
        # balanced (every step in every repetition once): double centring is the fit
        table = np.zeros((len(ci), len(ri), X.shape[1]))
        table[cell_idx, rep_idx] = X
        e = (
            table
            - table.mean(axis=1, keepdims=True)
            - table.mean(axis=0, keepdims=True)
            + table.mean(axis=(0, 1), keepdims=True)
        )
        e, dof = e[cell_idx, rep_idx], int((len(ci) - 1) * (len(ri) - 1))
    else:
        D = np.zeros((n, len(ci) + len(ri)))
        D[np.arange(n), cell_idx] = 1.0
        D[np.arange(n), len(ci) + rep_idx] = 1.0
        _, rank, fitted = lstsq_min_norm(D, X)
        e, dof = X - fitted, int(n - rank)
    return (e[:, 0] if flat else e), dof


def pool_step_noise(
    groups: list[str], dofs: list[int], ss: list[float], white_sd: list[float]
) -> list[tuple[str, int, float, float, float]]:
    """The noise of a step mean on one channel, per test group: (group, dof, step_sd,
    white_sd, instability_sd) from each group's pure-error sum of squares ``ss`` on ``dofs``
    and its within-step white sd. A group with fewer than ``MIN_POOL_DOF`` dof borrows the
    channel's pooled variance; a channel without any dof (one repetition) has the white part
    alone. The one pooling rule of the replayed tables and of discovery's noise model
    (:class:`calib_core.discovery.noise.NoiseModel`), in Python floats."""
    pooled_ss, pooled_dof = 0.0, 0
    for v, d in zip(ss, dofs):
        pooled_ss += v
        pooled_dof += int(d)
    pooled_var = pooled_ss / pooled_dof if pooled_dof else math.nan
    out = []
    for g, d, v, w in zip(groups, dofs, ss, white_sd):
        var = v / int(d) if d >= MIN_POOL_DOF else pooled_var
        step_sd = math.sqrt(var) if math.isfinite(var) else w
        out.append((g, int(d), step_sd, w, math.sqrt(max(step_sd**2 - w**2, 0.0))))
    return out


def estimate_noise(table: pd.DataFrame) -> NoiseEstimate:
    """Pool the repetition scatter of each step's residual per channel and test group.

    ``table`` is one or more replayed sessions of the same unit (:func:`replay_session`)."""
    return estimate_noise_arrays(
        table["channel"].to_numpy(str),
        table["test"].map(test_group).to_numpy(str),
        table["rep"].to_numpy(),
        table["step"].to_numpy(),
        table["residual"].to_numpy(float),
        table["sigma_white"].to_numpy(float),
    )


def estimate_noise_arrays(
    channel: np.ndarray,
    group: np.ndarray,
    rep: np.ndarray,
    step: np.ndarray,
    residual: np.ndarray,
    white: np.ndarray,
) -> NoiseEstimate:
    """:func:`estimate_noise` on aligned arrays (one entry per step, repetition, channel)."""
    multi = len(np.unique(rep)) > 1
    out = []
    for ch in CHANNELS:
        in_ch = channel == ch
        groups, dofs, sss, whites = [], [], [], []
        for g in sorted(set(group[in_ch])):
            m = in_ch & (group == g)
            if multi:
                e, dof = two_way_residual(residual[m], step[m], rep[m])
                ss = float(e @ e)
            else:
                ss, dof = 0.0, 0
            groups.append(g)
            dofs.append(dof)
            sss.append(ss)
            whites.append(float(np.sqrt(np.mean(white[m] ** 2))))
        for g, dof, step_sd, w, inst in pool_step_noise(groups, dofs, sss, whites):
            out.append(
                {
                    "channel": ch,
                    "group": g,
                    "dof": dof,
                    "step_sd": step_sd,
                    "white_sd": w,
                    "instability_sd": inst,
                }
            )
    return NoiseEstimate(pd.DataFrame(out), from_repetitions=multi)


def noise_sigma(
    noise: NoiseEstimate, channel: np.ndarray, group: np.ndarray, white: np.ndarray
) -> np.ndarray:
    """sigma = sqrt(white**2 + instability**2) per entry (instability 0 where unknown)."""
    tab = noise.table
    lut = {(c, g): v for c, g, v in zip(tab["channel"], tab["group"], tab["instability_sd"])}
    # looked up once per distinct (channel, group), not once per row
    ch_names, ch_idx = np.unique(np.asarray(channel, str), return_inverse=True)
    gr_names, gr_idx = np.unique(np.asarray(group, str), return_inverse=True)
    per_pair = np.array([[lut.get((c, g), 0.0) for g in gr_names] for c in ch_names], float)
    inst = per_pair[ch_idx.reshape(-1), gr_idx.reshape(-1)] if len(ch_names) else np.zeros(0)
    return np.sqrt(white**2 + np.nan_to_num(inst) ** 2)


def attach_noise(table: pd.DataFrame, noise: NoiseEstimate | None = None) -> pd.DataFrame:
    """Set ``sigma`` = sqrt(sigma_white**2 + instability**2) from the data's own scatter."""
    noise = noise or estimate_noise(table)
    out = table.copy()
    out["sigma"] = noise_sigma(
        noise,
        table["channel"].to_numpy(str),
        table["test"].map(test_group).to_numpy(str),
        table["sigma_white"].to_numpy(float),
    )
    return out


def replay_unit(
    cals: Calibration | list[Calibration], sessions: list[StepMeans], noise: NoiseEstimate | None = None
) -> pd.DataFrame:
    """Replay every repetition of a unit (one calibration for all, or one per repetition,
    e.g. with each repetition's own turn-on biases) and attach the data-estimated noise."""
    if isinstance(cals, Calibration):
        cals = [cals] * len(sessions)
    if len(cals) != len(sessions):
        raise ValueError(f"{len(cals)} calibrations for {len(sessions)} sessions")
    table = pd.concat([replay_session(c, sm) for c, sm in zip(cals, sessions)], ignore_index=True)
    return attach_noise(table, noise)


def summarise_residuals(table: pd.DataFrame) -> pd.DataFrame:
    """Normalised rms residual per channel and test: where the replay is wrong."""
    z = table["residual"] / table["sigma"]
    return (
        table.assign(z2=z**2)
        .groupby(["channel", "test"], sort=False)
        .agg(
            n=("z2", "size"),
            rms_z=("z2", lambda v: float(np.sqrt(v.mean()))),
            rms_residual=("residual", lambda v: float(np.sqrt((v**2).mean()))),
        )
        .reset_index()
    )


def xu2016_calibration(sm: StepMeans) -> Calibration:
    """The production baseline of one session: xu2016 multirate (K_g, w0) and multiposition
    (K_a, f0) fits, affine only."""
    from calib_core.models import xu2016

    g = xu2016.fit_gyro_multirate(sm)
    a = xu2016.fit_accel_multiposition(sm)
    return Calibration(
        K_g=g.K,
        w0=g.w0,
        K_a=a.K,
        f0=a.f0,
        gyro_unit=sm.gyro_unit,
        accel_unit=sm.accel_unit,
        g_local=sm.g_local,
    )


def replay_xu2016(sessions: list[StepMeans], noise: NoiseEstimate | None = None) -> pd.DataFrame:
    """Each repetition's own xu2016 calibration replayed over all of its steps. The +/-
    difference method is blind to even-in-rate errors and fits the accelerometers on static
    steps only: what it leaves shows here (e.g. on the accelerometers during rotation)."""
    return replay_unit([xu2016_calibration(sm) for sm in sessions], sessions, noise)
