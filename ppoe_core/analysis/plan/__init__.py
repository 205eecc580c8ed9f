"""``ppoe plan``: D-optimal calibration pose design from the calibration engine's own residual blocks.

* :mod:`information`: per candidate configuration, the information of the target effects' parameters from the
  engine's tracker block (:meth:`ResidualBlock.linearise`: the same columns ``ppoe diagnose`` fits), the
  registration (nuisance) eliminated by a Schur complement;
* :mod:`constraints`: random feasible candidates (joint limits with a margin, workspace box, self-collision
  capsules from the URDF, tracker line of sight, tags in the camera's view);
* :mod:`design`: greedy forward selection + exchange on ``log det`` (D-optimality), then a constrained minimax
  exchange (worst CI relative to 4N random poses', D-efficiency kept), Sun and Hollerbach's O1..O5;
* :mod:`planner`: :func:`plan` (design, predicted CIs and held-out error, random baselines, execution order);
* :mod:`outputs`: ``poses.csv``, ``trajectory.yaml`` (``trajectory_msgs/JointTrajectory``), ``plan.json``,
  ``plan.png``.
"""

from __future__ import annotations

from ppoe_core.analysis.plan.constraints import CameraView, Capsule, Constraints, sample_candidates, violations
from ppoe_core.analysis.plan.design import Design, design, observability_indices
from ppoe_core.analysis.plan.information import PoseInformation, Target, pose_information, target_effects
from ppoe_core.analysis.plan.planner import PlanOptions, PlanResult, Prediction, plan, predict

__all__ = ["CameraView", "Capsule", "Constraints", "Design", "PlanOptions", "PlanResult", "PoseInformation",
           "Prediction", "Target", "design", "observability_indices", "plan", "pose_information", "predict",
           "sample_candidates", "target_effects", "violations"]
