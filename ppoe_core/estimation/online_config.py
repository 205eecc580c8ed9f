"""What the online filter tracks (docs/online.md): the ``online_effects`` configuration, its flat node-parameter form,
and the default set chosen from the model and the streams present when nothing is configured."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core.errors import ModelConfigError, UnknownJointError
from ppoe_core.model.effects import Effect, effect_from_config, make_effect

__all__ = [
    "DEFAULT_INITIAL_SIGMA",
    "DEFAULT_PROCESS_NOISE",
    "ONLINE_EFFECT_NAMES",
    "STREAM_KINDS",
    "TrackedEffect",
    "default_online_entries",
    "entries_from_flat",
    "model_streams",
    "parse_online_config",
    "tilt_observable",
    "tracked",
]

#: process noise per parameter of each trackable effect [parameter unit / sqrt(s)]
DEFAULT_PROCESS_NOISE: dict[str, float] = {
    "base_tilt": 1e-5,            # rad/sqrt(s): 0.6 mrad per hour (1 sigma); a placement change is a jump
    "thermal_growth": 1e-7,       # (1/K)/sqrt(s)
    "gravity_compliance": 1e-6,   # rad/(N m)/sqrt(s)
    "mount_bending": 1e-6,        # rad/(N m)/sqrt(s)
    "camera_extrinsics": 1e-4,    # m/sqrt(s) and rad/sqrt(s)
    "joint_offset": 1e-5,         # rad/sqrt(s)
    "link_error": 1e-5,           # m/sqrt(s) and rad/sqrt(s)
}
#: prior 1-sigma of a tracked parameter that the diagnosed model does not hold (and after a jump) [parameter unit]
DEFAULT_INITIAL_SIGMA: dict[str, float] = {
    "base_tilt": 0.005, "thermal_growth": 1e-4, "gravity_compliance": 1e-3, "mount_bending": 1e-3,
    "camera_extrinsics": 0.01, "joint_offset": 0.005, "link_error": 0.002,
}
ONLINE_EFFECT_NAMES = tuple(DEFAULT_PROCESS_NOISE)
_ENTRY_KEYS = ("name", "location", "process_noise", "initial_sigma", "variable", "reference", "parameters")
#: kinds of measurement streams (:func:`model_streams`, :func:`tilt_observable`)
STREAM_KINDS = ("tracker", "imu", "tags", "pose", "point", "contact")


@dataclass
class TrackedEffect:
    """One effect whose parameters are estimated online.

    Attributes
    ----------
    effect : Effect
        Catalogue object; its ``params`` are the initial estimate (the diagnosed value, or zeros).
    process_noise : ndarray (P,)
        Random-walk intensity per parameter [parameter unit / sqrt(s)].
    initial_sigma : ndarray (P,)
        Prior 1-sigma [parameter unit]; also the covariance re-opened after a jump.
    """

    effect: Effect
    process_noise: np.ndarray
    initial_sigma: np.ndarray


def _vector(raw: Any, n: int, default: float, where: str) -> np.ndarray:
    if raw is None:
        return np.full(n, default)
    v = np.atleast_1d(np.asarray(raw, dtype=float)) if not isinstance(raw, str) else np.array([np.nan])
    if v.shape == (1,):
        v = np.full(n, v[0])
    if v.shape != (n,) or not np.all(np.isfinite(v)) or np.any(v < 0):
        raise ModelConfigError(f"{where}: expected {n} non-negative numbers (or one), got {raw!r}")
    return v


def tracked(effect: Effect, process_noise: Any = None, initial_sigma: Any = None, where: str = "") -> TrackedEffect:
    """``effect`` as a :class:`TrackedEffect` (defaults of its name for missing noise and sigma).

    Raises
    ------
    ModelConfigError
        The effect cannot be tracked online, or bad numbers.
    """
    if effect.name not in ONLINE_EFFECT_NAMES:
        raise ModelConfigError(f"{where or effect.describe()}: effect {effect.name!r} cannot be tracked online "
                               f"(can: {list(ONLINE_EFFECT_NAMES)})")
    noise = _vector(process_noise, effect.n_params, DEFAULT_PROCESS_NOISE[effect.name], where + ".process_noise")
    sigma = _vector(initial_sigma, effect.n_params, DEFAULT_INITIAL_SIGMA[effect.name], where + ".initial_sigma")
    frozen = np.flatnonzero((noise == 0.0) & (sigma == 0.0))
    if frozen.size:  # issue 25: such a parameter could never move (and its "jumps" would change nothing)
        raise ModelConfigError(f"{where or effect.describe()}: process_noise and initial_sigma are both 0 for "
                               f"parameter(s) {frozen.tolist()} of {effect.describe()}: the filter could never move "
                               "them; give one of them > 0")
    return TrackedEffect(effect, noise, sigma)


def model_streams(model: Any, sources: Iterable[Any] = ()) -> set[str]:
    """The measurement kinds a run may see (:data:`STREAM_KINDS`): the model's trackers (``tracker``, only with a
    ``tracker_registration``), ``imus``, ``tags`` (with a camera), ``contact``, plus the kinds of the fusion node's
    ``sources`` blocks (:class:`~ppoe_core.estimation.sources.SourceConfig`: ``point``, ``pose``, ``imu``)."""
    cfg = model.config
    out: set[str] = set()
    if any(e.name == "tracker_registration" for e in model.effects) and cfg.trackers:
        out.add("tracker")
    if cfg.imus:
        out.add("imu")
    if cfg.tags is not None and cfg.camera is not None:
        out.add("tags")
    if cfg.contact is not None:
        out.add("contact")
    for s in sources:
        if not getattr(s, "off", ""):
            out.add(s.kind)
    return out


def tilt_observable(model: Any, streams: Iterable[str], sources: Iterable[Any] = ()) -> bool:
    """Whether a tilt of the root (``base_tilt``: every joint hanging on the root rotates) changes a measurement.

    It does for an accelerometer (gravity), a tracker with a known registration (it stands on the ground), a 6D pose
    or point measured in the root frame or an external frame, tags or a camera on the root link itself (world-fixed
    markers seen by a camera on the arm); not for a camera and tags that both hang on the root (they tilt together).
    """
    kinds = set(streams)
    if kinds & {"imu", "tracker"}:
        return True
    root = model.robot.root
    for s in sources:
        if s.kind in ("pose", "point") and not getattr(s, "off", "") and (
                s.T_base_frame is not None or s.frame in ("", root)):
            return True
    cfg = model.config
    if "tags" in kinds and (cfg.camera.frame == root or any(t.link == root for t in cfg.tags.items)):
        return True
    return "contact" in kinds and (cfg.contact.plane_frame == root) != (cfg.contact.tool_link == root)


def default_online_entries(model: Any, streams: Iterable[str], sources: Iterable[Any] = ()) -> list[dict[str, Any]]:
    """The online set without configuration: every trackable effect the model holds, plus ``base_tilt`` at the root
    when a stream sees it (:func:`tilt_observable`).  Thermal candidates are the drift monitor's business (they need
    a temperature stream), not tracked by default."""
    sources = list(sources)
    out = [{"name": e.name, "location": e.location} for e in model.effects if e.name in ONLINE_EFFECT_NAMES]
    if tilt_observable(model, streams, sources) and not any(e["name"] == "base_tilt" for e in out):
        out.insert(0, {"name": "base_tilt", "location": model.robot.root})
    return out


def parse_online_config(raw: Any, model: Any, where: str = "online_effects",
                        streams: Iterable[str] | None = None, sources: Iterable[Any] = ()) -> list[TrackedEffect]:
    """The ``online_effects`` list (of a node YAML or ``ppoe evaluate --online-config``) -> tracked effects.

    Each entry is ``{name, location[, process_noise, initial_sigma, variable, reference]}``: ``process_noise``
    [parameter unit / sqrt(s)] and ``initial_sigma`` [parameter unit] are one number or one per parameter.  An
    effect the model already holds starts at the model's values; a new one at zero.  ``None``:
    :func:`default_online_entries` of the model and ``streams`` (default: :func:`model_streams` of the model and
    ``sources``).

    Raises
    ------
    ModelConfigError
        Unknown keys, names or parameters, bad numbers, an effect listed twice; the message names the entry.
    """
    if raw is None:
        sources = list(sources)
        raw = default_online_entries(model, model_streams(model, sources) if streams is None else streams, sources)
    if not isinstance(raw, Sequence) or isinstance(raw, str):
        raise ModelConfigError(f"{where} must be a list of {{name, location, process_noise, initial_sigma}}")
    out: list[TrackedEffect] = []
    for i, entry in enumerate(raw):
        w = f"{where}[{i}]"
        if not isinstance(entry, Mapping) or set(entry) - set(_ENTRY_KEYS):
            raise ModelConfigError(f"{w}: an entry is a mapping with keys {list(_ENTRY_KEYS)}, got {entry!r}")
        name = entry.get("name")
        if name not in ONLINE_EFFECT_NAMES:
            raise ModelConfigError(f"{w}: effect {name!r} cannot be tracked online (can: {list(ONLINE_EFFECT_NAMES)})")
        held = next((e for e in model.effects if e.name == name and e.location == str(entry.get("location"))), None)
        if held is not None:
            eff = held
        elif "parameters" in entry:
            cfg = {k: entry[k] for k in ("name", "location", "variable", "reference", "parameters") if k in entry}
            eff = effect_from_config(cfg, model.robot, where=w)
        else:  # every parameter of the effect, starting at zero
            opts = {k: entry[k] for k in ("variable", "reference") if k in entry}
            try:
                eff = make_effect(str(name), str(entry.get("location")), model.robot, **opts)
            except (ModelConfigError, UnknownJointError) as exc:
                raise type(exc)(f"{w}: {exc}") from None
        if any(t.effect.name == eff.name and t.effect.location == eff.location for t in out):
            raise ModelConfigError(f"{w}: effect {eff.describe()} is listed twice")
        out.append(tracked(eff, entry.get("process_noise"), entry.get("initial_sigma"), w))
    return out


def entries_from_flat(names: Sequence[str], process_noise: Sequence[float], initial_sigma: Sequence[float],
                      thermal_reference: float, where: str = "online_effects") -> list[dict[str, Any]] | None:
    """The flat form of a node parameter file -> ``online_effects`` entries for :func:`parse_online_config`.

    ``names`` are ``"<name>:<location>"`` (empty: None, the default set); ``process_noise`` [parameter unit /
    sqrt(s)] and ``initial_sigma`` [parameter unit] hold one number per effect (or are empty: defaults);
    a ``thermal_growth`` uses the temperature with ``thermal_reference`` [deg C] as its variable.

    Raises
    ------
    ModelConfigError
        A name without ``:``, or a list whose length is not the number of effects.
    """
    if not names:
        return None
    out: list[dict[str, Any]] = []
    for i, nl in enumerate(names):
        name, sep, loc = str(nl).partition(":")
        if not sep or not name or not loc:
            raise ModelConfigError(f"{where}[{i}]: expected '<effect name>:<location>', got {nl!r}")
        out.append({"name": name, "location": loc})
        if name == "thermal_growth":
            out[-1].update(variable="temperature", reference=float(thermal_reference))
    for key, vals in (("process_noise", process_noise), ("initial_sigma", initial_sigma)):
        if len(vals) and len(vals) != len(out):
            raise ModelConfigError(f"online_{key}: one number per entry of {where} ({len(out)}), got {len(vals)}")
        for e, v in zip(out, vals):
            e[key] = float(v)
    return out
