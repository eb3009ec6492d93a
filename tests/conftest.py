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
def untrained_weights_of(tmp_path_factory):
    """``model -> directory`` of freshly initialised checkpoints of the networks the model owns.

    ``model=fgn``/``hybrid`` and the Table 5 ablations need weights to build; tests that are about the
    scheme, not about what shipped weights learned, use these.
    """
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from lagfluid.models.checkpoint import network_payload, save_checkpoint
    from lagfluid.models.fgn.networks import build_network, owned_stages

    made: dict[str, Path] = {}

    def make(model: str = "fgn") -> Path:
        if model not in made:
            with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
                cfg = compose(config_name="config", overrides=[f"model={model}"]).model
            out = tmp_path_factory.mktemp(f"weights_{model}")
            for kind in owned_stages(cfg):
                options = OmegaConf.to_container(cfg[kind], resolve=True)
                net = build_network(kind, options)
                save_checkpoint(out / f"{kind}.pt", network_payload(net, kind, options, 0, {}))
            made[model] = out
        return made[model]

    return make


@pytest.fixture(scope="session")
def untrained_weights(untrained_weights_of) -> Path:
    """Checkpoints of freshly initialised FGN networks (see :func:`untrained_weights_of`)."""
    return untrained_weights_of("fgn")
