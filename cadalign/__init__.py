"""cadalign: CAD-aligned ground truth, models and maps for underwater inspection robots.

Importing the package is cheap: heavy dependencies (torch, open3d, pycolmap,
pyrender) are imported lazily inside the functions that need them.
"""

from cadalign._version import __version__

__all__ = ["__version__"]
