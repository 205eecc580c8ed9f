"""The covariance check (``covariance_check.py``) and ``ppoe evaluate --perturbations / --global-scale``
(``analysis/evaluate/perturbation_compare.py``): metrics against hand-computed values, and the comparison replay on
a shipped bag (a choice equal to the declared one gives the declared numbers; a global scale k divides the FK NEES by
about k^2)."""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest
from conftest import BAGS, CONFIG
from scipy.stats import chi2, norm

from ppoe_core.analysis.diagnose.covariance_check import check_covariance, compare_choices, size_regions
from ppoe_core.analysis.evaluate.perturbation_compare import variant_doc


def test_check_of_known_rows():
    rng = np.random.default_rng(3)
    n = 20000
    C = np.broadcast_to(np.diag([1.0, 4.0, 9.0]), (n, 3, 3)).copy()
    r = rng.normal(size=(n, 3)) * np.array([1.0, 2.0, 3.0])
    ok = check_covariance(r, C)
    assert ok.nees == pytest.approx(3.0, rel=0.03)
    for lvl, cov in ok.coverage.items():
        assert cov == pytest.approx(float(lvl), abs=0.01)
    np.testing.assert_allclose(ok.nees_per_axis, 1.0, atol=0.04)
    # a covariance too thin along its largest axis (3 -> 1.5): that axis's NEES is 4, the others stay 1
    thin = C.copy()
    thin[:, 2, 2] = 1.5 ** 2
    bad = check_covariance(r, thin)
    assert bad.nees_per_axis[1] == pytest.approx(4.0, rel=0.05)  # eigenvalues sorted: 1, 2.25, 4
    assert bad.coverage_per_axis[1]["0.95"] == pytest.approx(2 * norm.cdf(1.96 / 2) - 1, abs=0.01)
    # log-likelihood per row against scipy's
    from scipy.stats import multivariate_normal

    want = multivariate_normal(np.zeros(3), C[0]).logpdf(r[:100]).mean()
    assert check_covariance(r[:100], C[:100]).loglik == pytest.approx(want, rel=1e-10)
    # regions: terciles of the reference size
    reg = size_regions(np.arange(1, 10)[:, None, None] * np.eye(3))
    assert list(reg) == [0, 0, 0, 1, 1, 1, 2, 2, 2]
    both = compare_choices(r, {"right": C, "thin": thin}, reference="right")
    assert len(both["thin"].nees_per_region) == 3
    assert chi2.ppf(0.68, 3) > 3.0  # the 68 % ellipsoid is the chi-square quantile, not the mean


def test_variant_doc_scales_and_replaces():
    model = {"perturbations": {"a": {"sigma": [0, 0, 0, 1e-3, 1e-3, 2e-3]}, "b": {"covariance": np.eye(6).tolist()}},
             "joint_noise": {"a": 1e-3}, "tags": {"x": 1}}
    v = variant_doc(model, scale=3.0)
    assert v["perturbations"]["a"]["sigma"] == pytest.approx([0, 0, 0, 3e-3, 3e-3, 6e-3])
    assert v["perturbations"]["b"]["covariance"][0][0] == pytest.approx(9.0)
    assert v["joint_noise"]["a"] == pytest.approx(3e-3) and v["tags"] == {"x": 1}
    assert model["perturbations"]["a"]["sigma"][3] == 1e-3  # the input is not changed
    other = variant_doc(model, {"perturbations": {"b": {"sigma": [0.0] * 6}}})
    assert other["perturbations"] == {"b": {"sigma": [0.0] * 6}} and other["joint_noise"] == {}


def _evaluate(args):
    from ppoe_ros.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["evaluate", *args]) == 0
    return out.getvalue()


def test_evaluate_compares_the_choices(tmp_path):
    bag, model = BAGS / "table1_exp1", CONFIG / "robots" / "rover_model.yaml"
    if not bag.exists():
        pytest.fail(f"shipped bag {bag} is missing (bags/make_bags.sh regenerates it)")
    same = tmp_path / "same.yaml"
    same.write_text(model.read_text())
    doc = json.loads(_evaluate([str(bag), "--model", str(model), "--json", "--quiet", "--perturbations", str(same),
                                "--global-scale", "2"]))
    cmp = doc["perturbation_comparison"]
    assert list(cmp) == ["declared", "same.yaml", "global x 2"]
    d, s, g = cmp["declared"], cmp["same.yaml"], cmp["global x 2"]
    assert s["ppoe"]["position_3d"]["rms"] == pytest.approx(d["ppoe"]["position_3d"]["rms"], rel=1e-12)
    assert s["fk"]["nees"]["mean"] == pytest.approx(d["fk"]["nees"]["mean"], rel=1e-12)
    # the FK mean is the same, its covariance 4x: NEES about a quarter (second-order terms aside)
    assert g["fk"]["position_3d"]["rms"] == pytest.approx(d["fk"]["position_3d"]["rms"], rel=1e-12)
    assert g["fk"]["nees"]["mean"] == pytest.approx(d["fk"]["nees"]["mean"] / 4.0, rel=0.1)
    assert set(d["fk"]["coverage"]) == {"0.68", "0.95", "0.99"}
    table = _evaluate([str(bag), "--model", str(model), "--quiet", "--global-scale", "2"])
    assert "| declared |" in table and "| global x 2 |" in table
