#!/usr/bin/env bash
# FGN's CUDA path checked in one run on a GPU machine (never run yet: no GPU has been lent to this project):
#   1. the CUDA tests (rollouts on CUDA against the CPU's; neighbour search and operators on the device);
#   2. the host synchronisations per step as torch reports them (benchmarks.host_syncs --device cuda:
#      host_syncs_cuda.md, against the CPU's count in benchmarks/results/host_syncs.md);
#   3. Table 2 at 40k fluid particles on CUDA (benchmarks.tables --device cuda; every model's step);
#   4. a 1M-particle dam (100 x 100 x 100 l0 of fluid), FGN and MPS: median and mean ms per step
#      (goal of issue 19: FGN < 100 ms per step).
# Each part runs even when an earlier one fails (a GPU session is scarce); the exit status is 1 if any did.
# Everything lands in ${OUT:-runs/gpu_check}: logs, the Table 2 files (tables/), each run's metrics.json.
# Usage: bash benchmarks/gpu_check.sh [steps of the 1M dam, default 30]
set -uo pipefail
out=${OUT:-runs/gpu_check}
steps=${1:-30}
mkdir -p "$out"
rc=0
python - <<'PY' || exit 1
import torch
assert torch.cuda.is_available(), "benchmarks/gpu_check.sh needs a CUDA device; torch sees none"
print("device:", torch.cuda.get_device_name(), "torch", torch.__version__)
PY

python -m pytest -q -p no:cacheprovider -k cuda \
    tests/test_host_syncs.py tests/test_neighbors.py tests/test_operators.py 2>&1 | tee "$out/cuda_tests.log" || rc=1

python -m benchmarks.host_syncs --device cuda --results "$out" 2>&1 | tee "$out/host_syncs.log" || rc=1

python -m benchmarks.tables --only table2 --device cuda --threads "$(nproc)" \
    --results "$out/tables" --runs-dir "$out/runs" 2>&1 | tee "$out/table2.log" || rc=1

for model in fgn mps; do
    python -m lagfluid.run task=simulate model="$model" scene=dam_large "scene.fluid_size=[100,100,100]" \
        "scene.tank_size=[201,101]" device=cuda steps="$steps" write_every="$steps" progress=false \
        out_dir="$out/dam_1m_$model" 2>&1 | tail -n 2 | tee "$out/dam_1m_$model.log" || rc=1
done
python - "$out" <<'PY' || rc=1
import json, sys
from pathlib import Path
for model in ("fgn", "mps"):
    path = Path(sys.argv[1]) / f"dam_1m_{model}" / "metrics.json"
    if not path.is_file():
        print(f"1M dam, {model}: no metrics ({path} missing: see dam_1m_{model}.log)")
        continue
    m = json.loads(path.read_text())
    print(f"1M dam, {model}: {1e3 * m['time_per_step_median_s']:.1f} ms/step median, "
          f"{1e3 * m['time_per_step_mean_s']:.1f} mean over {m['steps']} steps")
PY
exit "$rc"
