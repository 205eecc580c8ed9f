"""``ppoe fk``: mean pose and covariance of one frame relative to another (docs/conventions.md sec. 6).

::

    ppoe fk --urdf URDF --model MODEL.yaml --from FRAME --to FRAME \\
            --joints NAME=VALUE ... [--order 2|4] [--json]
    ppoe fk --urdf URDF --model MODEL.yaml --from FRAME --to FRAME --batch CONFIGS.csv [--json]

With ``--json`` one JSON document goes to stdout with the keys ``T`` (4x4 mean pose
``T_from_to``), ``cov_local`` (6x6 covariance in the tangent space at ``T``, right
perturbation, ``[rho; theta]``, paper eq. 8-9) and ``cov_ros`` (6x6, ``B cov_local B^T``
with ``B = blockdiag(R, R)``: translation and small rotations in the axes of the ``--from``
frame, docs/conventions.md sec. 2), all as nested lists. With ``--batch`` (CSV, header = joint
names, one configuration per row) one such object is printed per line, in row order; all
rows are computed in one batched call. Without ``--json`` a readable text form is printed.

``--joints`` values apply to every batch row; a joint given both there and as a CSV column
is an error. ``--from`` / ``--to`` default to ``frames.base`` / ``frames.tool`` of the model.
Bad input raises :mod:`ppoe_core.errors` types naming the argument, CSV line and column;
``ppoe`` turns them into a message on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
from collections.abc import Mapping, Sequence
from typing import Any, TextIO

import numpy as np

from ppoe_core import lie
from ppoe_core.errors import JointValueError, ModelConfigError, UnknownJointError, UrdfError

__all__ = [
    "add_arguments",
    "run",
    "parse_joint_assignments",
    "read_batch_csv",
    "fk_result",
    "format_text",
]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``ppoe fk`` options to ``parser`` (docs/conventions.md sec. 6)."""
    parser.add_argument("--urdf", required=True, metavar="URDF", help="robot description (URDF file)")
    parser.add_argument(
        "--model",
        metavar="MODEL.yaml",
        default=None,
        help="PPOE model YAML (perturbations, joint noise, frames); without it every joint is exact",
    )
    parser.add_argument(
        "--from",
        dest="frm",
        metavar="FRAME",
        default=None,
        help="reference frame (URDF link); default: frames.base of the model",
    )
    parser.add_argument(
        "--to", metavar="FRAME", default=None, help="target frame (URDF link); default: frames.tool of the model"
    )
    parser.add_argument(
        "--joints",
        nargs="+",
        action="extend",
        default=[],
        metavar="NAME=VALUE",
        help="joint values [rad or m], URDF joint names; may be repeated",
    )
    parser.add_argument(
        "--batch",
        metavar="CONFIGS.csv",
        default=None,
        help="CSV file, header = joint names, one configuration per row; prints one result per row",
    )
    parser.add_argument(
        "--order",
        type=int,
        choices=(2, 4),
        default=2,
        help="covariance propagation: 2 = the paper's eq. 15/18, 4 = fourth order (Barfoot & Furgale)",
    )
    parser.add_argument("--json", action="store_true", help="JSON output (one object per configuration and line)")


def parse_joint_assignments(items: Sequence[str], joint_names: Sequence[str]) -> dict[str, float]:
    """Parse ``NAME=VALUE`` strings of ``--joints``.

    Parameters
    ----------
    items : sequence of str
        Each ``"<urdf joint>=<float>"``.
    joint_names : sequence of str
        The independent movable joints of the robot (``PPOEModel.joint_names``).

    Returns
    -------
    dict
        Joint name -> value [rad or m].

    Raises
    ------
    JointValueError
        Malformed item, a value that is not a finite number, or a joint given twice.
    UnknownJointError
        A name that is not an independent movable joint of the URDF.
    """
    known = set(joint_names)
    out: dict[str, float] = {}
    for item in items:
        name, sep, text = item.partition("=")
        name = name.strip()
        if not sep or not name:
            raise JointValueError(f"--joints: {item!r} is not of the form NAME=VALUE")
        if name not in known:
            raise UnknownJointError(
                f"--joints: {name!r} is not a movable (non-fixed, non-mimic) joint of the URDF; "
                f"known: {', '.join(joint_names)}"
            )
        try:
            value = float(text)
        except ValueError:
            raise JointValueError(f"--joints: value of joint {name!r} is not a number: {text!r}") from None
        if not math.isfinite(value):
            raise JointValueError(f"--joints: value of joint {name!r} is not finite: {text!r}")
        if name in out:
            raise JointValueError(f"--joints: joint {name!r} given twice")
        out[name] = value
    return out


