"""Shared helpers of the test suite: simulated units that several test modules fit, and the
manifest of a simulated fleet.

Test modules import these by name (``from conftest import paper_unit``) instead of from one
another, so a test module can be moved, renamed or deleted without breaking the others.
Everything here is seeded by the caller's generator or a seed argument.
"""

from __future__ import annotations

import json
import os
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
    ``tools.synthetic_store``, built once per test session (per worker): the report tests that
    read it only add report files to it."""
    from tools.synthetic_store import build_synthetic_store

    root = tmp_path_factory.mktemp("synthetic-store")
    return build_synthetic_store(root, n_units=12, n_outliers=2, n_failed=1, seed=7, nav_samples=3000)


@pytest.fixture(scope="session")
def thresholds() -> ThresholdTable:
    """The robust-z thresholds of the test session, each lot layout simulated once (as one
    nightly run does with its own table): pass it to ``flag_lots(..., thresholds=...)``."""
    return ThresholdTable()


# --- field units under hostile input (tests/test_hardening_field_corpus.py) --------------------
# The real MPU-6050 recording of Tedaldi et al. (shared/data/real/mpu6050_tedaldi/, 10,245
# samples at 100 Hz: ~0.4 s a fit). Each hostile unit of the lot below is a copy of it with one
# thing made hostile; H0 stays the good one.
REAL_FIELD_LOG = (
    Path(__file__).resolve().parents[1].parent
    / "shared"
    / "data"
    / "real"
    / "mpu6050_tedaldi"
    / "example_data_calibration.csv"
)
if not REAL_FIELD_LOG.is_file():
    REAL_FIELD_LOG = Path("/work/shared/data/real/mpu6050_tedaldi/example_data_calibration.csv")
FIELD_LOT_OPTIONS = {"accel_range": "2g", "gyro_range": "250dps"}
PASSWD_MARKERS = (b"root:x:0:0", b"/bin/bash", b"nologin")  # what /etc/passwd holds, never quoted


def _deep_json(depth: int) -> str:
    return '{"columns": ' + "[" * depth + "]" * depth + "}"


def _hostile_setups(outside: Path) -> dict:
    """unit -> (what is hostile, how it is made: f(field_dir), expected code or None for
    calibrated). ``outside``: a directory outside the dataset (link targets)."""
    text = REAL_FIELD_LOG.read_text()
    lines = text.splitlines()

    def options(doc):
        return lambda d: (d / "field.json").write_text(doc if isinstance(doc, str) else json.dumps(doc))

    def log(data: bytes | str):
        def make(d):
            (d / "log.csv").unlink()
            (d / "log.csv").write_bytes(data if isinstance(data, bytes) else data.encode())

        return make

    def link(target: Path, name: str = "log.csv"):
        def make(d):
            if name == "log.csv":
                (d / "log.csv").unlink()
            (d / name).symlink_to(target)

        return make

    def fifo(d):
        (d / "log.csv").unlink()
        os.mkfifo(d / "log.csv")

    def huge(d):
        with open(d / "log.csv", "r+b") as fh:
            fh.truncate(257 * 2**20)

    elsewhere = outside / "valid.csv"
    elsewhere.write_text(text)
    beyond = lines[:5] + [",".join(str(4 * int(v)) for v in ln.split(",")) for ln in lines[5:]]
    return {
        "H0": ("the good unit", lambda d: None, None),
        "H1": (
            "session_start 9999-12-31",
            options({"session_start": "9999-12-31T23:59:59Z"}),
            "E_BAD_METADATA",
        ),
        "H2": ("columns nested 20,000 deep (40 kB)", options(_deep_json(20_000)), "E_BAD_OPTION"),
        "H3": ("columns nested 100,000 deep (200 kB)", options(_deep_json(100_000)), "E_BAD_OPTION"),
        "H4": ("log.csv -> /etc/passwd", link(Path("/etc/passwd")), "E_BAD_PATH"),
        "H5": ("field.json -> /etc/passwd", link(Path("/etc/passwd"), "field.json"), "E_BAD_PATH"),
        "H6": ("log.csv -> a valid log outside the dataset", link(elsewhere), "E_BAD_PATH"),
        "H7": ("g_local -9.8", options({"g_local": -9.8}), "E_BAD_OPTION"),
        "H8": ("acc_scale 0", options({"acc_scale": 0}), "E_BAD_OPTION"),
        "H9": (
            "three axes mapped to one column",
            options({"columns": "ax=ax,ay=ax,az=ax,gx=gx,gy=gx,gz=gx"}),
            "E_BAD_OPTION",
        ),
        "H10": (
            "gyro_scale 1000 rad/s per count: a fit no sensor gives",
            options({"gyro_scale": 1000}),
            "E_IMPLAUSIBLE",
        ),
        "H11": ("log.csv a FIFO", fifo, "E_BAD_PATH"),
        "H12": ("log.csv -> /dev/zero", link(Path("/dev/zero")), "E_BAD_PATH"),
        "H13": ("binary garbage", log(np.random.default_rng(35).bytes(4096)), "E_UNREADABLE_FILE"),
        "H14": ("header only", log("\n".join(lines[:5]) + "\n"), "E_UNREADABLE_FILE"),
        "H15": ("CRLF line ends", log(text.replace("\n", "\r\n")), None),
        "H16": ("UTF-16", log(text.encode("utf-16")), "E_UNREADABLE_FILE"),
        "H17": (
            "constant data",
            log("\n".join(lines[:5] + [lines[5]] * 3000) + "\n"),
            "E_FIELD_TOO_FEW_POSES",
        ),
        "H18": (
            "values 4x beyond the int16 full scale",
            log("\n".join(beyond) + "\n"),
            "E_FIELD_TOO_FEW_POSES",
        ),
        "H19": ("window NaN (JSON's NaN literal)", options('{"window": NaN}'), "E_BAD_OPTION"),
        "H20": ("a 257 MiB log (sparse: never read)", huge, "E_UNREADABLE_FILE"),
    }


def make_hostile_field_lot(root: Path, outside: Path, units: list[str] | None = None) -> dict:
    """Lot F1 of copies of the real recording under ``root`` (lot options
    :data:`FIELD_LOT_OPTIONS`), each unit made hostile as :func:`_hostile_setups` says
    (``units``: only these). Returns unit -> (what, expected code)."""
    setups = _hostile_setups(outside)
    lot = root / "lot=F1"
    lot.mkdir(parents=True)
    (lot / "field.json").write_text(json.dumps(FIELD_LOT_OPTIONS))
    out = {}
    for u, (what, make, code) in setups.items():
        if units is not None and u not in units:
            continue
        d = lot / f"unit={u}" / "field"
        d.mkdir(parents=True)
        (d / "log.csv").write_bytes(REAL_FIELD_LOG.read_bytes())
        make(d)
        out[u] = (what, code)
    return out


@pytest.fixture(scope="session")
def hostile_field_night(tmp_path_factory):
    """One ``mimucal nightly`` over the hostile field lot (21 units, threads): the dataset,
    the results, the corpus, the exit code and stderr."""
    if not REAL_FIELD_LOG.is_file():
        pytest.skip(f"the real MPU-6050 recording is not at {REAL_FIELD_LOG}")
    import contextlib
    import io

    from flows import runtime

    runtime.ensure_environment()
    from flows.cli import main as cli_main

    base = tmp_path_factory.mktemp("hostile-field")
    data, results, outside = base / "data", base / "results", base / "outside"
    outside.mkdir()
    corpus = make_hostile_field_lot(data, outside)
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = cli_main(["nightly", str(data), "--results", str(results), "--runner", "threads", "--quiet"])
    return {"data": data, "results": results, "corpus": corpus, "rc": rc, "stderr": err.getvalue()}


# --- the order modules run in ---------------------------------------------------------------------
# `make test` runs `-n 2 --dist loadfile --no-loadscope-reorder`: each module goes whole to the
# next free worker, in collection order. The wall time is bounded by the module that starts
# last, so the modules expected to take longest go first (longest-processing-time first): a
# module's weight counts its tests that start a Prefect server, those marked slow, and the
# rest (rough costs in seconds; the order, not the numbers, matters).
_MODULE_WEIGHTS = {"server": 30.0, "slow": 10.0}


def pytest_collection_modifyitems(session, config, items):
    weight: dict[str, float] = {}
    for item in items:
        w = next((v for m, v in _MODULE_WEIGHTS.items() if item.get_closest_marker(m)), 0.5)
        weight[item.nodeid.split("::")[0]] = weight.get(item.nodeid.split("::")[0], 0.0) + w
    items.sort(key=lambda item: -weight[item.nodeid.split("::")[0]])  # stable: a module stays whole
