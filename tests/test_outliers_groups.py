"""flag_lots groups rows with numpy (pandas.factorize) instead of DataFrame.groupby: the
groups, their order and the order of rows within them must be groupby's."""

from __future__ import annotations

import numpy as np
import pandas as pd

from calib_core.outliers import _key_groups


def test_key_groups_are_those_of_groupby():
    rng = np.random.default_rng(7)
    n = 500
    model = rng.choice(["gyro", "accel", "accel_static", "b"], n).astype(object)
    param = rng.choice([f"k_{i}" for i in range(12)] + ["w0_x", "Z", "a"], n).astype(object)
    param[rng.choice(n, 5, replace=False)] = None  # a missing key: left out, as groupby does
    df = pd.DataFrame({"model": model, "parameter": param})
    expected = [(k, g.index.to_numpy()) for k, g in df.groupby(["model", "parameter"], sort=True)]
    got = _key_groups(model, param)
    assert [k for k, _ in got] == [k for k, _ in expected]
    for (_, a), (_, b) in zip(got, expected):
        np.testing.assert_array_equal(a, b)
    single = _key_groups(model)
    assert [k for k, _ in single] == [(m,) for m in sorted(set(model))]


def test_key_groups_of_nothing():
    assert _key_groups(np.array([], dtype=object)) == []
