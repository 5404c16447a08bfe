"""Online model-based tracking of the whole CAD structure from RGB video (issue 43).

The structure and its static parts are one rigid CAD assembly, so one pose per frame is tracked: the camera's
pose relative to the structure, ``T_cam_from_world``. Each frame starts from a motion-model prediction and is
corrected against the image by CAD occluding-contour / image-edge correspondences (moving edges, coarse to
fine, Tukey IRLS; :mod:`cadalign.infer.track.edges`). A frame whose contours find too little support in the
image is declared lost and no pose is reported for it.
"""
