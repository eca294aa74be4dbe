"""The smallest effect a protocol can find, before anyone runs the turntable.

For every excited parameter of every catalogue term, alone on a unit, two sizes:

- **detectable**: the size at which the term's targeted test (:meth:`calib_core.discovery.
  significance.Significance.targeted_test`: the repetitions' mean residual on the term's p joint
  directions against the repetitions' own scatter along every channel's copy of them)
  rejects at the share of alpha discovery gives it (alpha / 2 over the candidate groups)
  with probability ``power``. The noncentrality of that F is R |P W x|^2 theta^2: x the
  parameter's column on the steps, W the step means' whitening (white noise falling with
  each step's averaging window plus a Gauss-Markov wander of the bias, :class:`StepNoise`,
  as discovery models them), P the projection that removes each channel's affine
  calibration. A term confounded with others (an identifiability group) is tested with
  them: p counts the group's directions. The denominator's dof are (R - 1) per channel's
  copy, counted under a geometry 0.5 deg off nominal (a real unit's sensor column reaches
  every channel of its triad);
- **worth naming**: the size at which the held-out gain reaches ``min_gain``: gain^2 =
  1 + theta^2 mean((r / sd)^2) over the step means that carry
  :data:`~calib_core.discovery.results.EXCITED_SHARE` of the effect, r the residual of the
  column after the affine model's generalised least-squares fit, seen unwhitened (as
  discovery scores the held-out residual).

Discovery names an effect when it is above both (and it is selected among the candidates), so
``limit`` = the larger is the size below which a unit's effect is expected to stay unnamed.
Approximations, stated: the nominal unit's sensing geometry for the sizes (a 0.5 deg
misalignment lets a lever arm's tangential components leak into the sensed centripetal
acceleration: found at sizes smaller than predicted); the test's nominal dof (discovery's Box
epsilon lowers them a little); the held-out residual's noise taken as one sd and the fold's
estimation noise left out (a realised gain scatters by a few hundredths around the
expected). Checked against the physics simulator, which knows nothing of this module, in
``tests/test_detection_limits.py`` and docs/model-discovery.md ("Detection limits").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy import optimize, stats

from calib_core.discovery.identifiability import orthonormal_basis
from calib_core.discovery.results import DEFAULT_ALPHA, DEFAULT_MIN_GAIN, EXCITED_SHARE
from calib_core.effects import SensingGeometry, catalogue, get_effect

DEFAULT_POWER = 0.95
COVERAGE_SCALES = (0.25, 0.5, 1.0)  # sizes of the realistic effects the coverage counts


@dataclass(frozen=True)
class StepNoise:
    """Noise of the raw outputs per channel (gx gy gz in deg/s, ax ay az in g): a white noise
    of ``white_density`` per sqrt(Hz) (a sample's sd is density sqrt(rate)) and a bias
    instability of sd ``instability`` wandering as a Gauss-Markov process with time constant
    ``tau_s``. Defaults: a MEMS unit, the physics simulator's ``typical_physics_unit`` (0.05
    deg/s and 1 mg per sample at 50 Hz, 0.01 deg/s and 0.1 mg of instability, 20 s)."""

    white_density: np.ndarray = field(
        default_factory=lambda: np.array([0.05, 0.05, 0.05, 1e-3, 1e-3, 1e-3]) / np.sqrt(50.0)
    )
    instability: np.ndarray = field(default_factory=lambda: np.array([0.01, 0.01, 0.01, 1e-4, 1e-4, 1e-4]))
    tau_s: float = 20.0

    def covariance(self, c: int, t: np.ndarray, window_s: np.ndarray) -> np.ndarray:
        """(n, n) covariance of channel ``c``'s step means, averaged over ``window_s`` around
        the times ``t``: the white part falls as 1 / window, the wander keeps
        2 (tau/T)^2 (T/tau - 1 + exp(-T/tau)) of its variance and correlates the steps as
        exp(-|dt| / tau)."""
        x = np.maximum(window_s, 1e-9) / self.tau_s
        kept = np.where(x > 1e-6, 2.0 / x**2 * (x - 1.0 + np.exp(-x)), 1.0)
        wander = self.instability[c] ** 2 * np.exp(-np.abs(t[:, None] - t[None, :]) / self.tau_s)
        wander[np.diag_indices_from(wander)] *= kept
        return wander + np.diag(self.white_density[c] ** 2 / np.maximum(window_s, 1e-9))


@dataclass(frozen=True)
class DetectionLimit:
    """Sizes (in ``unit``) of one parameter, alone on a unit, that discovery detects with
    the stated power (``detectable``) and whose held-out gain reaches min_gain
    (``worth_naming``)."""

    term: str
    param: str
    unit: str
    detectable: float
    worth_naming: float

    @property
    def limit(self) -> float:
        return max(self.detectable, self.worth_naming)


@dataclass(frozen=True)
class TermDetection:
    """One term on a protocol: its excited parameters' columns on the steps, whitened with
    the affine model projected out (``white``, for the test) and, for the held-out gain, the
    residual of the affine model's generalised least-squares fit seen unwhitened in units of
    each step's sd (``plain``), each (p_live, 6, n)."""

    name: str
    params: tuple[str, ...]  # the excited ones, in the term's order
    units: tuple[str, ...]
    live: np.ndarray  # (n_params,) bool: which of the term's parameters the steps excite
    white: np.ndarray
    plain: np.ndarray
    p: int  # the term's joint directions beyond the affine model: its test is F(p, dof_den)
    dof_den: int  # (R - 1) per channel's own copy of the term's directions
    n_reps: int
    alpha: float  # the test's share of the per-unit false-alarm rate
    min_gain: float

    def _live(self, theta) -> np.ndarray:
        theta = np.asarray(theta, float)
        return theta[self.live] if theta.shape == self.live.shape else theta

    def noncentrality(self, theta) -> float:
        """Of the term's F when the unit's parameters are ``theta`` (all of the term's, or
        the excited ones): R |P W E theta|^2."""
        v = np.tensordot(self._live(theta), self.white, axes=1)
        return float(self.n_reps * np.sum(v**2))

    def power(self, theta) -> float:
        """Probability that the term's test rejects at its share of alpha."""
        crit = stats.f.isf(self.alpha, self.p, self.dof_den)
        return float(stats.ncf.sf(crit, self.p, self.dof_den, self.noncentrality(theta)))

    def gain(self, theta) -> float:
        """Held-out gain of the term on its channels, counted on the step means that carry
        EXCITED_SHARE of its effect: sqrt(1 + mean (effect / sigma)^2) there."""
        v = np.tensordot(self._live(theta), self.plain, axes=1)  # (6, n)
        d2 = np.sort((v**2).ravel())[::-1]
        if not d2.size or d2[0] <= 0:
            return 1.0
        m = int(np.searchsorted(np.cumsum(d2), EXCITED_SHARE * d2.sum())) + 1
        return float(np.sqrt(1.0 + np.mean(d2[:m])))

    def limits(self, power: float) -> tuple[DetectionLimit, ...]:
        lam = required_noncentrality(self.p, self.dof_den, self.alpha, power)
        out = []
        for j, (param, unit) in enumerate(zip(self.params, self.units)):
            one = np.zeros(len(self.params))
            one[j] = 1.0
            g2 = self.gain(one) ** 2 - 1.0  # the gain's excess is quadratic in the size
            out.append(
                DetectionLimit(
                    self.name,
                    param,
                    unit,
                    float(np.sqrt(lam / self.noncentrality(one))),
                    float(np.sqrt((self.min_gain**2 - 1.0) / g2)) if g2 > 0 else float("inf"),
                )
            )
        return tuple(out)


