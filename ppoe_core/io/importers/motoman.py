"""Import the CTU Motoman Leica datasets (``.mat``) into contract bags.

Source data: ``ctu-vras/multirobot-calibration`` (no data license: internal test data,
see ``../shared/datasets/motoman_leica/README.md``).  Bags and model YAMLs written here
are derived from those data and must not be committed or shipped.

The files carry no time; pose ``k`` (0-based, in pose-ID order) is stamped at
``T0_S + k * STOP_PERIOD_S``.  Bag layout (docs/conventions.md section 3, static dataset):

==============================  ================================  =====================================
topic                           type                              content
==============================  ================================  =====================================
``/robot_description``          ``std_msgs/msg/String``           ``motoman_right.urdf``, once, first
``/dataset/stop``               ``std_msgs/msg/String``           JSON per pose: ``stop``, ``pose_id``,
                                                                  ``has_tracker``, ``observations``
                                                                  (``{"camera_1": n1, "camera_2": n2}``)
``/joint_states``               ``sensor_msgs/msg/JointState``    :data:`BURST_COUNT` messages at 50 Hz:
                                                                  ``joint_E, joint_S1 .. joint_T1``
``/ground_truth/point``         ``geometry_msgs/msg/PointStamped``  Leica reflector (link ``LR1``) in the
                                                                  tracker frame ``leica``; poses with NaN
                                                                  Leica rows get no message
``/camera/camera_info``         ``sensor_msgs/msg/CameraInfo``    both cameras at every pose, told apart
                                                                  by ``header.frame_id``:
                                                                  ``camera_1_optical_frame`` (``rightEye``),
                                                                  ``camera_2_optical_frame`` (``leftEye``)
``/tag_bearing/observations``   ``sensor_msgs/msg/PointCloud2``   one message per camera per pose (may
                                                                  have 0 points); header.frame_id = that
                                                                  camera's optical frame; fields ``id``
                                                                  (marker face 1..20), ``corner`` (0 =
                                                                  centre), ``u``, ``v`` (raw px), ``x``,
                                                                  ``y`` (undistorted, normalised)
==============================  ================================  =====================================

The CameraInfo image size is unknown in the source and written as 0 x 0.

Either arm: the arm-number column (3) of a file is 1 (right: joints ``joint_E, joint_S1 .. joint_T1`` from
columns 7-13, markers on ``EE1``, reflector ``LR1``, URDF ``motoman_right.urdf``) or 2 (left: ``joint_E,
joint_S2 .. joint_T2`` from columns 7 and 14-19, markers on ``EE2``, reflector ``LR2``, URDF
``motoman_right.urdf`` plus the left arm built from ``model.yaml``'s ``left_arm`` DH by
:func:`left_arm_urdf`); a file mixing arms is refused naming the row.

:func:`motoman_model_dict` builds the matching ppoe model YAML (markers as ``tags`` on
``EE1``, the Leica reflector as ``tracker`` on ``LR1``); ``import_motoman`` writes it next
to the bag.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ppoe_core import lie
from ppoe_core.errors import DatasetError
from ppoe_core.io.importers import MODEL_HEADER, STOP_TOPIC, check_outputs  # STOP_TOPIC re-exported

__all__ = [
    "MotomanCamera",
    "MotomanDataset",
    "load_motoman",
    "load_motoman_cameras",
    "load_marker_poses",
    "motoman_model_dict",
    "write_motoman_bag",
    "import_motoman",
    "JOINT_NAMES",
    "ARM_JOINTS",
    "left_arm_urdf",
    "CAMERA_FRAMES",
    "CAMERA_INFO_TOPIC",
    "TRACKER_FRAME",
    "OBSERVATION_TOPIC",
    "STOP_TOPIC",
    "T0_S",
    "STOP_PERIOD_S",
]

#: URDF joint names of the data columns 7..13 (1-based): E, S, L, U, R, B, T (right arm, arm number 1)
JOINT_NAMES = ["joint_E", "joint_S1", "joint_L1", "joint_U1", "joint_R1", "joint_B1", "joint_T1"]
#: the same for each arm number: the left arm (2) uses columns 7 and 14..19
ARM_JOINTS = {1: JOINT_NAMES, 2: ["joint_E", "joint_S2", "joint_L2", "joint_U2", "joint_R2", "joint_B2", "joint_T2"]}
#: data columns (0-based) of each arm's joint values, in ARM_JOINTS order
ARM_COLUMNS = {1: list(range(6, 13)), 2: [6, *range(13, 19)]}
#: camera number (column 4) -> optical frame in motoman_right.urdf
CAMERA_FRAMES = {1: "camera_1_optical_frame", 2: "camera_2_optical_frame"}
#: both cameras' CameraInfo go to this topic, told apart by ``header.frame_id``
CAMERA_INFO_TOPIC = "/camera/camera_info"
#: frame_id of /ground_truth/point (the Leica tracker frame; not in the URDF)
TRACKER_FRAME = "leica"
OBSERVATION_TOPIC = "/tag_bearing/observations"
#: stamp of the first pose [s] and spacing of poses [s] (the data carry no time)
T0_S = 1_600_000_000.0
STOP_PERIOD_S = 1.0
BURST_COUNT = 5
BURST_PERIOD_S = 0.02
MEASUREMENT_DELAY_S = 0.1
#: Leica reflector 1-sigma written into the model YAML's tracker entry [m] (the files give 0)
LEICA_SIGMA_M = 0.0002

#: 1-sigma of each camera mount [m, m, m, rad, rad, rad] in the generated model YAML: the README's
#: camera re-estimation moved the calibrated cameras by 20-26 mm and 0.6-0.7 deg
CAMERA_MOUNT_SIGMA = (0.015, 0.015, 0.015, 0.01, 0.01, 0.01)

_N_COLUMNS = 26


@dataclass(frozen=True)
class MotomanCamera:
    """Intrinsics of one camera (model.yaml ``cameras/camera_<n>``).

    Attributes
    ----------
    number : int
        1 (``rightEye``) or 2 (``leftEye``).
    frame : str
        Optical frame in the URDF.
    K : ndarray, shape (3, 3)
        Camera matrix [px].
    D : ndarray, shape (5,)
        plumb_bob distortion ``[k1, k2, p1, p2, k3]``.
    """

    number: int
    frame: str
    K: np.ndarray
    D: np.ndarray


@dataclass
class MotomanDataset:
    """A parsed Motoman ``.mat`` file.

    Attributes
    ----------
    path : Path
    pose_ids : ndarray, shape (P,)
        Pose IDs in increasing order.
    joints : ndarray, shape (P, 7)
        Joint values in ``ARM_JOINTS[arm]`` order [rad].
    leica : ndarray, shape (P, 3)
        Reflector position in the tracker frame [m]; NaN rows = not logged.
    obs_pose : ndarray, shape (M,)
        Index into ``pose_ids`` of each marker observation.
    obs_face, obs_camera : ndarray, shape (M,)
        Marker face (1..20) and camera number (1, 2).
    obs_uv : ndarray, shape (M, 2)
        Detected marker centre [px, raw/distorted].
    arm : int
        Arm number of the file (column 3): 1 = right, 2 = left.
    """

    path: Path
    pose_ids: np.ndarray
    joints: np.ndarray
    leica: np.ndarray
    obs_pose: np.ndarray
    obs_face: np.ndarray
    obs_camera: np.ndarray
    obs_uv: np.ndarray
    arm: int = 1

    @property
    def has_tracker(self) -> np.ndarray:
        """Boolean mask, shape (P,): the pose has a Leica point."""
        return np.all(np.isfinite(self.leica), axis=1)


def load_motoman(path: str | Path) -> MotomanDataset:
    """Parse a Motoman Leica ``.mat`` file (variable ``dataset``, N x 26).

    Raises
    ------
    DatasetError
        Unreadable file, missing variable, wrong shape, joint values that differ between
        the rows of one pose, NaN joints or pixels, unknown camera or arm numbers. The
        message names the file and the row (1-based).
    """
    import scipy.io

    path = Path(path)
    try:
        mat = scipy.io.loadmat(str(path))
    except (OSError, ValueError, NotImplementedError) as exc:
        raise DatasetError(f"{path}: cannot read .mat file: {exc}") from None
    if "dataset" not in mat:
        raise DatasetError(f"{path}: no variable 'dataset' (has {sorted(k for k in mat if not k.startswith('__'))})")
    data = np.asarray(mat["dataset"], dtype=float)
    if data.ndim != 2 or data.shape[1] != _N_COLUMNS or data.shape[0] == 0:
        raise DatasetError(f"{path}: 'dataset' must be N x {_N_COLUMNS}, got {data.shape}")
    arm = int(data[0, 2]) if data[0, 2] in (1, 2) else 0
    if arm == 0 or np.any(data[:, 2] != arm):
        row = int(np.flatnonzero(data[:, 2] != (arm or data[0, 2]))[0]) + 1 if arm else 1
        raise DatasetError(f"{path}: row {row}: arm number {data[row - 1, 2]:g}; a file holds one arm, 1 (right) "
                           f"or 2 (left){f', and row 1 says {arm}' if arm else ''}")
    jcols = ARM_COLUMNS[arm]
    bad = ~np.all(np.isfinite(data[:, [0, 1, 2, 3, 4, 5, *jcols]]), axis=1)
    if np.any(bad):
        row = int(np.flatnonzero(bad)[0]) + 1
        raise DatasetError(f"{path}: row {row}: NaN/inf in the ids, pixels or arm {arm}'s joint columns")
    cams = data[:, 3]
    if not np.all(np.isin(cams, (1, 2))):
        row = int(np.flatnonzero(~np.isin(cams, (1, 2)))[0]) + 1
        raise DatasetError(f"{path}: row {row}: camera number {cams[row - 1]:g} is not 1 or 2")
    faces = data[:, 1]
    if not np.all((faces >= 1) & (faces <= 20) & (faces == np.round(faces))):
        row = int(np.flatnonzero(~((faces >= 1) & (faces <= 20)))[0]) + 1
        raise DatasetError(f"{path}: row {row}: marker face {faces[row - 1]:g} not in 1..20")
    pose_ids, first, inverse = np.unique(data[:, 0], return_index=True, return_inverse=True)
    per_pose = data[first]
    # the joint and Leica values repeat on every row of a pose: check it
    cols = jcols + [19, 20, 21]
    diff = np.abs(np.nan_to_num(data[:, cols] - per_pose[inverse][:, cols], nan=0.0))
    if np.any(diff > 1e-12):
        row = int(np.flatnonzero(np.any(diff > 1e-12, axis=1))[0]) + 1
        raise DatasetError(
            f"{path}: row {row}: joint/Leica values differ from the first row of pose {data[row - 1, 0]:g}"
        )
    return MotomanDataset(
        path=path,
        pose_ids=pose_ids.astype(int),
        joints=per_pose[:, jcols].copy(),
        leica=per_pose[:, 19:22].copy(),
        obs_pose=inverse.astype(int),
        obs_face=faces.astype(int),
        obs_camera=cams.astype(int),
        obs_uv=data[:, 4:6].copy(),
        arm=arm,
    )


def _read_model_yaml(model_yaml: str | Path) -> dict[str, Any]:
    model_yaml = Path(model_yaml)
    try:
        doc = yaml.safe_load(model_yaml.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise DatasetError(f"{model_yaml}: cannot read the Motoman model YAML: {exc}") from None
    if not isinstance(doc, dict) or "cameras" not in doc or "markers" not in doc:
        raise DatasetError(f"{model_yaml}: not the dataset's model.yaml (needs 'cameras' and 'markers')")
    return doc


def load_motoman_cameras(model_yaml: str | Path) -> dict[int, MotomanCamera]:
    """Camera intrinsics from the dataset's ``model.yaml``: camera number -> :class:`MotomanCamera`."""
    doc = _read_model_yaml(model_yaml)
    out = {}
    for n, frame in CAMERA_FRAMES.items():
        try:
            c = doc["cameras"][f"camera_{n}"]
            i = c["intrinsics"]
            K = np.array([[i["fx"], i.get("skew", 0.0), i["cx"]], [0.0, i["fy"], i["cy"]], [0.0, 0.0, 1.0]], float)
            dist = c["distortion"]
            if any(abs(float(dist.get(k, 0.0))) > 0 for k in ("k4", "k5", "k6")):
                raise DatasetError(f"{model_yaml}: cameras/camera_{n}: k4..k6 != 0 is not plumb_bob")
            D = np.array([dist["k1"], dist["k2"], dist["p1"], dist["p2"], dist["k3"]], float)
        except (KeyError, TypeError) as exc:
            raise DatasetError(f"{model_yaml}: cameras/camera_{n}: missing or bad entry {exc}") from None
        out[n] = MotomanCamera(number=n, frame=frame, K=K, D=D)
    return out


