"""Per-stop roles of a static dataset bag: the ``/dataset/stop`` topic (JSON per stop).

Written by the importers (:mod:`ppoe_core.io.importers`), read by ``ppoe evaluate`` and
``ppoe diagnose`` to score a bag by its protocol (registration vs scored stops).
"""

from __future__ import annotations

__all__ = ["STOP_TOPIC", "read_stop_info"]

#: topic of the per-stop JSON description (``std_msgs/msg/String``) written by both importers
STOP_TOPIC = "/dataset/stop"


def read_stop_info(bag_path: str) -> list[tuple[float, dict]]:
    """The ``/dataset/stop`` messages of a bag: ``[(stamp [s], info dict), ...]`` in log order.

    Returns an empty list if the bag has no such topic.

    Raises
    ------
    BagError
        A message that is not a JSON object (names the topic and the message index).
    """
    import json

    from ppoe_core.errors import BagError
    from ppoe_core.io.bagio import deserialize, iter_raw

    out = []
    for k, raw in enumerate(iter_raw(bag_path, topics=[STOP_TOPIC])):
        if raw.msgtype != "std_msgs/msg/String":
            raise BagError(f"bag {bag_path}: topic {STOP_TOPIC} carries {raw.msgtype}, expected std_msgs/msg/String")
        msg = deserialize(raw.data, raw.msgtype, topic=STOP_TOPIC)
        try:
            info = json.loads(msg.data)
        except json.JSONDecodeError as exc:
            raise BagError(f"bag {bag_path}: topic {STOP_TOPIC} message {k}: not JSON ({exc})") from None
        if not isinstance(info, dict):
            raise BagError(f"bag {bag_path}: topic {STOP_TOPIC} message {k}: not a JSON object")
        out.append((raw.stamp_ns * 1e-9, info))
    return out
