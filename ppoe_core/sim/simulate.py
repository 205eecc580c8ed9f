"""``ppoe simulate``: record contract bags (docs/conventions.md sec. 3) of a simulated robot.

The *true* robot is the nominal URDF plus

* the declared perturbations ``xi_i`` of the model YAML, drawn from their covariance
  (once per bag, once per stop, or not at all) and the declared joint noise (per stop),
* named systematic effects from the scenario's ``truth.effects`` that the model may not
  declare (docs/conventions.md sec. 6 vocabulary, implemented here independently of
  :mod:`ppoe_core.model.effects` so that ``ppoe diagnose`` is tested against physics, not
  against its own code): ``joint_offset``, ``link_error``, ``gravity_compliance``,
  ``mount_bending``, ``base_tilt``, ``backlash``, ``thermal_growth``, ``time_offset``,
  ``camera_extrinsics``; ``camera_intrinsics`` and ``tag_offset`` change what the camera sees
  (:mod:`ppoe_core.sim.camera_sim`); ``transmission_error`` is outside the vocabulary.

One link of the true chain is (paper eq. 16 with the effects inserted)::

    Exp(p_i) Exp(dxi_i) Exp(xi_i) Exp(zeta_i (q_i + dq_i))

with ``dq_i`` from joint offsets, backlash, gravity compliance and joint noise, and
``dxi_i`` from link errors, mount bending, thermal growth and camera extrinsics.

Sensors: joint states (the commanded / measured values), camera images with the model's
tags rendered at their TRUE pose (:func:`ppoe_core.sensing.tags.render_tags`), contact wrenches
against a true plane, ground-truth tool poses (tracker noise), tracker points in an
unknown tracker frame, accelerometers.  Everything is deterministic for a seed.

The scenario YAML is documented key by key in :data:`SCENARIO_DOC` (also printed by
``ppoe simulate --help-scenario``); example files are in ``bags/``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import PpoeError, ScenarioError
from ppoe_core.io.bagio import BagWriter
from ppoe_core.robot.tree import GRAVITY
from ppoe_core.sim.scenario import SCENARIO_DOC, TRUTH_EFFECTS, Scenario, load_scenario
from ppoe_core.sim.scenario_checks import check_joint_values, check_keys, check_number, key_location
from ppoe_core.sim.camera_sim import camera_events, check_camera_truth, tag_poses_cam, visible_tags
from ppoe_core.sim.schedule import parse_temperature, temperature_events, truth_entries
from ppoe_core.sim.sim_config import min_jerk, SimConfig, Stop
from ppoe_core.sim.truth import TrueRobot

__all__ = ["SCENARIO_DOC", "TRUTH_EFFECTS", "Scenario", "TrueRobot", "SimulationResult", "load_scenario", "simulate"]


# =============================================================================
# trajectory
# =============================================================================


@dataclass
class SimulationResult:
    """What :func:`simulate` wrote and the truth behind it."""

    bag: str
    counts: dict[str, int]
    truth: dict[str, Any]
    duration: float
    n_stops: int
    visible_tags: list[int] = field(default_factory=list)


class _Sim(SimConfig):
    """One simulation run (internal)."""

    def __init__(self, sc: Scenario, seed: int) -> None:
        self.sc = sc
        self.path = sc.path
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        raw = sc.raw
        self.robot = sc.robot
        self.model = sc.model
        truth = check_keys(raw.get("truth"), ("perturbations", "perturbation_scale", "joint_noise", "effects",
                                               "record_draws", "encoder_noise"),
                            self.path, "truth")
        self.draw = truth.get("perturbations", "once")
        if self.draw not in ("once", "per_stop", "none"):
            raise ScenarioError(f"{key_location(self.path, 'truth.perturbations')} must be once, per_stop or none")
        self.pscale = check_number(truth, "perturbation_scale", 1.0, self.path, "truth", minimum=0.0)
        self.use_joint_noise = bool(truth.get("joint_noise", True))
        self.record_draws = bool(truth.get("record_draws", False))
        self.temperature = parse_temperature(raw.get("temperature"), self.path, self.robot.root)
        self.true = TrueRobot(self.robot, truth.get("effects") or [], where=f"scenario {self.path}: truth.effects",
                              temperature=self.temperature["value"] if self.temperature else None)
        self.dt_js = self.true.effect_param("time_offset", "dt")
        self.joints = self.robot.independent_joints
        self._parse_trajectory(check_keys(raw.get("trajectory"), (
            "joint_rate", "dwell", "settle", "move_time", "extra_joints", "start", "stops", "stops_csv", "random_stops",
            "smooth"), self.path, "trajectory"))
        self._parse_sensors()
        self.encoder_noise = self._parse_encoder_noise(truth.get("encoder_noise", 0.0))
        check_camera_truth(self)

    def _parse_encoder_noise(self, raw: Any) -> np.ndarray:
        """``truth.encoder_noise``: 1-sigma per driven joint of the white noise on each recorded sample [rad|m]."""
        where = "truth.encoder_noise"
        if isinstance(raw, Mapping):
            m = check_joint_values(raw, self.path, where, self.robot)
            bad = sorted(set(m) - set(self.joints))
            if bad:
                raise ScenarioError(f"{key_location(self.path, where)}: {bad} are not driven joints")
            sig = np.array([m.get(j, 0.0) for j in self.joints])
        else:
            sig = np.full(len(self.joints), check_number({"v": raw}, "v", 0.0, self.path, where, minimum=0.0))
        if np.any(sig < 0):
            raise ScenarioError(f"{key_location(self.path, where)} must be >= 0")
        return sig

    def _draw_xi(self, n_sets: int) -> list[dict[str, np.ndarray]]:
        out = []
        for _ in range(n_sets):
            d = {}
            for jn, pert in self.model.perturbations.items():
                F = pert.factor
                d[jn] = self.pscale * (F @ self.rng.standard_normal(F.shape[1])) if self.draw != "none" else np.zeros(6)
            out.append(d)
        return out

    def _draw_noise(self, n_sets: int) -> list[dict[str, float]]:
        out = []
        for _ in range(n_sets):
            d = {}
            if self.use_joint_noise:
                for jn, s in self.model.joint_noise.items():
                    d[jn] = float(s * self.rng.standard_normal())
            out.append(d)
        return out

    # -- truth evaluation over a batch of samples --------------------------------
    def truth_poses(self, Q: np.ndarray, set_idx: np.ndarray, signs: np.ndarray,
                    t: np.ndarray) -> dict[str, np.ndarray]:
        """True link poses for commanded joints Q (n, nj), draw-set index (n,), motion signs (n, nj), stamps."""
        n = Q.shape[0]
        q = {j: Q[:, i] for i, j in enumerate(self.joints)}
        xi = {jn: np.stack([self.xi_sets[k][jn] for k in set_idx]) for jn in self.model.perturbations} if n else {}
        noise = {jn: np.array([self.noise_sets[k].get(jn, 0.0) for k in set_idx]) for jn in self.model.joint_noise}
        sg = {j: signs[:, i] for i, j in enumerate(self.joints)}
        return self.true.poses(q, xi, noise, sg, t - self.sc.start_time, n)

    # -- plan -----------------------------------------------------------------
    def plan(self) -> None:
        """Build the stop list (random stops, contact solving) and draw perturbation sets."""
        if self.smooth is None and self.random_cfg is not None:
            self._add_random_stops()
        n_stops = max(len(self.stops), 1)
        for k, s in enumerate(self.stops):
            s.draw = k
        n_sets = n_stops if self.draw == "per_stop" else 1
        self.xi_sets = self._draw_xi(n_sets)
        if n_sets == 1:
            self.xi_sets = self.xi_sets * n_stops
        # joint noise is drawn per stop in any case
        self.noise_sets = self._draw_noise(n_stops)
        if self.smooth is None:
            self._solve_contacts()

    def _add_random_stops(self) -> None:
        cfg = self.random_cfg
        need = cfg["count"]
        tries = 0
        names = list(cfg["spread"])
        lo_hi = {}
        for j in names:
            lim = self.robot.joints[j].limit
            lo_hi[j] = (
                (lim.lower if lim and lim.lower is not None else -np.inf),
                (lim.upper if lim and lim.upper is not None else np.inf),
            )
        got = 0
        while got < need:
            tries += 1
            if tries > cfg["max_tries"]:
                raise ScenarioError(
                    f"{key_location(self.path, 'trajectory.random_stops')}: only {got} of {need} "
                    f"acceptable configurations (min_visible_tags, min_link_z) in {cfg['max_tries']} tries"
                )
            q = dict(cfg["around"])
            for j in names:
                q[j] = float(np.clip(q[j] + self.rng.uniform(-cfg["spread"][j], cfg["spread"][j]), *lo_hi[j]))
            if cfg["min_z"]:
                Q = np.array([[q[j] for j in self.joints]])
                poses = self.true.poses({j: Q[:, i] for i, j in enumerate(self.joints)}, {}, {}, {}, np.zeros(1), 1)
                if any(poses[ln][0, 2, 3] < z for ln, z in cfg["min_z"].items()):
                    continue
            if cfg["min_visible"] > 0:
                if self.cam is None:
                    raise ScenarioError(
                        f"{key_location(self.path, 'trajectory.random_stops.min_visible_tags')} needs a camera"
                    )
                Q = np.array([[q[j] for j in self.joints]])
                poses = self.true.poses({j: Q[:, i] for i, j in enumerate(self.joints)}, {}, {}, {}, np.zeros(1), 1)
                Ts, _, sizes = tag_poses_cam(self, poses)
                if visible_tags(self.cam, Ts, sizes)[0].sum() < cfg["min_visible"]:
                    continue
            self.stops.append(Stop(q, self.dwell))
            got += 1

    def _contact_penetration(self, poses: Mapping[str, np.ndarray]) -> np.ndarray:
        """Depth [m] of the true tool point below the true plane (positive = pressing), (n,)."""
        c = self.contact
        T_root_plane = poses[c["frame"]] @ c["T_frame_plane"]
        p = (poses[c["link"]] @ np.append(c["xyz"], 1.0))[:, :3]
        d = np.einsum("nij,nj->ni", np.swapaxes(T_root_plane[:, :3, :3], 1, 2), p - T_root_plane[:, :3, 3])
        return -d[:, 2]

    def _solve_contacts(self) -> None:
        new: list[Stop] = []
        for k, s in enumerate(self.stops):
            if s.contact is None:
                new.append(s)
                continue
            if self.contact is None:
                raise ScenarioError(f"{key_location(self.path, f'trajectory.stops[{k}].contact')} needs the contact "
                                    "section")
            pj = s.contact["press_joint"]
            target = s.contact["force"] / self.contact["k"]

            def depth(v: float, s: Stop = s, pj: str = pj) -> float:
                q = dict(s.q)
                q[pj] = v
                Q = np.array([[q[j] for j in self.joints]])
                P = self.truth_poses(Q, np.array([s.draw]), np.zeros_like(Q), np.array([self.sc.start_time]))
                return float(self._contact_penetration(P)[0])

            v = s.q[pj]
            for _ in range(30):  # secant / Newton with numeric slope
                f = depth(v) - target
                if abs(f) < 1e-10:
                    break
                h = 1e-4
                slope = (depth(v + h) - depth(v - h)) / (2 * h)
                if abs(slope) < 1e-9:
                    raise ScenarioError(
                        f"{key_location(self.path, f'trajectory.stops[{k}].contact')}: joint {pj} does not "
                        "move the tool point towards the plane"
                    )
                v = v - f / slope
            else:
                raise ScenarioError(f"{key_location(self.path, f'trajectory.stops[{k}].contact')}: could not reach "
                                    "the plane")
            slope = (depth(v + 1e-4) - depth(v - 1e-4)) / 2e-4
            away = -math.copysign(abs(s.contact["approach"]), slope)
            qa = dict(s.q)
            qa[pj] = v + away
            qc = dict(s.q)
            qc[pj] = v
            new.append(Stop(qa, 0.2, None, measure=False, draw=s.draw))
            new.append(Stop(qc, s.dwell, s.contact, draw=s.draw))
            new.append(Stop(dict(qa), 0.2, None, measure=False, draw=s.draw))
        self.stops = new

    # -- time line ------------------------------------------------------------
    def timeline(self) -> None:
        """Commanded joints at the joint-state rate, stop windows, motion signs."""
        t0, dt = self.sc.start_time, 1.0 / self.rate
        nj = len(self.joints)
        if self.smooth is not None:
            t = t0 + np.arange(int(round(self.smooth["duration"] * self.rate)) + 1) * dt
            Q = self._smooth_q(t)
            self.t, self.Q = t, Q
            self.set_idx = np.zeros(t.shape[0], int)
            self.windows: list[tuple[float, float, int]] = []
        else:
            ts, qs, sets = [], [], []
            windows = []
            qprev = np.array([self.stops[0].q[j] for j in self.joints])
            now = t0
            for k, s in enumerate(self.stops):
                qk = np.array([s.q[j] for j in self.joints])
                if k > 0:
                    nmove = int(round(self.move_time * self.rate))
                    for i in range(nmove):
                        ts.append(now + i * dt)
                        qs.append(qprev + (qk - qprev) * min_jerk(np.array(i / nmove)))
                        sets.append(s.draw)
                    now += nmove * dt
                ndw = max(int(round(s.dwell * self.rate)), 1)
                start = now
                for i in range(ndw):
                    ts.append(now + i * dt)
                    qs.append(qk)
                    sets.append(s.draw)
                now += ndw * dt
                if s.measure:
                    windows.append((start, now - dt, k))
                qprev = qk
            self.t, self.Q, self.set_idx = np.array(ts), np.array(qs), np.array(sets)
            self.windows = windows
        # sign of the last motion per joint (backlash)
        dQ = np.diff(self.Q, axis=0, prepend=self.Q[:1])
        sg = np.sign(np.where(np.abs(dQ) > 1e-12, dQ, 0.0))
        last = np.zeros(nj)
        signs = np.zeros_like(self.Q)
        for i in range(self.Q.shape[0]):
            nz = sg[i] != 0
            last = np.where(nz, sg[i], last)
            signs[i] = last
        self.signs = signs

    def _smooth_q(self, ts: np.ndarray) -> np.ndarray:
        """Commanded joints of the smooth motion at stamps ``ts`` (analytic), (n, nj)."""
        sm, t0 = self.smooth, self.sc.start_time
        Q = np.zeros((ts.shape[0], len(self.joints)))
        for i, j in enumerate(self.joints):
            a = sm["amplitude"].get(j, 0.0)
            per = sm["period"].get(j, 10.0)
            Q[:, i] = sm["centre"][j] + a * np.sin(2 * np.pi * (ts - t0) / per + sm["phase"].get(j, 0.0))
        return Q

    def sensor_times(self, rate: float, during: str = "stops") -> np.ndarray:
        """Sample stamps: inside each stop window after ``settle`` (rate 0 = once per stop), or the whole bag."""
        if self.smooth is not None or during == "always":
            if rate <= 0:
                raise ScenarioError(f"{key_location(self.path, 'sensor rate')}: rate 0 (once per stop) needs stops")
            return np.arange(self.t[0], self.t[-1] + 1e-9, 1.0 / rate)
        out = []
        for a, b, _ in self.windows:
            s = a + self.settle
            if s > b:
                s = 0.5 * (a + b)
            if rate <= 0:
                out.append(s)
            else:
                out.extend(np.arange(s, b + 1e-9, 1.0 / rate).tolist())
        return np.array(out)

    def state_at(self, ts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Commanded joints (linear interpolation), draw set and motion signs at stamps ``ts``."""
        idx = np.clip(np.searchsorted(self.t, ts, side="right") - 1, 0, self.t.shape[0] - 1)
        nxt = np.minimum(idx + 1, self.t.shape[0] - 1)
        span = np.where(nxt > idx, self.t[nxt] - self.t[idx], 1.0)
        w = np.clip((ts - self.t[idx]) / span, 0.0, 1.0)[:, None]
        Q = self.Q[idx] * (1 - w) + self.Q[nxt] * w
        if self.smooth is not None:
            Q = self._smooth_q(ts)
        return Q, self.set_idx[idx], self.signs[idx]

    # -- run ------------------------------------------------------------------
    def run(self, out: str | os.PathLike, storage: str = "mcap", overwrite: bool = False) -> SimulationResult:
        self.plan()
        self.timeline()
        events: list[tuple[float, int, str, tuple]] = []  # (stamp, order, kind, payload)
        # joint states (time offset: a message stamped t carries the position at t - dt)
        names = list(self.joints) + list(self.extra)
        Qjs, _, _ = self.state_at(self.t - self.dt_js)
        if np.any(self.encoder_noise > 0):
            Qjs = Qjs + self.encoder_noise * self.rng.standard_normal(Qjs.shape)
        extra_vals = [float(v) for v in self.extra.values()]
        for i, t in enumerate(self.t):
            events.append((float(t), 0, "js", (names, np.concatenate([Qjs[i], extra_vals]))))
        visible_ids: set[int] = set()
        if self.cam is not None:
            visible_ids = camera_events(self, events)
        if self.gt_pose is not None:
            self._gt_pose_events(events)
        if self.gt_point is not None:
            self._gt_point_events(events)
        if self.imu is not None:
            self._imu_events(events)
        if self.contact is not None:
            self._wrench_events(events)
        if self.temperature is not None:
            temperature_events(self, events)
        events.sort(key=lambda e: (e[0], e[1]))
        counts = self._write(out, storage, overwrite, events)
        return SimulationResult(
            str(out), counts, self.truth_dict(), float(self.t[-1] - self.t[0]), len(self.windows), sorted(visible_ids)
        )

    def _gt_pose_events(self, events: list[tuple[float, int, str, tuple]]) -> None:
        """Ground-truth poses of the target in the tracked frame, with noise."""
        g = self.gt_pose
        ts = self.sensor_times(g["rate"])
        Q, S, G = self.state_at(ts)
        poses = self.truth_poses(Q, S, G, ts)
        T = lie.inverse(poses[g["frame"]]) @ poses[g["target"]]
        noise = np.concatenate(
            [g["sx"] * self.rng.standard_normal((len(ts), 3)), g["sr"] * self.rng.standard_normal((len(ts), 3))], axis=1
        )
        for i, t in enumerate(ts):
            events.append((float(t), 2, "gtpose", (T[i] @ lie.exp(noise[i]),)))
        if g["cov_topic"]:  # a second pose sensor: an independent draw, with its covariance (ROS convention)
            other = np.concatenate([g["sx"] * self.rng.standard_normal((len(ts), 3)),
                                    g["sr"] * self.rng.standard_normal((len(ts), 3))], axis=1)
            cov = np.diag([g["sx"] ** 2] * 3 + [g["sr"] ** 2] * 3)
            events += [(float(t), 2, "gtposecov", (T[i] @ lie.exp(other[i]), cov)) for i, t in enumerate(ts)]

    def _gt_point_events(self, events: list[tuple[float, int, str, tuple]]) -> None:
        """Tracker measurements of each reflector in its tracker frame, with noise."""
        for k, g in enumerate(self.gt_points):
            ts = self.sensor_times(g["rate"], g["during"])
            Q, S, G = self.state_at(ts)
            poses = self.truth_poses(Q, S, G, ts)
            p = (g["T_tracker_base"] @ poses[g["link"]] @ np.append(g["xyz"], 1.0))[:, :3]
            p = p + g["sigma"] * self.rng.standard_normal(p.shape)
            events.extend((float(t), 3, "gtpoint", (p[i], k)) for i, t in enumerate(ts))

    def _imu_events(self, events: list[tuple[float, int, str, tuple]]) -> None:
        """Accelerometer readings (gravity at rest in each IMU's link), with noise."""
        ts = self.sensor_times(self.imu["rate"])
        Q, S, G = self.state_at(ts)
        poses = self.truth_poses(Q, S, G, ts)
        for name, cfg in self.model.imus.items():
            sig = self.imu["sigma"] if self.imu["sigma"] is not None else cfg.sigma
            R = poses[cfg.link][:, :3, :3]
            a = np.einsum("nji,j->ni", R, np.array([0.0, 0.0, GRAVITY]))  # specific force at rest
            a = a + sig * self.rng.standard_normal(a.shape)
            for i, t in enumerate(ts):
                events.append((float(t), 4, "imu", (name, cfg.link, a[i], sig)))

    def _wrench_events(self, events: list[tuple[float, int, str, tuple]]) -> None:
        """Contact wrenches (spring law on the penetration of the tool point into the plane), with noise."""
        c = self.contact
        ts = np.arange(self.t[0], self.t[-1] + 1e-9, 1.0 / c["rate"])
        Q, S, G = self.state_at(ts)
        poses = self.truth_poses(Q, S, G, ts)
        depth = np.maximum(self._contact_penetration(poses), 0.0)
        T_root_plane = poses[c["frame"]] @ c["T_frame_plane"]
        f_root = c["k"] * depth[:, None] * T_root_plane[:, :3, 2]  # table pushes along its normal
        R_w = poses[c["wframe"]][:, :3, :3]
        f = np.einsum("nji,nj->ni", R_w, f_root) + c["sigma"] * self.rng.standard_normal((len(ts), 3))
        # torque of the contact force about the wrench frame origin
        p_c = (poses[c["link"]] @ np.append(c["xyz"], 1.0))[:, :3] - poses[c["wframe"]][:, :3, 3]
        tq = np.einsum("nji,nj->ni", R_w, np.cross(p_c, f_root)) + 0.01 * c["sigma"] * self.rng.standard_normal(
            (len(ts), 3)
        )
        for i, t in enumerate(ts):
            events.append((float(t), 5, "wrench", (f[i], tq[i])))

    def _write(self, out: str | os.PathLike, storage: str, overwrite: bool, events: list) -> dict[str, int]:
        cam_frame = self.cam["frame"] if self.cam else ""
        with BagWriter(out, storage=storage, overwrite=overwrite) as bag:
            bag.write_robot_description(self.sc.urdf_text, self.sc.start_time - 0.01)
            for t, _, kind, pl in events:
                if kind == "js":
                    bag.write_joint_state(t, pl[0], pl[1])
                elif kind == "cam":
                    bag.write_camera_info(t, cam_frame, self.cam["w"], self.cam["h"], self.cam["K"], self.cam["D"])
                    if self.cam["format"] == "raw":
                        bag.write_image(t, cam_frame, pl[0])
                    else:
                        bag.write_compressed_image(t, cam_frame, pl[0], self.cam["format"])
                elif kind == "obs":
                    bag.write_camera_info(t, cam_frame, self.cam["w"], self.cam["h"], self.cam["K"], self.cam["D"])
                    r = pl[0]
                    bag.write_tag_observations(t, cam_frame, r[:, 0], r[:, 1], r[:, 2:4], r[:, 4:6])
                elif kind == "gtpose":
                    bag.write_ground_truth_pose(t, self.gt_pose["frame"], pl[0])
                elif kind == "gtposecov":
                    bag.write_pose_with_covariance(self.gt_pose["cov_topic"], t, self.gt_pose["frame"], *pl)
                elif kind == "gtpoint":
                    gp = self.gt_points[pl[1]]
                    bag.write_ground_truth_point(t, gp["frame"], pl[0], topic=gp["topic"])
                elif kind == "imu":
                    bag.write_imu(pl[0], t, pl[1], pl[2], accel_sigma=pl[3])
                elif kind == "wrench":
                    bag.write_wrench(t, self.contact["wframe"], pl[0], pl[1])
                elif kind == "temp":
                    tc: Any = self.temperature
                    bag.write_temperature(t, tc["frame"], pl[0], tc["sigma"] ** 2, topic=tc["topic"])
            return dict(bag.counts)

    def truth_dict(self) -> dict[str, Any]:
        """The truth of the bag (what the tools are never told), plain types for YAML."""
        d: dict[str, Any] = {
            "seed": self.seed,
            "start_time": self.sc.start_time,
            "perturbations": self.draw,
            **truth_entries(self.true.effects, self.sc.start_time, self.temperature),
        }
        if self.draw == "once" and self.xi_sets:
            d["xi"] = {k: [float(x) for x in v] for k, v in self.xi_sets[0].items()}
        if self.gt_point is not None:
            T = self.gt_point["T_tracker_base"]
            d["T_tracker_base"] = [[float(x) for x in row] for row in T]
            d["tracker_registration"] = {
                "frame": self.gt_point["frame"],
                "xyz": [float(x) for x in self.gt_point["T_cfg"].get("xyz", [0, 0, 0])],
                "rpy": [float(x) for x in self.gt_point["T_cfg"].get("rpy", [0, 0, 0])],
            }
        if self.cam is not None:
            d["camera"] = {
                "frame": self.cam["frame"],
                "K": self.cam["K"].tolist(),
                "D": self.cam["D"].tolist(),
                "K_true": self.cam["K_true"].tolist(),
                "D_true": self.cam["D_true"].tolist(),
                "width": self.cam["w"],
                "height": self.cam["h"],
            }
        if self.contact is not None:
            d["contact_plane"] = {
                "frame": self.contact["frame"],
                "T_frame_plane": self.contact["T_frame_plane"].tolist(),
                "stiffness": self.contact["k"],
            }
        d["stops"] = len(self.windows)
        if self.record_draws:
            d["stop_draws"] = [
                {
                    "start": float(a),
                    "end": float(b),
                    "xi": {k: [float(x) for x in v] for k, v in self.xi_sets[self.stops[k_].draw].items()},
                    "joint_noise": {k: float(v) for k, v in self.noise_sets[self.stops[k_].draw].items()},
                }
                for a, b, k_ in self.windows
            ]
        return d


def simulate(
    scenario: str | os.PathLike | Scenario,
    out: str | os.PathLike,
    seed: int | None = None,
    storage: str = "mcap",
    overwrite: bool = False,
) -> SimulationResult:
    """Run a scenario and write the bag.

    Parameters
    ----------
    scenario
        Scenario YAML path (or a loaded :class:`Scenario`).
    out
        Bag directory to create.
    seed
        Overrides the scenario's ``seed``.
    storage
        ``mcap`` or ``sqlite3``.
    overwrite
        Replace an existing bag directory.

    Returns
    -------
    SimulationResult
        Message counts per topic and the truth (effects, drawn perturbations, registration).

    Raises
    ------
    ScenarioError
        Bad scenario; :class:`~ppoe_core.errors.BagError` if the bag cannot be written.
    """
    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    try:
        sim = _Sim(sc, sc.seed if seed is None else int(seed))
        return sim.run(out, storage=storage, overwrite=overwrite)
    except PpoeError:
        raise
    except (KeyError, ValueError, TypeError, AttributeError) as exc:  # malformed values that slipped through
        raise ScenarioError(f"scenario {sc.path}: {type(exc).__name__}: {exc}") from exc
