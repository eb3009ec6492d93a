"""The generic trainer and the trainables registry: lagfluid/tasks/train.py names no model (seconds)."""

import csv
import hashlib
import json
import re
import time

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import open_dict
from torch import nn
from torch_geometric.data import Data

from lagfluid import registry
from lagfluid.data.datasets import load_metadata
from lagfluid.errors import ConfigError
from lagfluid.models.checkpoint import read_checkpoint
from lagfluid.models.trainable import Trainable
from lagfluid.progress import progress_bar
from lagfluid.registry import UnknownNameError, get_trainables, trainable_models
from lagfluid.run import CONF_DIR
from lagfluid.tasks.generate import generate
from lagfluid.tasks.train import CSV_HEADER, Trainer, train


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


class LinearFit:
    """A toy trainable: a linear map fitted to y = x @ W, no FGN anywhere."""

    model = "toy"
    loss = None

    def __init__(self, name: str) -> None:
        self.name, self.options = name, {"width": 3}

    def datasets(self, data_dir):
        g = torch.Generator().manual_seed(0)
        w = torch.tensor([[1.0, -2.0, 0.5]]).T
        items = []
        for _ in range(8):
            x = torch.randn(5, 3, generator=g)
            items.append(Data(x=x, y=x @ w, num_nodes=5))
        return items[:6], items[6:]

    def build_network(self):
        return nn.Linear(self.options["width"], 1)

    def fit_statistics(self, net, items):
        return {"items": len(items)}

    def predict(self, net, batch):
        return net(batch.x), batch.y

    def identity(self):
        return {}


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny_train")
    generate(_compose("task=generate", "scene=random", "data=tiny", f"data.out_dir={out}", "progress=false"))
    return out


def test_fgn_trainables_come_from_the_registry():
    assert {"fgn", "hybrid"} <= set(trainable_models())
    trainables = get_trainables("fgn", _compose("task=train", "model=fgn"))
    assert list(trainables) == ["advection", "collision", "pressure"]
    for name, t in trainables.items():
        assert isinstance(t, Trainable) and t.name == name and t.model == "fgn"


def test_a_model_without_trainables_is_a_clear_error(tiny_data, tmp_path):
    listed = (
        r"model 'mps' has nothing to train.*fgn, fgn_gcn, fgn_mlp, fgn_sage, fgn_trained_here, gns, hybrid"
    )
    with pytest.raises(UnknownNameError, match=listed):
        train(_compose("task=train", "model=mps", f"data.out_dir={tiny_data}", f"out_dir={tmp_path}"))


