"""``cadalign eval``: trained networks scored on a dataset split (:mod:`.dense`), SfM against a simulation's truth
(:mod:`.sfm`), robustness sweeps (:mod:`.robustness`) and the demo's HTML report (:mod:`.report`)."""
