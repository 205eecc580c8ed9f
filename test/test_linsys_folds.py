"""All cross-validation folds at once (LinearSystem.folds: the held-out components' Gram matrices computed once, taken
out of the information in one step) equal the folds made one by one (LinearSystem.fold, segment by segment), for
leave-one-group-out folds (whole segments held out) and folds over poses (segments split between training and
test), with free components, an undetermined segment and registration rows."""

from __future__ import annotations

import numpy as np
import pytest

from ppoe_core.analysis.diagnose.linsys import LinearSystem, NuisanceSet


def _system(rng: np.random.Generator) -> tuple[LinearSystem, np.ndarray]:
    """6 segments of 12 components (segment 5 has 1: its 3 nuisances undetermined) and 10 free components, 7
    columns; each segment's first half are registration rows; the group of each component (3 groups)."""
    seg = np.concatenate([np.repeat(np.arange(5), 12), [5], np.full(10, -1)])
    n, C, k = seg.size, 7, 3
    G, e, N = rng.normal(size=(n, C)), rng.normal(size=n), rng.normal(size=(n, k))
    in_seg = np.flatnonzero(seg >= 0)
    reg = np.ones(n, dtype=bool)
    reg[:60] = np.tile(np.arange(12) < 6, 5)
    group = np.concatenate([[0] * 24, [1] * 24, [2] * 12, [2], [0, 1, 2] * 3, [0]])
    unit = np.arange(n) // 2
    sys = LinearSystem(e, G, [slice(i, i + 1) for i in range(C)], unit, int(unit.max()) + 1, group, reg,
                       np.ones(n, dtype=bool), [NuisanceSet(in_seg, N[in_seg], seg[in_seg], 0, 6)])
    return sys, group


def _same(a, b) -> None:
    np.testing.assert_allclose(a.H, b.H, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(a.b, b.b, rtol=1e-10, atol=1e-10)
    assert a.ee == pytest.approx(b.ee, rel=1e-10)
    np.testing.assert_array_equal(a.idx, b.idx)
    np.testing.assert_allclose(a.e, b.e, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(a.G, b.G, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("by", ["groups", "poses"])
def test_all_folds_at_once_equal_the_folds_one_by_one(by: str) -> None:
    rng = np.random.default_rng(12)
    sys, group = _system(rng)
    comp_fold = group if by == "groups" else (sys.unit * 7) % 3
    one = [sys.fold(comp_fold != f) for f in range(3)]
    fresh, _ = _system(np.random.default_rng(12))  # its G^T G made from the folds' own Gram matrices
    both = fresh.folds(comp_fold, 3)
    for a, b in zip(one, both):
        _same(a, b)
    _same(sys.full(), fresh.full())
    assert any(f.idx.size < (comp_fold == k).sum() for k, f in enumerate(one))  # some rows only register


def test_the_condition_of_one_new_column_next_to_a_model_is_its_eigenvalue_ratio() -> None:
    """The identifiability condition number of one new column (closed form) equals the eigenvalue ratio of the
    scaled information ``[[I, R], [R^T, 1]]`` of an orthonormal basis of the model and the column; next to a
    one-column model it is ``(1 + |rho|) / (1 - |rho|)`` with ``rho`` the columns' correlation; two new columns
    (the eigenvalue path) agree with the same matrix."""
    from ppoe_core.analysis.diagnose.crossval import Linearised
    from ppoe_core.analysis.diagnose.terms import Term

    rng = np.random.default_rng(3)
    n, C = 60, 6
    G = rng.normal(size=(n, C)) * np.array([1.0, 1e3, 1e-2, 1.0, 5.0, 1.0])  # columns of very different sizes
    G[:, 5] = 0.98 * G[:, 0] / 1.0 + 0.2 * rng.normal(size=n)  # nearly the first column
    sys = LinearSystem(rng.normal(size=n), G, [slice(i, i + 1) for i in range(C)], np.arange(n), n,
                       np.zeros(n, dtype=int), np.ones(n, dtype=bool), np.ones(n, dtype=bool))
    lin = Linearised(sys, None, np.zeros(C), np.arange(n) % 3)  # type: ignore[arg-type]
    H = G.T @ G

    def reference(model: list[int], new: list[int]) -> float:
        Q, _ = np.linalg.qr(G[:, model] / np.linalg.norm(G[:, model], axis=0))
        N = G[:, new] / np.linalg.norm(G[:, new], axis=0)
        R = Q.T @ N
        r = len(model)
        M = np.block([[np.eye(r), R], [R.T, N.T @ N]])
        ev = np.linalg.eigvalsh(M)
        return float(ev[-1] / ev[0])

    rho = H[0, 5] / np.sqrt(H[0, 0] * H[5, 5])
    one = lin.identifiable([Term(0, (0,))], [Term(5, (0,))], 1e12, 1.0).condition
    assert one == pytest.approx((1 + abs(rho)) / (1 - abs(rho)), rel=1e-9)
    for model, new in (([0, 1, 2], [5]), ([1, 2, 3, 4], [5]), ([1, 2], [0, 5])):
        got = lin.identifiable([Term(c, (0,)) for c in model], [Term(c, (0,)) for c in new], 1e12, 1.0).condition
        assert got == pytest.approx(reference(model, new), rel=1e-7)
    # a new column whose reduced information rounded below zero (all of it absorbed) scales to a huge entry: the
    # closed form says "not identifiable" (inf) as the eigenvalues did, without overflowing
    H2 = sys.G.T @ sys.G
    H2[5, 5] = -1e-20
    lin.all.H[...] = H2
    assert lin._condition(np.array([0, 1]), np.array([5])) == np.inf
