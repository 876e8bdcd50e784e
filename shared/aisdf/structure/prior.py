"""The global surfel map as a prior on distances for training (``TrainingConfig.surfel_bounds``).

A surfel is a piece of observed surface, so a point's distance to the nearest surfel is an
upper bound on its distance to any surface. :class:`SurfelPrior` answers that distance (and
the unit direction away from the nearest surfel point) for a trainer's free samples, from the
map as it stands (rebuilt when a keyframe has changed it). Restricted to a ball (a submap's
box), it keeps only the surfels that may come near it: dropping surfels only loosens the
bound, it never makes it wrong.
"""

from __future__ import annotations

import numpy as np

from .surfel_map import ExplicitSdf, _pack, _pair_distance


class SurfelPrior:
    """Distances to the global surfel map of ``structure`` (a :class:`~aisdf.structure.Structure`);
    with ``centre`` and ``radius``, only the surfels that come within ``radius`` of ``centre``."""

    def __init__(self, structure, centre: np.ndarray | None = None, radius: float | None = None):
        self.structure = structure
        self.centre = None if centre is None else np.asarray(centre, np.float64)
        self.radius = radius
        self._key: int | None = None
        self._sdf: ExplicitSdf | None = None

    def _current(self) -> ExplicitSdf | None:
        key = self.structure.n_keyframes
        if key != self._key:
            s = self.structure.aligned_surfels()
            if self.centre is not None and len(s):
                d, _, _ = _pair_distance(np.repeat(self.centre[None], len(s), 0), _pack(s), np.arange(len(s)))
                s = s[np.flatnonzero(d <= self.radius)]
            self._sdf = ExplicitSdf(s) if len(s) else None
            self._key = key
        return self._sdf

    def __call__(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sdf = self._current()
        if sdf is None:
            return np.full(len(points), np.inf), np.zeros((len(points), 3))
        d, g, _ = sdf(points, signed=False)
        return d, g
