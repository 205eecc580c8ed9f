"""The ``ppoe`` command line (docs/conventions.md section 6).

Each subcommand lives in its own module exposing ``add_arguments(parser)`` and
``run(args) -> int``; it is imported only when used, so ``ppoe fk`` works on a
machine without ROS 2 and this module never imports rclpy.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings
from collections.abc import Sequence

__all__ = ["main", "SUBCOMMANDS", "SIGNAL_COMMANDS", "StopFlag"]

#: subcommand -> (module, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "fk": ("ppoe_core.cli.fk", "mean pose and covariance of one frame relative to another"),
    "simulate": ("ppoe_core.cli.simulate", "record a simulated contract bag from a scenario file"),
    "evaluate": ("ppoe_core.cli.evaluate", "replay a bag offline: FK vs PPOE-fused vs naive-fused error"),
    "diagnose": ("ppoe_core.cli.diagnose", "find systematic effects the model lacks and add them"),
    "plan": ("ppoe_core.cli.plan", "choose calibration poses before recording (D-optimal, predicted CIs)"),
    "init": ("ppoe_core.cli.init", "write a first, commented model YAML from a URDF (and a bag)"),
    "check": ("ppoe_core.cli.check", "compare bags with a model: topics, joints, frames, stops, identifiable effects"),
    "urdf": ("ppoe_core.cli.urdf", "make a URDF (from-dh: from a Denavit-Hartenberg table)"),
    "import": ("ppoe_core.cli.importer", "turn measured datasets (hilti, motoman, csv) into contract bags"),
    "play": ("ppoe_ros.cli.play", "publish a recorded bag onto live ROS 2 topics"),
    "record": ("ppoe_ros.cli.record", "record live ROS 2 topics into a new bag"),
    "warmup": ("ppoe_ros.cli.warmup", "compile every node's kernels now (installation), not at a node's first start"),
}


#: subcommands that stop cleanly on SIGINT/SIGTERM: their flag is installed before their module (and rclpy,
#: numba) is imported, so a signal during a slow start-up is not lost (it used to kill ``ppoe record`` with -15)
SIGNAL_COMMANDS = ("record",)


class StopFlag:
    """SIGINT/SIGTERM set :attr:`raised` (instead of raising in the middle of a write); :meth:`restore` puts the
    previous handlers back."""

    def __init__(self) -> None:
        import signal

        self.raised = False
        self._old = {sig: signal.signal(sig, self._handle) for sig in (signal.SIGINT, signal.SIGTERM)}

    def _handle(self, signum: int, frame: object) -> None:
        self.raised = True

    def restore(self) -> None:
        """The handlers in place before this flag."""
        import signal

        for sig, old in self._old.items():
            signal.signal(sig, old)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """Build the parser; only the module of ``command`` is imported."""
    parser = argparse.ArgumentParser(prog="ppoe", description="Probabilistic Product-of-Exponentials kinematics tools.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        sp = sub.add_parser(name, help=help_text, description=help_text)
        if name == command:
            module = importlib.import_module(module_name)
            module.add_arguments(sp)
            sp.set_defaults(_run=module.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``ppoe``; returns the process exit code."""
    args_list = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in args_list if not a.startswith("-")), None)
    if command not in SUBCOMMANDS:
        command = None
    stop = StopFlag() if command in SIGNAL_COMMANDS else None
    parser = build_parser(command)
    args = parser.parse_args(args_list)
    args.stop_flag = stop
    from ppoe_core.errors import PpoeError

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)  # numpy's numerical warnings: summarised below
        try:
            return int(args._run(args) or 0)
        except PpoeError as exc:
            print(f"ppoe {args.command}: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            return 130
        finally:
            _report_warnings(args.command, caught)


def _report_warnings(command: str, caught: list[warnings.WarningMessage]) -> None:
    """Numerical RuntimeWarnings as one line on stderr (not numpy's raw lines); others as usual."""
    from ppoe_core.errors import PpoeWarning

    numeric = [w for w in caught if issubclass(w.category, RuntimeWarning)]
    for w in caught:
        if issubclass(w.category, PpoeWarning):
            print(f"ppoe {command}: warning: {w.message}", file=sys.stderr)
        elif not issubclass(w.category, RuntimeWarning):
            warnings.showwarning(w.message, w.category, w.filename, w.lineno)
    if numeric:
        first = numeric[0]
        print(f"ppoe {command}: note: {len(numeric)} numerical warning(s), first: '{first.message}' "
              f"at {first.filename}:{first.lineno}; results may hold NaN or inf", file=sys.stderr)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
