"""The diagnose engine's parts: block Jacobians against finite differences, the Schur-eliminated linear system
against a dense fit, the held-out protocol of a segment without training rows, the covariance routine and the
noise scales against seeded Monte Carlo, the selection's parsimony, ``--effects``, and the library call giving the
CLI's JSON.  Synthetic data made here (arm7)."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest
from conftest import BAGS, CONFIG
from jacobian_check import check_jacobian
from test_diagnose import POINT, _synthetic

from ppoe_core import lie
from ppoe_core.analysis.diagnose import DiagnoseOptions, PoseBlock, Problem, TrackerBlock, diagnose
from ppoe_core.analysis.diagnose.covariance import parameter_covariance
from ppoe_core.analysis.diagnose.linsys import LinearSystem, NuisanceSet
from ppoe_core.analysis.diagnose.noise import NoiseScales, estimate_scales
from ppoe_core.model.effects import make_effect
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf


@pytest.fixture(scope="module")
def robot():
    return parse_urdf(CONFIG / "robots" / "arm7.urdf")


def _effects(robot):
    rng = np.random.default_rng(3)
    return [make_effect("gravity_compliance", "joint_2", robot, [2e-4]),
            make_effect("lateral_compliance", "joint_3", robot, [1e-4, 2e-4]),
            make_effect("link_error", "joint_5", robot, rng.normal(0, 0.01, 6)),
            make_effect("mount_bending", "mount_joint", robot, [1e-4, -5e-5]),
            make_effect("backlash", "joint_4", robot, [0.003])]


def test_tracker_columns_and_registration_match_finite_differences(robot):
    """Derivative of the tracker prediction w.r.t. every effect's parameters and w.r.t. the registration's right
    perturbation (T0 Exp(d)), at a model with all of them non-zero."""
    tree = KinematicTree(robot)
    block = TrackerBlock(tree, _synthetic(robot, n=8, seed=1))
    effs = _effects(robot)
    lin = block.linearise(effs, effs, {}, {})
    for k, e in enumerate(effs):
        def predict(th, k=k):
            cur = list(effs)
            cur[k] = effs[k].with_params(th)
            return -block.linearise(cur, (), {}, {}).r
        check_jacobian(predict, e.params, lin.J[k], atol=1e-9, rtol=1e-6, eps=1e-7, err_msg=e.name)
    T0 = block.T0.copy()

    def predict_reg(d):
        block.T0 = T0.copy()
        block.apply_nuisance(np.tile(d, (len(T0), 1)))
        return -block.linearise(effs, (), {}, {}).r

    num = check_jacobian(predict_reg, np.zeros(6), lin.N, atol=1e-7, rtol=1e-6, err_msg="registration")
    assert np.abs(num).max() > 0.5
    block.T0 = T0


def test_pose_columns_match_finite_differences(robot):
    """6D pose block: position and rotation residual derivatives (the tool frame in base_link)."""
    tree = KinematicTree(robot)
    s = _synthetic(robot, n=6, seed=2)
    poses = tree.link_poses(s.q)
    s.kind, s.R_meas, s.p_meas, s.point = "pose", poses["tool0"][:, :3, :3], poses["tool0"][:, :3, 3], np.zeros(3)
    block = PoseBlock(tree, s)
    effs = _effects(robot)
    lin = block.linearise(effs, effs, {}, {})
    R0 = block._chain(effs)[1]
    for k, e in enumerate(effs):
        def predict(th, k=k):
            cur = list(effs)
            cur[k] = effs[k].with_params(th)
            x, R, _, _ = block._chain(cur)
            return np.concatenate([x, lie.so3_log(np.swapaxes(R0, -1, -2) @ R)], axis=1)
        check_jacobian(predict, e.params, lin.J[k], atol=1e-8, rtol=1e-5, eps=1e-7, err_msg=e.name)


def _random_system(rng, n_seg=4, m=12, C=3, k=2):
    """A linear system with ``n_seg`` segments of ``m`` components, ``C`` columns, ``k`` nuisances each."""
    n = n_seg * m
    G, e = rng.normal(size=(n, C)), rng.normal(size=n)
    seg = np.repeat(np.arange(n_seg), m)
    N = rng.normal(size=(n, k))
    unit = np.arange(n) // 3
    reg = np.tile(np.arange(m) < m // 2, n_seg)
    return LinearSystem(e, G, [slice(i, i + 1) for i in range(C)], unit, int(unit.max()) + 1,
                        np.zeros(n, dtype=int), reg, np.ones(n, dtype=bool),
                        [NuisanceSet(np.arange(n), N, seg, 0, n_seg)]), seg, N


def _dense(e, G, N, seg, rows):
    """Least squares of ``e`` on ``[G, N per segment]`` over ``rows``: the ``G`` coefficients."""
    segs = np.unique(seg[rows])
    A = np.concatenate([G[rows]] + [np.where((seg[rows] == s)[:, None], N[rows], 0.0) for s in segs], axis=1)
    return np.linalg.lstsq(A, e[rows], rcond=None)[0][:G.shape[1]]


def test_schur_fold_equals_the_dense_fit_and_held_out_protocol():
    """Training fit of a fold (nuisances eliminated per segment) = the dense fit with the nuisances; a held-out
    component of a segment with training rows uses that segment's training nuisance; a segment without training
    rows is registered on its reg rows and scored on the others."""
    rng = np.random.default_rng(4)
    sys, seg, N = _random_system(rng)
    cols = np.arange(3)
    train = ~((seg == 3) | ((seg == 0) & (np.arange(seg.size) % 5 == 0)))
    fold = sys.fold(train)
    th = fold.fit(cols, ridge=0.0)
    np.testing.assert_allclose(th, _dense(sys.e, sys.G, N, seg, np.flatnonzero(train)), rtol=1e-8)
    r = fold.heldout(cols, th)
    # segment 0's held-out rows: the nuisance of its training rows, with th fixed
    t0 = np.flatnonzero((seg == 0) & train)
    nu0 = np.linalg.lstsq(N[t0], sys.e[t0] - sys.G[t0] @ th, rcond=None)[0]
    for i, j in enumerate(fold.idx):
        if seg[j] == 0:
            assert r[i] == pytest.approx(sys.e[j] - sys.G[j] @ th - N[j] @ nu0)
    # segment 3 (no training rows): registered on its reg rows, scored on the others only
    reg3 = np.flatnonzero((seg == 3) & sys.reg)
    nu3 = np.linalg.lstsq(N[reg3], sys.e[reg3] - sys.G[reg3] @ th, rcond=None)[0]
    scored3 = [i for i, j in enumerate(fold.idx) if seg[j] == 3]
    assert {fold.idx[i] for i in scored3} == set(np.flatnonzero((seg == 3) & ~sys.reg))
    for i in scored3:
        j = fold.idx[i]
        assert r[i] == pytest.approx(sys.e[j] - sys.G[j] @ th - N[j] @ nu3)


def test_batched_segments_equal_the_dense_fit_with_an_inactive_column_and_an_undetermined_segment():
    """The segments' eliminations, batched per nuisance set (:class:`SegmentBatch`), give the dense least squares
    with a nuisance per segment: a segment whose second nuisance column is zero (a placement's tilt fixed by
    definition) keeps only its first; a segment with fewer components than nuisances is not determined (its
    components fit the effects alone, no nuisance); the nuisance step of a fit is each segment's least squares of
    its residual."""
    rng = np.random.default_rng(7)
    sys, seg, N = _random_system(rng, n_seg=5, m=10, C=3, k=2)
    N[seg == 1, 1] = 0.0  # inactive column in segment 1
    few = np.flatnonzero(seg == 4)[1:]  # segment 4 keeps one component: 2 nuisances undetermined
    keep = np.setdiff1d(np.arange(seg.size), few)
    e, G, N, seg = sys.e[keep], sys.G[keep], N[keep], seg[keep]
    n = seg.size
    sys = LinearSystem(e, G, sys.cols, np.arange(n) // 3, (n - 1) // 3 + 1, np.zeros(n, dtype=int),
                       np.ones(n, dtype=bool), np.ones(n, dtype=bool), [NuisanceSet(np.arange(n), N, seg, 0, 5)])
    cols = np.arange(3)
    th = sys.full().fit(cols, ridge=0.0)
    blocks = [np.where((seg == s)[:, None], N, 0.0)[:, [0] if s == 1 else [0, 1]] for s in range(4)]
    A = np.concatenate([G, *blocks], axis=1)
    x = np.linalg.lstsq(A, e, rcond=None)[0]
    np.testing.assert_allclose(th, x[:3], rtol=1e-8)
    step = sys.nuisance_step(th, cols)[0]
    r = e - G @ th
    for s in range(4):
        m = seg == s
        Ns = N[m][:, :1] if s == 1 else N[m]
        want = np.linalg.lstsq(Ns, r[m], rcond=None)[0]
        np.testing.assert_allclose(step[s, :want.size], want, rtol=1e-8, atol=1e-12)
    assert step[1, 1] == 0.0 and np.all(step[4] == 0.0)
    # the reduced cost: the dense residual's sum of squares
    full = sys.full()
    assert full.ee - float(th @ full.b) == pytest.approx(float(np.sum((e - A @ x) ** 2)), rel=1e-9)


def test_a_refit_at_its_minimum_takes_no_step(robot):
    """A refit started at its minimum stops at once: the undamped step is below the tolerance, so no trial is
    evaluated and the values stay exactly as they were (the solver's stopping rule, solver._small; before it, that
    step was taken and evaluated)."""
    truth = [make_effect("gravity_compliance", "joint_2", robot, [3e-4]),
             make_effect("link_error", "joint_5", robot, [0.004, -0.003, 0.002, 0.02, -0.015, 0.01])]
    tree = KinematicTree(robot)
    pr = Problem([TrackerBlock(tree, _synthetic(robot, truth, n=120, sessions=3, seed=5))])
    start = [make_effect("gravity_compliance", "joint_2", robot, [0.0]),
             make_effect("link_error", "joint_5", robot, np.zeros(6))]
    pr.system(start, start)  # the whitening
    fit = pr.refit(start)
    assert fit.converged and fit.iterations > 1
    for _ in range(5):  # (a refit that stopped on a negligible cost change may still take a step next time)
        prev, fit = fit, pr.refit(fit.effects)
        if fit.iterations == 1:
            break
    assert fit.converged and fit.iterations == 1
    for a, b in zip(prev.effects, fit.effects):
        np.testing.assert_array_equal(a.params, b.params)
    np.testing.assert_allclose(fit.effects[0].params, [3e-4], rtol=0.1)


def test_confidence_intervals_cover_monte_carlo(robot):
    """Seeded Monte Carlo of the one covariance routine (mount bending, 60 stops, registration eliminated): the
    95 % intervals cover the truth about 95 % of the time, in both kinds (s^2 H^-1 and the pose-clustered
    sandwich), and the spread of the estimates matches the reported sigma."""
    tree = KinematicTree(robot)
    truth = np.array([3e-5, 2e-5])
    hits: dict[bool, list[bool]] = {False: [], True: []}
    z = []
    for seed in range(50):
        st = _synthetic(robot, [make_effect("mount_bending", "mount_joint", robot, truth)], n=60, seed=100 + seed)
        st.imus = {}
        pr = Problem([TrackerBlock(tree, st)])
        fit = pr.refit([make_effect("mount_bending", "mount_joint", robot)])
        sys = pr.system(fit.effects, fit.effects, rewhiten=False)
        th = fit.effects[0].params
        for clustered in (False, True):
            sd = np.sqrt(np.diag(parameter_covariance(sys, np.arange(2), 12, clustered).cov))
            hits[clustered].extend(np.abs(th - truth) <= 1.96 * sd)
        z.extend((th - truth) / sd)
    for h in hits.values():  # 100 intervals each: 0.95 expected, binomial sd 0.022
        assert 0.88 <= np.mean(h) <= 1.0
    assert 0.8 < np.std(z) < 1.25


def test_noise_scales_monte_carlo():
    """Maximum-likelihood scales of C = a^2 S + k^2 Q recover (a, k) from residuals drawn with them; a prior that
    the data do not need is dropped (k = 0)."""
    rng = np.random.default_rng(5)
    n = 3000
    S = np.broadcast_to(np.eye(3) * 1e-8, (n, 3, 3)).copy()
    A = rng.normal(size=(n, 3, 3)) * 1e-3
    Q = A @ np.swapaxes(A, -1, -2)
    for a, k in [(2.0, 0.5), (0.7, 0.1)]:
        C = a * a * S + k * k * Q
        r = np.einsum("nij,nj->ni", np.linalg.cholesky(C), rng.normal(size=(n, 3)))
        got = estimate_scales(r, S, Q)
        assert got.a == pytest.approx(a, rel=0.08) and got.k == pytest.approx(k, rel=0.08), (a, k, got)
    r = np.einsum("nij,nj->ni", np.linalg.cholesky(S), rng.normal(size=(n, 3)))
    assert estimate_scales(r, S, Q, start=NoiseScales()).k == 0.0


def test_two_encoder_offsets_are_two_joint_offsets_not_a_link_error(robot):
    """Encoder offsets at joint_2 and joint_3: one link_error at joint_3 explains both (an upstream offset turns the
    downstream frame); the backward pass names the two one-parameter offsets, each with its truth in its CI."""
    truth = {"joint_2": 0.02, "joint_3": -0.03}
    effs = [make_effect("joint_offset", j, robot, [v]) for j, v in truth.items()]
    res = diagnose(robot, _synthetic(robot, effs, seed=21))
    named = sorted((e["name"], e["location"]) for e in res.to_json()["effects"])
    assert named == [("joint_offset", "joint_2"), ("joint_offset", "joint_3")], res.summary
    for e in res.to_json()["effects"]:
        assert e["ci"]["offset"][0] <= truth[e["location"]] <= e["ci"]["offset"][1]


def test_declared_effect_set_is_fitted_with_cis(robot):
    """--effects: the declared set is fitted (no selection) with CIs; an effect the measurements cannot see is
    left out with the reason."""
    eff = make_effect("gravity_compliance", "joint_2", robot, [2e-5])
    res = diagnose(robot, _synthetic(robot, [eff], seed=22), options=DiagnoseOptions(
        effects=["gravity_compliance@joint_2", "joint_offset@joint_4", "link_error@mount_joint[x,y,z]"]))
    doc = res.to_json()
    assert [(e["name"], e["location"]) for e in doc["effects"]] == [("joint_offset", "joint_4"),
                                                                     ("gravity_compliance", "joint_2")]
    g = doc["effects"][1]
    assert g["ci"]["compliance"][0] <= 2e-5 <= g["ci"]["compliance"][1]
    assert any(r["candidate"].startswith("link_error@mount_joint") for r in doc["rejected"])


def test_a_declared_thermal_growth_takes_the_variable_the_measurements_have(robot):
    """--effects thermal_growth@joint_3 on stops without a temperature: the measurements' own candidate (over time)
    is fitted; the effect is not built anew over a temperature that is not there (which failed, naming the missing
    context)."""
    eff = make_effect("gravity_compliance", "joint_2", robot, [2e-5])
    stops = _synthetic(robot, [eff], seed=23)
    res = diagnose(robot, stops, options=DiagnoseOptions(effects=["thermal_growth@joint_3"]))
    (e,) = res.found
    assert (e.name, e.location, e.variable) == ("thermal_growth", "joint_3", "time")


def test_library_and_cli_give_the_same_json(tmp_path):
    """``ppoe diagnose --json`` prints exactly the JSON of the library call diagnose_bags."""
    from ppoe_core.analysis.diagnose.files import diagnose_bags
    from ppoe_ros.cli import main

    bag, model = BAGS / "effect_joint_offset", CONFIG / "robots" / "arm7_model.yaml"
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(io.StringIO()):
        assert main(["diagnose", str(bag), "--model", str(model), "--json", "--test", str(BAGS / "no_effect")]) == 0
    lib = diagnose_bags([bag], model, [BAGS / "no_effect"]).result.to_json()
    assert json.loads(out.getvalue()) == json.loads(json.dumps(lib))
    assert lib["effects"][0]["name"] == "joint_offset" and "no_effect" in lib["test"]
    assert np.isfinite(POINT).all()


def test_the_same_bag_gives_the_same_json_in_every_process():
    """Two processes with different string hashes (``PYTHONHASHSEED``): the same JSON to the last digit.  The pose
    block once ordered the joints of its Jacobians by a set of names, so the structure tests (and the sums over
    joints) came out in another order per process (bags/contact: ``measurements.pose.structure``)."""
    import os
    import subprocess
    import sys

    from conftest import REPO

    docs = []
    for seed in ("1", "3"):
        env = {**os.environ, "PYTHONHASHSEED": seed, "PYTHONPATH": str(REPO)}
        out = subprocess.run([sys.executable, "-m", "ppoe_ros.cli", "diagnose", str(BAGS / "contact"), "--model",
                              str(CONFIG / "robots" / "humanoid_model.yaml"), "--json", "--quiet"],
                             env=env, capture_output=True, text=True, timeout=600, check=True)
        docs.append(json.loads(out.stdout))
    assert docs[0] == docs[1]
    assert docs[0]["measurements"]["pose"]["structure"], "no structure tests to compare"


def test_selection_on_a_linear_problem_names_the_true_column(robot):
    """``select_linear`` (the drift naming's entry, analysis/drift_naming.py): a whitened problem with free columns
    and one candidate's column in the data; the selection names exactly that candidate, with its drop-one gain."""
    from ppoe_core.analysis.diagnose import LinearProblem, select_linear

    tree = KinematicTree(robot)
    rng = np.random.default_rng(5)
    cands = [make_effect("joint_offset", f"joint_{k}", robot) for k in range(1, 7)]
    n = 240
    free = rng.normal(size=(n, 3))
    cols = [rng.normal(size=(n, 1)) for _ in cands]
    e = free @ np.array([1.0, -2.0, 0.5]) + 0.8 * cols[3][:, 0] + rng.normal(size=n)
    cluster = np.arange(n) // 2
    problem = LinearProblem(e, free, cands, cols, cluster, np.arange(n // 2) % 5, tree)
    sel = select_linear(problem)
    assert [(c.candidate, c.comps) for c in sel.chosen] == [(3, (0,))]
    assert sel.chosen[0].gain > 0.2 and sel.chosen[0].t > 4
    assert sel.chosen[0].effect.key == cands[3].key
