"""Fusion stopped by a real SIGINT (``os.kill`` of this process) keeps every fully fused frame and ends, after a
re-run, with the same map as an uninterrupted run. In-process, so the signal can be timed to a frame (the CLI
gives no outside sign of which frame it is fusing)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

import numpy as np
import pytest

from cadalign.fuse.config import FuseConfig
from cadalign.fuse.inputs import FrameSource
from cadalign.fuse.map_io import load_map, read_ply
from cadalign.fuse.run import REPORT, run
from cadalign.fuse.tsdf import SemanticTSDF
from cadalign.io import read_json
from cadalign.testing.tiny_scene import write_tiny_scene

CFG = FuseConfig(voxel_m=0.04, block_count=2000, depth_max_m=12.0)


@pytest.fixture(scope="module")
def sim6(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    from cadalign.sim.run import simulate

    root = tmp_path_factory.mktemp("sigfuse")
    scene = write_tiny_scene(root / "tiny.toml", effects=[], frames=6)
    return simulate(scene, root / "sim", video=False, contact_sheet=False)


@pytest.fixture()
def sigint_raises():
    """SIGINT -> KeyboardInterrupt, as in an interactive run: pytest-xdist workers ignore SIGINT."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


@pytest.mark.parametrize("where", ["read", "integrate"])
def test_fuse_sigint_resumes_to_the_uninterrupted_map(where: str, sim6: Path, tmp_path: Path, sigint_raises: None,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    """SIGINT to this process on the 5th frame, with the CLI's checkpoint interval (50 frames, so no periodic
    checkpoint yet). While the frame is read (between integrations), the 4 fused frames are checkpointed before
    the KeyboardInterrupt propagates; during its integration nothing is written (the map may hold part of it).
    Either way the re-run ends with map arrays bitwise equal to an uninterrupted run's and the same mesh."""
    ref = run(CFG, sim6, tmp_path / "ref", with_eval=False)
    cls, name = (FrameSource, "frame") if where == "read" else (SemanticTSDF, "integrate")
    real = getattr(cls, name)
    calls = {"n": 0}

    def ctrl_c_on_the_fifth(self, *args):  # noqa: ANN001, ANN202 - test double
        calls["n"] += 1
        if calls["n"] == 5:
            os.kill(os.getpid(), signal.SIGINT)  # a real signal
            for _ in range(400):  # the handler runs here, not later inside a C call of another thread's step
                time.sleep(0.005)
        return real(self, *args)

    monkeypatch.setattr(cls, name, ctrl_c_on_the_fifth)
    with pytest.raises(KeyboardInterrupt):
        run(CFG, sim6, tmp_path / "cut", with_eval=False)
    assert calls["n"] == 5 and not (tmp_path / "cut" / REPORT).exists()
    if where == "read":
        assert load_map(tmp_path / "cut" / "map.npz")[1].frame_ids == [0, 1, 2, 3]
    else:
        assert not (tmp_path / "cut" / "map.npz").exists()
    monkeypatch.setattr(cls, name, real)
    run(CFG, sim6, tmp_path / "cut", with_eval=False)
    assert read_json(tmp_path / "cut" / REPORT)["timing"]["frames"] == (2 if where == "read" else 6)
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
