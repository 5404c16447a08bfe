"""Pure metric functions over arrays and posed objects: pose (ADD, rotation and translation errors, BOP scores with
symmetries), segmentation, depth, dataset-vs-truth and map metrics, and ``CroppedMask``. No stage imports: every
stage and ``cadalign eval`` may use them."""
