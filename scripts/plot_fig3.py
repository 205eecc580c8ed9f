"""Redraw the PPOE paper's Fig. 3: the 3-link planar arm with 10 deg perturbations at the joints.

Four configurations of ``config/robots/planar3.urdf``:

(a) perturbation on joint 1 only (``config/robots/planar3_joint1_model.yaml``): a 1D arc;
(b) the stretched, singular configuration: the banana;
(c), (d) bent configurations: the banana widens and becomes more elliptical.

For each, the tool covariance ``cov_tool`` (tangent space at ``T_base_tool``, second order,
eq. 15/18) is drawn as its 80 % enclosure mapped onto the manifold as in the paper's Sec. IV-C:
the covariance is scaled to the 80 % chi-square contour (degrees of freedom = its rank), eigen-
decomposed, and for every pair of eigenvectors the ellipse on the ellipsoid surface in the tangent
space is mapped with ``T_base_tool @ Exp(xi)`` into the base frame; the xy projection is plotted
(blue). 200 Monte-Carlo samples of the same model (green), the arm (black, joints as circles,
perturbed joints red). The script also prints, per panel, the fraction of samples inside the
80 % tangent-space enclosure (Mahalanobis distance of ``Log(T^-1 T_s)``).

Usage::

    python scripts/plot_fig3.py [--out docs/img/fig3.png] [--samples 200] [--seed 3]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from scipy.stats import chi2  # noqa: E402

from ppoe_core import lie  # noqa: E402
from ppoe_core.model.ppoe import PPOEModel  # noqa: E402

__all__ = ["PANELS", "enclosure_curves", "fraction_inside", "main"]

#: (label, model yaml, joint values [rad], caption)
PANELS = [
    ("(a)", "planar3_joint1_model.yaml", (0.25, 0.8, 0.9), "joint 1 perturbed only"),
    ("(b)", "planar3_model.yaml", (0.0, 0.0, 0.0), "stretched (singular)"),
    ("(c)", "planar3_model.yaml", (0.15, 0.45, 0.45), "bent"),
    ("(d)", "planar3_model.yaml", (-0.2, 1.1, 1.2), "strongly bent"),
]
LINKS = ("base_link", "link1", "link2", "link3", "tool0")
JOINTS = ("joint1", "joint2", "joint3")
LEVEL = 0.8


def _rank_eig(cov: np.ndarray, rel_tol: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues/vectors of ``cov`` above ``rel_tol * max`` (the non-degenerate directions)."""
    w, V = np.linalg.eigh(cov)
    keep = w > rel_tol * w.max()
    return w[keep], V[:, keep]


def enclosure_curves(T: np.ndarray, cov: np.ndarray, level: float = LEVEL, n: int = 181) -> list[np.ndarray]:
    """Curves of the ``level`` enclosure of ``cov`` mapped onto SE(3) (paper Sec. IV-C).

    Parameters
    ----------
    T : ndarray, shape (4, 4)
        Mean pose ``T_base_tool``.
    cov : ndarray, shape (6, 6)
        Covariance in the tangent space at ``T`` (frame ``tool``, ``[rho; theta]``).
    level : float
        Enclosed probability; the scale is the chi-square quantile with ``rank(cov)`` dof.
    n : int
        Points per curve.

    Returns
    -------
    list of ndarray, each shape (n, 3)
        Positions in the base frame: one curve per pair of eigenvectors (for rank 1, the
        segment along the single eigenvector).
    """
    w, V = _rank_eig(cov)
    scale = np.sqrt(chi2.ppf(level, df=len(w)))
    axes = (V * np.sqrt(w)).T * scale  # (r, 6): semi-axes in the tangent space
    a = np.linspace(0.0, 2.0 * np.pi, n)
    curves = []
    if len(axes) == 1:
        xi = np.linspace(-1.0, 1.0, n)[:, None] * axes[0]
        curves.append((T @ lie.exp(xi))[:, :3, 3])
    for i in range(len(axes)):
        for j in range(i + 1, len(axes)):
            xi = np.cos(a)[:, None] * axes[i] + np.sin(a)[:, None] * axes[j]
            curves.append((T @ lie.exp(xi))[:, :3, 3])
    return curves


def fraction_inside(T: np.ndarray, cov: np.ndarray, samples: np.ndarray, level: float = LEVEL) -> float:
    """Fraction of sampled poses inside the ``level`` enclosure of ``cov`` in the tangent space at ``T``.

    ``cov`` lives in the tangent space at ``T``; rank-deficient covariances use the pseudo-inverse
    on their range (samples off the range would be outside, but the sampler stays on it).
    """
    w, V = _rank_eig(cov)
    xi = lie.log(lie.inverse(T) @ samples)
    z = (xi @ V) / np.sqrt(w)
    d2 = np.sum(z**2, axis=-1)
    return float(np.mean(d2 <= chi2.ppf(level, df=len(w))))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Redraw the PPOE paper's Fig. 3 (planar3).")
    ap.add_argument("--out", default=str(REPO / "docs" / "img" / "fig3.png"), help="output PNG")
    ap.add_argument("--samples", type=int, default=200, help="Monte-Carlo samples per panel")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--dpi", type=int, default=90)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    urdf = REPO / "config" / "robots" / "planar3.urdf"

    fig, axs = plt.subplots(1, 4, figsize=(14, 4.0))
    for ax, (label, yaml_name, q, caption) in zip(axs, PANELS):
        model = PPOEModel.from_files(str(urdf), str(REPO / "config" / yaml_name))
        joints = dict(zip(JOINTS, q))
        T, cov = model.fk(joints, "base_link", "tool0", order=2)
        samples = np.asarray(model.sample(joints, "base_link", "tool0", args.samples, rng))
        inside = fraction_inside(T, cov, samples)
        print(f"{label} {caption}: q = {q} rad, samples inside the 80% enclosure: {100 * inside:.1f} %")

        ax.plot(samples[:, 0, 3], samples[:, 1, 3], ".", color="tab:green", ms=3, alpha=0.7,
                label=f"{args.samples} samples")
        for k, c in enumerate(enclosure_curves(T, cov)):
            ax.plot(c[:, 0], c[:, 1], "-", color="tab:blue", lw=1.2, zorder=2,
                    label="80 % enclosure" if k == 0 else None)
        pts = np.array([model.fk_mean(joints, "base_link", link)[:3, 3] for link in LINKS])
        ax.plot(pts[:, 0], pts[:, 1], "-", color="k", lw=2.5, solid_capstyle="round", zorder=3)
        perturbed = set(model.config.perturbations)
        for p, jn in zip(pts[1:4], JOINTS):  # joint i sits at the origin of link i
            col = "tab:red" if jn in perturbed else "k"
            ax.plot(p[0], p[1], "o", ms=9, mfc="white", mec=col, mew=2, zorder=4)
        ax.plot(pts[-1, 0], pts[-1, 1], "s", ms=5, color="k", zorder=4)
        ax.set_title(f"{label} {caption}\nq = ({q[0]:.2f}, {q[1]:.2f}, {q[2]:.2f}) rad", fontsize=9)
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
        ax.set_xlabel("x [m]")
        ax.set_xlim(-0.5, 3.6)
        ax.set_ylim(-1.6, 2.6)
    axs[0].set_ylabel("y [m]")
    axs[0].legend(loc="lower right", fontsize=8)
    fig.suptitle("PPOE, planar 3-link arm, 10 deg perturbation about each perturbed joint axis (red)", fontsize=10)
    fig.tight_layout()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=args.dpi, bbox_inches="tight")
    print(f"wrote {out} ({out.stat().st_size / 1024:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