def test_the_generic_loop_trains_any_registered_trainable(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setitem(registry._REGISTERED_TRAINABLES, "fgn", lambda cfg: {"line": LinearFit("line")})
    cfg = _compose(
        "task=train",
        "model=fgn",
        "data=tiny",
        f"data.out_dir={tiny_data}",
        f"out_dir={tmp_path}",
        "progress=false",
        "+train.iterations.line=60",
        "+train.batch_size.line=2",
        "train.log_every=10",
        "train.valid_every=30",
        "train.checkpoint_every=30",
        "train.lr_start=0.1",
        "train.lr_end=0.05",
    )
    (summary,) = train(cfg)
    assert summary["kind"] == "line" and summary["step"] == 60
    ckpt = read_checkpoint(tmp_path / "line.pt", "line", model="toy")
    assert ckpt["meta"]["stats"] == {"items": 6} and ckpt["options"] == {"width": 3}
    with (tmp_path / "line_loss.csv").open() as f:
        losses = [float(r["train_loss"]) for r in csv.DictReader(f)]
    assert len(losses) == 6 and losses[-1] < 0.2 * losses[0], losses
    with pytest.raises(ConfigError, match=r"unknown stage 'advection' of model fgn; available: line, all"):
        train(_compose("task=train", "model=fgn", "stage=advection", f"data.out_dir={tiny_data}"))


def test_extra_data_trains_on_the_union_of_the_datasets_train_splits(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setitem(registry._REGISTERED_TRAINABLES, "fgn", lambda cfg: {"line": LinearFit("line")})
    common = ["task=train", "model=fgn", "data=tiny", f"data.out_dir={tiny_data}", "progress=false"]
    common += ["+train.iterations.line=1", "+train.batch_size.line=2"]
    train(_compose(*common, f"out_dir={tmp_path / 'one'}"))
    train(_compose(*common, f"out_dir={tmp_path / '2'}", f"train.extra_data=[{tiny_data}]"))
    one, two = (read_checkpoint(tmp_path / d / "line.pt", "line", model="toy")["meta"] for d in ("one", "2"))
    assert one["stats"] == {"items": 6} and two["stats"] == {"items": 12}  # 6 training items per dataset
    assert one["fingerprint"] != two["fingerprint"]  # a resume never mixes the two


def test_init_from_fine_tunes_trained_weights_with_their_statistics(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setitem(registry._REGISTERED_TRAINABLES, "fgn", lambda cfg: {"line": LinearFit("line")})
    common = [
        "task=train",
        "model=fgn",
        "data=tiny",
        f"data.out_dir={tiny_data}",
        "progress=false",
        "+train.batch_size.line=2",
        "train.log_every=1",
        "train.checkpoint_every=1",
    ]
    first = tmp_path / "first"
    train(
        _compose(
            *common, f"out_dir={first}", "+train.iterations.line=20", "train.lr_start=0.1", "train.lr_end=0.1"
        )
    )
    trained = read_checkpoint(first / "line.pt")["state_dict"]
    second = tmp_path / "second"
    monkeypatch.setattr(
        LinearFit, "fit_statistics", lambda self, net, items: pytest.fail("statistics refitted")
    )
    train(
        _compose(
            *common,
            f"out_dir={second}",
            "+train.iterations.line=1",
            "train.lr_start=1e-12",
            "train.lr_end=1e-12",
            f"train.init_from={first}",
        )
    )
    tuned = read_checkpoint(second / "line.pt")
    torch.testing.assert_close(tuned["state_dict"]["weight"], trained["weight"])
    assert tuned["meta"]["stats"] == {"items": 6} and "init_from" in tuned["meta"]["identity"]
    monkeypatch.setattr(LinearFit, "build_network", lambda self: nn.Linear(3, 1, bias=False))
    monkeypatch.setattr(
        LinearFit,
        "__init__",
        lambda self, name: (
            setattr(self, "name", name) or setattr(self, "options", {"width": 3, "bias": False})
        ),
    )
    with pytest.raises(ConfigError, match="has network options"):
        train(
            _compose(
                *common,
                f"out_dir={tmp_path / 'third'}",
                "+train.iterations.line=1",
                f"train.init_from={first}",
            )
        )


def test_init_from_per_trainable_and_zero_iterations_keep_a_published_net(tiny_data, tmp_path, monkeypatch):
    # {line: DIR} starts only that net from DIR (the other afresh); iterations 0 keeps its weights as they are
    monkeypatch.setitem(
        registry._REGISTERED_TRAINABLES,
        "fgn",
        lambda cfg: {"line": LinearFit("line"), "plane": LinearFit("plane")},
    )
    common = ["task=train", "model=fgn", "data=tiny", f"data.out_dir={tiny_data}", "progress=false"]
    common += [
        "+train.batch_size.line=2",
        "+train.batch_size.plane=2",
        "train.lr_start=0.1",
        "train.lr_end=0.1",
    ]
    first = tmp_path / "published"
    train(_compose(*common, f"out_dir={first}", "+train.iterations.line=20", "+train.iterations.plane=20"))
    second = tmp_path / "second"
    cfg = _compose(
        *common, f"out_dir={second}", "+train.iterations.line=0", "+train.iterations.plane=1",
        f"train.init_from={{line: '{first}'}}",
    )  # fmt: skip
    train(cfg)
    published, kept = read_checkpoint(first / "line.pt"), read_checkpoint(second / "line.pt")
    for key, value in published["state_dict"].items():
        assert torch.equal(kept["state_dict"][key], value), key
    assert kept["step"] == 0 and kept["meta"]["stats"] == {"items": 6}
    fresh = json.loads(read_checkpoint(second / "plane.pt")["meta"]["identity"])
    assert "init_from" not in fresh  # the plane started afresh
    with open_dict(cfg):
        cfg.train.init_from = 3
    with pytest.raises(
        ConfigError, match=r"train.init_from must be a folder of checkpoints or \{trainable: folder\}, got 3"
    ):
        train(cfg)


def test_export_to_copies_the_trained_networks_without_optimizer_state(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setitem(registry._REGISTERED_TRAINABLES, "fgn", lambda cfg: {"line": LinearFit("line")})
    exported = tmp_path / "shipped"
    train(
        _compose(
            "task=train",
            "model=fgn",
            "data=tiny",
            f"data.out_dir={tiny_data}",
            f"out_dir={tmp_path / 'run'}",
            f"export_to={exported}",
            "progress=false",
            "+train.iterations.line=3",
            "+train.batch_size.line=2",
        )
    )
    run, shipped = read_checkpoint(tmp_path / "run" / "line.pt"), read_checkpoint(exported / "line.pt")
    assert "optimizer" in run and "optimizer" not in shipped and "rng" not in shipped
    torch.testing.assert_close(shipped["state_dict"], run["state_dict"])
    assert shipped["step"] == 3 and shipped["meta"]["stats"] == run["meta"]["stats"]


def test_export_to_under_a_missing_folder_is_refused_naming_it(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setitem(registry._REGISTERED_TRAINABLES, "fgn", lambda cfg: {"line": LinearFit("line")})
    bad = tmp_path / "no" / "such" / "weights"
    cfg = _compose(
        "task=train",
        "model=fgn",
        "data=tiny",
        f"data.out_dir={tiny_data}",
        f"out_dir={tmp_path / 'run'}",
        f"export_to={bad}",
        "progress=false",
        "+train.iterations.line=1",
        "+train.batch_size.line=2",
    )
    with pytest.raises(ConfigError, match=r"export_to=.*its parent folder .* does not exist"):
        train(cfg)
    assert not bad.parent.exists()


def test_export_to_an_existing_file_is_refused_before_the_training(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setitem(registry._REGISTERED_TRAINABLES, "fgn", lambda cfg: {"line": LinearFit("line")})
    a_file = tmp_path / "weights"
    a_file.write_text("mine")
    cfg = _compose(
        "task=train",
        "model=fgn",
        "data=tiny",
        f"data.out_dir={tiny_data}",
        f"out_dir={tmp_path / 'run'}",
        f"export_to={a_file}",
        "progress=false",
        "+train.iterations.line=3",
        "+train.batch_size.line=2",
    )
    with pytest.raises(
        ConfigError, match=rf"^export_to={a_file} is a file, not a folder for the trained networks$"
    ):
        train(cfg)
    assert not (tmp_path / "run" / "line.pt").exists()  # refused before the training, not after it
    assert a_file.read_text() == "mine"


def _two_lines(monkeypatch):
    """Model fgn trains two toy trainables, ``a`` then ``b``."""
    monkeypatch.setitem(
        registry._REGISTERED_TRAINABLES, "fgn", lambda cfg: {"a": LinearFit("a"), "b": LinearFit("b")}
    )
    return [
        "task=train",
        "model=fgn",
        "data=tiny",
        "progress=false",
        "+train.iterations.a=5",
        "+train.iterations.b=2",
        "+train.batch_size.a=2",
        "+train.batch_size.b=2",
        "train.log_every=2",
        "train.valid_every=2",
        "train.checkpoint_every=3",
    ]


def _logged(path):
    with path.open() as f:  # every column but the wall time
        return [[r["iteration"], r["lr"], r["train_loss"], r["valid_loss"]] for r in csv.DictReader(f)]


def test_max_seconds_stops_after_a_checkpoint_and_the_same_command_continues_exactly(
    tiny_data, tmp_path, monkeypatch
):
    common = [*_two_lines(monkeypatch), f"data.out_dir={tiny_data}"]
    train(_compose(*common, f"out_dir={tmp_path / 'straight'}"))
    # a cap shorter than any iteration: each run trains one iteration, checkpoints it and stops
    capped = [*common, f"out_dir={tmp_path / 'capped'}", "train.max_seconds=1e-9"]
    capped.append(f"export_to={tmp_path / 'x'}")
    steps = []
    for call in range(1, 7):
        summaries = train(_compose(*capped))
        steps.append([(s["kind"], s["step"], s["stopped"]) for s in summaries])
        assert (tmp_path / "x" / "a.pt").exists() == (call == 6)  # the export waits for the end
    assert steps == [
        *([("a", k, True)] for k in range(1, 5)),
        [("a", 5, False), ("b", 1, True)],  # b waits for a's end, then gets its own iteration
        [("a", 5, False), ("b", 2, False)],  # a finished: skipped
    ]
    for name in ("a", "b"):
        runs = [read_checkpoint(tmp_path / run / f"{name}.pt") for run in ("straight", "capped")]
        assert runs[0]["step"] == runs[1]["step"] and runs[1]["step"] == {"a": 5, "b": 2}[name]
        for key, value in runs[0]["state_dict"].items():
            assert torch.equal(value, runs[1]["state_dict"][key]), key
        assert _logged(tmp_path / "capped" / f"{name}_loss.csv") == _logged(
            tmp_path / "straight" / f"{name}_loss.csv"
        )


@pytest.mark.parametrize("value", [0, -3, "abc", True, float("inf")])
def test_a_max_seconds_that_is_not_a_positive_number_is_refused_naming_it(
    tiny_data, tmp_path, monkeypatch, value
):
    cfg = _compose(*_two_lines(monkeypatch), f"data.out_dir={tiny_data}", f"out_dir={tmp_path}")
    cfg.train.max_seconds = value
    with pytest.raises(ConfigError, match=r"^train.max_seconds must be a number of seconds > 0 .*got "):
        train(cfg)
    assert not any(tmp_path.iterdir())


def test_max_seconds_with_onpolicy_rounds_is_refused_before_any_training(tiny_data, tmp_path, monkeypatch):
    cfg = _compose(
        *_two_lines(monkeypatch), "scene=random", f"data.out_dir={tiny_data}", f"out_dir={tmp_path}",
        "train.onpolicy.rounds=1", "train.onpolicy.trainables=[a]", "train.max_seconds=60",
    )  # fmt: skip
    with pytest.raises(ConfigError, match=r"train.max_seconds=60 caps the one-step training, not .*rounds=1"):
        train(cfg)
    assert not any(tmp_path.iterdir())


# ------------------------------------------------------------------- the Trainer's parts on their own
def _line(tiny_data, out_dir, *overrides):
    """A config training the toy ``line`` 4 iterations in batches of 2, lr 0.1 -> 0.05."""
    return _compose(
        "task=train", "model=fgn", "data=tiny", f"data.out_dir={tiny_data}", f"out_dir={out_dir}",
        "progress=false", "+train.iterations.line=4", "+train.batch_size.line=2", "train.lr_start=0.1",
        "train.lr_end=0.05", *overrides,
    )  # fmt: skip


def test_the_trainers_identity_holds_the_optional_settings_only_when_set(tiny_data, tmp_path):
    """Old checkpoints keep their fingerprint: a setting at its default adds no key to the identity."""
    scenes = load_metadata(tiny_data)["splits"]["train"]
    expected = {
        "options": {"width": 3},
        "data": {"dir": str(tiny_data.resolve()), "scenes": scenes},
        "batch_size": 2,
        "lr": [0.1, 0.05],
        "iterations": 4,
    }
    plain = Trainer(_line(tiny_data, tmp_path), LinearFit("line"), tmp_path)
    assert plain.identity == expected and list(plain.identity) == list(expected)
    digest = hashlib.sha256(json.dumps(expected, sort_keys=True).encode()).hexdigest()[:16]
    assert plain.fingerprint == digest
    options = ("+train.loss.line=huber", "+train.lr_milestones=[2]", f"train.init_from={tmp_path}")
    tuned = Trainer(_line(tiny_data, tmp_path, *options), LinearFit("line"), tmp_path)
    assert tuned.identity == {
        **expected,
        "loss": {"name": "huber", "delta": 1.0},
        "schedule": {"milestones": [2], "gamma": 0.5, "eps": 1e-8},
        "init_from": str(tmp_path.resolve()),
    }


def test_a_checkpoint_of_other_settings_is_refused_in_one_line_and_kept(tiny_data, tmp_path, monkeypatch):
    monkeypatch.setitem(registry._REGISTERED_TRAINABLES, "fgn", lambda cfg: {"line": LinearFit("line")})
    train(_line(tiny_data, tmp_path))
    ckpt = tmp_path / "line.pt"
    saved, meta = ckpt.read_bytes(), read_checkpoint(ckpt)["meta"]
    Trainer(_line(tiny_data, tmp_path), LinearFit("line"), tmp_path).check_resume(meta)  # the same run's
    other = _line(tiny_data, tmp_path, "train.batch_size.line=3")
    message = (
        f"^{re.escape(str(ckpt))} was trained with other settings \\(network options, data, batch size, "
        "schedule\\); use another out_dir or delete it to start afresh$"
    )
    with pytest.raises(ConfigError, match=message):
        Trainer(other, LinearFit("line"), tmp_path).check_resume(meta)
    with pytest.raises(ConfigError, match=message):  # a LagfluidError: one line from the command line
        train(other)
    assert ckpt.read_bytes() == saved


def test_the_stop_rules_are_all_iterations_and_max_seconds_after_any_iteration_but_the_last(
    tiny_data, tmp_path
):
    cfg, now = _line(tiny_data, tmp_path), time.monotonic()
    past, future, uncapped = (
        Trainer(cfg, LinearFit("line"), tmp_path, d) for d in (now - 1, now + 3600, None)
    )
    assert past.out_of_time(last=False) and not past.out_of_time(last=True)  # the last one ends the run
    assert not future.out_of_time(last=False) and not uncapped.out_of_time(last=False)
    assert [(setattr(past, "step", k), past.finished())[1] for k in range(6)] == [False] * 4 + [True] * 2


def test_one_iteration_is_one_adam_step_at_its_rate_logged_and_saved_for_the_resume(tiny_data, tmp_path):
    trainer = Trainer(_line(tiny_data, tmp_path), LinearFit("line"), tmp_path)
    trainer.build()
    assert trainer.resume() is None and trainer.step == 0
    trainer.make_loaders()
    trainer.fit_statistics()
    trainer.to_device()
    trainer.open_log()
    assert trainer.stats == {"items": 6}  # the 6 training items of LinearFit
    batch = next(iter(trainer.loader))
    w, b = trainer.net.weight.detach().clone(), trainer.net.bias.detach().clone()
    residual = batch.x @ w.T + b - batch.y  # (N, 1)
    loss, grad = float(torch.mean(residual**2)), 2 * torch.mean(residual * batch.x, dim=0, keepdim=True)
    lr = trainer.iteration(batch)
    assert lr == 0.1 and trainer.step == 1 and trainer.window == [pytest.approx(loss, rel=1e-6)]
    # Adam's first step moves each weight by lr against the sign of its gradient (m / sqrt(v) = g / |g|)
    torch.testing.assert_close(trainer.net.weight.detach(), w - lr * torch.sign(grad), atol=1e-6, rtol=0)

    trainer.log_row(lr, 0.25, progress_bar(4, enabled=False))
    trainer.csv_file.close()
    assert trainer.window == []
    with trainer.csv_path.open() as f:
        rows = list(csv.reader(f))
    assert rows == [list(CSV_HEADER), ["1", "0.1", f"{loss:.6g}", "0.25", f"{trainer.elapsed:.1f}"]]

    trainer.window = [0.5]  # a loss since the last logged row
    trainer.save()
    again = Trainer(_line(tiny_data, tmp_path), LinearFit("line"), tmp_path)
    again.build()
    assert again.resume() is None
    assert (again.step, again.window, again.stats, again.elapsed) == (1, [0.5], {"items": 6}, trainer.elapsed)
    assert torch.equal(again.net.weight, trainer.net.weight) and torch.equal(again.net.bias, trainer.net.bias)
    moments, saved = again.optimizer.state_dict()["state"], trainer.optimizer.state_dict()["state"]
    assert all(torch.equal(moments[k]["exp_avg_sq"], saved[k]["exp_avg_sq"]) for k in saved)
