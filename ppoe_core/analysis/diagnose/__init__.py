"""``ppoe diagnose``: trace the residual of a PPOE model to systematic effects, add them, report.

One design (docs/diagnose.md):

* **Residual blocks** (:mod:`block`): one per measurement kind -- tracker points (:mod:`block_tracker`, a
  registration per session), 6D poses (:mod:`block_pose`), tag pixels (:mod:`block_pixels`, camera intrinsics and
  tag placement as effects), accelerometer tilts (:mod:`block_imu`, a tilt per placement), contacts
  (:mod:`block_contact`): whitened residuals, Jacobians w.r.t. every candidate effect through
  :meth:`Effect.basis`, nuisances, robot poses as clusters.
* **One solver** (:mod:`solver`): all blocks stacked (:mod:`linsys`), nuisances eliminated per segment (Schur),
  Gauss-Newton / Levenberg-Marquardt on the nonlinear chain, optional robust loss; the noise of each block
  estimated from its residual (:mod:`noise`, two variance components: sensor and declared prior).
* **One selection routine** (:mod:`selection`): stepwise by penalised held-out likelihood (cross-validated over
  robot poses or bags, :mod:`crossval`), group moves, each step refitted, a backward pass after each (removal,
  nested simpler variants, simpler replacements; :mod:`terms`).
* **One covariance routine** (:mod:`covariance`): pose-clustered sandwich.
* **What is left** (:mod:`significance`): can held-out data predict the residual from the configuration, time or
  image position?  Not judged against the declared prior.
* :func:`diagnose` (:mod:`engine`) runs it on measurements; :func:`diagnose_bags` (:mod:`files`) on bags, exactly
  as the CLI; :mod:`report` writes the report and the diagnosed model; :mod:`testing` scores a fitted model on
  other bags.
"""

from __future__ import annotations

from ppoe_core.analysis.diagnose.block import Linearisation, ResidualBlock
from ppoe_core.analysis.diagnose.block_contact import ContactBlock, Contacts
from ppoe_core.analysis.diagnose.block_imu import ImuBlock
from ppoe_core.analysis.diagnose.block_pixels import PixelBlock
from ppoe_core.analysis.diagnose.block_pose import PoseBlock
from ppoe_core.analysis.diagnose.block_tracker import TrackerBlock
from ppoe_core.analysis.diagnose.candidates import candidate_effects, predict_nominal
from ppoe_core.analysis.diagnose.engine import Measurements, diagnose
from ppoe_core.analysis.diagnose.files import diagnose_bags, load_measurements
from ppoe_core.analysis.diagnose.linear_problem import ChosenTerm, LinearProblem, LinearSelection, select_linear
from ppoe_core.analysis.diagnose.load_pixels import contacts_from_bag, pixels_from_bag
from ppoe_core.analysis.diagnose.load_stops import stops_from_bag
from ppoe_core.analysis.diagnose.pixels import (
    PixelObs,
    camera_mount_joint,
    concat_pixel_obs,
    pixel_rms,
    pixel_stats,
    predict_pixels,
    project,
)
from ppoe_core.analysis.diagnose.report import load_model, write_model_yaml, write_report
from ppoe_core.analysis.diagnose.results import BlockReport, DiagnoseOptions, DiagnoseResult, EffectReport
from ppoe_core.analysis.diagnose.selection import SelectionOptions
from ppoe_core.analysis.diagnose.solver import Problem
from ppoe_core.analysis.diagnose.stops import Stops, motion_signs
from ppoe_core.analysis.diagnose.testing import protocol_scores, score_stops

__all__ = [
    "BlockReport",
    "ChosenTerm",
    "ContactBlock",
    "Contacts",
    "DiagnoseOptions",
    "DiagnoseResult",
    "EffectReport",
    "ImuBlock",
    "LinearProblem",
    "LinearSelection",
    "Linearisation",
    "Measurements",
    "PixelBlock",
    "PixelObs",
    "PoseBlock",
    "Problem",
    "ResidualBlock",
    "SelectionOptions",
    "Stops",
    "TrackerBlock",
    "camera_mount_joint",
    "candidate_effects",
    "concat_pixel_obs",
    "contacts_from_bag",
    "diagnose",
    "diagnose_bags",
    "load_measurements",
    "load_model",
    "motion_signs",
    "pixel_rms",
    "pixel_stats",
    "pixels_from_bag",
    "predict_nominal",
    "predict_pixels",
    "project",
    "protocol_scores",
    "score_stops",
    "select_linear",
    "stops_from_bag",
    "write_model_yaml",
    "write_report",
]
