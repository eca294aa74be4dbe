"""Which effects a protocol can estimate and tell apart, before any data are fitted.

Model discovery adds catalogue terms to a base model. Whether the data can estimate a term,
and tell it from another, depends on the steps (and the noise weights), not on the unit:

- a parameter combination ``v`` of term T is **undetermined** when, once the base model is
  projected out, T's columns leave almost nothing of it: ``||P Z_T v|| < tol ||Z_T v||``
  (``P`` projects on the complement of the base model's columns);
- term T is **confounded** with other terms when some determined combination of T's columns
  lies, up to the base model, in the span of theirs: the smallest principal angle between
  ``span(P Z_T)`` and ``span(P Z_others)`` has ``sin < tol``. The terms named are those that
  carry that direction, so a pair (vertical Earth rate vs a diagonal g-sensitivity) and a
  combination of several terms are both found.

``tol`` (default 0.05: the part of a column not explained by the others is below 5 % of its
size) is a statement about the design, not about the noise: an effect confounded at 5 %
needs a signal 20x the noise to show its own part at 1 sigma.

:func:`separating_additions` answers "which steps would separate them": it adds each
candidate step set of a library to the protocol and keeps those after which the group is
no longer confounded or undetermined. Everything here is linear algebra on given matrices;
the caller builds the columns (:mod:`calib_core.discovery` for a unit, ``mimucal plan`` for a
steps table).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from calib_core.linalg import lstsq_min_norm

DEFAULT_TOL = 0.05
# pairs whose own parts are below this (but above DEFAULT_TOL) are *near-confounded*: the
# design still separates them, but an effect must be several times the noise before the
# data can: an effect of 10 sigma shows its own part at under 1.5 sigma. Discovery lets the
# data decide such a pair (each tested given the other), :func:`near_confounded`
NEAR_TOL = 0.15


@dataclass(frozen=True)
class Undetermined:
    """A parameter combination of one term that the design cannot see."""

    term: str
    params: tuple[str, ...]  # the parameters the combination involves (largest weights)
    combination: tuple[float, ...]  # the unit direction over ``params``
    left: float  # ||P Z v|| / ||Z v||: what is left once the base model is projected out

    def describe(self) -> str:
        if len(self.params) == 1:
            return f"{self.term}.{self.params[0]}"
        return f"{self.term}: a combination of {', '.join(self.params)}"


@dataclass(frozen=True)
class Confounded:
    """Terms with a common direction once the base model is projected out."""

    terms: tuple[str, ...]
    sin_angle: float  # sine of the smallest principal angle between their spans

    def describe(self) -> str:
        return f"confounded: {', '.join(self.terms)} (sin of angle {self.sin_angle:.2g})"


@dataclass(frozen=True)
class Identifiability:
    terms: tuple[str, ...]
    undetermined: tuple[Undetermined, ...]
    confounded: tuple[Confounded, ...]
    rank: Mapping[str, int]  # determined parameter directions per term
    n_params: Mapping[str, int]
    tol: float = DEFAULT_TOL

    def identifiable(self, term: str) -> bool:
        """Every parameter of ``term`` determined and no direction shared with another term."""
        return self.rank[term] == self.n_params[term] and not any(term in c.terms for c in self.confounded)

    def groups(self) -> list[tuple[str, ...]]:
        """Test groups: confounded terms together (union of overlapping sets), others alone."""
        parent = {t: t for t in self.terms}

        def find(t: str) -> str:
            while parent[t] != t:
                parent[t] = parent[parent[t]]
                t = parent[t]
            return t

        for c in self.confounded:
            for other in c.terms[1:]:
                parent[find(other)] = find(c.terms[0])
        out: dict[str, list[str]] = {}
        for t in self.terms:
            out.setdefault(find(t), []).append(t)
        return [tuple(sorted(g)) for g in out.values()]

    def to_dict(self) -> dict:
        return {
            "tol": self.tol,
            "rank": dict(self.rank),
            "n_params": dict(self.n_params),
            "undetermined": [
                {
                    "term": u.term,
                    "params": list(u.params),
                    "combination": [round(x, 4) for x in u.combination],
                    "left": u.left,
                }
                for u in self.undetermined
            ],
            "confounded": [{"terms": list(c.terms), "sin_angle": c.sin_angle} for c in self.confounded],
        }


def orthonormal_basis(A: np.ndarray, rcond: float = 1e-10) -> np.ndarray:
    """Orthonormal columns spanning the columns of ``A`` (singular values above ``rcond``
    of the largest)."""
    if A.size == 0:
        return np.zeros((A.shape[0], 0))
    u, s, _ = np.linalg.svd(A, full_matrices=False)
    return _basis(u, s, rcond)


def _basis(u: np.ndarray, s: np.ndarray, rcond: float = 1e-10) -> np.ndarray:
    """The left singular vectors of an SVD whose singular values are above ``rcond`` of the
    largest (:func:`orthonormal_basis`)."""
    return u[:, s > rcond * max(s.max(initial=0.0), 1e-300)]


def svd_by_shape(
    mats: Mapping[str, np.ndarray], full_matrices: Callable[[tuple[int, ...]], bool] | bool = False
) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``np.linalg.svd`` of each matrix, one batched call per distinct shape (the same
    numbers as one call each); ``full_matrices`` may depend on the shape."""
    by_shape: dict[tuple[int, ...], list[str]] = {}
    for name, A in mats.items():
        by_shape.setdefault(A.shape, []).append(name)
    out = {}
    for shape, group in by_shape.items():
        full = full_matrices(shape) if callable(full_matrices) else full_matrices
        u, s, vt = np.linalg.svd(np.array([mats[n] for n in group]), full_matrices=full)
        for j, name in enumerate(group):
            out[name] = (u[j], s[j], vt[j])
    return out


