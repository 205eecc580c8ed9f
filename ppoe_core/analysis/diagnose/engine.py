"""``diagnose()``: every measurement block in one problem, effects selected, fitted, tested and reported.

1. **Blocks** (:mod:`block`): tracker points or 6D poses, tag pixels, accelerometer tilts, contact distances, each
   with its nuisances (registration per tracker session, placement tilt per accelerometer group) and noise model.
2. **Noise**: each block's sensor and prior scales are estimated from the residual of the current fit
   (:mod:`noise`), not taken from the declaration; the whitening follows them.
3. **Candidates** (:mod:`terms`): every catalogue effect at every location some block can see, with nested simpler
   variants and group moves.
4. **Selection** (:mod:`selection`): stepwise by penalised held-out likelihood, cross-validated over robot poses or
   bags (:mod:`crossval`), every accepted step refitted on the full nonlinear chain (:mod:`solver`), a backward pass
   after each.  ``options.effects`` fits a declared set instead.
5. **Result** (:mod:`outcome`): CIs (:mod:`covariance`), held-out residuals per block, the structure left in them
   (:mod:`significance`), summary.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
import numpy as np
import yaml

from ppoe_core.analysis.diagnose.block import ResidualBlock
from ppoe_core.analysis.diagnose.block_imu import ImuBlock, at_rest
from ppoe_core.analysis.diagnose.block_pixels import PixelBlock
from ppoe_core.analysis.diagnose.block_pose import PoseBlock
from ppoe_core.analysis.diagnose.block_tracker import TrackerBlock
from ppoe_core.analysis.diagnose.block_contact import ContactBlock, Contacts
from ppoe_core.analysis.diagnose.covariance import parameter_covariance
from ppoe_core.analysis.diagnose.crossval import Linearised, assign_folds
from ppoe_core.analysis.diagnose.noise import estimate_scales
from ppoe_core.analysis.diagnose.outcome import build_result
from ppoe_core.analysis.diagnose.pixels import PixelObs
from ppoe_core.analysis.diagnose.results import DiagnoseOptions, DiagnoseResult
from ppoe_core.analysis.diagnose.selection import Selection, SelectionOptions, select
from ppoe_core.analysis.diagnose.solver import Problem
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.analysis.diagnose.terms import Catalogue, Term, model_key
from ppoe_core.errors import MeasurementError, ModelConfigError, PpoeError, UnknownJointError
from ppoe_core.model.effects import Effect, make_effect
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import Robot

__all__ = ["Measurements", "Run", "build_blocks", "catalogue_of", "diagnose"]

#: an accelerometer block needs at least this many rows at rest
MIN_IMU_ROWS = 6
#: rounds of refit and noise re-estimation at the start (the declared scales are only a start)
NOISE_ROUNDS = 3
#: a refit confirms the linearisation when its cost is within this share of the linearised system's prediction
LINEARISATION_TOL = 0.01
#: everything is linearised again, with new noise scales, when a refit lowered the whitened cost by this share
NOISE_REESTIMATE = 0.05
#: the order of the candidates: an exact tie (effects the data cannot tell apart) goes to the earlier one
TIE_ORDER = ("camera_extrinsics", "camera_intrinsics", "tag_offset", "time_offset", "base_tilt", "joint_offset",
             "gravity_compliance", "lateral_compliance", "mount_bending", "backlash", "thermal_growth", "link_error")


@dataclass
class Measurements:
    """What a diagnosis fits: tracker points or poses (with accelerometers in ``stops.imus``), tag pixels, contacts."""

    stops: Stops | None = None
    pixels: PixelObs | None = None
    contacts: Contacts | None = None


def build_blocks(tree: KinematicTree, data: Measurements, declared: Sequence[Effect],
                 options: DiagnoseOptions) -> list[ResidualBlock]:
    """One residual block per measurement kind present (``options.blocks`` selects)."""
    want = set(options.blocks) if options.blocks else None
    blocks: list[ResidualBlock] = []
    s = data.stops
    if s is not None and len(s):
        kind = "tracker" if s.kind == "point" else "pose"
        if want is None or kind in want:
            blocks.append(TrackerBlock(tree, s, declared) if kind == "tracker" else PoseBlock(tree, s))
        if s.imus and (want is None or "imu" in want) and at_rest(s).sum() >= MIN_IMU_ROWS:
            blocks.append(ImuBlock(tree, s, options.imu_sigma or {}))
    if data.pixels is not None and len(data.pixels) and (want is None or "pixels" in want):
        blocks.append(PixelBlock(tree, data.pixels))
    if data.contacts is not None and len(data.contacts) and (want is None or "contact" in want):
        blocks.append(ContactBlock(tree, data.contacts))
    if not blocks:
        raise MeasurementError("diagnose: no measurements to fit (no tracker points, poses, pixels, accelerometers "
                               "or contacts)")
    return blocks


class Run:
    """One diagnosis in progress: the problem, the catalogue, the current values and the folds."""

    def __init__(self, problem: Problem, catalogue: Catalogue, unit_fold: np.ndarray) -> None:
        self.problem, self.catalogue, self.unit_fold = problem, catalogue, unit_fold
        self.values: dict[int, np.ndarray] = {}
        self.effects: list[Effect] = []
        self.model: tuple[Term, ...] = ()
        self.lin: Linearised | None = None
        self.nominal: Linearised | None = None  #: the first linearisation with every effect zero
        self.noise_cost: float | None = None
        self.lin_whitening = -1  #: the problem's whitening that ``lin`` was computed in
        self.lin_model: tuple[Term, ...] | None = None  #: the model ``lin`` was computed at
        self.refitted = False  #: whether a refit moved the values since

    def model_effects(self, model: Sequence[Term]) -> list[Effect]:
        return [self.catalogue.effect(t, self._masked(t)) for t in model]

    def _masked(self, t: Term) -> np.ndarray:
        v = self.values.get(t.cand, np.zeros(self.catalogue.effects[t.cand].n_params))
        out = np.zeros_like(v)
        out[list(t.comps)] = v[list(t.comps)]
        return out

    def relinearise(self, model: tuple[Term, ...], final: bool = False) -> Linearised:
        """Refit ``model`` on the nonlinear chain, re-estimate the noise scales, and linearise every candidate there
        (the first time and the ``final`` time :data:`NOISE_ROUNDS` rounds of refit and noise)."""
        if self.lin is not None and self.lin_model == model and not self.refitted and not final:
            return self.lin  # nothing changed since it was made
        first = self.lin is None
        rounds = NOISE_ROUNDS if first or final else 1
        for k in range(rounds):
            self.refit(model)
            self.estimate_noise(self.effects, self.catalogue.n_params(model))
            if k < rounds - 1:
                self.problem.system(self.effects, [])  # whitening with the new scales (the last: below)
        sys = self.problem.system(self.effects, self.catalogue.effects)
        by_cand = {t.cand: t for t in model}
        parts = [self._masked(by_cand[c]) if c in by_cand else np.zeros(e.n_params)
                 for c, e in enumerate(self.catalogue.effects)]
        theta = np.concatenate(parts) if parts else np.zeros(0)
        self.lin = Linearised(sys, self.catalogue, theta, self.unit_fold)
        self.lin.nominal = self.nominal
        if self.nominal is None and not np.any(theta):
            self.nominal = self.lin  #: every effect zero: where a term's own identifiability is judged too
        self.lin_whitening = self.problem.whitening_count
        self.lin_model, self.refitted = model, False
        self.noise_cost = self.lin.ssr(model)  # the cost in the new whitening
        return self.lin

    def refit(self, model: tuple[Term, ...]) -> float:
        """Refit ``model`` on the nonlinear chain (values kept as the next start); returns the whitened cost."""
        jac = None
        if self.lin is not None and self.lin_whitening == self.problem.whitening_count:
            jac = self.lin.sys.subset(self.lin.columns(model), [len(t.comps) for t in model])
        fit = self.problem.refit(self.model_effects(model), jacobian=jac)
        for t, e in zip(model, fit.effects):
            full = np.zeros(self.catalogue.effects[t.cand].n_params)
            full[list(t.comps)] = e.params
            self.values[t.cand] = full
        self.model, self.effects = model, fit.effects
        self.refitted = True
        return fit.cost

    def confirm(self, model: tuple[Term, ...], predicted: float) -> bool:
        """Refit ``model``; whether the current linearisation still holds: the refitted cost within
        :data:`LINEARISATION_TOL` (relative) of the ``predicted`` in-sample cost of the linearised system, and
        within :data:`NOISE_REESTIMATE` of the cost the noise scales were estimated at (a fit that took away much
        of the residual needs new scales: the old ones give the rows the shape of the error it took away)."""
        cost = self.refit(model)
        linear = abs(cost - predicted) <= LINEARISATION_TOL * max(predicted, 1e-300)
        noise = self.noise_cost is None or cost >= (1.0 - NOISE_REESTIMATE) * self.noise_cost
        return linear and noise

    def estimate_noise(self, effects: Sequence[Effect], n_params: int) -> None:
        """Each block's sensor and prior scales from its residual at the fitted model (:mod:`noise`)."""
        pr = self.problem
        model = [*pr.declared, *effects]
        total = sum(len(b) * b.dim for b in pr.blocks)
        for b, st in zip(pr.blocks, pr.state):
            if st.S is None or st.Q is None:
                continue
            r = b.residual(model)
            n_comp = r.size
            used = b.n_segments * b.nuisance_dim + n_params * n_comp / max(total, 1)
            frac = max(1.0 - used / max(n_comp, 1), 0.05)
            st.scales = estimate_scales(r, st.S, st.Q, frac, st.scales if self.lin is not None else None)


