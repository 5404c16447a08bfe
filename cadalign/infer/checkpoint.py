"""What a detector-path ``infer`` run (:func:`cadalign.infer.run.run`) stopped early keeps, and how it goes on.

Each finished frame's poses are appended to ``poses.jsonl.partial`` and its overlay picture to ``overlay.partN.mp4``.
Every ``checkpoint_every`` frames, and when SIGINT / SIGTERM (Ctrl-C, a scheduler) stops the run between two
frames, the run's state is pickled to ``infer_state.pkl``: the pipeline's memory across frames (its tracks, the
last frame's boxes, the completion's points), the frame lists so far, and how many poses lines and overlay pieces
they cover; the overlay then starts a new piece. The same command loads it, drops the poses lines and overlay pieces
written after it, and goes on from the next frame. Its results are an uninterrupted run's, but for the finished
frames' records, which it reads back from the poses file (scores to 6 decimals, boxes to 1/1000 px). The file is
this tool's own state of this run folder, read back only by the same command.
"""

from __future__ import annotations

import logging
import pickle
from dataclasses import dataclass, field, replace
from pathlib import Path

from cadalign.infer.pipeline import PosePipeline, PoseRecord
from cadalign.infer.video import overlay_pieces
from cadalign.io import atomic_path

log = logging.getLogger(__name__)

STATE = "infer_state.pkl"
POSES_PARTIAL = "poses.jsonl.partial"


@dataclass
class RunState:
    """A detector-path run's progress (module doc)."""

    last_index: int = -1
    """Index of the last frame finished (-1: none)."""
    poses_lines: int = 0
    """Lines of ``poses.jsonl.partial`` those frames wrote."""
    pieces: int = 0
    """Overlay pieces those frames filled (``overlay.part0.mp4`` ...)."""
    records: list[PoseRecord] = field(default_factory=list)
    """The records so far (not pickled: read back from ``poses.jsonl.partial``)."""
    names: list[str] = field(default_factory=list)
    stamps: dict[str, int] = field(default_factory=dict)
    shapes: dict[str, tuple[int, int]] = field(default_factory=dict)
    times: dict[str, list[float]] = field(default_factory=dict)
    memory: tuple = ()
    """The pipeline's state across frames: (temporal fuser, last frame's boxes, completion points)."""

    def save(self, out_dir: Path, pipeline: PosePipeline) -> None:
        """Pickle the state (atomically) with ``pipeline``'s memory across frames; not the records, which
        ``poses.jsonl.partial`` holds (a long video's would make each checkpoint longer than the last)."""
        self.memory = (pipeline.fuser, pipeline._prev, pipeline.points)
        with atomic_path(Path(out_dir) / STATE) as tmp, open(tmp, "wb") as fh:
            pickle.dump(replace(self, records=[]), fh, protocol=pickle.HIGHEST_PROTOCOL)

    def restore(self, pipeline: PosePipeline) -> None:
        """Give ``pipeline`` the memory across frames it had at the checkpoint."""
        if self.memory:
            pipeline.fuser, pipeline._prev, pipeline.points = self.memory


def take_over(out_dir: Path, same_config: bool) -> RunState:
    """The state an earlier run of the same config left in ``out_dir``, its poses and overlay cut back to it (a new
    run without one); with another config, or without a checkpoint, its partial files are deleted."""
    out_dir = Path(out_dir)
    path, poses = out_dir / STATE, out_dir / POSES_PARTIAL
    state = None
    if same_config and path.is_file():
        with open(path, "rb") as fh:
            state = pickle.load(fh)
    if not isinstance(state, RunState):
        for p in [path, poses, *overlay_pieces(out_dir)]:
            p.unlink(missing_ok=True)
        return RunState()
    lines = poses.read_text(encoding="utf-8").splitlines(keepends=True) if poses.is_file() else []
    if len(lines) < state.poses_lines:
        log.warning("%s holds %d lines but %s counts %d: starting the run again", poses, len(lines), path,
                    state.poses_lines)
        for p in [path, poses, *overlay_pieces(out_dir)]:
            p.unlink(missing_ok=True)
        return RunState()
    poses.write_text("".join(lines[:state.poses_lines]), encoding="utf-8")
    for p in overlay_pieces(out_dir)[state.pieces:]:
        p.unlink()
    log.info("infer: resuming %s after frame %s (%d frames finished before)", out_dir,
             state.names[-1] if state.names else "-", len(state.names))
    return state