def orthonormal_bases_by_shape(mats: Mapping[str, np.ndarray], rcond: float = 1e-10) -> dict[str, np.ndarray]:
    """:func:`orthonormal_basis` of each matrix, one batched SVD per distinct shape."""
    out = {}
    for name, (u, s, _) in svd_by_shape(mats).items():
        out[name] = _basis(u, s, rcond)
    return out


def analyse(
    base: np.ndarray,
    terms: Mapping[str, np.ndarray],
    param_names: Mapping[str, tuple[str, ...]],
    tol: float = DEFAULT_TOL,
    svds: Mapping[str, tuple[np.ndarray, np.ndarray]] | None = None,
) -> Identifiability:
    """Identifiability of each term's columns (``terms[name]``, (N, p)) against the base
    model's columns ``base`` (N, q) and against each other. Rows must already carry the noise
    weights the fit would use (1/sigma), so that every row counts as the fit counts it.
    ``svds``: (s, Vt) of ``np.linalg.svd`` of a term's columns each divided by its (nonzero)
    norm, ``full_matrices=False``, N >= p, when the caller has it (not computed again)."""
    Qb = orthonormal_basis(np.asarray(base, float))
    names = tuple(terms)
    undetermined: list[Undetermined] = []
    spans: dict[str, np.ndarray] = {}
    rank: dict[str, int] = {}
    # every term's three factorisations, each one batched call per distinct shape
    Zn: dict[str, np.ndarray] = {}
    for name in names:
        Z = np.asarray(terms[name], float)
        norms = np.linalg.norm(Z, axis=0)
        Zn[name] = Z / np.where(norms > 0, norms, 1.0)  # scale-free: columns of unit length
    # directions of parameter space: first those Z itself cannot see (zero or collinear
    # columns), then, within its range, the ratio ||P Z v|| / ||Z v|| (singular values of
    # P Z W with W mapping unit vectors of Z's range back to parameters); every right
    # singular vector of Z (p of them), the left ones only as many as needed
    known = {n: v for n, v in (svds or {}).items() if n in terms}
    svd_z = svd_by_shape(
        {n: z for n, z in Zn.items() if n not in known}, full_matrices=lambda shape: shape[0] < shape[1]
    )
    svd_z.update({n: (None, s, vt) for n, (s, vt) in known.items()})
    W: dict[str, np.ndarray] = {}
    X: dict[str, np.ndarray] = {}
    blind: dict[str, list] = {}
    for name in names:
        _, sz, vzt = svd_z[name]
        sz = np.concatenate([sz, np.zeros(Zn[name].shape[1] - len(sz))])
        inrange = sz > 1e-8 * max(sz.max(initial=0.0), 1e-300)
        W[name] = vzt[inrange].T / sz[inrange]
        X[name] = (Zn[name] - Qb @ (Qb.T @ Zn[name]) if Qb.shape[1] else Zn[name]) @ W[name]
        blind[name] = [(v, 0.0) for v in vzt[~inrange]]
    svd_x = svd_by_shape({n: x for n, x in X.items() if x.shape[1]})
    # each term's determined directions in the data space: the left singular vectors of X
    # whose ratio passes tol (an orthonormal basis of X's columns along its determined
    # directions; those ratios are at most 1, so no rank cut drops any of them)
    for name in names:
        spans[name] = np.zeros((len(Zn[name]), 0))
        if name in svd_x:
            ux, sig, at = svd_x[name]
            w = W[name]
            weak = [(w @ a / np.linalg.norm(w @ a), float(r)) for a, r in zip(at, sig) if r < tol]
            if (sig >= tol).any():
                spans[name] = ux[:, sig >= tol]
        else:
            weak = []
        for v, left in blind[name] + weak:
            order = np.argsort(-np.abs(v))
            big = [int(i) for i in order if abs(v[i]) >= 0.2] or [int(order[0])]
            undetermined.append(
                Undetermined(
                    name, tuple(param_names[name][i] for i in big), tuple(float(v[i]) for i in big), left
                )
            )
    for name in names:
        rank[name] = spans[name].shape[1]
    confounded: list[Confounded] = []
    seen: set[tuple[str, ...]] = set()
    apart, shared = _surely_apart(spans, tol)
    for name in names:
        Q = spans[name]
        others = [o for o in names if o != name and spans[o].shape[1]]
        if name in shared:  # in the design's one exact dependency: no SVD of the others
            involved, sin = shared[name]
            if len(involved) > 1 and involved not in seen:
                seen.add(involved)
                confounded.append(Confounded(involved, sin))
            continue
        if not Q.shape[1] or not others or name in apart:
            continue
        H = np.hstack([spans[o] for o in others])
        svd_h = np.linalg.svd(H, full_matrices=False)  # its basis and, below, the least squares on it
        Qo = _basis(svd_h[0], svd_h[1])
        if not Qo.shape[1]:
            continue
        u, cos, _ = np.linalg.svd(Q.T @ Qo, full_matrices=False)
        cmax = float(min(cos[0], 1.0))
        sin = float(np.sqrt(max(1.0 - cmax * cmax, 0.0)))
        if sin >= tol:
            continue
        # the shared direction, in the data space, written in the others' own columns: the
        # terms that carry it are those with a real part of it (not a chance projection)
        y = Q @ u[:, 0]
        coef = lstsq_min_norm(H, y, svd=svd_h)[0]
        share, at = {}, 0
        for o in others:
            k = spans[o].shape[1]
            share[o] = float(np.linalg.norm(spans[o] @ coef[at : at + k]))
            at += k
        involved = tuple(sorted({name, *[o for o, w in share.items() if w > 0.1]}))
        if len(involved) > 1 and involved not in seen:
            seen.add(involved)
            confounded.append(Confounded(involved, sin))
    return Identifiability(
        names,
        tuple(undetermined),
        tuple(confounded),
        rank,
        {n: int(np.asarray(terms[n]).shape[1]) for n in names},
        tol,
    )


