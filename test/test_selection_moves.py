"""Moves of the one selection routine (``ppoe_core/analysis/diagnose/selection.py``).

**Exchanges.** A term that entered ahead of an equal rival is exchanged for it when, at the final residual, the
rival explains the held-out data better (penalised ``L`` lower): on panda7 (``test/data/selection``, the robot in
``bench/scenarios_holdout/robots``) a sideways bend of j4 ties at the first step with j3's torsion, which explains
almost the same error with one parameter fewer. Without the exchange the diagnosis named ``gravity_compliance@j3``
(0.0963 mm held out against a 0.0866 mm noise floor); with it, ``lateral_compliance@j4`` (0.0878 mm).

**Splitting.** A term is split into parameter subsets only where a subset is itself an effect.

A candidate that is not identifiable as a whole is reduced to the components that are (``selection._reduce``), and
the backward pass tries each parameter less (``Catalogue.simpler``).  Both may only do it for effects that take
``components``: a ``base_tilt`` (tilt_x, tilt_y) or a gravity compliance enters whole or not at all.  Before
``Catalogue.splittable`` the reduction built a one-axis ``base_tilt`` and ``ppoe diagnose`` stopped with a
``TypeError`` traceback (a joint offset and a base tilt on a 6-axis arm, after an exchange move).
"""

from __future__ import annotations

import pytest
from conftest import CONFIG
from test_diagnose import _synthetic

from ppoe_core.analysis.diagnose.candidates import candidate_effects
from ppoe_core.analysis.diagnose.terms import Catalogue, Term
from ppoe_core.model.effects import make_effect
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf


@pytest.fixture(scope="module")
def catalogue() -> Catalogue:
    robot = parse_urdf(CONFIG / "robots" / "arm7.urdf")
    tree = KinematicTree(robot)
    stops = _synthetic(robot, n=40)
    # the accelerometer block's own candidate (block_imu.ImuBlock.candidates): the constant base tilt
    return Catalogue(tree, [*candidate_effects(tree, stops), make_effect("base_tilt", robot.root, tree)],
                     chains=["tool0"])


def test_every_kind_is_in_the_catalogue(catalogue):
    kinds = {e.name for e in catalogue.effects}
    assert {"base_tilt", "joint_offset", "link_error", "gravity_compliance", "lateral_compliance"} <= kinds, kinds


def test_a_subset_is_built_exactly_where_the_term_is_splittable(catalogue):
    split, whole = set(), set()
    for cand, e in enumerate(catalogue.effects):
        term = catalogue.full(cand)
        if len(term.comps) < 2:
            continue
        sub = Term(cand, term.comps[:-1])
        if catalogue.splittable(term):
            eff = catalogue.effect(sub)  # builds: the subset is an effect
            assert eff.n_params == len(sub.comps)
            split.add(e.name)
        else:
            with pytest.raises(TypeError):
                catalogue.effect(sub)  # what the selection must never ask for
            whole.add(e.name)
            assert catalogue.simpler(term) == [], e.key  # the backward pass never offers one either
    assert {"link_error", "lateral_compliance"} <= split and "base_tilt" in whole, (split, whole)


def test_a_term_is_exchanged_for_its_better_rival(tmp_path):
    """Diagnosed through the scenario bench (one implementation of making the bag, diagnosing and judging)."""
    from conftest import REPO, load_script

    # a copy of its own: its SETS gets one more set (test_engine_scenarios parametrizes over the module's)
    bench = load_script(REPO / "bench" / "bench_engine_scenarios.py", "bench_engine_scenarios_selection")
    bench.SETS["selection"] = REPO / "test" / "data" / "selection"
    row = bench.run("selection", "lateral_alias", tmp_path)
    assert row.verdict.named and not row.verdict.extra, (row.verdict.missing, row.verdict.extra)
    assert row.residual_after <= bench.FLOOR_FACTOR * row.floor
    steps = [s for s in row.doc["steps"] if s["action"] == "exchange"]
    assert [s["move"] for s in steps] == ["gravity_compliance@j3 -> lateral_compliance@j4"], row.doc["steps"]
