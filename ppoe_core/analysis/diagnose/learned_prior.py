"""``ppoe diagnose --learn-perturbations``: the perturbation covariances learned from a diagnosis' held-out
residual (:mod:`perturbations`), and the covariance check of the three choices (:mod:`covariance_check`).

The residual is the metric block's (tracker points, else 6D poses) held-out residual at the diagnosed model (the
systematic effects taken out by fits that did not see the row).  The covariances reported and written into the
model are learned from all of it.  The check is cross-fitted: the robot poses are split in two halves (by bag when
there are at least two, else alternating poses); each half is predicted by the covariances learned on the other
(the learned ones, with their structure chosen there; the one global scale of the declared prior and the sensor
scale, :func:`~ppoe_core.analysis.diagnose.noise.estimate_scales`; the declared ones as they are), and the held-out
NEES, coverage and log-likelihood of the three are compared on all rows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ppoe_core.analysis.diagnose.block import ResidualBlock
from ppoe_core.analysis.diagnose.covariance_check import CovarianceCheck, compare_choices
from ppoe_core.analysis.diagnose.noise import estimate_scales
from ppoe_core.analysis.diagnose.perturbations import (
    PerturbationFit,
    component_matrices,
    learn_perturbations,
    sigma_from_components,
)

if TYPE_CHECKING:
    from ppoe_core.analysis.diagnose.engine import Run

__all__ = ["CHOICES", "LearnedPrior", "learn_prior", "markdown_section", "write_into_model"]

#: the three covariance choices compared (the declared, the declared times one global scale, the learned)
CHOICES = ("declared", "global_scale", "learned")


@dataclass
class LearnedPrior:
    """What ``--learn-perturbations`` reports: the learned fit (components with CIs, sensor scale), the joints'
    6x6 covariances (tangent right after the joint origin, ``[rho; theta]``), and the cross-fitted check of the
    three choices (:data:`CHOICES`)."""

    block: str
    fit: PerturbationFit
    covariances: dict[str, np.ndarray]
    check: dict[str, CovarianceCheck] = field(default_factory=dict)
    split: str = ""
    #: the joints the block sees (candidates of the learning): the others keep their declared covariance
    joints: list[str] = field(default_factory=list)

    @property
    def best(self) -> str:
        """The choice with the highest held-out log-likelihood ("" without a check)."""
        return max(self.check, key=lambda k: self.check[k].loglik) if self.check else ""

    def to_json(self) -> dict[str, Any]:
        return {"block": self.block, **self.fit.to_json(),
                "covariances": {j: np.asarray(C).tolist() for j, C in self.covariances.items()},
                "joints": list(self.joints), "check_split": self.split,
                "check": {k: v.to_json() for k, v in self.check.items()}, "best_heldout": self.best}

    def summary(self) -> str:
        """One line per choice: held-out NEES (3 or 6 when right), worst coverage error, log-likelihood."""
        parts = []
        for k, c in self.check.items():
            parts.append(f"{k}: NEES {c.nees:.3g}, coverage 68/95/99 % "
                         + "/".join(f"{100 * v:.1f}" for v in c.coverage.values())
                         + f", worst axis error {100 * c.worst_coverage_error():.1f} %, log-lik {c.loglik:.4g}")
        comps = ", ".join(f"{c.name} {c.sigma:.3g}" for c in self.fit.components)
        return (f"learned perturbations ({self.block}): {comps or 'none'}; held-out check: " + "; ".join(parts)
                + (f"; best held-out log-likelihood: {self.best}" if self.best else ""))


def learn_prior(run: Run, model: tuple[Any, ...]) -> LearnedPrior | None:
    """:class:`LearnedPrior` of a finished run (module docstring); None without a tracker or pose block."""
    pr, lin = run.problem, run.lin
    assert lin is not None
    idx = next((i for i, b in enumerate(pr.blocks) if b.kind == "tracker"),
               next((i for i, b in enumerate(pr.blocks) if b.kind == "pose"), None))
    if idx is None:
        return None
    b, st = pr.blocks[idx], pr.state[idx]
    assert st.S is not None and st.Q is not None
    effects = [*pr.declared, *run.effects]
    r = lin.sys.parts[idx].raw(lin.heldout_residual(model))
    rj = b.tree.robot.joints
    axes = {j: np.asarray(rj[j].axis, dtype=float) if rj[j].movable else None for j in rj
            if rj[j].movable or j in pr.pert}
    parts = component_matrices(b, effects, axes)
    fit = learn_perturbations(r, st.S, parts)
    out = LearnedPrior(b.kind, fit, sigma_from_components(fit.components, axes),
                       joints=list(dict.fromkeys(j for j, _ in parts)))
    half, out.split = _halves(b, pr.units[idx])
    C = {k: np.full((len(r), b.dim, b.dim), np.nan) for k in CHOICES}
    for h in (0, 1):
        train, test = (half != h) & np.all(np.isfinite(r), axis=1), half == h
        if train.sum() < 10 or not test.any():
            return out
        f = learn_perturbations(r[train], st.S[train], {k: v[train] for k, v in parts.items()})
        g = estimate_scales(r[train], st.S[train], st.Q[train])
        D = sum(c.variance * np.sum([parts[m][test] for m in c.members], axis=0) for c in f.components)
        C["learned"][test] = f.sensor_scale ** 2 * st.S[test] + D
        C["global_scale"][test] = g.a ** 2 * st.S[test] + g.k ** 2 * st.Q[test]
        C["declared"][test] = st.S[test] + st.Q[test]
    ok = np.all(np.isfinite(r), axis=1)
    out.check = compare_choices(r[ok], {k: v[ok] for k, v in C.items()}, reference="learned")
    return out


def _halves(b: ResidualBlock, units: np.ndarray) -> tuple[np.ndarray, str]:
    """Half (0/1) of each row: by bag when there are >= 2 (alternating over the bags), else by robot pose."""
    groups = np.unique(b.group)
    if groups.size >= 2:
        return np.isin(b.group, groups[1::2]).astype(int), "by bag"
    return (np.asarray(units) % 2).astype(int), "by robot pose (alternating)"


#: off-diagonal share below which a learned 6x6 is written as ``sigma`` (diagonal) instead of ``covariance``
DIAGONAL_TOL = 1e-9


def write_into_model(doc: Any, learned: LearnedPrior) -> list[str]:
    """Put the learned covariances into a model document's ``perturbations`` (a ruamel round-trip mapping: other
    keys and comments stay): each learned joint's entry gets ``sigma`` (diagonal) or ``covariance``; declared
    joints the block sees that the learned model leaves out get zero sigmas (exact), joints it does not see keep
    theirs; ``joint_noise`` of the joints it sees is removed (the ``axial`` class holds it).  Returns the header
    lines saying so."""
    pert = doc.get("perturbations")
    if pert is None:
        doc["perturbations"] = pert = {}
    seen = set(learned.joints) | set(learned.covariances)
    for jn in list(pert):
        if jn in seen and jn not in learned.covariances:
            entry = pert[jn]
            entry.pop("covariance", None)
            entry["sigma"] = [0.0] * 6
    for jn, C in learned.covariances.items():
        C = np.asarray(C, dtype=float)
        entry = pert.get(jn)
        if entry is None:
            pert[jn] = entry = {}
        off = np.abs(C - np.diag(np.diag(C))).max(initial=0.0)
        if off <= DIAGONAL_TOL * max(float(np.abs(C).max(initial=0.0)), 1e-300):
            entry.pop("covariance", None)
            entry["sigma"] = [float(np.sqrt(max(v, 0.0))) for v in np.diag(C)]
        else:
            entry.pop("sigma", None)
            entry["covariance"] = [[float(v) for v in row] for row in C]
    jn_sec = doc.get("joint_noise") or {}
    dropped = [j for j in list(jn_sec) if j in seen]
    for j in dropped:
        del jn_sec[j]
    return [f"# perturbations learned from the held-out residual ({learned.block}; docs/covariance.md): "
            + ", ".join(f"{c.name} {c.sigma:.3g}" for c in learned.fit.components),
            f"# sensor noise scale estimated beside them: {learned.fit.sensor_scale:.3g} (the sensor sigmas here "
            "are unchanged)" + (f"; joint_noise of {dropped} removed (the learned axial class holds it)"
                                if dropped else ""),
            f"# held-out check: best log-likelihood {learned.best or 'not checked'} (diagnose.md, Learned "
            "perturbations)"]


def markdown_section(learned: LearnedPrior | None) -> list[str]:
    """The report's "Learned perturbations" section (none without ``--learn-perturbations``)."""
    if learned is None:
        return []
    out = ["## Learned perturbations", "",
           f"From the held-out {learned.block} residual at the diagnosed model (docs/covariance.md); 1-sigma per "
           "direction of the axis class [rad or m], 95 % interval; sensor noise scale "
           f"{learned.fit.sensor_scale:.3g} [{learned.fit.sensor_ci[0]:.3g}, {learned.fit.sensor_ci[1]:.3g}].", "",
           "| joints | axis class | sigma | 95 % interval |", "|---|---|---|---|"]
    for c in learned.fit.components:
        lo, hi = c.to_json()["sigma_ci"]
        out.append(f"| {', '.join(j for j, _ in c.members)} | {c.members[0][1]} | {c.sigma:.4g} | "
                   f"[{lo:.4g}, {hi:.4g}] |")
    out += ["", f"Held-out check ({learned.split}; each half predicted by what the other half gives; best "
            f"log-likelihood: {learned.best or '-'}):", "",
            "| covariance | NEES | coverage 68 / 95 / 99 % | NEES per principal axis (small -> large) | "
            "NEES per size region | log-likelihood / row |", "|---|---|---|---|---|---|"]
    for k, ch in learned.check.items():
        out.append(f"| {k} | {ch.nees:.3g} | " + " / ".join(f"{100 * v:.1f}" for v in ch.coverage.values())
                   + " | " + " ".join(f"{v:.2f}" for v in ch.nees_per_axis) + " | "
                   + " ".join(f"{v:.2f}" for v in ch.nees_per_region) + f" | {ch.loglik:.4g} |")
    return out + [""]
