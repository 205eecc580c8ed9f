"""Is a covariance right in every direction?  Held-out NEES per principal direction and per configuration region,
coverage of the 68 / 95 / 99 % ellipsoids, held-out log-likelihood; for the three choices of the PPOE perturbation
covariances: the user's, the user's times one global scale, the learned ones (:mod:`perturbations`).

For a residual row ``r_n`` (d components) and its predicted covariance ``C_n = V diag(s) V^T``:

* NEES ``r^T C^-1 r`` (mean d when right), and along each principal axis ``k`` (sorted by ``s``, smallest first)
  ``z_k^2 = (v_k^T r)^2 / s_k`` (mean 1 when the ellipsoid is right along that axis);
* coverage: the share of rows inside the ``p`` ellipsoid (``NEES <= chi2_d(p)``), and per axis ``|z_k| <=
  Phi^-1((1 + p) / 2)``; nominal ``p``;
* log-likelihood per row ``-1/2 (NEES + log det 2 pi C)``;
* regions: the rows split into terciles of the size of a reference covariance (``sqrt tr C``, by default the
  learned one), so an ellipsoid right on average but wrong near some configurations shows.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["LEVELS", "CovarianceCheck", "check_covariance", "compare_choices", "size_regions"]

#: the nominal coverage levels checked
LEVELS = (0.68, 0.95, 0.99)
#: configuration regions (terciles of the reference ellipsoid's size)
N_REGIONS = 3


@dataclass
class CovarianceCheck:
    """One covariance choice on held-out rows (module docstring); ``per_axis`` lists the principal axes smallest
    first; coverage keys are the nominal levels as strings (``"0.68"``)."""

    n: int
    nees: float
    loglik: float
    coverage: dict[str, float]
    nees_per_axis: list[float]
    coverage_per_axis: list[dict[str, float]]
    nees_per_region: list[float] = field(default_factory=list)
    coverage_per_region: list[dict[str, float]] = field(default_factory=list)

    def worst_coverage_error(self) -> float:
        """The largest |coverage - nominal| over the levels, the whole ellipsoid and every axis."""
        errs = [abs(self.coverage[k] - float(k)) for k in self.coverage]
        errs += [abs(c[k] - float(k)) for c in self.coverage_per_axis for k in c]
        return max(errs) if errs else float("nan")

    def to_json(self) -> dict[str, Any]:
        return {"n": self.n, "nees": self.nees, "loglik_per_row": self.loglik, "coverage": self.coverage,
                "nees_per_axis": self.nees_per_axis, "coverage_per_axis": self.coverage_per_axis,
                "nees_per_region": self.nees_per_region, "coverage_per_region": self.coverage_per_region}


def check_covariance(r: np.ndarray, C: np.ndarray, regions: np.ndarray | None = None,
                     levels: Sequence[float] = LEVELS) -> CovarianceCheck:
    """:class:`CovarianceCheck` of rows ``r`` (n, d) under ``C`` (n, d, d); ``regions`` (n,) ints (optional);
    non-finite rows are ignored."""
    from scipy.stats import chi2, norm

    ok = np.all(np.isfinite(r), axis=1)
    r, C = r[ok], C[ok]
    n, d = r.shape
    s, V = np.linalg.eigh(C)
    s = np.maximum(s, 1e-300)
    z2 = np.einsum("nik,ni->nk", V, r) ** 2 / s
    nees = z2.sum(axis=1)
    ll = -0.5 * (nees + np.sum(np.log(2.0 * np.pi * s), axis=1))
    lim = {f"{p:g}": (float(chi2.ppf(p, d)), float(norm.ppf(0.5 + p / 2.0) ** 2)) for p in levels}

    def cover(m: np.ndarray) -> dict[str, float]:
        return {k: float(np.mean(nees[m] <= v[0])) if m.any() else float("nan") for k, v in lim.items()}

    every = np.ones(n, dtype=bool)
    out = CovarianceCheck(
        n=n, nees=float(nees.mean()) if n else float("nan"), loglik=float(ll.mean()) if n else float("nan"),
        coverage=cover(every), nees_per_axis=[float(v) for v in z2.mean(axis=0)],
        coverage_per_axis=[{k: float(np.mean(z2[:, a] <= v[1])) for k, v in lim.items()} for a in range(d)])
    if regions is not None:
        reg = np.asarray(regions)[ok]
        for g in range(int(reg.max(initial=-1)) + 1):
            m = reg == g
            out.nees_per_region.append(float(nees[m].mean()) if m.any() else float("nan"))
            out.coverage_per_region.append(cover(m))
    return out


def size_regions(C_ref: np.ndarray, n_regions: int = N_REGIONS) -> np.ndarray:
    """Region (n,) of each row: the ``n_regions``-quantile of ``sqrt tr C_ref`` it falls in (0 = smallest)."""
    size = np.sqrt(np.trace(C_ref, axis1=-2, axis2=-1))
    edges = np.quantile(size, np.linspace(0.0, 1.0, n_regions + 1)[1:-1])
    return np.searchsorted(edges, size, side="right")


def compare_choices(r: np.ndarray, choices: Mapping[str, np.ndarray], reference: str | None = None
                    ) -> dict[str, CovarianceCheck]:
    """:func:`check_covariance` of each named covariance ``(n, d, d)`` on the same rows, with the regions of
    ``reference`` (default: the last choice)."""
    ref = choices[reference] if reference is not None else list(choices.values())[-1]
    regions = size_regions(ref)
    return {k: check_covariance(r, C, regions) for k, C in choices.items()}
