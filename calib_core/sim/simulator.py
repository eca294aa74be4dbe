"""Simulate a MIMU on the turntable: the truth model and the protocol, to raw samples or
directly to step means.

The truth is written in the paper's calibration form (xu2016 eq. 1-2): the *physical*
quantities follow from the raw outputs by ``w = K_g G + w0`` and ``f = K_a A + f0``. The unit
therefore outputs ``G = K_g^-1 (w_sensed - w0)`` with ``w_sensed`` the true rate plus any
physical effect (:mod:`calib_core.effects`) plus noise. Raw units are the units K is
expressed in: ``deg/s`` / ``g`` (K near identity) or ``LSB`` / ``V``.

Noise model, per channel, in physical units:
- white noise per sample (``*_noise``),
- a random offset per step (``*_bias_instability``): bias instability between steps, which is
  why step means scatter more than white noise predicts,
- a random offset per repetition (``*_bias_repeatability``): turn-on to turn-on bias,
  applied by :func:`draw_repetition_truth`.

Pure numerics: returns arrays and DataFrames; writing Parquet lives in ``schemas.writer``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from calib_core.effects import EffectTerm, MotionContext, SensingGeometry, total_error
from calib_core.steps import SessionKey, StepMeans


@dataclass(frozen=True)
class TemperatureProfile:
    """Warm-up curve T(t) = start + rise (1 - exp(-t / tau)) plus sensor noise."""

    start_c: float = 25.0
    rise_c: float = 10.0
    tau_s: float = 600.0
    noise_c: float = 0.02

    def at(self, t: np.ndarray) -> np.ndarray:
        return self.start_c + self.rise_c * (1.0 - np.exp(-np.asarray(t) / self.tau_s))


@dataclass(frozen=True)
class MimuTruth:
    """A simulated unit. Matrices map raw -> physical as in the paper (w = K_g G + w0)."""

    K_g: np.ndarray = field(default_factory=lambda: np.eye(3))
    w0: np.ndarray = field(default_factory=lambda: np.zeros(3))  # deg/s
    K_a: np.ndarray = field(default_factory=lambda: np.eye(3))
    f0: np.ndarray = field(default_factory=lambda: np.zeros(3))  # g
    # noise parameters: a scalar (all axes) or a per-axis 3-vector
    gyro_noise_dps: float = 0.05  # white, per sample
    gyro_bias_instability_dps: float = 0.003  # random per step
    gyro_bias_repeatability_dps: float = 0.0  # random per repetition
    accel_noise_g: float = 1e-3
    accel_bias_instability_g: float = 5e-5
    accel_bias_repeatability_g: float = 0.0
    gyro_unit: str = "deg/s"  # raw unit K_g is expressed in: deg/s, LSB or V
    accel_unit: str = "g"  # g, LSB or V
    # full scale of the output; a little above the rated +/-300 and +/-3600 deg/s so that the
    # paper's protocol (which goes to exactly the rated rate) does not saturate
    gyro_range_dps: tuple[float, float, float] = (350.0, 350.0, 4000.0)
    accel_range_g: tuple[float, float, float] = (50.0, 50.0, 50.0)
    gyro_quantum: float = 0.0  # raw LSB size (0: no quantisation)
    accel_quantum: float = 0.0
    effects: tuple[tuple[EffectTerm, np.ndarray], ...] = ()
    temperature: TemperatureProfile | None = None
    g_local: float = 9.80665

    def with_effects(self, *effects: tuple[EffectTerm, np.ndarray]) -> MimuTruth:
        return replace(
            self, effects=tuple(self.effects) + tuple((t, np.asarray(p, float)) for t, p in effects)
        )

    # -- forward model ---------------------------------------------------------------
    def effect_error(self, ctx: MotionContext) -> np.ndarray:
        """The effects' errors on the calibrated channels, through this unit's sensing
        geometry (the rows of K^-1), (n, 6)."""
        if not self.effects:
            return np.zeros((len(ctx), 6))
        return total_error(ctx, list(self.effects), SensingGeometry.from_gains(self.K_g, self.K_a))

    def raw_outputs(self, ctx: MotionContext) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free raw gyro and accel outputs, (n, 3) each."""
        sensed = np.hstack([ctx.w, ctx.f]) + self.effect_error(ctx)
        G = np.linalg.solve(self.K_g, (sensed[:, :3] - self.w0).T).T
        A = np.linalg.solve(self.K_a, (sensed[:, 3:] - self.f0).T).T
        return G, A

    def full_scale_raw(self) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """Declared full scale in raw units, (low, high) per sensor: the raw output at
        -range and +range on its own axis. Raw outputs need not be centred on zero (a V output
        with a 2.4 V zero bias saturates at 2.4 -/+ k range)."""

        def bounds(K, x0, rng):
            zero = np.linalg.solve(K, -x0)  # raw output at zero input
            half = np.asarray(rng, float) / np.abs(np.diag(K))
            return zero - half, zero + half

        return bounds(self.K_g, self.w0, self.gyro_range_dps), bounds(self.K_a, self.f0, self.accel_range_g)


