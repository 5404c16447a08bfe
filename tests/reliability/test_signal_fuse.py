"""Fusion stopped by a real SIGINT (``os.kill`` of this process while a frame is read) resumes from its last
checkpoint and ends with the same map as an uninterrupted run. In-process: the fusion CLI checkpoints every 50
frames, more than a test scene has, so the checkpoint interval is shrunk through the library call."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest
from sim_testdata import write_tiny_scene

from cadalign.fuse.config import FuseConfig
from cadalign.fuse.inputs import FrameSource
from cadalign.fuse.map_io import load_map, read_ply
from cadalign.fuse.run import REPORT, run
from cadalign.io import read_json

CFG = FuseConfig(voxel_m=0.04, block_count=2000, depth_max_m=12.0)


@pytest.fixture(scope="module")
def sim6(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    from cadalign.sim.run import simulate

    root = tmp_path_factory.mktemp("sigfuse")
    scene = write_tiny_scene(root / "tiny.toml", effects=[], frames=6)
    return simulate(scene, root / "sim", video=False, contact_sheet=False)


def test_fuse_sigint_resumes_from_its_checkpoint_to_the_uninterrupted_map(sim6: Path, tmp_path: Path,
                                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGINT while the 5th frame is read (checkpoint every 2 frames): KeyboardInterrupt, map.npz holds the 4
    checkpointed frames and loads; the re-run fuses the other 2 and the map's arrays are bitwise those of an
    uninterrupted run (same frames in the same order from the same state)."""
    ref = run(CFG, sim6, tmp_path / "ref", with_eval=False, checkpoint_every=2)
    real_frame = FrameSource.frame
    reads = {"n": 0}

    def frame_then_ctrl_c(self: FrameSource, im_id: int):  # noqa: ANN202 - test double
        reads["n"] += 1
        if reads["n"] == 5:
            os.kill(os.getpid(), signal.SIGINT)  # delivered as KeyboardInterrupt at the next bytecode
        return real_frame(self, im_id)

    monkeypatch.setattr(FrameSource, "frame", frame_then_ctrl_c)
    with pytest.raises(KeyboardInterrupt):
        run(CFG, sim6, tmp_path / "cut", with_eval=False, checkpoint_every=2)
    assert not (tmp_path / "cut" / REPORT).exists()
    assert load_map(tmp_path / "cut" / "map.npz")[1].frame_ids == [0, 1, 2, 3]
    monkeypatch.setattr(FrameSource, "frame", real_frame)
    run(CFG, sim6, tmp_path / "cut", with_eval=False, checkpoint_every=2)
    assert read_json(tmp_path / "cut" / REPORT)["timing"]["frames"] == 2
    (a, meta_a), (b, meta_b) = load_map(ref / "map.npz"), load_map(tmp_path / "cut" / "map.npz")
    assert meta_a.frame_ids == meta_b.frame_ids == list(range(6))
    sa, sb = a.state(), b.state()
    assert sa.keys() == sb.keys()
    for k in sa:
        np.testing.assert_array_equal(sa[k], sb[k], err_msg=k)
    # the mesh: the same vertices and labels (Open3D lists a re-opened map's blocks in another order)
    (va, fa), (vb, fb) = read_ply(ref / "mesh.ply"), read_ply(tmp_path / "cut" / "mesh.ply")
    assert len(va) == len(vb) > 1000 and len(fa) == len(fb)
    oa, ob = np.lexsort([va[n] for n in ("x", "y", "z")]), np.lexsort([vb[n] for n in ("x", "y", "z")])
    for n in va.dtype.names:
        np.testing.assert_array_equal(va[n][oa], vb[n][ob], err_msg=n)
