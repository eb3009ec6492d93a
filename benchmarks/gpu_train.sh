#!/usr/bin/env bash
# GNS at the paper's size (model=gns train=gns_paper) and DeepLagrangianFluids' full recipe (model=cconv
# train=cconv_paper) trained for a few minutes each on one CUDA GPU, on a dataset made there first (a GPU
# lease gets a copy of the repository without data/). Never run on a GPU yet: no GPU has been lent.
#   1. data: data=cpu's 12 random scenes (seeds 0-11, half of them column collapses) cut to 200 solver
#      steps (0.4 s: every falling block has landed by ~0.35 s), one one-thread CPU job per scene, all at
#      once (the CPU path that made the shipped weights' data; the GPU stays free). At the 2-core machine's
#      measured <= 0.63 s per step and thread (benchmarks/results/data_generation.md): ~2 min;
#   2. both trainings at once on the one GPU (small graphs, far from filling it), each stopped by
#      train.max_seconds at what is left of the budget after the data, less a reserve for start-up and the
#      last checkpoint. Checkpoints every 1000 (GNS) and 250 (CConv) iterations and at the stop. Each keeps
#      its profile's iterations, schedule and batch (2; 16): the start of the full run, which the same
#      command continues while GPU_TRAIN_WORK (the data and the runs) is still there;
#   3. into $OUT, six flat files: gns.pt and cconv.pt (networks without optimizer state; model=gns or
#      model=cconv with model.weights=$OUT rolls them out), gns_loss.csv, cconv_loss.csv, gpu_train.log
#      (every command's output; the GPU's use every 10 s) and provenance.md (commit, date, nvidia-smi,
#      versions, each command with its exit status and wall time, each training's iterations and losses).
# Time plan for a 15 min lease (~3-4 min of start-up; benchmarks/gpu_day.sh runs gpu_check.sh, then this):
# the default budget, 360 s, is ~2 min of data, ~3.5 min of the two trainings side by side and ~10 s of
# export; a slower data step leaves the trainings less (at least 60 s each). Timeouts end a hung step.
# Each part runs even when another failed (not the trainings without data); exit status 1 if any did.
# Needs lagfluid installed (pip install -e .: the models gns and cconv are plugins found by entry points;
# benchmarks/gpu_day.sh installs it and the packages a bare GPU machine lacks).
# Usage: bash benchmarks/gpu_train.sh [budget in s, default 360]
#   GPU_TRAIN_DRY_RUN=1: the same commands on the CPU at tiny sizes (data=tiny, small networks, seconds of
#   training; tests/test_gpu_train.py). GPU_TRAIN_WORK: the working folder (runs/gpu_train); OUT: where the
#   files go (runs/gpu_train/out); GPU_TRAIN_COMMIT: the commit to record where the copy has no .git.
set -uo pipefail
start=$SECONDS
out=${OUT:-runs/gpu_train/out}
work=${GPU_TRAIN_WORK:-runs/gpu_train}
mkdir -p "$out" "$work" && out=$(cd "$out" && pwd) && work=$(cd "$work" && pwd) || exit 1
cd "$(dirname "$0")/.." || exit 1  # the repository root: python -m lagfluid.run, benchmarks.provenance
python=python; command -v python >/dev/null || python=python3  # some images have only python3
if [ "${GPU_TRAIN_DRY_RUN:-0}" = 1 ]; then
    budget=${1:-20}; reserve=10; least=2; device=cpu; threads=1; jobs=1; scenes=3
    data=(data=tiny data.steps=24 data.next_steps=2)
    gns=(model.gns.latent=8 model.gns.hidden=8 model.gns.blocks=2 train.stat_samples=4)
    cconv=("model.cconv.layer_channels=[4,8,8,3]" train.batch_size.cconv=2 train.stat_samples=2)
    every=(train.log_every=1 train.valid_every=2 train.valid_batches=1)
    gns+=(train.checkpoint_every=2); cconv+=(train.checkpoint_every=2)
else
    budget=${1:-360}; reserve=30; least=60; device=cuda; threads=4; scenes=12
    jobs=$(( $(nproc) < scenes ? $(nproc) : scenes ))
    data=(data=cpu data.steps=200)
    every=()
    gns=(train.log_every=100 train.valid_every=1000 train.checkpoint_every=1000)
    cconv=(train.log_every=50 train.valid_every=500 train.checkpoint_every=250)
fi
back=(gns.pt cconv.pt gns_loss.csv cconv_loss.csv gpu_train.log provenance.md)
for name in "${back[@]}"; do  # never overwrite what is there (an earlier run's results, weights)
    if [ -e "$out/$name" ]; then
        echo "benchmarks/gpu_train.sh: $out/$name exists: move it, or set OUT" >&2
        exit 1
    fi
done
log=$work/gpu_train.log
steps=$work/steps.tsv  # one line per command: name, exit status, wall s, command
rm -f "$work"/{generate,train_gns,train_cconv}.log "$work/gpu_use.csv"  # an earlier run's, in $work
: >"$log"; : >"$steps"
rc=0

run() {  # run NAME COMMAND...: its output into $work/NAME.log, its line into steps.tsv
    local name=$1 t0=$SECONDS status; shift
    "$@" >"$work/$name.log" 2>&1
    status=$?
    printf '%s\t%s\t%s\t%s\n' "$name" "$status" "$((SECONDS - t0))" "$*" >>"$steps"
    return "$status"
}

if ! "$python" - "$device" <<'PY' 2>&1 | tee -a "$log"; then
import sys
import torch
from lagfluid.registry import trainable_models
if sys.argv[1] == "cuda" and not torch.cuda.is_available():
    sys.exit("benchmarks/gpu_train.sh needs a CUDA device; torch sees none")
