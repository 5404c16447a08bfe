"""The ``cadalign`` command line: one thin file per command."""
