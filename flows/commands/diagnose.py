"""`mimucal diagnose DATASET --unit UNIT [--json FILE]`: model discovery for one unit.

Replays the unit's joint affine fit over every step of every repetition, tests whether its
residuals exceed the noise estimated from the repetitions, names the catalogue effects that
explain the misfit (held-out gain, false-alarm rate ``--alpha`` per unit) and says whether
anything is left unexplained. See docs/model-discovery.md.
"""

from __future__ import annotations

import sys
from pathlib import Path

from flows.cli import CliError
from schemas.display import value_unit


def register(sub) -> None:
    p = sub.add_parser(
        "diagnose",
        help="model discovery: where the calibration model is wrong and why",
        description="Replay the fitted calibration of one unit as a simulation of its "
        "protocol, test its residuals against the noise estimated from the "
        "repetitions, and name the catalogue effects that explain the misfit.",
    )
    p.add_argument("dataset", type=Path, help="dataset root (lot=*/unit=*/rep=*/)")
    p.add_argument("--unit", required=True, help="unit id")
    p.add_argument(
        "--json", type=Path, default=None, metavar="FILE", help="also write the diagnosis as JSON here"
    )
    p.add_argument(
        "--residuals",
        type=Path,
        default=None,
        metavar="FILE.parquet",
        help="also write the replay residuals before/after (one table, column 'model') as Parquet",
    )
    p.add_argument(
        "--min-gain",
        type=float,
        default=1.05,
        help="held-out gain a term must reach on the channels it fixes to be named (default 1.05)",
    )
    p.add_argument("--alpha", type=float, default=0.01, help="false-alarm rate per unit (default 0.01)")
    p.set_defaults(func=run)


def _fmt_p(p: float) -> str:
    return "p<1e-300" if p <= 0 else f"p={p:.2g}"


def summary_lines(diag) -> list[str]:
    """A readable account of a :class:`calib_core.discovery.Diagnosis`."""
    from calib_core.discovery.presentation import channels_text

    lines = [
        f"unit {diag.unit} (lot {diag.lot}): {diag.n_reps} repetitions, false-alarm "
        f"rate {diag.alpha:g} per unit"
    ]
    step_sd = diag.noise.step_sd_by_channel()
    parts = []
    for ch in ("gx", "gy", "gz", "ax", "ay", "az"):
        if ch in step_sd:
            shown = value_unit("deg/s" if ch[0] == "g" else "g")
            parts.append(f"{ch} {step_sd[ch] * shown.factor:.3g} {shown.label}")
    source = getattr(diag, "noise_source", "estimated from the repetitions")
    where = "repetition scatter" if source.startswith("estimated") else source
    lines.append(f"noise of a step mean ({where}): " + ", ".join(parts))
    lb = diag.lack_of_fit_before
    bad = [c for c, t in diag.channel_misfit_before.items() if t.rejects]
    if not diag.misfit:
        verdict = " -> fits to noise"
    elif bad:
        verdict = f" -> MISFIT on {', '.join(bad)}"
    elif lb.rejects:
        verdict = " -> MISFIT (overall lack of fit; no single channel rejects)"
    else:
        between = list(getattr(diag, "misfit_between", []))
        targeted = [t for t in getattr(diag, "misfit_terms", []) if t not in between]
        tests = ([f"targeted test of {', '.join(targeted)}"] if targeted else []) + (
            [f"between-repetition test of {', '.join(between)}"] if between else []
        )
        verdict = f" -> MISFIT ({'; '.join(tests) or 'targeted test of a term'}; no lack-of-fit test rejects)"
    lines.append(
        f"affine model: lack of fit F={lb.statistic:.3g} ({lb.dof1}, {lb.dof2}), "
        f"{_fmt_p(lb.p_value)}" + verdict
    )
    if diag.effects or getattr(diag, "confounded", []):
        lines.append("effects found:")
    tags = {
        "partial": " (partial: leaves its channels misfit; not applied)",
        "negligible": f" (negligible: significant, but the unit fits without it or its "
        f"held-out gain is below {diag.min_gain:g}; not applied)",
    }
    listed = (
        [(e, "") for e in diag.effects]
        + [(e, tags["partial"]) for e in diag.partial]
        + [(e, tags["negligible"]) for e in diag.negligible]
    )
    for e, tag in listed:
        lines.append(f"  {e.name} on {','.join(e.axes) or '-'}{tag}")
        for n, v in e.estimate.items():
            se = e.stderr[n]
            if v is not None and se and se == se and abs(v) > 3 * se:
                lines.append(f"      {n} = {v:.4g} +/- {se:.2g} {e.units[n]}")
        for n, why in e.undetermined.items():
            lines.append(f"      {n}: undetermined ({why})")
        ev = e.evidence
        on = f" on {channels_text(e)}" if e.channels else ""
        lines.append(
            f"      evidence F={ev.statistic:.3g} ({ev.dof1}, {ev.dof2}), "
            f"{_fmt_p(ev.p_value)} (threshold {ev.threshold:.2g}); held-out rms{on} "
            f"{e.heldout_rms_before:.3g} -> {e.heldout_rms_after:.3g} sigma "
            f"(gain {e.gain:.3g})"
        )
    for c in getattr(diag, "confounded", []):
        ev = c.evidence
        on = f" on {channels_text(c)}" if c.channels else ""
        lines.append(f"  confounded: [{', '.join(c.terms)}] (combined fit applied; none named)")
        lines.append(
            f"      evidence F={ev.statistic:.3g} ({ev.dof1}, {ev.dof2}), "
            f"{_fmt_p(ev.p_value)}; held-out rms{on} {c.heldout_rms_before:.3g} -> "
            f"{c.heldout_rms_after:.3g} sigma (gain {c.gain:.3g})"
        )
        lines.append(f"      {c.advice()}")
    for g in getattr(diag, "confounded_set_aside", []):
        lines.append(f"  confounded, set aside (partial or negligible): [{', '.join(g)}]")
    advice = getattr(diag, "advice", [])
    if advice:
        lines.append("protocol advisor:")
        lines += [f"  {a}" for a in advice]
    la = diag.lack_of_fit_after
    if diag.effects:
        lines.append(
            f"extended model: lack of fit F={la.statistic:.3g} ({la.dof1}, {la.dof2}), {_fmt_p(la.p_value)}"
        )
    if diag.unexplained:
        still = [c for c, t in diag.channel_misfit_after.items() if t.rejects]
        lines.append(
            "UNEXPLAINED misfit left"
            + (f" on {', '.join(still)}" if still else "")
            + ": no catalogue effect accounts for it"
        )
    elif diag.misfit:
        lines.append("misfit explained by the effects above")
    return lines


