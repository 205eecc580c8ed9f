"""What the selection chooses from: candidate effects, their nested simpler variants and group moves.

A *term* is a candidate effect with a subset of its parameters (:class:`Term`: a ``link_error`` with some of its six
components, one axis of a two-axis compliance, a level of ``camera_intrinsics``); a *model* is a tuple of terms.
:class:`Catalogue` knows, for every term, the simpler terms nested in it (its parameters minus one, the intrinsics
level below, ``joint_offset@j`` in ``link_error@j``), and the group moves: one kind of effect on every joint of a
measured chain (``gravity_compliance`` on every joint of the left arm), the physical model of elastic robots that
one effect at a time does not reach.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import NamedTuple

import numpy as np

from ppoe_core.model.effects import Effect, make_effect
from ppoe_core.model.effects_sensor import INTRINSIC_LEVELS
from ppoe_core.robot.tree import KinematicTree

__all__ = ["Term", "Catalogue", "GROUP_KINDS"]

#: effects that model a sensor: a camera's pose and intrinsics, a tag's placement
SENSOR_EFFECTS = ("camera_extrinsics", "camera_intrinsics", "tag_offset")
#: effect kinds offered as group moves (one per measured chain): the elastic-robot model
GROUP_KINDS = ("joint_offset", "gravity_compliance", "lateral_compliance", "mount_bending")


class Term(NamedTuple):
    """Candidate ``cand`` (index into the catalogue) with its parameters ``comps`` (indices, ascending).  A named
    tuple: models are sorted and hashed hundreds of thousands of times in a selection (a dataclass's Python-level
    ``__hash__`` / ``__lt__`` took 7 % of a 19-joint diagnosis)."""

    cand: int
    comps: tuple[int, ...]


def model_key(model: Iterable[Term]) -> tuple[Term, ...]:
    """A model as a canonical (sorted) tuple."""
    return tuple(sorted(model))


class Catalogue:
    """Candidate effects (zero parameters, all components) and the relations between them (module docstring).

    Parameters
    ----------
    tree : KinematicTree
    effects : candidate effects; duplicates (same key) are dropped
    chains : measured links (the group moves run along the path from the root to each)
    cameras : camera mount joint -> camera optical frame
    """

    def __init__(self, tree: KinematicTree, effects: Sequence[Effect], chains: Sequence[str] = (),
                 cameras: dict[str, str] | None = None) -> None:
        self.tree = tree
        seen: dict[tuple[str, str, str], Effect] = {}
        for e in effects:  # one candidate per name, location and driving variable: the one with the most parameters
            place = (e.name, e.location, str(getattr(e, "variable", "")))  # (the others are nested in it)
            if place not in seen or e.n_params > seen[place].n_params:
                seen[place] = e.with_params(np.zeros(e.n_params))
        self.effects = list(seen.values())
        self.index = {e.key: i for i, e in enumerate(self.effects)}
        self.by_place = {(e.name, e.location): i for i, e in enumerate(self.effects)}
        self.chains = list(dict.fromkeys(chains))
        self._zero: dict[Term, Effect] = {}
        self.cameras = dict(cameras or {})  # camera_extrinsics location (mount joint) -> camera optical frame

    def __len__(self) -> int:
        return len(self.effects)

    def full(self, cand: int) -> Term:
        """The term with all of candidate ``cand``'s parameters (or its intrinsics' simplest level)."""
        e = self.effects[cand]
        if e.name == "camera_intrinsics":
            return Term(cand, self._level(e, INTRINSIC_LEVELS[0]))
        return Term(cand, tuple(range(e.n_params)))

    def entry_terms(self, cand: int) -> list[Term]:
        """Terms by which candidate ``cand`` may enter a model: all its parameters; every intrinsics level; a twist's
        translation or rotation alone (``link_error``, ``tag_offset``); a telescopic bending without its extension
        terms."""
        e = self.effects[cand]
        if e.name == "camera_intrinsics":
            return [Term(cand, self._level(e, lv)) for lv in INTRINSIC_LEVELS]
        if e.name == "mount_bending" and len(e.param_names) == 4:  # telescopic: the constant bending, or growing
            return [Term(cand, (0, 1)), self.full(cand)]
        if e.name in ("link_error", "tag_offset") and len(e.param_names) == 6:  # a shift, a turn, or both
            return [Term(cand, (0, 1, 2)), Term(cand, (3, 4, 5)), self.full(cand)]
        return [self.full(cand)]

    def _level(self, e: Effect, names: Sequence[str]) -> tuple[int, ...]:
        return tuple(i for i, p in enumerate(e.param_names) if p in names)

    def effect(self, term: Term, values: np.ndarray | None = None) -> Effect:
        """The effect of ``term`` with ``values`` (of the candidate's full parameter vector; zeros if None)."""
        if values is None:  # the zero-valued effect of a term: made once (the selection asks for it often)
            if term not in self._zero:
                self._zero[term] = self._effect(term, np.zeros(self.effects[term.cand].n_params))
            return self._zero[term]
        return self._effect(term, np.asarray(values, dtype=float))

    def _effect(self, term: Term, vals: np.ndarray) -> Effect:
        e = self.effects[term.cand]
        if len(term.comps) == e.n_params:
            return e.with_params(vals)
        comps = tuple(e.param_names[i] for i in term.comps)
        opts = {k: v for k, v in e.options().items() if k != "components"}
        sub = make_effect(e.name, e.location, self.tree, list(vals[list(term.comps)]), components=comps, **opts)
        return sub

    def n_params(self, model: Iterable[Term]) -> int:
        return int(sum(len(t.comps) for t in model))

    def describe(self, term: Term) -> str:
        return self.effect(term).key

    def splittable(self, term: Term) -> bool:
        """Whether a subset of ``term``'s parameters is itself an effect (``components``: a twist, the bending or
        lateral axes, the intrinsics); a ``base_tilt`` or a thermal growth enters whole or not at all."""
        return bool(self.effects[term.cand].all_components)

    def simpler(self, term: Term) -> list[Term]:
        """Terms nested in ``term`` with fewer parameters: one parameter less (an intrinsics level less; of a level
        with unidentifiable parameters pruned, the level below and each of its extra parameters less), and
        ``joint_offset@j`` for ``link_error@j``."""
        e = self.effects[term.cand]
        out: list[Term] = []
        if e.name == "camera_intrinsics":
            names = {e.param_names[i] for i in term.comps}
            below = [lv for lv in INTRINSIC_LEVELS if set(lv) < names]
            if below:  # the largest level inside it, and (a level with a part pruned) each extra parameter less
                level = set(below[-1])
                out.append(Term(term.cand, self._level(e, below[-1])))
                if names not in (set(lv) for lv in INTRINSIC_LEVELS):
                    out.extend(Term(term.cand, tuple(c for c in term.comps if c != k)) for k in term.comps
                               if e.param_names[k] not in level and len(names) - 1 > len(level))
        elif len(term.comps) > 1 and self.splittable(term):
            out.extend(Term(term.cand, tuple(c for c in term.comps if c != k)) for k in term.comps)
        if e.name == "link_error":
            j = self.by_place.get(("joint_offset", e.location))
            if j is not None:
                out.append(self.full(j))
        return out

    def is_sensor_own(self, cand: int) -> bool:
        """Whether candidate ``cand`` models a sensor rather than the robot (:data:`SENSOR_EFFECTS`, a time offset
        of a sensor frame)."""
        e = self.effects[cand]
        return e.name in SENSOR_EFFECTS or (e.name == "time_offset" and e.location in self.tree.robot.links)

    def richer(self, term: Term) -> list[Term]:
        """Terms that ``term`` is nested in, one step up: an intrinsics level more, one parameter more."""
        e = self.effects[term.cand]
        if e.name == "camera_intrinsics":
            names = {e.param_names[i] for i in term.comps}
            return [Term(term.cand, self._level(e, lv)) for lv in INTRINSIC_LEVELS if names < set(lv)]
        missing = [i for i in range(e.n_params) if i not in term.comps]
        return [Term(term.cand, tuple(sorted((*term.comps, i)))) for i in missing]

    def groups(self, model: Sequence[Term]) -> list[tuple[str, list[int]]]:
        """Group moves: ``(label, candidates)`` of one :data:`GROUP_KINDS` kind on every joint of a measured chain
        that the model does not hold yet (at least two)."""
        held = {t.cand for t in model}
        out, seen = [], set()
        for link in self.chains:
            path = self.tree.robot.path_from_root(link)
            for kind in GROUP_KINDS:
                members = [self.by_place[(kind, j)] for j in path
                           if (kind, j) in self.by_place and self.by_place[(kind, j)] not in held]
                key = (kind, tuple(members))
                if len(members) >= 2 and key not in seen:
                    seen.add(key)
                    out.append((f"{kind} on every joint to {link}", members))
        return out
