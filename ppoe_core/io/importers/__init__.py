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

from ppoe_core.io.stops import STOP_TOPIC, read_stop_info

__all__ = ["STOP_TOPIC", "read_stop_info"]
