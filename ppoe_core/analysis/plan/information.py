"""The information each candidate configuration adds, from the calibration engine's own residual blocks.

A planned pose is a row set of the engine's :class:`~ppoe_core.analysis.diagnose.block_tracker.TrackerBlock` (one
row per reflector of the model's ``trackers``, all in one tracker session: the planned poses are recorded with one
registration).  At the nominal model (the declared effects, the target effects at zero) the block's
:meth:`~ppoe_core.analysis.diagnose.block.ResidualBlock.linearise` gives, per row, the derivative ``J`` of the
prediction w.r.t. the target effects' parameters (through :meth:`Effect.basis`, the same columns ``ppoe diagnose``
fits) and ``N`` w.r.t. the registration (the nuisance).  Rows are whitened with the declared sensor noise
(:func:`~ppoe_core.analysis.diagnose.noise.whitening` at sensor scale 1, prior scale 0: the design assumes the
model explains the data down to the sensor noise, as it does after a successful calibration).

Per candidate ``u`` (summed over its rows) this module keeps ``A_u = G_u^T G_u`` (P, P), ``B_u = G_u^T N_u``
(P, K) and ``C_u = N_u^T N_u`` (K, K) with ``G = W J``, ``N = W N``.  The information of the target parameters of a
set ``S`` of poses with the registration eliminated (Schur complement) is

    ``I(S) = sum_S A_u - (sum_S B_u) (sum_S C_u)^-1 (sum_S B_u)^T``           (one registration for the set)

plus, with ``--given`` data, that data's own reduced information (its own registration).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose.block_tracker import TrackerBlock
from ppoe_core.analysis.diagnose.candidates import chain_candidates, predict_nominal
from ppoe_core.analysis.diagnose.noise import NoiseScales, whitening
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.errors import ModelConfigError, PpoeError
from ppoe_core.model.effects import Effect, make_effect
from ppoe_core.robot.tree import KinematicTree

__all__ = ["Target", "PoseInformation", "target_effects", "pose_information", "planned_stops", "reduced_information",
           "block_rows", "given_information", "PixelDesign", "check_identifiable", "ABSORBED",
           "UNPLANNABLE"]

#: effects whose columns depend on the recording (motion history, time, temperature), not on the configuration
#: alone: a pose design cannot plan them
UNPLANNABLE = ("backlash", "time_offset", "thermal_growth")
#: a parameter (or combination) keeping less than this share of its information once the registration is
#: eliminated, over every candidate at once, is not identifiable
ABSORBED = 1e-8


@dataclass
class Target:
    """One effect to plan for: the effect (zero parameters) and the indices of its planned components."""

    effect: Effect
    comps: list[int]

    @property
    def names(self) -> list[str]:
        """``name@location:parameter`` of each planned component."""
        return [f"{self.effect.name}@{self.effect.location}:{self.effect.param_names[i]}" for i in self.comps]


def target_effects(tree: KinematicTree, entries: Sequence[tuple[str, str, Sequence[str]]],
                   joints: Sequence[str] = ()) -> list[Target]:
    """The effects ``entries`` = ``(name, location, parameter names or [] for all)`` (``ppoe diagnose --effects``
    vocabulary) as :class:`Target`; an effect the engine's catalogue offers on the measured chain (``joints``: the
    joints on the path to the measured links) is taken from it (:func:`chain_candidates`: the same components as
    ``ppoe diagnose --effects`` fits, e.g. a telescopic ``mount_bending``).

    Raises
    ------
    PpoeError
        An unknown effect, a location that is not a joint / link of the URDF, an unknown parameter, an effect a pose
        design cannot plan (:data:`UNPLANNABLE`); the message names the entry.
    """
    offered = {(c.name, c.location): c for c in chain_candidates(tree, joints, {}, point=True)}
    out: list[Target] = []
    for k, (name, loc, comps) in enumerate(entries):
        where = f"effects[{k}] ({name}@{loc})"
        if name in UNPLANNABLE:
            raise ModelConfigError(f"{where}: a {name} depends on the recording (motion, time, temperature), not on "
                                   "the configuration: a pose design cannot plan it")
        if loc not in tree.robot.joints and loc not in tree.robot.links:
            raise ModelConfigError(f"{where}: location {loc!r} is neither a joint nor a link of the URDF")
        try:
            e = offered.get((name, loc)) or make_effect(name, loc, tree)
        except PpoeError as exc:
            raise ModelConfigError(f"{where}: {exc}") from exc
        bad = [c for c in comps if c not in e.param_names]
        if bad:
            raise ModelConfigError(f"{where}: unknown parameter(s) {bad} (has {list(e.param_names)})")
        idx = [e.param_names.index(c) for c in comps] if comps else list(range(e.n_params))
        out.append(Target(e, idx))
    if not out:
        raise ModelConfigError("plan: no target effects given")
    return out


def planned_stops(tree: KinematicTree, trackers: Sequence, q: Mapping[str, np.ndarray],
                  declared: Sequence[Effect]) -> Stops:
    """Tracker stops at configurations ``q`` (joint -> (M,)): one row per (configuration, reflector), reflector
    ``trackers[k]`` (``link``, ``xyz``, ``sigma``), measured = predicted by the nominal model (``declared``), one
    session.  Rows are configuration-major: row ``u * R + k``."""
    M = len(next(iter(q.values())))
    R = len(trackers)
    qq = {j: np.repeat(np.asarray(v, dtype=float), R) for j, v in q.items()}
    links = np.array([t.link for t in trackers] * M, dtype=object)
    point = np.tile(np.array([np.asarray(t.xyz, dtype=float) for t in trackers]), (M, 1))
    sigma = np.tile(np.array([float(t.sigma) for t in trackers]), M)
    n = M * R
    s = Stops(q=qq, p_meas=np.zeros((n, 3)), kind="point", link=trackers[0].link, point=point, sigma=sigma,
              session=np.zeros(n, dtype=int), session_names=["plan"], group=np.zeros(n, dtype=int),
              group_names=["plan"], reg_mask=np.ones(n, bool), score_mask=np.ones(n, bool), links=links)
    s.p_meas = predict_nominal(tree, s, list(declared))[0]
    return s


@dataclass
class PoseInformation:
    """Per candidate configuration (module docstring): ``A`` (M, P, P), ``B`` (M, P, K), ``C`` (M, K, K) and the
    whitened rows ``G`` (M, m, P), ``N`` (M, m, K) (``m`` components per configuration) for predictions; ``scale``
    (P,) the RMS column norm over the candidates (the D-criterion is computed on columns divided by it)."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    G: np.ndarray
    N: np.ndarray
    scale: np.ndarray
    sigma: np.ndarray  #: (M, m) the declared 1-sigma of each component [m or px] (whitening undone for predictions)
    points: int = -1  #: the first ``points`` components are tracker points (3 per reflector; -1: all)


