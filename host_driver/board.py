"""The board interface: block rays in, one blocked/clear bit per ray out.

Every back-end (``golden`` float64, ``model`` bit-exact, the simulated RTL ones) implements
:class:`Board`, and the host driver talks to nothing else. A **block ray** is the paper's bundle:
the rays from S_b shooter sample points to the centroids of R_b receiver patches (every
shooter-receiver pair is a ray), together with the voxels the bundle visits. The board tests
every patch registered in those voxels against every ray of the block.

Life cycle::

    board.prepare(scene, samples)   # fix the board's geometry (e.g. quantise); sets board.margin
    grid = VoxelGrid(..., margin=board.margin)
    board.load(grid)                # patch memory and voxel tables
    bits = board.run(blocks)        # list of (R_b, S_b) bool arrays, True = blocked
    board.counters()                # dict of measured counters (at least "tests")
"""

from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

__all__ = ["BlockRay", "Board"]


@dataclass
class BlockRay:
    shooter_patch: np.ndarray    # (S_b,) int64: patch of each shooter point (array column)
    shooter_sample: np.ndarray   # (S_b,) int64: sample index on that patch (see SampleScheme)
    receiver_patch: np.ndarray   # (R_b,) int64: receiver patches (array rows); end point = centroid
    voxels: np.ndarray           # (K,) int64: linear voxel indices the bundle visits, in order

    @property
    def rays(self):
        return len(self.shooter_patch) * len(self.receiver_patch)


class Board(ABC):
    """Answers visibility queries for block rays. See the module docstring for the life cycle."""

    name = "abstract"

    #: registration/traversal margin in scene units the voxel grid must add (set by prepare)
    margin: float = 0.0

    @abstractmethod
    def prepare(self, scene, samples):
        """Take the scene's geometry and the sample scheme; set :attr:`margin`."""

    @abstractmethod
    def load(self, grid):
        """Take the voxel grid's patch registration (voxel -> patch lists)."""

    @abstractmethod
    def run(self, blocks):
        """Return one (R_b, S_b) bool array per block: True where the ray is blocked."""

    @abstractmethod
    def counters(self):
        """Measured counters since prepare: at least ``tests`` (ray-patch tests performed)."""
