"""``ppoe evaluate``: replay a contract bag offline and score FK, PPOE-fused and naive-fused poses.

The replay runs the same core code as the live nodes:

* kinematics node -> :meth:`ppoe_core.model.ppoe.PPOEModel.fk` for every ``/joint_states`` message
  (prior ``T_base_tool`` and its PPOE covariance ``cov_tool``; batched over the bag);
* tag bearing node -> :func:`ppoe_core.sensing.tag_rows.observe_tags` (the node's function) on
  every camera image (only when the bag has images but no ``/tag_bearing/observations``:
  recorded observations are used as they are);
* contact node -> :class:`ppoe_core.sensing.contact.ContactDetector` (the node's force threshold with
  hysteresis) on every ``/wrench`` message, giving the model YAML's contact plane and
  ``Sigma_v`` at each wrench stamp in contact (only when the bag has no ``/contact/plane``:
  recorded planes are used as they are);
* fusion node -> :func:`ppoe_core.estimation.pipeline.make_pipeline` /
  :func:`~ppoe_core.estimation.pipeline.make_updater` (prior buffer, iterated LG-EKF update with
  gating, carried correction) with the fusion node's settings
  (:data:`ppoe_core.estimation.pipeline.FUSION_SETTINGS` defaults, or a node parameter file via
  :func:`load_fusion_params`; :data:`EVALUATE_SETTINGS` lists every key).

Three estimates are scored at every ground-truth sample:

``fk``
    The prior: forward kinematics of the nominal model (with its PPOE covariance for NEES).
``ppoe``
    The fusion pipeline fed with the PPOE priors.
``naive``
    The same pipeline fed with the same prior means but the model YAML's ``naive`` diagonal
    covariance (tool tangent space) instead of the PPOE covariance; the naive model knows
    nothing about the camera chain, so its tag updates get no camera-pose noise.

Ground truth
------------
``/ground_truth/pose``
    ``T_base_tool`` directly (``header.frame_id`` must be the base frame).
``/ground_truth/point``
    A reflector on ``tracker.link`` (model YAML) measured in the tracker's own frame.  The
    tracker-to-base transform is fitted (Kabsch, rotation + translation, no scale) between the
    FK reflector positions and the measured points of a **fit subset** of stops and scored on
    the disjoint **evaluation subset**:

    * bags with ``/dataset/stop`` roles (``ppoe import hilti``): one registration per station,
      fitted on its ``stationing`` stops of the chosen point set (``--fit-set``, default
      ``cross`` as the dataset's ``example_kabsch.py``), scored on its ``evaluation`` stops;
      stations without fit points are not scored (counted);
    * otherwise: one registration for the whole bag, fitted on the even-numbered ground-truth
      samples (0, 2, 4, ...) and scored on the odd-numbered ones.

Metrics (per method; all errors are estimate minus ground truth, in the base frame)
-----------------------------------------------------------------------------------
``position_3d``
    ``|p_est - p_gt|`` [m] of the tool origin (pose) or of the reflector (point).
``lateral``
    The part of that error perpendicular to the tool's z axis (approach / viewing direction;
    the paper's Table I metric): ``|e - (e . z) z|`` with ``z`` the tool z axis of the ground
    truth pose, or of the FK estimate for point ground truth [m].
``rotation``
    Angle of ``R_est^T R_gt`` [rad] (pose ground truth only).
``nees``
    ``e^T P^-1 e``: pose ground truth ``e = Log(T_est^-1 T_gt)`` with the 6x6 covariance (6
    dof); point ground truth the 3x3 covariance of the reflector position propagated from the
    tool covariance plus the tracker's ``sigma`` (3 dof).  Mean, 95 % chi-square bounds of the
    mean and the fraction of samples inside the per-sample 95 % interval.  Singular covariances
    are regularised with 1e-12 on the diagonal.

Each statistic is ``mean``, ``std``, ``rms``, ``max`` and ``n``.  NIS of the processed
measurements (at the prior, per measurement dimension) and the pipeline counts (accepted,
rejected, dropped, bad) are reported per fused method.
"""

from __future__ import annotations

from ppoe_core.analysis.evaluate.metrics import (
    METHODS, error_stats, nees_stats, point_covariance, position_errors, rotation_errors,
)
from ppoe_core.analysis.evaluate.options import (
    EVALUATE_SETTINGS, REPLAY_SETTINGS, EvaluateOptions, Evaluation, load_fusion_params, load_sources,
)
from ppoe_core.analysis.evaluate.replay import contact_measurements, evaluate_bag, joint_matrix
from ppoe_core.analysis.evaluate.report import markdown_report, write_report
from ppoe_core.analysis.evaluate.scoring import registration_split
from ppoe_core.analysis.evaluate.tag_stream import tag_measurements
from ppoe_core.io.progress import ProgressBar

__all__ = [
    "registration_split", "joint_matrix", "tag_measurements", "contact_measurements", "EvaluateOptions", "Evaluation",
    "evaluate_bag", "error_stats", "position_errors", "rotation_errors", "point_covariance", "nees_stats",
    "ProgressBar", "METHODS", "markdown_report", "write_report", "EVALUATE_SETTINGS", "REPLAY_SETTINGS",
    "load_fusion_params", "load_sources",
]