print("device:", torch.cuda.get_device_name() if sys.argv[1] == "cuda" else "cpu", "torch", torch.__version__)
missing = {"gns", "cconv"} - set(trainable_models())
if missing:
    sys.exit(f"no trainable model {', '.join(sorted(missing))}: install lagfluid (pip install -e .)")
PY
    cp "$log" "$out/gpu_train.log"
    exit 1
fi
if command -v nvidia-smi >/dev/null; then
    nvidia-smi --query-gpu=timestamp,utilization.gpu,memory.used --format=csv -l 10 \
        >"$work/gpu_use.csv" 2>&1 &
    monitor=$!
fi

common=("${data[@]}" "data.out_dir=$work/data" progress=false)
if run generate timeout -k 10 "$budget" "$python" -m lagfluid.run -m task=generate scene=random \
        "${common[@]}" threads=1 "data.scene_index=range(0,$scenes)" hydra.launcher.n_jobs="$jobs" \
        "hydra.sweep.dir=$work/generate" "out_dir=$work/generate" && [ -f "$work/data/metadata.json" ]; then
    train_s=$(( budget - (SECONDS - start) - reserve ))
    train_s=$(( train_s > least ? train_s : least ))
    common+=("device=$device" "threads=$threads" "train.max_seconds=$train_s" "${every[@]}")
    # train.max_seconds stops each; a timeout 2 min later ends one that hangs (its last checkpoint comes back)
    run train_gns timeout -k 10 $((train_s + 120)) "$python" -m lagfluid.run task=train model=gns \
        train=gns_paper "${common[@]}" "out_dir=$work/gns" "${gns[@]}" &
    gns_pid=$!
    run train_cconv timeout -k 10 $((train_s + 120)) "$python" -m lagfluid.run task=train model=cconv \
        train=cconv_paper "${common[@]}" "out_dir=$work/cconv" "${cconv[@]}" &
    cconv_pid=$!
    wait "$gns_pid" || rc=1
    wait "$cconv_pid" || rc=1
else
    echo "no dataset in $work/data (see generate in gpu_train.log): nothing to train" | tee -a "$log"
    rc=1
fi
[ -n "${monitor:-}" ] && kill "$monitor" 2>/dev/null

for name in generate train_gns train_cconv; do
    [ -f "$work/$name.log" ] && { printf '\n===== %s\n' "$name"; cat "$work/$name.log"; } >>"$log"
done
[ -f "$work/gpu_use.csv" ] && { printf '\n===== GPU use every 10 s\n'; cat "$work/gpu_use.csv"; } >>"$log"

"$python" - "$work" "$out" "$steps" "$budget" "$((SECONDS - start))" <<'PY' 2>&1 | tee -a "$log" || rc=1
# The networks without optimizer state, the loss logs and provenance.md into $OUT; each network read back.
import csv, datetime as dt, json, os, platform, shutil, subprocess, sys
from pathlib import Path
import torch
from benchmarks.provenance import git_commit
from lagfluid.models.checkpoint import export_weights, read_checkpoint

work, out, steps = Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
commit = git_commit()
if commit == "unknown":
    commit = os.environ.get("GPU_TRAIN_COMMIT", "unknown (no .git in this copy and no GPU_TRAIN_COMMIT)")
smi = shutil.which("nvidia-smi")
lines = [
    "# benchmarks/gpu_train.sh",
    "",
    f"- date: {dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M UTC}",
    f"- git commit: {commit}",
    f"- machine: {platform.platform()}, {os.cpu_count()} CPUs"
    + (f", {torch.cuda.get_device_name()}" if torch.cuda.is_available() else ", no CUDA device"),
    f"- versions: python {platform.python_version()}, torch {torch.__version__}, CUDA {torch.version.cuda}",
    f"- dry run: {os.environ.get('GPU_TRAIN_DRY_RUN', '0') == '1'}",
    f"- budget: {sys.argv[4]} s; wall time of the script before this step: {sys.argv[5]} s",
    "",
    "| step | exit status | wall s | command |",
    "| --- | --- | --- | --- |",
]
for name, status, seconds, command in csv.reader(steps.open(), delimiter="\t"):
    lines.append(f"| {name} | {status} | {seconds} | `{command}` |")
lines += ["", "| network | iterations | of | training s | last train loss | last valid loss |"]
lines += ["| --- " * 6 + "|"]
ok = True
for kind in ("gns", "cconv"):
    run = work / kind
    if not (run / f"{kind}.pt").is_file():
        lines.append(f"| {kind} | no checkpoint | | | | |")
        ok = False
        continue
    shutil.copyfile(run / f"{kind}_loss.csv", out / f"{kind}_loss.csv")
    export_weights(run, out, kinds=[kind])
    ckpt = read_checkpoint(out / f"{kind}.pt", kind)  # read back: what comes home loads
    rows = list(csv.DictReader((run / f"{kind}_loss.csv").open()))
    valid = [r["valid_loss"] for r in rows if r["valid_loss"] != "nan"]
    iterations = json.loads(ckpt["meta"]["identity"])["iterations"]
    lines.append(
        f"| {kind} | {ckpt['step']} | {iterations} | {ckpt['meta']['train_seconds']:.0f} | "
        f"{rows[-1]['train_loss'] if rows else '-'} | {valid[-1] if valid else '-'} |"
    )
lines += ["", "## nvidia-smi", "", "```"]
lines += [subprocess.run([smi], capture_output=True, text=True).stdout.rstrip() if smi else "not found"]
lines += ["```"]
(out / "provenance.md").write_text("\n".join(lines) + "\n")
print("\n".join(lines))
sys.exit(0 if ok else 1)
PY
cp "$log" "$out/gpu_train.log"
exit "$rc"
