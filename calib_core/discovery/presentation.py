"""What the results store keeps of a unit's discovery, ready to show: one row per finding
(named, confounded, partial, negligible, or unexplained misfit) with its numbers in physical
units at a precision its standard error supports, and the evidence series behind each figure
(the baseline residual against the variable that drives the effect, the fitted effect, the
residual after). Reports read these rows and draw them; they compute nothing.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd

from calib_core.effects import CHANNELS, FigureVariable, get_effect

KINDS = ("named", "confounded", "partial", "negligible", "unexplained")


def _decimals(se: float) -> int:
    """Decimals that show two significant digits of ``se``."""
    if not (se and math.isfinite(se) and se > 0):
        return 3
    return max(0, 1 - int(math.floor(math.log10(se))))


def value_with_error(v: float | None, se: float | None, unit: str) -> str:
    """``10.6 ± 0.43 deg/h`` (two significant digits of the standard error, the value to
    the same decimal); ``undetermined`` when the value is not known."""
    if v is None or not math.isfinite(v):
        return "undetermined"
    if se is None or not math.isfinite(se):
        return f"{v:.3g} {unit} (no standard error)"
    d = _decimals(se)
    return f"{v:.{d}f} ± {se:.{d}f} {unit}"


def estimates_text(e, max_shown: int = 6) -> str:
    """The parameters of a finding that differ from 0 by more than 2 standard errors
    (largest first), then how many others are within 2 standard errors of 0 and which are
    undetermined. Plain text, ``; `` separated."""
    rows = []
    for n, v in e.estimate.items():
        se = e.stderr.get(n)
        if v is None or se is None or not (se > 0):
            continue
        rows.append((abs(v) / se, n, v, se))
    rows.sort(reverse=True)
    shown = [r for r in rows if r[0] > 2.0][:max_shown] or rows[:1]
    parts = [f"{n} = {value_with_error(v, se, e.units.get(n, ''))}" for _, n, v, se in shown]
    rest = len(rows) - len(shown)
    if rest > 0:
        parts.append(f"{rest} other{'s' if rest > 1 else ''} within 2 SE of 0")
    if e.undetermined:
        parts.append(f"undetermined: {', '.join(e.undetermined)}")
    return "; ".join(parts)


def evidence_text(t) -> str:
    p = "p < 1e-300" if t.p_value <= 0 else f"p = {t.p_value:.2g}"
    return f"F = {t.statistic:.3g} ({t.dof1}, {t.dof2}), {p}"


def channels_text(finding) -> str:
    """The channels a finding's held-out gain counts on, and on how many of their step means
    when only some carry the effect: "gy (95 of 590 step means)"."""
    text = ",".join(finding.channels)
    steps = getattr(finding, "heldout_steps", None)
    if steps is not None and steps[0] < steps[1]:
        text += f" ({steps[0]} of {steps[1]} step means)"
    return text


def _row(diag, kind: str, effect: str, **kw) -> dict[str, Any]:
    return {
        "lot": diag.lot,
        "unit": diag.unit,
        "effect": effect,
        "kind": kind,
        "misfit": bool(diag.misfit),
        "unexplained": bool(diag.unexplained),
        **kw,
    }


def finding_rows(diag) -> list[dict[str, Any]]:
    """The store's ``discovery`` rows of one :class:`~calib_core.discovery.Diagnosis`."""
    unit_cols = {
        "confounded_groups": "; ".join(", ".join(c.terms) for c in diag.confounded),
        "partial_terms": ", ".join(e.name for e in diag.partial),
        "negligible_terms": ", ".join(e.name for e in diag.negligible),
        "advice": " | ".join(diag.advice),
    }
    rows = []

    def effect_row(e, kind):
        return _row(
            diag,
            kind,
            e.name,
            axes=",".join(e.axes),
            channels=channels_text(e),
            estimates=estimates_text(e),
            evidence=evidence_text(e.evidence),
            evidence_p=float(e.evidence.p_value),
            heldout_rms_before=float(e.heldout_rms_before),
            heldout_rms_after=float(e.heldout_rms_after),
            gain=float(e.gain),
            separated_by="",
            **unit_cols,
        )

    rows += [effect_row(e, "named") for e in diag.effects]
    for c in diag.confounded:
        est = " | ".join(f"if {m.name}: {estimates_text(m)}" for m in c.members)
        rows.append(
            _row(
                diag,
                "confounded",
                "confounded: " + ", ".join(c.terms),
                axes="",
                channels=channels_text(c),
                estimates=est,
                evidence=evidence_text(c.evidence),
                evidence_p=float(c.evidence.p_value),
                heldout_rms_before=float(c.heldout_rms_before),
                heldout_rms_after=float(c.heldout_rms_after),
                gain=float(c.gain),
                separated_by=c.advice(),
                **unit_cols,
            )
        )
    # a confounded group set aside is one row, as the group it is
    grouped = {n: tuple(g) for g in diag.confounded_set_aside for n in g}
    for kind, found in (("partial", diag.partial), ("negligible", diag.negligible)):
        seen = set()
        for e in found:
            g = grouped.get(e.name)
            if g is None:
                rows.append(effect_row(e, kind))
                continue
            if g in seen:
                continue
            seen.add(g)
            members = [m for m in found if m.name in g]
            row = effect_row(e, kind)
            row.update(
                effect="confounded: " + ", ".join(g),
                axes="",
                estimates=" | ".join(f"{m.name}: {estimates_text(m)}" for m in members),
            )
            rows.append(row)
    if diag.unexplained:
        still = [c for c, t in diag.channel_misfit_after.items() if t.rejects]
        la = diag.lack_of_fit_after
        rows.append(
            _row(
                diag,
                "unexplained",
                "unexplained misfit",
                axes="",
                channels=",".join(still),
                estimates="",
                evidence=evidence_text(la),
                evidence_p=float(la.p_value),
                heldout_rms_before=float(diag.heldout_rms_baseline),
                heldout_rms_after=float(diag.heldout_rms_final),
                gain=float(diag.heldout_rms_baseline / diag.heldout_rms_final)
                if diag.heldout_rms_final > 0
                else float("nan"),
                separated_by="",
                **unit_cols,
            )
        )
    if not rows:
        rows.append(_row(diag, "none", None, **unit_cols))
    return rows