def load_marker_poses(model_yaml: str | Path) -> dict[int, np.ndarray]:
    """Marker poses on ``EE1`` from the dataset's ``model.yaml``.

    Returns
    -------
    dict
        face (1..20) -> ``T_EE1_marker``, shape (4, 4) (translation + rotation vector,
        README "six_vector").
    """
    doc = _read_model_yaml(model_yaml)
    out = {}
    try:
        for face, six in doc["markers"]["poses"].items():
            six = np.asarray(six, float)
            if six.shape != (6,):
                raise DatasetError(f"{model_yaml}: markers/poses/{face}: expected 6 numbers")
            out[int(face)] = lie.from_rt(lie.so3_exp(six[3:]), six[:3])
    except (KeyError, TypeError, ValueError) as exc:
        raise DatasetError(f"{model_yaml}: markers/poses: bad entry {exc}") from None
    return out


def undistort(uv: np.ndarray, camera: MotomanCamera) -> np.ndarray:
    """Raw pixels ``(M, 2)`` -> undistorted normalised coordinates ``(M, 2)`` (x = X/Z, y = Y/Z),
    with the tag bearing node's :func:`ppoe_core.estimation.camera.undistort_pixels`."""
    from ppoe_core.estimation.camera import undistort_pixels

    return undistort_pixels(np.asarray(uv, float).reshape(-1, 2), camera.K, camera.D)


