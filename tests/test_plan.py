"""`mimucal plan`: what a protocol can identify, checked against the design's rank computed
here independently (generalised eigenvalues of the projected and the raw Gram matrices of
each term's columns), and the advisor on the protocol where the Earth rate and an isotropic
g-sensitivity are one column."""

from __future__ import annotations

import re

import numpy as np
import pyarrow.parquet as pq
import pytest
from scipy import linalg

from calib_core.discovery.plan import NOMINAL_SIGMA, step_context
from calib_core.effects import catalogue, get_effect
from calib_core.sim import protocols
from flows.cli import main
from schemas.writer import steps_table

PROTOCOLS = {
    "default": protocols.default_session(),
    "no_tilted": protocols.to_frame(
        protocols.xu2016_multirate()
        + protocols.xu2016_multiposition()
        + protocols.dynamic_steps(tilted=False)
    ),
    "static_only": protocols.to_frame(protocols.xu2016_multiposition() + protocols.zhang2017_six_position()),
}


def independent_rank(steps, name: str, tol: float = 0.05) -> tuple[int, int]:
    """(determined directions, excited parameters) of one term: per channel the weighted
    affine base [ref, 1] is projected out of the term's columns; a direction v counts when
    ||P Z v|| / ||Z v|| >= tol, i.e. a generalised eigenvalue of (Z'PZ, Z'Z) >= tol^2."""
    ctx = step_context(steps)
    E = get_effect(name).regressors(ctx)  # (n, 6, p)
    n = len(ctx)
    rows_Z, rows_PZ = [], []
    for c in range(6):
        ref = ctx.w if c < 3 else ctx.f
        B = np.column_stack([ref, np.ones(n)]) / NOMINAL_SIGMA[c]
        Z = E[:, c, :] / NOMINAL_SIGMA[c]
        coef, *_ = np.linalg.lstsq(B, Z, rcond=None)
        rows_Z.append(Z)
        rows_PZ.append(Z - B @ coef)
    Z, PZ = np.vstack(rows_Z), np.vstack(rows_PZ)
    norms = np.linalg.norm(Z, axis=0)
    live = norms > 1e-9 * norms.max()  # whole turns average a horizontal vector to ~1e-16
    Z, PZ = Z[:, live], PZ[:, live]
    Z = Z / np.linalg.norm(Z, axis=0)
    PZ = PZ / np.linalg.norm(np.vstack(rows_Z)[:, live], axis=0)
    lam = linalg.eigh(PZ.T @ PZ, Z.T @ Z, eigvals_only=True)
    return int(np.sum(lam >= tol**2)), int(live.sum())


def plan_output(tmp_path, steps, capsys, *extra) -> str:
    path = tmp_path / "steps.parquet"
    pq.write_table(steps_table(steps), path)
    assert main(["plan", str(path), *extra]) == 0
    return capsys.readouterr().out


@pytest.mark.slow
@pytest.mark.parametrize("which", sorted(PROTOCOLS))
def test_plan_reports_each_terms_rank_as_the_design_has_it(which, tmp_path, capsys):
    out = plan_output(tmp_path, PROTOCOLS[which], capsys)
    reported = {}
    for m in re.finditer(r"^  (\w+): (?:NOT )?identifiable, (\d+) of (\d+) parameter", out, re.M):
        reported[m.group(1)] = (int(m.group(2)), int(m.group(3)))
    for m in re.finditer(r"^  (\w+): not excited \(", out, re.M):
        reported[m.group(1)] = (0, 0)
    assert set(reported) == set(catalogue())
    for name in catalogue():
        assert reported[name] == independent_rank(PROTOCOLS[which], name), (which, name)


@pytest.mark.slow
def test_plan_lever_arm_and_static_facts(tmp_path, capsys):
    out = plan_output(tmp_path, PROTOCOLS["no_tilted"], capsys)
    # principal axes up only: each accelerometer sees its own arm component alone
    assert (
        "lever_arm: identifiable, 3 of 3 parameter directions determined; not excited: "
        "r1y, r1z, r2x, r2z, r3x, r3y" in out
    )
    out = plan_output(tmp_path, PROTOCOLS["static_only"], capsys)
    for name in ("gyro_scale_asymmetry", "gyro_scale_nonlinearity", "lever_arm"):
        assert f"  {name}: not excited" in out


@pytest.mark.slow
def test_plan_whole_turns_confound_earth_rate_and_says_what_separates_them(tmp_path, capsys):
    out = plan_output(tmp_path, protocols.whole_turn_session(), capsys)
    assert re.search(
        r"confounded: earth_rate, gyro_g_sensitivity \(sin of angle [0-9.e-]+\): "
        r"cannot be told apart",
        out,
    )
    line = next(
        ln
        for ln in out.splitlines()
        if ln.startswith("  to resolve confounded: earth_rate, gyro_g_sensitivity")
    )
    assert "stationary steps at two headings" in line
    # with stationary steps at two headings added, each has a direction of its own
    two = protocols.extended(protocols.whole_turn_session(), protocols.two_heading_stationary())
    out = plan_output(tmp_path, two, capsys)
    assert re.search(r"confounded: earth_rate, gyro_g_sensitivity .*each has one of its own", out)
    assert "to resolve confounded: earth_rate" not in out


def test_plan_reads_csv_and_rejects_bad_steps(tmp_path, capsys):
    path = tmp_path / "steps.csv"
    protocols.zhang2017_session(duration_s=3.0).to_csv(path, index=False)
    assert main(["plan", str(path)]) == 0
    assert "steps; base model" in capsys.readouterr().out
    bad = protocols.zhang2017_session().assign(test="nonsense")
    bad.to_csv(path, index=False)
    assert main(["plan", str(path)]) != 0
    assert "nonsense" in capsys.readouterr().err