def static_finding_rows(diag, lot: str, unit: str) -> list[dict[str, Any]]:
    """The store's ``discovery`` rows of a :class:`~calib_core.discovery.static.StaticDiagnosis`
    (model discovery on a field recording's static poses): one ``named`` row per effect
    kept, one ``unexplained`` row when a block's residual stays above its noise, else one
    ``none`` row; the columns of :func:`finding_rows` (held-out rms in the block's unit)."""
    unit_cols = {
        "confounded_groups": "",
        "partial_terms": "",
        "negligible_terms": "",
        "advice": f"static poses of field recording {diag.recording} (no turntable references)",
    }
    head = {"lot": lot, "unit": unit, "misfit": bool(diag.misfit), "unexplained": bool(diag.unexplained)}
    rows = [
        {
            **head,
            "effect": e.name,
            "kind": "named",
            "axes": ",".join(e.axes),
            "channels": ",".join(e.channels),
            "estimates": estimates_text(e),
            "evidence": evidence_text(e.evidence),
            "evidence_p": float(e.evidence.p_value),
            "heldout_rms_before": float(e.heldout_rms_before),
            "heldout_rms_after": float(e.heldout_rms_after),
            "gain": float(e.gain),
            "separated_by": "",
            **unit_cols,
        }
        for e in diag.effects
    ]
    if diag.unexplained:
        b = [
            k
            for k, v in diag.blocks.items()
            if v.get("chi2_white_p_after", 1.0) < diag.alpha / len(diag.blocks)
        ]
        blk = diag.blocks[b[0]] if b else {}
        before, after = (
            blk.get("heldout_rms_before", float("nan")),
            blk.get("heldout_rms_after", float("nan")),
        )
        rows.append(
            {
                **head,
                "effect": "unexplained misfit",
                "kind": "unexplained",
                "axes": "",
                "channels": ",".join(b),
                "estimates": "",
                "evidence": f"residual {blk.get('rms_over_white_after', float('nan')):.3g} x the white noise "
                f"of a pose mean ({', '.join(b)})",
                "evidence_p": float(blk.get("chi2_white_p_after", float("nan"))),
                "heldout_rms_before": float(before),
                "heldout_rms_after": float(after),
                "gain": float(before / after) if after and after > 0 else float("nan"),
                "separated_by": "",
                **unit_cols,
            }
        )
    if not rows:
        rows.append({**head, "effect": None, "kind": "none", **unit_cols})
    return rows