def _dh(row: dict[str, Any]) -> np.ndarray:
    """One standard DH row at q = 0: ``Rz(offset) Tz(d) Tx(a) Rx(alpha)`` (model.yaml conventions)."""
    th, al = float(row.get("offset", 0.0)), float(row["alpha"])
    R = lie.matrix_from_rpy([al, 0.0, th])
    return lie.from_rt(R, np.array([float(row["a"]) * np.cos(th), float(row["a"]) * np.sin(th), float(row["d"])]))


def left_arm_urdf(right_urdf_xml: str, model_yaml: str | Path) -> str:
    """``motoman_right.urdf`` with the left arm of ``model.yaml`` added (arm number 2): ``torso_to_TT2`` (its E row
    at E = 0; ``joint_E`` turns the torso), revolute ``joint_S2 .. joint_T2`` each followed by a fixed ``*_dh``
    joint (the right arm's pattern), ``EE2``, ``LR2`` and the marker links ``MK201 .. MK220`` on ``EE2``."""
    import xml.etree.ElementTree as ET

    doc = _read_model_yaml(model_yaml)
    try:
        rows, tools = doc["left_arm"]["dh"], doc["left_arm"]["tools"]
        markers = load_marker_poses(model_yaml)
        root = ET.fromstring(right_urdf_xml)
    except (KeyError, TypeError, ET.ParseError) as exc:
        raise DatasetError(f"{model_yaml}: cannot build the left arm (left_arm dh/tools, markers): {exc}") from None

    def add(name: str, jtype: str, parent: str, child: str, T: np.ndarray) -> None:
        ET.SubElement(root, "link", name=child)
        j = ET.SubElement(root, "joint", name=name, type=jtype)
        ET.SubElement(j, "parent", link=parent)
        ET.SubElement(j, "child", link=child)
        ET.SubElement(j, "origin", xyz=" ".join(repr(float(v)) for v in T[:3, 3]),
                      rpy=" ".join(repr(float(v)) for v in lie.rpy_from_matrix(T[:3, :3])))
        if jtype == "revolute":
            ET.SubElement(j, "axis", xyz="0 0 1")
            ET.SubElement(j, "limit", lower="-3.2", upper="3.2", effort="100", velocity="1")

    root.append(ET.Comment(" left arm (arm number 2) added from model.yaml by ppoe import motoman "))
    add("torso_to_" + rows[0]["frame"], "fixed", "torso", rows[0]["frame"], _dh(rows[0]))
    parent = rows[0]["frame"]
    for row in rows[1:]:
        frame = row["frame"]
        add(f"joint_{frame}", "revolute", parent, f"{frame}_rot", np.eye(4))
        add(f"{frame}_dh", "fixed", f"{frame}_rot", frame, _dh(row))
        parent = frame
    for tool, spec in tools.items():
        add(f"{spec['parent']}_to_{tool}", "fixed", spec["parent"], tool, _dh(spec["dh"]))
    for face, T in sorted(markers.items()):
        add(f"EE2_to_MK2{face:02d}", "fixed", "EE2", f"MK2{face:02d}", T)
    return ET.tostring(root, encoding="unicode") + "\n"


