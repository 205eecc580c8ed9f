"""A direction the measurements cannot see where every effect is zero is not admitted because other parameters'
values make it seem visible: a reflector on the tool's y axis cannot see a rotation of the tool about that axis,
but next to a fitted ``link_error`` translation ``z`` the rotation ``ry`` moves the reflector along x
(``Exp([rho, omega])`` translates by ``V(omega) rho``), so the linear identifiability test at that point alone
admitted ``[z, ry]`` (and ``ppoe diagnose`` once reported ``ry = 0.57 rad`` with a finite interval).  Synthetic
tracker points of arm7's tool0 (made here)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import CONFIG

from ppoe_core import lie
from ppoe_core.analysis.diagnose import DiagnoseOptions, Problem
from ppoe_core.analysis.diagnose.crossval import assign_folds
from ppoe_core.analysis.diagnose.engine import Measurements, Run, build_blocks, catalogue_of
from ppoe_core.analysis.diagnose.selection import SelectionOptions, Selector
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.analysis.diagnose.terms import Term
from ppoe_core.robot.tree import KinematicTree
from ppoe_core.robot.urdf import parse_urdf

#: the declared reflector on tool0: on its y axis
DECLARED = np.array([0.0, 0.08, 0.0])
#: where it truly is: 0.8 mm further along z (a translation the engine should find as link_error z)
TRUE = np.array([0.0, 0.08, 0.0008])
SIGMA = 5e-5


def _run() -> Run:
    robot = parse_urdf(CONFIG / "robots" / "arm7.urdf")
    tree = KinematicTree(robot)
    rng = np.random.default_rng(21)
    n = 120
    q = {j: rng.uniform(-1.2, 1.2, n) for j in tree.joint_names if robot.joints[j].type != "prismatic"}
    q.update({j: np.full(n, 0.01) for j in tree.joint_names if robot.joints[j].type == "prismatic"})
    x = (tree.link_poses(q)["tool0"] @ np.append(TRUE, 1.0))[:, :3]
    T = lie.from_xyz_rpy([2.0, -1.0, 0.4], [0.0, 0.0, 0.7])
    p = x @ T[:3, :3].T + T[:3, 3] + rng.normal(0.0, SIGMA, x.shape)
    stops = Stops(q=q, p_meas=p, kind="point", link="tool0", point=DECLARED, sigma=SIGMA,
                  session=np.zeros(n, dtype=int), session_names=["s0"], group=np.zeros(n, dtype=int),
                  group_names=["synthetic"], reg_mask=np.ones(n, dtype=bool), score_mask=np.ones(n, dtype=bool),
                  context={"time": np.arange(n) * 5.0}, base=robot.root)
    options = DiagnoseOptions()
    blocks = build_blocks(tree, Measurements(stops=stops), [], options)
    problem = Problem(blocks)
    unit_group = np.zeros(problem.n_units, dtype=int)
    _, unit_fold = assign_folds(unit_group, "stops", options.folds, options.seed)
    return Run(problem, catalogue_of(tree, blocks, options), unit_fold)


def test_a_rotation_about_the_axis_through_the_reflector_is_not_admitted_next_to_a_translation() -> None:
    run = _run()
    cat = run.catalogue
    cand = next(i for i, e in enumerate(cat.effects) if e.name == "link_error" and e.location == "tool_joint")
    names = cat.effects[cand].param_names
    x, z, ry = names.index("x"), names.index("z"), names.index("ry")
    run.relinearise(())
    lin = run.relinearise((Term(cand, (z,)),))
    assert run.values[cand][z] == pytest.approx(TRUE[2] - DECLARED[2], abs=5e-5)  # the translation is found
    # at this point ry's column is a multiple of x's: the linear test alone would take it
    sel = Selector(cat, run, SelectionOptions())
    sel.lin = lin
    idf = lin.identifiable((), [Term(cand, (z, ry))], 1e6, 0.999)
    assert not idf.ok and "effects are zero" in idf.reason
    assert sel.admissible((), Term(cand, (z, ry))) == Term(cand, (z,))
    assert sel.admissible((), Term(cand, tuple(range(6)))) is not None
    assert ry not in sel.admissible((), Term(cand, tuple(range(6)))).comps  # type: ignore[union-attr]
    # what the reflector does see stays identifiable
    assert lin.identifiable((), [Term(cand, (x, z))], 1e6, 0.999).ok
