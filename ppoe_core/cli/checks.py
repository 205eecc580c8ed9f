"""Input checks of the ``ppoe`` subcommands, made before any work (issue 25).

* **Numbers**: argparse ``type=`` callables that refuse, at parse time, a value outside its allowed range, NaN
  and infinity (:func:`int_range`, :func:`float_range`; argparse turns the message into
  ``ppoe diagnose: error: argument --folds: must be an integer >= 2, got '1'`` and exit code 2).
* **diagnose's inputs** (:func:`check_diagnose_inputs`, called first in ``ppoe diagnose``): ``--out`` checked
  and locked (:mod:`ppoe_core.cli.output`); every fit and
  ``--test`` bag opens as a bag, none is given twice (by path, or as a copy of the same recording), no fit bag
  is also a test bag, and the fit bags carry the same robot: the same joints, types, parents, children,
  origins, axes and mimics on ``/robot_description`` (the fit uses the first bag's URDF for all of them); the
  ``--test`` bags the same joints, types, parents and children (as ``check_same_robot`` later checks them).
* **online config** (:func:`check_online_entries`): the numbers of ``online_effects`` entries, naming the file.
"""

from __future__ import annotations

import argparse
import hashlib
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.errors import BagError, ModelConfigError

__all__ = [
    "check_diagnose_inputs",
    "check_online_entries",
    "float_range",
    "int_range",
    "robot_differences",
]

#: joint origins and axes further apart than this [m, rad, unit vector] are another robot
GEOMETRY_TOLERANCE = 1e-9
#: messages hashed from the start of a bag to recognise the same recording under another path
FINGERPRINT_MESSAGES = 50
#: differences named in one message
NAMED_AT_MOST = 5


def _bound_text(minimum: float | None, maximum: float | None, min_open: bool, max_open: bool) -> str:
    parts = []
    if minimum is not None:
        parts.append(f"{'>' if min_open else '>='} {minimum:g}")
    if maximum is not None:
        parts.append(f"{'<' if max_open else '<='} {maximum:g}")
    return " and ".join(parts)


def int_range(minimum: int | None = None, maximum: int | None = None) -> Callable[[str], int]:
    """argparse ``type=``: an integer in ``[minimum, maximum]`` (either bound optional)."""
    bounds = _bound_text(minimum, maximum, False, False)

    def parse(text: str) -> int:
        try:
            value = int(text.strip())
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer{' ' + bounds if bounds else ''}, "
                                             f"got {text!r}") from None
        if (minimum is not None and value < minimum) or (maximum is not None and value > maximum):
            raise argparse.ArgumentTypeError(f"must be an integer {bounds}, got {text!r}")
        return value

    parse.__name__ = "integer"
    return parse


def float_range(minimum: float | None = None, maximum: float | None = None, *, min_open: bool = False,
                max_open: bool = False) -> Callable[[str], float]:
    """argparse ``type=``: a finite number in the range (``min_open`` / ``max_open``: bound excluded)."""
    bounds = _bound_text(minimum, maximum, min_open, max_open)

    def parse(text: str) -> float:
        try:
            value = float(text.strip())
        except ValueError:
            value = math.nan
        below = minimum is not None and (value <= minimum if min_open else value < minimum)
        above = maximum is not None and (value >= maximum if max_open else value > maximum)
        if not math.isfinite(value) or below or above:
            raise argparse.ArgumentTypeError(f"must be a finite number{' ' + bounds if bounds else ''}, "
                                             f"got {text!r}")
        return value

    parse.__name__ = "number"
    return parse


# ----------------------------------------------------------------------------- diagnose's bags


def _joint_signature(joint: Any) -> dict[str, Any]:
    return {"type": joint.type, "parent": joint.parent, "child": joint.child,
            "origin": np.asarray(joint.origin, float), "axis": np.asarray(joint.axis, float),
            "mimic": joint.mimic_root}


def _vec(v: Any) -> str:
    return "[" + ", ".join(f"{x:.6g}" for x in np.asarray(v, float).ravel()) + "]"


def robot_differences(a: Any, b: Any, geometry: bool = True) -> list[str]:
    """How robot ``b`` differs from robot ``a`` (parsed URDFs), as phrases, e.g. ``"joints only in the fitted
    robot: ['joint_7']"`` or ``"joint_3: origin xyz [0, 0, 0.4] vs [0, 0, 0.5]"``; empty for the same robot.

    ``geometry=False`` compares only the joints, their types, parents and children."""
    only_a, only_b = sorted(set(a.joints) - set(b.joints)), sorted(set(b.joints) - set(a.joints))
    out = ([f"joints only in the fitted robot: {only_a[:NAMED_AT_MOST]}"] if only_a else []) \
        + ([f"joints only in this bag: {only_b[:NAMED_AT_MOST]}"] if only_b else [])
    for name in sorted(set(a.joints) & set(b.joints)):
        sa, sb = _joint_signature(a.joints[name]), _joint_signature(b.joints[name])
        for key in ("type", "parent", "child") + (("mimic",) if geometry else ()):
            if sa[key] != sb[key]:
                out.append(f"{name}: {key} {sa[key]!r} vs {sb[key]!r}")
        if not geometry:
            continue
        for key, value_a, value_b in (("origin xyz", sa["origin"][:3, 3], sb["origin"][:3, 3]),
                                      ("origin rotation", sa["origin"][:3, :3], sb["origin"][:3, :3]),
                                      ("axis", sa["axis"], sb["axis"])):
            if not np.allclose(value_a, value_b, rtol=0.0, atol=GEOMETRY_TOLERANCE):
                shown = f" {_vec(value_a)} vs {_vec(value_b)}" if key != "origin rotation" else ""
                out.append(f"{name}: {key}{shown}")
    return out


