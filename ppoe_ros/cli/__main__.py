"""``python -m ppoe_ros.cli``: the ``ppoe`` entry point."""

import sys

from ppoe_ros.cli import main

sys.exit(main())