def run(args) -> int:
    import pandas as pd

    from calib_core.discovery import diagnose_unit
    from calib_core.discovery.replay import replay_xu2016, summarise_residuals
    from calib_core.errors import DesignError
    from schemas.averaging import read_step_means
    from schemas.calibration_file import write_json_atomic
    from schemas.dataset import find_sessions
    from schemas.errors import SessionError

    if not args.dataset.is_dir():
        raise CliError(f"dataset {args.dataset} is not a directory")
    if not 0 < args.alpha < 1:
        raise CliError(f"--alpha must be between 0 and 1, got {args.alpha}")
    if not args.min_gain >= 1:
        raise CliError(f"--min-gain must be at least 1, got {args.min_gain}")
    refs, errors = find_sessions(args.dataset, unit=args.unit)
    for e in errors:
        print(f"skipped: {e}", file=sys.stderr)
    if not refs:
        from flows.user_errors import units_under

        raise CliError(
            f"no session of unit {args.unit!r} under {args.dataset} (units: {units_under(args.dataset)})"
        )
    sessions = []
    for ref in refs:
        try:
            sm, warnings = read_step_means(ref)
        except SessionError as exc:
            print(f"skipped: {exc}", file=sys.stderr)
            continue
        for w in warnings:
            print(f"warning: {ref.key}: {getattr(w, 'message', w)}", file=sys.stderr)
        sessions.append(sm)
    if len(sessions) < 2:
        raise CliError(
            f"unit {args.unit}: {len(sessions)} readable repetition(s); model "
            f"discovery needs at least 2 (the noise is estimated from their scatter)"
        )
    try:
        diag = diagnose_unit(
            sessions, alpha=args.alpha, tables=args.residuals is not None, min_gain=args.min_gain
        )
    except DesignError as exc:
        raise CliError(f"unit {args.unit}: {exc.reason}") from None
    print("\n".join(summary_lines(diag)))
    production = None
    try:  # the production calibration (xu2016, per repetition) replayed the same way
        production = replay_xu2016(sessions, diag.noise)
    except (DesignError, ValueError) as exc:
        print(f"xu2016 calibration not replayed: {exc}", file=sys.stderr)
    if production is not None:
        s = summarise_residuals(production).groupby("channel", sort=False)
        worst = s.apply(lambda g: g.loc[g.rms_z.idxmax()], include_groups=False)
        print(
            "xu2016 calibration replayed (rms residual / sigma, worst test per channel): "
            + ", ".join(f"{ch} {r.rms_z:.3g} ({r.test})" for ch, r in worst.iterrows())
        )
    if args.json:
        write_json_atomic(args.json, diag.to_dict())
        print(f"-> {args.json}")
    if args.residuals:
        parts = [diag.residuals_before.assign(model="affine"), diag.residuals_after.assign(model="extended")]
        if production is not None:
            parts.append(production.assign(model="xu2016"))
        table = pd.concat(parts, ignore_index=True)
        args.residuals.parent.mkdir(parents=True, exist_ok=True)
        table.to_parquet(args.residuals, index=False)
        print(f"-> {args.residuals}")
    return 0
