"""Old name of :mod:`lagfluid.models.fgn.simulator`, kept only for ``benchmarks/tables.py``'s import.

Delete this file once ``benchmarks/tables.py`` imports ``SHIPPED_WEIGHTS`` from
``lagfluid.models.fgn.simulator``.
"""

from lagfluid.models.fgn.simulator import SHIPPED_WEIGHTS, build_split_step

__all__ = ["SHIPPED_WEIGHTS", "build_split_step"]
