"""Regenerate the confounding, Earth-rate and thermal figures of docs/model-discovery.md.

    .venv/bin/python -m tools.identifiability_figures [N_UNITS [EFFECTS]]    # 40 units per row
        # EFFECTS: "earth" (the Earth-rate rows only) or comma-separated thermal rows only,
        # e.g. thermal_bias_drift,bias_time_drift; "pairs": the nonlinearity + thermal pair

Seeded: the same numbers every run.
"""

from __future__ import annotations

import sys
import time


def main(n_units: int = 40, sections: str = "") -> None:
    """``sections``: "earth" for the Earth-rate rows only, or comma-separated effect names
    for those thermal rows only (with "pairs": the nonlinearity + thermal pair rows);
    empty: everything."""
    from calib_core.sim import protocols
    from calib_core.sim.physics import Turntable, WarmUp
    from schemas.physics_sessions import physics_unit_step_means
    from tools.discovery_evaluation_ident import (
        earth_rate_scenario,
        pair_scenario,
        sensor_effect_scenario,
    )

    def repetitions(**how):
        """Step means of 5 repetitions run ``how`` (physics_unit_step_means' options)."""

        def step_means_of(unit, steps, rng, unit_id, table):
            return physics_unit_step_means(
                unit, steps, rng, n_reps=5, unit_id=unit_id, table=table or Turntable(), **how
            )

        return step_means_of

    step_means_of = repetitions()  # a cold start a day
    day_to_day = repetitions(ambient_sd_c=2.0)  # ... in a lab 2 degC (sd) different each day
    back_to_back = repetitions(back_to_back=True)  # the five on one warm-up

    default = protocols.default_session()
    whole = protocols.whole_turn_session()
    two = protocols.extended(whole, protocols.two_heading_stationary())
    earth = (
        []
        if sections and sections != "earth"
        else [
            ("whole turns about the vertical only", whole, False, True, 11),
            ("whole turns + stationary steps at two headings", two, False, True, 12),
            ("default protocol, latitude/heading not given", default, False, True, 13),
            ("default protocol, latitude_deg/table_heading_deg given", default, True, True, 14),
            ("default protocol, typical MEMS gyro (36 deg/h instability)", default, False, False, 15),
        ]
    )
    print(
        "| Earth rate, 45 deg latitude | units | named alone | confounded with "
        "gyro_g_sensitivity (applied) | confounded, set aside as negligible | other effect "
        "named | estimate within 2 SE of 10.64 deg/h |"
    )
    print("|---|---|---|---|---|---|---|")
    for label, steps, declare, quiet, seed in earth:
        t0 = time.perf_counter()
        o = earth_rate_scenario(step_means_of, steps, n_units, seed, declare=declare, quiet=quiet)
        within = f"{o.within_2se}/{o.named} ({100 * o.within_2se / o.named:.0f} %)" if o.named else "-"
        print(
            f"| {label} | {o.n} | {o.pct(o.named_alone):.0f} % | {o.pct(o.confounded):.0f} % | "
            f"{o.pct(o.confounded_set_aside):.0f} % | {o.pct(o.other_named):.0f} % | {within} |"
            f"  <!-- {time.perf_counter() - t0:.0f} s -->",
            flush=True,
        )
        for note in o.notes[:5]:
            print(f"<!--   {note} -->")
    print()
    print(
        "| hidden effect (default protocol) | units | named alone | confounded with its "
        "near-collinear partner (applied) | named | right parameter largest | other effect "
        "named alone |"
    )
    print("|---|---|---|---|---|---|---|")
    fast = WarmUp(rise_c=10.0, tau_s=150.0)
    cold, b2b = step_means_of, back_to_back
    for name, seed, warm, reps, label in (
        ("thermal_scale_drift", 21, WarmUp(), cold, ", 10 degC warm-up (600 s)"),
        ("thermal_bias_drift", 22, WarmUp(), cold, ", 10 degC warm-up (600 s)"),
        ("bias_time_drift", 23, WarmUp(), cold, ", 10 degC warm-up (600 s)"),
        ("thermal_bias_drift", 24, fast, cold, ", warm-up time constant 150 s"),
        ("bias_time_drift", 25, fast, cold, ", warm-up time constant 150 s"),
        ("thermal_scale_drift", 29, WarmUp(), day_to_day, ", cold starts, ambient 2 degC sd between days"),
        ("thermal_scale_drift", 26, WarmUp(), b2b, ", repetitions back to back on one warm-up"),
        ("thermal_bias_drift", 27, WarmUp(), b2b, ", repetitions back to back on one warm-up"),
        ("bias_time_drift", 28, WarmUp(), b2b, ", repetitions back to back on one warm-up"),
    ):
        if sections and name not in sections.split(","):
            continue
        t0 = time.perf_counter()
        o = sensor_effect_scenario(reps, default, name, n_units, seed, warm_up=warm)
        print(
            f"| {name}{label} | {o.n} | {o.pct(o.named_alone):.0f} % | {o.pct(o.confounded):.0f} % | "
            f"{o.pct(o.named):.0f} % | {o.right_axis}/{o.named} | {o.pct(o.other_named):.0f} % |"
            f"  <!-- {time.perf_counter() - t0:.0f} s -->",
            flush=True,
        )
        if name == "thermal_scale_drift":  # gyros and accelerometers apart (their limits differ)
            for kind, prefix in (("gyros", "sensor g"), ("accelerometers", "sensor a")):
                k = [v for p, v in o.by_place.items() if p.startswith(prefix)]
                print(f"<!--   {kind}: right axis {sum(v[1] for v in k)}/{sum(v[0] for v in k)} -->")
        for note in o.notes[:8]:
            print(f"<!--   {note} -->")
    if sections and "pairs" not in sections.split(","):
        return
    print()
    print(
        "| effects hidden (1x, default protocol) | units | both named, nothing else | found "
        "(named, or in a confounded group), nothing else named | of which confounded | "
        "other effect named |"
    )
    print("|---|---|---|---|---|---|")
    pair = ("gyro_scale_nonlinearity", "thermal_bias_drift")
    for warm, reps, label, seed in (
        (WarmUp(), step_means_of, "10 degC warm-up (600 s)", 31),
        (fast, step_means_of, "warm-up 150 s", 32),
        (WarmUp(), back_to_back, "repetitions back to back", 33),
    ):
        t0 = time.perf_counter()
        o = pair_scenario(reps, default, pair, n_units, seed, warm_up=warm)
        print(
            f"| {' + '.join(pair)}, {label} | {o.n} | {o.pct(o.named):.0f} % | {o.pct(o.found):.0f} % | "
            f"{o.pct(o.confounded):.0f} % | {o.pct(o.other_named):.0f} % |"
            f"  <!-- {time.perf_counter() - t0:.0f} s -->",
            flush=True,
        )
        for note in o.notes[:8]:
            print(f"<!--   {note} -->")


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 40, sys.argv[2] if len(sys.argv) > 2 else "")
