"""Effects that read a context (time, motion sign, temperature) in ``ppoe evaluate`` and the kinematics node.

A diagnosed model with ``thermal_growth`` against time or ``backlash`` used to be refused by ``ppoe evaluate``
and the nodes ("needs context 'time'"): the context now comes from the joint-state stream by the rules
``ppoe diagnose`` uses (``ppoe_core.model.context``).
"""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml
from conftest import BAGS, CONFIG_ROBOTS

from ppoe_core.errors import ModelConfigError
from ppoe_core.model.context import LiveContext, batch_context, motion_signs
from ppoe_core.model.ppoe import PPOEModel

URDF = CONFIG_ROBOTS / "arm7.urdf"
EFFECTS = [
    {"name": "thermal_growth", "location": "joint_3", "variable": "time", "reference": 0.0,
     "parameters": {"alpha": 2e-3}},
    {"name": "backlash", "location": "joint_2", "parameters": {"play": 0.01}},
]


def _model_yaml(tmp_path: Path, src: Path, effects: list) -> Path:
    doc = yaml.safe_load(src.read_text())
    doc["effects"] = effects
    out = tmp_path / f"{src.stem}_ctx.yaml"
    out.write_text(yaml.safe_dump(doc))
    return out


def _walk(rng: np.random.Generator, n: int, n_joints: int) -> tuple[np.ndarray, np.ndarray]:
    stamps = 100.0 + 0.05 * np.arange(n)
    Q = np.cumsum(rng.normal(0.0, 0.02, (n, n_joints)), axis=0)
    Q[5:9] = Q[4]  # a pause: the motion signs hold
    return stamps, Q


def test_live_context_equals_the_batch_context(tmp_path: Path) -> None:
    model = PPOEModel.from_files(URDF, _model_yaml(tmp_path, CONFIG_ROBOTS / "arm7_model.yaml", EFFECTS))
    stamps, Q = _walk(np.random.default_rng(3), 40, len(model.joint_names))
    batch = batch_context(model.effects, model.joint_names, stamps, Q, t0=stamps[0])
    live = LiveContext(model.effects, model.joint_names)
    assert live.needed == {"time", "motion_sign"}
    rows = [live.update(t, q) for t, q in zip(stamps, Q)]
    np.testing.assert_allclose([r["time"] for r in rows], batch["time"])
    for n in model.joint_names:
        np.testing.assert_array_equal([r["motion_sign"][n] for r in rows], batch["motion_sign"][n])
    # the signs follow the last step above the threshold and hold through the pause
    s = motion_signs(stamps, Q, stamps)
    assert np.all(s[5:9] == s[4]) and np.all(s[1:5] == np.sign(np.diff(Q[:5], axis=0)))
    # the FK of the batch equals the FK of each row with its own context (the node's way)
    T_b = model.fk_mean(Q, "base_link", "tool0", context=batch)
    live2 = LiveContext(model.effects, model.joint_names)
    T_l = np.stack([model.fk_mean(q, "base_link", "tool0", context=live2.update(t, q)) for t, q in zip(stamps, Q)])
    np.testing.assert_allclose(T_b, T_l, atol=1e-12)
    # the effects do act: without them the poses differ by millimetres
    T_0 = PPOEModel.from_files(URDF, CONFIG_ROBOTS / "arm7_model.yaml").fk_mean(Q, "base_link", "tool0")
    assert np.max(np.linalg.norm(T_b[:, :3, 3] - T_0[:, :3, 3], axis=1)) > 1e-3


def test_temperature_effect_needs_a_temperature(tmp_path: Path) -> None:
    eff = [{"name": "thermal_growth", "location": "joint_3", "variable": "temperature", "reference": 20.0,
            "parameters": {"alpha": 1e-4}}]
    model = PPOEModel.from_files(URDF, _model_yaml(tmp_path, CONFIG_ROBOTS / "arm7_model.yaml", eff))
    stamps, Q = _walk(np.random.default_rng(4), 5, len(model.joint_names))
    with pytest.raises(ModelConfigError, match="/temperature"):
        batch_context(model.effects, model.joint_names, stamps, Q, t0=stamps[0], where="bag b")
    series = SimpleNamespace(stamps=np.array([99.0, 101.0]), temperature=np.array([20.0, 30.0]))
    ctx = batch_context(model.effects, model.joint_names, stamps, Q, t0=stamps[0],
                        temperatures={"/temperature": series})
    np.testing.assert_allclose(ctx["temperature"], np.interp(stamps, [99.0, 101.0], [20.0, 30.0]))
    live = LiveContext(model.effects, model.joint_names)
    with pytest.raises(ModelConfigError, match="no /temperature"):
        live.update(stamps[0], Q[0])
    live.temperature = 25.0
    assert live.update(stamps[1], Q[1])["temperature"] == 25.0


