"""Write visp_rbt's reference camera poses for ``cadalign infer --gt-poses`` (run from the repository root):

    python datasets/real/visp_rbt_truth.py ../shared/data/visp_rbt runs/visp_rbt_truth.json

The objects stand still on the desk, so the camera's pose in the frame-0 camera (the world of visp_rbt.toml)
is cMg(t) @ inv(cMg(0)), cMg being the AprilTag board's pose per frame (apriltag_data.json "grid"). It is
approximate (the board's pose is noisier round frame 49; see the data's SOURCE.txt).
"""

import json
import sys
from pathlib import Path

import numpy as np

root, out = Path(sys.argv[1]), Path(sys.argv[2])
grid = [np.asarray(g, dtype=np.float64) for g in json.loads((root / "apriltag_data.json").read_text())["grid"]]
names = sorted(p.name for p in (root / "frames").glob("*.png"))
frames = {n: (g @ np.linalg.inv(grid[0])).tolist() for n, g in zip(names, grid, strict=True)}
out.parent.mkdir(parents=True, exist_ok=True)
out.write_text(json.dumps({"frames": frames, "source": str(root / "apriltag_data.json")}))