def _effect_of(tree: KinematicTree, name: str, loc: str, **options: str) -> Effect:
    """A declared effect (``--effects``) with all its parameters.

    Raises
    ------
    ModelConfigError, UnknownJointError
        Not an effect of the vocabulary, or not at a location of this robot (names it).
    """
    try:
        return make_effect(name, loc, tree, None, **options)
    except (ModelConfigError, UnknownJointError) as exc:
        raise type(exc)(f"--effects {name}@{loc}: {exc}") from None


def catalogue_of(tree: KinematicTree, blocks: Sequence[ResidualBlock], options: DiagnoseOptions,
               declared: Sequence[Effect] = ()) -> Catalogue:
    """Candidates of every block (``options.candidates`` prefixes filter), ``declared`` ones (``--effects``), the
    measured chains and the cameras."""
    cands = [c for b in blocks for c in b.candidates()] + list(declared)
    # exact ties are broken by catalogue order (TIE_ORDER): a sensor's own effect before a chain effect the sensor
    # cannot tell from it (a camera moved, or the whole arm relative to a camera fixed to the root), the generic
    # link_error last (a tilted base, not a link error at the first joint)
    cands.sort(key=lambda c: TIE_ORDER.index(c.name) if c.name in TIE_ORDER else len(TIE_ORDER))
    if options.candidates:
        cands = [c for c in cands if any(c.key.startswith(p) for p in options.candidates)]
    chains = [ln for b in blocks for ln in b.chain_links()]
    cameras = {j: f for b in blocks for j, f in b.camera_mounts().items()}
    return Catalogue(tree, cands, chains, cameras)


