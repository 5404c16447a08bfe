"""File formats: BOP datasets, COLMAP-style camera lists, images and meshes.

Format code has no dependency on the pipeline stages, so every stage may use it.
"""
