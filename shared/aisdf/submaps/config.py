"""The submap mapper's settings (``submap.*`` of the mapper's configuration): how space is
cut into submaps, how steps are shared among them, when changed ones are published, and
whether measured points go with them."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from ..config import Model


class SubmapConfig(Model):
    """How space is cut into submaps and how steps are shared among them."""

    cell_m: float = Field(6.0, gt=0, description="horizontal size of a submap's cell (m). Larger cells: fewer "
                          "submaps, more steps each, but a larger share of the map changes each period. aisdf bench "
                          "scaling, seeds 0-2, +60 s: 8 m gave the floor 3.83 cm and the office 1.28 (6 m the same "
                          "days: 4.02, 1.41), within one walk's noise, but published 0.315 of republishing "
                          "everything (one seed 0.34, over the issue's 1/3; 6 m: 0.29); 10 m (seeds 0-1) 0.37 "
                          "(docs/experiments/scaling-notes.md, Cell size)")
    cell_height_m: float = Field(6.0, gt=0, description="vertical size of a cell (m): one storey fits one layer")
    overlap_m: float = Field(0.5, gt=0, description="each submap reaches this far into its neighbours; answers "
                          "blend over twice this width")
    min_share: float = Field(0.03, ge=0, le=1, description="a keyframe joins a submap when at least this share of "
                          "its sampled ray points fall in the submap's box")
    min_points: int = Field(40, ge=1, description="... and at least this many of them")
    active_keyframes: int = Field(2, ge=1, description="submaps the newest this many keyframes see are trained")
    refine_every: int = Field(8, ge=0, description="every n-th step refines the least trained submap (0 = never)")
    idle_steps: int = Field(30, ge=1, description="after this many steps without a new keyframe, every step "
                         "refines the least trained submap")
    warm_start: bool = Field(True, description="a new submap's network starts as a copy of its most trained "
                             "neighbour's (else a fresh network)")
    grid_wait_keyframes: int = Field(3, ge=1, description="keyframes to wait for an Atlanta frame before the grid "
                                  "falls back to the world's axes")
    background_publish_steps: int = Field(8, ge=1, description="a submap out of view (none of the newest "
                                          "keyframes sees it) changed by background refinement is published once "
                                          "it has this many unpublished steps ...")
    background_publish_periods: int = Field(10, ge=1, description="... or this many publications after its first "
                                            "unpublished step; submaps in view and new ones go out at once")
    repose_networks: Literal["move", "reset", "keep"] = Field("move", description="after a pose correction "
                                                              "(protocol 1.11), a submap whose keyframes changed: "
                                                              "move = its network moved rigidly with them (the "
                                                              "motion fitted to their observed points in its box), "
                                                              "or reset when no one motion carries them within "
                                                              "repose_reset_m; reset = a fresh network trained on "
                                                              "the corrected keyframes (the old surfaces go at "
                                                              "once); keep = the old network trained on")
    repose_reset_m: float = Field(0.1, ge=0, description="... (reset only when one of its keyframes' observed "
                                  "points moved by more than this, m: a smaller correction keeps the network) ...")
    repose_distill_steps: int = Field(200, ge=0, description="... with move, a reset network first learns the "
                                      "old one's field warped by the correction, point by point, in this many "
                                      "steps (0: a fresh network only)")
    repose_steps: int = Field(30, ge=0, description="... and trained this many steps at once, before the corrected "
                              "map is published")
    measured: bool = Field(True, description="pool the keyframes' depth pixels into 10 cm voxels and publish, with "
                           "each submap, the mean points of the voxels in its extended box (protocol 1.4: the query "
                           "service's fused answers use them; docs/experiments/scaling-notes.md, The measured surface)")
