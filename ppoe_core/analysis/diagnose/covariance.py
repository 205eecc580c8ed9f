"""The one covariance routine of the effect parameters (their 95 % intervals).

At the fitted model, with the whitened residual ``e`` and the columns ``G`` of the chosen parameters, every
segment's nuisance projected out (:meth:`LinearSystem.projected`: the intervals are marginal over the
registrations), the information is ``H = G^T G``.  With at least :data:`MIN_CLUSTERS` robot poses the covariance is
the pose-clustered sandwich ``H^-1 (sum_u g_u g_u^T) H^-1 U/(U-P)``, ``g_u = G_u^T e_u`` summed over the components
of pose ``u`` (the rows of one pose share its arm error: tracker and pixels of one stop, the points of one image;
``U/(U-P)``: the scores' degrees of freedom left after the ``P`` parameters, without which 40 poses and 6 parameters
under-cover by a tenth of sigma); with fewer it is ``s^2 H^-1``, ``s^2`` the whitened residual variance per degree
of freedom.  Intervals are normal, ``theta +- 1.96 sigma`` (Monte-Carlo coverage tests in
``test/test_diagnose_engine.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ppoe_core.analysis.diagnose.linsys import LinearSystem

__all__ = ["MIN_CLUSTERS", "ParameterCovariance", "parameter_covariance"]

#: below this many robot poses the clustered sandwich is too noisy: ``s^2 H^-1`` instead
MIN_CLUSTERS = 20


@dataclass
class ParameterCovariance:
    """Covariance (P, P) of the chosen parameters, the step from the linearisation point to the least-squares
    solution (zero at a converged fit), ``s^2`` and the kind (``clustered sandwich`` or ``s^2 H^-1``)."""

    cov: np.ndarray
    step: np.ndarray
    s2: float
    kind: str


def parameter_covariance(sys: LinearSystem, cols: np.ndarray, n_nuisance: int,
                         clustered: bool = True) -> ParameterCovariance:
    """Covariance of the parameters on ``cols`` of ``sys`` (module docstring); ``n_nuisance`` parameters were
    eliminated (degrees of freedom)."""
    e, G_all = sys.projected()
    G = G_all[:, cols]
    P = G.shape[1]
    if P == 0:
        return ParameterCovariance(np.zeros((0, 0)), np.zeros(0), float(e @ e) / max(e.size - n_nuisance, 1),
                                   "none")
    H_inv = np.linalg.pinv(G.T @ G)
    step = H_inv @ (G.T @ e)
    r = e - G @ step
    s2 = float(r @ r) / max(e.size - P - n_nuisance, 1)
    units = np.unique(sys.unit)
    if not clustered or units.size < MIN_CLUSTERS:
        return ParameterCovariance(s2 * H_inv, step, s2, "s^2 H^-1")
    scores = np.zeros((int(sys.unit.max()) + 1, P))
    np.add.at(scores, sys.unit, G * r[:, None])
    S = scores.T @ scores
    U = units.size
    return ParameterCovariance(H_inv @ S @ H_inv * U / max(U - P, 1), step, s2, "pose-clustered sandwich")