def typical_truth(
    rng: np.random.Generator,
    misalignment: float = 0.01,
    scale: float = 0.01,
    gyro_bias_dps: float = 0.5,
    accel_bias_g: float = 5e-3,
    **kw,
) -> MimuTruth:
    """A random unit with K near identity: scale errors and cross-axis terms of the given
    size (standard deviations), biases of the given size."""

    def k(size_scale, size_mis):
        m = np.eye(3) + rng.normal(0, size_mis, (3, 3))
        m[np.diag_indices(3)] = 1.0 + rng.normal(0, size_scale, 3)
        return m

    return MimuTruth(
        K_g=k(scale, misalignment),
        w0=rng.normal(0, gyro_bias_dps, 3),
        K_a=k(scale, misalignment),
        f0=rng.normal(0, accel_bias_g, 3),
        **kw,
    )


def xu2016_truth(**kw) -> MimuTruth:
    """The unit of xu2016 with the averages of its Tables 1 and 2 as truth.

    Table 1 labels the gyro biases rad/s, but its Table 3 (uncompensated z error within
    -3.5..2.8 deg/s for x input, not the -20 deg/s a -0.35 rad/s bias would give) only fits
    deg/s; we read them as deg/s. Table 2 biases are in mg.
    """
    K_g = np.array([[0.99972, -0.01199, -0.00059], [0.02394, 1.00046, 0.01053], [0.01087, 0.01490, 1.00579]])
    w0 = np.array([-0.04317, -0.12395, -0.35153])
    K_a = np.array(
        [[0.96667, 0.01434, -0.00180], [-0.01760, 0.96965, -0.00851], [0.01476, -0.01494, 0.99326]]
    )
    f0 = np.array([-0.16417, 0.10724, 0.26508]) * 1e-3
    base = dict(
        K_g=K_g,
        w0=w0,
        K_a=K_a,
        f0=f0,
        gyro_range_dps=(350.0, 350.0, 4000.0),
        accel_range_g=(50.0, 50.0, 50.0),
    )
    base.update(kw)
    return MimuTruth(**base)


def draw_repetition_truth(truth: MimuTruth, rng: np.random.Generator) -> MimuTruth:
    """The unit as it is on one repetition: biases moved by turn-on repeatability."""
    return replace(
        truth,
        w0=truth.w0 + rng.normal(0.0, 1.0, 3) * _vec3(truth.gyro_bias_repeatability_dps),
        f0=truth.f0 + rng.normal(0.0, 1.0, 3) * _vec3(truth.accel_bias_repeatability_g),
    )


