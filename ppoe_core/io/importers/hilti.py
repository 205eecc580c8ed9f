"""Import the Hilti construction-robot stationing datasets into contract bags.

Source data: ``Hilti-Research/construction_robot_stationing_datasets`` (CC BY-NC-SA 3.0,
see ``../shared/datasets/hilti_stationing/README.md``).  The data are not ours to
redistribute: bags written here must not be committed or shipped.

Bag layout (docs/conventions.md section 3, static dataset; every stop is one waypoint of the file):

=====================  ==============================  ===========================================
topic                  type                            content
=====================  ==============================  ===========================================
``/robot_description`` ``std_msgs/msg/String``         the dataset URDF (``trailblazer.urdf``), once, first
``/dataset/stop``      ``std_msgs/msg/String``         one JSON object per stop (:data:`STOP_TOPIC`), stamped at
                                                       the stop's ``time``: ``stop`` (running index),
                                                       ``station`` (``"h<height>_s<space>"``), ``column_height`` [m],
                                                       ``solution_space``, ``role`` (``"stationing"`` or
                                                       ``"evaluation"``), ``waypoint_id``, ``upside_down``,
                                                       ``doosan_cmd`` [m], ``point_sets`` (stationing sets this
                                                       waypoint belongs to: ``"cross"``, ``"square"``)
``/joint_states``      ``sensor_msgs/msg/JointState``  burst of :data:`BURST_COUNT` identical messages at 50 Hz
                                                       starting at ``time``; the 7 recorded joints only (the
                                                       column mimic joints are resolved by the model)
``/ground_truth/point``  ``geometry_msgs/msg/PointStamped``  prism centre in the total-station frame
                                                       (``header.frame_id = total_station``), after the burst
``/imu/base``          ``sensor_msgs/msg/Imu``         ``tilt_sensor_base_accel`` (frame ``tilt_sensor_base``)
``/imu/column_tip``    ``sensor_msgs/msg/Imu``         ``tilt_sensor_column_accel`` (frame ``tilt_sensor_column_tip``)
=====================  ==============================  ===========================================

The IMU messages carry only ``linear_acceleration`` (m/s^2, specific force) with its
covariance from the datasheet std (4.361e-4 m/s^2); orientation is marked unknown
(``orientation_covariance[0] = -1``) and the angular velocity is zero (the robot is at rest).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ppoe_core.errors import DatasetError
from ppoe_core.io.importers import MODEL_HEADER, STOP_TOPIC, check_outputs  # STOP_TOPIC re-exported

__all__ = [
    "HiltiStop",
    "HiltiDataset",
    "load_hilti",
    "write_hilti_bag",
    "import_hilti",
    "hilti_model_dict",
    "STOP_TOPIC",
    "TRACKER_FRAME",
    "IMU_TOPICS",
    "BURST_COUNT",
    "BURST_PERIOD_S",
    "CROSS_POINTS",
    "SQUARE_POINTS",
    "TOTAL_STATION_SIGMA_M",
    "ACCEL_SIGMA",
]

#: frame_id of ``/ground_truth/point`` (the total station's own frame, not in the URDF)
TRACKER_FRAME = "total_station"
#: IMU topic -> URDF frame of the accelerometer
IMU_TOPICS = {"/imu/base": "tilt_sensor_base", "/imu/column_tip": "tilt_sensor_column_tip"}
#: joint-state messages written per stop, and their spacing [s] (50 Hz)
BURST_COUNT = 5
BURST_PERIOD_S = 0.02
#: measurements are stamped this long after the stop's ``time`` [s] (after the burst)
MEASUREMENT_DELAY_S = 0.1
#: stationing point sets as ``doosan_cmd`` xy [m] (README "Stationing point sets")
CROSS_POINTS = ((0.25, 0.15), (0.25, -0.15), (0.4, 0.0), (0.1, 0.0))
SQUARE_POINTS = ((0.1, 0.15), (0.1, -0.15), (0.4, 0.15), (0.4, -0.15))
#: total-station position 1-sigma [m] and accelerometer 1-sigma [m/s^2] (README datasheet table)
TOTAL_STATION_SIGMA_M = 0.75e-3
ACCEL_SIGMA = 4.3610059e-4

_EXPECTED_JOINTS = [
    "column_prismatic_joint",
    "dsr_joint1",
    "dsr_joint2",
    "dsr_joint3",
    "dsr_joint4",
    "dsr_joint5",
    "dsr_joint6",
]
_ROLES = {"stationing_measurements": "stationing", "evaluation_measurements": "evaluation"}


@dataclass(frozen=True)
class HiltiStop:
    """One static waypoint of a Hilti dataset file.

    Attributes
    ----------
    waypoint_id : int
        ``id`` field of the waypoint (unique only within its station and role).
    time : float
        Unix time [s].
    column_height : float
        Nominal column height of the station [m] (the ``column_heights`` key).
    solution_space : int
        Arm solution space of the station (0, 7, or 4 = upside down).
    role : str
        ``"stationing"`` or ``"evaluation"``.
    upside_down : bool
    doosan_cmd : ndarray, shape (3,)
        Cartesian arm command [m].
    joints : ndarray, shape (7,)
        Joint values in :attr:`HiltiDataset.joint_names` order [m, rad].
    prism_position : ndarray, shape (3,)
        Prism centre in the total-station frame [m].
    accel_base, accel_column_tip : ndarray, shape (3,)
        Specific force in ``tilt_sensor_base`` / ``tilt_sensor_column_tip`` [m/s^2].
    """

    waypoint_id: int
    time: float
    column_height: float
    solution_space: int
    role: str
    upside_down: bool
    doosan_cmd: np.ndarray
    joints: np.ndarray
    prism_position: np.ndarray
    accel_base: np.ndarray
    accel_column_tip: np.ndarray

    @property
    def station(self) -> str:
        """Station key ``"h<height>_s<space>"``, e.g. ``"h1.98_s0"``."""
        return f"h{self.column_height:g}_s{self.solution_space}"

    @property
    def point_sets(self) -> list[str]:
        """Stationing point sets (``"cross"``, ``"square"``) this stop belongs to.

        Only stationing stops belong to a set; membership is by ``doosan_cmd`` xy
        (within 1 mm) with z = 0.48 m, as in the README.
        """
        if self.role != "stationing":
            return []
        xy = self.doosan_cmd[:2]
        out = []
        for name, pts in (("cross", CROSS_POINTS), ("square", SQUARE_POINTS)):
            if any(np.hypot(xy[0] - p[0], xy[1] - p[1]) < 1e-3 for p in pts):
                out.append(name)
        return out

    def info(self, index: int) -> dict[str, Any]:
        """The JSON object written on :data:`STOP_TOPIC` for this stop."""
        return {
            "stop": index,
            "station": self.station,
            "column_height": self.column_height,
            "solution_space": self.solution_space,
            "role": self.role,
            "waypoint_id": self.waypoint_id,
            "upside_down": self.upside_down,
            "doosan_cmd": [float(v) for v in self.doosan_cmd],
            "point_sets": self.point_sets,
            "time": self.time,
        }


@dataclass
class HiltiDataset:
    """A parsed Hilti dataset file: stops sorted by time."""

    path: Path
    joint_names: list[str]
    stops: list[HiltiStop] = field(default_factory=list)
    incomplete: list[str] = field(default_factory=list)
    """Stations lacking a role list (``null`` or missing), one line each; their other stops are kept."""
    truncated: list[str] = field(default_factory=list)
    """Signs that the file was cut short (:func:`truncation_notes`), one line each."""

    @property
    def stations(self) -> list[str]:
        """Station keys in order of first appearance."""
        return list(dict.fromkeys(s.station for s in self.stops))


def _vector(value: Any, n: int, where: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise DatasetError(f"{where}: expected {n} numbers, got {value!r}") from None
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise DatasetError(f"{where}: expected {n} finite numbers, got {value!r}")
    return arr


def _waypoint(m: Any, height: Any, space: Any, role: str, where: str) -> HiltiStop:
    """One waypoint of a station (``where`` names file, station and index in errors)."""
    if not isinstance(m, dict):
        raise DatasetError(f"{where}: not a mapping")
    try:
        t = float(m["time"])
        stop = HiltiStop(
            waypoint_id=int(m["id"]),
            time=t,
            column_height=float(height),
            solution_space=int(space),
            role=role,
            upside_down=bool(m.get("upside_down", False)),
            doosan_cmd=_vector(m["doosan_cmd"], 3, where + "/doosan_cmd"),
            joints=_vector(m["joint_states"], 7, where + "/joint_states"),
            prism_position=_vector(m["prism_position"], 3, where + "/prism_position"),
            accel_base=_vector(m["tilt_sensor_base_accel"], 3, where + "/tilt_sensor_base_accel"),
            accel_column_tip=_vector(m["tilt_sensor_column_accel"], 3, where + "/tilt_sensor_column_accel"),
        )
    except KeyError as exc:
        raise DatasetError(f"{where}: missing key {exc.args[0]!r}") from None
    except (TypeError, ValueError) as exc:
        raise DatasetError(f"{where}: bad value: {exc}") from None
    if not math.isfinite(t):
        raise DatasetError(f"{where}/time: not finite")
    return stop


def load_hilti(path: str | Path, allow_incomplete: bool = False) -> HiltiDataset:
    """Parse a Hilti dataset YAML (``flat.yaml`` etc.).

    Parameters
    ----------
    path : str or Path
        The dataset file.
    allow_incomplete : bool
        Accept stations whose ``stationing_measurements`` or ``evaluation_measurements`` is
        ``null`` or missing (listed in :attr:`HiltiDataset.incomplete`); by default such a file is
        refused, naming every such station.  An empty list ``[]`` is explicit and accepted.

    Returns
    -------
    HiltiDataset
        All waypoints of all stations (stationing and evaluation), sorted by ``time``.

    Raises
    ------
    DatasetError
        Unreadable file, missing key or malformed value; the message names the file,
        the station and the waypoint.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read Hilti dataset: {exc}") from None
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    try:
        doc = yaml.load(text, Loader=loader)
    except yaml.YAMLError as exc:
        raise DatasetError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(doc, dict) or "joint_names" not in doc or "column_heights" not in doc:
        raise DatasetError(f"{path}: not a Hilti stationing dataset (needs keys joint_names, column_heights)")
    joint_names = [str(j) for j in doc["joint_names"]]
    if joint_names != _EXPECTED_JOINTS:
        raise DatasetError(f"{path}: joint_names {joint_names} differ from the expected {_EXPECTED_JOINTS}")
    stops: list[HiltiStop] = []
    incomplete: list[str] = []
    layout: dict[str, dict[str, list[tuple[str, int]]]] = {}
    heights = doc["column_heights"]
    if not isinstance(heights, dict):
        raise DatasetError(f"{path}: column_heights must be a mapping")
    for height, hval in heights.items():
        spaces = (hval or {}).get("solution_spaces") if isinstance(hval, dict) else None
        if not isinstance(spaces, dict):
            raise DatasetError(f"{path}: column_heights/{height}: missing solution_spaces mapping")
        for space, sval in spaces.items():
            if not isinstance(sval, dict):
                raise DatasetError(f"{path}: column_heights/{height}/solution_spaces/{space}: not a mapping")
            _station_stops(path, height, space, sval, stops, incomplete)
            layout.setdefault(f"{height}", {})[f"{space}"] = [(_ROLES[k], len(v or [])) for k, v in sval.items()
                                                               if k in _ROLES]
    stops.sort(key=lambda s: s.time)
    times = np.array([s.time for s in stops])
    if len(times) > 1 and np.min(np.diff(times)) <= (BURST_COUNT - 1) * BURST_PERIOD_S + MEASUREMENT_DELAY_S:
        i = int(np.argmin(np.diff(times)))
        raise DatasetError(
            f"{path}: waypoints {stops[i].station}/{stops[i].waypoint_id} and "
            f"{stops[i + 1].station}/{stops[i + 1].waypoint_id} are too close in time to be separate stops"
        )
    if incomplete and not allow_incomplete:
        raise DatasetError(
            f"{path}: {len(incomplete)} station role list(s) missing or null, so those stations cannot be "
            f"scored by the stationing protocol: " + "; ".join(incomplete)
            + " (pass --allow-incomplete to import the other stops)")
    truncated = truncation_notes(layout)
    if truncated and not allow_incomplete:
        raise DatasetError(f"{path}: the file looks cut short ({'; '.join(truncated)}); it holds {len(stops)} "
                           f"stops in {sum(map(len, layout.values()))} stations (the format declares no total); "
                           "pass --allow-incomplete to import them anyway")
    return HiltiDataset(path=path, joint_names=joint_names, stops=stops, incomplete=incomplete, truncated=truncated)


