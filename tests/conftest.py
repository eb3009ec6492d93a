"""Shared fixtures: the authors' grid, untrained weights, the resume check.

The published weights and the authors' dam grid ship in the repository; ``../shared/reference`` (where
present) is only their source, checked byte for byte, so no test needs it.
"""

from __future__ import annotations

import signal
from pathlib import Path

import pytest
import torch

# Test systems are tiny: intra-op threads buy nothing, and on a loaded machine (2 cores shared with other
# jobs) idle OpenMP threads spin-waiting made a 216-particle step 20x slower (measured: 5.2 s vs 0.25 s
# for 10 steps). One thread keeps the suite's runtime independent of what else the machine is doing.
torch.set_num_threads(1)

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"


def pytest_report_header(config: pytest.Config) -> str:
    """Say first whether the authors' grids and weights can be checked in this run."""
    present = (SHARED / "reference").is_dir()
    state = "present" if present else "absent: the shipped copies are not compared with their source"
    return f"../shared/reference: {state}"


@pytest.hookimpl(trylast=True)
def pytest_terminal_summary(terminalreporter, exitstatus: int, config: pytest.Config) -> None:
    """Count the checks skipped for want of ``../shared`` in one line at the end, so nobody misses them."""
    skipped = [
        r for r in terminalreporter.stats.get("skipped", []) if "../shared" in str(getattr(r, "longrepr", ""))
    ]
    if skipped:
        terminalreporter.write_line(
            f"NOTE: {len(skipped)} checks against the authors' grids and weights and DeepLagrangianFluids' "
            "weights were skipped: ../shared/reference is not beside this checkout",
            yellow=True,
        )


@pytest.fixture(scope="session")
def mesh_files(tmp_path_factory) -> tuple[Path, Path]:
    """A box tank (1.05 x 0.45 x 1 m) and a box of fluid in its corner (0.4 x 0.4 x 0.5 m) as STL files."""
    import numpy as np
    import trimesh

    root = tmp_path_factory.mktemp("meshes")
    paths = []
    for name, lower, upper in (("tank", [0, 0, 0], [1.05, 0.45, 1.0]), ("block", [0, 0, 0], [0.4, 0.4, 0.5])):
        mesh = trimesh.creation.box(extents=np.subtract(upper, lower))
        mesh.apply_translation(np.add(lower, upper) / 2)
        mesh.export(root / f"{name}.stl")
        paths.append(root / f"{name}.stl")
    return paths[0], paths[1]


@pytest.fixture
def authors_dam_grid() -> Path:
    """The authors' dam grid as the repository ships it (benchmarks/validate_mps/authors, MIT)."""
    path = REPO / "benchmarks" / "validate_mps" / "authors" / "dam_col_4k.npz"
    reference = SHARED / "reference" / "fgn_original" / "grids" / "dam_col_4k.npz"
    if reference.is_file():  # the copy beside the checkout, where present, is its source
        assert path.read_bytes() == reference.read_bytes()
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


@pytest.fixture
def assert_exact_resume(monkeypatch, tmp_path):
    """``check(config_for, name)``: a training stopped after its checkpoint resumes to the very same weights.

    ``config_for(out_dir)`` is a ``task=train`` config of one trainable ``name`` with 6 iterations and a
    checkpoint every 2. The run is stopped inside iteration 5 (after the checkpoint at 4, as a kill -9 would
    leave it), resumed, and compared with an uninterrupted run: every weight and every logged loss equal.
    """
    import csv

    from lagfluid.models.checkpoint import read_checkpoint
    from lagfluid.tasks.train import train

    def check(config_for, name: str) -> None:
        train(config_for(tmp_path / "straight"))
        original, calls = torch.optim.Adam.step, {"n": 0}

        def killed_in_iteration_5(self, *args, **kwargs):
            calls["n"] += 1
            if calls["n"] == 5:
                raise KeyboardInterrupt
            return original(self, *args, **kwargs)

        monkeypatch.setattr(torch.optim.Adam, "step", killed_in_iteration_5)
        with pytest.raises(KeyboardInterrupt):
            train(config_for(tmp_path / "resumed"))
        monkeypatch.setattr(torch.optim.Adam, "step", original)
        assert read_checkpoint(tmp_path / "resumed" / f"{name}.pt")["step"] == 4
        train(config_for(tmp_path / "resumed"))
        runs = [read_checkpoint(tmp_path / run / f"{name}.pt") for run in ("straight", "resumed")]
        assert runs[0]["step"] == runs[1]["step"] == 6
        for key, value in runs[0]["state_dict"].items():
            assert torch.equal(value, runs[1]["state_dict"][key]), key
        losses = [
            [row["train_loss"] for row in csv.DictReader((tmp_path / run / f"{name}_loss.csv").open())]
            for run in ("straight", "resumed")
        ]
        assert losses[0] == losses[1] and len(losses[0]) == 6

    return check


def _ctrl_c_as_from_a_terminal() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


@pytest.fixture
def interruptible() -> dict:
    """``Popen`` keywords giving the child Ctrl-C's default disposition, however the suite was started.

    A suite started in the background by a non-interactive shell (``nohup bash -c '...' &``) inherits SIGINT
    ignored, and so does every child: a test that sends SIGINT then saw no interruption at all.
    """
    return {"preexec_fn": _ctrl_c_as_from_a_terminal}
