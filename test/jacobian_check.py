"""The one Jacobian checker of the test suite (manif-style): central differences along tangent directions.

``numerical_jacobian(f, x0)`` returns ``J[..., i] = (f(x0 (+) h e_i) (-) f(x0 (+) -h e_i)) / 2h`` where ``(+)``
and ``(-)`` are vector addition / subtraction by default, or the right-perturbation operations of a Lie group
(``X (+) tau = X Exp(tau)``, ``Y (-) X = Log(X^-1 Y)``; docs/conventions.md) when ``plus`` / ``minus`` are given.
``check_jacobian`` compares an analytic Jacobian with it and says which column differs.
Every analytic Jacobian of ppoe_core is tested through these two functions.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ppoe_core import lie


def _vec_plus(x: Any, tau: np.ndarray) -> Any:
    return np.asarray(x, dtype=float) + tau


def _vec_minus(y: Any, x: Any) -> np.ndarray:
    return np.asarray(y, dtype=float) - np.asarray(x, dtype=float)


#: right-perturbation operations on SE(3) poses (..., 4, 4) and SO(3) rotations (..., 3, 3)
SE3_PLUS, SE3_MINUS = lie.oplus, lie.ominus


def SO3_PLUS(R: np.ndarray, w: np.ndarray) -> np.ndarray:  # noqa: N802 - constant-like name
    return R @ lie.so3_exp(w)


def SO3_MINUS(R1: np.ndarray, R0: np.ndarray) -> np.ndarray:  # noqa: N802
    return lie.so3_log(np.swapaxes(R0, -1, -2) @ R1)


def numerical_jacobian(f: Callable[[Any], Any], x0: Any, dim: int | None = None, eps: float = 1e-6,
                       plus: Callable[[Any, np.ndarray], Any] = _vec_plus,
                       minus: Callable[[Any, Any], np.ndarray] = _vec_minus) -> np.ndarray:
    """Central-difference Jacobian of ``f`` at ``x0``: shape ``f_shape + (dim,)``.

    ``dim`` is the tangent dimension of the domain (default: the size of a vector ``x0``).
    """
    n = int(np.asarray(x0).shape[-1]) if dim is None else int(dim)
    y0 = f(x0)
    cols = []
    for i in range(n):
        tau = np.zeros(n)
        tau[i] = eps
        yp, ym = f(plus(x0, tau)), f(plus(x0, -tau))
        cols.append((minus(yp, y0) - minus(ym, y0)) / (2.0 * eps))
    return np.stack(cols, axis=-1)


def check_jacobian(f: Callable[[Any], Any], x0: Any, J: np.ndarray, *, dim: int | None = None, eps: float = 1e-6,
                   atol: float = 1e-7, rtol: float = 0.0, plus: Callable[[Any, np.ndarray], Any] = _vec_plus,
                   minus: Callable[[Any, Any], np.ndarray] = _vec_minus, err_msg: str = "") -> np.ndarray:
    """Assert that the analytic ``J`` equals the numerical Jacobian of ``f`` at ``x0``; returns the latter."""
    num = numerical_jacobian(f, x0, dim, eps, plus, minus)
    J = np.asarray(J, dtype=float)
    assert J.shape == num.shape, f"{err_msg}: analytic Jacobian shape {J.shape} != numerical {num.shape}"
    for i in range(num.shape[-1]):
        np.testing.assert_allclose(J[..., i], num[..., i], atol=atol, rtol=rtol, err_msg=f"{err_msg} column {i}")
    return num
