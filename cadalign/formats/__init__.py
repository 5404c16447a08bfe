"""Code that knows file formats: ROS bags, STEP/IGES, calibration files, TUM trajectories (one module per
format). The lowest layer beside types/errors/io/config/geometry: it never imports a stage."""
