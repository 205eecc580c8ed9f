"""Tag observation rows <-> ``sensor_msgs/PointCloud2`` (``/tag_bearing/observations``).

Fields ``id``, ``corner``, ``u``, ``v`` (raw pixels), ``x``, ``y`` (undistorted normalised), FLOAT64;
written by the tag bearing node, read by the fusion node and ``ppoe play``-based tests.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField

from ppoe_core.errors import MeasurementError
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
    """``PointCloud2`` of ``/tag_bearing/observations`` -> ``{field: (n,) float64}``.

    Fields are read by name and offset (FLOAT64 or FLOAT32), so a producer may order them
    differently or add fields.

    Raises
    ------
    MeasurementError
        A required field is missing or not float, or the data size does not match.
    """
    by_name = {f.name: f for f in msg.fields}
    n = int(msg.width) * int(msg.height)
    step = int(msg.point_step)
    data = bytes(msg.data)
    if len(data) < n * step:
        raise MeasurementError(f"PointCloud2 has {len(data)} bytes for {n} points of {step} bytes")
    out: dict[str, np.ndarray] = {}
    endian = ">" if msg.is_bigendian else "<"
    for name in OBSERVATION_FIELDS:
        f = by_name.get(name)
        if f is None:
            raise MeasurementError(f"PointCloud2 has no field '{name}' (fields: {sorted(by_name)})")
        if f.datatype == PointField.FLOAT64:
            dt, size = np.dtype(endian + "f8"), 8
        elif f.datatype == PointField.FLOAT32:
            dt, size = np.dtype(endian + "f4"), 4
        else:
            raise MeasurementError(f"PointCloud2 field '{name}' has datatype {f.datatype}, expected FLOAT64")
        if f.offset + size > step:
            raise MeasurementError(f"PointCloud2 field '{name}' offset {f.offset} outside point_step {step}")
        buf = np.frombuffer(data, np.uint8, count=n * step).reshape(n, step)[:, f.offset:f.offset + size]
        out[name] = np.ascontiguousarray(buf).view(dt).reshape(n).astype(np.float64)
    return out
