"""Where the held-out pixel residual concentrates (``pixel_structure.pixel_residual_structure``): a principal
point error shows as image-position structure, a wrong tag point as a per-tag bias, noise as neither."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CONFIG, DATASETS

from ppoe_core.analysis.diagnose import predict_pixels
from ppoe_core.analysis.diagnose.joint_cv import joint_heldout
from ppoe_core.analysis.diagnose.joint_synthetic import K_SYN, arm7_joint_data
from ppoe_core.analysis.diagnose.pixel_structure import pixel_residual_structure, structure_summary
from ppoe_core.model.effects import make_effect
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf

CAM = "camera_optical_frame"


@pytest.fixture(scope="module")
def robot():
    return parse_urdf(CONFIG / "robots" / "arm7.urdf")


def _camera_fit_structure(robot, obs):
    """Cameras-only fit of ``camera_extrinsics@camera_joint``, held out over poses, and the residual's structure."""
    tree = KinematicTree(robot)
    held = joint_heldout(tree, [make_effect("camera_extrinsics", "camera_joint", tree)], None, obs, folds=5)
    return held, pixel_residual_structure(obs, held["pixel_residual"], tree)[CAM]


def _regenerate(robot, obs, K=None, shift=None, sigma=0.5, seed=1):
    """Measured pixels of ``obs`` made again with intrinsics ``K`` and / or tag points moved by ``shift`` (row mask,
    offset [m] on the link); the model keeps the nominal ones."""
    tree = KinematicTree(robot)
    true = obs.subset(np.arange(len(obs)))
    if K is not None:
        true.K = [K]
    if shift is not None:
        true.point = true.point + np.where(shift[0][:, None], shift[1], 0.0)
    obs.uv = predict_pixels(tree, true, []) + np.random.default_rng(seed).normal(0.0, sigma, (len(obs), 2))
    return obs


def test_principal_point_error_shows_as_image_position(robot):
    """Pixels made with the principal point 25 px off in u and 15 px in v, fitted with the nominal one: the camera
    pose absorbs most of it, the rest is a smooth image-position pattern (not a per-tag bias)."""
    _, obs = arm7_joint_data(robot, [], n=80)
    K = K_SYN.copy()
    K[0, 2] += 25.0
    K[1, 2] += 15.0
    held, s = _camera_fit_structure(robot, _regenerate(robot, obs, K=K))
    assert s["rms"] > 2.0, s
    assert s["explained_by"][0] == "image_position", s
    assert s["rms_after_image_position"] < 0.5 * s["rms"], s
    assert s["rms_after_tag_bias"] > 0.8 * s["rms"], s
    line = structure_summary({CAM: s})
    assert line.startswith(f"\nTag pixels of {CAM}: the held-out residual") and "principal point" in line, line


def test_wrong_tag_point_shows_as_tag_bias(robot):
    """One of the seven tag points 15 mm off its nominal place on its link: a per-tag (3D point) offset, no image
    pattern; as a constant pixel offset per tag (no chain given) it is not seen, the link turns between poses."""
    _, obs = arm7_joint_data(robot, [], n=80)
    moved = np.all(np.isclose(obs.point, obs.point[0]), axis=1) & (obs.links == obs.links[0])
    held, s = _camera_fit_structure(robot, _regenerate(robot, obs, shift=(moved, np.array([0.015, 0.0, 0.0]))))
    assert s["tags"] == 7
    assert s["explained_by"][0] == "tag_bias", s
    assert s["rms_after_tag_bias"] < 0.7 * s["rms"], s
    flat = pixel_residual_structure(obs, held["pixel_residual"])[CAM]
    assert flat["tag_model"] == "pixel offset" and flat["explained_by"] == [], flat


def test_noise_only_has_no_structure(robot):
    """Nothing but 0.5 px noise: neither model explains anything and the within-pose scatter is the noise."""
    _, obs = arm7_joint_data(robot, [], n=80)
    held, s = _camera_fit_structure(robot, _regenerate(robot, obs))
    assert s["explained_by"] == [], s
    assert s["rms"] < 1.0
    assert s["rms_after_tag_bias_and_image_position"] > 0.9 * s["rms"], s
    assert structure_summary({CAM: s}) == ""


def test_residual_shape_is_checked(robot):
    _, obs = arm7_joint_data(robot, [], n=10)
    with pytest.raises(ValueError, match="residual has shape"):
        pixel_residual_structure(obs, np.zeros((3, 2)))


@pytest.mark.datasets
@pytest.mark.skipif(not (DATASETS / "motoman_leica").exists(), reason="Motoman dataset not present")
def test_motoman_camera_residual_is_image_position():
    """Motoman 6x6x6, cameras only (3 folds): the held-out marker residual of both cameras is mostly a function of
    the image position (the source's principal point: docs/diagnose.md), not a per-marker bias."""
    from ppoe_core.analysis.diagnose import pixel_candidates
    from ppoe_core.cli.datasets import pixels_from_motoman

    d = DATASETS / "motoman_leica"
    robot = parse_urdf(d / "motoman_right.urdf")
    tree = KinematicTree(robot)
    obs = pixels_from_motoman(d / "leica_right_hand_6x6x6_dataset.mat", robot, d / "model.yaml")
    cams = [e for e in pixel_candidates(robot, obs) if e.name == "camera_extrinsics"]
    held = joint_heldout(tree, cams, None, obs, folds=3, rescale=0)
    for f, s in pixel_residual_structure(obs, held["pixel_residual"]).items():
        assert s["rms"] > 8.0, (f, s)
        assert s["explained_by"][0] == "image_position", (f, s)
        assert s["rms_after_image_position"] < 0.5 * s["rms"], (f, s)
