#!/usr/bin/env bash
# The GPU figures of README "On a GPU", in one call sized for a short lease of one GPU:
#   1. the paper configuration (configs/clevr.py: 128 px, 96 samples, 4 scenes x 1024 rays) trained
#      for TRAIN_SECONDS of wall time (data generation and compilation included), validated every
#      500 steps on 20 scenes, then stopped with SIGINT (it checkpoints; the same command resumes):
#      its steps/s and its emergence curve (metrics.jsonl, emergence.json);
#   2. experiments/bench.py on the paper's batch and on `fast` (bench_gpu.json).
# Everything it measures is copied to OUTDIR. Usage, from the repository root:
#   bash experiments/gpu_figures.sh OUTDIR [TRAIN_SECONDS] [BENCH_SECONDS]
# PYTHON picks the interpreter (default python3), WORKDIR the run folder (default /tmp/gpu_paper).
set -uo pipefail
out=${1:?usage: bash experiments/gpu_figures.sh OUTDIR [TRAIN_SECONDS] [BENCH_SECONDS]}
train_s=${2:-330}
bench_s=${3:-150}
py=${PYTHON:-python3}
workdir=${WORKDIR:-/tmp/gpu_paper}
mkdir -p "$out"

{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  $py -c "import jax, flax, optax; print('jax', jax.__version__, 'flax', flax.__version__, 'optax', optax.__version__, jax.devices())"
} 2>&1 | tee "$out/gpu.txt"

t0=$(date +%s)
timeout -s INT "$train_s" $py -m slotlifter_jax.main --config=configs/clevr.py --workdir="$workdir" \
  --config.train.eval_every=500 --config.train.eval_scenes=20 >"$out/train.log" 2>&1
# 130: stopped by the SIGINT above after a checkpoint, the expected end.
echo "train: rc $? after $(( $(date +%s) - t0 )) s" | tee -a "$out/gpu.txt"
for f in metrics.jsonl emergence.json config.json; do
  [ -f "$workdir/$f" ] && cp "$workdir/$f" "$out/paper_$f"
done

timeout "$bench_s" $py experiments/bench.py --configs=paper_batch,fast --steps=20 --out="$out" \
  >"$out/bench.log" 2>&1
echo "bench: rc $?" | tee -a "$out/gpu.txt"
tail -n 12 "$out/bench.log"
grep -E "steps_per_sec|\"val\"" "$out/paper_metrics.jsonl" 2>/dev/null | tail -n 3 | cut -c1-300