def read_batch_csv(path: str, joint_names: Sequence[str]) -> dict[str, np.ndarray]:
    """Read a ``--batch`` CSV: header = joint names, one configuration per row.

    Parameters
    ----------
    path : str
        CSV file (comma separated; blank lines are allowed only at the end of the file).
    joint_names : sequence of str
        The independent movable joints of the robot.

    Returns
    -------
    dict
        Joint name -> array of shape ``(n_rows,)`` [rad or m], rows in file order.

    Raises
    ------
    JointValueError
        Unreadable file, empty header, no data rows, a row with the wrong number of fields,
        a value that is not a finite number (message names file, line and column).
    UnknownJointError
        A header column that is not an independent movable joint of the URDF.
    """
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
        while rows and not any(cell.strip() for cell in rows[-1]):
            rows.pop()  # blank lines at the end of the file only
    except OSError as exc:
        raise JointValueError(f"--batch: cannot read {path}: {exc.strerror or exc}") from None
    except (UnicodeDecodeError, csv.Error) as exc:
        raise JointValueError(f"--batch: {path} is not a readable CSV file: {exc}") from None
    if not rows or not any(cell.strip() for cell in rows[0]):
        raise JointValueError(f"--batch: {path}: line 1: empty header, expected joint names")
    header = [cell.strip() for cell in rows[0]]
    known = set(joint_names)
    for col, name in enumerate(header, start=1):
        if not name:
            raise JointValueError(f"--batch: {path}: line 1, column {col}: empty joint name")
        if name not in known:
            raise UnknownJointError(
                f"--batch: {path}: line 1, column {col}: {name!r} is not a movable (non-fixed, non-mimic) "
                f"joint of the URDF; known: {', '.join(joint_names)}"
            )
        if header.index(name) != col - 1:
            raise JointValueError(f"--batch: {path}: line 1, column {col}: joint {name!r} appears twice")
    data = rows[1:]
    if not data:
        raise JointValueError(f"--batch: {path}: no configuration rows after the header")
    values = np.empty((len(data), len(header)))
    for r, row in enumerate(data):
        line = r + 2
        if len(row) != len(header):
            raise JointValueError(
                f"--batch: {path}: line {line} (row {r + 1}): {len(row)} fields, header has {len(header)}"
            )
        for c, cell in enumerate(row):
            try:
                v = float(cell)
            except ValueError:
                raise JointValueError(
                    f"--batch: {path}: line {line} (row {r + 1}), column {c + 1} ({header[c]!r}): "
                    f"not a number: {cell!r}"
                ) from None
            if not math.isfinite(v):
                raise JointValueError(
                    f"--batch: {path}: line {line} (row {r + 1}), column {c + 1} ({header[c]!r}): "
                    f"not finite: {cell.strip()!r}"
                )
            values[r, c] = v
    return {name: values[:, c] for c, name in enumerate(header)}


def fk_result(T_from_to: np.ndarray, cov_to: np.ndarray) -> dict[str, Any]:
    """The JSON object of one configuration.

    Parameters
    ----------
    T_from_to : ndarray, shape (4, 4)
        Mean pose of the target frame in the reference frame.
    cov_to : ndarray, shape (6, 6)
        Covariance in the tangent space at ``T_from_to`` (local, ``[rho; theta]``).

    Returns
    -------
    dict
        ``{"T": 4x4, "cov_local": 6x6, "cov_ros": 6x6}`` as nested lists; ``cov_ros`` is in the
        axes of the reference frame (docs/conventions.md sec. 2).
    """
    cov_ros = lie.cov_local_to_ros(T_from_to, cov_to)
    return {"T": T_from_to.tolist(), "cov_local": cov_to.tolist(), "cov_ros": cov_ros.tolist()}


