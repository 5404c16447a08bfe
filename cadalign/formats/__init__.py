"""Code that knows file formats: ROS bags, STEP/IGES, calibration files, ... (one module per format)."""
