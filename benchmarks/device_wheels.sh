#!/usr/bin/env bash
# The Python packages lagfluid needs that the GPU machine's image lacks, as wheels in .whl/ (ignored) for the
# device tool's `carry`: its image has torch, torch-geometric, numba, h5py, scipy, matplotlib, tqdm, pyyaml and
# joblib (.library/device/KINDS.md) but not hydra-core, omegaconf, antlr4-python3-runtime,
# hydra-joblib-launcher or pyevtk. Pure-Python wheels for its Python 3.12; antlr4-python3-runtime 4.9.3 (omegaconf's pin)
# is published as a source archive only, so its wheel is built here. Run here once, with network access:
#   bash benchmarks/device_wheels.sh [folder, default .whl]
# then `run` benchmarks/gpu_day.sh on the device with carry [".whl"] (it installs them first).
set -euo pipefail
cd "$(dirname "$0")/.."
dest=${1:-.whl}
mkdir -p "$dest"
python=python; command -v python >/dev/null || python=python3
"$python" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation py \
    --abi none --platform any -d "$dest" \
    hydra-core==1.3.8 omegaconf==2.3.1 hydra-joblib-launcher==1.2.0 pyevtk==1.7.0
"$python" -m pip wheel -q --no-deps -w "$dest" antlr4-python3-runtime==4.9.3
ls -l "$dest"
