"""Model discovery on measured noise: the misfit rate of clean units whose noise is a measured
model's, with that model in discovery's null and with discovery's own estimate.

    PYTHONPATH=. .venv/bin/python -m tools.discovery_measured_noise [N_UNITS [NOISE_JSON [JOBS [NULL]]]]

N_UNITS clean units (default 2,000) of the physics simulator (:mod:`calib_core.sim.physics`,
``typical_physics_unit``: its own noise processes off, turn-on biases kept), the default
protocol, 5 repetitions (each a cold start), 50 Hz. Each repetition's noise is drawn from a
measured model by :func:`calib_core.noise.synthesize` over the whole session (one record per
repetition, in each sensor's own frame and scale): a quarter of the units the real
MPU-6050's model as measured (NOISE_JSON: its ``mimucal noise --json``, made from
``../shared/data/real/mpu6050_tedaldi/example_data_tinit_calc.csv`` as docs/noise.md does
when not given or not there), the
others a fitted variant of it: each channel's white and bias-instability coefficients and
each line's amplitude scaled by its own log-uniform factor in [1/3, 3], each line kept or
dropped with probability 1/2. Discovery runs twice per unit, at alpha 1 %: with the unit's
model as its null (:class:`calib_core.discovery.measured_noise.MeasuredNoise`) and with the
noise it estimates from the repetitions. Prints the table of docs/model-discovery.md
("Discovery on measured noise"); JOBS worker processes (default 1). NULL "mismatched": the
measured model in discovery's null is the MPU-6050's as measured on every unit, whatever
the variant its noise was drawn from (what a wrong measured model costs). Seeded.
"""

from __future__ import annotations

import json
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

RECORDING = Path("../shared/data/real/mpu6050_tedaldi/example_data_tinit_calc.csv")
SEED = 3131
RATE_HZ = 50.0
N_REPS = 5
ALPHA = 0.01
MPU_SHARE = 0.25  # units with the real model as measured; the rest fitted variants


def mpu6050_model(path: Path | None = None) -> dict:
    """The real MPU-6050's ``mimucal noise --json`` document: read from ``path`` when it
    exists, else made from the recording as docs/noise.md does (and written to ``path``)."""
    if path is not None and path.exists():
        return json.loads(path.read_text())
    import tempfile

    from flows.cli import main

    with tempfile.TemporaryDirectory() as tmp:
        out = path or Path(tmp) / "noise.json"
        args = ["noise", str(RECORDING), "--gyro-unit", "counts", "--accel-unit", "counts"]
        args += ["--gyro-range", "250dps", "--accel-range", "2g", "--json", str(out)]
        try:
            main(args)
        except SystemExit as exc:
            if exc.code:
                raise
        return json.loads(out.read_text())


def variant(model, rng: np.random.Generator):
    """A fitted variant of ``model`` (module docstring)."""
    from calib_core.noise import NoiseModel

    def factor() -> float:
        return float(math.exp(rng.uniform(math.log(1 / 3), math.log(3))))

    channels = {}
    for name, ch in model.channels.items():
        coef = {k: v * factor() for k, v in ch.coefficients.items() if k in ("white", "bias_instability")}
        coef.update({k: v for k, v in ch.coefficients.items() if k not in coef and k != "ramp"})
        lines = tuple((f, a * factor()) for f, a in ch.periodic if rng.uniform() < 0.5)
        channels[name] = replace(ch, coefficients=coef, periodic=lines)
    return NoiseModel(model.rate_hz, model.duration_s, channels)


def quiet_unit(rng: np.random.Generator):
    """A clean physics unit whose own noise processes are off (the measured model's noise is
    added to its outputs); turn-on biases kept."""
    from calib_core.sim.physics import typical_physics_unit

    unit = typical_physics_unit(rng)
    for i in range(3):
        unit = unit.replace_gyro(i, white_density=0.0, instability=0.0, random_walk=0.0)
        unit = unit.replace_accel(i, white_density=0.0, instability=0.0, random_walk=0.0)
    return unit


def step_means_with_noise(unit, model, steps, rng: np.random.Generator, unit_id: str) -> list:
    """The unit's repetitions (cold starts, one a day) with the measured model's noise
    added to each sensor's output before averaging."""
    from calib_core.noise import synthesize
    from calib_core.sim.physics import simulate_physics_session
    from calib_core.steps import SessionKey
    from schemas.averaging import step_means_from_tables

    out = []
    sensors = dict(zip(("gx", "gy", "gz", "ax", "ay", "az"), unit.gyros + unit.accels))
    for rep in range(1, N_REPS + 1):
        samples, md = simulate_physics_session(
            unit, steps, rng, rate_hz=RATE_HZ, session_start=f"2026-11-{rep:02d}T02:00:00Z"
        )
        noise = synthesize(model, len(samples), RATE_HZ, rng)
        for name, s in sensors.items():
            samples[name] = (samples[name].to_numpy(float) + s.scale * noise[name]).astype(np.float32)
        sm, _ = step_means_from_tables(SessionKey("MEAS", unit_id, rep), steps, samples, md)
        out.append(sm)
    return out


