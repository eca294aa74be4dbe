"""Shortcuts of discovery's speed work (issue 32) against the work they skip.

- identifiability passes over a term only when its span is certainly apart from the others'
  (:func:`calib_core.discovery.identifiability._surely_apart`): never a term whose sine of
  the smallest principal angle, computed the plain way (a basis of the others, one SVD), is
  below the tolerance, and the sine it uses is that one; a term in the design's one exact
  dependency is confounded with the terms the plain examination names, at a sine of
  rounding noise either way;
- :func:`calib_core.linalg.pinv_solutions` (SVDs batched by shape) gives the covariance parts
  of :func:`calib_core.linalg.lstsq_pinv`, bit for bit;
- the held-out fits without terms take each fold's factor of the affine columns alone: the
  same gains as the fold's factor of every column, to rounding.
"""

from __future__ import annotations

import numpy as np

from calib_core.discovery import identifiability as ident
from calib_core.discovery.turntable import _Discovery
from calib_core.linalg import lstsq_pinv, pinv_solutions

from conftest import discovery_unit as _unit  # a simulated unit's sessions

TOL = ident.DEFAULT_TOL


def _plain_sine(spans: dict, name: str) -> float:
    others = np.hstack([q for n, q in spans.items() if n != name and q.shape[1]])
    cos = np.linalg.svd(spans[name].T @ ident.orthonormal_basis(others), compute_uv=False)
    return float(np.sqrt(max(1.0 - min(cos[0], 1.0) ** 2, 0.0)))


def _spans(rng, P: int = 40) -> dict:
    """Orthonormal spans of random terms, with an exactly collinear pair and pairs built at
    sines of 0.8, 1.1 and 1.3 x the tolerance (the other spans lower a term's sine further:
    both terms passed over and terms examined occur)."""

    def basis(A):
        return ident.orthonormal_basis(A)

    base = {f"t{i}": basis(rng.normal(size=(P, int(rng.integers(1, 5))))) for i in range(4)}
    d = rng.normal(size=P)
    base["exact_a"] = basis(np.column_stack([d, rng.normal(size=P)]))
    base["exact_b"] = basis(np.column_stack([-2.0 * d, rng.normal(size=P)]))
    for label, sine in (("under", 0.8 * TOL), ("over", 1.3 * TOL), ("margin", 1.1 * TOL)):
        u = rng.normal(size=P)
        e = rng.normal(size=P)
        e -= u * (u @ e) / (u @ u)
        v = u / np.linalg.norm(u) * np.sqrt(1.0 - sine**2) + e / np.linalg.norm(e) * sine
        base[f"{label}_a"] = basis(u[:, None])
        base[f"{label}_b"] = basis(np.column_stack([v, rng.normal(size=P)]))
    return base


def test_a_term_passed_over_is_never_confounded_and_its_sine_is_the_plain_one():
    rng = np.random.default_rng(7)
    passed = examined = 0
    for _ in range(30):
        spans = _spans(rng)
        apart, _ = ident._surely_apart(spans, TOL)
        for name in spans:
            sine = _plain_sine(spans, name)
            if name in apart:
                passed += 1
                assert sine >= TOL
            else:
                examined += 1
        # the pairs made confounded are never passed over
        assert not apart & {"exact_a", "exact_b", "under_a"}
    assert passed and examined


def test_analyse_finds_the_same_groups_with_and_without_the_shortcut(monkeypatch):
    rng = np.random.default_rng(11)
    for _ in range(10):
        spans = _spans(rng)
        terms = {n: q * rng.uniform(0.5, 2.0, size=q.shape[1]) for n, q in spans.items()}
        pnames = {n: tuple(f"p{k}" for k in range(q.shape[1])) for n, q in terms.items()}
        fast = ident.analyse(np.zeros((40, 0)), terms, pnames)
        monkeypatch.setattr(ident, "_surely_apart", lambda spans, tol: (set(), {}))
        full = ident.analyse(np.zeros((40, 0)), terms, pnames)
        monkeypatch.undo()
        assert (fast.undetermined, fast.rank) == (full.undetermined, full.rank)
        assert [c.terms for c in fast.confounded] == [c.terms for c in full.confounded]
        assert ("exact_a", "exact_b") in [c.terms for c in fast.confounded]
        for a, b in zip(fast.confounded, full.confounded):
            # the exactly collinear pair's sine is rounding noise by either route
            assert a.sin_angle == b.sin_angle or max(a.sin_angle, b.sin_angle) < 1e-7


def test_the_one_exact_dependency_names_the_terms_the_plain_examination_names():
    rng = np.random.default_rng(5)
    found = 0
    for _ in range(20):
        spans = _spans(rng)
        _, shared = ident._surely_apart(spans, TOL)
        assert set(shared) <= {"exact_a", "exact_b"}
        for name, (involved, sine) in shared.items():
            found += 1
            assert involved == ("exact_a", "exact_b")
            assert sine < 1e-12 and _plain_sine(spans, name) < 1e-7
    assert found


def test_batched_pinv_solutions_are_lstsq_pinvs():
    rng = np.random.default_rng(3)
    Zs = [rng.normal(size=(30, p)) for p in (3, 6, 3, 9, 6, 3)]
    Zs[1][:, 2] = 0.0  # a dead column
    Zs[3][:, 4] = Zs[3][:, 0]  # an undetermined direction
    for Z, sol in zip(Zs, pinv_solutions(Zs)):
        ref = lstsq_pinv(Z, np.zeros(len(Z)))[2]
        for field in ("Vt", "inv_s", "keep", "live", "scale"):
            np.testing.assert_array_equal(getattr(sol, field), getattr(ref, field))
        np.testing.assert_array_equal(sol.cov, ref.cov)


def test_the_affine_folds_give_the_full_folds_gains():
    d = _Discovery(_unit(5), 0.01)
    m = d.model
    _, KS = m.fold_factors()  # every column of each fold
    np.testing.assert_allclose(m.K_affine_folds, KS[..., -1], rtol=1e-10, atol=0.0)
