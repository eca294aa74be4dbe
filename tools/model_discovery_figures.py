"""Regenerate the measured figures of docs/model-discovery.md.

    .venv/bin/python -m tools.model_discovery_figures physics \
        [N_UNITS [N_CLEAN [SECTIONS [EFFECTS [SCALES [REPS [N_REPS]]]]]]]
        # the physics-simulator figures (40 units per cell, 200 clean units: ~20 min);
        # SECTIONS: comma-separated subset of effects,pairs,clean,ooc,limits ("effects" also
        # counts, on cold starts, its units above and below the protocol's detection limit;
        # "limits": the detection limits' prediction of each effects cell, no simulation;
        # not in the default); EFFECTS (5th
        # argument): comma-separated catalogue effects, the rows of the effects table ("all":
        # every one); SCALES (6th): comma-separated sizes of its columns, e.g. 0.25,1;
        # REPS (7th): "cold" (default: each repetition a cold start, one a day) or
        # "back-to-back" (the repetitions run on one warm-up); N_REPS (8th): repetitions
        # per unit (default 5, the production protocol)
    .venv/bin/python -m tools.model_discovery_figures xu2016    # the paper's gaps (~40 s)

Seeded: the same numbers every run.
"""

from __future__ import annotations

import sys

import numpy as np


def physics(
    n_units: int = 40,
    n_clean: int = 200,
    sections: str = "effects,pairs,clean,ooc",
    scales=(0.25, 0.5, 1.0),
    effects: tuple[str, ...] = (),
    back_to_back: bool = False,
    n_reps: int = 5,
) -> None:
    """The Done-when figures of the discovery on the independent physics simulator
    (``effects``: the rows of those catalogue effects only; empty: every one)."""
    from calib_core.discovery.detection import detection_limits
    from calib_core.effects import catalogue
    from calib_core.sim import protocols
    from schemas.physics_sessions import physics_unit_step_means
    from tools.discovery_evaluation import OUT_OF_CATALOGUE, PAIRS, run_scenario

    steps = protocols.default_session()

    def step_means_of(unit, steps, rng, unit_id, table=None):
        kw = {} if table is None else {"table": table}
        return physics_unit_step_means(
            unit, steps, rng, n_reps=n_reps, unit_id=unit_id, back_to_back=back_to_back, **kw
        )

    def seed(*parts) -> int:
        return sum(ord(ch) for p in parts for ch in str(p)) * 7919 % 2**31

    misses = []
    if "limits" in sections:
        limits_table(steps, scales, effects, n_reps)
    if "effects" in sections:
        # each unit's hidden effect against the protocol's detection limit (no random draw:
        # the units and the figures are the same with or without it); the limits model a
        # cold start a day, so repetitions back to back on one warm-up are not counted
        limits = None if back_to_back else detection_limits(steps, n_reps=n_reps)
        print(
            "| effect | "
            + " | ".join(f"{s:g}x: exactly right / extra term / median gain" for s in scales)
            + " |"
        )
        print("|---|" + "---|" * len(scales))
        within = []
        for name in sorted(catalogue()):
            if effects and name not in effects:
                continue
            cells, wcells = [], []
            for scale in scales:
                t = run_scenario(
                    step_means_of, steps, n_units, seed(name, scale), (name,), scale, limits=limits
                )
                g = f"{np.median(t.gains):.3g}" if t.gains else "-"
                # a hidden effect reported in a confounded group (combined fit applied, no
                # name picked) is neither right nor an extra term: shown beside
                conf = f" (confounded {t.pct(t.confounded_hidden):.0f} %)" if t.confounded_hidden else ""
                cells.append(f"{t.pct(t.exact):.0f} % / {t.pct(t.extra):.0f} % / {g}{conf}")
                wcells.append(
                    f"{t.within_exact}/{t.within}"
                    + (f" (confounded {t.within_confounded})" if t.within_confounded else "")
                    + f" / {t.n - t.within} / {t.below_extra}"
                    if limits is None or name in limits.terms
                    else "not excited"
                )
                misses += [f"{name} {scale:g}x {m}" for m in t.misses]
            print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
            within.append(f"| {name} | " + " | ".join(wcells) + " |")
        print()
        if limits is not None:
            print(
                "above the protocol's detection limit (detected with 95 % power, expected gain "
                ">= min_gain): exactly right / units above (reported confounded instead); units "
                "below; below and another effect named"
            )
            print("| effect | " + " | ".join(f"{s:g}x" for s in scales) + " |")
            print("|---|" + "---|" * len(scales))
            print("\n".join(within))
            print()
    if "pairs" in sections:
        print("| effects hidden (1x) | both named, nothing else | extra term |")
        print("|---|---|---|")
        for pair in PAIRS:
            t = run_scenario(step_means_of, steps, n_units, seed(*pair), pair)
            print(f"| {' + '.join(pair)} | {t.pct(t.exact):.0f} % | {t.pct(t.extra):.0f} % |", flush=True)
            misses += [f"{'+'.join(pair)} {m}" for m in t.misses]
        print()
    if "clean" in sections:
        t = run_scenario(step_means_of, steps, n_clean, seed("clean"))
        print(
            f"clean units: {t.n}; with a named effect: {t.any_named} "
            f"({t.pct(t.any_named):.1f} %); with a confounded group: {t.confounded}; "
            f"misfit: {t.misfit} ({t.pct(t.misfit):.1f} %); "
            f"discovery {1e3 * t.seconds / t.n:.0f} ms per unit",
            flush=True,
        )
        misses += [f"clean {m}" for m in t.misses]
        print()
    if "ooc" in sections:
        print(
            "| physical error not in the catalogue (1x) | named as a catalogue effect | "
            "misfit | misfit and unexplained |"
        )
        print("|---|---|---|---|")
        for name in OUT_OF_CATALOGUE:
            t = run_scenario(step_means_of, steps, n_units, seed(name), out_of_catalogue=name)
            print(
                f"| {name} | {t.pct(t.any_named):.0f} % | {t.pct(t.misfit):.0f} % | "
                f"{t.pct(t.unexplained):.0f} % |",
                flush=True,
            )
            misses += [f"{name} {m}" for m in t.misses]
    if misses:
        print("\nmisses:")
        for m in misses:
            print("  " + m)