@dataclass
class DeclaredEntry:
    """One ``--effects`` entry: effect ``name`` at ``location`` with the parameters ``components`` (all if empty)
    and, for ``thermal_growth``, its driving ``variable`` (None: the measurements' own candidate)."""

    name: str
    location: str
    components: list[str]
    variable: str | None = None


def declared_specs(specs: Sequence[str]) -> list[DeclaredEntry]:
    """``--effects``: the entries of ``name@location[comp,...]`` specs or of YAML files with an ``effects`` list of
    ``{name, location[, parameters][, variable]}`` (the parameters' names choose the components; all if none is
    given)."""
    entries: list[DeclaredEntry] = []
    for spec in specs:
        if spec.endswith((".yaml", ".yml")) and Path(spec).is_file():
            doc = yaml.safe_load(Path(spec).read_text(encoding="utf-8")) or {}
            for e in doc.get("effects") or []:
                entries.append(DeclaredEntry(str(e["name"]), str(e["location"]),
                                             list((e.get("parameters") or {}).keys()),
                                             str(e["variable"]) if e.get("variable") else None))
            continue
        head, _, comps = spec.partition("[")
        name, _, loc = head.partition("@")
        entries.append(DeclaredEntry(name, loc, [c for c in comps.rstrip("]").split(",") if c]))
    return entries


