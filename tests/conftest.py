"""Shared fixtures: paths to the shared reference data (tests skip when ../shared is absent)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.fixture
def authors_dam_grid() -> Path:
    path = SHARED / "reference" / "fgn_original" / "grids" / "dam_col_4k.npz"
    if not path.is_file():
        pytest.skip("../shared/reference is not present")
    return path
