"""The stacked, whitened linear system of all blocks, its nuisances eliminated, and its cross-validation folds.

At the linearisation point (the current model), every residual component ``i`` of every block is
``e_i - G_i dtheta - N_i dnu_s(i)`` (whitened), with ``G`` the columns of *all* candidate effects and ``N`` the
nuisance columns of the component's segment (a tracker session's registration, ...).  The nuisances are
eliminated exactly per segment (Schur complement): with ``A_s = N_s^T N_s``, ``M_s = N_s^T G_s``, ``g_s = N_s^T e_s``
the reduced information and gradient are ``H = G^T G - sum_s M_s^T A_s^-1 M_s``, ``b = G^T e - sum_s M_s^T A_s^-1
g_s``.  A model (a set of columns) is then a small solve ``H_SS dtheta_S = b_S``.

Held out (:class:`Fold`): the nuisance of a test component's segment comes from the training components of that
segment, ``dnu_s = A_s^-1 (g_s - M_s dtheta)``, so its residual ``e_V - G_V dtheta - N_V dnu_s`` is linear in
``dtheta`` again: ``e~_V - G~_V dtheta`` with ``e~_V = e_V - N_V A_s^-1 g_s`` and ``G~_V = G_V - N_V A_s^-1 M_s``,
precomputed once per fold for every column.  A segment without (enough) training components (a held-out file's
station) is registered on its own ``reg`` components with ``dtheta`` fixed and scored on its ``score`` components
that did not define it (the Hilti protocol; all of them when it has no separate scored rows).  Scoring any set of
columns on every fold is then ``O(n |S| + |S|^3)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import sparse

__all__ = ["NuisanceSet", "SegmentBatch", "BlockPart", "LinearSystem", "Fold", "FoldStack", "solve_scaled"]

#: a segment's nuisance is determined when its information's smallest scaled eigenvalue exceeds this
MIN_NUISANCE_EIG = 1e-9
#: a parameter acts on a fit's data when the square root of its information exceeds this share of the largest's
#: (units differ by many orders: rad vs rad/(N m)) -- below, it stays at zero (e.g. a spline piece without data)
MIN_ACTIVE = 1e-12


@dataclass
class NuisanceSet:
    """The nuisance columns of one block: component indices ``idx`` (m,) into the system, their nuisance rows
    ``N`` (m, k), segment ids ``seg`` (m,) (block-local, ``n_segments`` of them) and the block's index."""

    idx: np.ndarray
    N: np.ndarray
    seg: np.ndarray
    block: int = 0
    n_segments: int = 0


@dataclass
class BlockPart:
    """Where one block's components sit in the system (``start`` .. ``stop``, ``d`` per row) and the whitening
    ``W`` (n, d, d) of its rows (robust weights included): ``raw row = W^-1 whitened row``."""

    index: int
    start: int
    stop: int
    d: int
    W: np.ndarray

    def raw(self, e: np.ndarray) -> np.ndarray:
        """Raw residual rows (n, d) of this block from whitened components ``e`` of the whole system."""
        rows = e[self.start:self.stop].reshape(-1, self.d)
        return np.linalg.solve(self.W, rows[..., None])[..., 0]


@dataclass
class SegmentBatch:
    """The segments of one :class:`NuisanceSet`, their eliminations batched: segment ids ``ids`` (S,), each one's
    positions ``pos`` in the set, the sparse map ``P`` (S k, n) of a system vector to every segment's ``N_s^T v_s``,
    per segment the active nuisance columns ``act`` (S, k), whether it is determined ``det`` (S,), ``A_s^-1`` (S, k,
    k; zero where not determined), ``M_s = N_s^T G_s`` (S, k, C) and ``A_s^-1 M_s``."""

    set_index: int
    ids: np.ndarray
    pos: list[np.ndarray]
    P: sparse.csr_matrix
    act: np.ndarray
    det: np.ndarray
    A_inv: np.ndarray
    M: np.ndarray
    AM: np.ndarray

    @classmethod
    def build(cls, ns: NuisanceSet, set_index: int, G: np.ndarray) -> SegmentBatch:
        """The batch of ``ns`` with the system's columns ``G`` (n, C)."""
        k = ns.N.shape[1]
        order = np.argsort(ns.seg, kind="stable")
        ids, starts = np.unique(ns.seg[order], return_index=True)
        S = ids.size
        pos = np.split(order, starts[1:]) if order.size else []
        slot = np.repeat(np.arange(S), np.diff(np.append(starts, order.size)))  # segment slot of each sorted row
        Ns = ns.N[order]
        P = sparse.csr_matrix((Ns.reshape(-1), ((slot[:, None] * k + np.arange(k)).reshape(-1),
                                                 np.repeat(ns.idx[order], k))), shape=(S * k, G.shape[0]))
        A = np.add.reduceat(Ns[:, :, None] * Ns[:, None, :], starts, axis=0) if S else np.zeros((0, k, k))
        norm = np.sqrt(np.maximum(np.einsum("sii->si", A), 0.0))
        act = norm > 1e-12 * np.maximum(norm.max(axis=1, keepdims=True), 1e-300)
        A_inv, det = _nuisance_inverses(A, act, np.diff(np.append(starts, order.size)), [ns.N[p] for p in pos])
        M = np.asarray(P @ G).reshape(S, k, G.shape[1])
        return cls(set_index, ids, pos, P, act, det, A_inv, M, A_inv @ M)

    def project(self, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per segment ``g_s = N_s^T v_s`` (S, k) and ``A_s^-1 g_s`` (zero where not determined) of a system vector
        ``v`` (n,)."""
        g = np.asarray(self.P @ v).reshape(self.ids.size, -1)
        return g, np.einsum("sij,sj->si", self.A_inv, g)


def _flat(M: np.ndarray) -> np.ndarray:
    """(S, k, C) -> (S k, C) (also when empty)."""
    return M.reshape(M.shape[0] * M.shape[1], M.shape[2])


def _nuisance_inverses(A: np.ndarray, act: np.ndarray, counts: np.ndarray, Ns: Sequence[np.ndarray]
                       ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_nuisance_inverse` of every segment's information ``A`` (S, k, k) with active columns ``act`` (S, k)
    and ``counts`` rows: the inverses (zero where not determined) and which are determined (the segments with all
    columns active batched; the others, and any that fails, one by one from their rows ``Ns``)."""
    S, k = act.shape
    A_inv, det = np.zeros((S, k, k)), np.zeros(S, dtype=bool)
    full = act.all(axis=1) & (counts >= k)
    if full.any():
        Af = A[full]
        d = np.sqrt(np.maximum(np.einsum("sii->si", Af), 1e-300))
        ev = np.linalg.eigvalsh(Af / d[:, :, None] / d[:, None, :])
        ok = ev[:, 0] > MIN_NUISANCE_EIG * np.maximum(ev[:, -1], 1e-300)
        idx = np.flatnonzero(full)
        if ok.any():
            A_inv[idx[ok]] = np.linalg.inv(Af[ok])
            det[idx[ok]] = True
        full[idx[~ok]] = True  # not determined: the one-by-one check would say the same
    for s in np.flatnonzero(~full).tolist():
        inv = _nuisance_inverse(Ns[s], act[s])
        if inv is not None:
            A_inv[s], det[s] = inv, True
    return A_inv, det


@dataclass
class LinearSystem:
    """Whitened components of all blocks (module docstring).

    Attributes
    ----------
    e : ndarray (n,)
    G : ndarray (n, C)
        Columns of all candidates (``cols[c]`` the slice of candidate ``c``).
    unit : ndarray (n,) int
        Robot pose (cluster) of each component, 0..U-1.
    group : ndarray (n,) int
    reg, score : ndarray (n,) bool
        Stop roles of each component's row.
    nuisances : list of NuisanceSet
    parts : list of BlockPart
    """

    e: np.ndarray
    G: np.ndarray
    cols: list[slice]
    unit: np.ndarray
    n_units: int
    group: np.ndarray
    reg: np.ndarray
    score: np.ndarray
    nuisances: list[NuisanceSet] = field(default_factory=list)
    parts: list[BlockPart] = field(default_factory=list)
    _gramG: np.ndarray | None = field(default=None, init=False, repr=False)
    _gram_cache: tuple[np.ndarray, np.ndarray, float] | None = field(default=None, init=False, repr=False)
    _schur_cache: tuple[np.ndarray, list[tuple], np.ndarray, list[SegmentBatch]] | None = field(
        default=None, init=False, repr=False)
    _reduced_cache: tuple[np.ndarray, np.ndarray, float, list[tuple], np.ndarray] | None = field(
        default=None, init=False, repr=False)
    _absorbed: np.ndarray | None = field(default=None, init=False, repr=False)
    _term_index: np.ndarray | None = field(default=None, init=False, repr=False)

    @property
    def n_columns(self) -> int:
        return int(self.G.shape[1])

    def _gram(self) -> tuple[np.ndarray, np.ndarray, float]:
        """``G^T G``, ``G^T e`` and ``e^T e`` of all components (computed once)."""
        if self._gram_cache is None:
            if self._gramG is None:
                self._gramG = self.G.T @ self.G
            self._gram_cache = (self._gramG, self.G.T @ self.e, float(self.e @ self.e))
        return self._gram_cache

    def with_residual(self, e: np.ndarray) -> LinearSystem:
        """The system with the residual ``e`` and the same columns: what does not depend on the residual (``G^T
        G``, the segments' eliminations) is shared, not computed again."""
        out = replace(self, e=np.asarray(e, dtype=float))
        self._gram()
        out._gramG, out._schur_cache, out._term_index = self._gramG, self._schur(), self._term_index
        return out

    def subset(self, columns: np.ndarray, sizes: Sequence[int]) -> LinearSystem:
        """The system with only ``columns`` (in that order), grouped into consecutive slices of ``sizes``."""
        ends = np.cumsum([0, *sizes])
        return LinearSystem(self.e, self.G[:, columns], [slice(int(a), int(b)) for a, b in zip(ends[:-1], ends[1:])],
                            self.unit, self.n_units, self.group, self.reg, self.score, self.nuisances, self.parts)

    def _schur(self) -> tuple[np.ndarray, list[tuple], np.ndarray, list[SegmentBatch]]:
        """What the nuisance elimination needs that does not depend on the residual: ``G^T G - sum_s M_s^T A_s^-1
        M_s``, per segment ``(components, N, active columns, A^-1 (None: not determined), M, A^-1 M, nuisance set,
        segment id)``, the mask of components in a segment and the segments of each nuisance set batched
        (:class:`SegmentBatch`; computed once)."""
        if self._schur_cache is None:
            if self._gramG is None:
                self._gramG = self.G.T @ self.G
            H = self._gramG.copy()
            terms: list[tuple] = []
            batches = [SegmentBatch.build(ns, k, self.G) for k, ns in enumerate(self.nuisances)]
            for bt in batches:
                if bt.det.any():
                    Md, AMd = bt.M[bt.det], bt.AM[bt.det]
                    H -= _flat(Md).T @ _flat(AMd)
                ns = self.nuisances[bt.set_index]
                for s, (sid, pos) in enumerate(zip(bt.ids, bt.pos)):
                    rows, N = ns.idx[pos], ns.N[pos]
                    if not bt.det[s]:
                        terms.append((rows, N, bt.act[s], None, None, None, bt.set_index, int(sid)))
                    else:
                        terms.append((rows, N, bt.act[s], bt.A_inv[s], bt.M[s], bt.AM[s], bt.set_index, int(sid)))
            in_seg = np.zeros(self.e.size, dtype=bool)
            for t in terms:
                in_seg[t[0]] = True
            self._schur_cache = (H, terms, in_seg, batches)
        return self._schur_cache

    def _reduced(self) -> tuple[np.ndarray, np.ndarray, float, list[tuple], np.ndarray]:
        """The information with every segment's nuisance eliminated on all its components, per segment its terms
        ``(components, N, A^-1, M, g, A^-1 M, A^-1 g)`` and the mask of components in a segment (computed once; a
        fold only corrects the segments it touches)."""
        if self._reduced_cache is None:
            _, gb, gee = self._gram()
            H, sterms, in_seg, batches = self._schur()
            b, ee = gb.copy(), gee
            gs: list[np.ndarray] = []
            Ags: list[np.ndarray] = []
            for bt in batches:
                g, Ag = bt.project(self.e)
                if bt.det.any():
                    Md = bt.M[bt.det]
                    b -= _flat(Md).T @ Ag[bt.det].reshape(-1)
                    ee -= float(np.sum(g[bt.det] * Ag[bt.det]))
                gs.extend(g)
                Ags.extend(Ag)
            terms: list[tuple] = []
            for (rows, N, act, A_inv, M, AM, _, _), g, Ag in zip(sterms, gs, Ags):
                if A_inv is None:
                    terms.append((rows, N, act, None, None, None, None, None))
                else:
                    terms.append((rows, N, act, A_inv, M, g, AM, Ag))
            self._reduced_cache = (H, b, ee, terms, in_seg)
        return self._reduced_cache

    def absorbed(self) -> np.ndarray:
        """Per column (C,), the smallest share of its information the nuisances absorb in any block where it acts
        (1: absorbed everywhere, e.g. a rigid motion of the whole arm against a tracker's registration; a column
        that no block sees gets 1)."""
        if self._absorbed is None:
            _, _, _, terms, _ = self._reduced()
            out = np.ones(self.G.shape[1])
            for part in self.parts:
                G = self.G[part.start:part.stop]
                raw = np.einsum("ij,ij->j", G, G)
                red = raw.copy()
                for rows, _N, _act, A_inv, M, _g, AM, _Ag in terms:
                    if A_inv is not None and part.start <= rows[0] < part.stop:
                        red -= np.einsum("kj,kj->j", M, AM)
                acts = raw > 1e-300
                share = np.where(acts, 1.0 - red / np.where(acts, raw, 1.0), 1.0)
                out = np.minimum(out, share)
            self._absorbed = out
        return self._absorbed

    def folds(self, comp_fold: np.ndarray, n_folds: int) -> list[Fold]:
        """:meth:`fold` of every fold (``comp_fold``: each component's fold, 0..``n_folds``-1; the training part of
        fold ``f`` is every other fold), their held-out components' Gram matrices computed once: ``G^T G`` is their
        sum (when not computed yet), and each fold takes its own out of the all-components information in one step
        (not segment by segment)."""
        tests = [np.flatnonzero(comp_fold == f) for f in range(n_folds)]
        grams = []
        for tidx in tests:
            Gt, et = self.G[tidx], self.e[tidx]
            grams.append((tidx, Gt, Gt.T @ Gt, Gt.T @ et, float(et @ et)))
        if self._gramG is None and grams:
            self._gramG = sum((g[2] for g in grams[1:]), grams[0][2].copy())
        return [self.fold(comp_fold != f, held=grams[f]) for f in range(n_folds)]

    def fold(self, train: np.ndarray, held: tuple | None = None) -> Fold:
        """:class:`Fold` with training components ``train`` (n,) bool; the others are held out.  A segment whose
        training components cannot determine its nuisance does not train (it is scored as a held-out segment).
        ``held``: the held-out components' ``(indices, G, G^T G, G^T e, e^T e)`` (:meth:`folds`)."""
        test = ~train
        H0, b0, ee0, terms, in_seg = self._reduced()
        if not test.any():
            return Fold(H0, b0, ee0, np.zeros(0, dtype=int), np.zeros(0), np.zeros((0, self.G.shape[1])),
                        np.zeros(0, dtype=int))
        H, b, ee = H0.copy(), b0.copy(), ee0
        tidx = np.flatnonzero(test)
        touched = np.bincount(self._term_of()[tidx] + 1, minlength=len(terms) + 1)[1:] > 0
        if held is None:
            free_out = np.flatnonzero(~train & ~in_seg)
            Go, eo = self.G[free_out], self.e[free_out]
            H -= Go.T @ Go
            b -= Go.T @ eo
            ee -= float(eo @ eo)
            G_v = self.G[tidx].copy()
        else:  # every held-out component at once, and the touched segments' reductions undone at once
            _, G_v, Hh, bh, eeh = held
            H -= Hh
            b -= bh
            ee -= eeh
            undo = [t for t, touch in zip(terms, touched) if touch and t[3] is not None]
            if undo:
                M, AM = np.concatenate([t[4] for t in undo]), np.concatenate([t[6] for t in undo])
                H += M.T @ AM
                b += M.T @ np.concatenate([t[7] for t in undo])
                ee += float(sum(t[5] @ t[7] for t in undo))
        loc = np.full(self.e.size, -1)
        loc[tidx] = np.arange(tidx.size)
        e_v = self.e[tidx].copy()
        scored = np.ones(tidx.size, dtype=bool)
        for term, touch in zip(terms, touched):
            if touch or term[3] is None:  # (a determined segment all in training stays as reduced)
                ee = self._fold_segment(term, train, test, H, b, ee, e_v, G_v, loc, scored, held is None)
        keep = np.flatnonzero(scored)
        return Fold(H, b, ee, tidx[keep], e_v[keep], G_v[keep], self.unit[tidx[keep]])

    def _term_of(self) -> np.ndarray:
        """Per component (n,), the index of its segment in :meth:`_reduced`'s terms (-1: in none)."""
        if self._term_index is None:
            self._term_index = np.full(self.e.size, -1)
            for i, t in enumerate(self._schur()[1]):
                self._term_index[t[0]] = i
        return self._term_index

    def _fold_segment(self, term: tuple, train: np.ndarray, test: np.ndarray, H: np.ndarray, b: np.ndarray,
                      ee: float, e_v: np.ndarray, G_v: np.ndarray, loc: np.ndarray, scored: np.ndarray,
                      take_out: bool = True) -> float:
        """One segment in a fold (in place on ``H``, ``b``; returns ``e^T e``): kept as reduced when all its
        components train; else its reduction and its held-out components are taken out of the training system
        (here, or by the caller: ``take_out`` False), its training part (if it determines the nuisance) eliminated
        again, and its held-out components adjusted: by that training part, or, without one, by the segment's
        ``reg`` test components, scored on the others (``score`` and not ``reg``; every test component of the
        segment when it has no such split)."""
        rows, N, act, A_inv, M, g, AM, Ag = term
        tr = train[rows]
        if A_inv is not None and tr.all():
            return ee
        te = test[rows]
        if take_out:
            if A_inv is not None:  # undo the all-components reduction of this segment
                H += M.T @ AM
                b += M.T @ Ag
                ee += float(g @ Ag)
            out_rows = rows[~tr]
            Go, eo = self.G[out_rows], self.e[out_rows]
            H -= Go.T @ Go
            b -= Go.T @ eo
            ee -= float(eo @ eo)
        A2 = _nuisance_inverse(N[tr], act) if tr.any() else None
        if A2 is not None:
            fit_rows, fit_N, out, training = rows[tr], N[tr], te, True
        else:
            if tr.any():  # its training part cannot determine the nuisance: it does not train
                Gt, et = self.G[rows[tr]], self.e[rows[tr]]
                H -= Gt.T @ Gt
                b -= Gt.T @ et
                ee -= float(et @ et)
            reg = te & self.reg[rows]
            split = te & self.score[rows] & ~self.reg[rows]
            out = split if split.any() else te
            scored[loc[rows[te]]] = False
            fit_rows, fit_N, training = rows[reg], N[reg], False
            A2 = _nuisance_inverse(fit_N, act) if te.any() else None
            if A2 is None:
                return ee
            scored[loc[rows[out]]] = True
        M2, g2 = fit_N.T @ self.G[fit_rows], fit_N.T @ self.e[fit_rows]
        AM2, Ag2 = A2 @ M2, A2 @ g2
        if training:
            H -= M2.T @ AM2
            b -= M2.T @ Ag2
            ee -= float(g2 @ Ag2)
        if out.any():
            li, No = loc[rows[out]], N[out]
            e_v[li] -= No @ Ag2
            G_v[li] -= No @ AM2
        return ee

    def full(self) -> Fold:
        """All components as training (the in-sample fit); no held-out components."""
        return self.fold(np.ones(self.e.size, dtype=bool))

    def projected(self) -> tuple[np.ndarray, np.ndarray]:
        """``(e~, G~)``: residual and columns with every segment's nuisance projected out (all components), for
        per-component in-sample residuals and clustered covariances."""
        e_p, G_p = self.e.copy(), self.G.copy()
        for ns in self.nuisances:
            for s in np.unique(ns.seg):
                m = ns.seg == s
                rows, Ns = ns.idx[m], ns.N[m]
                A_inv = _nuisance_inverse(Ns, _active(Ns))
                if A_inv is None:
                    continue
                e_p[rows] -= Ns @ (A_inv @ (Ns.T @ self.e[rows]))
                G_p[rows] -= Ns @ (A_inv @ (Ns.T @ self.G[rows]))
        return e_p, G_p

    def nuisance_step(self, dtheta: np.ndarray, columns: np.ndarray) -> dict[int, np.ndarray]:
        """Per block (index) with nuisances, the step ``dnu`` (n_segments, k) that goes with ``dtheta`` on
        ``columns`` (all components)."""
        r = self.e - self.G[:, columns] @ dtheta
        steps = [np.zeros((ns.n_segments, ns.N.shape[1])) for ns in self.nuisances]
        for bt in self._schur()[3]:
            _, Ag = bt.project(r)
            steps[bt.set_index][bt.ids[bt.det]] = Ag[bt.det]
        return {ns.block: st for ns, st in zip(self.nuisances, steps)}


def _active(N: np.ndarray) -> np.ndarray:
    """The nuisance columns (k,) that act on a segment at all (a placement's tilt that is fixed by definition has a
    zero column)."""
    norm = np.sqrt(np.einsum("ij,ij->j", N, N))
    return norm > 1e-12 * max(float(norm.max(initial=0.0)), 1e-300)


def _nuisance_inverse(N: np.ndarray, act: np.ndarray) -> np.ndarray | None:
    """``(N^T N)^-1`` (k, k) on the ``act`` columns, zero elsewhere, if the nuisance rows ``N`` (m, k) determine
    them (their scaled information well conditioned: smallest eigenvalue above :data:`MIN_NUISANCE_EIG` of the
    largest), else None."""
    Na = N[:, act]
    if Na.shape[0] < Na.shape[1] or not act.any():
        return np.zeros((N.shape[1], N.shape[1])) if not act.any() else None
    A = Na.T @ Na
    d = np.sqrt(np.maximum(np.diag(A), 1e-300))
    ev = np.linalg.eigvalsh(A / d[:, None] / d[None, :])
    if not ev[0] > MIN_NUISANCE_EIG * max(ev[-1], 1e-300):
        return None
    if act.all():
        return np.linalg.inv(A)
    out = np.zeros((N.shape[1], N.shape[1]))
    out[np.ix_(act, act)] = np.linalg.inv(A)
    return out


@dataclass
class Fold:
    """One cross-validation fold, precomputed for every column (module docstring): reduced training information
    ``H`` (C, C), gradient ``b`` (C,), reduced ``e^T e`` of the training part, the scored held-out components
    ``idx`` with their adjusted residual ``e`` and columns ``G``, and their units."""

    H: np.ndarray
    b: np.ndarray
    ee: float
    idx: np.ndarray
    e: np.ndarray
    G: np.ndarray
    unit: np.ndarray

    def fit(self, cols: np.ndarray, fixed: np.ndarray | None = None, fixed_values: np.ndarray | None = None,
            ridge: float = 1e-10, scale: np.ndarray | None = None) -> np.ndarray:
        """``dtheta`` on ``cols`` (training least squares) with the columns ``fixed`` held at ``fixed_values``
        (``ridge``, ``scale``: :func:`solve_scaled`)."""
        b = self.b[cols]
        if fixed is not None and fixed.size:
            b = b - self.H[cols[:, None], fixed] @ fixed_values
        return solve_scaled(self.H[cols[:, None], cols], b, ridge, None if scale is None else scale[cols])

    def heldout(self, cols: np.ndarray, dtheta: np.ndarray, fixed: np.ndarray | None = None,
                fixed_values: np.ndarray | None = None) -> np.ndarray:
        """Held-out residual of the scored components with ``dtheta`` on ``cols`` and ``fixed`` at ``fixed_values``."""
        r = self.e - self.G[:, cols] @ dtheta
        if fixed is not None and fixed.size:
            r = r - self.G[:, fixed] @ fixed_values
        return r


class FoldStack:
    """All folds of a cross-validation stacked (the same numbers as :class:`Fold` s, scored in one batched solve):
    ``H`` (F, C, C), ``b`` (F, C), and every fold's scored held-out components in one list (``e``, ``G``, ``idx``,
    ``unit`` and ``fold`` per component)."""

    def __init__(self, folds: Sequence[Fold]) -> None:
        C = folds[0].H.shape[0] if folds else 0
        self.H = np.stack([f.H for f in folds]) if folds else np.zeros((0, C, C))
        self.b = np.stack([f.b for f in folds]) if folds else np.zeros((0, C))
        self.e = np.concatenate([f.e for f in folds]) if folds else np.zeros(0)
        #: held-out columns transposed (C, m): a model's columns are then contiguous rows
        self.GT = np.ascontiguousarray(np.concatenate([f.G for f in folds]).T) if folds else np.zeros((C, 0))
        self.idx = np.concatenate([f.idx for f in folds]).astype(int) if folds else np.zeros(0, dtype=int)
        self.unit = np.concatenate([f.unit for f in folds]).astype(int) if folds else np.zeros(0, dtype=int)
        ends = np.cumsum([0, *(f.idx.size for f in folds)])
        self.slices = [slice(int(a), int(b)) for a, b in zip(ends[:-1], ends[1:])]

    def heldout(self, cols: np.ndarray, fixed: np.ndarray, fixed_values: np.ndarray) -> np.ndarray:
        """Held-out residual of every scored component: ``cols`` fitted on each fold's training part (:meth:`Fold.fit`
        with the default ridge), ``fixed`` held at ``fixed_values``."""
        if not len(self.H):
            return np.zeros(0)
        b = self.b[:, cols]
        if fixed.size:
            b = b - self.H[:, cols[:, None], fixed[None, :]] @ fixed_values
        dth = solve_scaled_batch(self.H[:, cols[:, None], cols[None, :]], b)
        r = self.e.copy()
        if cols.size:
            Gc = self.GT[cols]
            for k, sl in enumerate(self.slices):
                r[sl] -= dth[k] @ Gc[:, sl]
        if fixed.size:
            r -= fixed_values @ self.GT[fixed]
        return r


def solve_scaled_batch(H: np.ndarray, b: np.ndarray, ridge: float = 1e-10) -> np.ndarray:
    """:func:`solve_scaled` of every ``H[k] x = b[k]`` (H (F, s, s), b (F, s)) in one batched solve."""
    F, s = b.shape
    if s == 0:
        return np.zeros((F, 0))
    d = np.sqrt(np.maximum(np.einsum("kii->ki", H), 0.0))
    act = d > MIN_ACTIVE * np.maximum(d.max(axis=1, keepdims=True), 1e-300)
    if act.all():  # (the common case: the masks below change nothing)
        Hs = H / d[:, :, None] / d[:, None, :]
        diag = np.einsum("kii->ki", Hs)
        diag[...] = diag + ridge
        try:
            return np.linalg.solve(Hs, (b / d)[..., None])[..., 0] / d
        except np.linalg.LinAlgError:
            return np.stack([solve_scaled(H[k], b[k], ridge) for k in range(F)])
    da = np.where(act, d, 1.0)
    Hs = H / da[:, :, None] / da[:, None, :]
    mask = act[:, :, None] & act[:, None, :]
    Hs = np.where(mask, Hs, 0.0)
    diag = np.einsum("kii->ki", Hs)
    diag[...] = np.where(act, diag + ridge, 1.0)
    rhs = np.where(act, b / da, 0.0)
    try:
        x = np.linalg.solve(Hs, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        return np.stack([solve_scaled(H[k], b[k], ridge) for k in range(F)])
    return np.where(act, x / da, 0.0)


def solve_scaled(H: np.ndarray, b: np.ndarray, ridge: float = 1e-10, scale: np.ndarray | None = None) -> np.ndarray:
    """Solution of ``H x = b`` with column scaling (by ``sqrt(diag H)``, or ``scale``: e.g. the columns' norms over
    all data, so that a column barely present in a fold's training data is not blown up) and a relative ridge.
    Parameters whose information is below :data:`MIN_ACTIVE` of the largest stay 0."""
    if b.size == 0:
        return np.zeros(0)
    d = np.sqrt(np.maximum(np.diag(H), 0.0))
    if scale is not None:
        d = np.where(d > MIN_ACTIVE * max(float(d.max(initial=0.0)), 1e-300), np.asarray(scale, dtype=float), 0.0)
    act = d > MIN_ACTIVE * max(float(d.max(initial=0.0)), 1e-300)
    x = np.zeros(b.size)
    if not act.any():
        return x
    da = d[act]
    Hs = H[np.ix_(act, act)] / da[:, None] / da[None, :]
    Hs[np.diag_indices_from(Hs)] += ridge
    try:
        x[act] = np.linalg.solve(Hs, b[act] / da) / da
    except np.linalg.LinAlgError:
        x[act] = np.linalg.lstsq(Hs, b[act] / da, rcond=1e-12)[0] / da
    return x


def stack_components(parts: Sequence[np.ndarray]) -> np.ndarray:
    """Concatenate per-block component arrays."""
    return np.concatenate(list(parts)) if parts else np.zeros(0)
