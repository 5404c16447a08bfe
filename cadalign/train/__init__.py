"""Training: the shared loop (checkpoints, resume, DDP), losses, augmentations, seg/depth trainers."""

from cadalign.train.loop import LoopConfig, StepFn, TrainResult, train_loop

__all__ = ["LoopConfig", "StepFn", "TrainResult", "train_loop"]