@dataclass(frozen=True)
class DetectionLimits:
    n_reps: int
    alpha: float  # the test's share of the per-unit false-alarm rate
    power: float
    min_gain: float
    terms: dict[str, TermDetection]

    @property
    def limits(self) -> tuple[DetectionLimit, ...]:
        return tuple(d for t in self.terms.values() for d in t.limits(self.power))

    def of(self, term: str, param: str) -> DetectionLimit:
        for d in self.terms[term].limits(self.power) if term in self.terms else ():
            if d.param == param:
                return d
        raise KeyError(f"{term}.{param}: not excited by these steps")

    def lines(self) -> list[str]:
        out = [
            f"smallest effect found, each parameter alone, {self.n_reps} repetitions "
            f"(detected by its term's test with {100 * self.power:g} % power at alpha "
            f"{self.alpha:.2g} / held-out gain {self.min_gain:g}: discovery names it above both)"
        ]
        for name, term in sorted(self.terms.items()):
            rows = term.limits(self.power)
            by_unit: dict[str, list[str]] = {}
            for d in rows:
                by_unit.setdefault(d.unit, []).append(
                    f"{d.param} {_fmt(d.detectable)} / {_fmt(d.worth_naming)}"
                )
            out.append(f"  {name}: " + "; ".join(f"[{u}] {', '.join(c)}" for u, c in by_unit.items()))
        return out

    def above(self, term: str, theta) -> bool | None:
        """Whether a unit whose term ``term`` has parameters ``theta`` (alone) is above the
        protocol's limit: detected with ``power`` and its expected held-out gain at least
        min_gain (None: the steps do not excite the term)."""
        det = self.terms.get(term)
        if det is None:
            return None
        return det.power(theta) >= self.power and det.gain(theta) >= det.min_gain

    def coverage(
        self, scales=COVERAGE_SCALES, draws: int = 1000, seed: int = 20261128
    ) -> dict[str, list[tuple[float, float]]]:
        """Per term, per scale: over ``draws`` realistic draws of the effect at that scale
        (its module's :meth:`~calib_core.effects.EffectTerm.realistic`, on random sensors),
        the mean probability that its test detects it, and that it is detected and its
        expected held-out gain reaches min_gain (what discovery names): the share of such
        effects a unit on this protocol is expected to have found. Seeded."""
        rng = np.random.default_rng(seed)
        out: dict[str, list[tuple[float, float]]] = {}
        for name, det in sorted(self.terms.items()):
            term = get_effect(name)
            cells = []
            for scale in scales:
                thetas = [term.realistic(rng, scale)[0] for _ in range(draws)]
                power = np.array([det.power(t) for t in thetas])
                worth = np.array([det.gain(t) >= det.min_gain for t in thetas])
                cells.append((float(power.mean()), float(np.mean(power * worth))))
            out[name] = cells
        return out

    def coverage_lines(self, scales=COVERAGE_SCALES, draws: int = 1000) -> list[str]:
        cov = self.coverage(scales, draws)
        head = " / ".join(f"{s:g}x" for s in scales)
        out = [
            f"realistic effects found, {self.n_reps} repetitions (named, at {head} of each "
            "effect module's realistic size; in brackets: detected by its test)"
        ]
        for name, cells in cov.items():
            named = " / ".join(f"{100 * n:.0f}" for _, n in cells)
            det = " / ".join(f"{100 * d:.0f}" for d, _ in cells)
            out.append(f"  {name}: {named} % ({det} %)")
        return out


