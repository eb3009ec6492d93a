"""Shared fixtures: paths to the shared reference data (tests skip when ../shared is absent)."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

# Test systems are tiny: intra-op threads buy nothing, and on a loaded machine (2 cores shared with other
# jobs) idle OpenMP threads spin-waiting made a 216-particle step 20x slower (measured: 5.2 s vs 0.25 s
# for 10 steps). One thread keeps the suite's runtime independent of what else the machine is doing.
torch.set_num_threads(1)

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


@pytest.fixture
def authors_dam_grid() -> Path:
    path = SHARED / "reference" / "fgn_original" / "grids" / "dam_col_4k.npz"
    if not path.is_file():
        pytest.skip("../shared/reference is not present")
    return path


@pytest.fixture(scope="session")
def untrained_weights(tmp_path_factory) -> Path:
    """Checkpoints of freshly initialised FGN networks (``model=fgn``/``hybrid`` need weights to build).

    Tests that are about the scheme, not about what the shipped weights learned, use these.
    """
    import yaml

    from lagfluid.models.checkpoint import network_payload, save_checkpoint
    from lagfluid.models.fgn.networks import build_network

    out = tmp_path_factory.mktemp("weights")
    options = yaml.safe_load((REPO / "conf" / "model" / "fgn.yaml").read_text())
    for kind in ("advection", "collision", "pressure"):
        net = build_network(kind, options[kind])
        save_checkpoint(out / f"{kind}.pt", network_payload(net, kind, options[kind], 0, {}))
    return out
