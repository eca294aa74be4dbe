"""The threshold simulation's draws, each lot's block written into one array and medians
taken in place, give the same statistic to the bit as the plain loop (one (m, n) normal draw
per lot, copying medians) it replaced: the thresholds, and so the flags, do not change."""

from __future__ import annotations

import numpy as np
import pytest

from calib_core.outliers import MAD_TO_SIGMA, _simulated_zmax


def _plain_zmax(rng: np.random.Generator, m: int, sizes: tuple[int, ...]) -> np.ndarray:
    dev_parts = []
    for n in sizes:
        x = rng.normal(size=(m, n))
        dev_parts.append(x - np.median(x, axis=1, keepdims=True))
    dev = np.abs(np.concatenate(dev_parts, axis=1))
    scale = MAD_TO_SIGMA * np.median(dev, axis=1)
    return dev.max(axis=1) / np.where(scale > 0, scale, np.inf)


@pytest.mark.parametrize("sizes", [(3,), (50,), (10, 10), (5, 7, 7, 20), (4, 4, 9, 9, 9)])
def test_batched_draws_equal_the_plain_loop(sizes):
    seed = 1234 + sum(sizes)
    a = np.random.default_rng(seed)
    b = np.random.default_rng(seed)
    for m in (1, 257, 1000):  # successive chunks keep consuming the same stream
        np.testing.assert_array_equal(_simulated_zmax(a, m, sizes), _plain_zmax(b, m, sizes))
    assert a.random() == b.random()  # and leave it at the same place