def _fires(d) -> dict[str, bool]:
    return {
        "overall": bool(d.lack_of_fit_before.rejects),
        "channel": any(t.rejects for t in d.channel_misfit_before.values()),
        "targeted": bool(d.misfit_terms),
        "between": bool(d.misfit_between),
    }


def run_units(first: int, count: int, doc: dict, mismatched: bool = False) -> list[dict]:
    """Units first..first + count - 1 (each seeded by its index): per unit and null, the
    misfit flag, the effects named and which tests fire."""
    from calib_core.discovery import diagnose_unit
    from calib_core.discovery.measured_noise import MeasuredNoise
    from calib_core.noise import NoiseModel
    from calib_core.sim import protocols

    steps = protocols.default_session()
    base = NoiseModel.from_dict(doc)
    out = []
    for u in range(first, first + count):
        rng = np.random.default_rng([SEED, u])
        mpu = rng.uniform() < MPU_SHARE
        model = base if mpu else variant(base, rng)
        unit = quiet_unit(rng)
        sessions = step_means_with_noise(unit, model, steps, rng, f"U{u:04d}")
        row = {"unit": u, "model": "mpu6050" if mpu else "variant"}
        in_null = base if mismatched else model
        for null, measured in (
            ("measured", MeasuredNoise(in_null, "recording mpu6050")),
            ("estimated", None),
        ):
            t0 = time.process_time()
            d = diagnose_unit(sessions, alpha=ALPHA, tables=False, measured_noise=measured)
            row[null] = {
                "misfit": bool(d.misfit),
                "named": sorted(e.name for e in d.effects),
                "fires": _fires(d),
                "noise_source": d.noise_source,
                "p_overall": float(d.lack_of_fit_before.p_value),
                "p_channel_min": float(min(t.p_value for t in d.channel_misfit_before.values())),
                "cpu_s": time.process_time() - t0,
            }
        out.append(row)
    return out


def table(rows: list[dict]) -> str:
    n = len(rows)
    lines = [
        f"{n} clean units ({sum(r['model'] == 'mpu6050' for r in rows)} with the MPU-6050's model as "
        f"measured, the others fitted variants), alpha {ALPHA:g}",
        "",
        "| noise in the null | misfit | with a named effect | overall | per channel | targeted | "
        "between | overall p < 10 % | channels' min p < 10 % | discovery CPU per unit |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for null in ("measured", "estimated"):
        res = [r[null] for r in rows]
        k = sum(x["misfit"] for x in res)
        named = sum(bool(x["named"]) for x in res)
        fires = {t: sum(x["fires"][t] for x in res) for t in ("overall", "channel", "targeted", "between")}
        cpu = np.mean([x["cpu_s"] for x in res])
        label = "measured model" if null == "measured" else "estimated from the repetitions"
        lines.append(
            f"| {label} | {k} ({100 * k / n:.2f} %) | {named} ({100 * named / n:.2f} %) | "
            + " | ".join(str(fires[t]) for t in ("overall", "channel", "targeted", "between"))
            + f" | {100 * np.mean([x['p_overall'] < 0.1 for x in res]):.1f} %"
            + f" | {100 * np.mean([x['p_channel_min'] < 0.1 for x in res]):.1f} %"
            + f" | {1e3 * cpu:.0f} ms |"
        )
    return "\n".join(lines)


def main(argv: list[str]) -> None:
    n = int(argv[0]) if argv else 2000
    doc = mpu6050_model(Path(argv[1]) if len(argv) > 1 else None)
    jobs = int(argv[2]) if len(argv) > 2 else 1
    mismatched = len(argv) > 3 and argv[3] == "mismatched"
    t0 = time.perf_counter()
    chunk = 50
    parts = [(i, min(chunk, n - i)) for i in range(0, n, chunk)]
    rows: list[dict] = []
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as ex:
            for part in ex.map(run_units, *zip(*parts), [doc] * len(parts), [mismatched] * len(parts)):
                rows += part
    else:
        for first, count in parts:
            rows += run_units(first, count, doc, mismatched)
    print(table(rows))
    print(
        "\n(overall p < 10 %: the share of units whose overall lack-of-fit p-value is below 0.1, "
        "10 % when the null is right; channels' min p: the smallest of six, 1 - 0.9^6 = 46.9 % "
        "for six independent channels)"
    )
    misfits = [r for r in rows if r["measured"]["misfit"]]
    if misfits:
        print("\nmisfit with the measured model in the null:")
        for r in misfits:
            fired = [t for t, v in r["measured"]["fires"].items() if v]
            named = r["measured"]["named"]
            print(f"  unit {r['unit']} ({r['model']}): {', '.join(fired) or '-'}; named {named}")
    print(f"\n{time.perf_counter() - t0:.0f} s wall")


if __name__ == "__main__":
    main(sys.argv[1:])
