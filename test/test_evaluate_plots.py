"""``errors.png`` of ppoe evaluate (ppoe_core/analysis/evaluate/report.py): errors against time, trajectory views."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ppoe_core import lie
from ppoe_core.analysis.evaluate.options import Evaluation
from ppoe_core.analysis.evaluate.report import plot_errors


def _evaluation(n: int = 12) -> Evaluation:
    rng = np.random.default_rng(4)
    stamps = 100.0 + np.cumsum(rng.uniform(0.5, 3.0, n))  # uneven spacing: time differs from the index
    gt = lie.from_xyz_rpy(rng.normal(size=(n, 3)) * 0.3, rng.normal(size=(n, 3)))
    samples: dict[str, np.ndarray] = {"stamp": stamps, "gt_T": gt}
    for k, m in enumerate(("fk", "ppoe")):
        samples[f"{m}_T"] = gt @ lie.exp(rng.normal(size=(n, 6)) * 1e-3 * (3 - 2 * k))
        for metric in ("position_3d", "lateral", "rotation"):
            samples[f"{m}_{metric}"] = np.abs(rng.normal(size=n)) * 1e-3
        samples[f"{m}_nees"] = rng.chisquare(6, n)
    summary = {"bag": "/x/my_bag", "base": "base_link", "methods": {"fk": {"nees": {"dof": 6}}}}
    return Evaluation(summary, samples)


def test_errors_against_time_and_trajectory_views(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import matplotlib.figure

    figures = []
    original = matplotlib.figure.Figure.savefig

    def keep(self, *args, **kwargs):
        figures.append(self)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    ev = _evaluation()
    plot_errors(ev, tmp_path / "errors.png")
    assert (tmp_path / "errors.png").stat().st_size > 10_000
    (fig,) = figures
    axes = {ax.get_ylabel(): ax for ax in fig.axes}
    t = ev.samples["stamp"] - ev.samples["stamp"][0]
    for label in ("position 3d [mm]", "lateral [mm]", "rotation [deg]", "NEES (6 dof; 95 % band)"):
        xdata = [np.asarray(line.get_xdata()) for line in axes[label].lines if len(line.get_xdata()) == len(t)]
        assert xdata and all(np.allclose(x, t) for x in xdata), label
    assert axes["NEES (6 dof; 95 % band)"].get_xlabel() == "time since the first scored sample [s]"
    views = {ax.get_title(): ax for ax in fig.axes if ax.get_title()}
    assert set(views) == {"top view (base_link frame)", "side view (base_link frame)"}
    gt = ev.samples["gt_T"][:, :3, 3]
    top = views["top view (base_link frame)"].lines[0]
    side = views["side view (base_link frame)"].lines[0]
    np.testing.assert_allclose(np.column_stack([top.get_xdata(), top.get_ydata()]), gt[:, [0, 1]])
    np.testing.assert_allclose(np.column_stack([side.get_xdata(), side.get_ydata()]), gt[:, [0, 2]])
    assert len(views["top view (base_link frame)"].lines) == 3  # ground truth + fk + ppoe
