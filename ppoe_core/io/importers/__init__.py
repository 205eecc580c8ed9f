"""Importers of measured datasets into contract bags (``ppoe import hilti|motoman``).

* :mod:`ppoe_core.io.importers.hilti`: Hilti construction-robot stationing YAML files
  (total-station prism points, two accelerometers, station / role per stop on
  ``/dataset/stop``).
* :mod:`ppoe_core.io.importers.motoman`: CTU Motoman Leica ``.mat`` files (laser-tracker
  points and already-detected marker pixels on ``/tag_bearing/observations``), plus a
  generated ppoe model YAML next to the bag.
* :mod:`ppoe_core.io.importers.csv_stops`: any robot's static data, one CSV row per stop and a
  mapping YAML (joint, point and pose columns, units, stations and roles).

Both datasets are third-party data that must not be redistributed: never commit the
bags or model files these importers write.  The submodules are imported lazily.
"""

from __future__ import annotations

from pathlib import Path

from ppoe_core.io.stops import STOP_TOPIC, read_stop_info

__all__ = ["MODEL_HEADER", "STOP_TOPIC", "check_outputs", "read_stop_info"]

#: first characters of a model YAML the importers write: ``--force`` replaces only a file starting with them
MODEL_HEADER = "# ppoe model for "


def check_outputs(bag: Path, model_out: Path | None, overwrite: bool) -> None:
    """Refuse, before any work, an output bag or model YAML that exists (without ``overwrite``) or is not ours
    (:mod:`ppoe_core.io.outputs`)."""
    from ppoe_core.io.outputs import check_bag_target, check_generated_file

    check_bag_target(bag, overwrite)
    if model_out is not None:
        check_generated_file(model_out, overwrite, MODEL_HEADER, "model file")