# _surely_apart: the stacked spans' singular values must each be either below _NULL_RTOL of
# the largest (an exact dependency among the columns, which orthonormal_basis's rank cut of
# 1e-10 drops too) or above _REGULAR_RTOL (well determined: the sines below come out to
# ~1e-8 relative or better); a term's sine must exceed tol by _APART_MARGIN to be passed over
_NULL_RTOL = 1e-12
_REGULAR_RTOL = 1e-4
_APART_MARGIN = 1.1


def _surely_apart(
    spans: Mapping[str, np.ndarray], tol: float
) -> tuple[set[str], dict[str, tuple[tuple[str, ...], float]]]:
    """Terms whose span is certainly not confounded with the others' (sine of the smallest
    principal angle at least ``_APART_MARGIN`` x ``tol``), from one SVD of every span
    stacked: with S = [Q_1 .. Q_m] (orthonormal blocks) and G = S^T S, the block of G^-1 of
    term i is (I - Q_i^T P_others Q_i)^-1, whose largest eigenvalue is 1 / sin^2 of that
    angle. Exact dependencies among the others' columns (a confounded pair) are set to
    unit weight in G: P_others is the same, the dependency adding no direction. A term
    that takes part in such a dependency, or a design with singular values between the
    exact and the well-determined ones, is left to :func:`analyse`, which examines every
    term not returned as before.

    Second, when the design has exactly one such dependency, S w = 0 (w unit, parts w_i):
    for each term i with a part in it, what :func:`analyse`'s examination finds, the terms
    confounded with it and the sine. The shared direction is y = Q_i w_i / |w_i| =
    -sum_o Q_o w_o / |w_i|; the others' columns have no dependency left, so y written in
    their columns is that sum, and term o carries |w_o| / |w_i| of it. Its sine is below
    |S w| / |w_i| (the dependency's singular value over the part: rounding noise, as is
    the sine :func:`analyse` computes from a cosine of 1 to rounding); every other
    direction of the design is well determined, so the shared direction is the only one
    with a sine that small."""
    blocks = [(n, q) for n, q in spans.items() if q.shape[1]]
    if len(blocks) < 2:
        return set(), {}
    S = np.hstack([q for _, q in blocks])
    _, s, Wt = np.linalg.svd(S, full_matrices=True)
    s = np.concatenate([s, np.zeros(S.shape[1] - len(s))])
    null = s <= _NULL_RTOL * s[0]
    if not (s[0] > 0 and np.all(null | (s > _REGULAR_RTOL * s[0]))):
        return set(), {}
    Ginv = (Wt.T * np.where(null, 1.0, 1.0 / np.where(null, 1.0, s) ** 2)) @ Wt
    Wn = Wt[null]
    out, parts, at = set(), {}, 0
    in_dependency = []
    for name, q in blocks:
        k = q.shape[1]
        part = slice(at, at + k)
        parts[name] = part
        at += k
        if Wn.size and np.abs(Wn[:, part]).max() > 1e-6:
            in_dependency.append(name)
            continue  # in an exact dependency: confounded
        top = float(np.linalg.eigvalsh(Ginv[part, part])[-1])
        if top > 0 and 1.0 / np.sqrt(top) >= _APART_MARGIN * tol:
            out.add(name)
    shared = {}
    if len(Wn) == 1:
        w = Wn[0]
        size = {name: float(np.linalg.norm(w[part])) for name, part in parts.items()}
        for name in in_dependency:
            carried = {o for o in parts if o != name and size[o] > 0.1 * size[name]}
            shared[name] = (tuple(sorted({name, *carried})), float(s[null][0]) / size[name])
    return out, shared


