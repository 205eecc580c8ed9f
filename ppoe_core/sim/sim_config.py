"""What a simulation scenario asks for: the stops/trajectory and the sensors, parsed and checked (file and key in
errors).

:class:`SimConfig` is the parsing part of the simulator (:class:`ppoe_core.sim.simulate._Sim` derives from it):
it sets the trajectory (rate, dwell, stops, random stops, smoothing) and sensor (camera, tracker, poses, IMUs,
contact) attributes from the scenario's ``trajectory`` and ``sensors`` sections.
"""

from __future__ import annotations

import csv
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core.errors import ScenarioError
from ppoe_core.robot.config import ModelConfig
from ppoe_core.robot.urdf import Robot
from ppoe_core.sim.scenario import Scenario
from ppoe_core.sim.scenario_checks import check_joint_values, check_keys, check_number, check_pose, key_location

__all__ = ["Stop", "SimConfig", "min_jerk"]


@dataclass
class Stop:
    """One static stop: joint values, dwell [s], optional contact, whether it is measured, which draw."""

    q: dict[str, float]
    dwell: float
    contact: dict | None = None
    measure: bool = True
    draw: int = 0


def min_jerk(s: np.ndarray) -> np.ndarray:
    """The minimum-jerk profile 10 s^3 - 15 s^4 + 6 s^5 of the fraction ``s`` of a move (clipped to [0, 1])."""
    s = np.clip(s, 0.0, 1.0)
    return s ** 3 * (10 - 15 * s + 6 * s * s)


