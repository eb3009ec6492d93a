#!/usr/bin/env bash
# A GPU day in one device call: the two prepared GPU scripts on a bare machine, their results in the few flat
# files a lease brings back. Never run on a GPU yet: no GPU has been lent to this project.
# Here, once, with network access (the packages the machine's image lacks, as wheels in .whl/, ignored):
#   bash benchmarks/device_wheels.sh
# There (the device tool's run, carry [".whl"], timeout_s 600):
#   bash benchmarks/gpu_day.sh [budget in s, default 520]
#   1. the carried wheels into /tmp/site (PYTHONPATH), and lagfluid installed without an index (pip -e: the
#      models gns and cconv are plugins found by entry points);
#   2. benchmarks/gpu_check.sh (CUDA tests, host syncs, Table 2 on CUDA, the 1M dam), stopped at a third of
#      the budget;
#   3. benchmarks/gpu_train.sh (paper-size GNS and DeepLagrangianFluids' recipe) with what is left, less a
#      reserve for packing;
#   4. $OUT holds at most 8 flat files, what a lease returns: gpu_day.log (each part's exit status and wall
#      time, then every part's output), gpu_check.tar.gz (gpu_check.sh's folder without trajectories) and
#      gpu_train.sh's six (gns.pt, cconv.pt, their loss logs, gpu_train.log, provenance.md).
# Each part runs even when an earlier one failed; the exit status is 1 if any did.
# GPU_DAY_DRY_RUN=1: on the CPU, gpu_check.sh skipped (it needs CUDA) and gpu_train.sh's own dry run
# (tests/test_gpu_train.py). GPU_DAY_WORK: the working folder (runs/gpu_day); OUT: where the files go
# (runs/gpu_day/out).
set -uo pipefail
start=$SECONDS
cd "$(dirname "$0")/.." || exit 1  # the repository root
out=${OUT:-runs/gpu_day/out}
work=${GPU_DAY_WORK:-runs/gpu_day}
mkdir -p "$out" && out=$(cd "$out" && pwd) || exit 1
if [ -n "$(ls -A "$out")" ]; then  # never mix with, or overwrite, an earlier day's files
    echo "benchmarks/gpu_day.sh: $out is not empty: move its files, or set OUT" >&2
    exit 1
fi
mkdir -p "$work" && work=$(cd "$work" && pwd) || exit 1
dry=${GPU_DAY_DRY_RUN:-0}
budget=${1:-520}
reserve=30
python=python; command -v python >/dev/null || python=python3
log=$work/gpu_day.log
parts=$work/parts.tsv  # one line per part: name, exit status, wall s
: >"$log"; : >"$parts"
rc=0

part() {  # part NAME COMMAND...: its output into $work/NAME.log, its line into parts.tsv
    local name=$1 t0=$SECONDS status; shift
    "$@" >"$work/$name.log" 2>&1
    status=$?
    printf '%s\t%s\t%s\n' "$name" "$status" "$((SECONDS - t0))" >>"$parts"
    [ "$status" = 0 ] || rc=1
}

environment() {  # the carried wheels, then lagfluid itself, each only where it is missing
    if compgen -G ".whl/*.whl" >/dev/null; then
        "$python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
            --target /tmp/site .whl/*.whl || return 1
    fi
    if ! "$python" -c "from lagfluid.registry import trainable_models as m; assert {'gns', 'cconv'} <= set(m())"; then
        "$python" -m pip install -q --no-index --no-deps --no-build-isolation -e . || return 1
    fi
    "$python" -c "import hydra, omegaconf, pyevtk, lagfluid; print('environment: hydra', hydra.__version__)"
}
[ -d .whl ] && export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
part environment environment

check=$work/check
if [ "$dry" = 1 ]; then
    mkdir -p "$check" && echo "dry run: benchmarks/gpu_check.sh needs a CUDA device; skipped" >"$work/check.log"
    printf 'check\tskipped\t0\n' >>"$parts"
else
    part check env OUT="$check" timeout -k 10 $((budget / 3)) bash benchmarks/gpu_check.sh
fi

train_s=$(( budget - (SECONDS - start) - reserve ))
if [ "$dry" = 1 ]; then
    part train env GPU_TRAIN_DRY_RUN=1 GPU_TRAIN_WORK="$work/train" OUT="$out" bash benchmarks/gpu_train.sh
else
    part train env GPU_TRAIN_WORK="$work/train" OUT="$out" bash benchmarks/gpu_train.sh \
        $(( train_s > 120 ? train_s : 120 ))
fi

# what comes back: the check's folder without trajectories and weights (a lease returns files <= 16 MiB)
tar -czf "$out/gpu_check.tar.gz" -C "$work" --exclude='*.h5' --exclude='*.pt' --exclude='*.vtu' check \
    || rc=1
{
    echo "# benchmarks/gpu_day.sh, $(date -u '+%Y-%m-%d %H:%M UTC'), budget $budget s, dry run: $dry"
    echo "part	exit status	wall s"
    cat "$parts"
    for name in environment check train; do
        [ -f "$work/$name.log" ] && { printf '\n===== %s\n' "$name"; cat "$work/$name.log"; }
    done
    echo "wall time: $((SECONDS - start)) s; exit status: $rc"
} >"$log"
cp "$log" "$out/gpu_day.log"
cat "$log"
exit "$rc"
