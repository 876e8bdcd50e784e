"""The mapper in-process, driven alike by the mapper service, the benchmarks and the tests:
the written interface (:class:`Mapper`), the keyframe intake both mappers share, the
one-network mapper (``single``), and ``factory`` (``make_mapper``, ``restore_mapper``).
The submap mapper lives in :mod:`aisdf.submaps`."""

from .interface import MAPPER_KINDS, Mapper

__all__ = ["MAPPER_KINDS", "Mapper"]
