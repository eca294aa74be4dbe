"""Model discovery: where the fitted model is wrong, which physical effect explains it, and
what extending the model buys on data it was not fitted to.

The model of a unit over R repetitions, per channel c (gx gy gz in deg/s, ax ay az in g):

    ref_c(step) = K_c . raw(step) + b_c(rep) - sum_T E_T,c(step) theta_T

K is shared by the repetitions; each repetition has its own biases b (turn-on
repeatability is not an effect); every catalogue term T (:func:`calib_core.effects.catalogue`)
adds its regressors E_T. All of it is linear, so the fit is one weighted least squares over
every step of both sensors (gyro channels during multiposition steps and accelerometer
channels during rotation steps included). Even-in-rate terms are visible because steps enter
one by one, not as the +/- differences of xu2016 (which cancel them).

Weights are 1/sigma of each step mean, estimated from the data (:mod:`calib_core.discovery.replay`):
within-step scatter plus the step-to-step scatter seen across repetitions.

Tests (alpha is the family-wise false-alarm rate per unit, default 1%):

- **misfit** (lack of fit): the residual of the model is split into *pure error* (the
  repetition-to-repetition scatter) and *lack of fit* (the mean over the repetitions the
  model does not explain), both projected on the directions the model leaves free
  (:meth:`calib_core.discovery.significance.Significance.projected_lack_of_fit`):
  F = (SS_lof/dof_lof) / (SS_pure/dof_pure) against F with Satterthwaite dof. A systematic
  error common to the repetitions inflates SS_lof only. "The unit misfits" is the union of
  the overall test (alpha / 4), the six channels' (alpha / 24 each) and every candidate's
  targeted test (its mean residual on the term's joint directions against the repetitions'
  scatter along every channel's copy of them, alpha / 2 over the candidates): at most
  alpha on a unit that fits.
- **a term** T added to the current set S: F = (dSS/p) / (SS_pure/dof_pure) against
  F(p, dof_pure) (p = rank gained), at alpha / 2 / (number of candidate terms) (Bonferroni
  over the catalogue), *and* its leave-one-repetition-out held-out rms must drop (gain > 1).
- forward selection adds the most significant eligible term and repeats; a backward pass
  drops any chosen term no longer significant given the others.
- a chosen term must fix at least one channel it acts on that misfit at baseline
  (per-channel lack-of-fit test at alpha/24), or, when no channel misfits, be what makes the
  unit misfit; a term that leaves all of them misfit only
  soaks up part of something else and is reported as a *partial* candidate, not an effect.
- **misfit**: the union test above rejects at baseline, or a term was chosen.
- **unexplained**: the lack-of-fit test still rejects after selection, or a partial term was
  set aside.

Held-out score: each repetition in turn is held out, the model is fitted on the others,
the held-out repetition is predicted (its own biases fitted, as at turn-on) and its residual
normalised by sigma; rms over all folds. ``gain`` = rms without the term / rms with it, over
the channels the term acts on.

The parts: :mod:`~calib_core.discovery.design` (the unit's grid and the terms' columns),
:mod:`~calib_core.discovery.noise` (the noise model), :mod:`~calib_core.discovery.fit` (the
joint fit, :class:`JointModel` / :class:`JointFit`), :mod:`~calib_core.discovery.significance`
(the tests on its fits), :mod:`~calib_core.discovery.policy` (selection and verdicts); this
module runs them, re-linearises the bilinear model and assembles the :class:`Diagnosis`.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd

from calib_core.calibration import Calibration, TermValue
from calib_core.discovery.fit import joint_model
from calib_core.discovery.measured_noise import ESTIMATED_SOURCE, MeasuredNoise
from calib_core.discovery.policy import Policy
from calib_core.discovery.presentation import empty_frame, evidence_frame
from calib_core.discovery.replay import NoiseEstimate, replay_unit
from calib_core.discovery.results import (
    DEFAULT_ALPHA,
    DEFAULT_MIN_GAIN,
    ConfoundedFinding,
    EffectFinding,
    FTest,
    jsonable,
)
from calib_core.discovery.significance import Significance
from calib_core.effects import SensingGeometry
from calib_core.steps import StepMeans


# -- results --------------------------------------------------------------------------
@dataclass
class Diagnosis:
    """What :func:`diagnose_unit` found for one unit."""

    lot: str
    unit: str
    n_reps: int
    alpha: float
    misfit: bool
    unexplained: bool
    effects: list[EffectFinding]
    partial: list[EffectFinding]  # significant but leave their channels misfit: not chosen
    negligible: list[EffectFinding]  # significant, but the unit fits without them or their
    # held-out gain is below min_gain: not applied
    terms: tuple[TermValue, ...]
    lack_of_fit_before: FTest
    lack_of_fit_after: FTest
    channel_misfit_before: dict[str, FTest]
    channel_misfit_after: dict[str, FTest]
    noise: NoiseEstimate
    calibrations_before: list[Calibration]  # one per repetition (own biases)
    calibrations_after: list[Calibration]
    residuals_before: pd.DataFrame = field(repr=False)
    residuals_after: pd.DataFrame = field(repr=False)
    heldout_rms_baseline: float = float("nan")  # all channels, affine model
    heldout_rms_final: float = float("nan")  # all channels, chosen model
    min_gain: float = DEFAULT_MIN_GAIN
    # largest change of a sensing direction (rad) at each re-linearisation of the geometry
    relinearisations: list[float] = field(default_factory=list)
    # terms the steps cannot tell apart, significant together: applied, named by none
    confounded: list[ConfoundedFinding] = field(default_factory=list)
    confounded_set_aside: list[list[str]] = field(default_factory=list)  # partial/negligible
    advice: list[str] = field(default_factory=list)  # which steps would separate them
    # candidates whose targeted (or between-repetition) test on the affine model rejects
    # (part of "misfit"); those of them whose between-repetition test rejects
    misfit_terms: list[str] = field(default_factory=list)
    misfit_between: list[str] = field(default_factory=list)
    # the series behind each finding's figure (calib_core.discovery.presentation)
    evidence: pd.DataFrame = field(default_factory=empty_frame, repr=False)
    # the noise the tests used: "measured: recording <name>" or "estimated from the repetitions"
    noise_source: str = ESTIMATED_SOURCE

    @property
    def calibration(self) -> Calibration:
        """The unit's extended calibration (biases averaged over the repetitions)."""
        cals = self.calibrations_after
        return replace(
            cals[0], w0=np.mean([c.w0 for c in cals], axis=0), f0=np.mean([c.f0 for c in cals], axis=0)
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready (non-finite numbers become None)."""
        return jsonable(
            {
                "unit": self.unit,
                "lot": self.lot,
                "n_reps": self.n_reps,
                "alpha": self.alpha,
                "misfit": self.misfit,
                "unexplained": self.unexplained,
                "effects": [e.to_dict() for e in self.effects],
                "partial": [e.to_dict() for e in self.partial],
                "negligible": [e.to_dict() for e in self.negligible],
                "min_gain": self.min_gain,
                "relinearisations": list(self.relinearisations),
                "confounded": [c.to_dict() for c in self.confounded],
                "confounded_set_aside": [list(g) for g in self.confounded_set_aside],
                "advice": list(self.advice),
                "misfit_terms": list(self.misfit_terms),
                "misfit_between": list(self.misfit_between),
                "lack_of_fit_before": self.lack_of_fit_before.to_dict(),
                "lack_of_fit_after": self.lack_of_fit_after.to_dict(),
                "misfit_channels_before": [c for c, t in self.channel_misfit_before.items() if t.rejects],
                "misfit_channels_after": [c for c, t in self.channel_misfit_after.items() if t.rejects],
                "heldout_rms_baseline": self.heldout_rms_baseline,
                "heldout_rms_final": self.heldout_rms_final,
                "noise": self.noise.records(),
                "noise_source": self.noise_source,
            }
        )


class _Discovery:
    """One pass of discovery on a unit: its joint model (:mod:`calib_core.discovery.fit`),
    the tests on its fits (:mod:`calib_core.discovery.significance`) and the decisions
    (:mod:`calib_core.discovery.policy`). ``geometry``: the sensing geometry the terms act
    through (default: that of the affine fit's K); ``noise_model`` = (K rows, physical
    residual) of the model whose residuals estimate the noise (default: the affine model).
    An attribute of none of its own is looked up in the policy, the tests, the model, in
    that order (the parts' methods, for callers that probe one of them)."""

    def __init__(
        self,
        sessions: list[StepMeans],
        alpha: float,
        geometry: SensingGeometry | None = None,
        noise_model: tuple[np.ndarray, np.ndarray] | None = None,
        min_gain: float = DEFAULT_MIN_GAIN,
        measured: MeasuredNoise | None = None,
    ):
        self.model = joint_model(sessions, geometry, noise_model, measured)
        self.tests = Significance(self.model)
        self.policy = Policy(self.model, self.tests, alpha, min_gain)

    def __getattr__(self, name: str):
        for part in ("policy", "tests", "model"):
            obj = self.__dict__.get(part)
            if obj is not None and hasattr(obj, name):
                return getattr(obj, name)
        raise AttributeError(name)


_BLAS_CONTROLLER: list = []  # threadpoolctl.ThreadpoolController, found once per process


def _single_thread_blas():
    """Many small factorisations: BLAS threads only cost synchronisation here (much slower
    on a loaded machine). threadpoolctl is optional. The controller is built once per
    process: finding the loaded libraries reads /proc/self/maps."""
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover
        import contextlib

        return contextlib.nullcontext()
    if not _BLAS_CONTROLLER:
        _BLAS_CONTROLLER.append(ThreadpoolController())
    return _BLAS_CONTROLLER[0].limit(limits=1, user_api="blas")


# re-linearisation of the bilinear model (K and the terms' geometry): stop when no sensing
# direction moves by more than this (rad; 1e-6 x 4 g of lever-arm acceleration is 0.004 mg,
# far below the 0.1 mg noise of a step mean), the chosen terms are the same and the noise
# estimate moved by less than 3 %; at most MAX_RELINEARISATIONS passes after the first
GEOMETRY_TOL = 1e-6
MAX_RELINEARISATIONS = 4


def diagnose_unit(
    step_means_by_rep: list[StepMeans],
    alpha: float = DEFAULT_ALPHA,
    tables: bool = True,
    min_gain: float = DEFAULT_MIN_GAIN,
    measured_noise: MeasuredNoise | None = None,
) -> Diagnosis:
    """Diagnose one unit from its repetitions (see the module docstring for the tests).

    ``alpha`` is the family-wise false-alarm rate per unit; ``min_gain`` the held-out gain a
    term must reach on the channels it fixes to be named; ``tables=False`` skips the
    replayed residual tables (Monte Carlo speed); ``measured_noise``: the unit's noise
    measured independently of its repetitions (e.g. a long static recording), which the
    tests then use in place of the noise estimated from the repetitions' scatter
    (:mod:`calib_core.discovery.measured_noise`)."""
    with _single_thread_blas():
        return _diagnose_unit(step_means_by_rep, alpha, tables, min_gain, measured_noise)


def _diagnose_unit(
    step_means_by_rep: list[StepMeans],
    alpha: float,
    tables: bool,
    min_gain: float,
    measured: MeasuredNoise | None = None,
) -> Diagnosis:
    d = _Discovery(step_means_by_rep, alpha, min_gain=min_gain, measured=measured)
    chosen, partial, negligible = d.policy.select()
    moves: list[float] = []
    while (chosen or partial or negligible) and len(moves) < MAX_RELINEARISATIONS:
        # the model is bilinear: the terms act through the geometry of K, and the affine
        # model's K is distorted by the effects it misses (and the noise reaches the
        # residual through K). Re-linearise around the model of every significant term (one
        # left partial or negligible on a poor geometry included) and select again.
        model = tuple(chosen + partial + negligible)
        K = d.model.fit(model).K
        geometry = SensingGeometry.from_gains(K[:3], K[3:])
        moves.append(geometry.distance(d.model.geometry))
        d2 = _Discovery(
            step_means_by_rep,
            alpha,
            geometry=geometry,
            noise_model=d.model.noise_model(model),
            min_gain=min_gain,
            measured=measured,
        )
        noise_moved = float(np.max(np.abs(np.log(d2.model.sigma / d.model.sigma))))
        before = (sorted(chosen), sorted(partial), sorted(negligible))
        d = d2
        chosen, partial, negligible = d.policy.select()
        if (
            moves[-1] < GEOMETRY_TOL
            and (sorted(chosen), sorted(partial), sorted(negligible)) == before
            and noise_moved < np.log(1.03)
        ):
            break
    m, t, p = d.model, d.tests, d.policy
    lof_before = t.lack_of_fit((), p.lof_alpha)
    chosen_t = tuple(chosen)
    lof_after = t.lack_of_fit(chosen_t, p.lof_alpha)
    thr = p.term_alpha / len(m.names)
    items = p.items
    groups = [i for kind in ("chosen", "partial", "negligible") for i in items[kind] if len(i) > 1]
    effects = [p.finding(chosen, i[0], thr) for i in items["chosen"] if len(i) == 1]
    partial_f = [p.finding(chosen + [n], n, thr) for n in partial]
    negligible_f = [p.finding(chosen + [n], n, thr) for n in negligible]
    advice = _advice(m.sessions[0]) if groups or any(e.undetermined for e in effects) else []
    confounded = [
        p.confounded_finding(chosen, i, thr, _separated_by(advice, i)) for i in items["chosen"] if len(i) > 1
    ]
    cal_before = m.calibrations(())
    cal_after = m.calibrations(chosen_t)
    if tables:
        res_before = replay_unit(cal_before, m.sessions, m.noise.estimate)
        res_after = replay_unit(cal_after, m.sessions, m.noise.estimate)
    else:
        res_before = res_after = empty_frame()
    sm0 = m.sessions[0]
    ch_before = t.channel_lack_of_fit((), p.channel_alpha)
    ch_after = t.channel_lack_of_fit(chosen_t, p.channel_alpha)
    diag = Diagnosis(
        lot=sm0.key.lot,
        unit=sm0.key.unit,
        n_reps=len(m.sessions),
        alpha=alpha,
        misfit=bool(p.unit_misfits() or chosen or partial),
        unexplained=bool(lof_after.rejects or partial or any(t.rejects for t in ch_after.values())),
        effects=effects,
        partial=partial_f,
        negligible=negligible_f,
        terms=cal_after[0].terms,
        lack_of_fit_before=lof_before,
        lack_of_fit_after=lof_after,
        channel_misfit_before=ch_before,
        channel_misfit_after=ch_after,
        noise=m.noise.estimate,
        calibrations_before=cal_before,
        calibrations_after=cal_after,
        residuals_before=res_before,
        residuals_after=res_after,
        heldout_rms_baseline=m.heldout_rms(()),
        heldout_rms_final=m.heldout_rms(chosen_t),
        min_gain=min_gain,
        relinearisations=moves,
        confounded=confounded,
        misfit_terms=list(p.misfit_terms()),
        misfit_between=list(p.misfit_between_terms()),
        noise_source=ESTIMATED_SOURCE if measured is None else measured.label,
        confounded_set_aside=[list(i) for k in ("partial", "negligible") for i in items[k] if len(i) > 1],
        advice=[
            a.describe()
            for a in advice
            if a.terms
            and (
                any(set(a.terms) == set(i) or set(a.terms) <= set(i) for i in groups)
                or any(e.name in a.terms and e.undetermined for e in effects)
            )
        ],
    )
    try:
        diag.evidence = evidence_frame(m, diag, chosen, items)
    except Exception:  # pragma: no cover - figures never cost the unit its diagnosis
        diag.evidence = empty_frame()
    return diag


_ADVICE_CACHE: dict[bytes, list] = {}


def _advice(sm: StepMeans) -> list:
    """:func:`calib_core.discovery.plan.advise` for the unit's protocol (the steps' motion and
    headings, nominal times and warm-up: the same for every unit of the protocol, kept)."""
    from calib_core.discovery.plan import advise

    key = b"".join(
        [
            np.asarray(sm.w_ref, float).tobytes(),
            np.asarray(sm.f_ref, float).tobytes(),
            sm.headings.tobytes(),
            sm.turned_deg().tobytes(),
            repr((sm.latitude_deg, sm.table_heading_deg)).encode(),
        ]
    )
    if key not in _ADVICE_CACHE:
        steps = pd.DataFrame(
            {
                "step": np.asarray(sm.step, np.int64),
                "test": np.asarray(sm.test).astype(str),
                **{f"w_ref_{a}": sm.w_ref[:, i] for i, a in enumerate("xyz")},
                **{f"f_ref_{a}": sm.f_ref[:, i] for i, a in enumerate("xyz")},
                "settle_s": np.zeros(len(sm)),
                "heading_deg": sm.headings,
                "turned0_deg": sm.turned_deg()[:, 0],
                "turned1_deg": sm.turned_deg()[:, 1],
            }
        )
        if len(_ADVICE_CACHE) >= 8:
            _ADVICE_CACHE.clear()
        _ADVICE_CACHE[key] = advise(
            steps, latitude_deg=sm.latitude_deg, table_heading_deg=sm.table_heading_deg
        )
    return _ADVICE_CACHE[key]


def _separated_by(advice: list, item: tuple[str, ...]) -> tuple[str, ...] | None:
    """The step sets that separate ``item`` (None: the protocol already sees a part of each
    member of its own, so no advice names it)."""
    for a in advice:
        if set(a.terms) & set(item) and len(a.terms) > 1:
            return tuple(a.separated_by)
    return None
