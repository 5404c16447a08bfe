#!/usr/bin/env bash
# Ten hand-picked outputs of sim, build-dataset, infer, fuse and emulate on the tiny scenes, hashed (issue 48:
# "behaviour unchanged" across a refactor). Run it at two commits and diff the two hashes.txt:
#   tests/tools/house_outputs.sh OUT_DIR            (from the repository root; PY=... to pick the interpreter)
#   diff OUT_BEFORE/hashes.txt OUT_AFTER/hashes.txt
# SfM runs with one thread (two threads are not bitwise repeatable). An .npz is hashed by its arrays (name,
# dtype, shape, bytes), not by its zip bytes, which hold a write timestamp.
set -euo pipefail
OUT=${1:?usage: house_outputs.sh OUT_DIR}
PY=${PY:-.venv/bin/python}
[ -x "$PY" ] || PY=/work/main/.venv/bin/python
export CADALIGN_DATA_DIR=${CADALIGN_DATA_DIR:-/work/shared/data}
export PYTHONPATH="$PWD:$PWD/tests${PYTHONPATH:+:$PYTHONPATH}"
cli() { "$PY" -c 'import sys; from cadalign.cli.main import main; sys.argv[0] = "cadalign"; sys.exit(main())' "$@"; }
rm -rf "$OUT" && mkdir -p "$OUT"
"$PY" - "$OUT" <<'PYEOF'
import sys
from pathlib import Path
from sim_testdata import write_build_capture, write_tiny_scene
out = Path(sys.argv[1])
write_tiny_scene(out / "tiny.toml", effects=[], frames=4)
write_build_capture(out / "capture.toml", effects=[], frames=12)
PYEOF
t0=$(date +%s)
cli sim "$OUT/tiny.toml" --out "$OUT/sim" > "$OUT/sim.log" 2>&1
cli sim "$OUT/capture.toml" --out "$OUT/capture" --no-video > "$OUT/capture.log" 2>&1
cli sfm "$OUT/capture/frames" --out "$OUT/build/sfm" --preset fast --set num_threads=1 > "$OUT/sfm.log" 2>&1 || \
  { echo "sfm failed, see $OUT/sfm.log"; exit 1; }
"$PY" - "$OUT" <<'PYEOF'
import sys
from pathlib import Path
from sim_testdata import write_picks_from_truth
out = Path(sys.argv[1])
write_picks_from_truth(out / "build" / "sfm", out / "capture", out / "picks.json")
PYEOF
cli build-dataset "$OUT/capture/frames" --cad "$OUT/capture.toml" --out "$OUT/build" --preset fast \
  --init "$OUT/picks.json" --sfm-set num_threads=1 --gt "$OUT/capture" > "$OUT/build.log" 2>&1
cli infer "$OUT/sim/frames" --oracle-gt "$OUT/sim" --cad "$OUT/tiny.toml" --depth "$OUT/sim" --gt "$OUT/sim" \
  --out "$OUT/infer" > "$OUT/infer.log" 2>&1
cli fuse "$OUT/sim" --out "$OUT/fuse" --voxel 0.03 > "$OUT/fuse.log" 2>&1
cli emulate lidar "$OUT/tiny.toml" --out "$OUT/lidar" --preset vlp16 --pose 2.5,-2.0,1.0 > "$OUT/lidar.log" 2>&1
cli emulate sonar "$OUT/tiny.toml" --out "$OUT/sonar" --preset fast --look-at 0,0,0.3 > "$OUT/sonar.log" 2>&1
echo "ran in $(( $(date +%s) - t0 )) s" > "$OUT/time.txt"
"$PY" - "$OUT" > "$OUT/hashes.txt" <<'PYEOF'
import hashlib
import sys
from pathlib import Path

import numpy as np

out = Path(sys.argv[1])
scene = "dataset/all/000000"
picked = ["sim/frames/000000.png", "sim/gt/sim/000000/depth/000000.png", f"build/{scene}/scene_gt.json",
          f"build/{scene}/mask_visib/000000_000000.png", f"build/{scene}/depth/000000.png", "infer/poses.jsonl",
          "fuse/mesh.ply", "fuse/map.npz", "lidar/scan.npz", "sonar/sonar.npz"]


def digest(p: Path) -> str:
    if p.suffix != ".npz":
        return hashlib.sha256(p.read_bytes()).hexdigest()
    h = hashlib.sha256()
    with np.load(p, allow_pickle=False) as z:
        for k in sorted(z.files):
            a = np.ascontiguousarray(z[k])
            h.update(f"{k}|{a.dtype.str}|{a.shape}|".encode())
            h.update(a.tobytes())
    return h.hexdigest()


for rel in picked:
    p = out / rel
    print(f"{digest(p) if p.is_file() else 'MISSING':64}  {rel}")
PYEOF
cat "$OUT/hashes.txt" "$OUT/time.txt"
