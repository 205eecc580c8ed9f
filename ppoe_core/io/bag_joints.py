"""Joint values of a bag at given stamps (``ppoe init`` and ``ppoe check``: :mod:`ppoe_core.io.bag_facts`,
:mod:`ppoe_core.io.tag_facts`, :mod:`ppoe_core.io.bag_check`)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ppoe_core.model.context import sample_series
from ppoe_core.robot.robot_model import Robot

__all__ = ["joints_at", "moved_joints", "MOVED"]

#: a joint whose values span less than this [rad or m] did not move (1 mrad: above encoder noise, below any pose
#: change that matters)
MOVED = 1e-3


def joints_at(data: Any, robot: Robot, stamps: np.ndarray) -> dict[str, np.ndarray]:
    """Independent joint values (N,) at ``stamps`` from the bag's ``/joint_states`` (``data``: a
    :class:`~ppoe_core.io.series.BagData`), sampled as diagnose samples them
    (:func:`ppoe_core.model.context.sample_series`); joints the bag never lists are 0 (``ppoe check`` names them)."""
    js = data.joint_states
    order = np.argsort(js.stamps, kind="stable")
    out = {}
    for jn in robot.independent_joints:
        col = js.positions[order, js.names.index(jn)] if jn in js.names else np.zeros(len(order))
        good = np.isfinite(col)
        out[jn] = sample_series(js.stamps[order][good], col[good], stamps)
    return out


def moved_joints(q: dict[str, np.ndarray]) -> set[str]:
    """The joints of ``q`` (name -> values) whose values span more than :data:`MOVED`."""
    return {j for j, v in q.items() if v.size and float(np.nanmax(v) - np.nanmin(v)) > MOVED}
