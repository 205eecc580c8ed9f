"""Node parameters: declared with descriptors and validated (:class:`ParamSpec`), checkers, YAML mapping access."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from rcl_interfaces.msg import (
    FloatingPointRange, IntegerRange, ParameterDescriptor, ParameterType, SetParametersResult,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from ppoe_core.errors import ModelConfigError, PpoeError
from ppoe_ros.common.paths import resolve_path_parameters

# ---------------------------------------------------------------------- parameters

Checker = Callable[[Any], "str | None"]

_PTYPE_OF_PYTHON = {
    bool: ParameterType.PARAMETER_BOOL,
    int: ParameterType.PARAMETER_INTEGER,
    float: ParameterType.PARAMETER_DOUBLE,
    str: ParameterType.PARAMETER_STRING,
}
_RCLPY_TYPE = {
    ParameterType.PARAMETER_BOOL: Parameter.Type.BOOL,
    ParameterType.PARAMETER_INTEGER: Parameter.Type.INTEGER,
    ParameterType.PARAMETER_DOUBLE: Parameter.Type.DOUBLE,
    ParameterType.PARAMETER_STRING: Parameter.Type.STRING,
    ParameterType.PARAMETER_BOOL_ARRAY: Parameter.Type.BOOL_ARRAY,
    ParameterType.PARAMETER_INTEGER_ARRAY: Parameter.Type.INTEGER_ARRAY,
    ParameterType.PARAMETER_DOUBLE_ARRAY: Parameter.Type.DOUBLE_ARRAY,
    ParameterType.PARAMETER_STRING_ARRAY: Parameter.Type.STRING_ARRAY,
}


@dataclass(frozen=True)
class ParamSpec:
    """One ROS parameter of a node.

    Parameters
    ----------
    name : str
        Parameter name (``a.b`` for nested YAML keys).
    default : bool | int | float | str | list
        Default value; with ``ptype`` unset its Python type gives the parameter type
        (a list needs ``ptype``, because an empty list has no element type).
    description : str
        Meaning of the parameter; the unit is appended in the descriptor.
    unit : str
        Unit ("N", "s", "m", "" for none).
    ptype : int | None
        ``rcl_interfaces.msg.ParameterType`` constant; inferred from ``default`` when None.
    check : callable or None
        ``check(value) -> reason | None``; a returned reason refuses the value.
    read_only : bool
        Refuse changes after start-up (structure parameters: topics, frames, files).
    min_value, max_value : float | None
        Inclusive range, put into the descriptor and checked.
    """

    name: str
    default: Any
    description: str
    unit: str = ""
    ptype: int | None = None
    check: Checker | None = None
    read_only: bool = True
    min_value: float | None = None
    max_value: float | None = None

    def parameter_type(self) -> int:
        """The ``ParameterType`` constant of this parameter."""
        if self.ptype is not None:
            return self.ptype
        for py_type, ptype in _PTYPE_OF_PYTHON.items():
            if type(self.default) is py_type:
                return ptype
        raise TypeError(f"ParamSpec '{self.name}': give ptype for default {self.default!r}")

    def descriptor(self) -> ParameterDescriptor:
        """The descriptor shown by ``ros2 param describe``."""
        ptype = self.parameter_type()
        text = self.description + (f" [{self.unit}]" if self.unit else "")
        desc = ParameterDescriptor(name=self.name, type=ptype, description=text, read_only=self.read_only)
        if self.min_value is not None or self.max_value is not None:
            lo = -math.inf if self.min_value is None else self.min_value
            hi = math.inf if self.max_value is None else self.max_value
            constraint = f"{lo} <= value <= {hi}"
            desc.additional_constraints = constraint
            if ptype == ParameterType.PARAMETER_DOUBLE and math.isfinite(lo) and math.isfinite(hi):
                desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi))]
            elif ptype == ParameterType.PARAMETER_INTEGER and math.isfinite(lo) and math.isfinite(hi):
                desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi))]
        return desc

    def validate(self, value: Any) -> str | None:
        """Reason why ``value`` is refused, or None when it is fine."""
        if isinstance(value, float) and not math.isfinite(value):
            return f"must be finite, got {value}"
        if self.min_value is not None and value < self.min_value:
            return f"must be >= {self.min_value}, got {value}"
        if self.max_value is not None and value > self.max_value:
            return f"must be <= {self.max_value}, got {value}"
        if self.check is not None:
            return self.check(value)
        return None


def check_nonempty(value: Any) -> str | None:
    """Checker: a non-empty string / list."""
    return None if len(value) > 0 else "must not be empty"


def check_length(*lengths: int) -> Checker:
    """Checker factory: a list of one of the given lengths (e.g. ``check_length(0, 6, 36)``)."""

    def _check(value: Any) -> str | None:
        if len(value) in lengths:
            return None
        return f"must have {' or '.join(map(str, lengths))} elements, got {len(value)}"

    return _check


def declare_parameters(
    node: Node,
    specs: Sequence[ParamSpec],
    on_change: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Declare and validate the node's parameters; return ``{name: value}``.

    Values come from ``--ros-args -p`` / ``--params-file`` overrides, else the
    spec's default.  A later ``set_parameters`` call is refused with the reason
    when a value fails its check (or the parameter is read-only); accepted
    changes of writable parameters are passed to ``on_change({name: value})``,
    which may refuse them by raising :class:`PpoeError` (its message is the reason).

    Raises
    ------
    ModelConfigError
        A start-up value fails its check; the message names node, parameter and reason.
    """
    values: dict[str, Any] = {}
    by_name = {s.name: s for s in specs}
    enforce_read_only: set[str] = set()  # read-only enforced by the callback (typed list defaults)
    node_name = node.get_fully_qualified_name()
    for spec in specs:
        ptype = spec.parameter_type()
        desc = spec.descriptor()
        try:
            if isinstance(spec.default, (list, tuple)):
                # A list default may be empty (no element type): declare statically typed,
                # then fill in the default when no override gave a value.  A read-only
                # descriptor would refuse that fill-in, so read-only is enforced below.
                if desc.read_only:
                    desc.read_only = False
                    enforce_read_only.add(spec.name)
                value = node.declare_parameter(spec.name, _RCLPY_TYPE[ptype], desc).value
                if value is None:
                    value = list(spec.default)
                    node.set_parameters([Parameter(spec.name, _RCLPY_TYPE[ptype], value)])
                value = list(value)
            else:
                value = node.declare_parameter(spec.name, spec.default, desc).value
        except PpoeError:
            raise
        except Exception as exc:  # rclpy raises its own types for an override of the wrong type
            raise ModelConfigError(f"node {node_name}: parameter '{spec.name}': {exc}") from None
        reason = spec.validate(value)
        if reason is not None:
            raise ModelConfigError(f"node {node_name}: parameter '{spec.name}' {reason}")
        values[spec.name] = value
    resolve_path_parameters(node, values)  # package:// and parameter-file-relative paths (common/paths.py)

    _report_unknown_overrides(node, by_name)

    def _on_set(params: list[Parameter]) -> SetParametersResult:
        changed: dict[str, Any] = {}
        for p in params:
            spec = by_name.get(p.name)
            if spec is None:
                continue
            if p.name in enforce_read_only:
                return SetParametersResult(successful=False, reason=f"parameter '{p.name}' is read-only")
            reason = spec.validate(p.value)
            if reason is not None:
                return SetParametersResult(successful=False, reason=f"parameter '{p.name}' {reason}")
            changed[p.name] = p.value
        if changed and on_change is not None:
            try:
                on_change(changed)
            except PpoeError as exc:  # the node refuses the combination (e.g. release >= enter)
                return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(_on_set)
    return values


