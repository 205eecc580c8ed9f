"""``ppoe diagnose``: trace the residual of a PPOE model to systematic effects, add them, report.

Pipeline (issue 6, docs/conventions.md sec. 6):

1. **Residuals.**  Static stops (:class:`Stops`): measured tracker points (a reflector on a link,
   in the tracker's own frame, the tracker-to-base registration is a nuisance estimated per
   session) or ground-truth poses (in the base frame).  The nominal model includes the effects
   already declared in the model YAML.
2. **Candidates.**  Every catalogue effect (:mod:`ppoe_core.model.effects`) at every plausible location
   of the measured chain.  All effects are linear in their parameters and small, so the
   measured quantity is linearised once at the nominal chain, ``x = x0 + G theta``; the
   linearisation error is checked on the final model with the full nonlinear chain.
3. **Fit.**  Gauss-Newton over the effect parameters and the per-session registrations
   (left perturbation ``T <- Exp(delta) T``), the registrations eliminated by a Schur complement.
4. **Selection.**  Greedy forward selection by held-out residual (cross-validation over stops
   within sessions, or leave-one-group-out over bags/files): a candidate is added when it is
   identifiable together with the registration and the effects already chosen (scaled
   reduced information matrix: condition number below ``max_condition``; components a
   ``link_error`` cannot separate are dropped), and when it lowers the held-out mean squared
   error by at least ``min_gain`` (relative) with a paired one-sided t statistic of at least
   ``min_t`` over the held-out stops (default 4: about 50 candidates are tested per round and
   held-out errors within a session are correlated, so the usual 2-3 would over-select).
   Compliances must come out non-negative (a structure yields along its load): a candidate
   whose fit needs a negative compliance is rejected as unphysical rather than used to absorb
   a residual of another shape.  What no candidate explains is reported as unexplained.
5. **Confidence intervals** from the Gauss-Newton covariance ``s^2 H_red^-1`` (``s^2`` the
   residual variance), 95 % two-sided normal.
6. **Sigma refit.**  The first-order PPOE covariance of the measured point (model perturbations
   and joint noise, eq. 18 to first order) plus the sensor noise is scaled by ``k^2`` so that the
   mean held-out NEES equals its expectation (the measurement dimension).
7. **Report**: JSON (contract keys ``effects``, ``residual_before``, ``residual_after``),
   markdown, a PNG plot and the updated model YAML.
8. **Tag pixels** (second stage, :func:`diagnose_pixels`): reprojection residuals of tag points
   through link -> root -> camera (plumb_bob), whitened by the pixel sigma plus the declared
   covariance propagated to the pixels; ``camera_extrinsics`` candidates at each camera's mount
   joint, selected by cross-validation over poses, CIs from a pose-clustered sandwich
   covariance; held-out pixel RMS, noise floor and NEES per camera.
9. **Joint fit** (final fit, :func:`joint_fit`, :mod:`joint_cv`): the effects the stages chose plus every
   camera's ``camera_extrinsics`` fitted to tracker points and tag pixels at once (robust nonlinear least
   squares, per-sensor noise, pose-clustered CIs), scored by k-fold cross-validation over robot poses.
"""

from __future__ import annotations

from ppoe_core.analysis.diagnose.candidates import Candidate, candidate_effects, measurement_jacobian, predict_nominal
from ppoe_core.analysis.diagnose.engine import diagnose, protocol_scores
from ppoe_core.analysis.diagnose.imu import (
                                             diagnose_imu,
                                             imu_candidates,
                                             imu_jacobian,
                                             imu_tilt_covariance,
                                             imu_tilt_raw,
                                             imu_tilt_residuals,
)
from ppoe_core.analysis.diagnose.joint_cv import add_joint_fit, joint_heldout, joint_pose_ids, score_joint
from ppoe_core.analysis.diagnose.joint_fit import JointFit, JointProblem, joint_fit
from ppoe_core.analysis.diagnose.linear import FitResult, LinearProblem, make_folds
from ppoe_core.analysis.diagnose.pixel_stage import (
                                             PixelDiagnosis,
                                             add_pixel_diagnosis,
                                             concat_pixel_obs,
                                             diagnose_pixels,
                                             pixels_from_bag,
)
from ppoe_core.analysis.diagnose.pixels import (
                                             PixelObs,
                                             camera_mount_joint,
                                             pixel_candidates,
                                             pixel_chain_jacobians,
                                             pixel_covariance,
                                             pixel_jacobian,
                                             pixel_rms,
                                             pixel_stats,
                                             predict_pixels,
)
from ppoe_core.analysis.diagnose.report import load_model, write_model_yaml, write_report
from ppoe_core.analysis.diagnose.results import DiagnoseOptions, DiagnoseResult
from ppoe_core.analysis.diagnose.stops import Stops, motion_signs, stops_from_bag

__all__ = [
    "measurement_jacobian",
    "predict_nominal",
    "imu_jacobian",
    "imu_tilt_raw",
    "Stops",
    "Candidate",
    "FitResult",
    "DiagnoseOptions",
    "DiagnoseResult",
    "LinearProblem",
    "candidate_effects",
    "motion_signs",
    "diagnose",
    "stops_from_bag",
    "protocol_scores",
    "imu_tilt_residuals",
    "make_folds",
    "load_model",
    "write_model_yaml",
    "write_report",
    "PixelObs",
    "PixelDiagnosis",
    "pixels_from_bag",
    "predict_pixels",
    "pixel_jacobian",
    "pixel_chain_jacobians",
    "pixel_covariance",
    "pixel_rms",
    "pixel_stats",
    "pixel_candidates",
    "camera_mount_joint",
    "diagnose_pixels",
    "concat_pixel_obs",
    "add_pixel_diagnosis",
    "diagnose_imu",
    "imu_candidates",
    "imu_tilt_covariance",
    "JointFit",
    "JointProblem",
    "joint_fit",
    "joint_heldout",
    "joint_pose_ids",
    "score_joint",
    "add_joint_fit",
]
