"""What the benchmark tests share (a module of its own: ``from conftest import ...`` picks whichever test
folder's conftest was imported first when several folders run together)."""

CHEAP_STAGES = ("render", "align", "emulate", "fuse")
"""The stages the shared tiny benchmark folder runs (seconds each at --size tiny)."""
