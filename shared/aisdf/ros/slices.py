"""The map sliced for 2D navigation, without ROS: the ground (which way is up, where the floor
is) from the surfel map, and the occupancy grid and 2D distance field of a height band above
the floor from the SDF sampled over it.

**Up.** The Atlanta frame's vertical has no sign. When it lies within 30 degrees of the world's
z axis, up is the side of it towards +z (REP-103: fixed frames are z-up), and within 3 degrees
it *is* +z (a grid tilted 2 degrees rises 3.5 cm a metre: the band would cut the floor), so a
z-up world gets a grid in its own x-y plane. Otherwise the horizontal surfels
decide: a floor's and a table top's surfels face up (their normals point into free space),
a ceiling's down, and up is the side whose surfels cover more area (a robot's camera sees far
more floor than ceiling; geometry alone cannot tell a floor from a ceiling, which face each
other). ``up`` in the settings overrides it.

**The floor** is the lowest height, in 5 cm bins, at which up-facing horizontal surfels cover at
least 30% of the area of the best-covered bin (a table top covers less than the floor it
stands on); its height is their area-weighted mean.

**The slice.** A column of the band is an obstacle where a sample the camera has observed is
within ``surface_m`` of a surface (the SDF below it); samples ``step`` apart vertically find
every surface in the band when ``step <= 2 surface_m`` (the sample nearest a surface point is
at most ``surface_m`` from it). The clearance of a column is the 2D Euclidean distance to the
nearest obstacle column (scipy's exact distance transform); the grid holds 100 where the
clearance is below the robot radius (and on every obstacle column, also with a radius of 0,
for consumers that inflate the grid themselves, as Nav2's inflation layer does), -1 elsewhere where no sample of the column was observed
(unknown) and 0 in the rest, as ``nav_msgs/OccupancyGrid`` and nvblox's static occupancy do.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

Z = np.array([0.0, 0.0, 1.0])
SNAP_DEG, HINT_DEG = 0.5, 30.0
BIN_M, FLOOR_SHARE = 0.05, 0.3


@dataclass(frozen=True)
class Ground:
    """The grid's frame in the world: columns of ``R`` are the grid's x and y (horizontal) and up;
    ``height`` is the floor's height along up (``up . p``)."""

    R: np.ndarray
    height: float | None

    @property
    def up(self) -> np.ndarray:
        return self.R[:, 2]

    @property
    def z_up(self) -> bool:
        """The grid's axes are the world's (boxes along the world axes sample it)."""
        return bool(np.allclose(self.R, np.eye(3)))

    def to_world(self, g: np.ndarray) -> np.ndarray:
        """Grid coordinates (x, y, height above the floor) -> world points."""
        g = np.asarray(g, np.float64)
        return (g + [0.0, 0.0, self.height or 0.0]) @ self.R.T

    def to_grid(self, p: np.ndarray) -> np.ndarray:
        return np.asarray(p, np.float64) @ self.R - [0.0, 0.0, self.height or 0.0]


def _horizontal_surfels(s: dict, v: np.ndarray):
    d = np.asarray(s.get("direction", np.zeros(0)))
    if len(d) == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    n = np.asarray(s["normal"], np.float64)
    keep = (d == -1) & (np.abs(n @ v) > 0.9)
    area = np.prod(np.asarray(s["extent"], np.float64), axis=1)
    return np.sign(n[keep] @ v), np.asarray(s["center"], np.float64)[keep] @ v, area[keep]


def find_up(vertical, surfels: dict, up=None) -> np.ndarray:
    if up is not None:
        u = np.asarray(up, np.float64)
        return u / np.linalg.norm(u)
    v = np.asarray(vertical, np.float64)
    v = v / np.linalg.norm(v)
    if abs(v @ Z) > np.cos(np.radians(HINT_DEG)):
        up = v * np.sign(v @ Z)
        return Z.copy() if up @ Z > np.cos(np.radians(SNAP_DEG)) else up
    side, _, a = _horizontal_surfels(surfels, v)
    return v if a[side > 0].sum() >= a[side < 0].sum() else -v


