"""The one selection routine: stepwise forward and backward over candidate effects by penalised held-out likelihood.

Criterion (docs/diagnose.md, "Selection"): a model ``M`` scores ``L(M) = sum_u d_u(M) / s^2 + kappa P(M)``, with
``d_u`` the held-out sum of squared whitened residuals of robot pose ``u`` (``-2 log`` likelihood of the held-out
data up to a constant, :meth:`Linearised.heldout`), ``s^2`` the in-sample residual variance of the model the step
starts from (the noise scale of the current fit), ``P`` the number of parameters and ``kappa = ln U`` per
parameter (``U`` scored poses; a BIC-like price).

* **Forward**: every candidate not in the model (each ``camera_intrinsics`` level, its identifiable components
  only, no significantly negative compliance), every held term grown by one nested step (a parameter more, an
  intrinsics level more) and every group move (one kind on every joint of a measured chain) is
  scored; of those that lower ``L`` with significant per-pose held-out gains in some measurement block (paired t
  or one-sided signed-rank z >= ``min_t`` over the poses of that block: a tracker's gain is not drowned by the
  scatter of a camera's pixels; a nested extension of a held term at :data:`NESTED_T`, the structure tests' level:
  a round scores a handful of extensions against about a hundred additions) and a relative gain >= ``min_gain``,
  the one that lowers ``L`` most is added.
* **Confirmation**: the new model is refitted on the full nonlinear chain (:meth:`Problem.refit`); every candidate
  is linearised again there unless the refitted cost is the one the current linearisation predicted.
* **Backward**, after every addition until nothing changes: for every term, its removal, each nested simpler term
  (one parameter less, an intrinsics level less, ``joint_offset@j`` for ``link_error@j``) and the simpler
  replacements by one or two other candidates with fewer parameters in all that explain nothing beyond it; the
  move that lowers ``L`` most is taken whenever ``L`` does not rise (the held-out fit does not get worse by more
  than ``kappa`` per parameter saved) and the held-out losses are not significant in any block (paired t or
  signed-rank z of the per-pose losses below :data:`BACKWARD_T`).  Backward moves are linear at the point of the
  last refit (the next accepted step refits them).
* **Exchanges**, once no forward move qualifies: the backward pass once more, with the *exchange* of a term for one
  of its rivals (the single additions that scored within ``kappa`` of it, one parameter's price, in the step that
  added it: at that step's noise scale the two were not told apart, at the final residual they may be), taken
  when it lowers ``L`` by more than rounding (:data:`EXCHANGE_MIN`); after a change the forward steps go on.
* **Stop** when no forward move qualifies (``max_effects`` optionally caps the number of terms).
* **Phases**: first the sensors' own effects only (camera extrinsics and intrinsics, tag placement, a sensor's time
  offset: the model of a measurement, before any arm effect is asked to explain what a sensor's own error does),
  then every candidate; the backward pass may still replace a sensor effect by an arm effect.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from ppoe_core.analysis.diagnose.crossval import Linearised
from ppoe_core.analysis.diagnose.stats import paired_t, signed_rank_z
from ppoe_core.analysis.diagnose.terms import Catalogue, Term, model_key

__all__ = ["SelectionOptions", "Move", "Selection", "Refitter", "select"]

#: replacements by other candidates scored held out per term (the best by in-sample fit)
SWAP_SCREEN = 6
#: terms with at least this many parameters are tried against simpler replacements by other candidates (two
#: parameters are covered by the nested one-parameter terms)
SWAP_MIN_PARAMS = 3
#: a backward move is not taken when it makes the held-out fit significantly worse: the per-pose losses' paired t
#: and signed-rank z both reach this (one-sided 2.3 %)
BACKWARD_T = 2.0
#: significance (paired t or signed-rank z) of a nested extension of a held term (an intrinsics level, a parameter
#: more): a round scores a handful of them (about a hundred additions, judged at ``min_t``), the level at which the
#: structure tests flag what is left (significance.STRUCTURE_T)
NESTED_T = 3.0
#: iterations of the backward pass at one linearisation (each removes or simplifies one term)
MAX_BACKWARD = 200
#: at most this many rivals of an added term are kept for the exchange moves (the closest first)
MAX_RIVALS = 4
#: an exchange is taken only when it lowers ``L`` by more than this: two equivalent terms (a base tilt and the
#: same turn of the first mount) score equal up to rounding, and :meth:`Selector.best` breaks such ties (to 1e-6)
#: by fewer parameters, then by catalogue order; an exchange must not undo that
EXCHANGE_MIN = 1e-6


class Refitter(Protocol):
    """What the selection needs of the solver: ``relinearise(model)`` refits ``model`` on the nonlinear chain and
    returns the system of every candidate there; ``confirm(model, predicted)`` refits it and says whether the
    refitted cost is still the one the current linearisation predicts (``predicted``), i.e. whether it still
    holds."""

    def relinearise(self, model: tuple[Term, ...]) -> Linearised: ...

    def confirm(self, model: tuple[Term, ...], predicted: float) -> bool: ...


@dataclass
class SelectionOptions:
    """Settings of :func:`select` (module docstring)."""

    min_t: float = 4.0
    min_gain: float = 0.0
    penalty: float | None = None
    max_condition: float = 1e6
    max_absorbed: float = 0.999
    max_effects: int | None = None
    groups: bool = True
    max_rounds: int = 60


@dataclass
class Move:
    """A scored change of the model: its new terms, the held-out gain (sum over poses of the drop of ``d_u``), the
    change of ``L``, the paired statistics, and what it did."""

    action: str
    model: tuple[Term, ...]
    label: str
    gain: float
    delta_L: float
    t: float = 0.0
    z: float = 0.0
    d: np.ndarray = field(default_factory=lambda: np.zeros(0))
    t_min: float = 0.0
    z_min: float = 0.0

    def record(self) -> dict[str, Any]:
        return {"action": self.action, "move": self.label, "heldout_gain": self.gain, "delta_L": self.delta_L,
                "t": self.t, "z": self.z}


@dataclass
class Selection:
    """Result: the chosen model, the values of every column at the end, the steps taken, the candidates refused
    (with the reason) and the held-out errors per pose of the empty and the final model."""

    model: tuple[Term, ...]
    steps: list[dict[str, Any]]
    rejected: dict[str, str]
    d_before: np.ndarray
    d_after: np.ndarray


class Selector:
    """State of one selection: the linearisation (rebuilt by the refitter when a refit leaves it)."""

    def __init__(self, catalogue: Catalogue, refitter: Refitter, options: SelectionOptions) -> None:
        self.catalogue, self.refitter, self.options = catalogue, refitter, options
        self.rejected: dict[str, str] = {}
        self.steps: list[dict[str, Any]] = []
        self.visited: set[tuple[Term, ...]] = set()
        self.allowed: set[int] | None = None  #: forward candidates of the current phase (None: all)
        self._lin: Linearised | None = None
        self._variance: dict[tuple[Term, ...], float] = {}
        #: :meth:`admissible` per (model, term) at the current linearisation: the term and the reasons it records
        self._admissible: dict[tuple, tuple[Term | None, dict[str, str], dict[str, str]]] = {}
        #: candidate index of an added term -> its rivals (:meth:`note_rivals`), for the exchange moves
        self.rivals: dict[int, list[Term]] = {}
        #: whether the backward pass tries exchanges (only once the forward steps are done, :func:`select`)
        self.exchanging = False

    @property
    def lin(self) -> Linearised | None:
        return self._lin

    @lin.setter
    def lin(self, value: Linearised | None) -> None:
        self._lin, self._variance, self._admissible = value, {}, {}

    # -- scoring --------------------------------------------------------------------------------------
    def kappa(self, d: np.ndarray) -> float:
        if self.options.penalty is not None:
            return float(self.options.penalty)
        return math.log(max(int(np.isfinite(d).sum()), 2))

    def score(self, base: tuple[Term, ...], model: tuple[Term, ...], action: str, label: str,
              stats: bool | None = None) -> Move:
        """The move ``base -> model`` scored held out (gains per pose, change of ``L`` in units of the current
        residual variance, paired statistics per measurement block: their largest is the move's ``t`` / ``z``,
        their smallest its ``t_min`` / ``z_min``).  The paired statistics are computed when ``stats`` (default:
        only when ``L`` does not rise; no move that raises ``L`` is taken, forward or backward)."""
        assert self.lin is not None
        d0, d1 = self.lin.heldout(base), self.lin.heldout(model)
        ok = np.isfinite(d0) & np.isfinite(d1)
        gain = float((d0[ok] - d1[ok]).sum()) / self.variance(base)
        dP = self.catalogue.n_params(model) - self.catalogue.n_params(base)
        delta_L = -gain + self.kappa(d0) * dP
        if not (delta_L <= 0.0 if stats is None else stats):
            return Move(action, model, label, gain, delta_L, d=d1)
        b0, b1 = self.lin.heldout_blocks(base), self.lin.heldout_blocks(model)
        per_block = []
        for x0, x1 in zip(b0, b1):
            m = np.isfinite(x0) & np.isfinite(x1)
            if m.sum() >= 3:
                diff = x0[m] - x1[m]
                per_block.append((paired_t(diff), signed_rank_z(diff)))
        ts, zs = [t for t, _ in per_block] or [0.0], [z for _, z in per_block] or [0.0]
        best = max(range(len(ts)), key=lambda k: max(ts[k], zs[k]))
        worst = min(range(len(ts)), key=lambda k: max(ts[k], zs[k]))
        return Move(action, model, label, gain, delta_L, ts[best], zs[best], d1, ts[worst], zs[worst])

    def variance(self, model: tuple[Term, ...]) -> float:
        """The residual variance of ``model`` in the current whitening (in-sample, per degree of freedom): ``-2 log
        L`` is counted in units of it, so a whitening from an older, noisier fit does not blur the penalty."""
        assert self.lin is not None
        key = model_key(model)
        if key not in self._variance:
            _, _, s2 = self.lin.fit(key)
            self._variance[key] = max(s2, 1e-12)
        return self._variance[key]

    # -- forward --------------------------------------------------------------------------------------
    def admissible(self, model: tuple[Term, ...], term: Term, record: bool = True) -> Term | None:
        """``term`` reduced to what can be identified with ``model`` (components taken one by one, those that
        explain the most in-sample first, each kept if still identifiable: of a far camera's nearly equivalent
        shift and turn, the one the data show) and physically signed; None (reason recorded) if nothing is left.
        Computed once per model and term at a linearisation (the selection asks again for the same ones: the
        backward pass after each step, the next round's additions)."""
        key = (tuple(model), term)
        if key not in self._admissible:
            saved = self.rejected
            self.rejected = {}
            try:
                notes: dict[str, str] = {}
                out = self._reduce(model, term, notes)
            finally:
                signed, self.rejected = self.rejected, saved
            self._admissible[key] = (out, notes, signed)
        out, notes, signed = self._admissible[key]
        if record:
            self.rejected.update(notes)
        self.rejected.update(signed)  # (the sign check records its reason either way)
        return out

    def _reduce(self, model: tuple[Term, ...], term: Term, notes: dict[str, str]) -> Term | None:
        """:meth:`admissible` computed; the reasons of a term left out go to ``notes``."""
        assert self.lin is not None
        o = self.options
        key = self.catalogue.describe(term)
        idf = self.lin.identifiable(model, [term], o.max_condition, o.max_absorbed)
        if not idf.ok:
            if len(term.comps) == 1 or "act" in idf.reason or not self.catalogue.splittable(term):
                notes[key] = idf.reason  # (a term whose parameters are not components enters whole or not at all)
                return None
            keep: list[int] = []
            singles = [Term(term.cand, (c,)) for c in term.comps]  # the components that explain most go first
            order = np.argsort(self.lin.added_ssr(model, singles), kind="stable")
            for c in (term.comps[i] for i in order):
                trial = Term(term.cand, tuple(sorted((*keep, c))))
                if self.lin.identifiable(model, [trial], o.max_condition, o.max_absorbed).ok:
                    keep.append(c)
            if not keep:
                notes[key] = idf.reason
                return None
            term = Term(term.cand, tuple(sorted(keep)))
        return self._signed(model, term)

    def _signed(self, model: tuple[Term, ...], term: Term) -> Term | None:
        """Drop the components of ``term`` that must be non-negative but fit significantly negative."""
        assert self.lin is not None
        eff = self.catalogue.effect(term)
        if not eff.nonnegative:
            return term
        values, sd = self.lin.term_fit(model, term)
        bad = [c for i, c in enumerate(term.comps)
               if eff.param_names[i] in eff.nonnegative and values[i] + 1.96 * sd[i] < 0.0]
        if not bad:
            return term
        keep = tuple(c for c in term.comps if c not in bad)
        if not keep:
            self.rejected[self.catalogue.describe(term)] = "fits with a negative compliance: unphysical sign"
            return None
        return self._signed(model, Term(term.cand, keep))

    def physical(self, model: Sequence[Term], record: bool = True) -> tuple[Term, ...]:
        """``model`` without the components that must be non-negative but fit significantly negative *together*
        (the most negative first, refitted after each): members of a group move, or terms a later addition turned
        around, are checked jointly, not only one at a time when they entered."""
        assert self.lin is not None
        model = model_key(model)
        while True:
            values, cov, _ = self.lin.fit(model)
            sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
            worst, k = None, 0
            for t in model:
                eff = self.catalogue.effect(t)
                for i, c in enumerate(t.comps):
                    z = (values[k + i] + 1.96 * sd[k + i]) / max(sd[k + i], 1e-300)
                    if eff.param_names[i] in eff.nonnegative and z < 0.0 and (worst is None or z < worst[0]):
                        worst = (z, t, c)
                k += len(t.comps)
            if worst is None:
                return model
            _, t, c = worst
            keep = tuple(x for x in t.comps if x != c)
            label = self.catalogue.describe(t)
            model = model_key([x for x in model if x != t] + ([Term(t.cand, keep)] if keep else []))
            if record:
                self.steps.append({"action": "remove", "move": label, "reason": "fits with a negative compliance "
                                   "next to the other terms: unphysical sign"})

    def forward_moves(self, model: tuple[Term, ...]) -> list[Move]:
        """Every single addition and group move, scored (module docstring)."""
        held = {t.cand for t in model}
        moves = []
        for t in model:  # a held term grown by a nested step (a parameter more, an intrinsics level more)
            rest = tuple(x for x in model if x != t)
            for r in self.catalogue.richer(t):
                r2 = self.admissible(rest, r, record=False)  # what of it can be identified (k2 next to k1 may not)
                if r2 is None or r2 == t or not set(t.comps) < set(r2.comps) or model_key([*rest, r2]) in self.visited:
                    continue
                moves.append(self.score(model, model_key([*rest, r2]), "extend", self.catalogue.describe(r2)))
        for cand in range(len(self.catalogue)):
            if cand in held or (self.allowed is not None and cand not in self.allowed):
                continue
            for entry in self.catalogue.entry_terms(cand):
                term = self.admissible(model, entry)
                if term is None:
                    continue
                new = model_key([*model, term])
                if new not in self.visited:
                    moves.append(self.score(model, new, "add", self.catalogue.describe(term)))
        if self.options.groups and self.allowed is None:
            moves.extend(self.group_moves(model))
        return moves

    def group_moves(self, model: tuple[Term, ...]) -> list[Move]:
        """One move per group (:meth:`Catalogue.groups`): its admissible members, added together."""
        out = []
        for label, members in self.catalogue.groups(model):
            cur = list(model)
            added = 0
            for cand in members:
                term = self.admissible(tuple(cur), self.catalogue.full(cand))
                if term is not None:
                    cur.append(term)
                    added += 1
            new = self.physical(cur, record=False)  # the members' signs checked together
            added -= len(cur) - len(new)
            if added >= 2 and new not in self.visited:
                out.append(self.score(model, new, "add group", f"{label} ({added})"))
        return out

    def accept(self, m: Move, d0: np.ndarray) -> bool:
        o = self.options
        ok = np.isfinite(d0) & np.isfinite(m.d)
        total = float(d0[ok].sum())
        rel = float((d0[ok] - m.d[ok]).sum()) / total if total > 0 else 0.0
        need = min(o.min_t, NESTED_T) if m.action == "extend" else o.min_t
        return m.delta_L < 0.0 and max(m.t, m.z) >= need and rel >= o.min_gain

    def best(self, moves: Sequence[Move], model: tuple[Term, ...]) -> Move:
        """The move that lowers ``L`` most; equal ones (to rounding) go by fewer parameters, then by catalogue order
        (a sensor's own effects first).  A camera's intrinsics give way to the same camera's extrinsics when those
        explain at least as much (the held-out gain, penalty aside) or explain, per pose held out, not significantly
        less (paired t and signed-rank z < ``BACKWARD_T``, the rule of the backward pass): a mount is more often off
        than a calibration, small errors of the two look alike in the pixels, and the extrinsics enter with all six
        components while the intrinsics enter at their best level (bags/effect_camera_extrinsics: the true
        ``[x, rz]`` scores better than ``[fx, fy, cx, cy]``, all six slightly worse)."""
        def key(m: Move) -> tuple[float, int, int]:
            new = [t.cand for t in m.model if t not in model]
            return (round(m.delta_L, 6), self.catalogue.n_params(m.model), min(new, default=-1))

        best = min(moves, key=key)
        new = [t for t in best.model if t not in model]
        eff = self.catalogue.effects[new[0].cand] if best.action == "add" and new else None
        if eff is None or eff.name != "camera_intrinsics":
            return best
        mounts = {j for j, f in self.catalogue.cameras.items() if f == eff.location}

        def camera_move(m: Move, name: str) -> bool:
            added = [self.catalogue.effects[t.cand] for t in m.model if t not in model]
            return m.action == "add" and len(added) == 1 and added[0].name == name and (
                added[0].location in mounts if name == "camera_extrinsics" else added[0].location == eff.location)

        rival = max((m for m in moves if camera_move(m, "camera_extrinsics")), key=lambda m: m.gain, default=None)
        own = max((m for m in moves if camera_move(m, "camera_intrinsics")), key=lambda m: m.gain)
        if rival is None or not rival.delta_L < 0.0:
            return best
        ok = np.isfinite(rival.d) & np.isfinite(own.d)
        loss = rival.d[ok] - own.d[ok]  # per pose: what the extrinsics explain less than the intrinsics, held out
        if rival.gain >= own.gain or (ok.sum() >= 3 and max(paired_t(loss), signed_rank_z(loss)) < BACKWARD_T):
            return rival  # the backward pass then keeps of the mount's six components those the data need
        return best

    def note_rivals(self, best: Move, moves: Sequence[Move], model: tuple[Term, ...], kappa: float) -> None:
        """Keep the rivals of the single addition ``best`` (from ``model``): the other single additions whose
        ``delta_L`` came within ``kappa`` of it (at most :data:`MAX_RIVALS`, the closest first)."""
        def added(m: Move) -> Term | None:
            new = [t for t in m.model if t not in model]
            return new[0] if m.action == "add" and len(new) == 1 else None

        term = added(best)
        if term is None:
            return
        close = sorted((m for m in moves if m is not best and m.delta_L <= best.delta_L + kappa and added(m)),
                       key=lambda m: m.delta_L)
        self.rivals[term.cand] = [t for t in (added(m) for m in close[:MAX_RIVALS]) if t is not None]

    def exchanges(self, model: tuple[Term, ...], t: Term, rest: tuple[Term, ...]) -> list[Move]:
        """``t`` exchanged for each of its rivals (:meth:`note_rivals`) not in the model, scored."""
        held = {x.cand for x in model}
        out = []
        for r in self.rivals.get(t.cand, []):
            r2 = None if r.cand in held else self.admissible(rest, r)
            if r2 is not None:
                out.append(self.score(model, model_key([*rest, r2]), "exchange",
                                      f"{self.catalogue.describe(t)} -> {self.catalogue.describe(r2)}"))
        return out

    # -- backward -------------------------------------------------------------------------------------
    def backward_moves(self, model: tuple[Term, ...]) -> list[Move]:
        """Removals, nested simplifications, simpler replacements and exchanges of every term, scored."""
        moves = []
        for t in model:
            rest = tuple(x for x in model if x != t)
            label = self.catalogue.describe(t)
            moves.append(self.score(model, rest, "remove", label))
            if self.exchanging:
                moves.extend(self.exchanges(model, t, rest))
            for s in self.catalogue.simpler(t):
                if s.cand != t.cand and any(x.cand == s.cand for x in rest):
                    continue
                s2 = self.admissible(rest, s)
                if s2 is not None and s2 != t:
                    moves.append(self.score(model, model_key([*rest, s2]), "simplify",
                                            f"{label} -> {self.catalogue.describe(s2)}"))
            if len(t.comps) >= SWAP_MIN_PARAMS:
                moves.extend(self.swaps(model, t, rest))
        return moves

    def swaps(self, model: tuple[Term, ...], t: Term, rest: tuple[Term, ...]) -> list[Move]:
        """Replacements of ``t`` by one or two other candidates with fewer parameters in all (screened in-sample,
        the best :data:`SWAP_SCREEN` scored held out) that explain what ``t`` explains and nothing more (added to the
        model with ``t``, they would not lower ``L``)."""
        assert self.lin is not None
        held = {x.cand for x in model}
        singles = [self.catalogue.full(c) for c in range(len(self.catalogue))
                   if c not in held and len(self.catalogue.full(c).comps) < len(t.comps)]
        fits = self.lin.added_ssr(rest, singles)
        ranked = [singles[k] for k in np.argsort(fits, kind="stable")[:SWAP_SCREEN]]
        combos = [(a,) for a in ranked] + [(a, b) for i, a in enumerate(ranked) for b in ranked[i + 1:]
                                           if len(a.comps) + len(b.comps) < len(t.comps)]
        combos.sort(key=lambda c: self.lin.ssr([*rest, *c]) if self.lin else 0.0)
        out = []
        for combo in combos[:SWAP_SCREEN]:
            cur: list[Term] = list(rest)
            for s in combo:
                s2 = self.admissible(tuple(cur), s)
                if s2 is None or s2 != s:
                    break
                cur.append(s2)
            else:
                if self.score(model, model_key([*model, *cur[len(rest):]]), "", "", stats=False).delta_L < 0.0:
                    continue  # the replacement explains something ``t`` does not: a forward step's business
                label = f"{self.catalogue.describe(t)} -> " + " + ".join(self.catalogue.describe(s) for s in combo)
                out.append(self.score(model, model_key(cur), "replace", label))
        return out

    def backward(self, model: tuple[Term, ...]) -> tuple[tuple[Term, ...], bool]:
        """Backward moves at the current linearisation until none lowers ``L`` (module docstring)."""
        changed = False
        for _ in range(MAX_BACKWARD):
            moves = [m for m in self.backward_moves(model) if m.delta_L <= 0.0 and -max(m.t_min, m.z_min) < BACKWARD_T
                     and (m.action != "exchange" or m.delta_L < -EXCHANGE_MIN)]
            if not moves:
                break
            best = min(moves, key=lambda m: (m.delta_L, self.catalogue.n_params(m.model)))
            self.steps.append(best.record())
            if best.action == "exchange":  # the term given up becomes a rival of the one taken
                (old,), (new,) = set(model) - set(best.model), set(best.model) - set(model)
                self.rivals[new.cand] = [old, *(r for r in self.rivals.get(old.cand, []) if r.cand != new.cand)]
            model, changed = best.model, True
        return model, changed


def select(catalogue: Catalogue, refitter: Refitter, options: SelectionOptions,
           start: Sequence[Term] = ()) -> Selection:
    """Stepwise selection (module docstring) with the nonlinear refits of ``refitter``."""
    sel = Selector(catalogue, refitter, options)
    model = model_key(start)
    sel.lin = refitter.relinearise(model)
    d_before = sel.lin.heldout(())
    sel.visited.add(model)
    sensors = {i for i, e in enumerate(catalogue.effects) if catalogue.is_sensor_own(i)}
    for phase, allowed in (("sensors", sensors), ("all", None)):
        if phase == "sensors" and not sensors:
            continue
        sel.allowed = allowed
        model = _forward(sel, model, phase)
    sel.exchanging = True  # the terms that entered ahead of an equal rival, judged at the final residual
    model, changed = sel.backward(model)
    if changed:
        sel.visited.add(model)
        model = _forward(sel, _settle(sel, model), "all")
    return Selection(model, sel.steps, sel.rejected, d_before, sel.lin.heldout(model))


def _forward(sel: Selector, model: tuple[Term, ...], phase: str) -> tuple[Term, ...]:
    """Forward steps (each settled by a refit and a backward pass) until none qualifies or the cap is reached."""
    assert sel.lin is not None
    for _ in range(sel.options.max_rounds):
        if sel.options.max_effects is not None and len(model) >= sel.options.max_effects:
            break
        d0 = sel.lin.heldout(model)
        moves = sel.forward_moves(model)
        ok = [m for m in moves if sel.accept(m, d0)]
        best = sel.best(ok or moves, model) if moves else None
        if best is None or not ok:
            if best is not None:  # the statistics of the best move refused (not computed for a rising L)
                best = sel.score(model, best.model, best.action, best.label, stats=True)
                sel.steps.append({**best.record(), "accepted": False, "phase": phase})
            break
        sel.steps.append({**best.record(), "accepted": True, "phase": phase})
        sel.note_rivals(best, moves, model, sel.kappa(d0))
        model = best.model
        sel.visited.add(model)
        model = _settle(sel, model)
    return model


def _settle(sel: Selector, model: tuple[Term, ...]) -> tuple[Term, ...]:
    """Refit after an accepted step (linearise every candidate again there unless the refit confirms the current
    linearisation), then the backward pass (its moves are linear; the next accepted step, or the end of the
    selection, refits what it leaves)."""
    assert sel.lin is not None
    if not sel.refitter.confirm(model, sel.lin.ssr(model)):
        sel.lin = sel.refitter.relinearise(model)
    model = sel.physical(model)
    model, _ = sel.backward(model)
    sel.visited.add(model)
    return model
