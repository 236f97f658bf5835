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
# compile cannot take the others with it. OUTDIR gets at most 8 files: machine.txt, the
# speed benchmarks' JSON (moglow_float32.json, glow_fixed.json, moglow_bfloat16.json), the
# bench's estimate.txt and estimate.json, quick_training.txt (both trainings' output) and
# log.txt (every part's stderr; the lines for people are also printed).
set -u
out=${1:?usage: benchmarks/gpu_speed.sh OUTDIR}
py=${PYTHON:-python3}
scale=${LIMIT_SCALE:-1}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
if [ -n "${QUICK:-}" ]; then size=--quick budget=smoke steps=30; else size= budget=full steps=400; fi

{
  date -u
  nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm --format=csv || true
  "$py" -c "import jax, flax, optax; print('jax', jax.__version__, 'flax', flax.__version__,
'optax', optax.__version__, jax.devices(), 'matmul precision', jax.config.jax_default_matmul_precision)"
} 2>&1 | tee "$out/machine.txt"

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
part estimate estimate.txt 120 "$py" -m motionflows.cli bench --data synthetic --budget $budget --estimate \
  --runs-dir "${TMPDIR:-/tmp}/gpu_speed_runs" --out "${TMPDIR:-/tmp}/gpu_speed_bench"
cp "${TMPDIR:-/tmp}/gpu_speed_bench/estimate.json" "$out/estimate.json" 2>/dev/null
# float32 against bfloat16 on a short `quick` MoGlow training (synthetic data): validation NLL
for dt in float32 bfloat16; do
  part "quick_$dt" quick_training.txt 60 "$py" -m experiments.moglow --preset quick \
    --steps $steps --set compute_dtype=$dt --runs-dir "${TMPDIR:-/tmp}/gpu_speed_runs" --run-name "quick_$dt" \
    --no-progress
done
