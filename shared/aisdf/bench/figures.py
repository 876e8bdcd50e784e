"""The benchmark's figures and meshes: metrics over sequence time, an SDF slice at
constant height per method (the paper's Fig. 4) and a mesh per method.

The slice plane is perpendicular to the scene's up direction (true for the synthetic
buildings, whose world frame is tilted; the mesh's z for Replica; gravity for 7-Scenes),
at a height between the floor and the ceiling of the observed surface points, so every
method is cut by the same plane.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..geometry import backproject, transform

SLICE_CLIP = (-0.5, 2.0)  # metres shown on the colour scale


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_over_time(path: Path, scene: str, over_time: list[dict], labels: dict[str, str], gt_label: str) -> None:
    """Three panels (SDF error, collision cost error, gradient distance) against stream time."""
    plt = _plt()
    from .report import METRICS, SHORT

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    methods = list(dict.fromkeys(m for cp in over_time for m in cp["methods"]))
    t = [cp["t"] for cp in over_time]
    for ax, k in zip(axes, METRICS, strict=True):
        for m in methods:
            ax.plot(t, [cp["methods"].get(m, {}).get(k, np.nan) for cp in over_time], marker="o", label=labels.get(m, m))
        ax.set_xlabel("sequence time (s)")
        ax.set_title(SHORT[k])
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{scene}: error over time (against {gt_label})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def slice_plane(up: np.ndarray, frames: list[dict], res: float, height: float = 0.35, margin: float = 0.3):
    """A grid of world points (h, w, 3) on the plane perpendicular to ``up`` at ``height``
    (fraction from the floor, 2nd percentile of the surface points along up, to the ceiling,
    98th), spanning the observed points' extent; also the plane's description."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    pts = []
    for f in frames:
        p = backproject(f["depth"][::4, ::4], np.diag([0.25, 0.25, 1.0]) @ f["K"]).reshape(-1, 3)
        pts.append(transform(f["T_WC"], p[np.isfinite(p[:, 0])]))
    P = np.concatenate(pts)
    h = P @ up
    lo, hi = np.percentile(h, [2, 98])
    z = lo + height * (hi - lo)
    horiz = P - np.outer(h, up)
    c = horiz.mean(axis=0)
    _, _, Vt = np.linalg.svd(horiz[:: max(1, len(horiz) // 20000)] - c, full_matrices=False)
    e1 = Vt[0] - (Vt[0] @ up) * up
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    a, b = (horiz - c) @ e1, (horiz - c) @ e2
    (a0, a1), (b0, b1) = np.percentile(a, [1, 99]) + [-margin, margin], np.percentile(b, [1, 99]) + [-margin, margin]
    A, B = np.meshgrid(np.arange(a0, a1, res), np.arange(b0, b1, res), indexing="xy")
    grid = c + z * up + A[..., None] * e1 + B[..., None] * e2
    info = {"up": up.round(4).tolist(), "height_m_along_up": round(float(z), 3),
            "floor_m": round(float(lo), 3), "ceiling_m": round(float(hi), 3), "height_fraction": height,
            "resolution_m": res, "extent_m": [round(float(a1 - a0), 2), round(float(b1 - b0), 2)]}
    return grid, (a0, a1, b0, b1), info


def plot_slices(path: Path, scene: str, fields: dict[str, np.ndarray], extent, info: dict, up_source: str) -> None:
    """One panel per field (h, w) metres: colour clipped to SLICE_CLIP, zero level in black."""
    plt = _plt()
    from matplotlib.colors import TwoSlopeNorm

    n = len(fields)
    cols = min(n, 3)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows), squeeze=False, layout="constrained")
    norm = TwoSlopeNorm(vmin=SLICE_CLIP[0], vcenter=0.0, vmax=SLICE_CLIP[1])
    im = None
    for ax, (name, F) in zip(axes.ravel(), fields.items()):
        im = ax.imshow(np.clip(F, *SLICE_CLIP), origin="lower", extent=extent, cmap="RdBu", norm=norm)
        if np.nanmin(F) < 0 < np.nanmax(F):
            ax.contour(F, levels=[0.0], colors="k", linewidths=0.8, origin="lower", extent=extent)
        ax.set_title(name, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    for ax in axes.ravel()[n:]:
        ax.axis("off")
    if im is not None:
        fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.8, label="SDF (m)")
    fig.suptitle(f"{scene}: SDF on the plane perpendicular to up ({up_source}), "
                 f"{info['height_m_along_up'] - info['floor_m']:.2f} m above the floor", fontsize=9)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def marching_cubes_mesh(sdf_fn, bounds: np.ndarray, res: float, chunk: int = 200_000):
    """Zero level set of ``sdf_fn(points (N, 3)) -> (N,)`` on a grid over ``bounds``: (V, F)."""
    from skimage.measure import marching_cubes

    lo, hi = np.asarray(bounds, dtype=np.float64)
    n = np.maximum(np.ceil((hi - lo) / res).astype(int) + 1, 2)
    axes = [lo[i] + res * np.arange(n[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    vol = np.concatenate([np.asarray(sdf_fn(grid[i:i + chunk]), np.float32) for i in range(0, len(grid), chunk)])
    vol = vol.reshape(tuple(n))
    if not (np.nanmin(vol) < 0 < np.nanmax(vol)):
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    V, F, _, _ = marching_cubes(np.nan_to_num(vol, nan=1.0), level=0.0, spacing=(res, res, res))
    return V + lo, F


def write_mesh(path: Path, V: np.ndarray, F: np.ndarray) -> None:
    import trimesh

    trimesh.Trimesh(np.asarray(V, np.float64), np.asarray(F, np.int64), process=False).export(path)


def surfel_mesh(surfels):
    """Two triangles per surfel rectangle: (V, F)."""
    c = surfels.corners().reshape(-1, 3)  # (S, 4, 3) -> (4S, 3)
    base = 4 * np.arange(len(surfels))[:, None]
    F = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    return c, F
