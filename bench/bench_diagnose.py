"""Speed and real-data results of ``ppoe diagnose`` (issue 20 targets), on one core.

Every line runs the library call that ``ppoe diagnose`` runs (:func:`~ppoe_core.analysis.diagnose.diagnose_bags`,
same JSON) on contract bags imported with ``ppoe import`` into a cache directory (``$PPOE_BENCH_CACHE``, default
``/tmp/ppoe_bench_diagnose``; the datasets are read from ``$PPOE_DATASETS``, default ``/work/shared/datasets``,
never committed).  ``fit`` time = the diagnosis itself (blocks, selection, refits, CIs, significance), bag reading
apart (``load``); both wall and CPU time (on a machine shared with other work the CPU time is the closer measure
of what one quiet core takes).

1. **Hilti, five files** (``hilti_stationing``, README protocol: per-station registration on the cross stationing
   points, scored on the evaluation points): one run on all five files (leave-one-file-out cross-validation inside);
   target fit <= 10 s.  Then leave-one-file-out through ``--test``: selected and fitted on four files, the fifth
   scored unchanged; target <= 2.5 mm RMS per file.
2. **Two-camera tracker + pixel arm** (``motoman_leica``, right arm 6x6x6, the shared ``model.yaml`` unchanged):
   target fit <= 15 s; held-out pixels per camera (target <= 3 px), tracker (target <= 0.1 mm), the effects.
3. **19-joint robot, 200 poses** (the dev scenario ``humanoid_fit``: two markers on two hands, elastic truth, loose
   prior; made by ``bench/bench_engine_scenarios.py``'s cache): target fit <= 20 s; test mean on ``humanoid_test``.

Each timing line also prints a baseline measured in the same run on the same bags: the fit with the found effects
declared (``--effects``, no selection), and the ratio of the CPU times.  Prints ``name: value unit`` lines.
Usage: ``python bench/bench_diagnose.py [--only hilti motoman humanoid]
[--no-lofo]``.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one core (before numpy is imported)

import argparse  # noqa: E402
import contextlib  # noqa: E402
import io  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from ppoe_core.analysis.diagnose import DiagnoseOptions, diagnose_bags  # noqa: E402
from ppoe_core.analysis.diagnose.files import LoadOptions  # noqa: E402

DATA = Path(os.environ.get("PPOE_DATASETS", "/work/shared/datasets"))
CACHE = Path(os.environ.get("PPOE_BENCH_CACHE", "/tmp/ppoe_bench_diagnose"))
HILTI = ["flat", "pallet", "orthogonal_wood", "wood_left_track", "diagonal_wood"]


def _cli(argv: list[str]) -> None:
    from ppoe_ros.cli import main

    with contextlib.redirect_stdout(io.StringIO()):
        main(argv)


def hilti_bag(name: str) -> tuple[Path, Path]:
    """The imported Hilti file's bag and model (made when missing)."""
    bag = CACHE / f"hilti_{name}"
    if not bag.exists():
        _cli(["import", "hilti", str(DATA / "hilti_stationing" / f"{name}.yaml"), "--out", str(bag)])
    return bag, Path(f"{bag}.model.yaml")


def motoman_bag() -> tuple[Path, Path]:
    """The imported Motoman right-arm 6x6x6 bag and its model (from the shared model.yaml, unchanged)."""
    d = DATA / "motoman_leica"
    bag = CACHE / "motoman_666"
    if not bag.exists():
        _cli(["import", "motoman", str(d / "leica_right_hand_6x6x6_dataset.mat"), "--model-yaml",
              str(d / "model.yaml"), "--out", str(bag)])
    return bag, Path(f"{bag}.model.yaml")


class Clock:
    """Stage times of one :func:`diagnose_bags` call (its ``stage`` callback): wall and CPU seconds."""

    def __init__(self) -> None:
        self.marks: list[tuple[str, float, float]] = []

    def __call__(self, text: str) -> None:
        self.marks.append((text, time.perf_counter(), time.process_time()))

    def span(self, start: str, end: tuple[float, float]) -> tuple[float, float]:
        """(wall, CPU) seconds from the first stage whose text starts with ``start`` to the next stage (or
        ``end``)."""
        for k, (text, t, c) in enumerate(self.marks):
            if text.startswith(start):
                t1, c1 = (self.marks[k + 1][1:] if k + 1 < len(self.marks) else end)
                return t1 - t, c1 - c
        return float("nan"), float("nan")


class Span(tuple):
    """(wall, CPU) seconds, printed as ``W s wall, C s CPU``."""

    def __format__(self, spec: str) -> str:
        return f"{self[0]:{spec or '.2f'}} s wall, {self[1]:{spec or '.2f'}} s CPU"


def run(bags: list[Path], model: Path, test: list[Path] = (), options: DiagnoseOptions | None = None,
        load: LoadOptions | None = None) -> tuple[Any, Span, Span]:
    """``diagnose_bags``; (result, load time, fit time)."""
    clock = Clock()
    done = diagnose_bags(bags, model, test, options, load, stage=clock)
    end = (time.perf_counter(), time.process_time())
    return done.result, Span(clock.span("reading", end)), Span(clock.span("fitting", end))


