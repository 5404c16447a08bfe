"""Image verification of a CAD alignment: the CAD's rendered edges and free space checked against the frames
(:mod:`.core`), the evidence per hypothesis (:mod:`.evidence`), its config (:mod:`.config`) and the stage step that
refuses a placement the images contradict (:mod:`.run`)."""