def floor_height(up: np.ndarray, surfels: dict) -> float | None:
    side, h, a = _horizontal_surfels(surfels, up)
    h, a = h[side > 0], a[side > 0]
    if len(h) == 0:
        return None
    bins = np.floor(h / BIN_M).astype(np.int64)
    keys, inv = np.unique(bins, return_inverse=True)
    cover = np.bincount(inv, weights=a)
    k = keys[np.nonzero(cover >= FLOOR_SHARE * cover.max())[0][0]]
    near = np.abs(h - (k + 0.5) * BIN_M) <= BIN_M
    return float(np.average(h[near], weights=a[near]))


def ground_from_surfels(vertical, surfels: dict, floor: float | None = None, up=None) -> Ground:
    """The ground of a surfel map (``SurfelMap.vertical`` and ``.surfels``); ``floor`` and ``up``
    override the floor height and the up direction found."""
    up = find_up(vertical, surfels, up)
    if np.allclose(up, Z):
        R = np.eye(3)
    else:
        x = np.array([1.0, 0.0, 0.0]) - up[0] * up
        if np.linalg.norm(x) < 0.3:
            x = np.array([0.0, 1.0, 0.0]) - up[1] * up
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(up, x), up], axis=1)
    return Ground(R, floor if floor is not None else floor_height(up, surfels))


def surfel_extent(ground: Ground, surfels: dict, margin: float = 0.5) -> tuple[np.ndarray, np.ndarray] | None:
    """The grid-plane box (lo, hi) of every surfel's corners, grown by ``margin``."""
    c = np.asarray(surfels.get("center", np.zeros((0, 3))), np.float64)
    if len(c) == 0:
        return None
    a1, a2 = np.asarray(surfels["axis1"], np.float64), np.asarray(surfels["axis2"], np.float64)
    e = np.asarray(surfels["extent"], np.float64) / 2
    corners = np.concatenate([c + s1 * e[:, :1] * a1 + s2 * e[:, 1:] * a2 for s1 in (-1, 1) for s2 in (-1, 1)])
    g = ground.to_grid(corners)[:, :2]
    return g.min(0) - margin, g.max(0) + margin


@dataclass
class Slice:
    """The band's result per column: ``obstacle`` and ``observed`` (nx, ny) booleans."""

    obstacle: np.ndarray
    observed: np.ndarray


def band_levels(band: tuple[float, float], surface_m: float) -> np.ndarray:
    """Heights above the floor sampled in the band: ends included, at most 2 ``surface_m`` apart."""
    lo, hi = band
    n = max(1, int(np.ceil((hi - lo) / (2 * surface_m) - 1e-9))) + 1
    return np.linspace(lo, hi, n)


def slice_columns(sdf: np.ndarray, observed: np.ndarray, surface_m: float) -> Slice:
    """Columns of SDF samples (nx, ny, levels) -> obstacles and observed columns."""
    seen = np.asarray(observed, bool)
    return Slice(((np.asarray(sdf) < surface_m) & seen).any(axis=-1), seen.any(axis=-1))


def clearance(obstacle: np.ndarray, resolution: float) -> np.ndarray:
    """Metres from each column's centre to the nearest obstacle column's centre (0 on one;
    inf when there is none)."""
    if not obstacle.any():
        return np.full(obstacle.shape, np.inf)
    return ndimage.distance_transform_edt(~obstacle, sampling=resolution)


def occupancy(obstacle: np.ndarray, observed: np.ndarray, resolution: float, robot_radius: float):
    """(int8 grid (nx, ny): 100 / 0 / -1, clearance (nx, ny) metres)."""
    d = clearance(obstacle, resolution)
    grid = np.where(obstacle | (d < robot_radius), 100, 0).astype(np.int8)
    grid[~observed & (d >= robot_radius)] = -1
    return grid, d