def _declared_effects(tree: KinematicTree, blocks: Sequence[ResidualBlock],
                      entries: Sequence[DeclaredEntry]) -> list[Effect]:
    """The ``--effects`` entries that no block offers as a candidate, as effects (a block's own candidate carries
    what the measurements drive it with: a ``thermal_growth`` over ``time`` when there is no temperature)."""
    offered = [c for b in blocks for c in b.candidates()]
    out = []
    for d in entries:
        if not any(_matches(c, d) for c in offered):
            opts = {"variable": d.variable} if d.variable else {}
            out.append(_effect_of(tree, d.name, d.location, **opts))
    return out


def _matches(e: Effect, d: DeclaredEntry) -> bool:
    return (e.name == d.name and (e.location == d.location or getattr(e, "frame", None) == d.location)
            and (d.variable is None or getattr(e, "variable", None) == d.variable))


def _declared_model(run: Run, entries: Sequence[DeclaredEntry], options: DiagnoseOptions
                    ) -> tuple[tuple[Term, ...], dict[str, str]]:
    """The terms of the ``--effects`` entries (:func:`declared_specs`) that these measurements can identify, and the
    reasons of those left out."""
    lin = run.relinearise(())
    terms: list[Term] = []
    left_out: dict[str, str] = {}
    for d in entries:
        t = _term_of(run.catalogue, d)
        idf = lin.identifiable(tuple(terms), [t], options.max_condition, options.max_absorbed)
        if idf.ok:
            terms.append(t)
        else:
            left_out[run.catalogue.describe(t)] = idf.reason
    return model_key(terms), left_out


def _term_of(catalogue: Catalogue, d: DeclaredEntry) -> Term:
    """The catalogue term of the entry ``d``: its effect at its location (or at the camera frame it names) with its
    parameters (all if none are named).

    Raises
    ------
    ModelConfigError
        No such candidate, or parameters it does not have.
    """
    name, loc, comps = d.name, d.location, d.components
    cand = next((i for i, e in enumerate(catalogue.effects) if _matches(e, d)), None)
    if cand is None:
        raise ModelConfigError(f"--effects {name}@{loc}: no such effect in the catalogue of this robot")
    e = catalogue.effects[cand]
    bad = [c for c in comps if c not in e.param_names]
    if bad:
        raise ModelConfigError(f"--effects {name}@{loc}: no parameters {bad} (has {list(e.param_names)})")
    return Term(cand, tuple(e.param_names.index(c) for c in comps) if comps else tuple(range(e.n_params)))


