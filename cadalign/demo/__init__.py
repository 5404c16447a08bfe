"""``cadalign demo``: the whole pipeline on the embedded default scene (:mod:`.run`), one function per stage
(:mod:`.stages`)."""