def _fingerprint(bag: str) -> str | None:
    """Topic counts and a hash of the first messages: equal for copies of one recording (None: unreadable)."""
    from ppoe_core.errors import PpoeError
    from ppoe_core.io.bagio import bag_topics, iter_raw

    h = hashlib.sha1(repr(sorted(bag_topics(bag).items())).encode())
    try:
        for k, raw in enumerate(iter_raw(bag)):
            if k >= FINGERPRINT_MESSAGES:
                break
            h.update(f"{raw.topic}{raw.stamp_ns}".encode())
            h.update(bytes(raw.data))
    except PpoeError:
        return None  # damaged: read_bag says how, later
    return h.hexdigest()


def _robot_of(bag: str) -> Any:
    from ppoe_core.io.bagio import read_bag
    from ppoe_core.robot.urdf import parse_urdf

    urdf = read_bag(bag, topics=["/robot_description"], load_images=False).robot_description
    if not urdf:
        raise BagError(f"bag {bag}: no /robot_description")
    return parse_urdf(urdf, text_source=f"bag {bag} /robot_description")


def _check_no_repeats(fit: Sequence[str], test: Sequence[str]) -> None:
    """The same bag (path, or a copy of the same recording) twice among fit and test bags is an error."""
    seen: dict[str, tuple[str, str]] = {}
    for role, bag in [("fit", b) for b in fit] + [("--test", b) for b in test]:
        for key in (f"path:{Path(bag).resolve()}", f"recording:{_fingerprint(bag)}"):
            if key.endswith(":None"):
                continue
            if key in seen:
                other_role, other = seen[key]
                how = "given twice" if key.startswith("path") else f"the same recording as bag {other}"
                if "--test" in (role, other_role) and role != other_role:
                    raise BagError(f"bag {bag}: {how} as a fit bag and a --test bag: a test bag must be held out "
                                   "from the fit")
                raise BagError(f"bag {bag}: {how} ({role} bags): its stops would count twice, shrink the "
                               "confidence intervals and sit on both sides of the cross-validation")
            seen[key] = (role, bag)


def check_diagnose_inputs(args: argparse.Namespace) -> None:
    """Every bag of ``ppoe diagnose`` (``args.bags``, ``args.test``) checked before the fit (module docstring).

    Raises
    ------
    BagError
        A path that is not a readable bag, a bag given twice, a fit bag also given as a test bag, a bag of
        another robot (naming the joints that differ).
    """
    from ppoe_core.cli.output import prepare_out_dir
    from ppoe_core.io.bagio import bag_topics

    if getattr(args, "out", None):  # locked for this run (cli/output.py); diagnose's own call re-uses the lock
        prepare_out_dir(args.out, kind="diagnose")
    fit, test = list(args.bags), list(getattr(args, "test", None) or [])
    for bag in fit + test:
        bag_topics(bag)  # BagError naming the bag: not a directory, no bag, unreadable metadata
    _check_no_repeats(fit, test)
    first = _robot_of(fit[0])
    for bag in fit[1:] + test:
        diff = robot_differences(first, _robot_of(bag), geometry=bag in fit)
        if diff:
            shown = "; ".join(diff[:NAMED_AT_MOST]) + (f"; and {len(diff) - NAMED_AT_MOST} more"
                                                       if len(diff) > NAMED_AT_MOST else "")
            kind = "fit bags must all record one robot (the fit uses one URDF)" if bag in fit \
                else "a test bag must record the fitted robot"
            raise BagError(f"bag {bag}: /robot_description is another robot than bag {fit[0]}'s ({shown}): {kind}")


# ----------------------------------------------------------------------------- online config


def _numbers(raw: Any, where: str) -> np.ndarray:
    try:
        v = np.atleast_1d(np.asarray(raw, dtype=float)) if not isinstance(raw, (str, bool)) else np.array([np.nan])
    except (TypeError, ValueError):
        v = np.array([np.nan])
    if v.ndim != 1 or not np.all(np.isfinite(v)) or np.any(v < 0):
        raise ModelConfigError(f"{where}: expected non-negative finite numbers (one, or one per parameter), "
                               f"got {raw!r}")
    return v


def check_online_entries(entries: Any, jump_probability: float | None, path: str | Path | None) -> None:
    """The numbers of an online config, at parse time: ``process_noise`` and ``initial_sigma`` finite and >= 0
    and never both 0 for one parameter (the filter could never move it), ``jump_probability`` in [0, 1).

    Raises
    ------
    ModelConfigError
        Naming the file, the entry and the key.
    """
    where = f"online config {path}" if path is not None else "online config"
    if jump_probability is not None and not (math.isfinite(jump_probability) and 0.0 <= jump_probability < 1.0):
        raise ModelConfigError(f"{where}: jump_probability must be in [0, 1), got {jump_probability!r}")
    for i, entry in enumerate(entries or []):
        if not isinstance(entry, Mapping):
            continue  # the entry's shape is checked (and named) when it is parsed against the model
        label = f"{where}: online_effects[{i}] ({entry.get('name')}@{entry.get('location')})"
        given = {k: _numbers(entry[k], f"{label}.{k}") for k in ("process_noise", "initial_sigma") if k in entry}
        if len(given) == 2:
            pn, sg = given["process_noise"], given["initial_sigma"]
            if pn.size == sg.size or 1 in (pn.size, sg.size):
                both = np.flatnonzero((pn == 0.0) & (sg == 0.0))
                if both.size:
                    raise ModelConfigError(f"{label}: process_noise and initial_sigma are both 0"
                                           f"{'' if max(pn.size, sg.size) == 1 else f' (parameter {both[0]})'}: "
                                           "the filter could never move it; give one of them > 0")
