"""Regenerate the measured figures of docs/model-discovery.md.

    .venv/bin/python docs/model_discovery_figures.py power     # detection vs magnitude (~5 min)
    .venv/bin/python docs/model_discovery_figures.py power 0.05,0.1   # other magnitudes
    .venv/bin/python docs/model_discovery_figures.py xu2016    # the paper's gaps (~40 s)

Seeded: the same numbers every run.
"""
from __future__ import annotations

import sys
import time

import numpy as np


def power(n_units: int = 20, scales=(0.25, 0.5, 1.0), n_clean: int = 200) -> None:
    from calib_core import protocols
    from calib_core import simulator as sim
    from calib_core.discovery import REALISTIC_NOISE, diagnose_unit, hidden_effect, simulate_unit
    from calib_core.effects import catalogue, get_effect

    steps = protocols.default_session()

    def truth0(rng):
        return sim.typical_truth(rng, **REALISTIC_NOISE, temperature=sim.TemperatureProfile())

    rng = np.random.default_rng(2026)
    t0 = time.perf_counter()
    fx = mis = 0
    for _ in range(n_clean):
        d = diagnose_unit(simulate_unit(truth0(rng), steps, rng)[0], tables=False)
        fx += bool(d.effects)
        mis += d.misfit
    per_unit = (time.perf_counter() - t0) / max(n_clean, 1)
    if n_clean:
        print(f"clean units: {n_clean}; with an effect reported: {fx} "
              f"({100 * fx / n_clean:.1f} %); misfit: {mis} ({100 * mis / n_clean:.1f} %); "
              f"{per_unit:.2f} s per unit")
    print()
    print("| effect | " + " | ".join(f"{s:g}x: right name / misfit / gain" for s in scales) + " |")
    print("|---|" + "---|" * len(scales))
    for name in sorted(catalogue()):
        cells = []
        for scale in scales:
            rng = np.random.default_rng(sum(map(ord, name)) + int(100 * scale))
            right = mis = 0
            gains = []
            for _ in range(n_units):
                theta, _ = hidden_effect(name, rng, scale)
                truth = truth0(rng).with_effects((get_effect(name), theta))
                d = diagnose_unit(simulate_unit(truth, steps, rng)[0], tables=False)
                ok = [e.name for e in d.effects] == [name]
                right += ok
                mis += d.misfit
                if ok:
                    gains.append(d.effects[0].gain)
            g = f"{np.median(gains):.3g}" if gains else "-"
            cells.append(f"{right}/{n_units} / {mis}/{n_units} / {g}")
        print(f"| {name} | " + " | ".join(cells) + " |")


def xu2016() -> None:
    from calib_core.discovery_xu2016 import gap_analysis

    r = gap_analysis()
    print("per-axis hypotheses (gyro_scale_nonlinearity fitted to the compensated range):")
    for a, hs in r["hypotheses"].items():
        for h in hs:
            print(f"  {a}: q={h['q']:.4g} c={h['c']:.4g}  compensated "
                  f"{h['compensated'][0]:.3f}~{h['compensated'][1]:.3f}  uncompensated predicted "
                  f"{h['uncompensated'][0]:.3f}~{h['uncompensated'][1]:.3f} (linear "
                  f"{h['uncompensated_linear'][0]:.3f}~{h['uncompensated_linear'][1]:.3f}, "
                  f"published {h['uncompensated_published'][0]}~{h['uncompensated_published'][1]})"
                  f"  gap closed {100 * h['gap_closed']:.0f} %")
    print("chosen theta:", {k: round(v, 4) for k, v in r["theta"].items()})
    print()
    print("| input | method | output | published | linear model | extended model | gap closed |")
    print("|---|---|---|---|---|---|---|")
    for row in r["table3"]:
        pub, lin, ext = row["published"], row["linear"], row["extended"]
        print(f"| {row['input']} | {row['method']} | {row['output']} | {pub[0]:.3f} ~ {pub[1]:.3f} | "
              f"{lin[0]:.3f} ~ {lin[1]:.3f} | {ext[0]:.3f} ~ {ext[1]:.3f} | {100 * row['closed']:.0f} % |")
    print()
    for b in r["bias"]:
        print(b)


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else "xu2016"
    if what == "power" and len(sys.argv) > 2:
        power(scales=tuple(float(x) for x in sys.argv[2].split(",")), n_clean=0)
    else:
        {"power": power, "xu2016": xu2016}[what]()
