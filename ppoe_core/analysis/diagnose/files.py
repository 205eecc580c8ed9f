"""Diagnose bags: read the measurements of contract bags, run :func:`~ppoe_core.analysis.diagnose.engine.diagnose`
and score the result on test bags -- exactly what ``ppoe diagnose BAG... --model MODEL.yaml [--test BAG...]`` does
(the CLI prints :meth:`DiagnoseResult.to_json` of :func:`diagnose_bags`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ppoe_core.analysis.diagnose.engine import Measurements, diagnose
from ppoe_core.analysis.diagnose.load_pixels import contacts_from_bag, pixels_from_bag
from ppoe_core.analysis.diagnose.load_stops import stops_from_bag
from ppoe_core.analysis.diagnose.pixels import concat_pixel_obs
from ppoe_core.analysis.diagnose.report import load_model
from ppoe_core.analysis.diagnose.results import DiagnoseOptions, DiagnoseResult
from ppoe_core.analysis.diagnose.stops import Stops
from ppoe_core.analysis.diagnose.testing import check_same_robot, score_stops
from ppoe_core.errors import BagError
from ppoe_core.model.effects import Effect
from ppoe_core.robot.urdf import Robot

__all__ = ["LoadOptions", "BagDiagnosis", "load_measurements", "diagnose_bags"]


@dataclass
class LoadOptions:
    """How bags are read: ``base`` / ``tool`` frames (default the model's ``frames`` / tracker link),
    ``measurement`` (``auto``, ``point``, ``pose``), ``stationing_set`` of bags with stop roles (``None`` = all),
    ``pixels`` (``auto``: when the model has ``tags`` and the bag tag observations or images; ``on``; ``off``),
    ``pixel_sigma`` [px] (default: the model's ``camera.pixel_sigma``, else 1), ``contacts`` (``auto``/``off``),
    ``accept_partial`` (read what can be read of a damaged bag)."""

    base: str | None = None
    tool: str | None = None
    measurement: str = "auto"
    stationing_set: str | None = "cross"
    pixels: str = "auto"
    pixel_sigma: float | None = None
    contacts: str = "auto"
    accept_partial: bool = False
    notes: list[str] = field(default_factory=list)


@dataclass
class BagDiagnosis:
    """:func:`diagnose_bags` output: the result and what the outputs are written from (robot, its URDF text, the
    model config and its declared effects)."""

    result: DiagnoseResult
    robot: Robot
    urdf: str
    config: Any
    declared: list[Effect]


def read_robot(bag: str | Path) -> tuple[str, Robot]:
    """The URDF text and robot of a bag's ``/robot_description``."""
    from ppoe_core.io.bagio import read_bag
    from ppoe_core.robot.urdf import parse_urdf

    urdf = read_bag(bag, topics=["/robot_description"], load_images=False).robot_description
    if not urdf:
        raise BagError(f"bag {bag}: no /robot_description")
    return urdf, parse_urdf(urdf, text_source=f"bag {bag} /robot_description")


def bag_stops(bag: str | Path, robot: Robot, cfg: Any, load: LoadOptions, name: str) -> Stops:
    """The tracker points or poses of one bag (reflectors and frames from the model, ``load`` overrides)."""
    tracker, frames = cfg.tracker, cfg.frames
    return stops_from_bag(
        bag, robot, tracker_link=load.tool or (tracker.link if tracker else None),
        tracker_xyz=tracker.xyz if (tracker and not load.tool) or (tracker and load.tool == tracker.link)
        else (0.0, 0.0, 0.0),
        tracker_sigma=tracker.sigma if tracker else 5e-4, base=load.base or (frames.base if frames else None),
        tool=load.tool or (frames.tool if frames else None), stationing_set=load.stationing_set, group_name=name,
        measurement=load.measurement, accept_partial=load.accept_partial,
        trackers=() if load.tool else tuple(getattr(cfg, "trackers", ()) or ()))


def load_measurements(bags: Sequence[str | Path], robot: Robot, cfg: Any, load: LoadOptions,
                      model_name: str = "the model") -> Measurements:
    """Every bag's tracker points or poses (with accelerometers), tag pixels and contacts as one
    :class:`Measurements` (a group per bag, named ``<index>:<directory name>``)."""
    from ppoe_core.io.bagio import bag_topics

    stops, pixels, contacts = [], [], []
    for i, bag in enumerate(bags):
        name = f"{i}:{Path(bag).name}"
        stops.append(bag_stops(bag, robot, cfg, load, name))
        if load.pixels != "off":
            topics = bag_topics(bag)
            has_tags = any(t == "/tag_bearing/observations" or t.startswith("/camera/image") for t in topics)
            if has_tags and cfg.tags is None and load.pixels == "auto":
                load.notes.append(f"Tag pixels of bag {bag} not used: {model_name} has no 'tags' section.")
            if cfg.tags is not None and has_tags:
                cam = getattr(cfg, "camera", None)
                sigma_px = load.pixel_sigma or (cam.pixel_sigma if cam is not None else 1.0)
                pixels.append(pixels_from_bag(bag, robot, cfg, sigma_px=sigma_px,
                                              accept_partial=load.accept_partial, group_name=name))
            elif load.pixels == "on":
                raise BagError(f"bag {bag}: --pixels on, but no tag observations/images or no 'tags' in {model_name}")
        if load.contacts != "off":
            c = contacts_from_bag(bag, robot, cfg, group_name=name, accept_partial=load.accept_partial)
            if c is not None:
                contacts.append(c)
    from ppoe_core.analysis.diagnose.block_contact import concat_contacts

    return Measurements(stops=Stops.concat(stops), pixels=concat_pixel_obs(pixels) if pixels else None,
                        contacts=concat_contacts(contacts) if contacts else None)


def diagnose_bags(bags: Sequence[str | Path], model: str | Path, test: Sequence[str | Path] = (),
                  options: DiagnoseOptions | None = None, load: LoadOptions | None = None,
                  stage: Callable[[str], None] | None = None) -> BagDiagnosis:
    """``ppoe diagnose`` as a library call (module docstring): the first bag's robot, the model's declared effects
    and covariance, every bag's measurements, the diagnosis, and (``test``) the fitted model scored unchanged on
    each test bag (``result.test``, keyed by the bag directory's name).  ``stage(text)`` is told each step."""
    load = load or LoadOptions()
    stage = stage or (lambda text: None)
    stage(f"reading {len(bags)} bag(s)")
    urdf, robot = read_robot(bags[0])
    cfg, declared, pert, jnoise = load_model(model, robot)
    data = load_measurements(bags, robot, cfg, load, str(model))
    options = options or DiagnoseOptions()
    if options.imu_sigma is None and getattr(cfg, "imus", None):
        options.imu_sigma = {k: v.sigma for k, v in cfg.imus.items()}
    stage("fitting the effects")
    res = diagnose(robot, data, declared, pert, jnoise, options)
    for note in load.notes:
        res.summary += "\n" + note
    if test:
        stage(f"scoring {len(test)} test bag(s)")
        res.test = {}
        for k, bag in enumerate(test):
            check_same_robot(robot, read_robot(bag)[1], str(bags[0]), str(bag))
            name = Path(bag).name if Path(bag).name not in res.test else f"{Path(bag).name}#{k}"
            stops = bag_stops(bag, robot, cfg, load, f"{len(bags) + k}:{Path(bag).name}")
            res.test[name] = score_stops(robot, stops, declared, res.found)
        res.summary += test_summary(res.test)
    return BagDiagnosis(res, robot, urdf, cfg, list(declared))


def test_summary(test: dict[str, dict[str, Any]]) -> str:
    """One summary line per test bag: RMS and p95 before -> after [mm]."""
    out = ""
    for name, t in test.items():
        b = t["before"]
        if t["n"] and b["n"]:
            out += (f"\ntest {name} ({t['n']} stops; {t['protocol']}): RMS {1e3 * b['rms']:.3f} -> "
                    f"{1e3 * t['rms']:.3f} mm, p95 {1e3 * b['p95']:.3f} -> {1e3 * t['p95']:.3f} mm")
        else:
            out += f"\ntest {name}: no stop could be scored ({t['unscored']} without a registration)"
    return out