# a unit whose sensors are each about 0.5 deg off their nominal axes, in fixed directions
_TILT = 0.5 * np.pi / 180.0 * np.array([[0.0, 1.0, -1.0], [-1.0, 0.0, 1.0], [1.0, -1.0, 0.0]])
_MISALIGNED = SensingGeometry(
    (np.eye(3) + _TILT) / np.linalg.norm(np.eye(3) + _TILT, axis=1, keepdims=True),
    (np.eye(3) - _TILT) / np.linalg.norm(np.eye(3) - _TILT, axis=1, keepdims=True),
)


def _rank(z: np.ndarray) -> int:
    """Directions spanned by columns (k, [6,] n), at discovery's tolerance (1e-8 of the
    largest)."""
    flat = z.reshape(len(z), -1)
    size = np.linalg.norm(flat, axis=1).max(initial=0.0)
    return int(np.linalg.matrix_rank(flat, tol=1e-8 * size)) if size > 0 else 0


def _fmt(x: float) -> str:
    return "-" if not np.isfinite(x) else f"{x:.2g}"


def required_noncentrality(p: int, dof_den: float, alpha: float, power: float) -> float:
    """Noncentrality at which F(p, dof_den) exceeds its 1 - alpha quantile with probability
    ``power``."""
    crit = stats.f.isf(alpha, p, dof_den)

    def short(lam: float) -> float:
        return float(stats.ncf.sf(crit, p, dof_den, lam)) - power

    hi = 1.0
    while short(hi) < 0:
        hi *= 2.0
    return float(optimize.brentq(short, hi / 2.0 if hi > 1.0 else 0.0, hi, xtol=1e-6, rtol=1e-8))


