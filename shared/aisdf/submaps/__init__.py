"""Submaps for whole buildings: the grid that partitions space (``grid``), the
blended field that answers from several submaps without seams (``field``) and the mapper's
submap pipeline (``pipeline``)."""

from .field import blend
from .grid import SubmapGrid, cell_id, parse_cell_id

__all__ = ["SubmapGrid", "blend", "cell_id", "parse_cell_id"]
