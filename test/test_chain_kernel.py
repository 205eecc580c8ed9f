"""The chain kernel's own sine and cosine (:func:`ppoe_core.model.chain_kernel.sincos`, branch-free so the loop over
configurations vectorises): within 2 ulp of numpy's over the range it serves, and numpy's beyond
:data:`~ppoe_core.model.chain_kernel.SINCOS_LIMIT` in the batched FK.  The batched fast path
(:func:`ppoe_core.model.chain_panel.eval_panels`) against :func:`~ppoe_core.model.chain_kernel.eval_chain`."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CONFIG

from ppoe_core import PPOEModel
from ppoe_core.model.chain_kernel import SINCOS_LIMIT, eval_chain, sincos
from ppoe_core.model.chain_panel import eval_panels

numba = pytest.importorskip("numba")


@numba.njit(cache=False)
def _many(x: np.ndarray, s: np.ndarray, c: np.ndarray) -> None:
    for i in range(x.shape[0]):
        s[i], c[i] = sincos(x[i])


def _ulps(got: np.ndarray, ref: np.ndarray) -> float:
    return float((np.abs(got - ref) / np.spacing(np.maximum(np.abs(ref), 1e-300))).max())


@pytest.mark.parametrize("limit", [np.pi / 4, np.pi, 100.0, SINCOS_LIMIT])
def test_sincos_within_2_ulp_of_numpy(limit: float) -> None:
    x = np.random.default_rng(7).uniform(-limit, limit, 200_000)
    s, c = np.empty_like(x), np.empty_like(x)
    _many(x, s, c)
    assert _ulps(s, np.sin(x)) <= 2.0 and _ulps(c, np.cos(x)) <= 2.0


def test_sincos_at_and_next_to_multiples_of_quarter_pi() -> None:
    k = np.arange(-2000, 2001) * (np.pi / 4)
    x = np.concatenate([k, np.nextafter(k, np.inf), np.nextafter(k, -np.inf), [0.0, -0.0, 5e-324, -1e-300]])
    s, c = np.empty_like(x), np.empty_like(x)
    _many(x, s, c)
    np.testing.assert_allclose(s, np.sin(x), rtol=0, atol=2.3e-16)
    np.testing.assert_allclose(c, np.cos(x), rtol=0, atol=2.3e-16)


def test_batched_fk_beyond_the_limit_takes_numpys_sine() -> None:
    """Angles beyond SINCOS_LIMIT (numpy's sine and cosine) and inside it give the same poses, batched and one by
    one (the configuration plus whole turns; atol: the ulp of 1e6 rad)."""
    model = PPOEModel.from_files(CONFIG / "robots" / "arm7.urdf", CONFIG / "robots" / "arm7_model.yaml")
    q = np.random.default_rng(3).uniform(-2.0, 2.0, (70, len(model.joint_names)))
    turns = 2 * np.pi * np.round(1.5 * SINCOS_LIMIT / (2 * np.pi))
    q_big = q.copy()
    q_big[::2, 0] += turns
    T, cov = model.fk(q)
    T_big, cov_big = model.fk(q_big)
    np.testing.assert_allclose(T_big, T, atol=1e-9)
    np.testing.assert_allclose(cov_big, cov, atol=1e-9 * np.abs(cov).max())
    T_one, _ = model.fk(q_big[0])
    np.testing.assert_allclose(T_one, T[0], atol=1e-9)


@pytest.mark.parametrize("frm, to", [("base_link", "tool0"), ("camera_optical_frame", "tool0"),
                                     ("tool0", "base_link"), ("base_link", "finger_left")])
@pytest.mark.parametrize("n", [2, 63, 64, 65, 200])
def test_panels_equal_eval_chain(frm: str, to: str, n: int) -> None:
    """The batched fast path gives :func:`eval_chain`'s poses and covariances (same expressions; fused multiply-adds
    may round differently, and eval_chain's chunk of one configuration takes numpy's sine: 1e-15 of the largest
    entry) for up, down and prismatic chains, partial chunks, and an angle beyond SINCOS_LIMIT."""
    model = PPOEModel.from_files(CONFIG / "robots" / "arm7.urdf", CONFIG / "robots" / "arm7_model.yaml")
    lean = model.lean_program(frm, to)
    assert lean is not None
    q = np.random.default_rng(n).uniform(-2.0, 2.0, (n, len(model.joint_names)))
    q[1, :] += 2 * np.pi * np.round(1.5 * SINCOS_LIMIT / (2 * np.pi))
    theta = np.ascontiguousarray((q[:, lean.motion_col] * lean.mult + lean.off).T)
    F, kind, arg, col_pos, X, mot_pos, mot_kind, site_start = lean.program
    D = np.zeros((0, 4, 4, 1))
    for order in (0, 2):
        T_ref, cov_ref = np.full((n, 4, 4), np.nan), np.zeros((n, 6, 6))
        eval_chain(F, kind, arg, col_pos, X, mot_pos, mot_kind, site_start, theta, D, order, T_ref, cov_ref,
                   np.empty((0, 6, 0)), np.empty((0, 6, 0)), None)
        T, cov = np.full((n, 4, 4), np.nan), np.full((n, 6, 6), np.nan if order else 0.0)
        eval_panels(F, kind, arg, col_pos, X, theta, D, order, T, cov)
        np.testing.assert_allclose(T, T_ref, rtol=0, atol=1e-15)
        np.testing.assert_allclose(cov, cov_ref, rtol=0, atol=1e-15 * np.abs(cov_ref).max())
        np.testing.assert_array_equal(cov, cov.transpose(0, 2, 1))