def test_evaluate_takes_a_model_with_time_and_motion_effects(tmp_path: Path, capsys) -> None:
    """``ppoe evaluate`` of a diagnosed-style model with thermal growth against time and backlash: it runs, the
    effects change the FK error, and with zero parameters the result equals the model without them."""
    from ppoe_ros.cli import main

    rover = CONFIG_ROBOTS / "rover_model.yaml"
    effects = [dict(e, location=loc) for e, loc in zip(EFFECTS, ("arm_joint_3", "arm_joint_2"))]
    zero = [dict(e, parameters={k: 0.0 for k in e["parameters"]}) for e in effects]
    docs = {}
    for name, eff in (("none", None), ("zero", zero), ("effects", effects)):
        (tmp_path / name).mkdir()
        model = rover if eff is None else _model_yaml(tmp_path / name, rover, eff)
        assert main(["evaluate", str(BAGS / "table1_exp1"), "--model", str(model), "--json", "--no-progress"]) == 0
        docs[name] = json.loads(capsys.readouterr().out)
    fk = {k: d["methods"]["fk"]["position_3d"]["rms"] for k, d in docs.items()}
    assert fk["zero"] == fk["none"]
    assert abs(fk["effects"] - fk["none"]) > 1e-4, fk


@pytest.mark.ros
def test_kinematics_node_applies_time_and_motion_effects_live(tmp_path: Path) -> None:
    """The kinematics node with such a model: every pose equals the model's FK with the context of the joint
    states so far (time since the first joint state, each joint's last motion sign)."""
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from ros_helpers import NodeProcess, Probe, ros_env, write_params_file
    from sensor_msgs.msg import JointState

    from ppoe_ros.common import ns_to_stamp, pose_cov_from_msg

    model_yaml = _model_yaml(tmp_path, CONFIG_ROBOTS / "arm7_model.yaml", EFFECTS)
    model = PPOEModel.from_files(URDF, model_yaml)
    stamps, Q = _walk(np.random.default_rng(5), 15, len(model.joint_names))
    env = ros_env(tmp_path)
    pf = write_params_file(tmp_path / "p.yaml", {
        "robot_description": URDF.read_text(), "model_file": str(model_yaml), "joint_states_reliable": True,
        "log_throttle": 0.0})
    with Probe(env) as probe, NodeProcess.node("kinematics_node", env, tmp_path, params_file=pf) as proc:
        js = probe.publisher("/joint_states", JointState, 100)
        out = probe.collect("/ppoe/pose", PoseWithCovarianceStamped)
        probe.wait_for_subscribers(js, proc)
        for t, q in zip(stamps, Q):
            msg = JointState(name=list(model.joint_names), position=[float(v) for v in q])
            msg.header.stamp = ns_to_stamp(int(round(t * 1e9)))
            js.publish(msg)
            probe.spin_for(0.02)
        probe.spin_until(lambda: len(out) >= len(stamps), 20, proc, f"{len(stamps)} poses")
    live = LiveContext(model.effects, model.joint_names)
    T_0 = PPOEModel.from_files(URDF, CONFIG_ROBOTS / "arm7_model.yaml")
    moved = 0.0
    for t, q, msg in zip(stamps, Q, out):
        ctx = live.update(round(t * 1e9) * 1e-9, q)
        T_ref = model.fk_mean(q, "base_link", "tool0", context=ctx)
        np.testing.assert_allclose(pose_cov_from_msg(msg)[0], T_ref, atol=1e-12)
        moved = max(moved, float(np.linalg.norm(T_ref[:3, 3] - T_0.fk_mean(q, "base_link", "tool0")[:3, 3])))
    assert moved > 1e-3  # the effects act on the published poses


def test_a_chain_without_the_effect_needs_no_context(tmp_path: Path) -> None:
    """Measurement models ask for chains the arm's effects are not on (the fixed camera; tool -> tool): those need
    no context; the arm's chain without one is refused with the effect and the key named."""
    model = PPOEModel.from_files(URDF, _model_yaml(tmp_path, CONFIG_ROBOTS / "arm7_model.yaml", EFFECTS))
    plain = PPOEModel.from_files(URDF, CONFIG_ROBOTS / "arm7_model.yaml")
    q = np.full(len(model.joint_names), 0.3)
    for frm, to in (("base_link", "camera_optical_frame"), ("tool0", "tool0")):
        T, cov = model.fk(q, frm, to)
        T0, cov0 = plain.fk(q, frm, to)
        np.testing.assert_allclose(T, T0, atol=1e-15)
        np.testing.assert_allclose(cov, cov0, atol=1e-18)
    with pytest.raises(ModelConfigError, match="needs context"):
        model.fk(q, "base_link", "tool0")
