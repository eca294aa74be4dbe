"""Outlier flags per lot (calib_core.outliers): robust z with MAD, spread, TOML limits.

Expected values come from hand computation or from an independent vectorised computation,
never from the module's own output."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from calib_core.outliers import (
    KIND_LIMIT,
    KIND_ROBUST,
    KIND_SPREAD,
    OutlierConfig,
    OutlierConfigError,
    apply_flags,
    flag_lot,
    flag_lots,
    robust_scale,
    robust_z,
)
from schemas.limits import config_from_toml

PARAMS = (
    [("gyro", f"k_g{i}{j}") for i in (1, 2, 3) for j in (1, 2, 3)]
    + [("gyro", f"w0_{a}") for a in "xyz"]
    + [("accel", f"k_a{i}{j}") for i in (1, 2, 3) for j in (1, 2, 3)]
    + [("accel", f"f0_{a}") for a in "xyz"]
)


def gaussian_fleet(rng, lots=3, units=20, n_reps=5, outliers=(), shift_sd=12.0):
    """Unit means drawn N(lot mean, sd) per parameter, rep std ~ sd_rep * chi; ``outliers`` a
    list of (lot index, unit index, parameter index) shifted by ``shift_sd`` sd."""
    rows, truth = [], set()
    sd = {p: rng.uniform(0.5, 2.0) * 10 ** rng.uniform(-4, -1) for p in PARAMS}
    for li in range(lots):
        lot_mean = {p: rng.normal(0, 1) for p in PARAMS}
        for ui in range(units):
            unit = f"U{li:02d}{ui:03d}"
            for pi, p in enumerate(PARAMS):
                x = lot_mean[p] + rng.normal(0, sd[p])
                if (li, ui, pi) in outliers:
                    x += shift_sd * sd[p]
                    truth.add(unit)
                s = 0.1 * sd[p] * np.sqrt(rng.chisquare(n_reps - 1) / (n_reps - 1))
                rows.append(
                    {
                        "lot": f"L{li}",
                        "unit": unit,
                        "model": p[0],
                        "parameter": p[1],
                        "mean": x,
                        "std": s,
                        "n_reps": n_reps,
                        "unit_of_measure": "-",
                    }
                )
    return pd.DataFrame(rows), truth


def flagged(lfs):
    return {u for lf in lfs for u in lf.flagged_units}


def test_robust_z_by_hand():
    x = np.array([1.0, 2.0, 3.0, 4.0, 100.0])
    # median 3, |dev| = 2,1,0,1,97 -> MAD 1 -> scale 1.4826
    np.testing.assert_allclose(robust_z(x), (x - 3.0) / 1.4826)
    assert robust_scale(x) == pytest.approx(1.4826)


def test_mad_zero_falls_back_to_mean_absolute_deviation():
    x = np.array([1.0, 1.0, 1.0, 1.0, 1.0, 2.0])
    # MAD 0; mean |dev| = 1/6 -> scale 1.2533/6
    assert robust_scale(x) == pytest.approx(1.2533 / 6)
    assert robust_z(x)[-1] == pytest.approx(6 / 1.2533)
    assert np.all(robust_z(np.full(7, 3.0)) == 0.0)


def test_identical_units_are_never_flagged(thresholds):
    df = pd.DataFrame(
        [
            {
                "lot": "L",
                "unit": f"U{i}",
                "model": "gyro",
                "parameter": "k_g11",
                "mean": 1.0,
                "std": 1e-4,
                "n_reps": 5,
            }
            for i in range(8)
        ]
    )
    lf = flag_lot(df, thresholds=thresholds)
    assert lf.robust and lf.flags == []


def test_small_lot_gets_no_robust_flags_but_limits_apply(thresholds):
    df = pd.DataFrame(
        [
            {
                "lot": "L",
                "unit": f"U{i}",
                "model": "gyro",
                "parameter": "k_g11",
                "mean": v,
                "std": 1e-4,
                "n_reps": 5,
            }
            for i, v in enumerate([1.0, 1.001, 0.999, 1.5])
        ]
    )
    cfg = config_from_toml("[limits.gyro.k_g11]\nmax = 1.2\n")
    lf = flag_lots(df, cfg, thresholds=thresholds)[0]
    assert not lf.robust and "fewer than 5" in lf.note
    assert [(f.unit, f.kind) for f in lf.flags] == [("U3", KIND_LIMIT)]
    assert "above limit max 1.2" in lf.flags[0].reason


def test_threshold_controls_family_wise_rate_independently_checked(thresholds):
    thr = thresholds.robust_z(20, 24, 3.5, 0.01)
    assert thr > 3.5
    assert thresholds.robust_z((20, 20, 20), 24) == pytest.approx(5.99, abs=0.25)
    assert thresholds.robust_z(20, 24, 3.5, 0.0) == 3.5
    # independent check: 4000 clean lots of 20 Gaussian units x 24 parameters; the chance a
    # lot gets any |z| > thr should be about 0.01 (binomial sd ~0.0016)
    rng = np.random.default_rng(7)
    x = rng.normal(size=(4000, 24, 20))
    med = np.median(x, axis=2, keepdims=True)
    mad = 1.4826 * np.median(np.abs(x - med), axis=2, keepdims=True)
    any_flag = (np.abs(x - med) / mad > thr).any(axis=(1, 2))
    assert 0.004 < any_flag.mean() < 0.02
    # and the plain 3.5 rule flags most clean lots (why the family-wise level exists)
    assert (np.abs(x - med) / mad > 3.5).any(axis=(1, 2)).mean() > 0.9


def test_clean_fleets_are_left_alone_and_outliers_found(thresholds):
    rng = np.random.default_rng(11)
    false_units, missed = 0, 0
    for _ in range(12):
        picks = {
            (int(rng.integers(3)), int(rng.integers(20)), int(rng.integers(len(PARAMS)))) for _ in range(2)
        }
        df, truth = gaussian_fleet(rng, outliers=picks, shift_sd=12.0)
        got = flagged(flag_lots(df, thresholds=thresholds))
        false_units += len(got - truth)
        missed += len(truth - got)
    # 12 fleets at family alpha 0.01 each: ~0.12 false units expected
    assert false_units <= 1
    assert missed == 0


def test_plain_per_lot_rule_floods_clean_units(thresholds):
    rng = np.random.default_rng(12)
    plain = OutlierConfig(family_alpha=0.0, scale_pool="lot")
    # ~7 false units per clean fleet of 3 x 20 units x 24 parameters (0.0975 per lot and
    # parameter, independent check above); 4 fleets: ~28
    n = sum(len(flagged(flag_lots(gaussian_fleet(rng)[0], plain, thresholds=thresholds))) for _ in range(4))
    assert n >= 12


def test_flag_reason_names_parameter_value_median_and_score(thresholds):
    rng = np.random.default_rng(3)
    df, truth = gaussian_fleet(rng, lots=1, outliers={(0, 4, 0)}, shift_sd=30.0)
    lf = flag_lots(df, thresholds=thresholds)[0]
    robust = [f for f in lf.flags if f.kind == KIND_ROBUST]
    assert {f.unit for f in robust} == truth
    f = robust[0]
    x = df[(df.unit == f.unit) & (df.parameter == "k_g11")]["mean"].iloc[0]
    med = np.median(df[df.parameter == "k_g11"]["mean"])
    assert f.parameter == "k_g11" and f.value == pytest.approx(x)
    assert f.lot_median == pytest.approx(med)
    assert f.score > 20
    assert "gyro.k_g11" in f.reason and "lot median" in f.reason and "robust z" in f.reason
    out = apply_flags(df, [lf])
    row = out[(out.unit == f.unit) & (out.parameter == "k_g11")].iloc[0]
    assert bool(row.flagged) and "robust z" in row.flag_reason
    assert out["flagged"].sum() == len({(g.unit, g.parameter) for g in lf.flags})
    assert row.lot_median == pytest.approx(med)


def test_spread_flag_needs_enough_reps(thresholds):
    rng = np.random.default_rng(5)
    df, _ = gaussian_fleet(rng, lots=1)
    sel = (df.unit == "U00007") & (df.parameter == "w0_z")
    df.loc[sel, "std"] *= 10.0
    lf = flag_lots(df, thresholds=thresholds)[0]
    spread = [f for f in lf.flags if f.kind == KIND_SPREAD]
    assert [(f.unit, f.parameter) for f in spread] == [("U00007", "w0_z")]
    assert spread[0].score == pytest.approx(
        df.loc[sel, "std"].iloc[0] / np.median(df[df.parameter == "w0_z"]["std"])
    )
    df.loc[sel, "n_reps"] = 2  # a std from two reps says too little
    assert not [f for f in flag_lots(df, thresholds=thresholds)[0].flags if f.kind == KIND_SPREAD]


def test_toml_config_and_errors():
    cfg = config_from_toml("""
[outliers]
z_threshold = 4.0
family_alpha = 0
spread_factor = 5

[limits.gyro.k_g11]
min = 0.95
max = 1.05
""")
    assert cfg.z_threshold == 4.0 and cfg.family_alpha == 0.0 and cfg.spread_factor == 5.0
    assert cfg.limit_of("gyro", "k_g11").min == 0.95
    with pytest.raises(OutlierConfigError, match="not valid TOML"):
        config_from_toml("[outliers\n")
    with pytest.raises(OutlierConfigError, match="min 2.0 > max 1.0"):
        config_from_toml("[limits.gyro.k_g11]\nmin = 2.0\nmax = 1.0\n")
    with pytest.raises(OutlierConfigError, match="unknown key"):
        config_from_toml("[outliers]\nthreshold = 3\n")
