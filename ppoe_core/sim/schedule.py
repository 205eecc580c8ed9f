"""Time-varying truth of a simulation: effect parameters that change during the recording and the temperature.

A truth effect parameter (``truth.effects[i].parameters.<key>``) is a number or one of::

    {step: {at: 40.0, before: 0.0, after: 0.003}}              # jumps at `at` [s since start_time]
    {ramp: {start: 10.0, end: 60.0, from: 0.0, to: 1.0e-6}}    # linear between start and end, held outside
    {table: [[0.0, 0.0], [30.0, 0.002], [60.0, 0.002]]}         # piecewise linear through (t [s], value), held

(e.g. the base moved onto a tilted floor halfway, a load picked up as a step of a compliance).  Times are
seconds since the scenario's ``start_time`` (the bag's first stamp).  The scenario's ``temperature`` section
(:func:`parse_temperature`) gives the temperature the same way and writes ``/temperature``; a
``thermal_growth`` truth effect with ``variable: temperature`` grows with ``temperature(t) - reference``.

:func:`truth_values` evaluates a truth file's effect parameters at given stamps: the truth over time that
tests and ``ppoe evaluate --online --truth`` compare the online estimate with.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ppoe_core.errors import ScenarioError

__all__ = ["Schedule", "parse_value", "parse_temperature", "temperature_events", "truth_entries", "truth_values",
           "TEMPERATURE_DOC"]

TEMPERATURE_DOC = """\
temperature:               # /temperature (sensor_msgs/Temperature), optional [none]
  topic: /temperature      # or /temperature/<name> [/temperature]
  frame: base_link         # header.frame_id [the URDF root link]
  value: 20.0              # [deg C]: a number, {step: ..}, {ramp: ..} or {table: ..} (times in s since start_time)
  sigma: 0.05              # measurement noise 1-sigma [deg C] [0.0]
  rate: 1.0                # [Hz] over the whole bag; 0 = once per stop [1.0]
