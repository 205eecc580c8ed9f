"""URDF parser: joint types, origins, axes, mimic, tree checks and error messages."""

from __future__ import annotations

import re

import numpy as np
import pytest
from conftest import DATA

from ppoe_core import lie
from ppoe_core.errors import UnknownFrameError, UnknownJointError, UrdfError
from ppoe_core.robot.urdf import parse_urdf

EDGE = DATA / "ppoe_edge.urdf"


def _rot(axis: str, a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    if axis == "x":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _robot(body: str) -> str:
    return f'<?xml version="1.0"?>\n<robot name="t">\n{body}\n</robot>\n'


def test_edge_robot_structure():
    r = parse_urdf(EDGE)
    assert r.name == "ppoe_edge"
    assert r.root == "base_link"
    assert r.source == str(EDGE)
    assert r.independent_joints == ["j1", "j2", "j3", "j4"]
    assert r.movable_joints == ["j1", "j2", "j3", "j4", "finger_joint"]
    types = {n: j.type for n, j in r.joints.items()}
    assert types["mount_joint"] == "fixed"
    assert types["j2"] == "continuous"
    assert types["j3"] == "prismatic"
    assert r.children("link4") == ["tool_joint", "finger_joint"]
    assert r.parent_joint("base_link") is None
    assert r.parent_joint("tool0").name == "tool_joint"


def test_origin_rpy_is_fixed_axis_zyx():
    r = parse_urdf(EDGE)
    T = r.joints["mount_joint"].origin
    R = _rot("z", 0.2) @ _rot("y", -0.1) @ _rot("x", 0.05)
    np.testing.assert_allclose(T[:3, :3], R, atol=1e-15)
    np.testing.assert_allclose(T[:3, 3], [0.1, -0.2, 0.3])
    np.testing.assert_allclose(T[3], [0, 0, 0, 1])


def test_axes_are_normalised_and_twists_by_type():
    r = parse_urdf(EDGE)
    np.testing.assert_allclose(r.joints["j1"].axis, [0, 0, 1])
    np.testing.assert_allclose(r.joints["j2"].axis, np.array([1, 1, 0]) / np.sqrt(2))
    a4 = np.array([0.3, -0.2, 0.9])
    np.testing.assert_allclose(r.joints["j4"].axis, a4 / np.linalg.norm(a4))
    np.testing.assert_allclose(r.joints["j3"].twist, [0, -1, 0, 0, 0, 0])
    np.testing.assert_allclose(r.joints["j1"].twist, [0, 0, 0, 0, 0, 1])
    np.testing.assert_allclose(r.joints["tool_joint"].twist, np.zeros(6))


def test_default_axis_is_x():
    r = parse_urdf(_robot(
        '<link name="a"/><link name="b"/>'
        '<joint name="j" type="revolute"><parent link="a"/><child link="b"/></joint>'
    ))
    np.testing.assert_allclose(r.joints["j"].axis, [1, 0, 0])
    np.testing.assert_allclose(r.joints["j"].origin, np.eye(4))


def test_limits_inertial_mimic():
    r = parse_urdf(EDGE)
    lim = r.joints["j3"].limit
    assert (lim.lower, lim.upper, lim.effort, lim.velocity) == (0.0, 0.3, 50.0, 0.2)
    assert r.joints["j2"].limit is None
    inert = r.links["link1"].inertial
    assert inert.mass == 2.5
    np.testing.assert_allclose(inert.inertia, [[0.01, 0.001, 0], [0.001, 0.02, 0], [0, 0, 0.03]])
    np.testing.assert_allclose(inert.origin[:3, 3], [0, 0, 0.1])
    assert r.links["tool0"].inertial is None
    f = r.joints["finger_joint"]
    assert f.mimic.joint == "j4" and f.mimic.multiplier == -0.5 and f.mimic.offset == 0.1
    assert f.mimic_root == ("j4", -0.5, 0.1)
    assert not f.independent and f.movable


def test_mimic_chain_resolves_to_master():
    r = parse_urdf(_robot(
        '<link name="a"/><link name="b"/><link name="c"/><link name="d"/>'
        '<joint name="m" type="revolute"><parent link="a"/><child link="b"/></joint>'
        '<joint name="s1" type="revolute"><parent link="b"/><child link="c"/>'
        '<mimic joint="m" multiplier="2" offset="0.5"/></joint>'
        '<joint name="s2" type="prismatic"><parent link="c"/><child link="d"/>'
        '<mimic joint="s1" multiplier="-3" offset="1"/></joint>'
    ))
    # q_s2 = -3 (2 q + 0.5) + 1 = -6 q - 0.5
    assert r.joints["s2"].mimic_root == ("m", -6.0, -0.5)
    assert r.independent_joints == ["m"]


def test_string_and_file_agree():
    a = parse_urdf(EDGE)
    b = parse_urdf(EDGE.read_text())
    assert b.source == "<string>"
    assert list(a.joints) == list(b.joints)
    for n in a.joints:
        np.testing.assert_array_equal(a.joints[n].origin, b.joints[n].origin)


def test_chain_up_and_down():
    r = parse_urdf(EDGE)
    up, down = r.chain("camera_optical_frame", "tool0")
    assert up == ["camera_optical_joint", "camera_joint"]
    assert down == ["j2", "j3", "j4", "tool_joint"]
    assert r.chain("tool0", "tool0") == ([], [])
    assert r.path_from_root("link2") == ["mount_joint", "j1", "j2"]


def test_unknown_names():
    r = parse_urdf(EDGE)
    with pytest.raises(UnknownFrameError, match="nope"):
        r.chain("base_link", "nope")
    with pytest.raises(UnknownJointError, match="jx"):
        r.joint("jx")


def _line_of(text: str, needle: str) -> int:
    for i, line in enumerate(text.splitlines(), start=1):
        if needle in line:
            return i
    raise AssertionError(needle)


@pytest.mark.parametrize(
    "body, needle, pattern",
    [
        ('<link name="a"/><link name="b"/>\n<joint name="fl" type="floating">'
         '<parent link="a"/><child link="b"/></joint>', 'name="fl"', "floating"),
        ('<link name="a"/><link name="b"/>\n<joint name="pl" type="planar">'
         '<parent link="a"/><child link="b"/></joint>', 'name="pl"', "planar"),
        ('<link name="a"/><link name="b"/>\n<joint name="w" type="screw">'
         '<parent link="a"/><child link="b"/></joint>', 'name="w"', "unknown type 'screw'"),
        ('<link name="a"/><link name="b"/>\n<joint name="z" type="revolute">'
         '<parent link="a"/><child link="b"/>\n<axis xyz="0 0 0"/></joint>', 'axis xyz', "zero axis"),
        ('<link name="a"/>\n<joint name="u" type="fixed"><parent link="a"/>'
         '<child link="ghost"/></joint>', 'name="u"', "unknown child link 'ghost'"),
        ('<link name="a"/><link name="b"/>\n<joint name="u" type="fixed"><parent link="gone"/>'
         '<child link="b"/></joint>', 'name="u"', "unknown parent link 'gone'"),
        ('<link name="a"/><link name="b"/>\n<joint name="d" type="fixed"><parent link="a"/>'
         '<child link="b"/></joint>\n<joint name="d" type="fixed"><parent link="b"/><child link="a"/></joint>',
         None, "duplicate joint name 'd'"),
        ('<link name="a"/>\n<link name="a"/>', None, "duplicate link name 'a'"),
        ('<link name="a"/><link name="b"/>\n<link name="c"/>\n<joint name="j" type="fixed">'
         '<parent link="a"/><child link="b"/></joint>', None, "2 root links"),
        ('<link name="a"/><link name="b"/><link name="c"/>\n<joint name="j1" type="fixed">'
         '<parent link="a"/><child link="b"/></joint>\n<joint name="j2" type="fixed">'
         '<parent link="c"/><child link="b"/></joint>', 'name="j2"', "two parent joints"),
        ('<link name="a"/><link name="b"/><link name="r"/>\n<joint name="j0" type="fixed">'
         '<parent link="r"/><child link="r"/></joint>', 'name="j0"', "to itself"),
        ('<link name="a"/><link name="b"/>\n<joint name="m" type="revolute"><parent link="a"/>'
         '<child link="b"/><mimic joint="nobody"/></joint>', 'name="m"', "mimics unknown joint 'nobody'"),
        ('<link name="a"/><link name="b"/>\n<joint name="o" type="fixed"><parent link="a"/>'
         '<child link="b"/>\n<origin xyz="0 x 0"/></joint>', 'origin xyz', "not 3 numbers"),
        ('<link name="a"/><link name="b"/>\n<joint name="o" type="fixed"><parent link="a"/>'
         '<child link="b"/>\n<origin xyz="0 0"/></joint>', 'origin xyz', "expected 3 numbers"),
        ('<link name="a"/><link name="b"/>\n<joint name="o" type="fixed"><parent link="a"/>'
         '<child link="b"/>\n<origin rpy="0 nan 0"/></joint>', 'origin rpy', "NaN"),
        ('<link name="a"/><link name="b"/>\n<joint name="nt"><parent link="a"/>'
         '<child link="b"/></joint>', 'name="nt"', "no 'type'"),
        ('<link name="a"><inertial>\n<mass value="heavy"/></inertial></link>', 'mass value', "not a number"),
        ('<link/>', '<link/>', "without a 'name'"),
    ],
)
def test_bad_urdf_names_file_line_and_item(body, needle, pattern):
    text = _robot(body)
    with pytest.raises(UrdfError, match=re.escape(pattern)) as ei:
        parse_urdf(text)
    msg = str(ei.value)
    assert msg.startswith("<string>")
    if needle is not None:
        assert f"<string>:{_line_of(text, needle)}:" in msg


def test_cycle_without_root():
    text = _robot(
        '<link name="a"/><link name="b"/>'
        '<joint name="j1" type="fixed"><parent link="a"/><child link="b"/></joint>'
        '<joint name="j2" type="fixed"><parent link="b"/><child link="a"/></joint>'
    )
    with pytest.raises(UrdfError, match="cycle"):
        parse_urdf(text)


def test_mimic_cycle():
    text = _robot(
        '<link name="a"/><link name="b"/><link name="c"/>'
        '<joint name="j1" type="revolute"><parent link="a"/><child link="b"/><mimic joint="j2"/></joint>'
        '<joint name="j2" type="revolute"><parent link="b"/><child link="c"/><mimic joint="j1"/></joint>'
    )
    with pytest.raises(UrdfError, match="mimic cycle"):
        parse_urdf(text)


def test_xml_syntax_error_names_file_and_line(tmp_path):
    p = tmp_path / "broken.urdf"
    p.write_text('<?xml version="1.0"?>\n<robot name="x">\n  <link name="a">\n  </lnk>\n</robot>\n')
    with pytest.raises(UrdfError) as ei:
        parse_urdf(p)
    msg = str(ei.value)
    assert str(p) in msg and ":4:" in msg and "not well-formed" in msg


def test_missing_file_and_wrong_root(tmp_path):
    with pytest.raises(UrdfError, match="cannot read URDF"):
        parse_urdf(tmp_path / "nothing.urdf")
    with pytest.raises(UrdfError, match="expected <robot>"):
        parse_urdf("<sdf><model/></sdf>")
    with pytest.raises(UrdfError, match="no <link>"):
        parse_urdf("<robot name='e'></robot>")


def test_origin_matches_lie_from_xyz_rpy():
    r = parse_urdf(EDGE)
    np.testing.assert_allclose(
        r.joints["camera_optical_joint"].origin,
        lie.from_xyz_rpy([0, 0, 0], [-np.pi / 2, 0, -np.pi / 2]),
    )
    # optical frame convention: z forward = camera_link x, x right = -camera_link y
    R = r.joints["camera_optical_joint"].origin[:3, :3]
    np.testing.assert_allclose(R[:, 2], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(R[:, 0], [0, -1, 0], atol=1e-12)