def limits_table(steps, scales, effects, n_reps: int, draws: int = 4000) -> None:
    """Each effects cell as :mod:`calib_core.discovery.detection` predicts it: over ``draws``
    realistic draws of the hidden effect, the mean probability that its term's test detects
    it / that it is detected and its expected held-out gain reaches min_gain."""
    from calib_core.discovery.detection import detection_limits

    coverage = detection_limits(steps, n_reps=n_reps).coverage(scales, draws)
    print(f"predicted ({n_reps} repetitions): detected / detected and worth naming")
    print("| effect | " + " | ".join(f"{s:g}x" for s in scales) + " |")
    print("|---|" + "---|" * len(scales))
    for name, cells in coverage.items():
        if effects and name not in effects:
            continue
        print(f"| {name} | " + " | ".join(f"{100 * d:.0f} % / {100 * n:.0f} %" for d, n in cells) + " |")
    print()


def xu2016() -> None:
    from tools.xu2016_gap import gap_analysis

    r = gap_analysis()
    print("per-axis hypotheses (gyro_scale_nonlinearity fitted to the compensated range):")
    for a, hs in r["hypotheses"].items():
        for h in hs:
            print(
                f"  {a}: q={h['q']:.4g} c={h['c']:.4g}  compensated "
                f"{h['compensated'][0]:.3f}~{h['compensated'][1]:.3f}  uncompensated predicted "
                f"{h['uncompensated'][0]:.3f}~{h['uncompensated'][1]:.3f} (linear "
                f"{h['uncompensated_linear'][0]:.3f}~{h['uncompensated_linear'][1]:.3f}, "
                f"published {h['uncompensated_published'][0]}~{h['uncompensated_published'][1]})"
                f"  gap closed {100 * h['gap_closed']:.0f} %"
            )
    print("chosen theta:", {k: round(v, 4) for k, v in r["theta"].items()})
    print()
    print("| input | method | output | published | linear model | extended model | gap closed |")
    print("|---|---|---|---|---|---|---|")
    for row in r["table3"]:
        pub, lin, ext = row["published"], row["linear"], row["extended"]
        print(
            f"| {row['input']} | {row['method']} | {row['output']} | {pub[0]:.3f} ~ {pub[1]:.3f} | "
            f"{lin[0]:.3f} ~ {lin[1]:.3f} | {ext[0]:.3f} ~ {ext[1]:.3f} | {100 * row['closed']:.0f} % |"
        )
    print()
    for b in r["bias"]:
        print(b)


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else "xu2016"
    if what == "physics":
        args = sys.argv[2:]
        physics(
            n_units=int(args[0]) if args else 40,
            n_clean=int(args[1]) if len(args) > 1 else 200,
            sections=args[2] if len(args) > 2 else "effects,pairs,clean,ooc",
            effects=tuple(args[3].split(",")) if len(args) > 3 and args[3] != "all" else (),
            scales=(
                tuple(float(x) for x in args[4].split(","))
                if len(args) > 4 and args[4] != "all"
                else (0.25, 0.5, 1.0)
            ),
            back_to_back={"cold": False, "back-to-back": True}[args[5] if len(args) > 5 else "cold"],
            n_reps=int(args[6]) if len(args) > 6 else 5,
        )
    else:
        {"xu2016": xu2016}[what]()