_EMPTY = pd.DataFrame()


def empty_frame() -> pd.DataFrame:
    """A new empty frame (a copy of one: building ``pd.DataFrame()`` costs a few times more,
    and a diagnosis without tables or figures has three)."""
    return _EMPTY.copy()


def evidence_frame(model, diag, chosen: list[str], items: dict) -> pd.DataFrame:
    """The series behind each figure, from the final joint model's public results
    (:class:`calib_core.discovery.fit.JointModel`: ``residual``, ``fitted_effect``,
    ``steps``, ``contexts``): per finding (named, confounded; the misfit left for
    unexplained), per channel it was judged on, every repetition's steps: ``x`` (the
    variable that drives it, :meth:`EffectTerm.figure_variable`), ``before`` (residual of
    the affine model), ``fitted`` (the finding's fitted effect, drawn over ``before``),
    ``after`` (residual of the chosen model); gyro channels in deg/s, accelerometer
    channels in mg."""
    if not items["chosen"] and not diag.unexplained:
        return empty_frame()  # no finding and nothing unexplained: no series
    real, steps, contexts = model.real, model.steps, model.contexts
    r_before = model.residual(())
    r_after = model.residual(tuple(chosen))
    frames = []

    def add(
        effect: str, kind: str, names: tuple[str, ...], channels: tuple[str, ...], fitted: np.ndarray | None
    ):
        for ch in channels:
            c = CHANNELS.index(ch)
            scale = 1.0 if c < 3 else 1e3
            for r, ctx in enumerate(contexts):
                m = real[r]
                if names:
                    fv = get_effect(names[0]).figure_variable(ctx, c)
                else:  # unexplained: against the channel's own reference
                    own = (ctx.w if c < 3 else ctx.f)[:, c % 3]
                    fv = FigureVariable(f"reference on {ch}", "deg/s" if c < 3 else "g", own)
                n = int(m.sum())
                frames.append(
                    pd.DataFrame(
                        {
                            "lot": diag.lot,
                            "unit": diag.unit,
                            "effect": effect,
                            "kind": kind,
                            "channel": ch,
                            "rep": int(model.sessions[r].key.rep),
                            "step": steps[r, m].astype(np.int32),
                            "x": np.asarray(fv.values, float)[:n].astype(np.float32),
                            "x_label": fv.label,
                            "x_unit": fv.unit,
                            "y_unit": "deg/s" if c < 3 else "mg",
                            "before": (scale * r_before[r, m, c]).astype(np.float32),
                            "fitted": (
                                np.full(n, np.nan) if fitted is None else scale * fitted[r, m, c]
                            ).astype(np.float32),
                            "after": (scale * r_after[r, m, c]).astype(np.float32),
                        }
                    )
                )

    for item in items["chosen"]:
        fitted = model.fitted_effect(tuple(chosen), item)
        if len(item) == 1:
            e = next(x for x in diag.effects if x.name == item[0])
            add(item[0], "named", item, e.channels, fitted)
        else:
            cf = next(x for x in diag.confounded if set(x.terms) == set(item))
            add(cf.name, "confounded", tuple(item), cf.channels, fitted)
    if diag.unexplained:
        still = tuple(c for c, t in diag.channel_misfit_after.items() if t.rejects) or (
            min(diag.channel_misfit_after, key=lambda c: diag.channel_misfit_after[c].p_value),
        )
        add("unexplained misfit", "unexplained", (), still, None)
    if not frames:
        return empty_frame()
    return pd.concat(frames, ignore_index=True)
