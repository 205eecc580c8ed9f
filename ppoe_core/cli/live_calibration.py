"""A calibration collected live, easy_handeye2 style: take samples at static stops, then compute.

Each sample is one static stop: the robot's joint positions and one external measurement of it, a tracker point
(``PointStamped`` of the reflector, in the tracker's frame) or a tool pose (``PoseStamped`` in the base frame).
:meth:`CalibrationSession.compute` writes the samples as a contract bag (``/robot_description``, per stop two
identical ``/joint_states`` 5 ms around the measurement, which is the contract's static-stop layout, CONTRACT.md
sec. 3) and runs ``ppoe diagnose`` on it through its public entry points (:mod:`ppoe_core.cli.diagnose`, which
calls :func:`ppoe_core.analysis.diagnose.diagnose`), so the result and the files are those of the command line:
``diagnose.md/.json/.png``, ``model_diagnosed.yaml`` (the model with the effects found),
``robot_calibrated.urdf`` and ``model_calibrated.yaml``.  The bag stays beside them (``samples/``) and can be
diagnosed again, with other options, by ``ppoe diagnose``.

No ROS: ``ppoe_ros/common/calibration.py`` is the node (``~/take_sample``, ``~/compute``).
"""

from __future__ import annotations

import argparse
import io
import json
from collections.abc import Sequence
from contextlib import redirect_stdout
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.errors import PpoeError

__all__ = ["CalibrationSample", "CalibrationSession", "CalibrationResult", "STOP_HALF_WIDTH_S"]

#: the two joint states of a stop are written this long before and after its measurement [s]
STOP_HALF_WIDTH_S = 0.005


@dataclass(frozen=True)
class CalibrationSample:
    """One static stop.

    Attributes
    ----------
    stamp : float
        Time of the measurement [s].
    joint_names : tuple of str
    positions : ndarray (n,)
        Joint positions [rad or m] while the robot stands still.
    frame : str
        ``header.frame_id`` of the measurement (tracker frame of a point; base frame of a pose).
    value : ndarray (3,) or (4, 4)
        Reflector position [m] in ``frame``, or the tool pose ``T_frame_tool``.
    """

    stamp: float
    joint_names: tuple[str, ...]
    positions: np.ndarray
    frame: str
    value: np.ndarray

    @property
    def kind(self) -> str:
        """``"point"`` or ``"pose"``."""
        return "pose" if np.shape(self.value) == (4, 4) else "point"


@dataclass(frozen=True)
class CalibrationResult:
    """What :meth:`CalibrationSession.compute` found and wrote: the ``ppoe diagnose --json`` document and paths."""

    document: dict[str, Any]
    out_dir: Path
    bag: Path

    def summary(self) -> str:
        """One line: the effects found and the held-out residual before / after [mm]."""
        d = self.document
        effects = ", ".join(f"{e['name']}@{e['location']}" for e in d.get("effects", [])) or "no effect"
        return (f"{effects}; held-out residual {1e3 * float(d['residual_before']):.3f} -> "
                f"{1e3 * float(d['residual_after']):.3f} mm; wrote {self.out_dir}")


class CalibrationSession:
    """Samples of one robot and their diagnosis.

    Parameters
    ----------
    urdf_xml : str
        Nominal URDF of the robot (``/robot_description``).
    model_path : str or Path
        Model YAML (perturbations, ``trackers`` / ``tracker`` naming the reflector's link, ``frames``).
    """

    def __init__(self, urdf_xml: str, model_path: str | Path) -> None:
        self.urdf_xml = str(urdf_xml)
        self.model_path = Path(model_path)
        self.samples: list[CalibrationSample] = []

    def add(self, sample: CalibrationSample) -> int:
        """Append a stop; returns the number of samples.

        Raises
        ------
        PpoeError
            Non-finite values, or a sample of another kind, frame or joint set than the first one, or not
            later than the previous one (named).
        """
        if not (np.all(np.isfinite(sample.positions)) and np.all(np.isfinite(sample.value))):
            raise PpoeError(f"calibration sample at {sample.stamp:.6f} s: NaN or inf in the joints or measurement")
        if self.samples:
            first, last = self.samples[0], self.samples[-1]
            if (sample.kind, sample.frame) != (first.kind, first.frame):
                raise PpoeError(f"calibration sample: a {sample.kind} in frame '{sample.frame}', but the session "
                                f"holds {first.kind}s in frame '{first.frame}'")
            if sample.stamp <= last.stamp + 2 * STOP_HALF_WIDTH_S:
                raise PpoeError(f"calibration sample at {sample.stamp:.6f} s is not after the previous one "
                                f"({last.stamp:.6f} s)")
        self.samples.append(sample)
        return len(self.samples)

    def write_bag(self, path: str | Path) -> Path:
        """The samples as a contract bag at ``path`` (replaced if it exists)."""
        from ppoe_core.io.bagio import BagWriter

        if not self.samples:
            raise PpoeError("calibration: no sample taken yet")
        with BagWriter(path, overwrite=True) as bag:
            bag.write_robot_description(self.urdf_xml, self.samples[0].stamp - 1.0)
            for s in self.samples:
                for dt in (-STOP_HALF_WIDTH_S, STOP_HALF_WIDTH_S):
                    bag.write_joint_state(s.stamp + dt, s.joint_names, s.positions)
                if s.kind == "point":
                    bag.write_ground_truth_point(s.stamp, s.frame, s.value)
                else:
                    bag.write_ground_truth_pose(s.stamp, s.frame, s.value)
        return Path(path)

    def compute(self, out_dir: str | Path, extra_args: Sequence[str] = ()) -> CalibrationResult:
        """Write the bag to ``out_dir/samples`` and run ``ppoe diagnose`` on it into ``out_dir``.

        ``extra_args`` are further ``ppoe diagnose`` options (e.g. ``["--min-t", "3"]``).

        Raises
        ------
        PpoeError
            Too few samples for the diagnosis, or whatever ``ppoe diagnose`` refuses (its message).
        """
        from ppoe_core.cli import diagnose as cli_diagnose

        out = Path(out_dir)
        bag = self.write_bag(out / "samples")
        parser = argparse.ArgumentParser(prog="ppoe diagnose")
        cli_diagnose.add_arguments(parser)
        args = parser.parse_args([str(bag), "--model", str(self.model_path), "--out", str(out), "--json",
                                  "--quiet", *extra_args])
        text = io.StringIO()
        with redirect_stdout(text):
            cli_diagnose.run(args)
        return CalibrationResult(json.loads(text.getvalue()), out, bag)