@dataclass
class PixelDesign:
    """Tag pixels in the design (:mod:`~ppoe_core.analysis.plan.pixels`): the constraints that hold the camera and
    the tags, and the pixel noise [px] (1-sigma per coordinate)."""

    constraints: Any
    sigma_px: float


def block_rows(block: TrackerBlock, targets: Sequence[Target], declared: Sequence[Effect] = ()
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whitened target columns ``G`` (n, 3, P), nuisance columns ``N`` (n, 3, K) and the declared 1-sigma (n, 3) of
    every row of ``block`` at the nominal model (module docstring)."""
    lin = block.linearise(list(declared), [t.effect for t in targets], {}, {})
    W = whitening(lin.S, np.zeros_like(lin.S), NoiseScales(a=1.0, k=0.0))
    J = np.concatenate([Jc[:, :, t.comps] for Jc, t in zip(lin.J, targets)], axis=2)
    return W @ J, W @ lin.N, np.sqrt(np.einsum("nii->ni", lin.S))


def pose_information(tree: KinematicTree, trackers: Sequence, q: Mapping[str, np.ndarray],
                     targets: Sequence[Target], declared: Sequence[Effect] = (),
                     scale: np.ndarray | None = None, pixels: PixelDesign | None = None) -> PoseInformation:
    """:class:`PoseInformation` of the configurations ``q`` (joint -> (M,)) for the ``targets`` (module docstring:
    the engine's tracker block, its Jacobians and whitening).  ``scale``: the column scale of an earlier candidate
    set (then these configurations are extra poses for it: no observability checks).  ``pixels``: also one image
    of the camera's usable tags per configuration (:mod:`~ppoe_core.analysis.plan.pixels`; the camera pose a
    second nuisance)."""
    M = len(next(iter(q.values())))
    block = TrackerBlock(tree, planned_stops(tree, trackers, q, declared), declared)
    if block.dropped:
        raise PpoeError(f"plan: {block.dropped} candidate rows could not be registered (fewer than 3 "
                        "non-collinear reflector positions)")
    Gr, Nr, sr = block_rows(block, targets, declared)
    G, N, sig = Gr.reshape(M, -1, Gr.shape[2]), Nr.reshape(M, -1, Nr.shape[2]), sr.reshape(M, -1)
    points = G.shape[1]
    if pixels is not None:
        from ppoe_core.analysis.plan.pixels import pixel_rows
        Gp, Np = pixel_rows(tree, pixels.constraints, q, targets, pixels.sigma_px, declared)
        G = np.concatenate([G, Gp], axis=1)
        N = np.concatenate([np.concatenate([N, np.zeros((M, N.shape[1], Np.shape[2]))], axis=2),
                            np.concatenate([np.zeros((M, Np.shape[1], N.shape[2])), Np], axis=2)], axis=1)
        sig = np.concatenate([sig, np.full((M, Np.shape[1]), float(pixels.sigma_px))], axis=1)
    A = np.einsum("umi,umj->uij", G, G)
    B = np.einsum("umi,umk->uik", G, N)
    C = np.einsum("umk,uml->ukl", N, N)
    if scale is not None:
        return PoseInformation(A, B, C, G, N, scale, sig, points)
    scale = np.sqrt(np.mean(np.einsum("uii->ui", A), axis=0))
    names = [n for t in targets for n in t.names]
    dead = [names[i] for i in np.flatnonzero(scale <= 1e-12 * max(float(scale.max()), 1e-300))]
    if dead:
        raise PpoeError(f"plan: {dead} move no measured point in any candidate configuration (not observable by "
                        "the model's trackers)")
    check_identifiable(A.sum(0), B.sum(0), C.sum(0), scale, names)
    return PoseInformation(A, B, C, G, N, scale, sig, points)


def check_identifiable(A: np.ndarray, B: np.ndarray, C: np.ndarray, scale: np.ndarray, names: Sequence[str]) -> None:
    """Raise when the target parameters are not identifiable even from every candidate at once (``A``, ``B``,
    ``C`` summed over the candidates): a parameter whose column the registration absorbs (its information
    falls by more than :data:`ABSORBED` when the registration is eliminated), or a combination of parameters
    no pose set can tell apart (smallest scaled eigenvalue below :data:`ABSORBED` of the largest).

    Raises
    ------
    PpoeError
        Naming the parameters.
    """
    H = reduced_information(A, B, C)
    kept = np.diag(H) / np.maximum(np.diag(A), 1e-300)
    bad = [names[int(i)] for i in np.flatnonzero(kept < ABSORBED)]
    if bad:
        raise PpoeError(f"plan: {bad} cannot be told apart from the tracker registration in any pose (a rigid "
                        "motion of the whole measured chain): drop them from --effects")
    d = 1.0 / scale
    w, V = np.linalg.eigh(H * d[:, None] * d[None, :])
    if w[0] < ABSORBED * w[-1]:
        v = np.abs(V[:, 0])
        mix = [names[int(i)] for i in np.flatnonzero(v > 0.2 * v.max())]
        raise PpoeError(f"plan: {mix} cannot be told apart from each other (and the registration) in any pose of "
                        "the feasible set: drop one of them from --effects or widen the constraints")


def given_information(tree: KinematicTree, stops: Stops, targets: Sequence[Target],
                      declared: Sequence[Effect] = ()) -> np.ndarray:
    """Reduced information (P, P) of tracker stops already recorded (``ppoe plan --given``): every session with its
    own registration eliminated, at the nominal model (the measured values do not enter the information)."""
    block = TrackerBlock(tree, stops, declared)
    G, N, _ = block_rows(block, targets, declared)
    P = G.shape[2]
    H = np.zeros((P, P))
    for s in np.unique(block.segment):
        m = block.segment == s
        Gs, Ns = G[m].reshape(-1, P), N[m].reshape(-1, N.shape[2])
        H += reduced_information(Gs.T @ Gs, Gs.T @ Ns, Ns.T @ Ns)
    return H


def reduced_information(A: np.ndarray, B: np.ndarray, C: np.ndarray, ridge: float = 1e-9) -> np.ndarray:
    """``A - B C^-1 B^T`` over leading batch axes (``A`` (..., P, P), ``B`` (..., P, K), ``C`` (..., K, K)); ``C``
    gets ``ridge`` times its mean diagonal (a registration not yet determined by a few poses)."""
    K = C.shape[-1]
    if K == 0:
        return A
    d = np.einsum("...ii->...", C)[..., None, None] / K
    Cr = C + ridge * np.maximum(d, 1e-300) * np.eye(K)
    X = np.linalg.solve(Cr, np.swapaxes(B, -1, -2))
    return A - B @ X