def motoman_model_dict(model_yaml: str | Path, arm: int = 1) -> dict[str, Any]:
    """A ppoe model YAML (as a dict) for ``motoman_right.urdf`` (arm 1) or :func:`left_arm_urdf` (arm 2) built
    from the dataset's model.yaml.

    Markers become ``tags`` on ``EE1`` (id = face, centre only: ``size`` is not known
    from the source and only matters for corners, which these data do not have), the
    Leica reflector the ``tracker`` on ``LR1``, camera 1 the default camera. The
    uncertainty numbers are our assumptions, documented in the YAML comments written
    by :func:`import_motoman`: 0.5 mrad joint noise, :data:`CAMERA_MOUNT_SIGMA` on each
    camera mount (README: re-estimating the camera poses moves them by 20-26 mm and
    0.6-0.7 deg, i.e. the calibrated chains are that far off), 2 px marker-centre noise.
    """
    markers = load_marker_poses(model_yaml)
    items = []
    for face, T in sorted(markers.items()):
        rpy = lie.rpy_from_matrix(T[:3, :3])
        items.append(
            {
                "id": face,
                "link": f"EE{arm}",
                "size": 0.03,
                "xyz": [float(v) for v in T[:3, 3]],
                "rpy": [float(v) for v in rpy],
            }
        )
    return {
        "joint_noise": {j: 0.0005 for j in ARM_JOINTS[arm]},
        "perturbations": {
            "torso_to_rightHead": {"sigma": list(CAMERA_MOUNT_SIGMA)},
            "torso_to_leftHead": {"sigma": list(CAMERA_MOUNT_SIGMA)},
        },
        "frames": {"base": "base", "tool": f"EE{arm}"},
        "camera": {"frame": CAMERA_FRAMES[1], "pixel_sigma": 2.0},
        "tags": {"family": "aruco_centre", "items": items},
        "tracker": {"link": f"LR{arm}", "xyz": [0.0, 0.0, 0.0], "sigma": LEICA_SIGMA_M},
        "naive": {"sigma": [0.002, 0.002, 0.002, 0.0035, 0.0035, 0.0035]},
    }


