"""Options and result of ``ppoe evaluate``: fusion settings, overrides, the :class:`Evaluation` record."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ppoe_core.analysis.evaluate.metrics import METHODS
from ppoe_core.errors import ModelConfigError
from ppoe_core.estimation.pipeline import FUSION_SETTINGS
from ppoe_core.estimation.sources import SourceConfig, parse_sources
from ppoe_core.estimation.updater import FUSION_RANGES
from ppoe_core.sensing.contact import FORCE_COMPONENTS
from ppoe_core.sensing.tag_rows import DEFAULT_CORNER_REFINEMENT

# ----------------------------------------------------------------------------
# Options and result
# ----------------------------------------------------------------------------


#: settings of the replay beyond the fusion node's (:data:`ppoe_core.estimation.pipeline.FUSION_SETTINGS`):
#: the tag bearing node's and the contact node's parameters of the same names and meanings
REPLAY_SETTINGS: dict[str, Any] = {
    # tag bearing node (bags with images): edges (default), subpix, contour, apriltag or none (ppoe_core.sensing.tags)
    "corner_refinement": DEFAULT_CORNER_REFINEMENT,
    # contact node (bags with /wrench): N; 0 = model YAML contact.force_threshold / release_threshold
    "force_threshold": 0.0,
    "release_threshold": 0.0,
    "force_component": "norm",  # norm, or a signed axis x, y, z, -x, -y, -z of the wrench frame
}
#: every setting of :attr:`EvaluateOptions.fusion` with its default: the fusion node's
#: (``FUSION_SETTINGS``, shared with ``ppoe_ros/fusion_node.py``) and :data:`REPLAY_SETTINGS`
EVALUATE_SETTINGS: dict[str, Any] = {**FUSION_SETTINGS, **REPLAY_SETTINGS}


def _ros_parameters(path: Path) -> dict[str, Any]:
    """The first ``ros__parameters`` mapping of a ROS 2 parameter file, nested keys flattened to ``a.b`` (as ROS
    reads them).

    Raises
    ------
    ModelConfigError
        Unreadable file or no ``ros__parameters``.
    """
    import yaml

    try:
        doc = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise ModelConfigError(f"{path}: cannot read fusion parameters: {exc}") from None
    params = None
    if isinstance(doc, dict):
        for v in doc.values():
            if isinstance(v, dict) and isinstance(v.get("ros__parameters"), dict):
                params = v["ros__parameters"]
                break
    if params is None:
        raise ModelConfigError(f"{path}: no '<node>: ros__parameters:' mapping (ROS 2 parameter file)")

    def flat(d: dict[str, Any], prefix: str) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
        return out

    return flat(params, "")


def load_sources(path: str | Path) -> list[SourceConfig]:
    """The fusion node's sensor blocks (``sources`` and a block of keys per name, docs/fusion_node.md) of a ROS 2
    parameter file, checked as the node checks them (:func:`ppoe_core.estimation.sources.parse_sources`).

    Raises
    ------
    ModelConfigError
        Unreadable file, or a block that does not fit its type (names the file, the block and the key).
    """
    path = Path(path)
    params = _ros_parameters(path)
    names = params.get("sources") or []
    if not isinstance(names, list):
        raise ModelConfigError(f"{path}: parameter 'sources' must be a list of names, got {names!r}")
    return parse_sources(params, [str(n) for n in names], str(path))


def load_fusion_params(path: str | Path) -> dict[str, Any]:
    """The fusion settings of a ROS 2 parameter file of the fusion node.

    Reads the first ``ros__parameters`` mapping of the file (``/**`` or the node's name) and
    returns the keys of :data:`EVALUATE_SETTINGS` it sets (for :attr:`EvaluateOptions.fusion`);
    node-only keys (topics, QoS, diagnostics) are ignored (the sensor blocks: :func:`load_sources`).
    A ``/**`` file shared by all nodes thus also sets the tag bearing and contact node settings of
    :data:`REPLAY_SETTINGS`.

    Raises
    ------
    ModelConfigError
        Unreadable file, no ``ros__parameters``, or a value of the wrong type (names the key).
    """
    path = Path(path)
    params = _ros_parameters(path)
    out = {k: params[k] for k in EVALUATE_SETTINGS if k in params}
    try:
        EvaluateOptions(fusion=out).fusion_settings()
    except ModelConfigError as exc:
        raise ModelConfigError(f"{path}: {exc}") from None
    return out


@dataclass
class EvaluateOptions:
    """Options of :func:`evaluate_bag` (``ppoe evaluate`` flags).

    Attributes
    ----------
    base, tool : str, optional
        State frames ``T_base_tool``; default the model YAML's ``frames``.
    order : int
        Covariance order of ``model.fk`` (2 = paper eq. 15/18, 4).
    fit_set : str
        Stationing point set fitted by the per-station registration of bags with
        ``/dataset/stop`` roles: ``"cross"`` (default), ``"square"`` or ``"all"``.
    fusion : dict
        Settings, keys and defaults of :data:`EVALUATE_SETTINGS` (the fusion node's parameters
        and those of :data:`REPLAY_SETTINGS`); missing keys take the defaults.
    ground_truth : str
        ``"pose"`` (``/ground_truth/pose``), ``"point"`` (``/ground_truth/point``) or ``"auto"``
        (default: the pose if the bag has one, else the point).
    progress : bool
        Draw a progress bar on stderr.
    estimate : str or None
        Also score this recorded ``PoseWithCovarianceStamped`` topic of the bag (method ``recorded``: the
        latest estimate at or before each ground-truth stamp), e.g. ``/ppoe/fused_pose`` of a live run.
    urdf : str or None
        A URDF file used instead of the bag's ``/robot_description`` (e.g. the ``robot_calibrated.urdf``
        of ``ppoe diagnose --out``).
    accept_partial : bool
        Score what can be read of a damaged bag (``read_bag(accept_partial=True)``); the summary's
        ``bag_notes`` then say per topic what was lost.
    sources : list of SourceConfig
        The fusion node's sensor blocks (tracker points, 6D poses, accelerometers; :func:`load_sources`), replayed
        from the bag's topics as the node fuses them.
    tag_windows : bool
        Detect the tags of the bag's images in windows around the corners the forward kinematics predicts
        (:mod:`ppoe_core.analysis.evaluate.tag_prediction`; the same corners, bit for bit, as the whole image, which is
        used where the windows cannot promise that; ``ppoe evaluate --tag-windows``). Off by default: every image
        whole, as the tag node does, so tags of ids the model does not know are still counted in
        ``unknown_tag_points`` and a tag far from where a badly wrong model puts it is still found.
    image_processes : bool
        Decode the images and detect their tags in two worker processes forked for the evaluation (default, on
        Linux: :class:`ppoe_core.sensing.forked.ForkedResults`), else on two threads of this process; the same
        results (``bench/bench_evaluate.py`` times both).
    """

    base: str | None = None
    tool: str | None = None
    order: int = 2
    fit_set: str = "cross"
    fusion: dict[str, Any] = field(default_factory=dict)
    ground_truth: str = "auto"
    progress: bool = False
    accept_partial: bool = False
    urdf: str | None = None
    estimate: str | None = None
    sources: list[SourceConfig] = field(default_factory=list)
    tag_windows: bool = False
    image_processes: bool = True

    def fusion_settings(self) -> dict[str, Any]:
        """:data:`EVALUATE_SETTINGS` updated with :attr:`fusion`.

        Raises
        ------
        ModelConfigError
            An unknown key or a value of the wrong type (names the key).
        """
        bad = sorted(set(self.fusion) - set(EVALUATE_SETTINGS))
        if bad:
            raise ModelConfigError(f"unknown fusion setting(s) {bad}; known: {sorted(EVALUATE_SETTINGS)}")
        for k, v in self.fusion.items():
            default = EVALUATE_SETTINGS[k]
            if isinstance(default, bool):
                ok = isinstance(v, bool)
            elif isinstance(default, str):
                ok = isinstance(v, str)
            else:
                ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            if not ok:
                raise ModelConfigError(f"fusion setting {k} = {v!r} has the wrong type (default {default!r})")
        for k, (lo, hi) in FUSION_RANGES.items():
            if k in self.fusion and not lo <= self.fusion[k] <= hi:
                raise ModelConfigError(f"fusion setting {k} = {self.fusion[k]!r} is outside [{lo:g}, {hi:g}] "
                                       "(the fusion node's range)")
        if self.fusion.get("force_component", "norm") not in FORCE_COMPONENTS:
            raise ModelConfigError(f"fusion setting force_component = {self.fusion['force_component']!r}: "
                                   f"must be one of {FORCE_COMPONENTS}")
        return {**EVALUATE_SETTINGS, **self.fusion}


@dataclass
class Evaluation:
    """Result of :func:`evaluate_bag`.

    Attributes
    ----------
    summary : dict
        JSON-ready summary (see :meth:`to_dict`), lengths in m and angles in rad.
    samples : dict
        Per scored ground-truth sample arrays: ``stamp`` (n,), and per method
        ``<method>_position_3d``, ``<method>_lateral``, ``<method>_rotation``, ``<method>_nees`` (n,)
        and ``<method>_position_error`` (n, 3): estimate minus ground truth in base-frame axes [m].
    """

    summary: dict[str, Any]
    samples: dict[str, np.ndarray] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The JSON document printed by ``ppoe evaluate --json`` (NaN / inf as ``null``: strict JSON)."""
        return _json_safe(self.summary)

    def table_rows(self) -> list[tuple[str, dict[str, Any]]]:
        """``[(method, metrics), ...]`` for the methods present, in :data:`METHODS` order."""
        return [(m, self.summary["methods"][m]) for m in METHODS if m in self.summary["methods"]]


def _json_safe(obj: Any) -> Any:
    """Copy of ``obj`` with non-finite floats replaced by None and numpy scalars as Python numbers."""
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(float(obj)) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj
