"""Object poses of a build of the ViSP rbt capture against its derived truth.

Usage: CADALIGN_DATA_DIR=/work/shared/data python -m benchmarks.visp_rbt_truth OUT [DATA]

Truth (objects static on the desk): cMo(t) = cMg(t) @ inv(cMg(0)) @ cMo(0), from apriltag_data.json and
init/<name>.json (see the data's SOURCE.txt: a few mm / 1-2 deg, worse around frame 49). The scene file
datasets/real/visp_rbt.toml puts the world at camera 0, so cMo(0) is the objects' world pose.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def main(out: Path, data: Path = Path("/work/shared/data/visp_rbt")) -> dict:
    grid = [np.array(m) for m in json.loads((data / "apriltag_data.json").read_text())["grid"]]
    init = {n: np.array(json.loads((data / "init" / f"{n}.json").read_text())) for n in ("cube", "dragon")}
    scene = out / "dataset" / "all" / "000000"
    names = json.loads((scene / "frame_names.json").read_text())
    gt = json.loads((scene / "scene_gt.json").read_text())
    objs = {1: "cube", 2: "dragon"}
    errs: dict[str, list[tuple[float, float]]] = {n: [] for n in objs.values()}
    for im, annos in gt.items():
        k = int(Path(names[im]).stem.split("_")[-1])
        for a in annos:
            n = objs[a["obj_id"]]
            T = np.eye(4)
            T[:3, :3] = np.reshape(a["cam_R_m2c"], (3, 3))
            T[:3, 3] = np.asarray(a["cam_t_m2c"]) / 1000.0
            true = grid[k] @ np.linalg.inv(grid[0]) @ init[n]
            dR = T[:3, :3] @ true[:3, :3].T
            ang = float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))))
            errs[n].append((float(np.linalg.norm(T[:3, 3] - true[:3, 3])), ang))
    res = {n: {"frames": len(e), "median_cm": 100 * float(np.median([x[0] for x in e])),
               "median_deg": float(np.median([x[1] for x in e]))} for n, e in errs.items() if e}
    print(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main(Path(sys.argv[1]), *(Path(a) for a in sys.argv[2:3]))
