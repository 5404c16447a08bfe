"""Accuracy-versus-time benchmarks (``cadalign bench``): the framework (:mod:`.framework`), the registry of stages
(:mod:`.registry`), one sweep module per stage, the Pareto front (:mod:`.pareto`) and the HTML page (:mod:`.report`)."""