def write_motoman_bag(
    dataset: MotomanDataset,
    cameras: dict[int, MotomanCamera],
    urdf_xml: str,
    out: str | Path,
    overwrite: bool = False,
) -> dict[str, int]:
    """Write a parsed dataset as a contract bag (layout in the module docstring).

    Returns
    -------
    dict
        Messages written per topic, plus ``"points:camera_1"`` / ``"points:camera_2"``:
        marker observations written per camera.
    """
    from ppoe_core.io.bagio import BagWriter, typestore

    String = typestore().types["std_msgs/msg/String"]
    xy = np.zeros_like(dataset.obs_uv)
    for n, cam in cameras.items():
        sel = dataset.obs_camera == n
        xy[sel] = undistort(dataset.obs_uv[sel], cam)
    has_tracker = dataset.has_tracker
    points_per_camera = {n: 0 for n in cameras}
    with BagWriter(out, overwrite=overwrite) as w:
        w.write_robot_description(urdf_xml, stamp=T0_S - 1.0)
        for k, pose_id in enumerate(dataset.pose_ids):
            t = T0_S + k * STOP_PERIOD_S
            rows = np.flatnonzero(dataset.obs_pose == k)
            n_obs = {f"camera_{n}": int(np.sum(dataset.obs_camera[rows] == n)) for n in cameras}
            info = {"stop": k, "pose_id": int(pose_id), "has_tracker": bool(has_tracker[k]), "observations": n_obs}
            w.write_message(STOP_TOPIC, String(data=json.dumps(info)), t)
            for b in range(BURST_COUNT):
                w.write_joint_state(t + b * BURST_PERIOD_S, ARM_JOINTS[dataset.arm], dataset.joints[k])
            t_meas = t + MEASUREMENT_DELAY_S
            if has_tracker[k]:
                w.write_ground_truth_point(t_meas, TRACKER_FRAME, dataset.leica[k])
            for n, cam in sorted(cameras.items()):
                w.write_camera_info(t_meas, cam.frame, 0, 0, cam.K, cam.D, topic=CAMERA_INFO_TOPIC)
                sel = rows[dataset.obs_camera[rows] == n]
                w.write_tag_observations(
                    t_meas, cam.frame, dataset.obs_face[sel], np.zeros(len(sel), int), dataset.obs_uv[sel], xy[sel]
                )
                points_per_camera[n] += len(sel)
        counts: dict[str, int] = dict(w.counts)
    for n, c in points_per_camera.items():
        counts[f"points:camera_{n}"] = c
    return counts