def diagnose(robot: Robot, data: Measurements | Stops, declared: Sequence[Effect] = (),
             perturbation_cov: Mapping[str, np.ndarray] | None = None, joint_noise: Mapping[str, float] | None = None,
             options: DiagnoseOptions | None = None) -> DiagnoseResult:
    """Find the catalogue effects that explain the measurements (module docstring).

    Parameters
    ----------
    robot : Robot
    data : Measurements (or tracker / pose Stops alone)
    declared : effects the model already declares (part of every prediction)
    perturbation_cov : joint -> 6x6 covariance of the model's perturbation xi_j (tangent space right after the
        joint's origin); joint_noise : joint -> 1-sigma along the axis [rad or m]
    options : DiagnoseOptions
    """
    options = options or DiagnoseOptions()
    data = data if isinstance(data, Measurements) else Measurements(stops=data)
    tree = KinematicTree(robot)
    if data.stops is not None:
        check_stops(robot, data.stops)
    blocks = build_blocks(tree, data, declared, options)
    problem = Problem(blocks, declared, perturbation_cov, joint_noise, options.loss, options.loss_scale)
    entries = declared_specs(options.effects or [])
    catalogue = catalogue_of(tree, blocks, options, _declared_effects(tree, blocks, entries))
    unit_group = np.zeros(problem.n_units, dtype=int)
    for g, u in zip(problem.groups, problem.units):
        unit_group[u] = g
    mode, unit_fold = assign_folds(unit_group, options.cv, options.folds, options.seed)
    run = Run(problem, catalogue, unit_fold)
    before = run.relinearise(())
    insample_before = [b.residual([*problem.declared]) for b in blocks]
    if options.effects:
        model, left_out = _declared_model(run, entries, options)
        lin = run.relinearise(model, final=True)
        selection = Selection(model, [], left_out, before.heldout(()), lin.heldout(model))
    else:
        sel_opts = SelectionOptions(min_t=options.min_t, min_gain=options.min_gain, penalty=options.penalty,
                                    max_condition=options.max_condition, max_absorbed=options.max_absorbed,
                                    max_effects=options.max_effects, groups=options.groups)
        selection = select(catalogue, run, sel_opts)
        run.relinearise(selection.model, final=True)
        selection = _physical_signs(run, selection)
    return build_result(run, before, insample_before, selection, mode, options)


def _physical_signs(run: Run, selection: Selection) -> Selection:
    """The final model without compliance components whose reported 95 % interval (:mod:`covariance`, at the final
    noise scales) lies below zero, the most negative first, refitted after each: a reported compliance is never
    significantly negative (the selection checks the same with the linearised covariance it works with, which an
    older noise estimate may have made wider)."""
    model = selection.model
    while model:
        pr = run.problem
        sys = pr.system(run.effects, run.effects, rewhiten=False)
        n_nuis = int(sum(ns.n_segments * ns.N.shape[1] for ns in sys.nuisances))
        pc = parameter_covariance(sys, np.arange(sys.n_columns), n_nuis)
        sd = np.sqrt(np.maximum(np.diag(pc.cov), 0.0))
        worst: tuple[float, Term, int] | None = None
        for k, (t, e) in enumerate(zip(model, run.effects)):
            for i, c in enumerate(t.comps):
                v, s_ = float(e.params[i]), float(sd[sys.cols[k]][i])
                z = (v + 1.96 * s_) / max(s_, 1e-300)
                if e.param_names[i] in e.nonnegative and z < 0.0 and (worst is None or z < worst[0]):
                    worst = (z, t, c)
        if worst is None:
            break
        _, t, c = worst
        keep = tuple(x for x in t.comps if x != c)
        selection.steps.append({"action": "remove", "move": run.catalogue.describe(t),
                                "reason": "its 95 % interval lies below zero: unphysical sign"})
        model = model_key([x for x in model if x != t] + ([Term(t.cand, keep)] if keep else []))
        run.relinearise(model, final=True)
    if model == selection.model:
        return selection
    assert run.lin is not None
    return Selection(model, selection.steps, selection.rejected, selection.d_before, run.lin.heldout(model))


def check_stops(robot: Robot, stops: Stops) -> None:
    """At least 6 stops; no NaN/inf in the measurements or in the joint values the measured link needs.

    Raises
    ------
    PpoeError, MeasurementError
        Naming the first bad stop, its bag and session.
    """
    n = len(stops)
    if n < 6:
        raise PpoeError(f"diagnose: only {n} stops with measurements; need at least 6")
    bad = ~np.all(np.isfinite(stops.p_meas), axis=1)
    for jn, v in stops.q.items():
        if jn in stops.chain_joints(robot):
            bad |= ~np.isfinite(v)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise MeasurementError(f"diagnose: {int(bad.sum())} stops have non-finite measurements or joint "
                               f"values (first: stop {i} of {stops.group_names[stops.group[i]]}, session "
                               f"{stops.session_names[stops.session[i]]})")