# -- helpers shared by the two simulation paths ---------------------------------------
def _refs(steps: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    w = steps[["w_ref_x", "w_ref_y", "w_ref_z"]].to_numpy(float)
    f = steps[["f_ref_x", "f_ref_y", "f_ref_z"]].to_numpy(float)
    return w, f


def _timeline(steps: pd.DataFrame, rate_hz: float, gap_s: float):
    """Start time and sample count of each step, with ``gap_s`` of transition between."""
    dur = steps["duration_s"].to_numpy(float) if "duration_s" in steps else np.full(len(steps), 3.0)
    n = np.maximum(np.round(dur * rate_hz).astype(int), 1)
    n_gap = int(round(gap_s * rate_hz))
    starts = np.concatenate([[0], np.cumsum(n + n_gap)[:-1]]) + n_gap
    return starts, n, n_gap


def _step_context(truth: MimuTruth, steps: pd.DataFrame, t_mid: np.ndarray) -> MotionContext:
    w, f = _refs(steps)
    temp = truth.temperature.at(t_mid) if truth.temperature else np.full(len(steps), np.nan)
    return MotionContext.from_refs(w, f, temp_c=temp, t=t_mid, g_local=truth.g_local)


def _vec3(x) -> np.ndarray:
    """Noise parameters are scalars or per-axis 3-vectors."""
    return np.broadcast_to(np.asarray(x, dtype=float), (3,))


def _white_sd(truth: MimuTruth) -> np.ndarray:
    return np.concatenate([_vec3(truth.gyro_noise_dps), _vec3(truth.accel_noise_g)])


def _step_offsets(truth: MimuTruth, n_steps: int, rng: np.random.Generator) -> np.ndarray:
    """Per-step bias instability in physical units, (n, 6)."""
    sd = np.concatenate([_vec3(truth.gyro_bias_instability_dps), _vec3(truth.accel_bias_instability_g)])
    return rng.normal(0.0, 1.0, (n_steps, 6)) * sd


def _to_raw(truth: MimuTruth, phys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    G = np.linalg.solve(truth.K_g, (phys[:, :3] - truth.w0).T).T
    A = np.linalg.solve(truth.K_a, (phys[:, 3:] - truth.f0).T).T
    return G, A


def simulate_session(
    truth: MimuTruth,
    steps: pd.DataFrame,
    rng: np.random.Generator,
    sample_rate_hz: float = 100.0,
    gap_s: float = 0.04,
    dtype=np.float32,
) -> pd.DataFrame:
    """Raw samples of one session (the columns of the contract's samples.parquet).

    Between steps (``step == -1``) the outputs ramp linearly from one step to the next, as
    the table accelerates. Outputs saturate at the declared full scale.
    """
    starts, n, n_gap = _timeline(steps, sample_rate_hz, gap_s)
    total = int(starts[-1] + n[-1])
    t = np.arange(total) / sample_rate_hz
    step_of = np.full(total, -1, dtype=np.int32)
    idx = np.full(total, -1)
    for k, (s, m) in enumerate(zip(starts, n)):  # per step, not per sample
        step_of[s : s + m] = steps["step"].iloc[k]
        idx[s : s + m] = k
    t_mid = (starts + n / 2.0) / sample_rate_hz
    ctx = _step_context(truth, steps, t_mid)
    phys = np.hstack([ctx.w, ctx.f]) + truth.effect_error(ctx)
    phys = phys + _step_offsets(truth, len(steps), rng)
    # transitions: interpolate the per-step physical outputs over the sample index
    in_step = idx >= 0
    centre = starts + n / 2.0
    per_sample = np.empty((total, 6))
    for ch in range(6):
        per_sample[:, ch] = np.interp(np.arange(total), centre, phys[:, ch])
    per_sample[in_step] = phys[idx[in_step]]
    per_sample += rng.normal(0.0, 1.0, (total, 6)) * _white_sd(truth)
    G, A = _to_raw(truth, per_sample)
    (g_lo, g_hi), (a_lo, a_hi) = truth.full_scale_raw()
    G = np.clip(G, g_lo, g_hi)
    A = np.clip(A, a_lo, a_hi)
    if truth.gyro_quantum:
        G = np.round(G / truth.gyro_quantum) * truth.gyro_quantum
    if truth.accel_quantum:
        A = np.round(A / truth.accel_quantum) * truth.accel_quantum
    out = pd.DataFrame(
        {
            "step": step_of,
            "t": t,
            "gx": G[:, 0].astype(dtype),
            "gy": G[:, 1].astype(dtype),
            "gz": G[:, 2].astype(dtype),
            "ax": A[:, 0].astype(dtype),
            "ay": A[:, 1].astype(dtype),
            "az": A[:, 2].astype(dtype),
        }
    )
    if truth.temperature is not None:
        temp = truth.temperature.at(t) + rng.normal(0, truth.temperature.noise_c, total)
        out["temp_c"] = temp.astype(np.float32)
    return out


def session_metadata(
    truth: MimuTruth, sample_rate_hz: float = 100.0, session_start: str = "2026-11-20T02:00:00Z", **extra: str
) -> dict[str, str]:
    """Key-value metadata of samples.parquet for a simulated session."""
    md = {
        "gyro_unit": truth.gyro_unit,
        "accel_unit": truth.accel_unit,
        "sample_rate_hz": f"{sample_rate_hz:g}",
        "gyro_range_dps": ",".join(f"{v:g}" for v in truth.gyro_range_dps),
        "accel_range_g": ",".join(f"{v:g}" for v in truth.accel_range_g),
        "g_local": f"{truth.g_local:.5f}",
        "session_start": session_start,
        "source": "mimucal simulator",
    }
    md.update(extra)
    return md


def simulate_step_means(
    truth: MimuTruth,
    steps: pd.DataFrame,
    rng: np.random.Generator,
    sample_rate_hz: float = 100.0,
    gap_s: float = 0.04,
    key: SessionKey = SessionKey("SIM", "U000", 1),
) -> StepMeans:
    """Step means drawn directly from their distribution (no samples): the fast path for
    Monte Carlo. Same truth, same noise model as :func:`simulate_session` followed by step
    averaging; steps whose noise-free output reaches full scale are left out, as the reader
    would leave them out."""
    starts, n, _ = _timeline(steps, sample_rate_hz, gap_s)
    settle = np.round(steps["settle_s"].to_numpy(float) * sample_rate_hz).astype(int)
    count = np.maximum(n - settle, 1)
    t_mid = (starts + settle + count / 2.0) / sample_rate_hz
    ctx = _step_context(truth, steps, t_mid)
    phys = np.hstack([ctx.w, ctx.f]) + truth.effect_error(ctx)
    G0, A0 = _to_raw(truth, phys)
    (g_lo, g_hi), (a_lo, a_hi) = truth.full_scale_raw()
    ok = ((G0 > g_lo) & (G0 < g_hi)).all(axis=1) & ((A0 > a_lo) & (A0 < a_hi)).all(axis=1)
    phys = phys + _step_offsets(truth, len(steps), rng)
    phys = phys + rng.normal(0.0, 1.0, phys.shape) * _white_sd(truth) / np.sqrt(count)[:, None]
    G, A = _to_raw(truth, phys)
    # within-step sample std in raw units (noise through K^-1)
    g_std = np.sqrt((np.linalg.inv(truth.K_g) ** 2) @ _vec3(truth.gyro_noise_dps) ** 2)
    a_std = np.sqrt((np.linalg.inv(truth.K_a) ** 2) @ _vec3(truth.accel_noise_g) ** 2)
    w, f = _refs(steps)
    sm = StepMeans(
        key=key,
        step=steps["step"].to_numpy(np.int64),
        test=steps["test"].to_numpy(str),
        up_axis=steps["up_axis"].to_numpy(str),
        rate_dps=steps["rate_dps"].to_numpy(float),
        angle_deg=steps["angle_deg"].to_numpy(float),
        w_ref=w,
        f_ref=f,
        gyro=G,
        accel=A,
        gyro_std=np.tile(g_std, (len(steps), 1)),
        accel_std=np.tile(a_std, (len(steps), 1)),
        count=count,
        t_mid=t_mid,
        temp_c=ctx.temp_c,
        gyro_unit=truth.gyro_unit,
        accel_unit=truth.accel_unit,
        g_local=truth.g_local,
        sample_rate_hz=sample_rate_hz,
        gyro_range_dps=tuple(truth.gyro_range_dps),
        accel_range_g=tuple(truth.accel_range_g),
    )
    return sm.select(ok)


def simulate_repetition_step_means(
    truth: MimuTruth,
    steps: pd.DataFrame,
    rng: np.random.Generator,
    sample_rate_hz: float,
    key: SessionKey,
    averager=None,
) -> StepMeans:
    """One repetition's step means: drawn directly (``averager=None``, fast path) or by
    simulating raw samples and averaging them with ``averager(key, steps, samples,
    metadata)`` (the reader's own averaging, so the whole path runs)."""
    if averager is None:
        return simulate_step_means(truth, steps, rng, sample_rate_hz, key=key)
    samples = simulate_session(truth, steps, rng, sample_rate_hz=sample_rate_hz)
    return averager(key, steps, samples, session_metadata(truth, sample_rate_hz))


# Noise of a MEMS unit as the validation lots use it: white noise per sample, bias
# instability between steps (3x the white noise of a 2.5 s step mean), turn-on repeatability.
REALISTIC_NOISE = dict(
    gyro_noise_dps=0.05,
    gyro_bias_instability_dps=0.01,
    gyro_bias_repeatability_dps=0.05,
    accel_noise_g=1e-3,
    accel_bias_instability_g=1e-4,
    accel_bias_repeatability_g=1e-3,
)


def simulate_unit(
    truth,
    steps: pd.DataFrame,
    rng: np.random.Generator,
    n_reps: int = 5,
    lot: str = "SIM",
    unit: str = "U000",
) -> tuple[list[StepMeans], list]:
    """Step means of ``n_reps`` repetitions of one unit (each with its own turn-on biases),
    and the per-repetition truths."""
    sessions, truths = [], []
    for r in range(1, n_reps + 1):
        tr = draw_repetition_truth(truth, rng)
        truths.append(tr)
        sessions.append(simulate_step_means(tr, steps, rng, key=SessionKey(lot, unit, r)))
    return sessions, truths