def truncation_notes(layout: dict[str, dict[str, list[tuple[str, int]]]]) -> list[str]:
    """Signs that a file was cut short, from its layout (column height -> solution space -> [(role, stop count)],
    all in file order).  The format declares no stop count, but every complete file repeats one pattern of
    solution spaces per column height: the last height lacking a space that every other height has, or the last
    list of the file (its last station's last role) holding fewer stops than that list does at any other height,
    is what a cut leaves."""
    heights = list(layout)
    if len(heights) < 2:
        return []
    last, others = heights[-1], heights[:-1]
    notes = []
    common = [sp for sp in layout[others[0]] if all(sp in layout[h] for h in others)]
    missing = [sp for sp in common if sp not in layout[last]]
    if missing:
        notes.append(f"column height {last}, the last in the file, lacks solution space(s) {', '.join(missing)} "
                     "that every other height has")
    space = list(layout[last])[-1]
    if not layout[last][space]:
        return notes
    role, count = layout[last][space][-1]
    ref = [n for h in others for r, n in layout[h].get(space, []) if r == role]
    if ref and count < min(ref):
        notes.append(f"its last station h{last}_s{space} has {count} {role} stops where solution space {space} "
                     f"has {min(ref)}-{max(ref)} at the other heights")
    return notes


def _station_stops(path: Path, height: Any, space: Any, sval: dict, stops: list[HiltiStop],
                   incomplete: list[str]) -> None:
    """Append one station's waypoints to ``stops``; a null or missing role list to ``incomplete``."""
    for key, role in _ROLES.items():
        entries = sval.get(key)
        if entries is None:  # an empty list is explicit (space 4 has no stationing points)
            incomplete.append(_incomplete_line(sval, key, height, space))
            continue
        if not isinstance(entries, list):
            raise DatasetError(f"{path}: column_heights/{height}/solution_spaces/{space}/{key}: not a list")
        for k, m in enumerate(entries):
            where = f"{path}: column_heights/{height}/solution_spaces/{space}/{key}[{k}]"
            stops.append(_waypoint(m, height, space, role, where))


