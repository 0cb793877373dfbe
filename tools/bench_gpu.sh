#!/bin/bash
# BENCHMARKS.md "On a GPU (CUDA) beside the same machine's CPU", in one run on a CUDA machine, inside a time budget:
#   bash tools/bench_gpu.sh OUT_DIR [BUDGET_SECONDS]
# (on this project's lent GPU machines: bash .gpu/on_device.sh bash tools/bench_gpu.sh "$OUT" 540).
# Steps, most wanted first; a step that would not fit in what is left of the budget is skipped and says so:
#   dataset   myoArm's 100 000 equilibrium samples on every core (the cache both myoArm fits read)
#   fit_pm    `bodyschema fit --config configs/myoarm-polynomial.yaml --trainer.accelerator gpu` (the per-muscle body; the
#             same fit on a GPU)
#   fit_dense the same with configs/myoarm-dense.yaml (the dense body, configs/myoarm.yaml until 2026-11-27)
#   adapter   the prepared structured adapter of each fit on CUDA and on this machine's CPU (one thread), batch 1
#             and 4000
#   tests     python -m pytest -m gpu -q
# STEPS="dataset fit_pm tests" (an environment variable) runs only the steps it names (default: every step);
# TESTS_FIRST=1 runs the tests before the fits (TESTS_CAP: their most seconds).
# Each step's output is OUT_DIR/<step>.log; OUT_DIR/summary.txt holds the machine and each step's exit status and
# wall seconds; the two fits' checkpoints are copied to OUT_DIR/dense.ckpt and OUT_DIR/per_muscle.ckpt (their runs
# live under RUNS_DIR, default /tmp/bench_gpu).
set -u
out=${1:?usage: bench_gpu.sh OUT_DIR [BUDGET_SECONDS]}
budget=${2:-540}
runs=${RUNS_DIR:-/tmp/bench_gpu}
mkdir -p "$out" "$runs"
start=$(date +%s)
left() { echo $(( budget - ($(date +%s) - start) )); }

step() {  # step NAME NEEDS_S CAP_S COMMAND...: run COMMAND, killed after CAP_S or at the budget's end; log status, wall
  local name=$1 need=$2 cap=$3 t0 rc
  shift 3
  [[ " ${STEPS:-$name} " == *" $name "* ]] || return 0
  if (( $(left) < need )); then
    echo "$name skipped: $(left) s left, needs about $need" | tee -a "$out/summary.txt"
    return
  fi
  t0=$(date +%s%N)
  (( cap > $(left) )) && cap=$(left)
  timeout "$cap" "$@" >"$out/$name.log" 2>&1
  rc=$?
  echo "$name rc=$rc wall_s=$(( ($(date +%s%N) - t0) / 1000000 ))e-3" | tee -a "$out/summary.txt"
}

{ nvidia-smi -L; nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
  python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda)"; nproc; } \
  >"$out/summary.txt" 2>&1
cat "$out/summary.txt"
dataset='import yaml; from lightning_bodyschema.data.datamodule import EquilibriumDataModule as D
D(**yaml.safe_load(open("configs/myoarm.yaml"))["data"]).prepare_data()'
[[ "${TESTS_FIRST:-0}" == 1 ]] && step tests 60 "${TESTS_CAP:-600}" python3 -m pytest -m gpu -q -p no:cacheprovider
step dataset 60 120 python3 -c "$dataset"
step fit_pm 60 300 bodyschema fit --config configs/myoarm-polynomial.yaml --trainer.accelerator gpu \
  --trainer.default_root_dir "$runs/pm"
step fit_dense 120 330 bodyschema fit --config configs/myoarm-dense.yaml --trainer.accelerator gpu \
  --trainer.default_root_dir "$runs/dense"
last() { ls "$runs/$1"/lightning_logs/version_*/checkpoints/*.ckpt 2>/dev/null | tail -1; }
[ -n "$(last dense)" ] && cp "$(last dense)" "$out/dense.ckpt"
[ -n "$(last pm)" ] && cp "$(last pm)" "$out/per_muscle.ckpt"
adapter='import sys, torch; sys.path.insert(0, "tools"); torch.set_num_threads(1); torch.set_flush_denormal(True)
from bench_structured_adapter import myoarm_cases, adapter_latency
_, _, faults, q = myoarm_cases(4000)
for ckpt in sys.argv[1:]:
    for device in ("cuda", "cpu"):
        print(ckpt, device); adapter_latency(ckpt, faults, q, 5, device, 50)'
fitted=$(ls "$out/per_muscle.ckpt" "$out/dense.ckpt" 2>/dev/null)
[ -n "$fitted" ] && step adapter 30 120 python3 -c "$adapter" $fitted
[[ "${TESTS_FIRST:-0}" == 1 ]] || step tests 60 600 python3 -m pytest -m gpu -q -p no:cacheprovider
cat "$out/summary.txt"
