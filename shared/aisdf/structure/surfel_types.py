"""The rectangular surfel container every part shares (extraction, training, the
global map, the query service). World frame, float64 in memory; protocol.md's
SurfelMap carries the same fields as float32.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FIELDS = ("center", "normal", "axis1", "axis2", "extent", "direction", "keyframe")


def _empty(n: int, d: int | None) -> np.ndarray:
    return np.zeros((n, d) if d else (n,))


@dataclass
class Surfels:
    """N axis-aligned rectangles on Atlanta planes.

    center (N,3); normal (N,3) unit, pointing to free space; axis1, axis2 (N,3) unit,
    in-plane, orthogonal; extent (N,2) full side lengths along axis1, axis2;
    direction (N,) -1 for the vertical, k for horizontal[k]; keyframe (N,) frame_id or -1.
    """

    center: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    axis1: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    axis2: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    extent: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    direction: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.int64))
    keyframe: np.ndarray = field(default_factory=lambda: np.zeros((0,), dtype=np.int64))

    def __post_init__(self) -> None:
        self.center = np.asarray(self.center, dtype=np.float64).reshape(-1, 3)
        self.normal = np.asarray(self.normal, dtype=np.float64).reshape(-1, 3)
        self.axis1 = np.asarray(self.axis1, dtype=np.float64).reshape(-1, 3)
        self.axis2 = np.asarray(self.axis2, dtype=np.float64).reshape(-1, 3)
        self.extent = np.asarray(self.extent, dtype=np.float64).reshape(-1, 2)
        self.direction = np.asarray(self.direction, dtype=np.int64).reshape(-1)
        self.keyframe = np.asarray(self.keyframe, dtype=np.int64).reshape(-1)
        n = {len(getattr(self, f)) for f in FIELDS}
        if len(n) != 1:
            raise ValueError(f"surfel fields have different lengths: {n}")

    def __len__(self) -> int:
        return len(self.center)

    def __getitem__(self, idx) -> "Surfels":
        return Surfels(**{f: getattr(self, f)[idx] for f in FIELDS})

    @staticmethod
    def concat(items: list["Surfels"]) -> "Surfels":
        items = [s for s in items if len(s)]
        if not items:
            return Surfels()
        return Surfels(**{f: np.concatenate([getattr(s, f) for s in items]) for f in FIELDS})

    def area(self) -> np.ndarray:
        return self.extent[:, 0] * self.extent[:, 1]

    def half_axes(self) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) twice: the rectangles' half sides along axis1 and axis2."""
        return self.axis1 * self.extent[:, :1] / 2, self.axis2 * self.extent[:, 1:] / 2

    def corners(self) -> np.ndarray:
        """(N, 4, 3) corners in order (-,-), (+,-), (+,+), (-,+)."""
        h1, h2 = self.half_axes()
        c = self.center
        return np.stack([c - h1 - h2, c + h1 - h2, c + h1 + h2, c - h1 + h2], axis=1)

    def sample_uniform(self, n_per: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``n_per`` points uniform on each rectangle: points (N*n_per, 3), surfel index (N*n_per,)."""
        n = len(self)
        uv = rng.uniform(-0.5, 0.5, size=(n, n_per, 2))
        pts = (
            self.center[:, None]
            + self.axis1[:, None] * (uv[..., :1] * self.extent[:, None, :1])
            + self.axis2[:, None] * (uv[..., 1:] * self.extent[:, None, 1:])
        )
        return pts.reshape(-1, 3), np.repeat(np.arange(n), n_per)

    def to_protocol_dict(self) -> dict[str, np.ndarray]:
        """Arrays with protocol.md's SurfelMap dtypes."""
        return {
            "center": self.center.astype(np.float32), "normal": self.normal.astype(np.float32),
            "axis1": self.axis1.astype(np.float32), "axis2": self.axis2.astype(np.float32),
            "extent": self.extent.astype(np.float32), "direction": self.direction.astype(np.int32),
            "keyframe": self.keyframe.astype(np.int64),
        }

    @classmethod
    def from_protocol_dict(cls, d: dict[str, np.ndarray]) -> "Surfels":
        return cls(**{f: d[f] for f in FIELDS})