def detection_limits(
    steps: pd.DataFrame,
    n_reps: int = 5,
    alpha: float = DEFAULT_ALPHA,
    power: float = DEFAULT_POWER,
    min_gain: float = DEFAULT_MIN_GAIN,
    noise: StepNoise | None = None,
    latitude_deg: float | None = None,
    table_heading_deg: float | None = None,
    names: list[str] | None = None,
) -> DetectionLimits:
    """:class:`DetectionLimits` of the catalogue's terms (``names``: those only) on a steps
    table (contract columns; :func:`calib_core.discovery.plan.step_context` fills times and
    temperatures). The test's share of ``alpha`` is discovery's: alpha / 2 over the
    candidate groups (the catalogue, confounded terms counted once)."""
    from calib_core.discovery.plan import DEFAULT_DURATION_S, analyse_steps, step_context

    if n_reps < 2:
        raise ValueError("detection needs at least 2 repetitions (the noise is their scatter)")
    noise = StepNoise() if noise is None else noise
    ctx = step_context(steps, latitude_deg, table_heading_deg)
    n = len(ctx)
    ident = analyse_steps(steps, latitude_deg=latitude_deg, table_heading_deg=table_heading_deg)
    grouped = {m for g in ident.groups() for m in g}
    n_groups = len(ident.groups()) + sum(1 for t in catalogue() if t not in grouped)
    alpha_term = alpha / 2.0 / max(n_groups, 1)
    dur = steps["duration_s"].to_numpy(float) if "duration_s" in steps else np.full(n, DEFAULT_DURATION_S)
    settle = steps["settle_s"].to_numpy(float) if "settle_s" in steps else np.zeros(n)
    window = np.where(np.isfinite(dur), dur, DEFAULT_DURATION_S) - np.nan_to_num(settle)
    # per channel: the whitening (generalised least squares, as discovery's) with the affine
    # model projected out for the test; for the held-out gain, the residual of the same
    # generalised least-squares fit of the affine model, seen unwhitened in units of each
    # step's sd (as discovery scores it)
    white, sd, Q_white, gls_fit = [], [], [], []
    for c in range(6):
        ref = ctx.w if c < 3 else ctx.f
        base = np.column_stack([ref, np.ones(n)])
        C = noise.covariance(c, ctx.t, window)
        Linv = np.linalg.inv(np.linalg.cholesky(C))
        white.append(Linv)
        sd.append(np.sqrt(np.diag(C)))
        Q_white.append(orthonormal_basis(Linv @ base))
        gls_fit.append(base @ np.linalg.pinv(Linv @ base) @ Linv)

    def columns(name: str, geometry: SensingGeometry | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(n_params, 6, n) the term's columns whitened, and in sigma, affine removed."""
        E = get_effect(name).regressors(ctx, geometry)  # (n, 6, p): each parameter's effect per channel
        zw = np.zeros((E.shape[-1], 6, n))
        zs = np.zeros((E.shape[-1], 6, n))
        for c in range(6):
            w = white[c] @ E[:, c, :]
            zw[:, c] = (w - Q_white[c] @ (Q_white[c].T @ w)).T
            zs[:, c] = ((E[:, c, :] - gls_fit[c] @ E[:, c, :]) / sd[c][:, None]).T
        return zw, zs

    terms = {}
    for name in sorted(catalogue()) if names is None else names:
        term = get_effect(name)
        zw, zs = columns(name)
        size = np.sqrt(np.sum(zw**2, axis=(1, 2)))
        live = size > 1e-9 * max(size.max(initial=0.0), 1e-300)
        if not live.any():
            continue
        group = next((g for g in ident.groups() if name in g), (name,))
        # a term confounded with others is tested with them: the group's directions
        p = _rank(np.concatenate([zw[live]] + [columns(m)[0] for m in group if m != name]))
        # discovery's denominator: the repetitions' scatter along every channel's own copy of
        # the columns; on a real unit each sensor is a little off its axis, so a sensor's
        # column reaches every channel of its triad (counted, not sized, under _MISALIGNED)
        tilted = np.concatenate([columns(m, _MISALIGNED)[0] for m in group])
        p_den = sum(_rank(tilted[:, c]) for c in range(6))
        terms[name] = TermDetection(
            name,
            tuple(np.array(term.param_names)[live]),
            tuple(np.array(term.param_units)[live]),
            live,
            zw[live],
            zs[live],
            p,
            (n_reps - 1) * max(p_den, p),
            n_reps,
            alpha_term,
            # a term named as soon as it is significant (an effect of where the table stands)
            1.0 if term.named_when_significant else min_gain,
        )
    return DetectionLimits(n_reps, alpha_term, power, min_gain, terms)
