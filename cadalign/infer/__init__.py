"""Per-frame 6-DoF pose inference on ROV video: detector -> refinement against the CAD -> temporal fusion."""
