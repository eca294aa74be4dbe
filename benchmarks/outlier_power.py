"""Detection power of the outlier flags vs lot size, with and without the fleet history
(calib_core.outliers): the table of docs/flows.md.

    python -m benchmarks.outlier_power [--trials 200] [--sizes 5 8 12 20 40] [--shifts 0 4 6 8 10]

Each trial: three earlier lots of 20 clean units (acquired before), then the lot under test
of ``n`` units; every unit has 24 parameters (the gyro and accel models), unit means
Gaussian with sd 1 around 0 (the same population in every lot); one unit of the lot under
test has one parameter shifted by ``shift`` lot sd. The fleet's summary goes through
:func:`calib_core.outliers.flag_lots` with ``history_units = 0`` ("own lot": its own median,
the scale pooled over the lots), "lot alone" (the same with no earlier lot in the store:
the lot's own median and scale), the default configuration ("history spread": lots below 20
units judged with their own median and the spread of the last 60 good units of earlier
lots) and ``history_location = "history"`` (median and spread of those units). "found":
the shifted unit flagged on that parameter (robust z); "false units": other units of the
lot under test flagged, per lot (a shift of 0 is a clean lot). Seeded: the same table every
time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pandas as pd

from calib_core.outliers import KIND_ROBUST, OutlierConfig, ThresholdTable, flag_lots

PARAMS = (
    [("gyro", f"k_g{i}{j}") for i in (1, 2, 3) for j in (1, 2, 3)]
    + [("gyro", f"w0_{a}") for a in "xyz"]
    + [("accel", f"k_a{i}{j}") for i in (1, 2, 3) for j in (1, 2, 3)]
    + [("accel", f"f0_{a}") for a in "xyz"]
)
EARLIER_LOTS = 3
EARLIER_UNITS = 20


def simulated_fleet(
    rng: np.random.Generator, n: int, shift: float
) -> tuple[pd.DataFrame, dict, tuple[str, str, str]]:
    """(summary, unit times, (unit, model, parameter) shifted) of one trial."""
    lots = [(f"E{k}", EARLIER_UNITS, k * 86400.0) for k in range(EARLIER_LOTS)]
    lots.append(("T", n, EARLIER_LOTS * 86400.0))
    rows, times = [], {}
    target = (f"T-U{int(rng.integers(n))}", *PARAMS[int(rng.integers(len(PARAMS)))])
    for lot, size, t0 in lots:
        values = rng.standard_normal((size, len(PARAMS)))
        for u in range(size):
            unit = f"{lot}-U{u}"
            times[(lot, unit)] = t0 + 60.0 * u
            for j, (model, name) in enumerate(PARAMS):
                v = values[u, j] + (shift if (unit, model, name) == target else 0.0)
                rows.append((lot, unit, model, name, v))
    df = pd.DataFrame(rows, columns=["lot", "unit", "model", "parameter", "mean"])
    df["std"] = np.nan  # no spread rule: the robust z alone
    df["n_reps"] = 5
    return df, times, target


def measure(sizes: list[int], shifts: list[float], trials: int, seed: int = 20261124) -> pd.DataFrame:
    configs = {
        "lot alone": OutlierConfig(history_units=0),
        "own lot": OutlierConfig(history_units=0),
        "history spread (default)": OutlierConfig(),
        "history median and spread": OutlierConfig(history_location="history"),
    }
    out = []
    thresholds = ThresholdTable()  # one simulation per lot layout for the whole study
    for n in sizes:
        for shift in shifts:
            rng = np.random.default_rng([seed, n, int(round(shift * 10))])
            found = {k: 0 for k in configs}
            false = {k: 0 for k in configs}
            thr = {k: [] for k in configs}
            for _ in range(trials):
                df, times, target = simulated_fleet(rng, n, shift)
                for name, cfg in configs.items():
                    # "lot alone": no earlier lot in the store (a first small lot)
                    rows = df[df["lot"] == "T"] if name == "lot alone" else df
                    lf = flag_lots(rows, cfg, ["T"], times, thresholds)[0]
                    hit = {(f.unit, f.model, f.parameter) for f in lf.flags if f.kind == KIND_ROBUST}
                    found[name] += target in hit and shift > 0
                    false[name] += len({f.unit for f in lf.flags} - {target[0]})
                    thr[name].append(lf.z_threshold_used)
            for name in configs:
                out.append(
                    {
                        "lot units": n,
                        "reference": name,
                        "shift (lot sd)": shift,
                        "found": found[name] / trials if shift > 0 else np.nan,
                        "false units per lot": false[name] / trials,
                        "threshold": float(np.nanmedian(thr[name])),
                    }
                )
    return pd.DataFrame(out)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--sizes", type=int, nargs="+", default=[5, 8, 12, 20, 40])
    ap.add_argument("--shifts", type=float, nargs="+", default=[0, 4, 6, 8, 10])
    a = ap.parse_args(argv)
    t = time.perf_counter()
    df = measure(a.sizes, a.shifts, a.trials)
    # one row per lot size and reference: threshold, false units, found per shift
    print(
        "| lot units | reference | |z| threshold | false units per clean lot | "
        + " | ".join(f"found at {s:g} sd" for s in a.shifts if s > 0)
        + " |"
    )
    print("|---|---|---|---|" + "---|" * sum(s > 0 for s in a.shifts))
    for (n, ref), g in df.groupby(["lot units", "reference"], sort=False):
        clean = g[g["shift (lot sd)"] == 0]
        cells = [f"{x:.0%}" for x in g.loc[g["shift (lot sd)"] > 0, "found"]]
        fp = f"{clean['false units per lot'].iloc[0]:.3f}" if len(clean) else "-"
        print(f"| {n} | {ref} | {g['threshold'].median():.2f} | {fp} | " + " | ".join(cells) + " |")
    print(f"({a.trials} trials per cell, {time.perf_counter() - t:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
