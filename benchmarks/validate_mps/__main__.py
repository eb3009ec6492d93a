"""``python -m benchmarks.validate_mps``: see :mod:`benchmarks.validate_mps`."""

import sys

from benchmarks.validate_mps.cli import main

sys.exit(main())
