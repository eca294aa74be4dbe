"""How often the nightly's noise flags name the right units (docs/noise.md, "Noise in the
fleet run"): simulated 10-unit lots with a static recording per unit, K of them with N times
the lot's angle random walk, calibrated, stored and re-flagged as the nightly does (its plain
functions, without Prefect).

    python -m tools.noise_fleet_flags --lots 20 --noisy 1 --first-seed 200
    python -m tools.noise_fleet_flags --lots 60 --noisy 0 --first-seed 100

Prints each lot's noisy and flagged units and the tally: lots whose flags are exactly the
noisy units, lots with a unit flagged that is not noisy.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path


def run_lot(root: Path, seed: int, noisy: int, factor: float, rate_hz: float, recording_s: float) -> tuple:
    from calib_core.outliers import OutlierConfig
    from flows.fleet_sim import simulate_fleet
    from flows.nightly import store_results
    from flows.unit_pipeline import calibrate_batch
    from schemas.dataset import find_sessions
    from schemas.flagging import reflag_after_update
    from schemas.results_store import ResultsStore
    from schemas.unit_plan import plan_unit_jobs

    m = simulate_fleet(
        root / "data",
        lots=1,
        units=10,
        reps=2,
        seed=seed,
        sample_rate_hz=rate_hz,
        noise_recording_s=recording_s,
        noisy_units=noisy,
        noise_factor=factor,
    )
    truth = {u["unit"] for u in m["noise"]["noisy_units"]}
    refs, _ = find_sessions(root / "data")
    jobs, _, _ = plan_unit_jobs(refs, {})
    results = calibrate_batch(jobs, run_discovery=False)
    store = ResultsStore(root / "results")
    store_results(store, results, "run", "tools")
    reflag_after_update(store, ["L01"], OutlierConfig())
    noise = store.read("noise")
    return truth, set(noise.loc[noise["flagged"].astype(bool), "unit"])


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--lots", type=int, default=20)
    p.add_argument("--noisy", type=int, default=1, help="noisy units per lot")
    p.add_argument("--factor", type=float, default=3.0, help="their angle random walk factor")
    p.add_argument("--first-seed", type=int, default=200)
    p.add_argument("--rate", type=float, default=10.0)
    p.add_argument("--recording", type=float, default=900.0, help="recording length, s")
    args = p.parse_args()
    from flows import runtime

    runtime.ensure_environment()
    exact = wrong = 0
    for seed in range(args.first_seed, args.first_seed + args.lots):
        root = Path(tempfile.mkdtemp(prefix="noise-flags-"))
        try:
            truth, flagged = run_lot(root, seed, args.noisy, args.factor, args.rate, args.recording)
        finally:
            shutil.rmtree(root, ignore_errors=True)
        exact += flagged == truth
        wrong += bool(flagged - truth)
        print(f"seed {seed}: noisy {sorted(truth)}, flagged {sorted(flagged)}", flush=True)
    print(f"{args.lots} lots: flags exactly the noisy units on {exact}, a unit not noisy flagged on {wrong}")


if __name__ == "__main__":
    main()
