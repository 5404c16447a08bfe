"""Mask R-CNN with a per-RoI 6-DoF pose head, in pure torch (+ kornia)."""

from cadalign.models.maskrcnn.detector import Detection, MaskRCNNConfig, MaskRCNNPose, PoseRoIs, load_pose_model

__all__ = ["Detection", "MaskRCNNConfig", "MaskRCNNPose", "PoseRoIs", "load_pose_model"]
