"""``diagnose.png``: every measurement kind's held-out residual before and after the diagnosis, in its own unit.

One panel per residual block of the run (tracker points, 6D poses, tag pixels, accelerometer tilts, contacts, in
that order): held-out RMS of the nominal model ("before") and of the diagnosed one ("after"), for the whole block
and, when it has several, per sensor (camera, reflector, accelerometer), with the block's noise floor as a line.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.analysis.diagnose.results import BlockReport, DiagnoseResult

__all__ = ["BLOCK_ORDER", "block_figure", "display_unit", "ordered_blocks", "plot_blocks"]

#: panel order: the metric blocks first, then the sensors that see part of the chain
BLOCK_ORDER = ("tracker", "pose", "pixels", "imu", "contact")

#: a block's unit -> (factor, unit shown): millimetres and milliradians read better than 0.008 rad
_DISPLAY = {"m": (1e3, "mm"), "rad": (1e3, "mrad")}

#: colours of the two bars (matplotlib's default cycle's first two: before, after)
_COLOURS = ("tab:blue", "tab:orange")


def display_unit(unit: str) -> tuple[float, str]:
    """``(factor, shown unit)`` of a block unit: ``m`` -> mm, ``rad`` -> mrad, others as they are."""
    return _DISPLAY.get(unit, (1.0, unit))


def ordered_blocks(result: DiagnoseResult) -> list[BlockReport]:
    """The result's blocks in :data:`BLOCK_ORDER` (unknown kinds after them, as they come)."""
    rank = {k: i for i, k in enumerate(BLOCK_ORDER)}
    return sorted(result.blocks.values(), key=lambda b: rank.get(b.kind, len(rank)))


def _bars(b: BlockReport) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Labels and held-out RMS before / after of the block and, if there are several, of each sensor."""
    labels, before, after = ["all"], [b.rms_before], [b.rms_after]
    if len(b.per_sensor) > 1:
        for name, v in b.per_sensor.items():
            labels.append(name)
            before.append(v["rms_before"])
            after.append(v["rms_after"])
    return labels, np.array(before, dtype=float), np.array(after, dtype=float)


def block_figure(result: DiagnoseResult, title: str = "") -> Any:
    """The figure (module docstring) as a matplotlib ``Figure`` (Agg backend), one axes per block in
    :func:`ordered_blocks` order; None without matplotlib or blocks."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:  # matplotlib is optional for the report
        return None
    blocks = ordered_blocks(result)
    if not blocks:
        return None
    widths = [max(1.6, 1.1 * len(_bars(b)[0])) for b in blocks]
    fig, axes = plt.subplots(1, len(blocks), figsize=(min(2.2 + sum(widths), 14.0), 3.4),
                             gridspec_kw={"width_ratios": widths}, squeeze=False)
    for ax, b in zip(axes[0], blocks):
        _panel(ax, b)
    handles, labels = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=3, fontsize=7, frameon=False)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0.0, 0.07, 1.0, 1.0))
    return fig


def plot_blocks(result: DiagnoseResult, png: str | Path, title: str = "") -> bool:
    """Write :func:`block_figure` to ``png``; False (nothing written) without matplotlib or blocks."""
    fig = block_figure(result, title)
    if fig is None:
        return False
    import matplotlib.pyplot as plt

    fig.savefig(png, dpi=80)
    plt.close(fig)
    return True


def _panel(ax, b: BlockReport) -> None:  # noqa: ANN001 (a matplotlib Axes, imported lazily)
    """One block: before / after bars per group, the noise floor, the change in the title."""
    f, u = display_unit(b.unit)
    labels, before, after = _bars(b)
    x = np.arange(len(labels))
    ax.bar(x - 0.2, f * before, 0.4, color=_COLOURS[0], label="before (nominal model)")
    ax.bar(x + 0.2, f * after, 0.4, color=_COLOURS[1], label="after (diagnosed model)")
    if math.isfinite(b.noise_floor):
        ax.axhline(f * b.noise_floor, color="k", lw=1, ls="--", label="noise floor")
    ax.set_xticks(x, labels, fontsize=7, rotation=20 if len(labels) > 2 else 0)
    ax.set_ylabel(f"held-out RMS [{u}]", fontsize=8)
    ax.tick_params(axis="y", labelsize=7)
    change = (f"{f * b.rms_before:.3g} -> {f * b.rms_after:.3g} {u}"
              if math.isfinite(b.rms_before) and math.isfinite(b.rms_after) else "not scored")
    mark = "\nstructure left" if b.significant else ""
    ax.set_title(f"{b.kind} ({b.n} rows)\n{change}{mark}", fontsize=8)
