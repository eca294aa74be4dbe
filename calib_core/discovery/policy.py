"""The decisions of model discovery: which catalogue terms the unit needs, and what each
chosen one is called.

- "the unit misfits": the union of the overall lack-of-fit test (alpha / 4), the six
  channels' (alpha / 24 each) and every candidate's targeted or between-repetition test
  (alpha / 2 over the tests that run): at most alpha on a unit that fits;
- candidates: terms the steps cannot tell apart are tested together (identifiability), the
  others alone; forward selection adds the most significant candidate (at alpha / 2 over
  the catalogue) that improves the held-out score, a backward pass drops any no longer
  significant (:func:`calib_core.discovery.selection.stepwise`); a chosen group keeps the
  members the data single out, a near-confounded pair is settled by the data;
- the verdict of each chosen item: *named* when it fixes a channel of its sensors that
  misfit at baseline (or, when none does, is what makes the unit misfit) with a held-out
  gain of at least ``min_gain``; *partial* when it leaves every misfit channel it acts on
  misfit; *negligible* otherwise.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy import stats

from calib_core.discovery.fit import HeldOutScore, JointModel
from calib_core.discovery.identifiability import (
    Confounded,
    Identifiability,
    analyse,
    near_confounded,
)
from calib_core.discovery.results import ConfoundedFinding, EffectFinding, FTest
from calib_core.discovery.selection import stepwise
from calib_core.discovery.significance import Significance, significant_parameters
from calib_core.effects import CHANNELS, get_effect

# terms whose columns share a direction up to this sine of angle (the part of a column the
# others do not explain is below 5 % of it) are tested together: calib_core.discovery.identifiability
CONFOUNDING_TOL = 0.05


def select_terms(
    candidates: list[str],
    test: Callable[[tuple[str, ...], str, float], FTest],
    heldout: Callable[[tuple[str, ...], str], HeldOutScore],
    alpha: float,
    backward: bool = True,
    bonferroni_over: int | None = None,
) -> list[str]:
    """Stepwise selection (:func:`stepwise`) of the candidates whose F test rejects and
    whose held-out score improves (gain above 1): ``test(current, name, threshold)``,
    ``heldout(current, name)`` the score of adding ``name`` to ``current``. The turntable
    and the static-pose discovery select by this one rule."""
    return stepwise(
        candidates,
        test,
        lambda current, name: heldout(current, name).gain > 1.0,
        alpha,
        backward=backward,
        bonferroni_over=bonferroni_over,
    )


class Policy:
    """Selection and verdicts on one :class:`JointModel` through its :class:`Significance`
    tests, at the unit's false-alarm rate ``alpha`` and the held-out gain ``min_gain`` a
    named term must reach."""

    def __init__(self, model: JointModel, tests: Significance, alpha: float, min_gain: float):
        self.model = model
        self.tests = tests
        self.alpha = alpha
        self.min_gain = float(min_gain)

    @property
    def identifiability(self) -> Identifiability:
        """Which terms the unit's steps cannot tell apart (:func:`identifiability.analyse`
        on the terms' columns with the affine model projected out, weighted and whitened as
        every fit here: the R factor of the full fold), undetermined columns left out."""
        if "_ident" not in self.__dict__:
            P = self.model.g.P
            Rg = self.model.Rg0[:P, :P]
            terms, pnames, svds = {}, {}, {}
            for n, keep in self._determined_columns().items():
                a = self.model.g.offset[n][0]
                if keep:
                    terms[n] = Rg[:, keep]
                    pnames[n] = tuple(get_effect(n).param_names[k - a] for k in keep)
                    known = self.model.term_svds.get(n)
                    if known is not None and np.array_equal(known[0], keep):  # the same columns
                        svds[n] = known[1:]
            self.__dict__["_ident"] = analyse(np.zeros((P, 0)), terms, pnames, CONFOUNDING_TOL, svds)
        return self.__dict__["_ident"]

    @property
    def near_confounded(self) -> tuple[Confounded, ...]:
        """Pairs of terms near-collinear on the unit's steps but not confounded
        (:func:`identifiability.near_confounded` on the same columns as
        :attr:`identifiability`): the data decide them (:meth:`_settle_near_confounded`)."""
        if "_near" not in self.__dict__:
            P = self.model.g.P
            Rg = self.model.Rg0[:P, :P]
            grouped = {n for grp in self.identifiability.groups() if len(grp) > 1 for n in grp}
            terms = {}
            for n, keep in self._determined_columns().items():
                if keep and n not in grouped:
                    terms[n] = Rg[:, keep]
            self.__dict__["_near"] = near_confounded(terms, CONFOUNDING_TOL)
        return self.__dict__["_near"]

    def _determined_columns(self) -> dict[str, list[int]]:
        """Each term's columns (global) that some channel has and the steps determine."""
        live = self.model.g.live_mask.any(axis=0)
        live[list(self.model.undetermined)] = False
        out = {}
        for n in self.model.names:
            a, b = self.model.g.offset[n]
            out[n] = (a + np.flatnonzero(live[a:b])).tolist()
        return out

    def _settle_near_confounded(self, items: list[tuple[str, ...]]) -> list[tuple[str, ...]]:
        """A chosen term A with a near-confounded partner B (:attr:`near_confounded`) that
        alone would explain the data as well (B significant given the other chosen terms
        without A): A stays named when it is significant given B; B replaces it when B is
        significant given A and A not given B; when neither is significant given the other,
        the pair is one confounded item (the combined fit applied, no name picked). Tests
        at the terms' share of alpha (``term_alpha``) over the catalogue, as :meth:`_resolve`."""
        out = list(items)
        if not any(len(i) == 1 for i in out):
            return out  # no single term chosen: no pair to settle (the pairs not worked out)
        thr = self.term_alpha / len(self.model.names)
        for pair in self.near_confounded:
            names = tuple(n for i in out for n in i)
            a, b = pair.terms
            if (a in names) == (b in names) or (a,) not in out and (b,) not in out:
                continue  # both chosen (each significant given the other), or neither
            kept, rival = (a, b) if (a,) in out else (b, a)
            others = tuple(n for n in names if n != kept)
            if not self.tests.term_test(others, rival, thr).rejects:
                continue  # the partner alone does not explain the data
            if self.tests.term_test(others + (rival,), kept, thr).rejects:
                continue  # the chosen one is significant given its partner
            rival_given_kept = self.tests.term_test(names, rival, thr).rejects
            out[out.index((kept,))] = (rival,) if rival_given_kept else tuple(sorted((kept, rival)))
        return out

    def test_groups(self) -> list[tuple[str, ...]]:
        """Candidates as tested: confounded terms together, the others alone."""
        ident = self.identifiability
        grouped = {n for g in ident.groups() for n in g}
        return sorted(ident.groups() + [(n,) for n in self.model.names if n not in grouped])

    def channels_of(self, name: str) -> tuple[int, ...]:
        a, b = self.model.g.offset[name]
        return tuple(int(c) for c in np.flatnonzero(self.model.g.live_mask[:, a:b].any(axis=1)))

    def sensor_channels(self, name: str) -> tuple[int, ...]:
        """The channels of the sensors the term's parameters act on (a term reaches the
        other channels of its triad only through misalignment)."""
        a, b = self.model.g.offset[name]
        live = self.model.g.live_mask[:, a:b].any(axis=0)
        return tuple(sorted({int(c) for c in get_effect(name).param_sensor()[live]}))

    # selection
    def select(self) -> tuple[list[str], list[str], list[str]]:
        """(chosen, partial, negligible) terms: stepwise selection (:func:`stepwise`) over
        the test groups (:meth:`test_groups`: terms the steps cannot tell apart enter
        together), each chosen group resolved (:meth:`_resolve`), then each chosen item must
        matter (:meth:`_verdict`); the worst that does not is set aside and the rest judged
        again. The items (a term, or a confounded group) are kept in ``self.items``."""
        groups = {"+".join(g): g for g in self.test_groups()}

        def flat(labels: tuple[str, ...]) -> tuple[str, ...]:
            return tuple(n for lab in labels for n in groups[lab])

        def test(current: tuple[str, ...], lab: str, threshold: float) -> FTest:
            return self.tests.group_test(flat(current), groups[lab], threshold)

        def heldout(current: tuple[str, ...], lab: str) -> HeldOutScore:
            # the held-out score as the verdict counts it: on the channels the item acts on
            # significantly, on the steps it acts on. On every channel it could act on, the
            # parameters a one-sensor effect does not have add fitted noise that hides its
            # gain on its own channel (docs/model-discovery.md, "Design choices")
            item, cur = groups[lab], flat(current)
            ch = self.item_channels(list(cur + item), item) or tuple(
                sorted({c for n in item for c in self.channels_of(n)})
            )
            return self.model.heldout_score(cur, cur + item, ch)

        labels = select_terms(list(groups), test, heldout, self.term_alpha)
        chosen = self._settle_near_confounded(self._resolve([groups[lab] for lab in labels]))
        partial: list[tuple[str, ...]] = []
        negligible: list[tuple[str, ...]] = []
        while chosen:
            names = [n for item in chosen for n in item]
            verdicts = {item: self._verdict(names, item) for item in chosen}
            failing = [
                (kind != "partial", gain, item)
                for item, (kind, gain, _) in verdicts.items()
                if kind != "named"
            ]
            if not failing:
                break
            is_negligible, _, worst = min(failing)
            chosen.remove(worst)
            (negligible if is_negligible else partial).append(worst)
        self.items = {"chosen": chosen, "partial": partial, "negligible": negligible}
        return (
            [n for i in chosen for n in i],
            [n for i in partial for n in i],
            [n for i in negligible for n in i],
        )

    def _resolve(self, items: list[tuple[str, ...]]) -> list[tuple[str, ...]]:
        """A chosen group of confounded terms keeps the members the data single out: each
        member tested given everything else chosen (its group included), at alpha over the
        catalogue. Members that pass are named alone; when none does, the group stays one
        item (reported confounded, its combined fit applied)."""
        out: list[tuple[str, ...]] = []
        thr = self.term_alpha / len(self.model.names)
        names = [n for i in items for n in i]
        for item in items:
            if len(item) == 1:
                out.append(item)
                continue
            alone = [
                m for m in item if self.tests.term_test(tuple(n for n in names if n != m), m, thr).rejects
            ]
            if alone:
                names = [n for n in names if n not in item or n in alone]
                out += [(m,) for m in alone]
            else:
                out.append(item)
        return out

    # alpha, the false-alarm rate per unit, is shared by the tests that say "the unit
    # misfits" (Bonferroni): half by the lack-of-fit tests (the overall one alpha / 4, each
    # channel alpha / 24), half by the catalogue's targeted tests (alpha / 2 over the
    # candidates), which see a small effect along its own direction long before an omnibus
    # test over every direction does
    @property
    def lof_alpha(self) -> float:
        return self.alpha / 4

    @property
    def channel_alpha(self) -> float:
        return self.alpha / 24

    @property
    def term_alpha(self) -> float:
        return self.alpha / 2

    def misfit_channels(self) -> list[int]:
        """Channels whose lack of fit rejects at baseline (``channel_alpha`` each)."""
        before = self.tests.channel_lack_of_fit((), self.channel_alpha)
        return [c for c in range(6) if before[CHANNELS[c]].rejects]

    def misfit_terms(self) -> list[str]:
        """Candidates (:meth:`test_groups`, joined by "+") whose targeted test on the affine
        model (:meth:`targeted_test`) or between-repetition test
        (:meth:`between_repetition_test`) rejects at ``term_alpha`` over the tests that run:
        the targeted part of "the unit misfits"."""
        return self._misfit_tests()[0]

    def misfit_between_terms(self) -> list[str]:
        """The candidates of :meth:`misfit_terms` whose between-repetition test rejects."""
        return self._misfit_tests()[1]

    def _misfit_tests(self) -> tuple[list[str], list[str]]:
        if "_misfit_terms" not in self.__dict__:
            groups = self.test_groups()
            # the between-repetition tests share the candidates' alpha only where they run
            varying = [g for g in groups if self.tests.between_repetition_test(g, 1.0) is not None]
            thr = self.term_alpha / (len(groups) + len(varying))
            between = ["+".join(g) for g in varying if self.tests.between_repetition_test(g, thr).rejects]
            self.__dict__["_misfit_terms"] = (
                [
                    "+".join(g)
                    for g in groups
                    if self.tests.targeted_test(g, thr).rejects or "+".join(g) in between
                ],
                between,
            )
        return self.__dict__["_misfit_terms"]

    def unit_misfits(self) -> bool:
        """The union test: the overall or a channel's lack of fit, or a candidate's targeted
        test rejects; its false-alarm rate on a unit that fits is at most alpha."""
        return bool(
            self.tests.lack_of_fit((), self.lof_alpha).rejects
            or self.misfit_channels()
            or self.misfit_terms()
        )

    def _verdict(self, chosen: list[str], name: str | tuple[str, ...]) -> tuple[str, float, tuple[int, ...]]:
        """("named" | "partial" | "negligible", held-out gain, channels it fixes) of a term
        or a confounded group. Named: the unit misfits, the term fixes a channel of its
        sensors that misfit at baseline (misfit without it, given the other chosen terms,
        and not with it) and its held-out gain on the channels it fixes is at least
        ``min_gain``. Partial: it acts on misfit channels and leaves them all misfit (it
        soaks up part of something else). A term whose presence is physics, not a defect
        (``named_when_significant``, the Earth rate), and any group holding one, is named
        once chosen when it improves the held-out score of its channels."""
        item = (name,) if isinstance(name, str) else tuple(name)
        others = tuple(x for x in chosen if x not in item)
        if any(get_effect(n).named_when_significant for n in item):
            ch = tuple(sorted({c for n in item for c in self.sensor_channels(n)}))
            gain = self._gain(others, tuple(chosen), ch)
            return ("named" if gain > 1.0 else "negligible"), gain, ch
        sensors = sorted({c for n in item for c in self.sensor_channels(n)})
        if not self.unit_misfits():
            return "negligible", 1.0, ()
        if not self.misfit_channels():
            # only the overall test or the targeted tests reject: the term must be what
            # makes the unit misfit (the overall test rejects without it and not with it,
            # or its own test given the other chosen terms rejects at the targeted tests'
            # threshold), and its gain counts on the sensors of its individually
            # significant parameters
            overall_fixed = (
                self.tests.lack_of_fit(others, self.lof_alpha).rejects
                and not self.tests.lack_of_fit(tuple(chosen), self.lof_alpha).rejects
            )
            targeted = any(set(item) & set(lab.split("+")) for lab in self.misfit_terms())
            if not (overall_fixed or targeted):
                return "negligible", 1.0, ()
            ch = self.item_channels(list(chosen), item) or tuple(sensors)
            if not ch:
                return "negligible", 1.0, ()
            gain = self._gain(others, tuple(chosen), ch)
            return ("named" if gain >= self.min_gain else "negligible"), gain, ch
        bad = [c for c in sensors if c in self.misfit_channels()]
        without = self.tests.channel_lack_of_fit(others, self.channel_alpha) if bad else {}
        if not any(without[CHANNELS[c]].rejects for c in bad):
            # no channel of its sensors misfits, or the other chosen terms already fix every
            # one that did (two effects on one sensor): on its own sensors this term is
            # judged as when no channel misfits, by its own targeted or between-repetition
            # test (a drift between repetitions never makes a channel's lack of fit reject)
            if not any(set(item) & set(lab.split("+")) for lab in self.misfit_terms()):
                return "negligible", 1.0, ()
            ch = self.item_channels(list(chosen), item) or tuple(sensors)
            gain = self._gain(others, tuple(chosen), ch)
            return ("named" if gain >= self.min_gain else "negligible"), gain, ch
        with_ = self.tests.channel_lack_of_fit(tuple(chosen), self.channel_alpha)
        fixed = tuple(c for c in bad if without[CHANNELS[c]].rejects and not with_[CHANNELS[c]].rejects)
        if not fixed:
            if all(with_[CHANNELS[c]].rejects for c in bad):
                return "partial", 1.0, ()
            return "negligible", 1.0, ()
        gain = self._gain(others, tuple(chosen), fixed)
        return ("named" if gain >= self.min_gain else "negligible"), gain, fixed

    def _gain(self, without: tuple[str, ...], with_: tuple[str, ...], channels: tuple[int, ...]) -> float:
        return self.model.heldout_score(without, with_, channels).gain

    def _param_t(self, chosen: list[str], name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(theta, stderr, |t| > the Bonferroni-corrected normal quantile) of the term's
        parameters in the fit of ``chosen`` (which holds ``name``)."""
        full = tuple(chosen)
        f = self.model.fit(full)
        k = self._theta_index(full, name)
        theta = f.theta[k]
        se = np.sqrt(np.diag(f.cov)[k] * self.model.variance_scale(full))
        sig = significant_parameters(theta, se, self.alpha)
        t = np.abs(theta) / np.where(np.isfinite(se) & (se > 0), se, np.inf)
        if not sig.any() and np.isfinite(t).any() and np.nanmax(t) > 0:
            sig[int(np.nanargmax(t))] = True
        return theta, se, sig

    @staticmethod
    def _theta_index(full: tuple[str, ...], name: str) -> np.ndarray:
        """Indices of the term ``name``'s parameters in the coefficients of the fit of
        ``full`` (its terms in sorted order)."""
        names_sorted = sorted(full)
        off = sum(get_effect(m).n_params for m in names_sorted[: names_sorted.index(name)])
        return off + np.arange(get_effect(name).n_params)

    def significant_channels(self, chosen: list[str], name: str) -> tuple[int, ...]:
        """Channels of the sensors the term's individually significant parameters act on."""
        _, _, sig = self._param_t(chosen, name)
        return tuple(sorted({int(c) for c in get_effect(name).param_sensor()[sig]}))

    def item_channels(self, chosen: list[str], item: tuple[str, ...]) -> tuple[int, ...]:
        """Channels a term (:meth:`significant_channels`) or a confounded group acts on
        significantly. A group's members are near-collinear, so in their joint fit no single
        parameter need be significant while their sum on a sensor is: each sensor's
        parameters of the group are Wald-tested together (Bonferroni over the sensors), and
        the sensor with the largest statistic stands in when none passes."""
        if len(item) == 1:
            return self.significant_channels(chosen, item[0])
        full = tuple(chosen)
        f = self.model.fit(full)
        cov = f.cov * self.model.variance_scale(full)
        idx = np.concatenate([self._theta_index(full, n) for n in item])
        sensor = np.concatenate([get_effect(n).param_sensor() for n in item])
        wald: dict[int, float] = {}
        for c in np.unique(sensor):
            k = idx[sensor == c]
            C = cov[np.ix_(k, k)]
            if not np.all(np.isfinite(C)):
                continue
            # the Wald statistic on the directions the covariance determines (one eigh)
            lam, V = np.linalg.eigh(C)
            keep = lam > 1e-10 * max(float(lam.max()), 0.0)
            if keep.any():
                z = V[:, keep].T @ f.theta[k]
                wald[int(c)] = float(stats.chi2.sf(np.sum(z**2 / lam[keep]), int(keep.sum())))
        if not wald:
            return ()
        hit = tuple(sorted(c for c, p in wald.items() if p < self.alpha / len(wald)))
        return hit or (min(wald, key=wald.get),)

    def finding(self, chosen: list[str], name: str, threshold: float) -> EffectFinding:
        others = tuple(x for x in chosen if x != name)
        full = tuple(others) + (name,)
        term = get_effect(name)
        p = term.n_params
        theta, se, sig = self._param_t(list(full), name)
        a = self.model.g.offset[name][0]
        undet = {term.param_names[k - a]: why for k, why in self.model.undetermined.items() if a <= k < a + p}
        _, _, fixed = self._verdict(list(full), name)
        ch = fixed or self.sensor_channels(name) or self.channels_of(name)
        sensor = term.param_sensor()
        axes = {CHANNELS[int(sensor[k])][1] for k in np.flatnonzero(sig)}

        def number(n: str, v: float) -> float | None:
            return None if n in undet or not np.isfinite(v) else float(v)

        return EffectFinding(
            name=name,
            axes=tuple(sorted(axes)),
            estimate={n: number(n, v) for n, v in zip(term.param_names, theta)},
            stderr={n: number(n, v) for n, v in zip(term.param_names, se)},
            units=dict(zip(term.param_names, term.param_units)),
            evidence=self.tests.term_test(others, name, threshold),
            heldout_rms_before=(score := self.model.heldout_score(others, full, ch)).before,
            heldout_rms_after=score.after,
            heldout_steps=(score.steps, score.steps_total),
            channels=tuple(CHANNELS[c] for c in ch),
            undetermined=undet,
        )

    def confounded_finding(
        self,
        chosen: list[str],
        item: tuple[str, ...],
        threshold: float,
        separated_by: tuple[str, ...] | None = None,
    ) -> ConfoundedFinding:
        """A group the steps cannot tell apart, fitted together with ``chosen``."""
        full = list(chosen) + [n for n in item if n not in chosen]
        others = tuple(n for n in full if n not in item)
        # the channels its verdict judged it on (as a single term's finding), else all its sensors'
        _, _, fixed = self._verdict(full, tuple(item))
        ch = fixed or tuple(sorted({c for n in item for c in self.sensor_channels(n)}))
        sin = min(
            (
                c.sin_angle
                for c in self.identifiability.confounded + self.near_confounded
                if set(c.terms) & set(item)
            ),
            default=0.0,
        )
        # each member as if it were the whole explanation (with the other chosen terms): the
        # combined fit's split along the shared direction is arbitrary
        return ConfoundedFinding(
            terms=tuple(item),
            members=tuple(self.finding(list(others) + [n], n, threshold) for n in item),
            evidence=self.tests.group_test(others, item, threshold),
            heldout_rms_before=(score := self.model.heldout_score(others, tuple(full), ch)).before,
            heldout_rms_after=score.after,
            heldout_steps=(score.steps, score.steps_total),
            channels=tuple(CHANNELS[c] for c in ch),
            sin_angle=float(sin),
            separated_by=tuple(separated_by or ()),
            separable=separated_by is None,
        )
