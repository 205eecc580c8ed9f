"""Tag observation rows <-> ``sensor_msgs/PointCloud2`` (``/tag_bearing/observations``).

Fields ``id``, ``corner``, ``u``, ``v`` (raw pixels), ``x``, ``y`` (undistorted normalised), FLOAT64;
written by the tag bearing node, read by the fusion node and ``ppoe play``-based tests.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from ppoe_core.io.rows import tag_rows_from_cloud
from ppoe_core.sensing.tag_rows import OBSERVATION_FIELDS

__all__ = ["cloud_from_observations", "observations_from_cloud"]


def cloud_from_observations(rows: np.ndarray, header: Any) -> PointCloud2:
    """Observation rows ``(n, 6)`` ``[id, corner, u, v, x, y]`` -> ``PointCloud2`` (FLOAT64 fields)."""
    rows = np.ascontiguousarray(np.asarray(rows, dtype="<f8").reshape(-1, len(OBSERVATION_FIELDS)))
    msg = PointCloud2()
    msg.header = header
    msg.height = 1
    msg.width = int(rows.shape[0])
    msg.fields = [PointField(name=n, offset=8 * i, datatype=PointField.FLOAT64, count=1)
                  for i, n in enumerate(OBSERVATION_FIELDS)]
    msg.is_bigendian = False
    msg.point_step = 8 * len(OBSERVATION_FIELDS)
    msg.row_step = msg.point_step * msg.width
    msg.data = rows.tobytes()
    msg.is_dense = True
    return msg


def observations_from_cloud(msg: Any) -> dict[str, np.ndarray]:
    """``PointCloud2`` of ``/tag_bearing/observations`` -> ``{field: (n,) float64}`` (the bag reader's rule,
    :func:`ppoe_core.io.rows.tag_rows_from_cloud`; MeasurementError naming a missing or bad field)."""
    rows = tag_rows_from_cloud(msg)
    return {name: rows[:, j] for j, name in enumerate(OBSERVATION_FIELDS)}
