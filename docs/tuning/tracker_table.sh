#!/bin/bash
# Issue 43's comparison table on the demo's held-out frames (val + test of its split, 33 frames), RGB frames;
# intrinsics from calibration.json; --gt for scoring only. Networks: the recipe (training/pose_fast_zoom_{improved,
# thesis}.toml, 7400 steps, seed 0) trained on the demo's dataset (/work/dev/s51/demo/build/dataset).
# Session 61 ran it again with networks trained again the same way (/work/dev/s61/pose_{improved,thesis}, heldout,
# table; docs/tuning/tracker.md#the-comparison-table-and-speed-at-the-final-code-with-the-recipe-networks-trained-again-s61).
# Usage, from the repository root (session 52's paths in brackets):
#   S=SIM H=HELDOUT I=IMPROVED_RUN T=THESIS_RUN INIT=INIT.json O=OUT docs/tuning/tracker_table.sh ROW...
# SIM: `cadalign sim datasets/scenes/default.toml` [/work/dev/sim_default]; HELDOUT: a folder of that simulation's
# frames in the demo split's val + test blocks [/work/dev/s50/table/heldout, 33 frames]; the runs:
#   cadalign train pose DS --out RUN --preset fast --config training/pose_fast_zoom_{improved,thesis}.toml --steps 7400
# with DS the demo's dataset [runs/demo/build/dataset]; INIT: the first frame's true pose turned 10 deg / moved
# 0.5 m (docs/tuning/tracker_runs.sh writes one). ROW: thesis improved icp_oracle track_net track_net_init
# track_init track_nav (its --nav is $S/navigation.json; session 52 wrote that one with seed 1).
set -u
C="--cad datasets/scenes/default.toml --calib $S/calibration.json --gt $S --overwrite"
ca() { ${CA:-.venv/bin/cadalign} "$@"; }
row() { name=$1; shift; t0=$SECONDS; ca infer $H $C --out $O/$name "$@" > $O/$name.log 2>&1; echo "== $name: $* ($((SECONDS - t0)) s wall)"; grep -E "F1|frames:" $O/$name.log | tail -3; }
for r in "$@"; do
  case $r in
    thesis) row thesis --model $T --no-tracker --preset none ;;
    improved) row improved --model $I --no-tracker --preset none ;;
    icp_oracle) row icp_oracle --model $I --no-tracker --depth $S ;;
    track_net) row track_net --model $I ;;
    track_init) row track_init --init-pose $INIT ;;
    track_nav) row track_nav --nav $S/navigation.json ;;
    track_net_init) row track_net_init --model $I --init-pose $INIT ;;
  esac
done
