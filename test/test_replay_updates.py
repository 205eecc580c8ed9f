"""The tag update of the replay and the fusion node (ppoe_core.estimation.updater): tag points kept for a tag fixed to
the tool frame, made anew at every configuration for a tag on a link that moves relative to it."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ppoe_core.estimation.measurements import tag_points
from ppoe_core.estimation.pipeline import make_updater
from ppoe_core.model.ppoe import PPOEModel

ROBOTS = Path(__file__).resolve().parents[1] / "config" / "robots"


def _counting(model):
    calls = []
    real = model.fk_mean

    def fk_mean(joints, frm=None, to=None, context=None):
        calls.append((frm, to))
        return real(joints, frm, to, context)

    model.fk_mean = fk_mean
    return calls


def _joints(model, q6):
    return {n: (q6 if n == "arm_joint_6" else 0.3) for n in model.joint_names}


def test_points_of_a_tag_fixed_to_the_tool_are_made_once():
    model = PPOEModel.from_files(ROBOTS / "rover.urdf", ROBOTS / "rover_model.yaml")
    up = make_updater(model, "base_link", "tool_link")
    calls = _counting(model)
    ids, corners = np.array([1, 1, 3, 3]), np.array([0, 2, 0, 4])
    first = up._tag_points_tool(ids, corners, _joints(model, 0.0), "here")
    again = up._tag_points_tool(ids, corners, _joints(model, 1.0), "here")
    assert calls == [("tool_link", "tag1_link"), ("tool_link", "tag3_link")]  # once per tag, not per update
    for a, b in zip(first[0], again[0]):
        np.testing.assert_array_equal(a, b)
    item = up.tags[3]
    expected = tag_points(item.size, model.fk_mean({}, "tool_link", "tag3_link") @ item.T_link_tag)
    np.testing.assert_array_equal(again[0][3], expected[4])
    assert again[2] == ["tag 1 corner 0", "tag 1 corner 2", "tag 3 corner 0", "tag 3 corner 4"]


def test_points_of_a_tag_on_a_moving_link_follow_the_joints():
    """State frame arm_link_5: arm_joint_6 lies between it and the tags, so their points change with it."""
    model = PPOEModel.from_files(ROBOTS / "rover.urdf", ROBOTS / "rover_model.yaml")
    up = make_updater(model, "base_link", "arm_link_5")
    calls = _counting(model)
    ids, corners = np.array([1]), np.array([1])
    pts = []
    for q6 in (0.0, 1.0, 0.0):
        j = _joints(model, q6)
        p = up._tag_points_tool(ids, corners, j, "here")[0][0]
        item = up.tags[1]
        np.testing.assert_array_equal(p, tag_points(item.size, model.fk_mean(j, "arm_link_5", "tag1_link")
                                                    @ item.T_link_tag)[1])
        pts.append(p)
    assert len(calls) == 6  # one per update (and one per check above)
    assert not np.allclose(pts[0], pts[1])
    np.testing.assert_array_equal(pts[0], pts[2])
