"""The online configuration shared by ``ppoe evaluate --online`` and the live hook: what is tracked, the jump rule,
the drift monitor, the temperature timeout and (node parameter files) the fusion node's ``sources`` blocks.

Two file forms for ``--online-config``: a plain YAML (``online_effects``, ``jump_probability``, ``monitor``,
``temperature_timeout``), or a ROS 2 node parameter file whose ``online_*`` parameters and ``sources`` are read (the
same file configures the fusion node, so offline and live run one configuration).  :func:`settings_from_params` is
the rule from node parameters to settings; the live hook calls it with its declared parameters.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ppoe_core.analysis.drift_naming import NamingSettings
from ppoe_core.errors import ModelConfigError
from ppoe_core.estimation.online_config import entries_from_flat
from ppoe_core.estimation.online_monitor import MonitorSettings
from ppoe_core.estimation.sources import SourceConfig, parse_sources
from ppoe_core.robot.yaml_io import read_yaml_file

__all__ = ["MONITOR_PARAMS", "OnlineSettings", "load_online_config", "load_online_settings", "settings_from_params"]

#: node parameter -> (key of the plain file's ``monitor`` mapping, default, meaning [unit]); declared by the live hook
MONITOR_PARAMS: dict[str, tuple[str, Any, str]] = {
    "online_monitor_enable": ("enable", True, "run the drift monitor (docs/online.md)"),
    "online_monitor_window": ("window", 20, "measurements per source in the windowed NIS test"),
    "online_monitor_false_alarm": ("false_alarm", 1e-4, "probability that one test alarms while the tracked effects "
                                   "explain the data (at most this many alarms per measurement)"),
    "online_monitor_name_window": ("name_window", 40, "measurements (all sources) screened for the effect that "
                                   "explains a drift"),
    "online_monitor_add": ("add_named", False, "add the named trackable effect(s) to the online state"),
    "online_monitor_min_gain": ("min_gain", 0.2, "a named effect lowers the held-out residual by at least this "
                                "fraction"),
    "online_monitor_min_t": ("min_t", 3.0, "... with a paired t statistic of at least this"),
}


@dataclass
class OnlineSettings:
    """Everything the online run is configured with.

    Attributes
    ----------
    entries : list of mappings or None
        ``online_effects`` (None: the default set from the model and the streams).
    jump_probability : float or None
        NIS tail probability of the jump rule (None: off).
    monitor : MonitorSettings or None
        The drift monitor (None: off).
    naming : NamingSettings
        Its screening.
    temperature_timeout : float
        A temperature older than this [s] at a measurement is stale (counted).
    sources : list of SourceConfig
        The fusion node's ``sources`` blocks (6D poses, points, accelerometers).
    """

    entries: Any = None
    jump_probability: float | None = 1e-6
    monitor: MonitorSettings | None = field(default_factory=MonitorSettings)
    naming: NamingSettings = field(default_factory=NamingSettings)
    temperature_timeout: float = 10.0
    sources: list[SourceConfig] = field(default_factory=list)


def _monitor(values: Mapping[str, Any], where: str) -> tuple[MonitorSettings | None, NamingSettings]:
    """``monitor`` keys (:data:`MONITOR_PARAMS`) -> settings, checked."""
    v = {key: values.get(key, default) for key, default, _ in MONITOR_PARAMS.values()}
    try:
        window, name_window = int(v["window"]), int(v["name_window"])
        fa, gain, t = float(v["false_alarm"]), float(v["min_gain"]), float(v["min_t"])
    except (TypeError, ValueError) as exc:
        raise ModelConfigError(f"{where}: drift monitor: {exc}") from None
    if window < 2 or name_window < 10 or not 0.0 < fa < 0.5 or not 0.0 <= gain < 1.0 or t < 0.0:
        raise ModelConfigError(f"{where}: drift monitor needs window >= 2, name_window >= 10, 0 < false_alarm < "
                               f"0.5, 0 <= min_gain < 1, min_t >= 0; got {v}")
    naming = NamingSettings(min_gain=gain, min_t=t)
    if not bool(v["enable"]):
        return None, naming
    return MonitorSettings(window, fa, name_window, bool(v["add_named"])), naming


def settings_from_params(p: Mapping[str, Any], where: str, source_names: list[str] | None = None) -> OnlineSettings:
    """Node parameters (``online_*`` and the ``sources`` blocks) -> :class:`OnlineSettings`.

    Raises
    ------
    ModelConfigError
        Bad values; names ``where`` and the parameter.
    """
    p = _flat(p)
    try:
        entries = entries_from_flat(list(p.get("online_effects") or []), list(p.get("online_process_noise") or []),
                                    list(p.get("online_initial_sigma") or []),
                                    float(p.get("online_thermal_reference", 20.0)), where=f"{where}: online_effects")
        jp = float(p.get("online_jump_probability", 1e-6))
        timeout = float(p.get("online_temperature_timeout", 10.0))
    except (TypeError, ValueError) as exc:
        raise ModelConfigError(f"{where}: {exc}") from None
    mon, naming = _monitor({key: p[name] for name, (key, _, _) in MONITOR_PARAMS.items() if name in p}, where)
    names = list(p.get("sources") or []) if source_names is None else source_names
    sources = [s for s in parse_sources(p, names, where) if s.kind in ("pose", "point", "imu")]
    return OnlineSettings(entries, jp or None, mon, naming, timeout, sources)


def _flat(p: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested mappings of a parameter file (``mocap: {type: pose}``) as ROS parameters (``mocap.type``)."""
    out: dict[str, Any] = {}
    for k, v in p.items():
        if isinstance(v, Mapping):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def load_online_settings(path: str | Path | None) -> OnlineSettings:
    """``--online-config FILE`` -> :class:`OnlineSettings` (module docstring; no file: the defaults).

    Raises
    ------
    ModelConfigError
        Unknown keys, bad values; names the file.
    """
    if path is None:
        return OnlineSettings()
    raw, _ = read_yaml_file(Path(path), "online config", ModelConfigError)
    if isinstance(raw, Mapping) and len(raw) == 1:  # a node parameter file (``/**: ros__parameters: online_*``)
        node = next(iter(raw.values()))
        if isinstance(node, Mapping) and isinstance(node.get("ros__parameters"), Mapping):
            return settings_from_params(node["ros__parameters"], f"online config {path}")
    keys = {"online_effects", "jump_probability", "monitor", "temperature_timeout"}
    if not isinstance(raw, Mapping) or set(raw) - keys:
        raise ModelConfigError(f"online config {path}: a mapping with keys {sorted(keys)}")
    jp = raw.get("jump_probability", 1e-6)
    if not isinstance(jp, (int, float)) or not 0 <= jp < 1:
        raise ModelConfigError(f"online config {path}: jump_probability must be in [0, 1), got {jp!r}")
    mraw = raw.get("monitor") or {}
    known = {k for k, _, _ in MONITOR_PARAMS.values()}
    if not isinstance(mraw, Mapping) or set(mraw) - known:
        raise ModelConfigError(f"online config {path}: monitor is a mapping with keys {sorted(known)}")
    mon, naming = _monitor(mraw, f"online config {path}")
    timeout = raw.get("temperature_timeout", 10.0)
    if not isinstance(timeout, (int, float)) or timeout < 0:
        raise ModelConfigError(f"online config {path}: temperature_timeout must be >= 0 [s], got {timeout!r}")
    return OnlineSettings(raw.get("online_effects"), float(jp) or None, mon, naming, float(timeout))


def load_online_config(path: str | Path | None) -> tuple[Any, float | None]:
    """``--online-config FILE`` -> (``online_effects`` list or None, jump probability): the part of
    :func:`load_online_settings` the filter alone needs."""
    s = load_online_settings(path)
    return s.entries, s.jump_probability
