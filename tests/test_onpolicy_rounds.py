"""``train.onpolicy.rounds``: DAgger rounds after the one-step training, resumable, exported (seconds)."""

import hashlib
import json
import shutil

import h5py
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from lagfluid.data.layout import GROUP
from lagfluid.errors import ConfigError
from lagfluid.models.checkpoint import read_checkpoint
from lagfluid.run import CONF_DIR
from lagfluid.tasks.generate import generate
from lagfluid.tasks.train import train


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny_rounds")
    generate(_compose("task=generate", "scene=random", "data=tiny", f"data.out_dir={out}", "progress=false"))
    return out


def _train_cfg(data, out, *extra):
    short = [f"train.iterations.{n}=2" for n in ("advection", "collision", "pressure")]
    return _compose(
        "task=train", "model=fgn", "scene=random", "data=tiny", f"data.out_dir={data}", f"out_dir={out}",
        "progress=false", "threads=1", *short, "train.checkpoint_every=1", "train.stat_samples=2",
        "train.onpolicy.iterations=3", *extra,
    )  # fmt: skip


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def _policy_networks(data_dir):
    return json.loads((data_dir / "metadata.json").read_text())["policy"]["networks"]


def test_each_round_rolls_out_the_previous_rounds_nets_and_fine_tunes_from_them(tiny_data, tmp_path):
    out, export = tmp_path / "run", tmp_path / "export"
    export.mkdir()
    train(_train_cfg(tiny_data, out, "train.onpolicy.rounds=2", f"export_to={export}"))
    r1, r2 = out / "onpolicy" / "round1", out / "onpolicy" / "round2"
    # round 1's scenes were moved by the one-step nets, round 2's by round 1's fine-tuned pressure net
    assert _policy_networks(r1 / "data")["pressure"] == _sha(out / "pressure.pt")
    assert _policy_networks(r2 / "data")["pressure"] == _sha(r1 / "pressure.pt")
    assert _policy_networks(r2 / "data")["advection"] == _sha(r1 / "advection.pt")
    for k, here in ((1, r1), (2, r2)):
        identity = json.loads(read_checkpoint(here / "pressure.pt")["meta"]["identity"])
        assert identity["init_from"] == str((out if k == 1 else r1).resolve())
        assert identity["iterations"] == 3 and identity["lr"][0] == 3e-4
    # the export is the last round's pressure net beside the one-step advection and collision nets
    for name, source in (("pressure", r2), ("advection", out), ("collision", out)):
        mine, shipped = read_checkpoint(source / f"{name}.pt"), read_checkpoint(export / f"{name}.pt")
        for key, value in mine["state_dict"].items():
            assert torch.equal(value, shipped["state_dict"][key]), (name, key)
    tuned = read_checkpoint(r2 / "pressure.pt")["state_dict"]
    first = read_checkpoint(out / "pressure.pt")["state_dict"]
    assert any(not torch.equal(tuned[k], first[k]) for k in tuned)


def test_aggregate_fine_tunes_round_k_on_the_data_of_rounds_1_to_k(tiny_data, tmp_path):
    out = tmp_path / "run"
    train(_train_cfg(tiny_data, out, "train.onpolicy.rounds=2", "train.onpolicy.aggregate=true"))
    identity = json.loads(read_checkpoint(out / "onpolicy" / "round2" / "pressure.pt")["meta"]["identity"])
    assert identity["data"]["dir"] == str((out / "onpolicy" / "round2" / "data").resolve())
    round1 = str((out / "onpolicy" / "round1" / "data").resolve())
    assert [d["dir"] for d in identity["extra_data"]] == [round1]


def test_scenes_generated_two_at_a_time_are_the_scenes_generated_one_after_another(tiny_data, tmp_path):
    train(_train_cfg(tiny_data, tmp_path / "one_step"))  # the same policy networks for both, byte for byte
    for jobs in (1, 2):
        shutil.copytree(tmp_path / "one_step", tmp_path / f"jobs{jobs}")
        cfg = _train_cfg(
            tiny_data, tmp_path / f"jobs{jobs}", "train.onpolicy.rounds=1", f"train.onpolicy.jobs={jobs}"
        )
        train(cfg)
    one, two = (tmp_path / f"jobs{j}" / "onpolicy" / "round1" / "data" for j in (1, 2))
    assert json.loads((two / "metadata.json").read_text())["num_scenes"] == 3
    for k in range(3):
        with (
            h5py.File(one / "scenes" / f"scene_{k:05d}.h5") as a,
            h5py.File(two / "scenes" / f"scene_{k:05d}.h5") as b,
        ):
            assert a[GROUP].attrs["fingerprint"] == b[GROUP].attrs["fingerprint"]
            np.testing.assert_array_equal(a[GROUP]["position"][:], b[GROUP]["position"][:])


