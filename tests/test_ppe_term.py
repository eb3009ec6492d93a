"""The PPE residual term of the pressure net's training (paper eq. 31): the rebuilt system and its rows."""

import pytest
import torch
from hydra import compose, initialize_config_dir
from torch_geometric.data import Batch

from lagfluid.data.datasets import PressureSamples
from lagfluid.errors import ConfigError, LagfluidError
from lagfluid.models.checkpoint import read_checkpoint
from lagfluid.models.fgn.ppe_term import LABEL_TOLERANCE, WithPPESystem, ppe_residual_rows
from lagfluid.models.fgn.trainables import PressureTrainable
from lagfluid.run import CONF_DIR
from lagfluid.tasks.generate import generate
from lagfluid.tasks.train import train


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny_ppe")
    generate(_compose("task=generate", "scene=random", "data=tiny", f"data.out_dir={out}", "progress=false"))
    return out


@pytest.fixture(scope="module")
def systems(tiny_data):
    return WithPPESystem(PressureSamples(tiny_data, split="train"))


def _rms_per_sample(rows, batch):
    return [float(rows[batch.batch == g].square().mean().sqrt()) for g in range(batch.num_graphs)]


def test_the_rebuilt_system_is_the_one_the_labels_solve(systems):
    items = [systems[i] for i in range(len(systems))]
    assert all(float(it.ppe_label_residual) < LABEL_TOLERANCE for it in items)
    batch = Batch.from_data_list(items[:3])
    # eq. 31 per sample: ~0 for the label, 1 for p = 0, |a| for (1 + a) p_label
    assert max(_rms_per_sample(ppe_residual_rows(batch.y, batch), batch)) < LABEL_TOLERANCE
    zero = _rms_per_sample(ppe_residual_rows(torch.zeros_like(batch.y), batch), batch)
    assert zero == pytest.approx([1.0] * 3, rel=1e-4)
    scaled = _rms_per_sample(ppe_residual_rows(1.5 * batch.y, batch), batch)
    assert scaled == pytest.approx([0.5] * 3, abs=LABEL_TOLERANCE)


def test_residual_rows_of_a_batch_are_each_samples_own(systems):
    items = [systems[i] for i in range(3)]
    g = torch.Generator().manual_seed(0)
    fields = [torch.randn(it.num_nodes, generator=g) * 1e3 for it in items]
    batch = Batch.from_data_list(items)
    together = ppe_residual_rows(torch.cat(fields), batch)
    pairs = zip(fields, items, strict=True)
    alone = torch.cat([ppe_residual_rows(f, Batch.from_data_list([it])) for f, it in pairs])
    torch.testing.assert_close(together, alone)


def test_a_sample_whose_file_settings_did_not_make_it_is_refused(tiny_data, monkeypatch):
    samples = PressureSamples(tiny_data, split="train")
    real = samples.scene_attributes

    def other_beta(idx):
        attrs = real(idx)
        attrs["config"] = attrs["config"].replace("surface_beta: 0.97", "surface_beta: 0.5")
        return attrs

    monkeypatch.setattr(samples, "scene_attributes", other_beta)
    with pytest.raises(LagfluidError, match=r"pressure sample 0: .*(unknowns|residual)"):
        WithPPESystem(samples)[0]


def test_training_with_the_ppe_term_records_its_weight_and_refuses_a_bad_one(tiny_data, tmp_path):
    common = [
        "task=train",
        "model=fgn",
        "stage=pressure",
        "data=tiny",
        f"data.out_dir={tiny_data}",
        "progress=false",
        "train.iterations.pressure=4",
        "train.batch_size.pressure=2",
        "train.stat_samples=4",
        "train.valid_every=2",
    ]
    (summary,) = train(_compose(*common, f"out_dir={tmp_path / 'ppe'}", "train.ppe_weight=0.1"))
    assert summary["step"] == 4
    meta = read_checkpoint(tmp_path / "ppe" / "pressure.pt")["meta"]
    assert '"ppe_weight": 0.1' in meta["identity"]
    with pytest.raises(ConfigError, match=r"train.ppe_weight must be a finite number >= 0, got -1.0"):
        PressureTrainable("pressure", {}, ppe_weight=-1.0)


def test_a_sample_differing_only_at_the_surface_threshold_gets_no_ppe_term(tiny_data, monkeypatch):
    samples = PressureSamples(tiny_data, split="train")
    real = samples.get

    def one_node_less(idx):
        item = real(idx)
        item.particle_id = item.particle_id[:-1]  # as if one particle sat at n = beta n0 to rounding
        return item

    monkeypatch.setattr(samples, "get", one_node_less)
    item = WithPPESystem(samples)[0]
    assert item.ppe_index.shape == (2, 0) and not item.ppe_b.any()
    rows = ppe_residual_rows(torch.randn(item.num_nodes), Batch.from_data_list([item]))
    assert not rows.any()


def test_without_the_ppe_term_a_pressure_run_keeps_its_earlier_fingerprint():
    assert PressureTrainable("pressure", {}).identity() == {"materials": None}  # resumable across the change
    assert PressureTrainable("pressure", {}, ppe_weight=0.5).identity() == {
        "materials": None,
        "ppe_weight": 0.5,
    }
