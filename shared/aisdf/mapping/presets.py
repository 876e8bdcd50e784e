"""Named training presets: plain dicts of ``TrainingConfig`` overrides.

* ``paper``: iSDF's numbers exactly (the config defaults): width 256 (460k parameters),
  5 frames x 200 rays x 27 samples = 27,000 points a step. Measured on the 2-core dev CPU
  (AMD EPYC, torch 2.13): 3.0 s/step with 1 thread, ~1.6 s with 2 threads.
* ``cpu``: a 2-core CPU, chosen by measurement (box-room scene, mean |SDF error| on iSDF's
  evaluation points after equal CPU time, 60 s): width 128 (148k parameters), iSDF's 5-frame
  window kept, 40 rays per frame, 1 + 5 + 11 = 17 samples per ray = 3,400 points a step;
  170 ms/step with 1 thread (~105 ms with 2 on an idle machine). Reached 2.4 cm in 60 s, vs
  2.6 cm (60 rays), 2.8 cm (4 frames x 50 rays), 3.6 cm (60 rays x 27 samples), 3.5 cm
  (width 64); single runs, noise about 1 cm. One thread: with 2, a step took 2-3.5 s
  whenever another process kept one of the two cores busy (OpenMP barrier stalls), so the
  preset sets ``torch_threads=1``.
* ``auto``: ``paper`` when CUDA is available, else ``cpu``.

Submaps (``SubmapPipeline.from_settings``) add ``SUBMAP_PRESETS[name]`` under the caller's
overrides. For ``cpu``, measured on the built-in floor (``aisdf bench scaling``, 200
keyframes at one a second, whole-floor fused error 60 s after the walk, single runs; run to
run spread about 0.5 cm):

* width 64 instead of 128: 5.99, 6.04, 5.48 cm vs 7.38, 6.78, 6.87 cm (a step costs 75 ms
  instead of 131 ms: 3,300 steps instead of 1,900; a submap covers only a few metres);
* ``lr_settle`` 2e-4: iSDF's constant rate keeps a trained field jittering (one cell trained
  on alone: 5.5, 6.3, 5.3, 6.1, 5.0 cm every 100 steps at 1.3e-3; 4.1, 3.7, 3.6, 3.6 cm at
  5e-4; 3.8, 3.8, 3.8, 3.7 cm at 2e-4). Decaying towards 2e-4 with steps since the submap's
  newest keyframe, half-life 100 / 25 / 10 steps: 5.11 / 4.57 / 4.44 cm; towards 1e-4 (10
  steps): 4.77 cm; with steps since the start (100): 5.44 cm. Settling only once a submap has
  had 5 steps per keyframe it holds (``lr_settle_after``): 4.69 cm. Without that condition an
  under-trained map suffered: two robots on the floor (tests/e2e/test_e2e_submaps.py with
  AISDF_TWO_ROBOTS_BUILDING=floor, 292 keyframes, ~830 steps) 15.0 cm against 10.9 cm at
  iSDF's constant rate; with it, 10.2 cm. The 200 m test: one run is chaotic (the office
  room shifted by 1 mm mapped 6.48 cm against 6.05 cm unshifted, seed 0), so single seeds
  at 200 m ranged 0.94-1.20x the origin's after 300 steps (six seeds, mean 1.067); with 200
  settling steps after the walk, 1.029, 1.038, 1.011x (seeds 0-2). The test compares those.
* ``replay_uniform`` 1: one of the three replayed keyframes of a window drawn uniformly
  (iSDF draws all three by their last loss, so a room learnt earlier, whose estimates are
  low and stale, is not revisited while its submap trains on new views at full rate). Floor
  at +60 s, seeds 0 / 1 / 2: 4.08 / 4.12 / 4.19 cm against 3.93 / 4.44 / 4.75 with iSDF's
  replay; worst room ratio 1.13 / 1.03 / 1.15 against 1.44 / 1.18 / 1.43; the office 1.28 /
  2.09 against 1.44 / 1.94 (seeds 1, 2). All three uniform: 3.81 / 4.23 / 4.13 cm, rooms
  1.07 / 1.41 / 1.80, the office 1.41 / 2.18 (docs/experiments/scaling-notes.md, Replay).
"""

from __future__ import annotations

from typing import Any

import torch

from ..config import deep_merge
from .config import TrainingConfig

PRESETS: dict[str, dict[str, Any]] = {
    "paper": {},
    "cpu": {
        "network": {"width": 128},
        "window_size": 5,
        "n_rays": 40,
        "n_gaussian": 5,
        "n_stratified": 11,
        "torch_threads": 1,
    },
}


SUBMAP_PRESETS: dict[str, dict[str, Any]] = {
    "paper": {},
    "cpu": {"network": {"width": 64}, "lr_settle": 2e-4, "lr_halflife_steps": 10.0, "lr_settle_after": 5.0,
            "replay_uniform": 1},
}


def resolve_preset(name: str) -> str:
    if name == "auto":
        return "paper" if torch.cuda.is_available() else "cpu"
    if name not in PRESETS:
        raise ValueError(f"unknown training preset {name!r}; known: {sorted(PRESETS) + ['auto']}")
    return name


def training_config(preset: str = "auto", **overrides: Any) -> TrainingConfig:
    """The preset's config with ``overrides`` (nested dicts merge, e.g. network={"width": 64})."""
    name = resolve_preset(preset)
    data = deep_merge({**PRESETS[name], "preset": name}, overrides)
    return TrainingConfig.model_validate(data)


def submap_training_config(preset: str = "auto", **overrides: Any) -> TrainingConfig:
    """A submap's config: the preset, then ``SUBMAP_PRESETS``, then ``overrides``."""
    name = resolve_preset(preset)
    return training_config(name, **deep_merge(SUBMAP_PRESETS[name], overrides))


def structure_overrides(training: dict[str, Any] | None, atlanta: bool, surfel_mask: bool = True,
                        surfel_loss: bool = True, surfel_bounds: bool = True) -> dict[str, Any]:
    """``training`` overrides with the Table II switches (and ``surfel_bounds``, beyond the
    paper) set where not given; each only matters with ``atlanta`` on (both mappers)."""
    overrides = dict(training or {})
    overrides.setdefault("surfel_bounds", bool(atlanta and surfel_bounds))
    overrides.setdefault("surfel_mask", bool(atlanta and surfel_mask))
    overrides.setdefault("surfel_loss", bool(atlanta and surfel_loss))
    return overrides
