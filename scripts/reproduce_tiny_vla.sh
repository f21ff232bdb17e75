#!/usr/bin/env bash
# Reproduce checkpoints/tiny_vla from scratch: expert demonstrations, DART demonstrations, a first
# policy, DAgger data the policies visit (labelled by the expert), v6, a fine-tune of v6 (shipped).
# About 3 hours on 2 idle cores (recording ~85 min, training ~85 min). Data goes to data/ (gitignored).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
OUT=${OUT:-checkpoints/tiny_vla}
rec() { "$PY" -m training.tabletop_demos "$@"; }

# 1. clean expert demonstrations (init states from episode 100000 on: never an evaluation's)
rec --root data/tabletop_demos_po --episodes 50 --tasks pick_color stack_color
rec --root data/tabletop_demos_org --episodes 25 --tasks organize
# 2. DART: noisy execution, clean expert labels (recoveries from small drifts)
rec --root data/dart_pick_color --episodes 100 --tasks pick_color --noise 0.3 --first-episode 200000 &
rec --root data/dart_stack_color --episodes 100 --tasks stack_color --noise 0.3 --first-episode 200000
wait
rec --root data/dart_organize --episodes 20 --tasks organize --noise 0.3 --first-episode 200000
# 3. a first policy
"$PY" -m training.train_tiny_vla --data data/tabletop_demos_po data/dart_pick_color \
    data/dart_stack_color data/tabletop_demos_org --out data/tiny_vla_dart --steps 3000 \
    --batch-size 64 --seed 0 --threads 1
# 4. DAgger on the weakest task: the first policy drives, the expert labels every visited state
rec --root data/dagger_stack_0 --episodes 30 --tasks stack_color --policy data/tiny_vla_dart \
    --first-episode 300000 &
rec --root data/dagger_stack_1 --episodes 30 --tasks stack_color --policy data/tiny_vla_dart \
    --first-episode 301000
wait
# 5. a second policy (the one shipped before v6)
"$PY" -m training.train_tiny_vla --data data/tabletop_demos_po data/dart_pick_color \
    data/dart_stack_color data/dagger_stack_0 data/dagger_stack_1 data/tabletop_demos_org \
    data/dart_organize --out data/tiny_vla_v4 --steps 4000 --batch-size 64 --seed 0 --threads 1
# 6. DAgger with the second policy on stack_color and organize
rec --root data/dagger_stack_2 --episodes 25 --tasks stack_color --policy data/tiny_vla_v4 \
    --first-episode 302000 &
rec --root data/dagger_stack_3 --episodes 25 --tasks stack_color --policy data/tiny_vla_v4 \
    --first-episode 303000
wait
rec --root data/dagger_organize_0 --episodes 15 --tasks organize --policy data/tiny_vla_v4 \
    --first-episode 310000
# 7. v6: all of the above from scratch, 4x the steps of the second policy (~45 min)
"$PY" -m training.train_tiny_vla --data data/tabletop_demos_po data/dart_pick_color \
    data/dart_stack_color data/dagger_stack_0 data/dagger_stack_1 data/dagger_stack_2 \
    data/dagger_stack_3 data/tabletop_demos_org data/dart_organize data/dagger_organize_0 \
    --out data/tiny_vla_v6 --steps 16000 --batch-size 64 --seed 0 --threads 1
# 8. DAgger with v6
rec --root data/dagger_stack_4 --episodes 25 --tasks stack_color --policy data/tiny_vla_v6 \
    --first-episode 304000 &
{ rec --root data/dagger_stack_5 --episodes 15 --tasks stack_color --policy data/tiny_vla_v6 \
    --first-episode 305000 && rec --root data/dagger_organize_1 --episodes 10 --tasks organize \
    --policy data/tiny_vla_v6 --first-episode 311000; }
wait
# 9. the shipped policy: v6 fine-tuned on everything (keeps v6's normalization and vocabulary)
"$PY" -m training.train_tiny_vla --data data/tabletop_demos_po data/dart_pick_color \
    data/dart_stack_color data/dagger_stack_0 data/dagger_stack_1 data/dagger_stack_2 \
    data/dagger_stack_3 data/tabletop_demos_org data/dart_organize data/dagger_organize_0 \
    data/dagger_stack_4 data/dagger_stack_5 data/dagger_organize_1 --init data/tiny_vla_v6 \
    --out "$OUT" --steps 4000 --batch-size 64 --lr 3e-4 --seed 0 --threads 1
