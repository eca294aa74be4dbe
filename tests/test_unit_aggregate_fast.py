"""The unit's aggregate: ``summarise`` gives each parameter's statistics over the
repetitions as their definitions give them (numbers worked by hand, and numpy on each
parameter's values), NaN values and missing models included; every fit's ``parameters()``
lists the names, values and units of the paper's parameters.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import pytest

from calib_core.models.pipeline import calibrate_repetitions
from calib_core.models.xu2016 import AXES
from calib_core.results import Param, RepetitionCalibration, param_list, summarise
from calib_core.sim import protocols

from conftest import STEPS_WITH_VERIFICATION, unit_step_means


def _reps(n: int = 5, seed: int = 7, steps=STEPS_WITH_VERIFICATION):
    return [f.calibration for f in calibrate_repetitions(unit_step_means(n, seed, steps))]


@dataclass(frozen=True)
class _Listed:
    """A fit that only lists parameters: (name, value, stderr) in unit "u"."""

    params: tuple
    model: str = "m"

    def parameters(self):
        return [Param(self.model, n, v, e, "u") for n, v, e in self.params]


def _rep(rep: int, *params) -> RepetitionCalibration:
    return RepetitionCalibration("L", "U", rep, fits={"m": _Listed(params)})


def test_summarise_known_numbers():
    nan = float("nan")
    reps = [
        _rep(3, ("a", 3.0, nan)),
        _rep(1, ("a", 1.0, 0.1), ("b", 10.0, nan)),
        _rep(2, ("a", 2.0, 0.3), ("b", 20.0, nan)),
    ]
    a, b = summarise(reps)  # in the order the parameters first appear, reps in rep order
    assert (a.model, a.name, a.unit, a.n_reps, a.values) == ("m", "a", "u", 3, (1.0, 2.0, 3.0))
    assert (a.mean, a.std, a.min, a.max) == (2.0, 1.0, 1.0, 3.0)
    assert a.mean_stderr == pytest.approx(0.2, rel=1e-15)  # the NaN stderr left out
    # sqrt(0.1^2 + 0.3^2) / 2 over the two repetitions with a standard error
    assert a.stderr_of_mean == pytest.approx(math.sqrt(0.1) / 2, rel=1e-15)
    assert (b.n_reps, b.values, b.mean, b.min, b.max) == (2, (10.0, 20.0), 15.0, 10.0, 20.0)
    assert b.std == pytest.approx(math.sqrt(50.0), rel=1e-15)
    assert math.isnan(b.mean_stderr) and math.isnan(b.stderr_of_mean)  # no repetition has one
    one = summarise(reps[:1])[0]
    assert one.n_reps == 1 and one.mean == 3.0 and math.isnan(one.std)
    assert summarise([]) == []
    with pytest.raises(ValueError, match="repetition 4 lists a parameter twice"):
        summarise([_rep(4, ("a", 1.0, 0.1), ("a", 2.0, 0.1))])


def _by_definition(reps):
    """Each parameter's statistics from its values, one parameter at a time (numpy)."""
    by_key: dict = {}
    for rep in sorted(reps, key=lambda r: r.rep):
        for p in rep.parameters():
            by_key.setdefault((p.model, p.name), []).append(p)
    out = {}
    for key, ps in by_key.items():
        v, se = np.array([p.value for p in ps]), np.array([p.stderr for p in ps])
        out[key] = dict(
            unit=ps[0].unit,
            n_reps=len(v),
            values=tuple(v.tolist()),
            mean=v.mean(),
            std=v.std(ddof=1) if len(v) > 1 else np.nan,
            min=v.min(),
            max=v.max(),
            mean_stderr=np.nanmean(se) if np.isfinite(se).any() else np.nan,
            stderr_of_mean=(
                np.sqrt(np.sum(se[np.isfinite(se)] ** 2)) / np.isfinite(se).sum()
                if np.isfinite(se).any()
                else np.nan
            ),
        )
    return out


def _check(summaries, reps) -> None:
    expected = _by_definition(reps)
    assert [(s.model, s.name) for s in summaries] == list(expected)
    for s in summaries:
        e = expected[(s.model, s.name)]
        assert (s.unit, s.n_reps) == (e["unit"], e["n_reps"])
        np.testing.assert_allclose(s.values, e["values"], rtol=0, atol=0)
        for stat in ("mean", "std", "min", "max", "mean_stderr", "stderr_of_mean"):
            np.testing.assert_allclose(getattr(s, stat), e[stat], rtol=1e-12, err_msg=stat)
        assert all(type(getattr(s, k)) is float for k in ("mean", "std", "min", "max"))


