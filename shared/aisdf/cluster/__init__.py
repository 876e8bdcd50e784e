"""Several mapper processes sharing one map (protocol 1.14): who owns which region of the
submap grid (``ownership``), and which regions a keyframe touches (``regions``)."""

from .ownership import ALL, LEGACY, needed_acks, owners, rank, region_id, region_of, satisfied, surfel_owner

__all__ = ["ALL", "LEGACY", "needed_acks", "owners", "rank", "region_id", "region_of", "satisfied", "surfel_owner"]
