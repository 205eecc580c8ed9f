"""Model YAML loading: every section, defaults, and every bad input with file/line."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import DATA

from ppoe_core import lie
from ppoe_core.errors import CovarianceError, ModelConfigError, UnknownFrameError, UnknownJointError
from ppoe_core.robot.config import load_contact_config, load_model_config, low_rank_factor
from ppoe_core.robot.urdf import parse_urdf

EDGE = DATA / "ppoe_edge.urdf"
EDGE_YAML = DATA / "ppoe_edge_model.yaml"


@pytest.fixture(scope="module")
def robot():
    return parse_urdf(EDGE)


def test_full_model_file(robot):
    c = load_model_config(EDGE_YAML, robot)
    assert c.source == str(EDGE_YAML)
    assert set(c.perturbations) == {"mount_joint", "j1", "j2", "j3", "j4", "finger_joint", "camera_optical_joint"}
    p = c.perturbations["j1"]
    np.testing.assert_allclose(p.covariance, np.diag([0, 0, 0, 0.0087**2, 0.0087**2, 0]))
    assert p.factor.shape == (6, 2)  # only the non-zero sigmas
    full = c.perturbations["j2"]
    assert full.covariance[0, 1] == 2.0e-7
    np.testing.assert_allclose(full.factor @ full.factor.T, full.covariance, atol=1e-20)
    assert c.joint_noise == {"j1": 0.001, "j3": 0.0002}
    assert (c.frames.base, c.frames.tool) == ("base_link", "tool0")
    assert c.camera.frame == "camera_optical_frame" and c.camera.pixel_sigma == 0.7
    assert c.tags.family == "tag36h11"
    tags = c.tags.by_id()
    assert set(tags) == {3, 7} and tags[3].link == "tool0" and tags[3].size == 0.04
    np.testing.assert_allclose(tags[3].T_link_tag, lie.from_xyz_rpy([0, 0, 0.01], [0, 0, 0]))
    np.testing.assert_allclose(tags[7].T_link_tag, np.eye(4))
    assert c.contact.plane_frame == "base_link" and c.contact.tool_link == "tool0"
    np.testing.assert_allclose(c.contact.covariance, np.diag(np.square([0.5, 0.5, 0.001, 0.017, 0.017, 0.17])))
    np.testing.assert_allclose(c.contact.tool_xyz, [0, 0, 0.01])
    assert (c.contact.force_threshold, c.contact.release_threshold) == (6.0, 2.5)
    assert c.tracker.link == "link4" and c.tracker.sigma == 0.0003
    assert c.imus["upper"].sigma == 0.0005 and c.imus["lower"].sigma == 0.0004  # default
    np.testing.assert_allclose(np.sqrt(np.diag(c.naive.covariance)), [0.07, 0.07, 0.03, 0.087, 0.087, 0.26])
    assert c.effects == []


def test_text_dict_and_file_agree(robot):
    text = EDGE_YAML.read_text()
    a = load_model_config(EDGE_YAML, robot)
    b = load_model_config(text, robot)
    d = load_model_config(yaml.safe_load(text), robot)
    assert b.source == "<string>" and d.source == "<dict>"
    for c in (b, d):
        assert set(c.perturbations) == set(a.perturbations)
        for n in a.perturbations:
            np.testing.assert_array_equal(c.perturbations[n].covariance, a.perturbations[n].covariance)


def test_defaults(robot):
    c = load_model_config(None, robot)
    assert c.perturbations == {} and c.joint_noise == {} and c.effects == []
    assert c.frames.base == "base_link"
    assert c.frames.tool is None  # the edge robot has several leaves
    assert c.camera is None and c.tags is None and c.contact is None and c.tracker is None
    p3 = parse_urdf(DATA / "planar3.urdf")
    assert load_model_config("", p3).frames.tool == "tool0"  # single leaf


def test_effects_section(robot):
    c = load_model_config(
        "effects:\n"
        "  - {name: joint_offset, location: j1, parameters: {offset: 0.001}}\n"
        "  - {name: thermal_growth, location: link2, parameters: {alpha: 1.0e-5},"
        " variable: temperature, reference: 20}\n"
        "  - {name: link_error, location: j3, parameters: {x: 0.001, rz: [0.1]}, ci: {x: [0.0, 0.002]}}\n",
        robot,
    )
    assert c.effects[0] == {"name": "joint_offset", "location": "j1", "parameters": {"offset": 0.001}}
    assert c.effects[1]["variable"] == "temperature" and c.effects[1]["reference"] == 20.0
    assert c.effects[2]["ci"] == {"x": [0.0, 0.002]}
    assert c.effect_wheres == ["<string>:2", "<string>:3", "<string>:4"]


def test_low_rank_factor():
    d = np.diag([0, 1e-6, 0, 4e-4, 0, 0])
    L = low_rank_factor(d)
    assert L.shape == (6, 2)
    np.testing.assert_allclose(L @ L.T, d)
    rng = np.random.default_rng(0)
    A = rng.normal(size=(6, 3))
    C = A @ A.T
    L = low_rank_factor(C)
    assert L.shape == (6, 3)
    np.testing.assert_allclose(L @ L.T, C, atol=1e-12)


def _err(robot, text, exc=ModelConfigError):
    with pytest.raises(exc) as ei:
        load_model_config(text, robot)
    return str(ei.value)


def test_unknown_top_level_key_names_key_and_line(robot):
    msg = _err(robot, "perturbations:\n  j1: {sigma: [0, 0, 0, 0, 0, 0.01]}\nperturbation_typo: {}\n")
    assert "'perturbation_typo'" in msg and msg.startswith("<string>:3:")


def test_unknown_key_in_entry(robot, tmp_path):
    p = tmp_path / "m.yaml"
    p.write_text("perturbations:\n  j1:\n    sigma: [0, 0, 0, 0, 0, 0.01]\n    sigmas: [1]\n")
    msg = _err(robot, p)
    assert str(p) in msg and ":4:" in msg and "'sigmas'" in msg and "perturbations.j1" in msg


@pytest.mark.parametrize(
    "text, exc, pattern",
    [
        ("perturbations:\n  j9: {sigma: [0, 0, 0, 0, 0, 1]}\n", UnknownJointError, "unknown joint 'j9'"),
        ("joint_noise:\n  jj: 0.1\n", UnknownJointError, "unknown joint 'jj'"),
        ("joint_noise:\n  tool_joint: 0.1\n", ModelConfigError, "fixed"),
        ("camera: {frame: cam_nope}\n", UnknownFrameError, "unknown link 'cam_nope'"),
        ("frames: {base: base_link, tool: tool9}\n", UnknownFrameError, "unknown link 'tool9'"),
        ("tags:\n  items:\n    - {id: 1, link: l9, size: 0.04}\n", UnknownFrameError, "unknown link 'l9'"),
        (
            "tags:\n  items:\n    - {id: 1, link: tool0, size: 0.04}\n    - {id: 1, link: link4, size: 0.04}\n",
            ModelConfigError,
            "duplicate tag id 1",
        ),
        ("tags:\n  items:\n    - {id: 1, link: tool0}\n", ModelConfigError, "missing required key 'size'"),
        ("imus:\n  a: {link: link1, rate: 3}\n", ModelConfigError, "unknown key 'rate'"),
        ("tracker: {link: link4, sigma: -1}\n", ModelConfigError, "must be > 0"),
        ("perturbations:\n  j1: {sigma: [0, 0, 0, 0, 0]}\n", ModelConfigError, "list of 6 numbers"),
        ("perturbations:\n  j1: {sigma: [0, 0, 0, 0, 0, -1]}\n", ModelConfigError, ">= 0"),
        ("perturbations:\n  j1: {sigma: [0, 0, 0, 0, 0, .nan]}\n", ModelConfigError, "finite"),
        ("perturbations:\n  j1: {sigma: [0, 0, 0, 0, 0, x]}\n", ModelConfigError, "must be a number"),
        ("perturbations:\n  j1: {}\n", ModelConfigError, "exactly one of 'sigma'"),
        ("perturbations:\n  j1: [1, 2]\n", ModelConfigError, "must be a mapping, got a list of 2 items"),
        ("perturbations:\n  j1: {covariance: [[1, 0], [0, 1]]}\n", ModelConfigError, "6x6"),
        ("contact:\n  plane: {frame: base_link}\n  tool_point: {link: tool0}\n", ModelConfigError, "'sigma'"),
        (
            "contact:\n  plane: {frame: base_link}\n  sigma: [1, 1, 1, 1, 1, 1]\n  tool_point: {link: tool0}\n"
            "  force_threshold: 2\n  release_threshold: 3\n",
            ModelConfigError,
            "above the force threshold",
        ),
        (
            "effects:\n  - {name: gremlins, location: j1, parameters: {}}\n",
            ModelConfigError,
            "unknown effect 'gremlins'",
        ),
        (
            "effects:\n  - {name: joint_offset, location: j1, parameters: {offset: 1}, note: x}\n",
            ModelConfigError,
            "unknown key 'note'",
        ),
        ("perturbations: {j1: {sigma: [0, 0, 0, 0, 0, 1]}}\nperturbations: {}\n", ModelConfigError, "duplicate key"),
        ("perturbations:\n  j1: {sigma: [0, 0\n", ModelConfigError, "does not parse"),
        ("- just\n- a list\n", ModelConfigError, "mapping at the top level, got a list of 2 items"),
    ],
)
def test_bad_inputs(robot, text, exc, pattern):
    msg = _err(robot, text, exc)
    assert re.search(re.escape(pattern), msg), msg
    assert msg.startswith("<string>")
    assert "_LList" not in msg and "_LDict" not in msg, msg  # no internal class names


def _cov_yaml(C):
    rows = "\n".join("      - [" + ", ".join(repr(float(x)) for x in r) + "]" for r in C)
    return f"perturbations:\n  j4:\n    covariance:\n{rows}\n"


def test_non_symmetric_covariance_names_joint(robot):
    C = np.eye(6) * 1e-4
    C[0, 3] = 1e-5
    msg = _err(robot, _cov_yaml(C), CovarianceError)
    assert "j4" in msg and "not symmetric" in msg and msg.startswith("<string>:3:")  # the key line


def test_non_psd_covariance_names_joint(robot):
    C = np.eye(6) * 1e-4
    C[1, 2] = C[2, 1] = 3e-4  # eigenvalue 1e-4 - 3e-4 < 0
    msg = _err(robot, _cov_yaml(C), CovarianceError)
    assert "j4" in msg and "positive semi-definite" in msg


def test_unreadable_file(robot, tmp_path):
    with pytest.raises(ModelConfigError, match="cannot read model YAML"):
        load_model_config(tmp_path / "absent.yaml", robot)
    binary = tmp_path / "binary.yaml"
    binary.write_bytes(b"\xff\xfe\x00perturbations")
    with pytest.raises(ModelConfigError, match=r"binary.yaml: model YAML is not UTF-8 text"):
        load_model_config(binary, robot)


def test_contact_section_alone_without_urdf(robot, tmp_path):
    """load_contact_config (the contact node has no URDF) gives what load_model_config gives."""
    humanoid = Path(__file__).resolve().parents[1] / "config" / "robots" / "humanoid_model.yaml"
    full = load_model_config(humanoid, parse_urdf(humanoid.parent / "humanoid.urdf")).contact
    alone = load_contact_config(humanoid)
    np.testing.assert_array_equal(alone.T_frame_plane, full.T_frame_plane)
    np.testing.assert_array_equal(alone.covariance, full.covariance)
    assert (alone.plane_frame, alone.force_threshold, alone.release_threshold) == (
        full.plane_frame,
        full.force_threshold,
        full.release_threshold,
    )
    assert load_contact_config("perturbations: {}\n", is_text=True) is None
    text = "contact:\n  plane: {frame: table}\n  sigma: [1, 1, 1, 1, 1, 1]\n  tool_point: {link: tip}\n"
    assert load_contact_config(text, is_text=True).plane_frame == "table"  # no URDF: names not checked
    with pytest.raises(UnknownFrameError, match="unknown link 'table'"):
        load_contact_config(text, robot, is_text=True)
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "frames: {base: x}\ncontact:\n  plane: {frame: table}\n  sigma: [1, 1, 1]\n  tool_point: {link: tip}\n"
    )
    with pytest.raises(ModelConfigError, match=r"bad.yaml:4: contact.sigma: must be a list of 6 numbers"):
        load_contact_config(bad)