def _incomplete_line(sval: dict, key: str, height: Any, space: Any) -> str:
    """One line naming a station's missing role list and what it leaves unusable."""
    state = "missing" if key not in sval else "null"
    other = [k for k in _ROLES if k != key][0]
    n_other = len(sval.get(other) or [])
    return (f"column_heights/{height}/solution_spaces/{space}/{key} is {state} "
            f"(the station's {n_other} {other.split('_')[0]} stops are kept)")


def _string_msg(text: str) -> Any:
    from ppoe_core.io.bagio import typestore

    return typestore().types["std_msgs/msg/String"](data=text)


def write_hilti_bag(
    dataset: HiltiDataset, urdf_xml: str, out: str | Path, overwrite: bool = False
) -> dict[str, int]:
    """Write a parsed dataset as a contract bag (layout in the module docstring).

    Parameters
    ----------
    dataset : HiltiDataset
    urdf_xml : str
        Text of the robot's URDF, written once on ``/robot_description``.
    out : str or Path
        Bag directory to create.
    overwrite : bool
        Replace an existing bag directory at ``out`` (otherwise BagError).

    Returns
    -------
    dict
        Messages written per topic.
    """
    from ppoe_core.io.bagio import BagWriter

    with BagWriter(out, overwrite=overwrite) as w:
        t0 = dataset.stops[0].time if dataset.stops else 0.0
        w.write_robot_description(urdf_xml, stamp=t0 - 1.0)
        for i, stop in enumerate(dataset.stops):
            w.write_message(STOP_TOPIC, _string_msg(json.dumps(stop.info(i))), stop.time)
            for k in range(BURST_COUNT):
                w.write_joint_state(stop.time + k * BURST_PERIOD_S, dataset.joint_names, stop.joints)
            t_meas = stop.time + MEASUREMENT_DELAY_S
            w.write_ground_truth_point(t_meas, TRACKER_FRAME, stop.prism_position)
            for (topic, frame), acc in zip(IMU_TOPICS.items(), (stop.accel_base, stop.accel_column_tip)):
                w.write_imu(topic[len("/imu/"):], t_meas, frame, acc, accel_sigma=ACCEL_SIGMA)
        counts = dict(w.counts)
    return counts