def test_stderr_of_mean_matches_the_monte_carlo_spread_of_the_mean():
    # five repetitions with unequal standard errors, each value drawn around the truth with
    # its own: the spread of the mean over many draws is what stderr_of_mean predicts
    rng = np.random.default_rng(2026)
    se = np.array([0.5, 1.0, 1.0, 2.0, 3.0])
    means = []
    for _ in range(4000):
        v = 10.0 + rng.normal(0.0, se)
        (s,) = summarise([_rep(i + 1, ("a", float(x), float(e))) for i, (x, e) in enumerate(zip(v, se))])
        means.append(s.mean)
    assert np.std(means, ddof=1) == pytest.approx(s.stderr_of_mean, rel=0.05)
    assert s.mean_stderr == pytest.approx(se.mean())  # another quantity: 1.5, not 0.86


def test_summarise_fitted_repetitions():
    reps = _reps()
    out = summarise(reps)
    _check(out, reps)
    assert len(out) == len(reps[0].parameters()) and out[0].n_reps == 5
    assert summarise(reps[::-1]) == out  # summarised in rep order whatever the given order


def test_summarise_with_nan_parameters():
    # untilted dynamic steps: some lever-arm components are NaN (value and stderr)
    steps = protocols.to_frame(
        protocols.xu2016_multirate()
        + protocols.xu2016_multiposition()
        + protocols.dynamic_steps(tilted=False)
    )
    reps = _reps(seed=10, steps=steps)
    assert np.isnan(reps[0].fits["lever_arm"].lever_arm_mm).any()
    out = summarise(reps)
    _check(out, reps)
    assert any(math.isnan(s.mean) and math.isnan(s.mean_stderr) for s in out)
    _check(summarise(reps[:1]), reps[:1])


def test_summarise_missing_models_and_other_fits():
    reps = _reps(3)
    # a repetition without the lever-arm model: those parameters over the other two
    short = replace(reps[0], fits={k: v for k, v in reps[0].fits.items() if k != "lever_arm"})
    mixed = summarise([short] + reps[1:])
    _check(mixed, [short] + reps[1:])
    assert {(x.model, x.name): x.n_reps for x in mixed}[("lever_arm", "r1x")] == 2

    # a fit without param_blocks: summarised from its parameter list
    @dataclass(frozen=True)
    class Other:
        value: float
        model: str = "other"

        def parameters(self):
            return param_list(self.model, ["x"], [self.value], [0.5], "u")

    extra = [replace(r, fits={**r.fits, "other": Other(float(i))}) for i, r in enumerate(reps)]
    out = summarise(extra)
    _check(out, extra)
    assert out[-1].name == "x" and out[-1].mean == 1.0


def test_parameters_from_blocks_are_the_former_params():
    rep = _reps(1)[0]
    fits = rep.fits

    def params(model, names, values, stderrs, unit):
        return [
            Param(model, n, float(v), float(e), unit)
            for n, v, e in zip(names, np.ravel(values), np.ravel(stderrs))
        ]

    g, a, st, lv = fits["gyro"], fits["accel"], fits["accel_static"], fits["lever_arm"]
    mat = [f"{i}{j}" for i in "123" for j in "123"]
    expected = {
        "gyro": params("gyro", [f"k_g{s}" for s in mat], g.K, g.K_stderr, f"deg/s per {g.raw_unit}")
        + params("gyro", [f"w0_{x}" for x in AXES], g.w0, g.w0_stderr, "deg/s"),
        "accel": params("accel", [f"k_a{s}" for s in mat], a.K, a.K_stderr, f"g per {a.raw_unit}")
        + params("accel", [f"f0_{x}" for x in AXES], a.f0, a.f0_stderr, "g"),
        "accel_static": params(
            "accel_static", [f"k_{x}" for x in AXES], st.scale, st.scale_stderr, f"{st.unit}/g"
        )
        + params("accel_static", [f"u0_{x}" for x in AXES], st.bias, st.bias_stderr, st.unit)
        + params(
            "accel_static",
            [f"theta_{x}{y}" for x in AXES for y in AXES],
            st.angles_deg,
            st.angles_stderr,
            "deg",
        ),
        "lever_arm": params(
            "lever_arm", [f"r{i}{x}" for i in "123" for x in AXES], lv.lever_arm_mm, lv.stderr, "mm"
        ),
    }
    for name in ("gyro_traditional", "accel_traditional"):
        t = fits[name]
        s, b = ("s_g", "b_g") if name.startswith("gyro") else ("s_a", "b_a")
        expected[name] = params(
            name, [f"{s}{x}" for x in mat], t.S, t.S_stderr, f"{t.raw_unit} per {t.physical_unit}"
        ) + params(name, [f"{b}_{x}" for x in AXES], t.b, t.b_stderr, t.raw_unit)
    assert set(expected) == set(fits)
    for name, fit in fits.items():
        got = fit.parameters()
        assert got == expected[name], name
        assert all(type(p.value) is float and type(p.stderr) is float for p in got)
