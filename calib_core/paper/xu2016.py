"""Reproduce Xu et al. (2016): simulate its unit, run the whole method five times, and set
Tables 1, 2 and 3 beside the published numbers.

Truth: the averages of Tables 1 and 2 (gyro biases read as deg/s, see
:func:`calib_core.sim.simulator.xu2016_truth`). Noise is *derived* from the published repetition
spreads, not tuned by hand: the spread of K_ii over repetitions fixes the step-level noise of
axis i through the design of the multirate (or multiposition) test, and what the bias spread
has beyond that noise becomes turn-on repeatability. Where one noise level cannot explain two
published spreads at once, the report says so: that gap is input for model discovery.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from calib_core.models import xu2016
from calib_core.sim import protocols, simulator
from calib_core.steps import SessionKey

PUBLISHED_TABLE1 = {  # Number 1..5, Average
    "k_g11": [0.99974, 0.99973, 0.99973, 0.99970, 0.99969, 0.99972],
    "k_g12": [-0.01196, -0.01191, -0.01191, -0.01208, -0.01209, -0.01199],
    "k_g13": [-0.00059, -0.00056, -0.00063, -0.00058, -0.00058, -0.00059],
    "k_g21": [0.02402, 0.02390, 0.02394, 0.02391, 0.02393, 0.02394],
    "k_g22": [1.00045, 1.00047, 1.00044, 1.00046, 1.00050, 1.00046],
    "k_g23": [0.01051, 0.01053, 0.01052, 0.01055, 0.01055, 0.01053],
    "k_g31": [0.01089, 0.01087, 0.01075, 0.01090, 0.01093, 0.01087],
    "k_g32": [0.01486, 0.01487, 0.01487, 0.01495, 0.01496, 0.01490],
    "k_g33": [1.00546, 1.00551, 1.00590, 1.00607, 1.00600, 1.00579],
    "w0_x": [-0.03732, -0.04505, -0.04289, -0.04636, -0.04424, -0.04317],
    "w0_y": [-0.14450, -0.14354, -0.13033, -0.11033, -0.09103, -0.12395],
    "w0_z": [-0.29703, -0.41339, -0.30428, -0.36567, -0.37728, -0.35153],
}
PUBLISHED_TABLE2 = {
    "k_a11": [0.96698, 0.96695, 0.96676, 0.96642, 0.96625, 0.96667],
    "k_a12": [0.01448, 0.01419, 0.01444, 0.01441, 0.01417, 0.01434],
    "k_a13": [-0.00145, -0.00245, -0.00191, -0.00096, -0.00221, -0.00180],
    "k_a21": [-0.01760, -0.01753, -0.01748, -0.01769, -0.01769, -0.01760],
    "k_a22": [0.96947, 0.96966, 0.96998, 0.96948, 0.96964, 0.96965],
    "k_a23": [-0.00835, -0.00860, -0.00852, -0.00859, -0.00851, -0.00851],
    "k_a31": [0.01555, 0.014672, 0.01467, 0.014361, 0.01454, 0.01476],
    "k_a32": [-0.01525, -0.01447, -0.01490, -0.01503, -0.01505, -0.01494],
    "k_a33": [0.99333, 0.99286, 0.99299, 0.99357, 0.99357, 0.99326],
    "f0_x": [-0.16403, -0.16128, -0.17054, -0.16464, -0.16037, -0.16417],  # mg
    "f0_y": [0.11392, 0.10270, 0.11108, 0.10385, 0.10464, 0.10724],
    "f0_z": [0.28710, 0.256601, 0.27716, 0.25291, 0.25164, 0.26508],
}
# Table 3: output error ranges (deg/s), [input axis][method] -> (x, y, z) as (min, max)
PUBLISHED_TABLE3 = {
    "x": {
        "uncompensated": [(0.004, 0.288), (-7.305, -7.185), (-3.474, 2.825)],
        "proposed": [(-0.142, 0.144), (-0.005, 0.034), (-0.081, 0.039)],
        "traditional": [(-0.142, 0.143), (-0.0048, 0.034), (-0.081, 0.041)],
    },
    "y": {
        "uncompensated": [(-3.445, 3.738), (-0.364, 0.4684), (-4.829, 4.105)],
        "proposed": [(-0.005, 0.014), (-0.15, 0.162), (0.007, 0.069)],
        "traditional": [(-0.005, 0.015), (-0.15, 0.161), (0.007, 0.071)],
    },
    "z": {
        "uncompensated": [(-37.773, 37.959), (-1.174, 1.607), (-17.449, 16.48)],
        "proposed": [(-0.149, 0.218), (-0.214, 0.358), (-2.954, 4.838)],
        "traditional": [(-0.149, 0.218), (-0.214, 0.358), (-2.950, 4.835)],
    },
}
AXES = "xyz"


def _published_spread(table: dict, name: str) -> float:
    return float(np.std(table[name][:5], ddof=1))


def derive_noise(duration_s: float, settle_s: float, sample_rate_hz: float) -> dict[str, Any]:
    """Step noise and repeatability per axis implied by the published spreads."""
    truth = simulator.xu2016_truth()
    steps = protocols.default_session(duration_s, settle_s, dynamic=False)
    sm = simulator.simulate_step_means(
        replace(
            truth,
            gyro_noise_dps=0.0,
            gyro_bias_instability_dps=0.0,
            accel_noise_g=0.0,
            accel_bias_instability_g=0.0,
        ),
        steps,
        np.random.default_rng(0),
        sample_rate_hz,
    )
    dG, _, _ = xu2016.multirate_pairs(sm)
    # std(K_ii) = sigma_step * sqrt(2) * sqrt([(dG^T dG)^-1]_ii)
    g_unscaled = np.sqrt(np.diag(np.linalg.pinv(dG.T @ dG)) * 2.0)
    sig_g = np.array([_published_spread(PUBLISHED_TABLE1, f"k_g{i}{i}") for i in (1, 2, 3)]) / g_unscaled
    st = sm.of_test("multiposition")
    X = np.hstack([st.accel, np.ones((len(st), 1))])
    a_unscaled = np.sqrt(np.diag(np.linalg.pinv(X.T @ X)))
    sig_a = np.array([_published_spread(PUBLISHED_TABLE2, f"k_a{i}{i}") for i in (1, 2, 3)]) / a_unscaled[:3]
    n_stat = int((sm.test == "stationary").sum())
    w0_spread = np.array([_published_spread(PUBLISHED_TABLE1, f"w0_{a}") for a in AXES])
    f0_spread = np.array([_published_spread(PUBLISHED_TABLE2, f"f0_{a}") for a in AXES]) * 1e-3
    # A step noise also spreads the biases: the bias spread bounds it from above. Where the
    # K spread asks for more noise than the bias spread allows, the scale factor itself moves
    # between repetitions; we keep the smaller noise and report the excess.
    sig_g_bound = w0_spread * np.sqrt(n_stat)
    sig_a_bound = f0_spread / a_unscaled[3]
    sig_g_used = np.minimum(sig_g, sig_g_bound)
    sig_a_used = np.minimum(sig_a, sig_a_bound)
    w0_from_noise = sig_g_used / np.sqrt(n_stat)
    f0_from_noise = sig_a_used * a_unscaled[3]
    return {
        "gyro_step_sigma_dps": sig_g_used,
        "accel_step_sigma_g": sig_a_used,
        "gyro_sigma_from_K_dps": sig_g,
        "gyro_sigma_bound_from_w0_dps": sig_g_bound,
        "accel_sigma_from_K_g": sig_a,
        "accel_sigma_bound_from_f0_g": sig_a_bound,
        "gyro_repeatability_dps": np.sqrt(np.maximum(w0_spread**2 - w0_from_noise**2, 0.0)),
        "accel_repeatability_g": np.sqrt(np.maximum(f0_spread**2 - f0_from_noise**2, 0.0)),
        "w0_spread_published": w0_spread,
        "f0_spread_published_g": f0_spread,
    }


@dataclass
class ReproductionReport:
    text: str
    table1: list[dict[str, Any]] = field(default_factory=list)
    table2: list[dict[str, Any]] = field(default_factory=list)
    table3: list[dict[str, Any]] = field(default_factory=list)
    findings: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {
            "table1": self.table1,
            "table2": self.table2,
            "table3": self.table3,
            "findings": self.findings,
        }


def reproduce(
    rate_hz: float = 100.0,
    reps: int = 5,
    seed: int = 0,
    duration_s: float = 3.0,
    settle_s: float = 0.5,
    averager=None,
) -> ReproductionReport:
    """Run the method ``reps`` times on the simulated unit.

    ``averager(key, steps, samples, metadata) -> StepMeans`` turns simulated raw samples into
    step means (the CLI passes the reader's own averaging, so the whole path runs); without
    it step means are drawn directly from their distribution (fast path, same noise model).
    """
    rng = np.random.default_rng(seed)
    noise = derive_noise(duration_s, settle_s, rate_hz)
    n_per_step = (duration_s - settle_s) * rate_hz
    # split each axis' step noise evenly between white (averaged over the step) and instability
    truth = simulator.xu2016_truth(
        gyro_noise_dps=noise["gyro_step_sigma_dps"] * np.sqrt(n_per_step / 2.0),
        gyro_bias_instability_dps=noise["gyro_step_sigma_dps"] / np.sqrt(2.0),
        gyro_bias_repeatability_dps=noise["gyro_repeatability_dps"],
        accel_noise_g=noise["accel_step_sigma_g"] * np.sqrt(n_per_step / 2.0),
        accel_bias_instability_g=noise["accel_step_sigma_g"] / np.sqrt(2.0),
        accel_bias_repeatability_g=noise["accel_repeatability_g"],
    )
    steps = protocols.default_session(duration_s, settle_s, dynamic=False, verification=True)
    fits = []
    for r in range(reps):
        rep_truth = simulator.draw_repetition_truth(truth, rng)
        key = SessionKey("xu2016", "MIMU", r + 1)
        sm = simulator.simulate_repetition_step_means(rep_truth, steps, rng, rate_hz, key, averager)
        g = xu2016.fit_gyro_multirate(sm)
        fits.append((sm, g, xu2016.fit_accel_multiposition(sm), xu2016.fit_gyro_traditional(sm)))
    lines: list[str] = []
    t1 = _param_table(PUBLISHED_TABLE1, [f[1] for f in fits], "gyro", 1.0)
    t2 = _param_table(PUBLISHED_TABLE2, [f[2] for f in fits], "accel", 1e3)
    lines += _format_table("Table 1: gyro  w = K_g G + w0   (w0 in deg/s)", t1)
    lines += _format_table("Table 2: accelerometer  f = K_a A + f0   (f0 in mg)", t2)
    t3 = _table3(fits)
    lines += _format_table3(t3)
    findings = _findings(noise, t3)
    lines += ["", "Findings (what this linear simulation cannot match):"]
    lines += [f"- {f}" for f in findings]
    return ReproductionReport("\n".join(lines), t1, t2, t3, findings)


def _param_table(published: dict, fits: list, kind: str, bias_scale: float) -> list[dict]:
    rows = []
    for name, vals in published.items():
        if name.startswith("k_"):
            i, j = int(name[-2]) - 1, int(name[-1]) - 1
            ours = np.array([f.K[i, j] for f in fits])
        else:
            a = AXES.index(name[-1])
            ours = np.array([(f.w0 if kind == "gyro" else f.f0)[a] for f in fits]) * bias_scale
        rows.append(
            {
                "parameter": name,
                "published_mean": vals[5],
                "mean": float(ours.mean()),
                "difference": float(ours.mean() - vals[5]),
                "published_std": _published_spread(published, name),
                "std": float(ours.std(ddof=1)) if len(ours) > 1 else float("nan"),
                "per_rep": ours.tolist(),
            }
        )
    return rows


def _format_table(title: str, rows: list[dict]) -> list[str]:
    out = [
        "",
        title,
        f"{'parameter':<10}{'published':>12}{'mimucal':>12}{'diff':>11}"
        f"{'pub. spread':>13}{'our spread':>12}{'ratio':>8}",
    ]
    for r in rows:
        ratio = r["std"] / r["published_std"] if r["published_std"] > 0 else float("nan")
        out.append(
            f"{r['parameter']:<10}{r['published_mean']:>12.5f}{r['mean']:>12.5f}"
            f"{r['difference']:>11.5f}{r['published_std']:>13.5f}{r['std']:>12.5f}{ratio:>8.2f}"
        )
    return out


def _table3(fits) -> list[dict]:
    rows = []
    for sm, g, _, trad in fits:
        df = xu2016.compensation_errors(sm, g, trad, tests=("verification",))
        rows.append(df)
    import pandas as pd

    df = pd.concat(rows)
    agg = (
        df.groupby(["input_axis", "method", "output_axis"])
        .agg(err_min=("err_min", "min"), err_max=("err_max", "max"))
        .reset_index()
    )
    out = []
    for _, r in agg.iterrows():
        pub = PUBLISHED_TABLE3[r.input_axis][r.method][AXES.index(r.output_axis)]
        out.append(
            {
                "input_axis": r.input_axis,
                "method": r.method,
                "output_axis": r.output_axis,
                "err_min": float(r.err_min),
                "err_max": float(r.err_max),
                "published_min": pub[0],
                "published_max": pub[1],
            }
        )
    return out


def _format_table3(rows) -> list[str]:
    out = [
        "",
        "Table 3: output error of the angular rates (deg/s), min~max over the "
        "verification sweep and all repetitions",
        f"{'input':<6}{'method':<15}{'axis':<5}{'published':>20}{'mimucal':>22}",
    ]
    order = {"uncompensated": 0, "proposed": 1, "traditional": 2}
    for r in sorted(rows, key=lambda r: (r["input_axis"], order[r["method"]], r["output_axis"])):
        out.append(
            f"{r['input_axis']:<6}{r['method']:<15}{r['output_axis']:<5}"
            f"{r['published_min']:>9.3f} ~ {r['published_max']:>8.3f}"
            f"{r['err_min']:>11.3f} ~ {r['err_max']:>8.3f}"
        )
    return out


def _findings(noise: dict, t3: list[dict]) -> list[str]:
    f = []
    for sensor, unit, k_sig, bound, scale in (
        ("gyro", "deg/s", noise["gyro_sigma_from_K_dps"], noise["gyro_sigma_bound_from_w0_dps"], 1.0),
        ("accelerometer", "mg", noise["accel_sigma_from_K_g"], noise["accel_sigma_bound_from_f0_g"], 1e3),
    ):
        for a, ks, b in zip(AXES, k_sig, bound):
            if ks > 1.5 * b:
                f.append(
                    f"{sensor} {a}: the published K spread needs a step noise of "
                    f"{scale * ks:.4g} {unit}, but the published bias spread allows at most "
                    f"{scale * b:.4g} {unit}: the scale factor itself changes between "
                    f"repetitions ({ks / b:.0f}x more K spread than noise explains); a linear, "
                    "stationary model cannot express it (thermal scale-factor drift is the "
                    "likely cause)."
                )
    rep = noise["gyro_repeatability_dps"]
    f.append(
        "Gyro bias spreads of Table 1 exceed what the step noise gives by a turn-on "
        "repeatability of "
        + ", ".join(f"{a} {s:.4f}" for a, s in zip(AXES, rep))
        + " deg/s; w0_y drifts monotonically over the five repetitions (-0.1445 to -0.0910): "
        "a drift (e.g. thermal), not white noise."
    )
    z = [r for r in t3 if r["input_axis"] == "z" and r["method"] == "proposed" and r["output_axis"] == "z"]
    if z:
        z = z[0]
        f.append(
            f"Table 3, z input, proposed compensation, z output: the linear simulation leaves "
            f"{z['err_min']:.3f} ~ {z['err_max']:.3f} deg/s where the paper reports "
            f"{z['published_min']} ~ {z['published_max']}: an error growing with rate that an "
            "affine model does not leave; consistent with z gyro scale-factor nonlinearity "
            "(see docs/model-discovery.md)."
        )
    xy = [
        r for r in t3 if r["input_axis"] == "x" and r["method"] == "uncompensated" and r["output_axis"] == "y"
    ]
    if xy:
        xy = xy[0]
        f.append(
            f"Table 3, x input, uncompensated y output: the published -7.305 ~ -7.185 deg/s "
            f"is nearly constant, but k_g21 = 0.02394 makes the y output swing with the x rate "
            f"({xy['err_min']:.3f} ~ {xy['err_max']:.3f} here over +/-300 deg/s): that row "
            "cannot come from Table 1 with any linear model (another sign convention or a "
            "transcription error in the paper)."
        )
    f.append(
        "Table 1 labels the gyro biases rad/s; Table 3's uncompensated errors only fit "
        "deg/s (a -0.35 rad/s z bias would show as -20 deg/s), so they are read as deg/s."
    )
    return f