# A truth effect parameter may be time-varying the same way, e.g. the base moved onto a tilted floor at 40 s:
#   - {name: base_tilt, location: ROOT, parameters: {tilt_x: {step: {at: 40.0, before: 0.0, after: 0.003}}}}
#   {ramp: {start: s, end: s, from: v, to: v}}; {table: [[t, v], ...]} (piecewise linear, held outside).
# thermal_growth accepts variable: temperature | time [time] and reference [deg C or s] [0 / start_time]:
#   - {name: thermal_growth, location: JOINT, variable: temperature, reference: 20.0, parameters: {alpha: 2.0e-5}}
"""


@dataclass(frozen=True)
class Schedule:
    """A value over time [s since start]: piecewise linear through ``(times, values)`` (held outside), or a step
    (``values[0]`` before ``times[0]``, ``values[1]`` from then on)."""

    times: tuple[float, ...]
    values: tuple[float, ...]
    kind: str = "linear"  # linear | step

    def __call__(self, elapsed: Any) -> np.ndarray:
        """Values at ``elapsed`` (array of seconds since start), same shape."""
        t = np.asarray(elapsed, dtype=float)
        if self.kind == "step":
            return np.where(t >= self.times[0], self.values[1], self.values[0])
        return np.interp(t, np.asarray(self.times), np.asarray(self.values))

    def to_config(self) -> Any:
        """The plain-YAML form (as in the scenario)."""
        if self.kind == "step":
            return {"step": {"at": self.times[0], "before": self.values[0], "after": self.values[1]}}
        if len(self.times) == 1:
            return self.values[0]
        return {"table": [[t, v] for t, v in zip(self.times, self.values)]}


def _finite(v: Any, where: str) -> float:
    try:
        f = float(v)
    except (TypeError, ValueError):
        raise ScenarioError(f"{where} must be a number, got {v!r}") from None
    if not math.isfinite(f):
        raise ScenarioError(f"{where} must be finite, got {v!r}")
    return f


def _keys(d: Any, allowed: Sequence[str], where: str) -> Mapping[str, Any]:
    if not isinstance(d, Mapping) or set(d) - set(allowed) or set(allowed) - set(d):
        raise ScenarioError(f"{where} must be a mapping with exactly the keys {list(allowed)}, got {d!r}")
    return d


def parse_value(raw: Any, where: str) -> Schedule:
    """A number or ``{step|ramp|table: ...}`` (module docstring) -> :class:`Schedule`.

    Raises
    ------
    ScenarioError
        Unknown form, missing or non-numeric entries, times not increasing; names ``where``.
    """
    if not isinstance(raw, Mapping):
        return Schedule((0.0,), (_finite(raw, where),))
    if len(raw) != 1 or next(iter(raw)) not in ("step", "ramp", "table"):
        raise ScenarioError(f"{where}: a time-varying value is one of {{step: ..}}, {{ramp: ..}}, {{table: ..}}, "
                            f"got keys {sorted(raw)}")
    kind, body = next(iter(raw.items()))
    if kind == "step":
        s = _keys(body, ("at", "before", "after"), f"{where}.step")
        return Schedule((_finite(s["at"], f"{where}.step.at"),),
                        (_finite(s["before"], f"{where}.step.before"), _finite(s["after"], f"{where}.step.after")),
                        "step")
    if kind == "ramp":
        r = _keys(body, ("start", "end", "from", "to"), f"{where}.ramp")
        t0, t1 = _finite(r["start"], f"{where}.ramp.start"), _finite(r["end"], f"{where}.ramp.end")
        if not t1 > t0:
            raise ScenarioError(f"{where}.ramp: end ({t1}) must be after start ({t0})")
        return Schedule((t0, t1), (_finite(r["from"], f"{where}.ramp.from"), _finite(r["to"], f"{where}.ramp.to")))
    if not isinstance(body, Sequence) or not body:
        raise ScenarioError(f"{where}.table must be a non-empty list of [t, value] pairs")
    pts = []
    for i, row in enumerate(body):
        if not isinstance(row, Sequence) or len(row) != 2:
            raise ScenarioError(f"{where}.table[{i}] must be [t, value], got {row!r}")
        pts.append((_finite(row[0], f"{where}.table[{i}][0]"), _finite(row[1], f"{where}.table[{i}][1]")))
    ts = [p[0] for p in pts]
    if any(b <= a for a, b in zip(ts, ts[1:])):
        raise ScenarioError(f"{where}.table: times must increase, got {ts}")
    return Schedule(tuple(ts), tuple(p[1] for p in pts))


def parse_temperature(raw: Any, path: str, root_link: str) -> dict[str, Any] | None:
    """Scenario ``temperature`` section (:data:`TEMPERATURE_DOC`) -> dict, or None when absent."""
    if raw is None:
        return None
    where = f"scenario {path}: temperature"
    if not isinstance(raw, Mapping):
        raise ScenarioError(f"{where} must be a mapping")
    bad = sorted(set(raw) - {"topic", "frame", "value", "sigma", "rate"})
    if bad:
        raise ScenarioError(f"{where}: unknown keys {bad} (allowed: topic, frame, value, sigma, rate)")
    topic = str(raw.get("topic", "/temperature"))
    if topic != "/temperature" and not topic.startswith("/temperature/"):
        raise ScenarioError(f"{where}.topic must be /temperature or /temperature/<name>, got {topic!r}")
    if "value" not in raw:
        raise ScenarioError(f"{where}.value is required [deg C]")
    sigma = _finite(raw.get("sigma", 0.0), f"{where}.sigma")
    rate = _finite(raw.get("rate", 1.0), f"{where}.rate")
    if sigma < 0 or rate < 0:
        raise ScenarioError(f"{where}: sigma and rate must be >= 0")
    return {"topic": topic, "frame": str(raw.get("frame", root_link)), "value": parse_value(raw["value"], where +
            ".value"), "sigma": sigma, "rate": rate}


def temperature_events(sim: Any, events: list[tuple[float, int, str, tuple]]) -> None:
    """``/temperature`` events of the simulator ``sim`` (its ``temperature`` dict, stamps and rng)."""
    cfg = sim.temperature
    ts = sim.sensor_times(cfg["rate"], "always" if cfg["rate"] > 0 else "stops")
    vals = cfg["value"](ts - sim.sc.start_time) + cfg["sigma"] * sim.rng.standard_normal(len(ts))
    events.extend((float(t), 6, "temp", (float(v),)) for t, v in zip(ts, vals))


def truth_entries(effects: Sequence[Mapping[str, Any]], start_time: float,
                  temperature: Mapping[str, Any] | None) -> dict[str, Any]:
    """``effects`` (and ``temperature``) of the truth file: the true effects with their schedules in plain YAML;
    a thermal growth over time gets its reference on the bag clock (``start_time`` + the scenario's)."""
    out: list[dict[str, Any]] = []
    for e in effects:
        d = dict(e, parameters={k: v.to_config() if isinstance(v, Schedule) else v
                                for k, v in e["parameters"].items()})
        if d["name"] == "thermal_growth" and d.get("variable", "time") == "time":
            d["variable"], d["reference"] = "time", start_time + d.get("reference", 0.0)
        out.append(d)
    if temperature is None:
        return {"effects": out}
    return {"effects": out, "temperature": {"topic": temperature["topic"], "value": temperature["value"].to_config()}}


def truth_values(truth: Mapping[str, Any], stamps: Any) -> dict[str, np.ndarray]:
    """Effect parameters of a truth file (``ppoe simulate``'s ``BAG.truth.yaml`` as a mapping) at ``stamps``.

    Returns
    -------
    dict ``"<name>@<location>/<parameter>"`` -> ndarray like ``stamps``: the true value at each stamp [s, bag
    clock] (a constant parameter repeated).
    """
    t = np.asarray(stamps, dtype=float) - float(truth.get("start_time", 0.0))
    out: dict[str, np.ndarray] = {}
    for i, e in enumerate(truth.get("effects") or []):
        for k, v in (e.get("parameters") or {}).items():
            key = f"{e['name']}@{e['location']}/{k}"
            out[key] = out.get(key, 0.0) + parse_value(v, f"truth effects[{i}].parameters.{k}")(t)
    return out
