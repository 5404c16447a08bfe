"""Networks (``nn.Module`` only): ResUNet segmentation, DispNet-style depth, Mask R-CNN + pose head, ops.

Import the submodules directly (``from cadalign.models.resunet import ResUNet``); this package imports
nothing so that loading one network does not load the others.
"""
