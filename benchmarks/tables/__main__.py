"""``python -m benchmarks.tables``: see :mod:`benchmarks.tables`."""

import sys

from benchmarks.tables.cli import main

sys.exit(main())
