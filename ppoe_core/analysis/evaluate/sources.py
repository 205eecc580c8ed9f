"""The fusion node's sensor blocks replayed from a bag (``ppoe evaluate --fusion-params`` with ``sources``): every
message of a block's topic turned into a measurement by the node's own rules
(:mod:`ppoe_core.estimation.sources`: frame checks, the at-rest gate, the noise choice), in the node's counters.

Topics a block may name (what :func:`ppoe_core.io.bagio.read_bag` keeps): a point source ``/ground_truth/point`` or
``/ground_truth/point/<name>``, an accelerometer ``/imu/<name>``, a pose source any ``PoseWithCovarianceStamped``
topic.  A relative topic is taken in the root namespace (as ``ppoe play`` publishes the bag).
"""

from __future__ import annotations

from typing import Any

from ppoe_core.errors import BagError, MeasurementError, ModelConfigError
from ppoe_core.estimation.corrections import Measurement
from ppoe_core.estimation.pipeline import source_key
from ppoe_core.estimation.sources import (
    SourceConfig, UnknownFrame, complete_source, imu_payload, point_payload, pose_payload,
)
from ppoe_core.io.messages import IMU_TOPIC_PREFIX, TOPIC_GT_POINT

__all__ = ["source_measurements", "measurement_dim"]


def _series(data: Any, topic: str) -> Any:
    """The bag's series of ``topic`` for a source, or None."""
    if topic == TOPIC_GT_POINT:
        return data.ground_truth_point if len(data.ground_truth_point) else None
    if topic.startswith(IMU_TOPIC_PREFIX):
        return data.imus.get(topic[len(IMU_TOPIC_PREFIX):])
    return data.ground_truth_points.get(topic) or data.poses_with_covariance.get(topic)


def _payloads(src: SourceConfig, model: Any, series: Any) -> list[Any]:
    """One payload (or the exception it raised, or the not-at-rest reason) per message of ``series``."""
    out: list[Any] = []
    for i, frame_id in enumerate(series.frame_ids):
        try:
            if src.kind == "point":
                out.append(point_payload(src, model, frame_id, series.p[i]))
            elif src.kind == "pose":
                T = series.T[i]
                out.append(pose_payload(src, model, frame_id, T, series.cov_ros[i]))
            else:
                out.append(imu_payload(src, model, frame_id, series.linear_acceleration[i],
                                       series.accel_covariance[i]))
        except MeasurementError as exc:
            out.append(exc)
    return out


def source_measurements(data: Any, model: Any, sources: list[SourceConfig],
                        bag: str) -> tuple[list[Measurement], dict[str, Any]]:
    """The measurements of ``sources`` in ``data`` (and per source the node's counts: ``measurements``,
    ``unknown_link``, ``not_at_rest``, ``bad`` with the first errors).

    Raises
    ------
    ModelConfigError
        A source the node would switch off (its link is not in the URDF, no tracker entry for it ...).
    BagError
        A source's topic has no messages in the bag it can read.
    """
    out: list[Measurement] = []
    counts: dict[str, Any] = {}
    for src in sources:
        topic = "/" + src.topic.lstrip("/")
        off = complete_source(src, model)
        if off:
            raise ModelConfigError(f"source '{src.name}' on {topic}: {off}")
        series = _series(data, topic)
        if series is None or len(series) == 0:
            raise BagError(f"bag {bag}: source '{src.name}' ({src.kind}): no messages on {topic} (a point source reads "
                           f"{TOPIC_GT_POINT}[/<name>], an imu source {IMU_TOPIC_PREFIX}<name>, a pose source a "
                           "PoseWithCovarianceStamped topic)")
        c: dict[str, Any] = {"topic": topic, "kind": src.kind, "measurements": 0, "unknown_link": 0,
                             "not_at_rest": 0, "bad": 0, "errors": []}
        for i, p in enumerate(_payloads(src, model, series)):
            if isinstance(p, UnknownFrame):
                c["unknown_link"] += 1
            elif isinstance(p, str):
                c["not_at_rest"] += 1
            elif isinstance(p, Exception):
                c["bad"] += 1
                if len(c["errors"]) < 5:
                    c["errors"].append(str(p))
            else:
                c["measurements"] += 1
                out.append(Measurement(float(series.stamps[i]), source_key(topic, series.frame_ids[i]), p))
        counts[src.name] = c
    return out, counts


def measurement_dim(payload: Any, known_tags: Any) -> int:
    """Dimension of a measurement (for the mean NIS per dimension): 2 per known tag point, 1 for a contact plane,
    the used components of a point, pose or accelerometer."""
    if hasattr(payload, "ids"):
        return 2 * sum(int(t) in known_tags for t in payload.ids)
    mask = getattr(payload, "mask", None)
    if hasattr(payload, "T_frame_link"):
        return 6 if mask is None else int(sum(mask))
    if hasattr(payload, "point_frame") or hasattr(payload, "accel"):
        return 3 if mask is None else int(sum(mask))
    return 1