def _matrix_lines(M: np.ndarray, indent: str = "  ") -> list[str]:
    return [indent + " ".join(f"{v: .6e}" for v in row) for row in M]


def format_text(T_from_to: np.ndarray, cov_to: np.ndarray, frm: str, to: str) -> str:
    """Readable form of one result (same content as :func:`fk_result`).

    ``cov_to`` lives in the tangent space at ``T_from_to`` (frame ``to``).
    """
    cov_ros = lie.cov_local_to_ros(T_from_to, cov_to)
    rpy = lie.rpy_from_matrix(T_from_to[:3, :3])
    sig_local = np.sqrt(np.clip(np.diag(cov_to), 0.0, None))
    sig_ros = np.sqrt(np.clip(np.diag(cov_ros), 0.0, None))
    out = [f"T_{frm}_{to} (pose of '{to}' in '{frm}'):"]
    out += _matrix_lines(T_from_to)
    out.append("  xyz [m]:   " + " ".join(f"{v: .6f}" for v in T_from_to[:3, 3]))
    out.append("  rpy [rad]: " + " ".join(f"{v: .6f}" for v in rpy))
    out.append(f"cov_local (tangent space at T, [rho; theta] in '{to}' axes, m / rad):")
    out += _matrix_lines(cov_to)
    out.append("  1-sigma: " + " ".join(f"{v:.6g}" for v in sig_local))
    out.append(f"cov_ros (x y z rot_x rot_y rot_z in '{frm}' axes, m / rad):")
    out += _matrix_lines(cov_ros)
    out.append("  1-sigma: " + " ".join(f"{v:.6g}" for v in sig_ros))
    return "\n".join(out)


def _load_model(urdf: str, model_yaml: str | None) -> Any:
    from ppoe_core.model.ppoe import PPOEModel  # imported here so `ppoe --help` stays fast

    if not os.path.isfile(urdf):
        raise UrdfError(f"--urdf: no such file: {urdf}")
    if model_yaml is not None and not os.path.isfile(model_yaml):
        raise ModelConfigError(f"--model: no such file: {model_yaml}")
    return PPOEModel.from_files(urdf, model_yaml)


def _frames(model: Any, frm: str | None, to: str | None, model_yaml: str | None) -> tuple[str, str]:
    frames = getattr(model.config, "frames", None)
    if frm is None:
        frm = getattr(frames, "base", None)
    if to is None:
        to = getattr(frames, "tool", None)
    where = model_yaml or "no --model given"
    if frm is None:
        raise ModelConfigError(f"--from not given and the model has no frames.base ({where})")
    if to is None:
        raise ModelConfigError(f"--to not given and the model has no frames.tool ({where})")
    return frm, to


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Run ``ppoe fk``; returns the exit code (errors propagate as :class:`PpoeError`)."""
    out = sys.stdout if out is None else out
    model = _load_model(args.urdf, args.model)
    frm, to = _frames(model, args.frm, args.to, args.model)
    names = list(model.joint_names)
    joints: Mapping[str, Any] = parse_joint_assignments(args.joints, names)
    if args.batch is not None:
        batch = read_batch_csv(args.batch, names)
        both = sorted(set(batch) & set(joints))
        if both:
            raise JointValueError(
                f"--batch: {args.batch}: joint(s) {', '.join(both)} given both in the CSV header and in --joints"
            )
        n = len(next(iter(batch.values())))
        merged = {k: np.full(n, v) for k, v in joints.items()}
        merged.update(batch)
        T, cov = model.fk(merged, frm, to, order=args.order)
        T = np.broadcast_to(T, (n, 4, 4))
        cov = np.broadcast_to(cov, (n, 6, 6))
        for i in range(n):
            if args.json:
                out.write(json.dumps(fk_result(np.asarray(T[i]), np.asarray(cov[i]))) + "\n")
            else:
                out.write(f"# row {i + 1}\n" + format_text(np.asarray(T[i]), np.asarray(cov[i]), frm, to) + "\n")
        return 0
    T, cov = model.fk(joints, frm, to, order=args.order)
    if args.json:
        out.write(json.dumps(fk_result(np.asarray(T), np.asarray(cov))) + "\n")
    else:
        out.write(format_text(np.asarray(T), np.asarray(cov), frm, to) + "\n")
    return 0
