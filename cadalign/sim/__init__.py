"""Synthetic underwater scenes with exact ground truth.

``load_scene`` reads and validates a scene TOML; ``simulate`` renders it into a
capture folder (frames, video) plus BOP ground truth.
"""
