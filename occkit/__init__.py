"""occkit: 3D semantic occupancy prediction in pure PyTorch.

Importing the package is cheap (no torch import), so ``occkit --help`` answers at once; import the
subpackages you need: ``occkit.geometry``, ``occkit.config``, ``occkit.classes``.
"""

__version__ = "0.1.0"
