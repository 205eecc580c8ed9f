"""Issue 22, the pieces: every measurement kind's update Jacobian (finite differences), the drift monitor's
false-alarm rate (Monte Carlo), the naming of a drift on a synthetic window, the default online set, and the
bad-input rules of the online inputs (camera_info change, a tag seen by two cameras, a stale temperature)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import REPO
from jacobian_check import check_jacobian
from scipy.stats import binomtest

from ppoe_core import lie
from ppoe_core.analysis.drift_naming import name_drift
from ppoe_core.estimation.direct_measurements import GravityObservation, PointObservation, PoseObservation
from ppoe_core.estimation.measurements import ContactPlaneModel, TagBearingModel, tag_points
from ppoe_core.estimation.online_config import default_online_entries, model_streams
from ppoe_core.estimation.online_effects import OnlineEffects, OnlineUpdate, parse_online_config
from ppoe_core.estimation.online_inputs import OnlineInputs, OnlineMeasurement
from ppoe_core.estimation.online_models import FramePart, OnlineRow
from ppoe_core.estimation.online_monitor import DriftMonitor, MonitorSettings
from ppoe_core.estimation.updater import TagMeasurement
from ppoe_core.model.effects import make_effect
from ppoe_core.model.ppoe import PPOEModel
from ppoe_core.robot.dh import dh_to_urdf

ONLINE = REPO / "bags" / "online"
Q0 = {"shoulder_pan": 0.25, "shoulder_lift": -1.8, "elbow": -1.6, "wrist_1": -1.2, "wrist_2": 1.5, "wrist_3": 0.2}


@pytest.fixture(scope="module")
def camera_model(tmp_path_factory) -> PPOEModel:
    """cobot6 with the wrist camera and the table tags (bags/online/cobot6_camera_*.yaml)."""
    urdf = tmp_path_factory.mktemp("cam") / "cobot6_camera.urdf"
    urdf.write_text(dh_to_urdf(ONLINE / "cobot6_camera_dh.yaml"))
    return PPOEModel.from_files(urdf, ONLINE / "cobot6_camera_model.yaml")


def _filter(model: PPOEModel, entries=None) -> OnlineEffects:
    return OnlineEffects(model, parse_online_config(entries, model), 1e-6)


TRACKED = [{"name": "base_tilt", "location": "world"},
           {"name": "gravity_compliance", "location": "shoulder_lift"},
           {"name": "camera_extrinsics", "location": "camera_optical_frame"},
           {"name": "thermal_growth", "location": "elbow", "variable": "temperature", "reference": 20.0}]


def _parts(model: PPOEModel, f: OnlineEffects) -> dict[str, FramePart]:
    """One part of every kind (state ``T_ref_link``), measured value at the filter's estimate (the pose residual's
    ``H = I`` is exact at a zero residual)."""
    item = model.config.tags.items[1]
    K = np.array([[900.0, 0, 0], [0, 900.0, 0], [0, 0, 1]])
    T_cam = f.pose(Q0, "camera_optical_frame", "world")
    pts = tag_points(item.size, item.T_link_tag)
    tag = TagBearingModel(pts, K, mode="normalized", pixel_sigma=0.25)
    plane = lie.from_rt(np.eye(3), np.array([0.0, 0.0, 0.9]))
    return {
        "tags": FramePart("camera_optical_frame", "world", tag, tag.h(T_cam)),
        "pose": FramePart("world", "tool0", PoseObservation(np.eye(6) * 1e-8), f.pose(Q0, "world", "tool0")),
        "point": FramePart("world", "tool0", PointObservation([0.05, 0.0, -0.03], 5e-5),
                           f.pose(Q0, "world", "tool0")[:3, 3]),
        "gravity": FramePart("world", "base_link", GravityObservation(4e-4), np.array([0.0, 0.0, 9.81])),
        "contact": FramePart("world", "tool0", ContactPlaneModel(plane, np.eye(6) * 1e-8, [0.0, 0.0, 0.0]),
                             np.zeros(1)),
    }


@pytest.mark.parametrize("kind", ["tags", "pose", "point", "gravity", "contact"])
def test_every_kind_update_jacobian_matches_finite_differences(camera_model, kind):
    """``H = H_X J_theta`` of the generic update (tag pixels with the camera on the arm, a 6D pose, a point, an
    accelerometer, a contact plane) against central differences of the predicted measurement in theta."""
    f = _filter(camera_model, TRACKED)
    f.set_temperature(0.0, 35.0)
    f.theta = f.theta + np.r_[0.001, -0.002, 1e-4, np.full(6, 1e-3), 2e-5]
    row = OnlineRow(1.0, kind, dict(Q0), [_parts(camera_model, f)[kind]], {"temperature": 35.0})
    lin = f.linearize(row)[0]
    H = lin.H_state @ f.param_jacobian(row.q, lin.chain, None, row.context)

    def neg_residual(theta):
        return -f.linearize(row, f.effects(theta))[0].residual

    check_jacobian(neg_residual, f.theta.copy(), H, eps=1e-7, atol=1e-6 * max(1.0, float(np.abs(H).max())),
                   err_msg=kind)
    seen = np.abs(H).max(axis=0) > 1e-9  # state: tilt_x, tilt_y, compliance, camera x..rz, alpha
    if kind == "gravity":
        assert seen[:2].all() and not seen[2:].any()  # the base accelerometer sees the tilt, nothing else
    elif kind == "tags":
        assert seen.all()  # a camera on the arm seeing floor tags sees the tilt, its extrinsics, the arm
    else:
        assert seen[[0, 1, 2, 9]].all() and not seen[3:9].any()  # the camera's extrinsics do not move the tool


def test_tag_update_corrects_a_tilt_from_pixels(camera_model):
    """One image of floor tags, taken with a 2 mrad tilt the filter does not know, moves the tilt towards it."""
    f = _filter(camera_model, [{"name": "base_tilt", "location": "world", "initial_sigma": 0.005}])
    true = [make_effect("base_tilt", "world", f.tree, [0.002, -0.001])]
    parts = []
    for item in camera_model.config.tags.items[:3]:
        T = f.pose(Q0, "camera_optical_frame", "world", true, {})
        obs = TagBearingModel(tag_points(item.size, item.T_link_tag), np.diag([900.0, 900.0, 1.0]),
                              mode="normalized", pixel_sigma=0.25)
        parts.append(FramePart("camera_optical_frame", "world", obs, obs.h(T)))
    up = f.update(OnlineRow(1.0, "cam", dict(Q0), parts), "tags")
    assert isinstance(up, OnlineUpdate) and up.dim == 30
    np.testing.assert_allclose(f.theta, [0.002, -0.001], atol=2e-4)
    assert f.counts.by_kind == {"tags": 1}


def test_monitor_false_alarm_rate_monte_carlo():
    """Under the model (independent chi-square NIS) each windowed test alarms with the stated probability, and
    the alarm episodes stay below false_alarm x tests."""
    rng = np.random.default_rng(22)
    alpha, window = 0.01, 10
    mon = DriftMonitor(MonitorSettings(window=window, false_alarm=alpha))

    class _F:
        class counts:
            updates = 0

    fires = 0
    for k in range(20000):
        dim = int(rng.choice([2, 3, 6]))
        up = OnlineUpdate(np.zeros(dim), float(rng.chisquare(dim)), False, dim, float("nan"))
        mon.observe(_F(), OnlineRow(float(k), "s", {}, []), up)
        if mon.trace and mon.trace[-1][0] == float(k):
            fires += mon.trace[-1][2] > mon.trace[-1][3]
    assert mon.tests == 20000 - window + 1
    assert binomtest(fires, mon.tests, alpha).pvalue > 1e-3, (fires, mon.tests)
    assert len(mon.events) <= fires <= 2 * alpha * mon.tests
    assert len(mon.events) > 0  # the test can fire


def _thermal_window(model: PPOEModel, f: OnlineEffects, alpha: float, n: int = 40) -> list[OnlineRow]:
    """Tracker-like 3D points of tool0 in the world at random joints and a temperature ramp, the truth growing the
    upper arm (thermal_growth at elbow) by ``alpha``; noise 50 um."""
    rng = np.random.default_rng(5)
    truth = make_effect("thermal_growth", "elbow", f.tree, [alpha], variable="temperature", reference=20.0)
    rows = []
    for k in range(n):
        q = {j: v + rng.uniform(-0.4, 0.4) for j, v in Q0.items()}
        ctx = {"temperature": 20.0 + 0.5 * k}
        p = f.pose(q, "world", "tool0", [truth], ctx)[:3, 3] + rng.normal(0, 5e-5, 3)
        rows.append(OnlineRow(float(k), "/tracker", q, [FramePart("world", "tool0", PointObservation(
            np.zeros(3), 5e-5), p)], ctx))
    return rows


def test_naming_finds_the_thermal_link_and_nothing_without_drift(camera_model):
    f = _filter(camera_model, [{"name": "base_tilt", "location": "world"}])
    f.set_temperature(0.0, 20.0)
    named = name_drift(f, _thermal_window(camera_model, f, 5e-5))
    assert [e.key for e in named.named][:1] == ["thermal_growth@elbow"]
    e = named.named[0]
    assert e.gain > 0.5 and e.trackable and abs(e.effect.params[0] - 5e-5) < 4 * e.sigma[0]
    quiet = name_drift(f, _thermal_window(camera_model, f, 0.0))
    assert quiet.named == [] and "no candidate" in quiet.why and quiet.candidates > 10


def test_default_set_follows_the_streams(camera_model):
    """No configuration: the base tilt is tracked when a stream sees it (tags on the floor seen from the arm), not
    for a camera and tags that tilt together."""
    assert model_streams(camera_model) == {"tags"}
    assert default_online_entries(camera_model, {"tags"}) == [{"name": "base_tilt", "location": "world"}]
    assert default_online_entries(camera_model, set()) == []
    cobot = PPOEModel.from_strings(dh_to_urdf(REPO / "config" / "robots" / "cobot6_dh.yaml"),
                                   {"camera": {"frame": "camera_optical_frame"},
                                    "tags": {"items": [{"id": 1, "link": "tool0", "size": 0.04}]}})
    assert default_online_entries(cobot, {"tags"}) == []  # camera stand and arm both hang on the root
    assert default_online_entries(cobot, {"imu"}) == [{"name": "base_tilt", "location": "world"}]


def _tags(frame: str, stamp_ns: int, ids: list[int]) -> OnlineMeasurement:
    n = 5 * len(ids)
    payload = TagMeasurement(frame, np.repeat(ids, 5), np.tile(np.arange(5), len(ids)), np.full((n, 2), 0.01),
                             np.full((n, 2), 500.0), 900.0, 900.0)
    return OnlineMeasurement(stamp_ns, "/tag_bearing/observations", frame, payload=payload)


def test_bad_input_is_counted_and_named(camera_model):
    """A camera_info that changes, a tag seen by two cameras at the same instant, a temperature stream that
    stopped: each counted with a note naming what and where; the inputs keep working."""
    f = _filter(camera_model, TRACKED)
    inp = OnlineInputs(f, temperature_timeout_ns=10_000_000_000)
    K = np.diag([900.0, 900.0, 1.0])
    assert inp.camera_info("camera_optical_frame", K, np.zeros(5)) is None
    assert inp.camera_info("camera_optical_frame", K, np.zeros(5)) is None
    note = inp.camera_info("camera_optical_frame", np.diag([910.0, 900.0, 1.0]), np.zeros(5))
    assert note and "camera_optical_frame" in note and "fx 900 -> 910" in note
    assert inp.counts.camera_info_changed == 1
    t = 5_000_000_000
    temp = (t - 1_000_000, 30.0)
    first = inp.take(_tags("camera_optical_frame", t, [40, 41]), Q0, temp)
    second = inp.take(_tags("camera_link", t + 200_000, [41, 42]), Q0, temp)
    assert first is not None and second is not None
    assert [p.obs.dim for p in second.row.parts] == [10]  # tag 41 dropped from the second camera, 42 kept
    assert inp.counts.tags_seen_twice == 1
    assert any("tag(s) [41] seen by cameras ['camera_optical_frame'] and 'camera_link'" in n for _, n in inp.notes)
    stale = inp.take(_tags("camera_optical_frame", t + 30_000_000_000, [43]), Q0, temp)
    assert stale is not None and inp.counts.temperature_stale == 1
    assert any(k == "temperature_stale" and "30.0 s older" in n and "30.0 degC" in n for k, n in inp.notes)
    bad = inp.take(_tags("no_such_camera", t + 31_000_000_000, [43]), Q0, temp)
    assert bad is None and inp.counts.bad == 1 and "no_such_camera" in inp.notes[-1][1]


def test_an_added_effect_joins_the_state(camera_model):
    """``add_effects``: the state grows, labels follow, the old covariance is kept."""
    f = _filter(camera_model, [{"name": "base_tilt", "location": "world"}])
    P0 = f.P.copy()
    th = make_effect("thermal_growth", "elbow", f.tree, [1e-5], variable="temperature", reference=20.0)
    f.add_effects(parse_online_config([{"name": "thermal_growth", "location": "elbow", "variable": "temperature",
                                        "reference": 20.0, "parameters": {"alpha": 1e-5}}], camera_model))
    assert f.labels[-1] == "thermal_growth@elbow/alpha" and f.theta[-1] == pytest.approx(th.params[0])
    np.testing.assert_array_equal(f.P[:2, :2], P0)
    f.set_temperature(0.0, 40.0)
    rows = _thermal_window(camera_model, f, 1e-5, n=1)
    P1 = f.P.copy()
    f.update(rows[0], "tracker")
    assert f.P[2, 2] < P1[2, 2]  # the point informs the added alpha