def declared_set(res: Any) -> list[str]:
    """The found effects as ``--effects`` specs (``name@location[comp,...]``)."""
    return [f"{e.name}@{e.location}[{','.join(e.parameters)}]" for e in res.effects]


def baseline(bags: list[Path], model: Path, res: Any, test: list[Path] = ()) -> Span:
    """Fit time of the SAME bags with the found effects declared (``--effects``: blocks, nonlinear refit, noise,
    intervals, significance; no selection), measured in the same run: the ratio ``fit / baseline`` is the price of
    the selection, independent of the machine's speed and load."""
    _, _, fit = run(bags, model, test, DiagnoseOptions(effects=declared_set(res) or None))
    return fit


def timing_line(name: str, fit: Span, base: Span, target: float) -> str:
    return (f"{name}_fit_time: {fit} (target <= {target:g} s); baseline {base}; ratio "
            f"{fit[1] / max(base[1], 1e-9):.2f} CPU (fit with the found effects declared, no selection)")


def effects_line(res: Any) -> str:
    return "; ".join(f"{e.name}@{e.location}[{','.join(e.parameters)}]" for e in res.effects) or "(none)"


def hilti(lofo: bool) -> None:
    """Section 1 (module docstring)."""
    files = {f: hilti_bag(f) for f in HILTI}
    bags = [files[f][0] for f in HILTI]
    res, load, fit = run(bags, files["flat"][1])
    print(f"hilti_5files_load_time: {load}")
    print(timing_line("hilti_5files", fit, baseline(bags, files["flat"][1], res), 10.0))
    print(f"hilti_5files_effects: {effects_line(res)}")
    print(f"hilti_5files_heldout_rms: {1e3 * res.residual_before:.3f} -> {1e3 * res.residual_after:.3f} mm "
          f"(leave-one-file-out inside the run)")
    if not lofo:
        return
    worst = 0.0
    for f in HILTI:
        train = [files[g][0] for g in HILTI if g != f]
        res, _, fit = run(train, files[f][1], [files[f][0]])
        t = next(iter((res.test or {}).values()))
        worst = max(worst, t["rms"])
        print(f"hilti_lofo_{f}: {1e3 * t['before']['rms']:.3f} -> {1e3 * t['rms']:.3f} mm RMS (target <= 2.5 mm), "
              f"p95 {1e3 * t['p95']:.2f} mm, fit {fit:.1f}, effects {effects_line(res)}", flush=True)
    print(f"hilti_lofo_worst: {1e3 * worst:.3f} mm RMS")


def motoman() -> None:
    """Section 2 (module docstring)."""
    bag, model = motoman_bag()
    res, load, fit = run([bag], model)
    print(f"motoman_load_time: {load}")
    print(timing_line("motoman", fit, baseline([bag], model, res), 15.0))
    print(f"motoman_effects: {effects_line(res)}")
    for e in res.effects:
        if e.name == "camera_intrinsics":
            print(f"motoman_intrinsics_{e.location}: " + ", ".join(f"{k}={v:.4g}" for k, v in e.parameters.items()))
    px = res.blocks.get("pixels")
    if px is not None:
        for cam, s in px.per_sensor.items():
            print(f"motoman_pixels_heldout_{cam}: {s.get('rms_before', float('nan')):.3f} -> "
                  f"{s.get('rms_after', float('nan')):.3f} px (target <= 3 px)")
    tr = res.blocks.get("tracker")
    if tr is not None:
        print(f"motoman_tracker_heldout: {1e3 * tr.rms_before:.4f} -> {1e3 * tr.rms_after:.4f} mm (target <= 0.1 mm)")
    print(f"motoman_unexplained_significant: {res.to_json()['unexplained_significant']}")


def humanoid() -> None:
    """Section 3 (module docstring)."""
    sys.path.insert(0, str(REPO / "bench"))
    from bench_engine_scenarios import bag_for

    fit_bag, _ = bag_for("dev", "humanoid_fit")
    test_bag, _ = bag_for("dev", "humanoid_test")
    model = REPO / "config" / "robots" / "humanoid19_model.yaml"
    res, load, fit = run([fit_bag], model, [test_bag])
    print(f"humanoid19_load_time: {load}")
    print(timing_line("humanoid19", fit, baseline([fit_bag], model, res, [test_bag]), 20.0) + f" ({res.n_poses} poses)")
    print(f"humanoid19_effects: {len(res.effects)} effects, "
          f"{sum(len(e.parameters) for e in res.effects)} parameters")
    t = next(iter((res.test or {}).values()))
    print(f"humanoid19_test_mean: {1e3 * t['before']['mean']:.3f} -> {1e3 * t['mean']:.3f} mm "
          f"(ratio to the true model: bench/bench_engine_scenarios.py --only humanoid)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", nargs="+", default=["hilti", "motoman", "humanoid"],
                    choices=["hilti", "motoman", "humanoid"])
    ap.add_argument("--no-lofo", action="store_true", help="skip Hilti's leave-one-file-out runs")
    args = ap.parse_args()
    CACHE.mkdir(parents=True, exist_ok=True)
    if "hilti" in args.only:
        hilti(not args.no_lofo)
    if "motoman" in args.only:
        motoman()
    if "humanoid" in args.only:
        humanoid()


if __name__ == "__main__":
    main()
