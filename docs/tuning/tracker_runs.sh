#!/usr/bin/env bash
# The tracker measurements of docs/tuning/tracker.md (session 50), RGB only: intrinsics from each capture's
# calibration.json, the start from --init-pose (the first frame's true pose turned 10 deg about a random axis and
# moved 0.5 m, seed 1: a navigation fix), --gt for scoring only. Run from the repository root:
#   docs/tuning/tracker_runs.sh OUT
#   START=nav docs/tuning/tracker_runs.sh OUT   # instead of --init-pose: --nav (a rough pose per frame, 10 deg /
#                                                # 0.5 m off, as `cadalign sim` writes SIM/navigation.json; s52)
# Simulations are made when missing (`cadalign sim`, ~4 min each on 2 cores); visp_rbt is read from
# ../shared/data (set CADALIGN_DATA_DIR elsewhere).
set -euo pipefail
OUT=${1:?usage: tracker_runs.sh OUT}
PY=${PY:-.venv/bin/python}
CA=${CA:-.venv/bin/cadalign}
mkdir -p "$OUT"
run_sim() {  # scene name, simulation folder, scene file the tracker gets
  local scene=$1 sim=$2 cad=$3
  [ -d "$sim/frames" ] || $CA sim "datasets/scenes/$scene.toml" --out "$sim"
  $PY -c "import json, sys; from cadalign.sim.navigation import first_fix, true_poses
json.dump({'T_cam_from_world': first_fix(sys.argv[1], min(true_poses(sys.argv[1])), 1).matrix().tolist()},
          open(sys.argv[2], 'w'))" "$sim" "$OUT/init_$scene.json"
  local start=(--init-pose "$OUT/init_$scene.json")
  if [ "${START:-}" = nav ]; then  # seed 1 as the init pose's (frame 0's is the same pose)
    $PY -c "import sys; from cadalign.sim.navigation import write_navigation as w; w(sys.argv[1], 1, sys.argv[2])" \
      "$sim" "$OUT/nav_$scene.json"
    start=(--nav "$OUT/nav_$scene.json")
  fi
  $CA infer "$sim/frames" --cad "$cad" --calib "$sim/calibration.json" "${start[@]}" \
    --gt "$sim" --out "$OUT/$scene" --overwrite
}
for s in default two_pass turbid_lawnmower cluttered_hover; do
  run_sim $s "$OUT/sim_$s" datasets/scenes/$s.toml
done
# the missing part: the video has no hot_stab_1, the CAD has it
run_sim default_without_hot_stab_1 "$OUT/sim_default_without_hot_stab_1" datasets/scenes/default.toml
# the real clip
$PY datasets/real/visp_rbt_truth.py ../shared/data/visp_rbt "$OUT/visp_truth.json"
$CA infer ../shared/data/visp_rbt/frames --cad datasets/real/visp_rbt.toml --calib datasets/real/visp_rbt_calibration.json \
  --init-pose datasets/real/visp_rbt_init.json --gt-poses "$OUT/visp_truth.json" --out "$OUT/visp" --overwrite
