#!/usr/bin/env bash
# The zoo's ResNet members (ACT and Diffusion: the ones 2 CPU cores take hours over) trained side
# by side on one CUDA machine by lerobot-train, each stopped after a time budget at its last
# checkpoint, exported, and packed at float16 in parts of at most 15 MiB for a channel with a
# per-file limit (training/zoo_carry.py; `python -m training.zoo_carry unpack` restores them).
#
#   bash scripts/train_zoo_gpu.sh OUT_DIR [SECONDS] [BENCHMARK] [DATASET]
#
# Data workers share the machine's cores (two kept for the trainers). A run stopped by the budget
# resumes with the same command (lerobot-train --resume from the run's last checkpoint).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:?usage: train_zoo_gpu.sh OUT_DIR [SECONDS] [BENCHMARK] [DATASET]}
BUDGET=${2:-300}
BENCH=${3:-tabletop_pos}
DATA=${4:-data/zoo/$BENCH}
PY=${PY:-python3}
MEMBERS=${MEMBERS:-act diffusion}
FRAMES=${FRAMES:-64}
DEVICE=${DEVICE:-cuda}
read -r -a names <<<"$MEMBERS"
workers=$(((($(nproc) - 2) / ${#names[@]}) > 1 ? ($(nproc) - 2) / ${#names[@]} : 1))
mkdir -p "$OUT"
for m in "${names[@]}"; do
    "$PY" -m training.zoo train "$m" --benchmark "$BENCH" --dataset "$DATA" --device "$DEVICE" \
        --threads 1 --num-workers "$workers" --save-freq 250 --time-limit-s "$BUDGET" \
        >"$OUT/train_$m.log" 2>&1 &
done
wait || true
# a member that failed leaves no checkpoint and its log; the others are still exported and packed
for m in "${names[@]}"; do
    if "$PY" -m training.zoo export "$m" --benchmark "$BENCH" --dataset "$DATA" \
        --dest "data/zoo/gpu/$m" >>"$OUT/train_$m.log" 2>&1; then
        "$PY" -m training.zoo_carry pack "data/zoo/gpu/$m" --out "$OUT" --dataset "$DATA" \
            --frames "$FRAMES" >>"$OUT/train_$m.log" 2>&1 || echo "$m: not packed (see its log)"
    else
        echo "$m: no checkpoint to export (see $OUT/train_$m.log)"
    fi
done
