"""``ppoe plan`` measured, not only predicted (issue 26's Must-show, on ONE robot here; the three-robot study is
``bench/bench_plan.py``, its numbers in docs/plan.md): plan N poses, simulate them and random feasible poses
(``ppoe simulate`` with ``trajectory.stops_csv``), diagnose each bag with the declared effects (``ppoe diagnose
--effects``) and compare the achieved 95 % intervals.  Uses bench/bench_plan.py's functions (one implementation of
planning, simulating and diagnosing a study)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, load_script

bench = load_script(REPO / "bench" / "bench_plan.py", "bench_plan")

#: the achieved half-width of one bag of 12 poses (36 residuals) scatters by about 13 % (chi-square with ~27 degrees
#: of freedom); a parameter the plan predicts tighter by this much is measured tighter (mean of two bags)
CLEARLY_TIGHTER = 0.85
#: predicted within 20 % of achieved (issue 26)
PREDICTION_TOL = 0.20


@pytest.fixture(scope="module")
def work(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("plan_roundtrip")


def test_planned_poses_as_tight_as_four_times_as_many_random_ones(work: Path) -> None:
    """cobot6 in its cell region: 12 planned poses vs 48 random feasible ones, both simulated and diagnosed.

    Judged as the D-criterion states it: the joint confidence region (the geometric mean of the achieved
    half-widths) at least as tight as with 4N random poses; per parameter, every one the plan predicts clearly
    tighter than 4N random is measured tighter (the shoulder offset is not one: D-optimality trades it for the
    elbow pair, docs/plan.md); every predicted half-width within 20 % of the achieved one.  And ``--criterion
    minimax`` lowers the worst predicted planned / random-4N ratio below the D-optimal plan's (1.07, the shoulder
    offset) to at most 1.02 (the best any 12 poses of the pool give that offset alone is 0.99, docs/plan.md)."""
    res = bench.run_study(bench.STUDIES["cobot6"], repeats=2, sets=("planned", "random_4n"), work=work)
    bench.print_study(res)
    ratios = []
    for name, r in res["parameters"].items():
        assert abs(r["predicted"] / r["planned"] - 1.0) <= PREDICTION_TOL, (name, r)
        ratios.append(r["planned_over_random_4n"])
        if r["predicted"] <= CLEARLY_TIGHTER * r["predicted_random_4n"]:
            assert r["planned"] < r["random_4n"], (name, r)
    assert sum(r["predicted"] <= CLEARLY_TIGHTER * r["predicted_random_4n"] for r in res["parameters"].values()) >= 2
    assert float(np.exp(np.mean(np.log(ratios)))) <= 1.0, ratios
    study = bench.STUDIES["cobot6"]

    def worst(doc: dict) -> float:
        return max(doc["planned"]["ci95"][p] / doc["random_4n"]["ci95"][p] for p in doc["parameters"])

    import json
    mm = json.loads(bench.ppoe(["plan", "--urdf", str(bench.urdf_of(study, work / "cobot6")), "--model",
                                str(study.model), "--effects", str(study.effects), "--n", str(study.n), "--out",
                                str(work / "cobot6_minimax"), "--json", "--criterion", "minimax", *study.plan_args]))
    d_only = json.loads((work / "cobot6" / "plan" / "plan.json").read_text())
    assert worst(mm) < worst(d_only) and worst(mm) <= 1.02, (worst(mm), worst(d_only))
    assert mm["design"]["minimax_exchanges"] > 0 and d_only["design"]["minimax_exchanges"] == 0


def test_information_bound_shows_where_4n_random_cannot_be_matched(work: Path) -> None:
    """lift5 (whole ranges): the j3 offset's information bound (no 12 poses of the pool can give it less) is wider
    than the 4N-random median's predicted half-width, and the plan, with either criterion, is no tighter than the
    bound; the parameters whose bound is below 1 are the ones a plan can still win."""
    import json

    study = bench.STUDIES["lift5"]
    for crit in ("d", "minimax"):
        doc = json.loads(bench.ppoe(["plan", "--urdf", str(bench.urdf_of(study, work)), "--model", str(study.model),
                                     "--effects", str(study.effects), "--n", str(study.n), "--out",
                                     str(work / f"lift5_{crit}"), "--json", "--criterion", crit, *study.plan_args]))
        bound, over = doc["information_bound"]["ci95"], doc["information_bound"]["over_random_4n"]
        assert over["joint_offset@j3:offset"] > 1.0, over
        for p, h in doc["planned"]["ci95"].items():
            assert h >= bound[p] * (1 - 1e-9), (p, h, bound[p])
        assert doc["planned"]["ci95"]["joint_offset@j3:offset"] > doc["random_4n"]["ci95"]["joint_offset@j3:offset"]


def test_planned_poses_separate_what_random_poses_cannot(work: Path) -> None:
    """An elbow offset (-0.9 mrad) and a small elbow gravity compliance (2.5e-5 rad/(N m)) in a narrow workspace:
    with 12 random poses at least one interval holds zero (not separated); with 12 planned poses both exclude
    zero and hold the truth."""
    res = bench.run_study(bench.STUDIES["cobot6_pair"], repeats=1, sets=("planned", "random_n"), work=work)
    bench.print_study(res)
    truth = {"joint_offset@elbow:offset": -0.0009, "gravity_compliance@elbow:compliance": 2.5e-5}
    par = res["parameters"]
    for name, r in par.items():
        v, h = r["values"]["planned"], r["planned"]
        assert abs(v) > h, (name, r)                          # zero outside the planned interval
        assert abs(v - truth[name]) <= h, (name, r)           # the truth inside
    assert any(abs(r["values"]["random_n"]) <= r["random_n"] for r in par.values()), par


def test_diagnose_reports_achieved_next_to_planned(work: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``ppoe diagnose --planned plan.json``: key ``planned`` with planned, achieved (the effects' ``ci``) and the
    ratio per planned parameter; a file that is no plan is a clear error."""
    import json

    from ppoe_ros.cli import main

    study = bench.STUDIES["cobot6"]
    base = work / "cobot6"
    if not (base / "planned_0_bag").is_dir():
        bench.run_study(study, repeats=1, sets=("planned",), work=work)
    argv = ["diagnose", str(base / "planned_0_bag"), "--model", str(study.model), "--effects", str(study.effects),
            "--quiet", "--json", "--planned"]
    assert main([*argv, str(base / "plan" / "plan.json")]) == 0
    doc = json.loads(capsys.readouterr().out)
    cmp = doc["planned"]
    assert set(cmp) == set(json.loads((base / "plan" / "plan.json").read_text())["parameters"])
    for e in doc["effects"]:
        for p, (lo, hi) in e["ci"].items():
            r = cmp[f"{e['name']}@{e['location']}:{p}"]
            assert r["achieved"] == pytest.approx((hi - lo) / 2)
            assert r["ratio"] == pytest.approx(r["achieved"] / r["planned"])
            assert abs(r["ratio"] - 1.0) <= PREDICTION_TOL
    bad = work / "not_a_plan.json"
    bad.write_text("{}")
    assert main([*argv, str(bad)]) == 2
    assert "not a ppoe plan plan.json" in capsys.readouterr().err


def test_prediction_with_tag_pixels_in_the_design(work: Path) -> None:
    """cobot6 with the side camera: tracker and tag pixels in the design (the camera pose a nuisance, fitted by the
    diagnosis too); every predicted half-width within 20 % of the achieved one."""
    res = bench.run_study(bench.STUDIES["cobot6_camera"], repeats=1, sets=("planned",), work=work)
    bench.print_study(res)
    for name, r in res["parameters"].items():
        assert abs(r["predicted"] / r["planned"] - 1.0) <= PREDICTION_TOL, (name, r)