def hilti_model_dict() -> dict[str, Any]:
    """A ppoe model YAML (as a dict) for ``trailblazer.urdf``.

    State ``T_base_link_tool_link``; the prism (link ``prism``) is the ``tracker``, the two
    accelerometers are ``imus``.  The sigmas of the sensors are the README's datasheet
    values; the joint noise (0.5 mrad on the arm joints, 0.5 mm on the column) is our
    assumption, so that FK has a covariance to compute NEES with.
    """
    joints = {"column_prismatic_joint": 0.0005}
    joints.update({f"dsr_joint{i}": 0.0005 for i in range(1, 7)})
    return {
        "joint_noise": joints,
        "frames": {"base": "base_link", "tool": "tool_link"},
        "tracker": {"link": "prism", "xyz": [0.0, 0.0, 0.0], "sigma": TOTAL_STATION_SIGMA_M},
        "imus": {
            name[len("/imu/"):]: {"link": frame, "sigma": ACCEL_SIGMA} for name, frame in IMU_TOPICS.items()
        },
    }


def import_hilti(
    path: str | Path,
    out: str | Path,
    urdf: str | Path | None = None,
    overwrite: bool = False,
    ppoe_model_out: str | Path | None = None,
    allow_incomplete: bool = False,
) -> dict[str, Any]:
    """``ppoe import hilti``: parse ``path`` and write the bag ``out``.

    Parameters
    ----------
    path : str or Path
        Dataset YAML.
    out : str or Path
        Output bag directory.
    urdf : str or Path, optional
        Robot URDF; default ``trailblazer.urdf`` next to ``path``.
    overwrite : bool
        Replace an existing bag at ``out``.
    ppoe_model_out : str or Path, optional
        Where to write the ppoe model YAML (:func:`hilti_model_dict`); default
        ``<out>.model.yaml`` next to the bag.
    allow_incomplete : bool
        See :func:`load_hilti`.

    Returns
    -------
    dict
        ``counts`` (messages per topic), ``model`` (path of the written model YAML),
        ``incomplete`` (stations with a missing role list, one line each), ``truncated`` (signs of a file cut
        short, accepted with ``allow_incomplete``), ``stops`` and ``stations`` (how many were imported).
    """
    path, out = Path(path), Path(out)
    model_out = Path(ppoe_model_out) if ppoe_model_out is not None else out.with_name(out.name + ".model.yaml")
    check_outputs(out, model_out, overwrite)  # before the work: a path we may not replace is refused now
    dataset = load_hilti(path, allow_incomplete=allow_incomplete)
    urdf_path = Path(urdf) if urdf is not None else path.with_name("trailblazer.urdf")
    try:
        urdf_xml = urdf_path.read_text()
    except OSError as exc:
        raise DatasetError(f"{urdf_path}: cannot read the URDF for {path} (use --urdf): {exc}") from None
    if not dataset.stops:
        raise DatasetError(f"{path}: no waypoints")
    counts = write_hilti_bag(dataset, urdf_xml, out, overwrite=overwrite)
    header = (
        f"{MODEL_HEADER}trailblazer.urdf, generated by `ppoe import hilti` (Hilti data, CC BY-NC-SA 3.0:\n"
        "# do not commit). joint_noise: 1-sigma joint noise [rad, m] (our assumption);\n"
        "# tracker: prism on link prism, total-station 1-sigma [m]; imus: accelerometers, 1-sigma [m/s^2].\n"
    )
    model_out.write_text(header + yaml.safe_dump(hilti_model_dict(), sort_keys=False))
    return {"counts": counts, "model": str(model_out), "incomplete": list(dataset.incomplete),
            "truncated": list(dataset.truncated), "stops": len(dataset.stops), "stations": len(dataset.stations)}
