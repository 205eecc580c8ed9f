"""Speed of the iterated LG-EKF update (ppoe_core.estimation.fusion.iterated_update).

Prints ``name: value unit`` lines: median and minimum microseconds per single update for
* a two-tag bearing update (2 tags x 5 points = 20 pixel coordinates, camera pose
  covariance entering through M, exactly 3 iterations), analytic Jacobians;
* the same with central-difference Jacobians (baseline measured in the same run);
* a 1D contact-plane update (paper Sigma_v), analytic and numerical.

Run: ``cd /work/main && python bench/bench_fusion.py [--repeat N]``
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core, before numpy is imported

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from ppoe_core import lie  # noqa: E402
from ppoe_core.estimation.fusion import iterated_update  # noqa: E402
from ppoe_core.estimation.measurements import ContactPlaneModel, TagBearingModel, tag_points  # noqa: E402

__all__ = ["main"]


def _pose(t, w):
    T = np.eye(4)
    T[:3, :3] = lie.so3_exp(np.asarray(w, dtype=float))
    T[:3, 3] = t
    return T


def _time(fn, repeat: int) -> tuple[float, float]:
    """(median, minimum) microseconds of single calls; the minimum is the least disturbed by
    other processes on a shared machine."""
    fn()  # warm-up
    t = np.empty(repeat)
    for i in range(repeat):
        t0 = time.perf_counter()
        fn()
        t[i] = time.perf_counter() - t0
    return float(np.median(t) * 1e6), float(t.min() * 1e6)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=300, help="timed single updates per case (default 300)")
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
    D = np.array([-0.2, 0.08, 0.001, -0.001, -0.01])
    T_base_cam = _pose([0.2, 0.0, 1.0], [-2.0, 0.0, 0.0])
    pts = np.vstack(
        [tag_points(0.04, _pose([0.03, 0, 0], [0, 0, 0])), tag_points(0.04, _pose([-0.03, 0, 0], [0, 0, 0]))]
    )
    A = rng.normal(size=(6, 6))
    cov_cam = 1e-5 * (A @ A.T / 6 + 0.1 * np.eye(6))
    tags = TagBearingModel(pts, K, D, 0.5, T_ref_camera=T_base_cam, cov_camera=cov_cam)
    X0 = T_base_cam @ _pose([0.02, -0.01, 0.6], [np.pi, 0.2, 0.1])
    B = rng.normal(size=(6, 6))
    P = 1e-5 * (B @ B.T / 6 + 0.1 * np.eye(6))
    z = tags.h(X0 @ lie.exp(np.linalg.cholesky(P) @ rng.normal(size=6)))
    kw = dict(max_iterations=3, step_tolerance=0.0)
    r = iterated_update(X0, P, z, tags, **kw)
    assert r.iterations == 3 and r.accepted
    t_tag = _time(lambda: iterated_update(X0, P, z, tags, **kw), args.repeat)
    t_tag_num = _time(lambda: iterated_update(X0, P, z, tags, jacobians="numerical", **kw), args.repeat // 3 + 1)

    sigma_v = np.diag([0.5, 0.5, 0.001, 0.017, 0.017, 0.17]) ** 2
    contact = ContactPlaneModel(np.eye(4), sigma_v, [0.0, 0.0, 0.02])
    Xc = _pose([0.4, 0.1, -0.018], [0.0, 0.0, 0.3])  # tool point 2 mm above the table
    t_c = _time(lambda: iterated_update(Xc, P, [0.0], contact), args.repeat)
    t_c_num = _time(lambda: iterated_update(Xc, P, [0.0], contact, jacobians="numerical"), args.repeat // 3 + 1)
    rc = iterated_update(Xc, P, [0.0], contact)
    assert rc.accepted

    for name, (med, mn) in (
        ("two_tag_bearing_update_3iter", t_tag),
        ("two_tag_bearing_update_3iter_numerical_jacobians", t_tag_num),
        ("contact_update", t_c),
        ("contact_update_numerical_jacobians", t_c_num),
    ):
        print(f"{name}_median: {med:.1f} us")
        print(f"{name}_min: {mn:.1f} us")
    print(f"contact_update_iterations: {rc.iterations} count")
    print(f"two_tag_numerical_over_analytic_min: {t_tag_num[1] / t_tag[1]:.2f} x")
    print(f"contact_numerical_over_analytic_min: {t_c_num[1] / t_c[1]:.2f} x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