class SimConfig:
    """Scenario ``trajectory`` and ``sensors`` -> attributes of the simulator."""

    # set by the simulator before parsing
    sc: Scenario
    path: str
    robot: Robot
    model: ModelConfig
    joints: list[str]

    # -- parsing -------------------------------------------------------------
    def _parse_trajectory(self, tr: dict) -> None:
        P = self.path
        self.rate = check_number(tr, "joint_rate", 100.0, P, "trajectory", minimum=50.0, maximum=2000.0)
        self.dwell = check_number(tr, "dwell", 0.5, P, "trajectory", minimum=0.0)
        self.settle = check_number(tr, "settle", 0.1, P, "trajectory", minimum=0.0)
        self.move_time = check_number(tr, "move_time", 1.0, P, "trajectory", minimum=0.01)
        extra = tr.get("extra_joints") or {}
        if not isinstance(extra, Mapping):
            raise ScenarioError(f"{key_location(P, 'trajectory.extra_joints')} must map joint names to values")
        self.extra = {str(k): check_number(extra, k, 0.0, P, "trajectory.extra_joints") for k in extra}
        clash = sorted(set(self.extra) & set(self.robot.independent_joints))
        if clash:
            raise ScenarioError(f"{key_location(P, 'trajectory.extra_joints')}: {clash} are driven joints of the URDF")
        self.start = {j: 0.0 for j in self.joints}
        self.start.update(check_joint_values(tr.get("start"), P, "trajectory.start", self.robot))
        self.smooth: Any = None
        self.stops: list[Stop] = []
        if tr.get("smooth") is not None:
            sm = check_keys(
                tr["smooth"], ("duration", "centre", "amplitude", "period", "phase"), P, "trajectory.smooth"
            )
            self.smooth = {
                "duration": check_number(sm, "duration", 60.0, P, "trajectory.smooth", minimum=0.1),
                "centre": {**self.start,
                           **check_joint_values(sm.get("centre"), P, "trajectory.smooth.centre", self.robot)},
                "amplitude": check_joint_values(sm.get("amplitude"), P, "trajectory.smooth.amplitude", self.robot),
                "period": check_joint_values(sm.get("period"), P, "trajectory.smooth.period", self.robot),
                "phase": check_joint_values(sm.get("phase"), P, "trajectory.smooth.phase", self.robot),
            }
            if tr.get("stops") or tr.get("random_stops"):
                raise ScenarioError(f"{key_location(P, 'trajectory')}: give either smooth or stops/random_stops")
            return
        self.stops = [self._parse_stop(i, s) for i, s in enumerate(tr.get("stops") or [])]
        if tr.get("stops_csv") is not None:
            self.stops.extend(Stop({**self.start, **q}, self.dwell) for q in self._csv_stops(str(tr["stops_csv"])))
        self.random_cfg: Any = None
        if tr.get("random_stops") is not None:
            self.random_cfg = self._parse_random_stops(tr["random_stops"])
        if not self.stops and self.random_cfg is None:
            raise ScenarioError(f"{key_location(P, 'trajectory')}: needs stops, random_stops or smooth")

    def _parse_stop(self, i: int, s: Any) -> Stop:
        """``trajectory.stops[i]``: joints (over the start), dwell [s], optional contact press."""
        P = self.path
        s = check_keys(s, ("joints", "dwell", "contact"), P, f"trajectory.stops[{i}]")
        q = dict(self.start)
        q.update(check_joint_values(s.get("joints"), P, f"trajectory.stops[{i}].joints", self.robot))
        c = None
        if s.get("contact") is not None:
            c = check_keys(s["contact"], ("press_joint", "force", "approach"), P, f"trajectory.stops[{i}].contact")
            pj = c.get("press_joint")
            if pj not in self.joints:
                raise ScenarioError(
                    f"{key_location(P, f'trajectory.stops[{i}].contact.press_joint')}: {pj!r} is not an "
                    "independent joint"
                )
            c = {
                "press_joint": pj,
                "force": check_number(c, "force", 10.0, P, f"trajectory.stops[{i}].contact", minimum=0.0),
                "approach": check_number(c, "approach", 0.15, P, f"trajectory.stops[{i}].contact"),
            }
        return Stop(q, check_number(s, "dwell", self.dwell, P, f"trajectory.stops[{i}]", minimum=0.0), c)

    def _csv_stops(self, path: str) -> list[dict[str, float]]:
        """``trajectory.stops_csv``: one configuration per row, the header names independent joints."""
        where = f"{key_location(self.path, 'trajectory.stops_csv')}: {path}"
        try:
            with open(path, newline="", encoding="utf-8") as f:
                rows = [r for r in csv.reader(f) if r and any(c.strip() for c in r)]
        except OSError as exc:
            raise ScenarioError(f"{where}: cannot read ({exc.strerror})") from None
        if len(rows) < 2:
            raise ScenarioError(f"{where}: needs a header of joint names and at least one row")
        head = [h.strip() for h in rows[0]]
        bad = [h for h in head if h not in self.joints]
        if bad:
            raise ScenarioError(f"{where}: line 1: {bad} are not independent joints of the URDF")
        out = []
        for i, r in enumerate(rows[1:], start=2):
            try:
                v = [float(c) for c in r]
            except ValueError:
                raise ScenarioError(f"{where}: line {i}: not a number in {r}") from None
            if len(v) != len(head) or not all(np.isfinite(v)):
                raise ScenarioError(f"{where}: line {i}: {len(v)} values for {len(head)} joints, or not finite")
            out.append(dict(zip(head, v)))
        return out

    def _parse_random_stops(self, raw: Any) -> dict[str, Any]:
        """``trajectory.random_stops``: count, centre and spread per joint, visibility and height constraints."""
        P = self.path
        rs = check_keys(
            raw,
            ("count", "around", "spread", "min_visible_tags", "max_tries", "min_link_z"),
            P,
            "trajectory.random_stops",
        )
        min_z = rs.get("min_link_z") or {}
        if not isinstance(min_z, Mapping) or any(k not in self.robot.links for k in min_z):
            raise ScenarioError(
                f"{key_location(P, 'trajectory.random_stops.min_link_z')} must map links of "
                f"{self.robot.source} to heights [m]"
            )
        min_z = {str(k): check_number(min_z, k, 0.0, P, "trajectory.random_stops.min_link_z") for k in min_z}
        spread = rs.get("spread", 0.2)
        around = {**self.start, **check_joint_values(rs.get("around"), P, "trajectory.random_stops.around", self.robot)}
        if isinstance(spread, Mapping):
            spread = check_joint_values(spread, P, "trajectory.random_stops.spread", self.robot)
        else:
            spread = {j: float(spread) for j in (rs.get("around") or {})}
        return {
            "count": int(check_number(rs, "count", 20, P, "trajectory.random_stops", minimum=1)),
            "around": around,
            "spread": spread,
            "min_visible": int(check_number(rs, "min_visible_tags", 0, P, "trajectory.random_stops", minimum=0)),
            "min_z": min_z,
            "max_tries": int(check_number(rs, "max_tries", 5000, P, "trajectory.random_stops", minimum=1)),
        }

    def _parse_sensors(self) -> None:
        """Scenario ``camera``, ``ground_truth``, ``imus`` and ``contact`` (each None when absent)."""
        raw = self.sc.raw
        self.cam: Any = None  # camera dict (frame, w, h, K, D, rate, ...) or None
        if raw.get("camera") is not None:
            self.cam = self._parse_camera(raw["camera"])
        gt = check_keys(raw.get("ground_truth"), ("pose", "point"), self.path, "ground_truth")
        self.gt_pose: Any = None
        if gt.get("pose") is not None:
            self.gt_pose = self._parse_gt_pose(gt["pose"])
        self.gt_point: Any = None  # the first reflector (its registration goes into the truth)
        self.gt_points: list[dict[str, Any]] = []  # every reflector: ``point`` is one mapping or a list
        if gt.get("point") is not None:
            raw_points = gt["point"] if isinstance(gt["point"], list) else [gt["point"]]
            self.gt_points = [self._parse_gt_point(r, f"ground_truth.point[{i}]" if isinstance(gt["point"], list)
                                                   else "ground_truth.point") for i, r in enumerate(raw_points)]
            self.gt_point = self.gt_points[0]
        self.imu: Any = None
        if raw.get("imus") is not None:
            self.imu = self._parse_imus(raw["imus"])
        self.contact: Any = None
        if raw.get("contact") is not None:
            self.contact = self._parse_contact(raw["contact"])

    def _parse_camera(self, raw_cam: Any) -> dict[str, Any]:
        """Scenario ``camera``: frame, size, intrinsics, plumb_bob D, rate, format, noise, blur."""
        P, m = self.path, self.model
        c = check_keys(
            raw_cam,
            (
                "frame",
                "width",
                "height",
                "intrinsics",
                "D",
                "rate",
                "during",
                "format",
                "noise_sigma",
                "blur_sigma",
                "background",
                "time_offset",
                "pixel_sigma",
            ),
            P,
            "camera",
        )
        if m.tags is None:
            raise ScenarioError(f"{key_location(P, 'camera')}: the model {m.source} has no tags section to render")
        frame = c.get("frame") or (m.camera.frame if m.camera else None)
        if frame not in self.robot.links:
            raise ScenarioError(f"{key_location(P, 'camera.frame')}: {frame!r} is not a link of {self.robot.source}")
        w = int(check_number(c, "width", 640, P, "camera", minimum=16))
        h = int(check_number(c, "height", 480, P, "camera", minimum=16))
        intr = c.get("intrinsics", [600.0, 600.0, w / 2.0, h / 2.0])
        D = np.asarray(c.get("D", [0.0] * 5), dtype=float).reshape(-1)
        if len(intr) != 4 or D.shape[0] != 5:
            raise ScenarioError(f"{key_location(P, 'camera')}: intrinsics = [fx, fy, cx, cy], D = 5 plumb_bob numbers")
        fx, fy, cx, cy = (float(v) for v in intr)
        fmt = c.get("format", "png")
        if fmt not in ("png", "jpeg", "raw", "observations"):
            raise ScenarioError(f"{key_location(P, 'camera.format')} must be png, jpeg, raw or observations")
        during = c.get("during", "stops")
        if during not in ("stops", "always"):
            raise ScenarioError(f"{key_location(P, 'camera.during')} must be stops or always")
        return {
            "frame": frame,
            "w": w,
            "h": h,
            "K": np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]),
            "D": D,
            "rate": check_number(c, "rate", 5.0, P, "camera", minimum=0.01, maximum=30.0),
            "during": during,
            "format": fmt,
            "noise": check_number(c, "noise_sigma", 1.0, P, "camera", minimum=0.0),
            "blur": check_number(c, "blur_sigma", 0.0, P, "camera", minimum=0.0),
            "background": int(check_number(c, "background", 128, P, "camera", minimum=0, maximum=255)),
            "time_offset": check_number(c, "time_offset", 0.0, P, "camera"),
            "pixel_sigma": check_number(c, "pixel_sigma", 0.3, P, "camera", minimum=0.0),
        }

    def _parse_gt_pose(self, raw_gt: Any) -> dict[str, Any]:
        """Scenario ``ground_truth.pose``: tracked frame and target, noise, rate."""
        P, m = self.path, self.model
        g = check_keys(raw_gt, ("frame", "target", "sigma_xyz", "sigma_rot", "rate", "covariance_topic"), P,
                        "ground_truth.pose")
        frame = g.get("frame") or (m.frames.base if m.frames else self.robot.root)
        target = g.get("target") or (m.frames.tool if m.frames else None)
        for k, v in (("frame", frame), ("target", target)):
            if v not in self.robot.links:
                raise ScenarioError(f"{key_location(P, 'ground_truth.pose.' + k)}: {v!r} is not a link")
        return {
            "frame": frame,
            "target": target,
            "sx": check_number(g, "sigma_xyz", 1e-4, P, "ground_truth.pose", minimum=0.0),
            "sr": check_number(g, "sigma_rot", 2e-4, P, "ground_truth.pose", minimum=0.0),
            "rate": check_number(g, "rate", 0.0, P, "ground_truth.pose", minimum=0.0),
            "cov_topic": str(g.get("covariance_topic") or ""),
        }

    def _parse_gt_point(self, raw_gt: Any, where: str = "ground_truth.point") -> dict[str, Any]:
        """Scenario ``ground_truth.point`` (or one entry of its list): reflector topic, link and position,
        noise, tracker frame and pose; link, position and noise default to the model's tracker of that topic."""
        P, m = self.path, self.model
        g = check_keys(raw_gt, ("topic", "link", "xyz", "sigma", "frame", "T_tracker_base", "rate", "during"), P,
                        where)
        if g.get("during", "stops") not in ("stops", "always"):
            raise ScenarioError(f"{key_location(P, where + '.during')} must be stops or always")
        topic = str(g.get("topic", "/ground_truth/point"))
        tr = next((t for t in m.trackers if t.topic == topic), m.tracker)
        link = g.get("link") or (tr.link if tr else None)
        if link not in self.robot.links:
            raise ScenarioError(f"{key_location(P, where + '.link')}: {link!r} is not a link")
        xyz = np.asarray(g.get("xyz", tr.xyz if tr else [0, 0, 0]), dtype=float).reshape(3)
        return {
            "link": link,
            "xyz": xyz,
            "sigma": check_number(g, "sigma", tr.sigma if tr else 2e-4, P, where, minimum=0.0),
            "frame": str(g.get("frame", "tracker")),
            "T_tracker_base": check_pose(g.get("T_tracker_base"), P, where + ".T_tracker_base"),
            "T_cfg": g.get("T_tracker_base") or {},
            "rate": check_number(g, "rate", 0.0, P, where, minimum=0.0),
            "during": str(g.get("during", "stops")),
            "topic": topic,
        }

    def _parse_imus(self, raw_imus: Any) -> dict[str, Any]:
        """Scenario ``imus``: rate and noise of the model's accelerometers."""
        P, m = self.path, self.model
        g = check_keys(raw_imus, ("rate", "sigma"), P, "imus")
        if not m.imus:
            raise ScenarioError(f"{key_location(P, 'imus')}: the model {m.source} declares no imus")
        return {
            "rate": check_number(g, "rate", 0.0, P, "imus", minimum=0.0),
            "sigma": check_number(g, "sigma", None, P, "imus", minimum=0.0),
        }

    def _parse_contact(self, raw_contact: Any) -> dict[str, Any]:
        """Scenario ``contact``: plane, tool point, stiffness, force noise, wrench frame, rate."""
        P, m = self.path, self.model
        c = check_keys(raw_contact, ("plane", "tool_point", "stiffness", "force_sigma", "frame", "rate"), P, "contact")
        mc = m.contact
        if c.get("plane") is not None:
            pl = check_keys(c["plane"], ("frame", "xyz", "rpy"), P, "contact.plane")
            frame = pl.get("frame", self.robot.root)
            T_fp = check_pose(pl, P, "contact.plane")
        elif mc is not None:
            frame, T_fp = mc.plane_frame, mc.T_frame_plane
        else:
            raise ScenarioError(f"{key_location(P, 'contact.plane')} is required (the model has no contact section)")
        tp = c.get("tool_point") or ({"link": mc.tool_link, "xyz": list(mc.tool_xyz)} if mc else None)
        if tp is not None:
            tp = check_keys(tp, ("link", "xyz"), P, "contact.tool_point")
        if tp is None or tp.get("link") not in self.robot.links:
            raise ScenarioError(f"{key_location(P, 'contact.tool_point')}: needs a link of the URDF")
        if frame not in self.robot.links:
            raise ScenarioError(f"{key_location(P, 'contact.plane.frame')}: {frame!r} is not a link")
        out = {
            "frame": frame,
            "T_frame_plane": T_fp,
            "link": tp["link"],
            "xyz": np.asarray(tp.get("xyz", [0, 0, 0]), float).reshape(3),
            "k": check_number(c, "stiffness", 1e5, P, "contact", minimum=1.0),
            "sigma": check_number(c, "force_sigma", 0.1, P, "contact", minimum=0.0),
            "wframe": str(c.get("frame", tp["link"])),
            "rate": check_number(c, "rate", self.rate, P, "contact", minimum=1.0),
        }
        if out["wframe"] not in self.robot.links:
            raise ScenarioError(f"{key_location(P, 'contact.frame')}: not a link")
        return out

    # -- random draws ----------------------------------------------------------
