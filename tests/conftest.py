"""Shared helpers of the test suite: simulated units that several test modules fit, and the
manifest of a simulated fleet.

Test modules import these by name (``from conftest import paper_unit``) instead of from one
another, so a test module can be moved, renamed or deleted without breaking the others.
Everything here is seeded by the caller's generator or a seed argument.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calib_core.models.zhang2017 import C_from_angles
from calib_core.outliers import ThresholdTable
from calib_core.sim import protocols, simulator
from calib_core.sim.accel_unit import AccelUnitTruth
from calib_core.steps import SessionKey, StepMeans

# Zhang et al. 2017: the published installation angles theta_ij (deg) of the paper's unit
PAPER_ANGLES = np.array(
    [[0.75997, 90.71425, 89.74038], [89.25516, 0.74486, 90.5630], [90.52202, 89.17706, 0.97456]]
)
# the accelerometer noise and bias instability used to simulate the paper's unit
PAPER_NOISE = dict(accel_noise_g=1e-3, accel_bias_instability_g=1e-5)

# the default turntable protocol with its verification sweep
STEPS_WITH_VERIFICATION = protocols.default_session(verification=True)


def random_unit(rng, tilt_deg=1.0, lever_mm=8.0) -> AccelUnitTruth:
    """Scale ~0.4 V/g, bias ~2.4 V, each sensitive axis tilted by up to ``tilt_deg``."""
    c = np.eye(3) + rng.normal(0, np.radians(tilt_deg) / 2, (3, 3)) * (1 - np.eye(3))
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    r = -lever_mm * np.eye(3) + rng.normal(0, 1.5, (3, 3)) * (1 - np.eye(3))
    return AccelUnitTruth(
        scale=rng.uniform(0.38, 0.42, 3), bias=rng.uniform(2.3, 2.5, 3), C=c.T, lever_arm_mm=r, unit="V"
    )


def paper_unit() -> AccelUnitTruth:
    """The unit of Zhang et al. 2017: its published scales, biases, angles and lever arms."""
    return AccelUnitTruth(
        scale=np.array([0.39496, 0.39808, 0.40024]),
        bias=np.array([2.405098, 2.380978, 2.435503]),
        C=C_from_angles(PAPER_ANGLES),
        lever_arm_mm=np.array([[-8.34, -0.42, -1.32], [-2.56, -8.93, -0.26], [-0.60, -0.50, -8.24]]),
    )


def unit_step_means(n: int = 5, seed: int = 7, steps=STEPS_WITH_VERIFICATION, **truth_kw) -> list[StepMeans]:
    """Step means of ``n`` repetitions of one simulated unit (``simulator.typical_truth``)."""
    rng = np.random.default_rng(seed)
    truth = simulator.typical_truth(rng, **truth_kw)
    return [
        simulator.simulate_step_means(truth, steps, rng, key=SessionKey("L1", "U1", r))
        for r in range(1, n + 1)
    ]


def discovery_unit(seed: int, n_reps: int = 3, unit: str = "U000") -> list[StepMeans]:
    """A typical unit with realistic noise on the default protocol, ``n_reps`` repetitions
    from the fast simulator (seeded): what the discovery engine's bookkeeping tests take."""
    rng = np.random.default_rng(seed)
    truth = simulator.typical_truth(rng, **simulator.REALISTIC_NOISE)
    sessions, _ = simulator.simulate_unit(truth, protocols.default_session(), rng, n_reps, unit=unit)
    return sessions


def load_manifest(fleet_dir: Path | str) -> dict:
    """The truth ``flows.fleet_sim.simulate_fleet`` wrote beside a simulated fleet."""
    # imported here: pytest imports this file before the test modules that set up the flows'
    # environment (flows.runtime) before importing flows
    from flows.fleet_sim import MANIFEST

    return json.loads((Path(fleet_dir) / MANIFEST).read_text())


@pytest.fixture(scope="session")
def synthetic_store(tmp_path_factory):
    """The 12-unit synthetic lot (2 outlier units, 1 failed session, seed 7) of
    ``reports.synthetic``, built once per test session (per worker): the report tests that
    read it only add report files to it."""
    from reports.synthetic import build_synthetic_store

    root = tmp_path_factory.mktemp("synthetic-store")
    return build_synthetic_store(root, n_units=12, n_outliers=2, n_failed=1, seed=7, nav_samples=3000)


@pytest.fixture(scope="session")
def thresholds() -> ThresholdTable:
    """The robust-z thresholds of the test session, each lot layout simulated once (as one
    nightly run does with its own table): pass it to ``flag_lots(..., thresholds=...)``."""
    return ThresholdTable()
