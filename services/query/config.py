"""Query service configuration (defaults here; file, AISDF_* environment, command line)."""

from __future__ import annotations

import secrets
from typing import Literal

from pydantic import Field, field_validator

from aisdf import keys
from aisdf.config import ServiceConfig
from aisdf.structure.fusion import DEFAULT_FUSE_RADIUS


def default_replica_id() -> str:
    """``<hostname>-<6 random hex digits>``, new at every start and kept nowhere: replicas on one
    host (or in containers sharing the host's name) never collide, and an operator sees the host."""
    return f"{keys.host_chunk()}-{secrets.token_hex(3)}"


class QueryConfig(ServiceConfig):
    """Settings of ``aisdf-query``."""

    replica_id: str | None = Field(None, description="protocol 1.12: this replica's id in "
                                   "query/replica/<id>/{sdf,mesh} and its liveliness tokens (one key chunk: letters, "
                                   "digits, '-', '_', '.'); None = <hostname>-<6 random hex digits>, new at every "
                                   "start. Give each replica in a namespace its own")

    max_points: int = Field(1_000_000, ge=1, description="largest batch answered; above it: too_large")
    chunk_points: int = Field(65_536, ge=1, description="points evaluated per network pass on a GPU (bounds memory); "
                              "on a CPU at most 4,096 (the activations of each pass with gradients, per worker)")
    device: Literal["auto", "cpu", "cuda"] = Field("auto", description="auto = cuda when available")
    torch_threads: int | None = Field(1, ge=1, description="torch CPU threads per evaluation; None keeps torch's "
                                      "default. Parallelism comes from `workers` and `bake_threads` instead: several "
                                      "threads each running single-threaded torch do not spin-wait on a busy machine")
    fuse_radius: float = Field(DEFAULT_FUSE_RADIUS, gt=0, description="fused source uses a surfel only when it is "
                               "this close (m); the incremental bake re-evaluates this far (+5 cm) around changed "
                               "surfels (aisdf.structure.fusion)")
    mesh_resolution: float = Field(0.05, gt=0, description="default marching-cubes voxel size (m)")
    mesh_max_cells: int = Field(16_000_000, ge=1, description="largest marching-cubes grid; above it: too_large")
    mesh_tile: int = Field(64, ge=2, le=1024, description="marching cubes in tiles of at most this many samples per "
                           "edge (memory: one tile's samples, whatever the map's size)")
    weights_retry_s: float = Field(2.0, gt=0, description="how often to ask for the latest map until one arrives")
    submap_get_timeout_s: float = Field(5.0, gt=0, description="protocol 1.3: how long a get on map/submaps/** "
                                        "(late join, a submap the index lists newer) waits for its replies")
    # Protocol 1.1: the baked field and load shedding.
    bake: bool = Field(True, description="bake the fused field of every new map and answer fused requests from it")
    bake_threads: int = Field(2, ge=1, le=64, description="threads evaluating the network while baking")
    bake_nice: int = Field(0, ge=0, le=19, description="nice value of the baking threads (Linux); above 0 a mapper "
                           "on the machine goes first. 0: under planners' load a starved bake leaves the space mapped "
                           "since to the networks at every request (aisdf bench load: p50 47 ms at 0, 76-90 ms at 10)")
    bake_duty: float = Field(0.75, gt=0, le=1, description="largest share of the time spent baking: after a bake "
                             "of t seconds the baker rests t * (1/bake_duty - 1) seconds")
    fresh_s: float = Field(2.0, ge=0, description="protocol 1.7: once the bake trails the newest map by more than "
                           "this (s), the regions of the submaps that changed since the bake are answered from the "
                           "newest map until the bake catches up; 0 = always")
    fresh_busy: bool = Field(False, description="freshen (fresh_s) also while sdf requests wait for a worker; false = "
                             "planners first: while they wait, answers come from the bake (its version and map_age_s "
                             "in the reply), since an answer from the newest map costs some 40x a baked one")
    bake_block: float = Field(0.2, gt=0, description="baked field: block edge and coarse spacing (m)")
    bake_fine: int = Field(2, ge=1, le=16, description="baked field: fine cells per block edge where refined")
    bake_tol: float = Field(0.005, gt=0, description="baked field: refine a block whose coarse interpolant misses "
                            "the field at its centre by more (m)")
    bake_near_surface: bool = Field(False, description="baked field: also refine every block a surface may cross")
    bake_band: float = Field(0.05, ge=0, description="baked field: extra margin (m) of the near-surface test")
    bake_surfel_tol: float = Field(0.001, ge=0, description="baked field: a re-bake keeps the samples around a surfel "
                                   "that moved less than this (m; every surfel moves a little whenever the Atlanta "
                                   "frame is refined); 0 = re-evaluate around every change")
    layout_prior: bool = Field(True, description="protocol 1.13: fused answers are capped at the layout predicted "
                               "beyond what was observed (floor, ceiling and walls carried on into unobserved space, "
                               "aisdf.structure.layout; docs/protocol.md, The layout prior); false = 1.12's answers")
    measured: bool = Field(True, description="fused answers use the measured points a submap mapper publishes with "
                           "each submap (protocol 1.4: the surfel distance where nothing was measured nearer, capped "
                           "at the nearest measured point; docs/experiments/scaling-notes.md, The measured surface); false = the 1.3 answer")
    workers: int = Field(2, ge=1, le=64, description="threads evaluating sdf requests")
    queue_max: int = Field(32, ge=1, description="sdf requests waiting; beyond, an immediate 'busy' error reply")

    @field_validator("replica_id")
    @classmethod
    def _replica_id(cls, v: str | None) -> str | None:
        return None if v is None else keys.validate_replica_id(v)
