"""On-policy datasets (``data.policy=model``): moved by a learned model, labelled by the exact solver."""

import json

import h5py
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from lagfluid.data.datasets import AdvectionSamples, PressureSamples, StepWindows, TrajectoryWindows
from lagfluid.data.layout import GROUP
from lagfluid.errors import ConfigError, LagfluidError
from lagfluid.models.checkpoint import network_payload, save_checkpoint
from lagfluid.models.fgn.networks import build_network
from lagfluid.models.fgn.ppe_term import LABEL_TOLERANCE, WithPPESystem
from lagfluid.run import CONF_DIR
from lagfluid.tasks.generate import generate
from lagfluid.tasks.generate.spec import DataSpec


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


TINY = ("task=generate", "scene=random", "data=tiny", "progress=false")


@pytest.fixture(scope="module")
def datasets(tmp_path_factory):
    """(MPS dataset, on-policy dataset of the shipped FGN), the same tiny scenes."""
    root = tmp_path_factory.mktemp("onpolicy")
    generate(_compose(*TINY, f"data.out_dir={root / 'mps'}"))
    generate(_compose(*TINY, "data.policy=model", "model=fgn", f"data.out_dir={root / 'fgn'}"))
    return root / "mps", root / "fgn"


def _last_frame(root, scene=0):
    meta = json.loads((root / "metadata.json").read_text())
    with h5py.File(root / meta["scenes"][scene]["file"], "r") as f:
        return f[GROUP]["position"][-1], dict(f[GROUP].attrs)


EQ11 = ("model.advection.linear_in_viscosity=false", "model.advection.features=[vel_dir,speed,vel,is_fluid]")


def test_the_model_moves_the_particles_and_the_metadata_says_so(datasets, tmp_path):
    mps, fgn = datasets
    meta = json.loads((fgn / "metadata.json").read_text())
    assert meta["model"] == "fgn" and meta["policy"]["model"] == "fgn"
    assert set(meta["policy"]["networks"]) == {"advection", "collision", "pressure"}
    assert "policy" not in json.loads((mps / "metadata.json").read_text())
    (pos_mps, _), (pos_fgn, attrs) = _last_frame(mps), _last_frame(fgn)
    assert json.loads(attrs["policy"])["model"] == "fgn"
    # The tiny scenes are 8 steps of a block in free fall: the shipped FGN's advection is exact in g
    # (linear in nu), so it falls as MPS's block does; a net that learns a itself, untrained, does not.
    cfg = _compose("model=fgn", *EQ11).model
    weights = tmp_path / "weights"
    for kind in ("advection", "collision", "pressure"):
        options = OmegaConf.to_container(cfg[kind], resolve=True)
        save_checkpoint(
            weights / f"{kind}.pt", network_payload(build_network(kind, options), kind, options, 0, {})
        )
    generate(
        _compose(
            *TINY,
            "data.policy=model",
            "model=fgn",
            *EQ11,
            f"model.weights={weights}",
            f"data.out_dir={tmp_path / 'data'}",
        )
    )
    pos_other = _last_frame(tmp_path / "data")[0]
    assert np.abs(pos_fgn - pos_mps).max() < 1e-5 < np.abs(pos_other - pos_mps).max()


def test_every_pressure_label_solves_the_ppe_at_the_models_own_state(datasets):
    systems = WithPPESystem(PressureSamples(datasets[1], split=None))  # refuses a label off its system
    residuals = [float(systems[i].ppe_label_residual) for i in range(len(systems))]
    assert max(residuals) < LABEL_TOLERANCE


def test_advection_labels_are_the_exact_acceleration_not_the_networks(datasets):
    samples = AdvectionSamples(datasets[1], split=None)
    for i in range(len(samples)):
        item = samples[i]
        # water (nu = 1e-6) at these speeds: nu lap(v) is ~1e-4 m/s^2, the label is gravity
        torch.testing.assert_close(item.y, item.gravity.expand_as(item.y), atol=1e-3, rtol=0)


def test_datasets_of_trajectories_refuse_an_on_policy_dataset(datasets):
    for dataset in (TrajectoryWindows, StepWindows):
        with pytest.raises(LagfluidError, match=r"on-policy dataset .* model=fgn"):
            dataset(datasets[1], split="train")


def test_the_policy_is_part_of_each_files_fingerprint(untrained_weights):
    solver = DataSpec.from_config(_compose(*TINY))
    shipped = DataSpec.from_config(_compose(*TINY, "data.policy=model", "model=fgn"))
    untrained = _compose(*TINY, "data.policy=model", "model=fgn", f"model.weights={untrained_weights}")
    other = DataSpec.from_config(untrained)
    prints = {spec.fingerprint(0) for spec in (solver, shipped, other)}
    assert len(prints) == 3
    assert solver.policy is None


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (("data.policy=fgn",), r"data.policy must be null .* got 'fgn'"),
        (("data.policy=model", "model=fgn", "model.stages.pressure=none"), "pressure is none"),
    ],
)
def test_a_bad_policy_is_refused_before_any_simulation(overrides, message):
    with pytest.raises(ConfigError, match=message):
        DataSpec.from_config(_compose(*TINY, *overrides))


def test_a_policy_that_leaves_the_domain_keeps_the_states_it_visited(tmp_path):
    """DAgger data: the model's trajectory up to the guard's stop, each sample labelled, is a shorter scene.

    The ground truth stopping stays an error (tests/test_data.py); a learned policy stopping is what the
    rounds are there to correct. Here the guard's Courant limit is so low that every scene stops before its
    8 steps: 0.005 is |v| = 0.125 m/s, above the initial speeds (< 0.1 m/s), below 7 steps of free fall.
    """
    out = tmp_path / "stopped"
    limit = "solver.guard.max_courant=0.005"
    generate(_compose(*TINY, "data.policy=model", "model=fgn", limit, f"data.out_dir={out}"))
    meta = json.loads((out / "metadata.json").read_text())
    for scene in meta["scenes"]:
        with h5py.File(out / scene["file"], "r") as f:
            attrs = dict(f[GROUP].attrs)
            assert attrs["complete"] and 0 < attrs["stopped_at_step"] < 8  # data=tiny asks 8 steps
            assert "Courant number" in attrs["stop_reason"]
            # a sample every 2 steps, each of a step that was accepted: those before the stop
            assert f["samples/step"].shape[0] == (attrs["stopped_at_step"] + 1) // 2
    assert len(AdvectionSamples(out, "train")) > 0
    with pytest.raises(LagfluidError, match=r"scene\(s\) failed: .*stopped: step \d+: Courant number"):
        generate(_compose(*TINY, limit, f"data.out_dir={tmp_path / 'mps'}"))
