"""SE(3) and SO(3) Lie group tools, batched over leading axes.

Conventions (docs/conventions.md section 1, paper section III):

* A twist is ``xi = [rho; theta]`` with shape ``(..., 6)``: translation first.
* Poses are homogeneous matrices of shape ``(..., 4, 4)``.
* Perturbations are right / local: ``X = Xbar @ exp(xi)`` (paper eq. 8); a
  covariance ``E[xi xi^T]`` lives in the tangent space at ``Xbar`` (eq. 9).

Every function broadcasts over leading batch axes, in the style of
pytransform3d's ``trajectories`` module.  Exp, Log, the Jacobians, the inverse and
the quaternions have one implementation, compiled (:mod:`ppoe_core.lie.kernels`,
called for one pose or a flat batch; numba is imported on the first call): small
angles by Taylor series, the logarithm through a quaternion (Shepperd's method),
which keeps it accurate at and near ``pi``.
"""

from __future__ import annotations

from ppoe_core.lie.covariance import check_covariance, cov_local_to_ros, cov_ros_to_local
from ppoe_core.lie.se3 import (
    adjoint, compose, curly_hat, exp, fit_rigid, from_rt, from_xyz_rpy, hat, interpolate, inverse, left_jacobian,
    left_jacobian_inv, log, ominus, oplus, right_jacobian, right_jacobian_inv, vee,
)
from ppoe_core.lie.so3 import (
    hat3, matrix_from_quat, matrix_from_rpy, quat_from_matrix, rpy_from_matrix, so3_exp, so3_left_jacobian,
    so3_left_jacobian_inv, so3_log, so3_right_jacobian, so3_right_jacobian_inv, vee3,
)

__all__ = [
    "hat3", "vee3", "hat", "vee", "so3_exp", "so3_log", "so3_left_jacobian", "so3_left_jacobian_inv",
    "so3_right_jacobian", "so3_right_jacobian_inv", "exp", "log", "adjoint", "curly_hat", "left_jacobian",
    "right_jacobian", "left_jacobian_inv", "right_jacobian_inv", "inverse", "compose", "oplus", "ominus", "from_rt",
    "fit_rigid", "from_xyz_rpy", "matrix_from_rpy", "rpy_from_matrix", "quat_from_matrix", "matrix_from_quat",
    "interpolate", "cov_local_to_ros", "cov_ros_to_local", "check_covariance",
]