def near_confounded(
    terms: Mapping[str, np.ndarray], tol: float = DEFAULT_TOL, near_tol: float = NEAR_TOL
) -> tuple[Confounded, ...]:
    """Pairs of terms whose columns (``terms[name]``, (N, p), the base model already
    projected out and the noise weights applied) are near-collinear: the sine of the
    smallest principal angle between their spans is in ``[tol, near_tol)``. Below ``tol``
    they are confounded (:func:`analyse`); above ``near_tol`` each has a part of its own
    large enough to be tested apart. E.g. a bias drift in temperature and one in time on a
    warm-up nearly linear in time over the session (sine about 0.04-0.09)."""
    spans = {}
    for name, Z in terms.items():
        Z = np.asarray(Z, float)
        norms = np.linalg.norm(Z, axis=0)
        if Z.size and (norms > 0).any():
            spans[name] = orthonormal_basis(Z[:, norms > 0] / norms[norms > 0])
    names = sorted(n for n, q in spans.items() if q.shape[1])
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            cos = np.linalg.svd(spans[a].T @ spans[b], compute_uv=False)
            c = float(min(cos[0], 1.0)) if cos.size else 0.0
            sin = float(np.sqrt(max(1.0 - c * c, 0.0)))
            if tol <= sin < near_tol:
                out.append(Confounded((a, b), sin))
    return tuple(out)


@dataclass(frozen=True)
class Advice:
    """For one confounded set or undetermined term: the step sets that would resolve it."""

    issue: str  # e.g. "confounded: earth_rate, gyro_g_sensitivity"
    terms: tuple[str, ...]
    separated_by: tuple[str, ...] = field(default_factory=tuple)

    def describe(self) -> str:
        if not self.separated_by:
            return f"{self.issue}: no step set of the library separates it"
        return f"{self.issue}: add {' or '.join(self.separated_by)}"


def separating_additions(
    analyse_protocol: Callable[[object], Identifiability],
    protocol,
    library: Mapping[str, Callable[[object], object]],
) -> list[Advice]:
    """For each confounded set and each term with undetermined parameters of ``protocol``,
    the labels of ``library`` (label -> function adding steps to a protocol) after whose
    addition it is resolved (no longer confounded, every parameter determined)."""
    base = analyse_protocol(protocol)
    issues: list[tuple[str, tuple[str, ...], Callable[[Identifiability], bool]]] = []
    for c in base.confounded:
        issues.append(
            (
                c.describe(),
                c.terms,
                lambda ident, c=c: (
                    not any(
                        set(c.terms) <= set(d.terms) or set(d.terms) <= set(c.terms) for d in ident.confounded
                    )
                ),
            )
        )
    for term in sorted({u.term for u in base.undetermined}):
        params = sorted({p for u in base.undetermined if u.term == term for p in u.params})
        issues.append(
            (
                f"undetermined: {term} ({', '.join(params)})",
                (term,),
                lambda ident, term=term: ident.rank[term] == ident.n_params[term],
            )
        )
    if not issues:
        return []
    extended = {label: analyse_protocol(add(protocol)) for label, add in library.items()}
    return [
        Advice(text, terms, tuple(label for label, ident in extended.items() if ok(ident)))
        for text, terms, ok in issues
    ]
