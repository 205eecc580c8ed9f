"""Commands of the nodes, with std_srvs types only (robot_localization's ``reset`` / ``set_pose`` as the model).

Fusion node (:class:`FusionServices`)
    ``~/reset`` (``std_srvs/Trigger``): the filter starts over: the prior buffer, the pending measurements and
    every carried correction are forgotten (the response counts them); ``/diagnostics`` says "converging" until
    the next measurement is fused.
    ``~/set_pose`` (topic, ``geometry_msgs/PoseWithCovarianceStamped``, as robot_localization's ``set_pose``
    topic): the tool pose ``T_base_tool`` with its covariance (ROS convention, ``header.frame_id`` =
    ``frame_prefix + base_frame``) at its stamp.  The filter forgets its carried corrections and takes the pose
    as an ungated 6D measurement of the tool: the fused pose moves to it as far as the two covariances say (a
    small covariance pins it there), and the correction is carried on like any other (it fades as the arm
    moves).  Unlike robot_localization the state stays the kinematics prior plus a correction, so the prior's
    uncertainty keeps counting.  A bad message is counted and named; the node keeps running.
Online effects (:func:`add_save_model_service`)
    ``~/save_model`` (``std_srvs/Trigger``): write the current estimate as a model YAML to ``online_model_out``
    now (the response names the file; refused while ``online_model_out`` is empty or no model is built).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from geometry_msgs.msg import PoseWithCovarianceStamped
from std_srvs.srv import Trigger

from ppoe_core import lie
from ppoe_core.errors import MeasurementError
from ppoe_ros.common.conversions import pose_cov_from_msg
from ppoe_ros.common.diagnostics import NodeStats, guarded
from ppoe_ros.common.qos import reliable_qos

__all__ = ["FusionServices", "SET_POSE_SOURCE", "add_save_model_service"]

#: source key of a set_pose measurement (its correction replaces the previous set_pose's)
SET_POSE_SOURCE = "~/set_pose"


class FusionServices:
    """``~/reset`` and ``~/set_pose`` of a fusion node (see the module docstring).

    Parameters
    ----------
    node
        The fusion node (creates the service and the subscription).
    pipeline
        Its :class:`ppoe_core.estimation.pipeline.FusionPipeline`.
    measure
        The node's one entry of measurements into the pipeline (it reports and counts the outcome).
    prefix
        Its ``frame_prefix`` (``node.base_frame`` and ``node.tool_frame`` name the state's frames).
    stats
        The node's counters (a bad ``set_pose`` message is counted there).
    """

    def __init__(self, node: Any, pipeline: Any, measure: Callable[[Any], None], prefix: str,
                 stats: NodeStats) -> None:
        self.node, self.pipeline, self.measure = node, pipeline, measure
        self.prefix, self.base_frame, self.tool_frame = prefix, node.base_frame, node.tool_frame
        node.create_service(Trigger, "~/reset", self.reset)
        node.create_subscription(PoseWithCovarianceStamped, "~/set_pose",
                                 guarded(stats, "~/set_pose")(self.set_pose), reliable_qos(10))

    def reset(self, request: Any, response: Any) -> Any:
        """Forget priors, pending measurements and corrections; the response counts them."""
        p = self.pipeline
        n_prior, n_pending, n_corr = len(p.buffer), len(p.pending), len(p.corrections)
        p.reset()
        p.counts["resets"] += 1  # the node's "converging" status starts over
        response.success = True
        response.message = (f"filter reset: forgot {n_prior} priors, {n_pending} pending measurements and "
                            f"{n_corr} carried corrections")
        self.node.get_logger().info(response.message)
        return response

    def set_pose(self, msg: PoseWithCovarianceStamped) -> None:
        """Drop the carried corrections and fuse ``msg`` as an ungated 6D measurement of the tool."""
        from ppoe_core.estimation.pipeline import Measurement
        from ppoe_core.estimation.source_updater import PoseMeasurement

        T, cov_ros, stamp_ns, frame = pose_cov_from_msg(msg)
        if frame != self.prefix + self.base_frame:
            raise MeasurementError(f"set_pose frame '{frame}' is not base_frame '{self.prefix}{self.base_frame}'")
        if not cov_ros.any():
            raise MeasurementError("set_pose covariance is zero: give the pose's uncertainty")
        cov = lie.check_covariance(lie.cov_ros_to_local(T, cov_ros), name="set_pose covariance", size=6)
        n_corr = len(self.pipeline.corrections)
        self.pipeline.corrections.clear()
        payload = PoseMeasurement(self.tool_frame, self.base_frame, T, cov, None, None, 1.0)
        self.measure(Measurement(stamp_ns * 1e-9, SET_POSE_SOURCE, payload))
        self.node.get_logger().info(f"set_pose at {stamp_ns * 1e-9:.6f} s: {n_corr} carried corrections dropped, "
                                    f"the pose fused")


def add_save_model_service(node: Any, write_model: Callable[[], Any], out_param: str) -> Any:
    """``~/save_model`` (Trigger) calling ``write_model()`` (returns the path written, or None when off).

    ``out_param`` is the value of ``online_model_out`` (named in the refusal when empty)."""

    def save(request: Any, response: Any) -> Any:
        try:
            path = write_model() if out_param else None
        except Exception as exc:  # noqa: BLE001 - the answer names any failure; the node keeps running
            response.success, response.message = False, f"cannot write the model: {type(exc).__name__}: {exc}"
            return response
        if path is None:
            response.success = False
            response.message = ("online_model_out is empty: nowhere to write" if not out_param
                                else "no model yet (waiting for robot_description)")
        else:
            response.success, response.message = True, f"wrote {path}"
        return response

    return node.create_service(Trigger, "~/save_model", save)
