"""ppoe_core.sensing.contact: the contact node's detector, force measure, wrench replay and plane (no ROS)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import REPO
from hypothesis import given, settings
from hypothesis import strategies as st

from ppoe_core import lie
from ppoe_core.errors import MeasurementError, ModelConfigError
from ppoe_core.robot.config import load_contact_config
from ppoe_core.sensing.contact import (
    FORCE_COMPONENTS,
    ContactDetector,
    contact_stamps,
    force_measure,
    plane_from_config,
)

MODEL = REPO / "config" / "robots" / "humanoid_model.yaml"


def test_threshold_and_hysteresis_edges() -> None:
    det = ContactDetector(5.0, 2.0)
    # 4.99 stays off, exactly 5.0 enters (>=), exactly 2.0 stays on (release is strict <), 1.99 leaves,
    # 4.0 between the thresholds stays off (hysteresis), 7.0 enters again
    forces = [0.0, 4.99, 5.0, 3.0, 2.0, 1.99, 4.0, 7.0, 2.0, 0.0]
    states = [det.update(f) for f in forces]
    assert states == [False, False, True, True, True, False, False, True, True, False]
    assert det.in_contact is False


@pytest.mark.parametrize("enter, release", [(2.0, 2.0), (2.0, 3.0), (float("nan"), 1.0), (5.0, float("inf"))])
def test_bad_thresholds_refused(enter: float, release: float) -> None:
    with pytest.raises(ModelConfigError, match="threshold"):
        ContactDetector(enter, release)


def test_signed_axis_mode() -> None:
    f = np.array([[3.0, -4.0, 0.0], [0.0, 0.0, -6.0], [0.0, 0.0, 6.0]])
    np.testing.assert_allclose(force_measure(f, "norm"), [5.0, 6.0, 6.0])
    np.testing.assert_allclose(force_measure(f, "x"), [3.0, 0.0, 0.0])
    np.testing.assert_allclose(force_measure(f, "-y"), [4.0, 0.0, 0.0])
    np.testing.assert_allclose(force_measure(f, "-z"), [-0.0, 6.0, -6.0])
    with pytest.raises(ModelConfigError, match="force_component must be one of"):
        force_measure(f, "sideways")
    # pressing down (-z of the sensor) is contact; pulling up with the same magnitude is not
    stamps = np.array([1.0, 2.0, 3.0])
    on, counts = contact_stamps(stamps, f, ContactDetector(5.0, 2.0), "-z")
    assert on.tolist() == [2.0] and counts["contacts"] == 1
    on, _ = contact_stamps(stamps, f, ContactDetector(5.0, 2.0), "norm")
    assert on.tolist() == [1.0, 2.0, 3.0]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-20.0, 20.0, allow_nan=False), min_size=1, max_size=40), st.sampled_from(FORCE_COMPONENTS))
def test_replay_equals_message_by_message_detection(fz: list[float], component: str) -> None:
    """contact_stamps == feeding the detector one force measure per message (the node's callback)."""
    force = np.column_stack([np.full(len(fz), 1.0), np.zeros(len(fz)), fz])
    stamps = 10.0 + 0.01 * np.arange(len(fz))
    on, counts = contact_stamps(stamps, force, ContactDetector(5.0, 2.0), component)
    det = ContactDetector(5.0, 2.0)
    expect = [t for t, f in zip(stamps, force) if det.update(float(force_measure(f, component)))]
    np.testing.assert_array_equal(on, expect)
    assert counts["published"] == len(expect) and counts["bad"] == 0


def test_replay_ignores_bad_messages_like_the_node() -> None:
    # as test_contact_node's live sequence: NaN is bad (no update), a stamp jumping back is bad
    f = np.array([[0, 0, 0], [0, 3, 0], [0, 0, -6], [4, 0, 0], [1.5, 2, 0], [np.nan, 0, 0], [0, 0, 1.9],
                  [0, 4, 0], [3, 0, 4], [1, 0, 0], [0, 0, 9.0], [0, 0, 9.0]], dtype=float)
    stamps = 10.0 + 0.01 * np.arange(len(f))
    stamps[10] = 10.0  # jumps back: ignored, even with 9 N
    on, counts = contact_stamps(stamps, f, ContactDetector(5.0, 2.0))
    np.testing.assert_array_equal(on, stamps[[2, 3, 4, 8, 11]])
    assert counts == {"received": 12, "bad": 2, "contacts": 3, "published": 5}
    with pytest.raises(MeasurementError, match="/wrench: 3 stamps but force of shape"):
        contact_stamps(stamps[:3], f, ContactDetector(5.0, 2.0))


def test_plane_from_model_yaml_and_parameter_overrides() -> None:
    contact = load_contact_config(MODEL)
    plane = plane_from_config(contact, "camera_optical_frame")
    assert plane.frame == contact.plane_frame
    np.testing.assert_array_equal(plane.T_frame_plane, contact.T_frame_plane)
    np.testing.assert_allclose(plane.cov_plane, contact.covariance)
    np.testing.assert_allclose(plane.cov_ros, lie.cov_local_to_ros(plane.T_frame_plane, plane.cov_plane))
    # the node's empty parameters keep the YAML; given ones replace single parts
    p = plane_from_config(contact, None, {"plane_frame": "", "plane_xyz": [0.1, 0.2, 0.3], "plane_rpy": [],
                                          "plane_sigma": [0.1, 0.1, 0.002, 0.01, 0.01, 0.1]})
    np.testing.assert_array_equal(p.T_frame_plane[:3, :3], contact.T_frame_plane[:3, :3])
    np.testing.assert_array_equal(p.T_frame_plane[:3, 3], [0.1, 0.2, 0.3])
    np.testing.assert_allclose(np.sqrt(np.diag(p.cov_plane)), [0.1, 0.1, 0.002, 0.01, 0.01, 0.1])
    # no contact section: frame from frames.base, Sigma_v required
    p = plane_from_config(None, "base_link", {"plane_sigma": [0.1] * 6, "plane_rpy": [0.0, 0.0, 0.5]})
    assert p.frame == "base_link"
    np.testing.assert_allclose(p.T_frame_plane, lie.from_xyz_rpy([0, 0, 0], [0, 0, 0.5]))
    with pytest.raises(ModelConfigError, match="node x: no plane Sigma_v"):
        plane_from_config(None, "base_link", where="node x")
    with pytest.raises(ModelConfigError, match="no contact plane frame"):
        plane_from_config(None, None, {"plane_sigma": [0.1] * 6})
    with pytest.raises(ModelConfigError, match="parameter plane_xyz must be finite"):
        plane_from_config(contact, None, {"plane_xyz": [0.0, float("nan"), 0.0]})
    with pytest.raises(ModelConfigError, match="parameter plane_sigma must have 0 or 6 values"):
        plane_from_config(contact, None, {"plane_sigma": [0.1, 0.1]})
    with pytest.raises(ModelConfigError, match="parameter plane_sigma must be finite"):
        plane_from_config(contact, None, {"plane_sigma": [0.1, 0.1, float("inf"), 0.1, 0.1, 0.1]})
