"""The board interface lives in the shared layer (:mod:`blockray.board`): the model (sim/) and the
host driver both implement it. Imported here for the host driver's modules."""

from ..board import BlockBatch, BlockBits, BlockRay, Board, ranges

__all__ = ["BlockRay", "BlockBatch", "BlockBits", "Board", "ranges"]
