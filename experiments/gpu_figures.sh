#!/usr/bin/env bash
# The GPU figures of README "On a GPU", in one call sized for a short lease of one GPU:
#   1. CONFIG (default the paper configuration, configs/clevr.py: 128 px, 96 samples, 4 scenes x
#      1024 rays) trained for TRAIN_SECONDS of wall time (data generation and compilation
#      included), then stopped with SIGINT (it checkpoints; the same command resumes): its steps/s
#      and its emergence curve (metrics.jsonl, emergence.json). The paper configuration is
#      validated every 500 steps on 20 scenes, a variant at its own interval;
#   2. experiments/bench.py on the paper's batch and on `scene` (bench_gpu.json), unless
#      BENCH_SECONDS is 0.
# Everything it measures is copied to OUTDIR. Usage, from the repository root:
#   bash experiments/gpu_figures.sh OUTDIR [TRAIN_SECONDS] [BENCH_SECONDS] [CONFIG]
# PYTHON picks the interpreter (default python3), WORKDIR the run folder (default /tmp/gpu_<name>).
set -uo pipefail
out=${1:?usage: bash experiments/gpu_figures.sh OUTDIR [TRAIN_SECONDS] [BENCH_SECONDS] [CONFIG]}
train_s=${2:-330}
bench_s=${3:-150}
config=${4:-configs/clevr.py}
py=${PYTHON:-python3}
case "$config" in
  *:*) name=${config##*:}; name=${name//+/_}; extra=() ;;
  *) name=paper; extra=(--config.train.eval_every=500 --config.train.eval_scenes=20) ;;
esac
workdir=${WORKDIR:-/tmp/gpu_$name}
mkdir -p "$out"

{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
  $py -c "import jax, flax, optax; print('jax', jax.__version__, 'flax', flax.__version__, 'optax', optax.__version__, jax.devices())"
} 2>&1 | tee "$out/gpu.txt"

t0=$(date +%s)
timeout -s INT "$train_s" $py -m slotlifter_jax.main --config="$config" --workdir="$workdir" \
  "${extra[@]}" >"$out/${name}_train.log" 2>&1
# 124: timeout sent the SIGINT, the expected end (the run checkpointed and exited 130; its log says so).
echo "train: rc $? after $(( $(date +%s) - t0 )) s" | tee -a "$out/gpu.txt"
for f in metrics.jsonl emergence.json config.json; do
  [ -f "$workdir/$f" ] && cp "$workdir/$f" "$out/${name}_$f"
done
grep -E '"val"' "$out/${name}_metrics.jsonl" 2>/dev/null | tail -n 3 | cut -c1-300
[ "$bench_s" = 0 ] && exit 0

timeout "$bench_s" $py experiments/bench.py --configs=paper_batch,scene --steps=20 --out="$out" \
  >"$out/bench.log" 2>&1
echo "bench: rc $?" | tee -a "$out/gpu.txt"
tail -n 12 "$out/bench.log"
