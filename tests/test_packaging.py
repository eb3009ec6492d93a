"""A non-editable install (a wheel, ``pip install .``) carries the configs and runs the CLI (seconds)."""

import subprocess
import sys
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_a_wheel_carries_the_configs_and_its_cli_composes_from_them(tmp_path):
    built = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(tmp_path / "dist"), str(REPO)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert built.returncode == 0, built.stderr[-2000:]
    (wheel,) = (tmp_path / "dist").glob("lagfluid-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    for name in (
        "lagfluid/conf/config.yaml",
        "lagfluid/conf/model/fgn.yaml",
        "baselines/gns/conf/model/gns.yaml",
        # the published networks, the default weights of model=fgn_original and cconv_original, with licences
        "lagfluid/weights/fgn_original/adv_net.npz",
        "lagfluid/weights/fgn_original/prs_net.scalers.json",
        "lagfluid/weights/fgn_original/LICENSE",
        "lagfluid/weights/fgn_original/MODEL_CARD.md",
        "baselines/cconv/weights/dlf/pretrained_model_weights.pt",
        "baselines/cconv/weights/dlf/LICENSE-CDLA-Permissive-1.0",
        "baselines/cconv/weights/dlf/MODEL_CARD.md",
    ):
        assert name in names, name
    target = tmp_path / "site"
    installed = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target), str(wheel)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert installed.returncode == 0, installed.stderr[-2000:]
    # from a folder outside the repository, with the installed copy first on the path
    env = {"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1"}
    where = subprocess.run(
        [sys.executable, "-c", "import lagfluid.run as r; print(r.CONF_DIR)"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert where.stdout.strip() == str(target / "lagfluid" / "conf"), where.stderr[-2000:]
    job = subprocess.run(
        [sys.executable, "-m", "lagfluid.run", "model=gns", "scene=dam", "--cfg", "job"],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert job.returncode == 0, job.stderr[-2000:]
    assert "name: gns" in job.stdout and "name: dam" in job.stdout
