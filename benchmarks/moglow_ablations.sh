#!/usr/bin/env bash
# The MoGlow ablations of docs/readme/moglow_quality.md: the `quick` preset on Bandai data
# split by performer (test = the unseen D2-C), one field changed per run, scored at 1600
# steps at temperatures 1.0, 0.8 and 0.6 by benchmarks/model_quality.py. `all` is the
# unchanged preset (the dev and extra takes); `base` (dev takes only, milestones 400 to 3200)
# was run by hand; `res-*` change one field of the residual model.
# Usage: bash benchmarks/moglow_ablations.sh [OUT=runs/quality] [NAME ...]
set -euo pipefail
out=${1:-runs/quality}
shift || true
declare -A SETS=(
  [all]=""
  [dropout0]="dropout=0.0"
  [residual]="residual=true"
  [res-dropout0]="residual=true dropout=0.0"
  [res-dropout0.95]="residual=true dropout=0.95"
  [res-ff]="residual=true conditioner=ff"
  [res-tau5]="residual=true tau=5"
  [res-tau20]="residual=true tau=20"
  [res-K8]="residual=true K=8"
  [res-hidden256]="residual=true hidden=256"
  [res-studentt]="residual=true base=studentt"
  [res-bf16]="residual=true compute_dtype=bfloat16"
  [res-keeplast]="residual=true dropout_keeps_last=true"
  [res-noise0.03]="residual=true history_noise=0.03"
  [res-noise0.1]="residual=true history_noise=0.1"
  [res-noise0.01]="residual=true history_noise=0.01"
  [res-noise0.003]="residual=true history_noise=0.003"
  [res-noise0.03-world]="residual=true history_noise=0.03 residual_world=true"
  [res-noise0.03-reverse]="residual=true history_noise=0.03 data.reverse=true"
)
names=("$@")
[ ${#names[@]} -eq 0 ] && names=(all residual res-dropout0 res-K8 res-hidden256 res-dropout0.95 res-ff res-tau5 res-studentt res-bf16 dropout0 res-tau20)
for name in "${names[@]}"; do
  [ -f "$out/moglow-quick-$name/QUALITY.md" ] && continue
  python benchmarks/model_quality.py moglow --preset quick --data bandai --split performer \
    --steps 1600 --temperatures 1.0,0.8,0.6 ${SETS[$name]:+--set ${SETS[$name]}} \
    --out "$out/moglow-quick-$name" > "$out/moglow-quick-$name.log" 2>&1
done
