"""Model YAML -> :class:`ModelConfig`, validated against a :class:`~ppoe_core.robot.urdf.Robot`.

The ``perturbations`` section is fixed by docs/conventions.md section 5; the other
sections are the project's (docs/ARCHITECTURE.md, "Model YAML").  Every key is
checked: an unknown key, a wrong shape, an unknown joint or link, or a
non-symmetric / non-PSD covariance raises one of the package's errors that names
the entry, the file and the line.

Defaults (a section that is absent):

* ``perturbations``: none (every joint exact); ``joint_noise``: none.
* ``frames``: ``base`` = the URDF root link, ``tool`` = the only leaf link if the
  tree has exactly one leaf, else None (then callers must name it).
* ``camera``, ``tags``, ``contact``, ``tracker``, ``naive``: None; ``imus``, ``trackers``: empty;
  ``effects``: empty.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.errors import ModelConfigError, UnknownJointError
from ppoe_core.robot.config_checks import (
    check_keys,
    CheckContext,
    kind_of,
    check_link_name,
    check_mapping,
    check_number,
    check_pose_entry,
    sigma_or_covariance,
    check_vector,
    low_rank_factor,
)
from ppoe_core.robot.config_types import (
    EFFECT_NAMES,
    CameraConfig,
    ContactConfig,
    Frames,
    ImuConfig,
    ModelConfig,
    NaiveConfig,
    Perturbation,
    TagItem,
    TOPIC_GT_POINT,
    TagsConfig,
    TrackerConfig,
)
from ppoe_core.robot.urdf import Robot
from ppoe_core.robot.yaml_io import LineDict, read_yaml_file, read_yaml_text

__all__ = [
    "Perturbation",
    "Frames",
    "CameraConfig",
    "TagItem",
    "TagsConfig",
    "ContactConfig",
    "TrackerConfig",
    "ImuConfig",
    "NaiveConfig",
    "ModelConfig",
    "EFFECT_NAMES",
    "load_model_config",
    "load_contact_config",
    "low_rank_factor",
]


# ----------------------------------------------------------------------------
# Sections
# ----------------------------------------------------------------------------


def _perturbations(ctx: CheckContext, robot: Robot, sec: Any, top: Mapping) -> dict[str, Perturbation]:
    if sec is None:
        return {}
    sec = check_mapping(ctx, sec, top, "perturbations", "perturbations")
    out = {}
    for jn, entry in sec.items():
        path = f"perturbations.{jn}"
        if jn not in robot.joints:
            raise UnknownJointError(
                f"{ctx.at(sec, jn)}: {path}: unknown joint '{jn}' (not in URDF {robot.source})"
            )
        entry = check_mapping(ctx, entry, sec, jn, path)
        cov = sigma_or_covariance(ctx, entry, path, f"joint '{jn}'")
        out[str(jn)] = Perturbation(joint=str(jn), covariance=cov, factor=low_rank_factor(cov))
    return out


def _joint_noise(ctx: CheckContext, robot: Robot, sec: Any, top: Mapping) -> dict[str, float]:
    if sec is None:
        return {}
    sec = check_mapping(ctx, sec, top, "joint_noise", "joint_noise")
    out = {}
    for jn, val in sec.items():
        path = f"joint_noise.{jn}"
        if jn not in robot.joints:
            raise UnknownJointError(f"{ctx.at(sec, jn)}: {path}: unknown joint '{jn}' (not in URDF {robot.source})")
        if not robot.joints[jn].movable:
            raise ctx.error(sec, jn, path, f"joint '{jn}' is {robot.joints[jn].type}: it has no joint value")
        out[str(jn)] = check_number(ctx, val, sec, jn, path, minimum=0.0)
    return out


def _default_tool(robot: Robot) -> str | None:
    parents = {j.parent for j in robot.joints.values()}
    leaves = [ln for ln in robot.links if ln not in parents]
    return leaves[0] if len(leaves) == 1 else None


def _frames(ctx: CheckContext, robot: Robot, sec: Any, top: Mapping) -> Frames:
    if sec is None:
        return Frames(base=robot.root, tool=_default_tool(robot))
    sec = check_mapping(ctx, sec, top, "frames", "frames")
    check_keys(ctx, sec, ("base", "tool"), "frames")
    base = check_link_name(ctx, robot, sec["base"], sec, "base", "frames.base") if "base" in sec else robot.root
    tool = (check_link_name(ctx, robot, sec["tool"], sec, "tool", "frames.tool") if "tool" in sec
            else _default_tool(robot))
    return Frames(base=base, tool=tool)


def _camera(ctx: CheckContext, robot: Robot, sec: Any, top: Mapping) -> CameraConfig | None:
    if sec is None:
        return None
    sec = check_mapping(ctx, sec, top, "camera", "camera")
    check_keys(ctx, sec, ("frame", "pixel_sigma"), "camera", required=("frame",))
    frame = check_link_name(ctx, robot, sec["frame"], sec, "frame", "camera.frame")
    ps = 0.5
    if "pixel_sigma" in sec:
        ps = check_number(ctx, sec["pixel_sigma"], sec, "pixel_sigma", "camera.pixel_sigma", positive=True)
    return CameraConfig(frame=frame, pixel_sigma=ps)


def _tags(ctx: CheckContext, robot: Robot, sec: Any, top: Mapping) -> TagsConfig | None:
    if sec is None:
        return None
    sec = check_mapping(ctx, sec, top, "tags", "tags")
    check_keys(ctx, sec, ("family", "items"), "tags", required=("items",))
    family = sec.get("family", "tag36h11")
    if not isinstance(family, str):
        raise ctx.error(sec, "family", "tags.family", f"must be a string, got {family!r}")
    items_raw = sec["items"]
    if not isinstance(items_raw, list):
        raise ctx.error(sec, "items", "tags.items", "must be a list")
    items = []
    seen: dict[int, str] = {}
    for i, it in enumerate(items_raw):
        path = f"tags.items[{i}]"
        it = check_mapping(ctx, it, items_raw, None, path)
        check_keys(ctx, it, ("id", "link", "size", "xyz", "rpy"), path, required=("id", "link", "size"))
        tid = it["id"]
        if isinstance(tid, bool) or not isinstance(tid, int) or tid < 0:
            raise ctx.error(it, "id", path + ".id", f"must be a non-negative integer, got {tid!r}")
        if tid in seen:
            raise ctx.error(it, "id", path + ".id", f"duplicate tag id {tid} (also {seen[tid]})")
        seen[tid] = path
        link = check_link_name(ctx, robot, it["link"], it, "link", path + ".link")
        size = check_number(ctx, it["size"], it, "size", path + ".size", positive=True)
        items.append(TagItem(id=tid, link=link, size=size, T_link_tag=check_pose_entry(ctx, it, path)))
    return TagsConfig(family=family, items=tuple(items))


def _contact(ctx: CheckContext, robot: Robot | None, sec: Any, top: Mapping) -> ContactConfig | None:
    if sec is None:
        return None
    sec = check_mapping(ctx, sec, top, "contact", "contact")
    check_keys(
        ctx,
        sec,
        ("plane", "sigma", "covariance", "tool_point", "force_threshold", "release_threshold"),
        "contact",
        required=("plane", "tool_point"),
    )
    plane = check_mapping(ctx, sec["plane"], sec, "plane", "contact.plane")
    check_keys(ctx, plane, ("frame", "xyz", "rpy"), "contact.plane", required=("frame",))
    frame = check_link_name(ctx, robot, plane["frame"], plane, "frame", "contact.plane.frame")
    T = check_pose_entry(ctx, plane, "contact.plane")
    cov_d = {k: sec[k] for k in ("sigma", "covariance") if k in sec}
    if not cov_d:
        raise ctx.error(sec, None, "contact", "give 'sigma' (6 numbers) or 'covariance' (6x6) of the contact")
    cov_src = LineDict(cov_d)
    cov_src.line = sec.line if isinstance(sec, LineDict) else None
    cov_src.key_lines = {k: sec.key_lines.get(k) for k in cov_d} if isinstance(sec, LineDict) else {}
    cov = sigma_or_covariance(ctx, cov_src, "contact", "contact plane")
    tp = check_mapping(ctx, sec["tool_point"], sec, "tool_point", "contact.tool_point")
    check_keys(ctx, tp, ("link", "xyz"), "contact.tool_point", required=("link",))
    tlink = check_link_name(ctx, robot, tp["link"], tp, "link", "contact.tool_point.link")
    txyz = check_vector(ctx, tp["xyz"], tp, "xyz", "contact.tool_point.xyz", 3) if "xyz" in tp else np.zeros(3)
    fth = (
        check_number(ctx, sec["force_threshold"], sec, "force_threshold", "contact.force_threshold", positive=True)
        if "force_threshold" in sec
        else 5.0
    )
    rth = (
        check_number(ctx, sec["release_threshold"], sec, "release_threshold", "contact.release_threshold", minimum=0.0)
        if "release_threshold" in sec
        else min(2.0, fth)
    )
    if rth > fth:
        raise ctx.error(
            sec,
            "release_threshold",
            "contact.release_threshold",
            f"release threshold {rth} N is above the force threshold {fth} N",
        )
    return ContactConfig(
        plane_frame=frame,
        T_frame_plane=T,
        covariance=cov,
        tool_link=tlink,
        tool_xyz=txyz,
        force_threshold=fth,
        release_threshold=rth,
    )


def _tracker(ctx: CheckContext, robot: Robot, sec: Any, top: Mapping) -> TrackerConfig | None:
    if sec is None:
        return None
    sec = check_mapping(ctx, sec, top, "tracker", "tracker")
    return _tracker_entry(ctx, robot, sec, "tracker", ("link", "xyz", "sigma"), TOPIC_GT_POINT)


def _tracker_entry(ctx: CheckContext, robot: Robot, sec: Mapping, path: str, keys: tuple, topic: str) -> TrackerConfig:
    """One reflector: ``link`` (required), ``xyz`` [m] (default 0), ``sigma`` [m] (default 0.0005)."""
    check_keys(ctx, sec, keys, path, required=("link",))
    link = check_link_name(ctx, robot, sec["link"], sec, "link", path + ".link")
    xyz = check_vector(ctx, sec["xyz"], sec, "xyz", path + ".xyz", 3) if "xyz" in sec else np.zeros(3)
    sigma = check_number(ctx, sec["sigma"], sec, "sigma", path + ".sigma", positive=True) if "sigma" in sec else 0.0005
    return TrackerConfig(link=link, xyz=xyz, sigma=sigma, topic=topic)


def _trackers(ctx: CheckContext, robot: Robot, sec: Any, top: Mapping) -> tuple[TrackerConfig, ...]:
    """``trackers`` (docs/conventions.md sec. 5): one entry per reflector, ``topic``
    ``/ground_truth/point[/<name>]``."""
    if sec is None:
        return ()
    if "tracker" in top:
        raise ctx.error(top, "trackers", "trackers", "give either 'tracker' (one reflector) or 'trackers', not both")
    if not isinstance(sec, list) or not sec:
        raise ctx.error(top, "trackers", "trackers", "must be a non-empty list of {topic, link, xyz, sigma}")
    out: list[TrackerConfig] = []
    seen: dict[str, str] = {}
    for i, entry in enumerate(sec):
        path = f"trackers[{i}]"
        entry = check_mapping(ctx, entry, sec, None, path)
        check_keys(ctx, entry, ("topic", "link", "xyz", "sigma"), path, required=("topic", "link"))
        topic = entry["topic"]
        if not isinstance(topic, str) or not (topic == TOPIC_GT_POINT or (
                topic.startswith(TOPIC_GT_POINT + "/") and len(topic) > len(TOPIC_GT_POINT) + 1)):
            raise ctx.error(entry, "topic", path + ".topic",
                            f"must be {TOPIC_GT_POINT} or {TOPIC_GT_POINT}/<name>, got {topic!r}")
        if topic in seen:
            raise ctx.error(entry, "topic", path + ".topic", f"topic {topic} is also {seen[topic]}")
        seen[topic] = path
        out.append(_tracker_entry(ctx, robot, entry, path, ("topic", "link", "xyz", "sigma"), topic))
    return tuple(out)


def _imus(ctx: CheckContext, robot: Robot, sec: Any, top: Mapping) -> dict[str, ImuConfig]:
    if sec is None:
        return {}
    sec = check_mapping(ctx, sec, top, "imus", "imus")
    out = {}
    for name, entry in sec.items():
        path = f"imus.{name}"
        entry = check_mapping(ctx, entry, sec, name, path)
        check_keys(ctx, entry, ("link", "sigma"), path, required=("link",))
        link = check_link_name(ctx, robot, entry["link"], entry, "link", path + ".link")
        sigma = (
            check_number(ctx, entry["sigma"], entry, "sigma", path + ".sigma", positive=True) if "sigma" in entry
            else 0.0004
        )
        out[str(name)] = ImuConfig(name=str(name), link=link, sigma=sigma)
    return out


def _naive(ctx: CheckContext, robot: Robot, sec: Any, top: Mapping) -> NaiveConfig | None:
    if sec is None:
        return None
    sec = check_mapping(ctx, sec, top, "naive", "naive")
    return NaiveConfig(covariance=sigma_or_covariance(ctx, sec, "naive", "naive tool covariance"))


def _effects(ctx: CheckContext, robot: Robot, sec: Any, top: Mapping) -> list[dict]:
    wheres: list[str] = ctx.effect_wheres
    if sec is None:
        return []
    if not isinstance(sec, list):
        raise ctx.error(top, "effects", "effects", "must be a list of {name, location, parameters}")
    out = []
    for i, e in enumerate(sec):
        path = f"effects[{i}]"
        e = check_mapping(ctx, e, sec, None, path)
        check_keys(
            ctx,
            e,
            # ci, sigma, share, measurement, frame, camera_info: what ppoe diagnose adds to an entry (kept, not used)
            ("name", "location", "parameters", "ci", "sigma", "share", "measurement", "frame", "camera_info",
             "variable", "reference"),
            path,
            required=("name", "location"),
        )
        name = e["name"]
        if name not in EFFECT_NAMES:
            raise ctx.error(
                e, "name", path + ".name",
                f"unknown effect '{name}' (docs/conventions.md section 6: {', '.join(EFFECT_NAMES)})"
            )
        loc = e["location"]
        if not isinstance(loc, str) or not loc:
            raise ctx.error(
                e, "location", path + ".location", f"must be a joint, link, topic or frame name, got {loc!r}"
            )
        params = e.get("parameters", {}) or {}
        params = check_mapping(ctx, params, e, "parameters", path + ".parameters")
        pclean: dict[str, Any] = {}
        for k, v in params.items():
            if isinstance(v, (list, tuple)):
                pclean[str(k)] = [check_number(ctx, x, params, k, f"{path}.parameters.{k}") for x in v]
            else:
                pclean[str(k)] = check_number(ctx, v, params, k, f"{path}.parameters.{k}")
        entry: dict[str, Any] = {"name": name, "location": loc, "parameters": pclean}
        for key in ("ci", "sigma", "share", "measurement", "frame", "camera_info"):
            if key in e:
                entry[key] = _plain(e[key])
        if "variable" in e:  # thermal_growth: name of the context variable (e.g. temperature)
            if not isinstance(e["variable"], str):
                raise ctx.error(e, "variable", path + ".variable", f"must be a string, got {e['variable']!r}")
            entry["variable"] = e["variable"]
        if "reference" in e:  # thermal_growth: reference value of that variable
            entry["reference"] = check_number(ctx, e["reference"], e, "reference", path + ".reference")
        wheres.append(ctx.at(e))
        out.append(entry)
    return out


def _plain(v: Any) -> Any:
    if isinstance(v, Mapping):
        return {k: _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    return v


_SECTIONS = {
    "perturbations": _perturbations,
    "joint_noise": _joint_noise,
    "frames": _frames,
    "camera": _camera,
    "tags": _tags,
    "contact": _contact,
    "tracker": _tracker,
    "trackers": _trackers,
    "imus": _imus,
    "naive": _naive,
    "effects": _effects,
}


# ----------------------------------------------------------------------------
# Public entry point
# ----------------------------------------------------------------------------


def load_model_config(
    source: str | os.PathLike | Mapping | None, robot: Robot, *, is_text: bool = False
) -> ModelConfig:
    """Load and validate a model YAML against ``robot``.

    Parameters
    ----------
    source : path-like, str, mapping or None
        A file path, YAML text, an already-parsed mapping, or None (empty model: every
        joint exact).  A one-line string ending in ``.yaml``/``.yml`` or naming an existing
        file is a path; any other string is YAML text.
    robot : Robot
    is_text : bool
        Treat a string ``source`` as YAML text, never as a path.

    Returns
    -------
    ModelConfig

    Raises
    ------
    ModelConfigError
        Unreadable file, YAML syntax error, unknown key (top level or in an entry),
        wrong shapes or values; the message names the key, file and line.
    UnknownJointError, UnknownFrameError
        A joint / link name the URDF does not contain.
    CovarianceError
        A non-symmetric or non-PSD covariance; names the joint (or section).
    """
    data, where = _read_yaml(source, is_text, "load_model_config")
    ctx = CheckContext(where)
    if not isinstance(data, Mapping):
        raise ModelConfigError(f"{where}: model YAML must be a mapping at the top level, got {kind_of(data)}")
    check_keys(ctx, data, tuple(_SECTIONS), "model")
    kwargs: dict[str, Any] = {name: fn(ctx, robot, data.get(name), data) for name, fn in _SECTIONS.items()}
    if kwargs["tracker"] is not None:
        kwargs["trackers"] = (kwargs["tracker"],)
    elif len(kwargs["trackers"]) == 1:
        kwargs["tracker"] = kwargs["trackers"][0]
    return ModelConfig(source=where, effect_wheres=list(ctx.effect_wheres), **kwargs)


def _read_yaml(source: str | os.PathLike | Mapping | None, is_text: bool, caller: str) -> tuple[Any, str]:
    """Model YAML source -> (parsed data with line numbers, where) (see :func:`load_model_config`)."""
    if source is None:
        return {}, "<none>"
    if isinstance(source, Mapping):
        return source, "<dict>"
    if isinstance(source, os.PathLike) or (
        isinstance(source, str)
        and not is_text
        and source.strip() != ""
        and "\n" not in source
        and (Path(source).suffix in (".yaml", ".yml") or Path(source).is_file())
    ):
        return read_yaml_file(source, "model YAML")
    if isinstance(source, str):
        return read_yaml_text(source, "<string>", "model YAML"), "<string>"
    raise ModelConfigError(f"{caller}: expected a path, YAML text or mapping, got {type(source).__name__}")


def load_contact_config(
    source: str | os.PathLike | Mapping | None, robot: Robot | None = None, *, is_text: bool = False
) -> ContactConfig | None:
    """Only the ``contact`` section of a model YAML, validated as :func:`load_model_config` does.

    For users that have no URDF at hand (the contact node): with ``robot=None`` the link names
    (``contact.plane.frame``, ``contact.tool_point.link``) are checked for type only; the other
    sections are not read.

    Parameters
    ----------
    source : path-like, str, mapping or None
        As for :func:`load_model_config`.
    robot : Robot, optional
        Check the link names against this URDF.
    is_text : bool
        Treat a string ``source`` as YAML text, never as a path.

    Returns
    -------
    ContactConfig or None
        None when the YAML has no ``contact`` section.  ``covariance`` is the plane's Sigma_v
        (6, 6) in the tangent space at ``T_frame_plane`` (plane frame).

    Raises
    ------
    ModelConfigError
        Unreadable file, YAML syntax error, unknown key or bad value in ``contact`` (message
        names file, line and key).
    CovarianceError
        Non-symmetric or non-PSD contact covariance.
    UnknownFrameError
        A link name not in ``robot`` (only when ``robot`` is given).
    """
    data, where = _read_yaml(source, is_text, "load_contact_config")
    ctx = CheckContext(where)
    if not isinstance(data, Mapping):
        raise ModelConfigError(f"{where}: model YAML must be a mapping at the top level, got {kind_of(data)}")
    return _contact(ctx, robot, data.get("contact"), data)