def mapping_get(d: Mapping[str, Any] | None, *keys: str, default: Any = None) -> Any:
    """``d[k1][k2]...`` or ``default`` when any level is missing (for optional YAML sections)."""
    cur: Any = d
    for k in keys:
        if not isinstance(cur, Mapping) or k not in cur:
            return default
        cur = cur[k]
    return cur


#: parameters every rclpy node has (not in a node's specs)
_BUILTIN_PARAMETERS = ("use_sim_time", "start_type_description_service")


def _report_unknown_overrides(node: Node, by_name: Mapping[str, Any]) -> list[str]:
    """Log (warning) every value given for this node (``--params-file`` / ``-p``) that is not one of its
    parameters, with the closest valid name: a misspelled key must not be silently ignored.  Returns the
    warnings."""
    import difflib

    overrides = getattr(node, "_parameter_overrides", {}) or {}  # rclpy: the node's overrides by name
    out = []
    for name in sorted(overrides):
        if name in by_name or name in _BUILTIN_PARAMETERS or name.startswith("qos_overrides."):
            continue
        close = difflib.get_close_matches(name, list(by_name), n=1, cutoff=0.6)
        out.append(f"node {node.get_fully_qualified_name()}: unknown parameter '{name}' ignored"
                   + (f" (did you mean '{close[0]}'?)" if close else f" (valid: {', '.join(sorted(by_name))})"))
        node.get_logger().warning(out[-1])
    return out
