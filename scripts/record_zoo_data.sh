#!/usr/bin/env bash
# The zoo's tabletop demonstrations as one LeRobotDataset (data/zoo/tabletop, git-ignored), the
# dataset every zoo architecture is trained on by lerobot-train. Two recorders at a time (one per
# core): clean expert and DART episodes (noisy execution, expert labels) on pick_color and
# stack_color, expert organize chains, and DAgger episodes on stack_color driven by the shipped
# tiny VLA and labelled by the expert. Init states come from episode 100000 on, never an
# evaluation's (evaluations use episodes 0 ... n-1). About 25 minutes on 2 cores (recorded 2026-12-03).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
PARTS=${PARTS:-data/zoo/parts}
OUT=${OUT:-data/zoo/tabletop}
rec() { "$PY" -m training.tabletop_demos "$@"; }
mkdir -p "$PARTS"
{
    rec --root "$PARTS/expert_pick" --episodes 50 --tasks pick_color --first-episode 100000
    rec --root "$PARTS/dart_pick" --episodes 100 --tasks pick_color --noise 0.3 --first-episode 200000
    rec --root "$PARTS/dagger_stack" --episodes 30 --tasks stack_color \
        --policy checkpoints/tiny_vla --first-episode 300000
} &
{
    rec --root "$PARTS/expert_stack" --episodes 50 --tasks stack_color --first-episode 100000
    rec --root "$PARTS/dart_stack" --episodes 100 --tasks stack_color --noise 0.3 --first-episode 200000
    rec --root "$PARTS/expert_organize" --episodes 7 --tasks organize --first-episode 100000
}
wait
"$PY" -m training.zoo_data --out "$OUT" "$PARTS"/expert_pick "$PARTS"/dart_pick \
    "$PARTS"/expert_stack "$PARTS"/dart_stack "$PARTS"/dagger_stack "$PARTS"/expert_organize
