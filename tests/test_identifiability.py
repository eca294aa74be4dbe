"""calib_core.discovery.identifiability on designs whose answer is known by construction: collinear
columns, a combination of several terms, dead columns, and the lever arm of a protocol with
and without the tilted dynamic steps (columns written here from w x (w x r), not from the
catalogue's term code)."""

from __future__ import annotations

import numpy as np

from calib_core.discovery.identifiability import analyse, separating_additions
from calib_core.sim.protocols import dynamic_steps, to_frame

NAMES = {"A": ("a1", "a2"), "B": ("b1", "b2"), "C": ("c1", "c2"), "D": ("d1",)}


def _base(rng, n=300):
    return rng.normal(size=(n, 3))


def test_pair_confounded_up_to_the_base_model():
    rng = np.random.default_rng(0)
    base = _base(rng)
    A = rng.normal(size=(300, 2))
    # B's first column is A's first plus a base column: the same once the base is out
    B = np.c_[2.0 * A[:, 0] + base[:, 0], rng.normal(size=300)]
    C = rng.normal(size=(300, 2))
    r = analyse(base, {"A": A, "B": B, "C": C}, NAMES)
    assert [c.terms for c in r.confounded] == [("A", "B")]
    assert sorted(r.groups()) == [("A", "B"), ("C",)]
    assert r.rank == {"A": 2, "B": 2, "C": 2}
    assert not r.identifiable("A") and r.identifiable("C")


def test_combination_of_several_terms_and_threshold():
    rng = np.random.default_rng(1)
    base = _base(rng)
    A, C = rng.normal(size=(300, 1)), rng.normal(size=(300, 1))
    for noise, expect in ((1e-3, True), (0.5, False)):
        D = (A[:, 0] + C[:, 0] + noise * rng.normal(size=300))[:, None]
        r = analyse(base, {"A": A, "C": C, "D": D}, {"A": ("a",), "C": ("c",), "D": ("d",)})
        got = [c.terms for c in r.confounded]
        assert (got == [("A", "C", "D")]) is expect, got
        # pairwise none of them is collinear: only the combination is
        assert all(len(g) in (1, 3) for g in r.groups())


def test_dead_and_base_collinear_columns_are_undetermined():
    rng = np.random.default_rng(2)
    base = _base(rng)
    C = np.c_[rng.normal(size=300), np.zeros(300)]
    D = base[:, [1]] * 3.0
    r = analyse(base, {"C": C, "D": D}, {"C": ("c1", "c2"), "D": ("d1",)})
    assert sorted(u.describe() for u in r.undetermined) == ["C.c2", "D.d1"]
    assert r.rank == {"C": 1, "D": 0}


def _lever_arm_design(steps):
    """Rows: (dynamic step, accelerometer i); base: a bias and the reference f_i per
    accelerometer; term columns: the centripetal acceleration w x (w x r_i) along axis i."""
    w = np.radians(steps[["w_ref_x", "w_ref_y", "w_ref_z"]].to_numpy(float))
    f = steps[["f_ref_x", "f_ref_y", "f_ref_z"]].to_numpy(float)
    n = len(w)
    rows_base, rows_term = [], []
    for i in range(3):
        for k in range(n):
            wk = w[k]
            # (w x (w x r))_i = w_i (w . r) - |w|^2 r_i, linear in r
            m = wk[i] * wk - (wk @ wk) * np.eye(3)[i]
            b = np.zeros(3 * 4)
            b[4 * i : 4 * i + 4] = [1.0, *f[k]]
            t = np.zeros(9)
            t[3 * i : 3 * i + 3] = m
            rows_base.append(b)
            rows_term.append(t)
    return np.array(rows_base), np.array(rows_term)


LEVER = tuple(f"r{i}{c}" for i in (1, 2, 3) for c in "xyz")


def _lever(steps):
    base, term = _lever_arm_design(steps)
    return analyse(base, {"lever_arm": term}, {"lever_arm": LEVER})


def test_lever_arm_needs_the_tilted_steps():
    flat = to_frame(dynamic_steps(tilted=False))
    tilted = to_frame(dynamic_steps(tilted=True))
    r = _lever(flat)
    assert r.rank["lever_arm"] == 3
    # accelerometer i sees only its own component along its own axis: the other six are blind
    assert sorted(p for u in r.undetermined for p in u.params) == sorted(set(LEVER) - {"r1x", "r2y", "r3z"})
    assert _lever(tilted).rank["lever_arm"] == 9


def test_advisor_finds_the_steps_that_separate():
    flat = to_frame(dynamic_steps(tilted=False))
    library = {
        "dynamic steps on the 45-degree diagonals": lambda p: to_frame(
            p.drop(columns="step").to_dict("records") + dynamic_steps(rates=(), tilted=True)
        ),
        "more rates about the principal axes": lambda p: to_frame(
            p.drop(columns="step").to_dict("records") + dynamic_steps(rates=(300,), tilted=False)
        ),
    }
    advice = separating_additions(_lever, flat, library)
    assert len(advice) == 1 and advice[0].terms == ("lever_arm",)
    assert advice[0].separated_by == ("dynamic steps on the 45-degree diagonals",)
