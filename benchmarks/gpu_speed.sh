#!/usr/bin/env bash
# The GPU figures of the README in one go: paper-size MoGlow and fixed-length Glow speed
# (training step, sampling, streaming; float32 = JAX's default matmul precision, and
# bfloat16 conditioner matmuls), the paper budgets' projected wall time, and a short
# float32-vs-bfloat16 training check of the validation NLL.
#
#   benchmarks/gpu_speed.sh OUTDIR            # after `pip install -e '.[cuda]'`
#   QUICK=1 benchmarks/gpu_speed.sh OUTDIR    # small sizes: checks the script, any machine
#
# Each part runs under its own time limit (seconds, scaled by LIMIT_SCALE) so that one slow
# compile cannot take the others with it (a first run compiles from cold: the estimate's
# probes took 67 s for the Glow and 30 s for MoGlow on an H200; LIMIT_SCALE=4 suits a
# CPU). OUTDIR gets 8 files: the speed benchmarks' JSON (moglow_float32.json,
# glow_fixed.json, moglow_bfloat16.json), the bench's estimate.txt and estimate.json,
# training.txt (the four trainings' test tables), training_metrics.jsonl (their metrics,
# each run's rows after a {"run": NAME} line) and log.txt (the GPU and versions, then every
# part's stderr; the lines for people are also printed).
set -u
out=${1:?usage: benchmarks/gpu_speed.sh OUTDIR}
py=${PYTHON:-python3}
scale=${LIMIT_SCALE:-1}
mkdir -p "$out"
runs=$(mktemp -d)  # the trainings' run directories: fresh, so a second call trains again
export PYTHONUNBUFFERED=1
if [ -n "${QUICK:-}" ]; then
  size=--quick budget=smoke quick_steps=30 big=smoke big_steps=30
else
  size= budget=full quick_steps=400 big=paper big_steps=600
fi

{
  date -u
  nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv || true
  "$py" -c "import jax, flax, optax; print('jax', jax.__version__, 'flax', flax.__version__,
'optax', optax.__version__, jax.devices(), 'matmul precision', jax.config.jax_default_matmul_precision)"
} 2>&1 | tee -a "$out/log.txt"

part() {  # part NAME FILE LIMIT_S COMMAND...: stdout to OUTDIR/FILE, stderr to log.txt
  local name=$1 file=$2 limit=$(( $3 * scale )) start rc
  shift 3
  echo "== $name (limit ${limit} s): $*" | tee -a "$out/log.txt"
  start=$(date +%s)
  timeout "$limit" "$@" >> "$out/$file" 2> >(tee -a "$out/log.txt" | grep -v '^{' >&2)
  rc=$?
  echo "== $name: exit $rc after $(( $(date +%s) - start )) s" | tee -a "$out/log.txt"
}

part moglow_float32 moglow_float32.json 150 "$py" benchmarks/moglow_speed.py $size --dtypes float32 --repeats 10
part moglow_bfloat16 moglow_bfloat16.json 130 "$py" benchmarks/moglow_speed.py $size --dtypes bfloat16 --repeats 10
part glow_fixed glow_fixed.json 100 "$py" benchmarks/glow_fixed_speed.py $size --repeats 10
part estimate estimate.txt 300 "$py" -m motionflows.cli bench --data synthetic --budget $budget --estimate \
  --runs-dir "$runs" --out "$runs/bench"
cp "$runs/bench/estimate.json" "$out/estimate.json" 2>/dev/null
# float32 against bfloat16 on short MoGlow trainings (synthetic data): validation and test NLL
for run in "quick $quick_steps 60" "$big $big_steps 180"; do
  read -r preset steps limit <<< "$run"
  for dt in float32 bfloat16; do
    part "${preset}_$dt" training.txt "$limit" "$py" -m experiments.moglow --preset "$preset" \
      --steps "$steps" --set compute_dtype=$dt --runs-dir "$runs" --run-name "${preset}_$dt" \
      --no-progress
    echo "{\"run\": \"${preset}_$dt\"}" >> "$out/training_metrics.jsonl"
    cat "$runs/moglow/${preset}_$dt/metrics.jsonl" >> "$out/training_metrics.jsonl" 2>/dev/null
  done
done
