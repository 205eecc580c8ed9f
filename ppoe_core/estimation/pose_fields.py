"""The fusion node's per-prior conversion, compiled: a pose message's 43 fields -> a pose and its tool-frame
covariance, in one call (the other way is :func:`ppoe_core.lie.kernels.pose_cov_fields_into`, the one writer of
these fields, shared with the kinematics node).

The fields are what a ``geometry_msgs/PoseWithCovarianceStamped`` carries after its header (and what
:class:`ppoe_core.io.cdr.PoseCovarianceWriter` keeps in its buffer): position ``x y z``, quaternion ``x y z w``, the
covariance in the ROS convention (docs/conventions.md sec. 2) row-major; a ``tf2_msgs/TFMessage`` transform's 7
doubles are their first 7.  :func:`prior_from_fields` runs the same compiled pieces, in the same order, as the
Python path it replaces (:func:`ppoe_ros.common.conversions.pose_cov_from_cdr` +
:func:`ppoe_core.lie.cov_ros_to_local`): the same floats (``test/test_fusion_node.py``), one dispatch instead of
several numpy steps.
"""

from __future__ import annotations

import math

import numpy as np

from ppoe_core.jit import njit
from ppoe_core.lie.kernels import pose_from_quat_one, rotate_covariance_into

__all__ = ["FIELDS", "prior_from_fields"]

#: doubles of a pose message after its header: position (3), quaternion x y z w (4), ROS covariance (36)
FIELDS = 43
#: a quaternion norm below this is not a rotation (``conversions._matrix_from_quat_xyz``'s rule)
MIN_QUAT_NORM = 1e-9


@njit(cache=True)
def prior_from_fields(v: np.ndarray, T: np.ndarray, cov_tool: np.ndarray) -> bool:
    """``T`` (4, 4) and ``cov_tool`` (6, 6, the tangent space at ``T``) of the fields ``v`` (43,): the quaternion
    normalised (then normalised again by :func:`~ppoe_core.lie.kernels.pose_from_quat_one`, as the Python path
    does) and ``B^T cov_ros B``.  False (outputs unspecified) when the quaternion's norm is not finite or below
    :data:`MIN_QUAT_NORM`: the caller's Python path raises the error."""
    x, y, z, w = v[3], v[4], v[5], v[6]
    nq = math.sqrt(x * x + y * y + z * z + w * w)
    if not math.isfinite(nq) or nq < MIN_QUAT_NORM:
        return False
    pose_from_quat_one(x / nq, y / nq, z / nq, w / nq, v[0], v[1], v[2], T)
    cov_ros = np.empty((6, 6))
    for i in range(6):
        for j in range(6):
            cov_ros[i, j] = v[7 + 6 * i + j]
    rotate_covariance_into(T, cov_ros, True, cov_tool, np.empty((3, 3)), np.empty((3, 3)))
    return True
