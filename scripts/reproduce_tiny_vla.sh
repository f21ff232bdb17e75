#!/usr/bin/env bash
# Reproduce checkpoints/tiny_vla from scratch: expert demonstrations, DART demonstrations, a first
# policy, DAgger data that policy visits (labelled by the expert), the final policy.
# About 90 minutes on 2 idle cores (recording ~60, training ~25). Data goes to data/ (gitignored).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
OUT=${OUT:-checkpoints/tiny_vla}
rec() { "$PY" -m workers.envs.tabletop_demos "$@"; }

# 1. clean expert demonstrations (init states from episode 100000 on: never an evaluation's)
rec --root data/tabletop_demos_po --episodes 50 --tasks pick_color stack_color
rec --root data/tabletop_demos_org --episodes 25 --tasks organize
# 2. DART: noisy execution, clean expert labels (recoveries from small drifts)
rec --root data/dart_pick_color --episodes 100 --tasks pick_color --noise 0.3 --first-episode 200000 &
rec --root data/dart_stack_color --episodes 100 --tasks stack_color --noise 0.3 --first-episode 200000
wait
rec --root data/dart_organize --episodes 20 --tasks organize --noise 0.3 --first-episode 200000
# 3. a first policy
"$PY" -m workers.backbones.tiny_vla.train --data data/tabletop_demos_po data/dart_pick_color \
    data/dart_stack_color data/tabletop_demos_org --out data/tiny_vla_dart --steps 3000 \
    --batch-size 64 --seed 0 --threads 1
# 4. DAgger on the weakest task: the first policy drives, the expert labels every visited state
rec --root data/dagger_stack_0 --episodes 30 --tasks stack_color --policy data/tiny_vla_dart \
    --first-episode 300000 &
rec --root data/dagger_stack_1 --episodes 30 --tasks stack_color --policy data/tiny_vla_dart \
    --first-episode 301000
wait
# 5. the shipped policy
"$PY" -m workers.backbones.tiny_vla.train --data data/tabletop_demos_po data/dart_pick_color \
    data/dart_stack_color data/dagger_stack_0 data/dagger_stack_1 data/tabletop_demos_org \
    data/dart_organize --out "$OUT" --steps 4000 --batch-size 64 --seed 0 --threads 1
