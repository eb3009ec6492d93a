"""A third-party model's whole path through lagfluid: registered by entry points only, then trained with
``task=train``, rolled out with ``task=simulate``, evaluated with ``task=evaluate`` and listed and run in
``benchmarks.tables``, with no line of ``lagfluid`` or ``benchmarks`` naming it.

The plugin (``tests/plugins/tinymlp``) is copied into a temporary site folder beside a ``dist-info`` whose
``entry_points.txt`` is what ``pip install`` of a package declaring the groups would write; the command
line runs see it through ``PYTHONPATH``, the in-process ones through ``sys.path``.
"""

import importlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from lagfluid.models.checkpoint import read_checkpoint

REPO = Path(__file__).resolve().parents[1]
PLUGIN = Path(__file__).resolve().parent / "plugins" / "tinymlp"
ENTRY_POINTS = """\
[lagfluid.simulators]
tiny_mlp = tinymlp.model:build_simulator

[lagfluid.trainables]
tiny_mlp = tinymlp.model:build_trainables

[lagfluid.configs]
tiny_mlp = tinymlp.conf
"""


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A site folder holding the plugin as an installed distribution; on sys.path for this module."""
    root = tmp_path_factory.mktemp("site")
    shutil.copytree(PLUGIN, root / "tinymlp", ignore=shutil.ignore_patterns("__pycache__"))
    dist = root / "tinymlp-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: tinymlp\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(ENTRY_POINTS)
    sys.path.insert(0, str(root))
    importlib.invalidate_caches()
    yield root
    sys.path.remove(str(root))
    for name in [m for m in sys.modules if m == "tinymlp" or m.startswith("tinymlp.")]:
        del sys.modules[name]


def _cli(site, *args, timeout=300):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(REPO)]), "OMP_NUM_THREADS": "1"}
    out = subprocess.run(
        [sys.executable, "-m", "lagfluid.run", *args, "threads=1", "progress=false"],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
        cwd=REPO,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return out


@pytest.fixture(scope="module")
def trained(site, tmp_path_factory):
    """Tiny MPS data, then ``task=train model=tiny_mlp``; the weights are shipped into the plugin."""
    work = tmp_path_factory.mktemp("plugin_run")
    data, run = work / "data", work / "train"
    _cli(site, "task=generate", "scene=random", "data=tiny", f"data.out_dir={data}")
    _cli(
        site,
        "task=train",
        "model=tiny_mlp",
        "train=tiny_mlp",
        "data=tiny",
        f"data.out_dir={data}",
        f"out_dir={run}",
    )
    (site / "tinymlp" / "weights").mkdir()
    shutil.copy(run / "tiny_mlp.pt", site / "tinymlp" / "weights" / "tiny_mlp.pt")
    return work, run


def test_nothing_in_lagfluid_or_benchmarks_names_the_plugin():
    for folder in ("lagfluid", "benchmarks"):
        for path in (REPO / folder).rglob("*.py"):
            text = path.read_text()
            assert "tiny_mlp" not in text and "tinymlp" not in text, path


def test_the_plugin_model_composes_from_its_own_config_folder(site):
    from hydra import compose, initialize_config_dir

    from lagfluid.run import CONF_DIR, available_models, check_command_line

    assert "tiny_mlp" in available_models()
    assert check_command_line(["model=tiny_mlp", "train=tiny_mlp"]) is None
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="config", overrides=["model=tiny_mlp", "train=tiny_mlp"])
    assert cfg.model.tiny_mlp.hidden == 16 and cfg.train.iterations.tiny_mlp == 20
    with pytest.raises(Exception, match="hiden"):  # struct mode still on for plugin groups
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            compose(config_name="config", overrides=["model=tiny_mlp", "model.tiny_mlp.hiden=3"])


def test_train_writes_a_checkpoint_of_the_plugin_model(trained):
    _, run = trained
    ckpt = read_checkpoint(run / "tiny_mlp.pt", kind="tiny_mlp", model="tiny_mlp")
    assert ckpt["step"] == 20 and ckpt["model"] == "tiny_mlp"
    rows = (run / "tiny_mlp_loss.csv").read_text().splitlines()
    assert rows[0].startswith("iteration") and len(rows) == 1 + 4  # every 5 of 20 iterations


def test_simulate_runs_the_plugin_at_its_own_time_step(site, trained):
    work, _ = trained
    out = work / "simulate"
    _cli(site, "model=tiny_mlp", "scene=dam_small", "steps=10", f"out_dir={out}")
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["model"] == "tiny_mlp" and metrics["complete"], metrics["stop_reason"]
    assert metrics["dt"] == pytest.approx(0.004)  # the spacing of data=tiny's frames: 2 steps of 2 ms
    assert metrics["parameters"] == 7 * 16 + 16 + 16 * 16 + 16 + 16 * 3 + 3
    assert set(metrics["stage_median_s"]) == {"network"}
    assert (out / "rollout.h5").is_file() and (out / "preview.png").is_file()


def test_evaluate_compares_the_plugin_with_mps_over_the_same_time(site, trained):
    work, _ = trained
    out, ref = work / "evaluate", work / "reference"
    args = ("task=evaluate", "model=tiny_mlp", "scene=dam_small", "steps=10", "write_every=5")
    _cli(site, *args, f"out_dir={out}", f"evaluate.reference_dir={ref}", "evaluate.figures=false")
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["model"] == "tiny_mlp" and metrics["dt"] == pytest.approx(0.004)
    # MPS ran 20 steps of 2 ms: the three stored frames (0, 20, 40 ms) are compared at equal times
    assert metrics["reference"]["key"]["steps"] == 20 and metrics["frames"]["time_s"] == pytest.approx(
        [0.0, 0.02, 0.04]
    )
    assert metrics["frames"]["chamfer_mm"][0] == 0.0 and metrics["frames"]["chamfer_mm"][-1] > 0.0
    assert all(v is None for v in metrics["frames"]["advection_nmae"])  # an end-to-end model: no stages


def test_the_tables_list_and_run_the_plugin(site, trained, tmp_path):
    from benchmarks.tables.cli import main
    from benchmarks.tables.simulators import all_simulators

    assert "tiny_mlp" in [s.key for s in all_simulators()]
    results, runs = tmp_path / "results", tmp_path / "runs"
    # what a plugin's author runs: its rows beside MPS and FGN, not the whole zoo's (0.4 min against 2.1)
    argv = ["--quick", "--simulators", "tiny_mlp", "--threads", "1", "--results", str(results)]
    assert main([*argv, "--runs-dir", str(runs)]) == 0
    assert not (results / "tables_quick_report.md").exists()  # the whole zoo's files are not replaced
    report = (results / "tables_quick_tiny_mlp_report.md").read_text()
    assert "only tiny_mlp beside MPS and FGN (--simulators)" in report
    listed = {line.split(" | ")[1] for line in report.splitlines() if line.startswith("| `dam_small`")}
    assert listed == {"Ground truth (MPS)", "FGN", "tiny_mlp"}, listed
    rows = [line for line in report.splitlines() if "| tiny_mlp |" in line]
    # Tables 1/3 (dam and water fall, against the same MPS references as every other row), Table 2 (time
    # per step, with its parameter count) and the trade-off table; the tiny net may be stopped by the guard
    assert sum(line.startswith(("| `dam_small`", "| `waterfall`")) for line in rows) == 2, rows
    assert any(
        line.startswith(f"| tiny_mlp | {7 * 16 + 16 + 16 * 16 + 16 + 16 * 3 + 3} |") for line in rows
    ), rows
    assert all("complete" in line or "stopped" in line for line in rows), rows