def test_a_rerun_resumes_and_regenerates_nothing(tiny_data, tmp_path):
    out = tmp_path / "run"
    train(_train_cfg(tiny_data, out, "train.onpolicy.rounds=1"))
    scene = next((out / "onpolicy" / "round1" / "data" / "scenes").glob("*.h5"))
    stamp = scene.stat().st_mtime_ns, _sha(out / "onpolicy" / "round1" / "pressure.pt")
    train(_train_cfg(tiny_data, out, "train.onpolicy.rounds=1"))
    assert (scene.stat().st_mtime_ns, _sha(out / "onpolicy" / "round1" / "pressure.pt")) == stamp


def test_rounds_start_from_a_folder_of_weights_and_train_nothing_before(tiny_data, tmp_path):
    start, out = tmp_path / "start", tmp_path / "run"
    train(_train_cfg(tiny_data, start))  # e.g. the shipped weights or another run's
    cfg = _train_cfg(
        tiny_data, out, "train.onpolicy.rounds=1", f"train.onpolicy.start_from={start}",
        "train.onpolicy.trainables=[advection,pressure]",
    )  # fmt: skip
    train(cfg)
    r1 = out / "onpolicy" / "round1"
    assert sorted(p.name for p in out.glob("*.pt")) == []  # no one-step training in out_dir
    networks = _policy_networks(r1 / "data")
    assert {name: networks[name] for name in ("advection", "collision", "pressure")} == {
        name: _sha(start / f"{name}.pt") for name in ("advection", "collision", "pressure")
    }
    for name in ("advection", "pressure"):
        identity = json.loads(read_checkpoint(r1 / f"{name}.pt")["meta"]["identity"])
        assert identity["init_from"] == str(start.resolve()) and identity["iterations"] == 3
    # the collision net, not fine-tuned, is the start folder's beside them
    mine, theirs = read_checkpoint(r1 / "collision.pt"), read_checkpoint(start / "collision.pt")
    for key, value in theirs["state_dict"].items():
        assert torch.equal(value, mine["state_dict"][key]), key


def test_rounds_refuse_a_start_folder_that_is_not_there_or_lacks_a_network(tiny_data, tmp_path):
    missing = tmp_path / "nowhere"
    with pytest.raises(ConfigError, match=rf"train.onpolicy.start_from={missing} is not a folder"):
        train(
            _train_cfg(
                tiny_data, tmp_path / "run", "train.onpolicy.rounds=1", f"train.onpolicy.start_from={missing}"
            )
        )
    half = tmp_path / "half"
    train(_train_cfg(tiny_data, half, "stage=advection"))
    with pytest.raises(
        ConfigError, match=r"collision.pt, pressure.pt are not in .*half; set train.onpolicy.start_from"
    ):
        train(
            _train_cfg(
                tiny_data, tmp_path / "run", "train.onpolicy.rounds=1", f"train.onpolicy.start_from={half}"
            )
        )
    assert not (tmp_path / "run" / "onpolicy").exists()


def test_rounds_refuse_a_command_that_does_not_remake_the_datasets_scenes(tiny_data, tmp_path):
    cfg = _train_cfg(tiny_data, tmp_path / "run", "train.onpolicy.rounds=1", "scene=dam")
    with pytest.raises(ConfigError, match=r"scene=dam; the dataset's is scene=random"):
        train(cfg)
    assert not (tmp_path / "run" / "onpolicy").exists()


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("train.onpolicy.rounds=-1", r"train.onpolicy.rounds must be a whole number >= 0, got -1"),
        ("train.onpolicy.trainables=[gns]", r"train.onpolicy.trainables=\['gns'\]: model fgn trains"),
        ("train.onpolicy.iterations=0", r"train.onpolicy.iterations must be a whole number >= 1, got 0"),
        ("train.onpolicy.jobs=0", r"train.onpolicy.jobs must be a whole number >= 1, got 0"),
    ],
)
def test_bad_round_settings_are_refused_naming_the_value(tiny_data, tmp_path, override, message):
    cfg = _train_cfg(tiny_data, tmp_path / "run", "train.onpolicy.rounds=1", override)
    with pytest.raises(ConfigError, match=message):
        train(cfg)
