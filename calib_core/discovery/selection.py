"""Stepwise selection of catalogue terms, the same for every kind of discovery.

Forward: among the candidates whose F test rejects (threshold ``alpha / remaining
candidates``, Bonferroni) and that improve the held-out score, add the most significant (when
p underflows, the larger explained sum of squares); repeat. Backward (optional): drop a
chosen term no longer significant given the others (threshold ``alpha / all candidates``).
"""

from __future__ import annotations

from collections.abc import Callable

from scipy import stats

from calib_core.discovery.results import FTest

TermTest = Callable[[tuple[str, ...], str, float], FTest]
Improves = Callable[[tuple[str, ...], str], bool]


def stepwise(
    candidates: list[str],
    test: TermTest,
    improves: Improves,
    alpha: float,
    backward: bool = True,
    bonferroni_over: int | None = None,
) -> list[str]:
    """The chosen terms, in the order they entered. ``bonferroni_over`` fixes the number of
    comparisons of the forward threshold (default: the candidates left at each round)."""
    chosen: list[str] = []
    while True:
        cands = [n for n in candidates if n not in chosen]
        if not cands:
            break
        thr = alpha / (bonferroni_over or len(cands))
        best, best_score = None, None
        for n in cands:
            t = test(tuple(chosen), n, thr)
            if not t.rejects or not improves(tuple(chosen), n):
                continue
            score = (float(stats.f.logsf(t.statistic, t.dof1, t.dof2)), -t.statistic * t.dof1)
            if best is None or score < best_score:
                best, best_score = n, score
        if best is None:
            break
        chosen.append(best)
    changed = backward
    while changed and len(chosen) > 1:
        changed = False
        thr = alpha / len(candidates)
        worst, worst_p = None, -1.0
        for n in chosen:
            t = test(tuple(x for x in chosen if x != n), n, thr)
            if not t.rejects and t.p_value > worst_p:
                worst, worst_p = n, t.p_value
        if worst is not None:
            chosen.remove(worst)
            changed = True
    return chosen