def import_motoman(
    path: str | Path,
    model_yaml: str | Path,
    out: str | Path,
    urdf: str | Path | None = None,
    ppoe_model_out: str | Path | None = None,
    overwrite: bool = False,
) -> dict[str, Any]:
    """``ppoe import motoman``: parse ``path``, write the bag ``out`` and a ppoe model YAML.

    Parameters
    ----------
    path : str or Path
        The ``.mat`` file.
    model_yaml : str or Path
        The dataset's ``model.yaml`` (intrinsics, marker poses).
    out : str or Path
        Output bag directory.
    urdf : str or Path, optional
        Default ``motoman_right.urdf`` next to ``model_yaml``.
    ppoe_model_out : str or Path, optional
        Where to write the ppoe model YAML; default ``<out>.model.yaml`` next to the bag.
    overwrite : bool
        Replace an existing bag at ``out``.

    Returns
    -------
    dict
        ``counts`` (messages per topic) and ``model`` (path of the written model YAML).
    """
    path, model_yaml, out = Path(path), Path(model_yaml), Path(out)
    model_out = Path(ppoe_model_out) if ppoe_model_out is not None else out.with_name(out.name + ".model.yaml")
    check_outputs(out, model_out, overwrite)  # before the work: a path we may not replace is refused now
    dataset = load_motoman(path)
    cameras = load_motoman_cameras(model_yaml)
    urdf_path = Path(urdf) if urdf is not None else model_yaml.with_name("motoman_right.urdf")
    try:
        urdf_xml = urdf_path.read_text()
    except OSError as exc:
        raise DatasetError(f"{urdf_path}: cannot read the URDF (use --urdf): {exc}") from None
    if dataset.arm == 2:
        urdf_xml = left_arm_urdf(urdf_xml, model_yaml)
    counts = write_motoman_bag(dataset, cameras, urdf_xml, out, overwrite=overwrite)
    header = (
        f"{MODEL_HEADER}motoman_right.urdf, generated by `ppoe import motoman` from\n"
        f"# {model_yaml} (CTU multirobot-calibration data: internal test data, do not commit).\n"
        "# joint_noise: 1-sigma joint angle noise [rad], our assumption (0.5 mrad).\n"
        "# perturbations torso_to_*Head: camera mount 1-sigma [m, rad], from the README's camera re-estimation.\n"
        "# tags: marker faces on EE1 (centre pose from model.yaml markers/poses; size unknown, centre only).\n"
        "# camera.pixel_sigma: marker-centre noise [px], our assumption.\n"
        "# tracker: Leica reflector on LR1, 1-sigma [m], our assumption.\n"
        "# naive: diagonal tool covariance [m, rad] for the naive baseline, our assumption.\n"
    )
    if dataset.arm == 2:
        header = header.replace("motoman_right.urdf", "motoman_right.urdf + the left arm").replace("EE1", "EE2")
        header = header.replace("LR1", "LR2")
    model_out.write_text(header + yaml.safe_dump(motoman_model_dict(model_yaml, dataset.arm), sort_keys=False))
    return {"counts": counts, "model": str(model_out), "arm": dataset.arm}
