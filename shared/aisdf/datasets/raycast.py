"""Depth rendering and point-to-mesh distance for triangle meshes, with two backends.

* ``open3d`` (the ``bench`` extra): Open3D's ``RaycastingScene`` (Embree BVH, all cores).
  About 0.1 s for a 1200x680 frame of the 50k-face Replica office; 1M closest-point
  queries in about 2 s on 2 cores.
* ``numpy`` (always there): a vectorised z-buffer rasteriser with exact per-pixel
  ray-plane depth (same pixel-centre rays as open3d's, so both agree to float precision),
  and closest points by a KD-tree over surface samples refined with the exact
  point-triangle distance to the candidates' triangles.

``auto`` picks open3d when it imports, else numpy. trimesh's own ray casting needs
embree or rtree, which this project does not require.

Rays follow ``aisdf.geometry``: pixel (u, v) looks along ((u - cx)/fx, (v - cy)/fy, 1), so
the ray parameter at the hit is the z-depth.
"""

from __future__ import annotations

import numpy as np

from ..geometry import invert, kdtree, ray_dirs_C, transform


def open3d_available() -> bool:
    try:
        import open3d  # noqa: F401
    except Exception:  # ImportError, or a missing system library (libusb) raising OSError
        return False
    return True


# Feature codes of closest_point_on_triangles: where on triangle (a, b, c) the point lies.
VERT_A, VERT_B, EDGE_AB, VERT_C, EDGE_AC, EDGE_BC, FACE = range(7)


def closest_point_on_triangles(
    p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Closest points on triangles (a, b, c) to points p, all (N, 3) (Ericson, RTCD 5.1.5),
    and the feature each lies on (VERT_A ... FACE), (N,) int."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = p - b
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = p - c
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    vc = d1 * d4 - d3 * d2
    vb = d5 * d2 - d1 * d6
    va = d3 * d6 - d5 * d4
    with np.errstate(divide="ignore", invalid="ignore"):
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        den = va + vb + vc
        v, w = vb / den, vc / den
    conds = [  # in the order of the feature codes
        (d1 <= 0) & (d2 <= 0),
        (d3 >= 0) & (d4 <= d3),
        (vc <= 0) & (d1 >= 0) & (d3 <= 0),
        (d6 >= 0) & (d5 <= d6),
        (vb <= 0) & (d2 >= 0) & (d6 <= 0),
        (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),
    ]
    choices = [a, b, a + t_ab[:, None] * ab, c, a + t_ac[:, None] * ac, b + t_bc[:, None] * (c - b)]
    out = a + v[:, None] * ab + w[:, None] * ac
    feature = np.full(len(p), FACE)
    for code in reversed(range(6)):  # the first matching region wins
        out = np.where(conds[code][:, None], choices[code], out)
        feature = np.where(conds[code], code, feature)
    return out, feature


def pseudo_normals(vertices: np.ndarray, faces: np.ndarray, face_normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angle-weighted vertex pseudo-normals (V, 3) and, per face, the pseudo-normals of
    its edges ab, bc, ca (F, 3, 3) (Baerentzen and Aanaes 2005): the sign of
    (p - closest) . pseudo-normal is the inside/outside test, even at edges and corners."""
    tri = vertices[faces]
    vn = np.zeros_like(vertices)
    for k in range(3):
        e1 = tri[:, (k + 1) % 3] - tri[:, k]
        e2 = tri[:, (k + 2) % 3] - tri[:, k]
        cosang = _dot(e1, e2) / (np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1))
        np.add.at(vn, faces[:, k], np.arccos(np.clip(cosang, -1, 1))[:, None] * face_normals)
    edges = np.sort(np.stack([faces, np.roll(faces, -1, axis=1)], axis=-1), axis=-1).reshape(-1, 2)
    _, inv = np.unique(edges, axis=0, return_inverse=True)
    en = np.zeros((inv.max() + 1, 3))
    np.add.at(en, inv.ravel(), np.repeat(face_normals, 3, axis=0))
    return vn, en[inv.ravel()].reshape(-1, 3, 3)


def _dot(x, y):
    return np.einsum("ij,ij->i", x, y)


class MeshScene:
    """A triangle mesh ready for depth rendering and closest-point queries."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, backend: str = "auto", sample_spacing: float = 0.02):
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        tri = self.vertices[self.faces]
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area2 = np.linalg.norm(n, axis=1)
        ok = area2 > 0
        self.faces, tri, n, area2 = self.faces[ok], tri[ok], n[ok], area2[ok]
        self._tri = tri
        self.face_normals = n / area2[:, None]
        if backend == "auto":
            backend = "open3d" if open3d_available() else "numpy"
        if backend not in ("open3d", "numpy"):
            raise ValueError(f"unknown backend {backend!r}; use auto, open3d or numpy")
        self.backend = backend
        self.sample_spacing = sample_spacing
        self._o3d = None
        self._kd = None
        self._pseudo = None

    @classmethod
    def from_trimesh(cls, mesh, **kw) -> MeshScene:
        return cls(np.asarray(mesh.vertices), np.asarray(mesh.faces), **kw)

    @classmethod
    def from_file(cls, path, **kw) -> MeshScene:
        import trimesh

        return cls.from_trimesh(trimesh.load(path, force="mesh", process=False), **kw)

    # --- open3d --------------------------------------------------------------------------
    def _scene(self):
        if self._o3d is None:
            import open3d as o3d

            s = o3d.t.geometry.RaycastingScene()
            s.add_triangles(
                o3d.core.Tensor(self.vertices.astype(np.float32)), o3d.core.Tensor(self.faces.astype(np.uint32))
            )
            self._o3d = s
        return self._o3d

    # --- rendering -----------------------------------------------------------------------
    def render_depth(self, K: np.ndarray, T_WC: np.ndarray, H: int, W: int, near: float = 1e-3) -> np.ndarray:
        """Z-depth image (H, W) float32 in metres seen from camera ``T_WC``; 0 where no hit."""
        if self.backend == "open3d":
            import open3d as o3d

            dirs_W = ray_dirs_C(K, H, W) @ T_WC[:3, :3].T
            rays = np.concatenate([np.broadcast_to(T_WC[:3, 3], dirs_W.shape), dirs_W], axis=-1)
            t = self._scene().cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
            depth = np.where(np.isfinite(t) & (t > near), t, 0.0)
        else:
            depth = _rasterise(self._tri, K, T_WC, H, W, near)
        return depth.astype(np.float32)

    # --- distances -----------------------------------------------------------------------
    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(distance (N,), closest points (N, 3), face index (N,)) for (N, 3) points."""
        return self._closest_all(points)[:3]

    def _closest_all(self, points, chunk: int = 1_000_000):
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        dist = np.empty(len(points))
        cp = np.empty((len(points), 3))
        fid = np.empty(len(points), dtype=np.int64)
        feat = np.empty(len(points), dtype=np.int64)
        step = self._closest_open3d if self.backend == "open3d" else self._closest_numpy
        for s in range(0, len(points), chunk):
            sl = slice(s, s + chunk)
            dist[sl], cp[sl], fid[sl], feat[sl] = step(points[sl])
        return dist, cp, fid, feat

    def distance(self, points: np.ndarray, sign: str = "normal") -> np.ndarray:
        """Distance to the mesh. ``sign="normal"``: negative where the point lies behind the
        surface, i.e. opposite the angle-weighted pseudo-normal at its closest point (exact
        inside/outside for a closed, consistently oriented mesh; for an open scan whose
        normals face the sensor, negative behind the scanned surface). ``"unsigned"``:
        plain distance."""
        d, cp, fid, feat = self._closest_all(points)
        if sign == "unsigned":
            return d
        if sign != "normal":
            raise ValueError(f"unknown sign mode {sign!r}; use normal or unsigned")
        side = _dot(np.asarray(points, dtype=np.float64).reshape(-1, 3) - cp, self._normal_at(fid, feat))
        return np.where(side < 0, -d, d)

    def _normal_at(self, fid: np.ndarray, feature: np.ndarray) -> np.ndarray:
        """The pseudo-normal of the feature (vertex, edge, face) holding each closest point."""
        if self._pseudo is None:
            self._pseudo = pseudo_normals(self.vertices, self.faces, self.face_normals)
        vn, en = self._pseudo
        f = self.faces[fid]
        table = [vn[f[:, 0]], vn[f[:, 1]], en[fid, 0], vn[f[:, 2]], en[fid, 2], en[fid, 1], self.face_normals[fid]]
        return np.choose(feature[:, None], table)

    def _closest_open3d(self, p):
        import open3d as o3d

        r = self._scene().compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))
        fid = r["primitive_ids"].numpy().astype(np.int64)
        # Refine in float64 on the face open3d found (its float32 result is ~1e-7 m off).
        t = self._tri[fid]
        cp, feat = closest_point_on_triangles(p, t[:, 0], t[:, 1], t[:, 2])
        return np.linalg.norm(p - cp, axis=1), cp, fid, feat

    def _samples(self):
        if self._kd is None:
            tri = self._tri
            area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
            n = np.maximum(1, np.ceil(area / self.sample_spacing**2)).astype(np.int64)
            owner = np.repeat(np.arange(len(tri)), n)
            rng = np.random.default_rng(0)
            r1, r2 = rng.random(len(owner)), rng.random(len(owner))
            s = np.sqrt(r1)
            w = np.stack([1 - s, s * (1 - r2), s * r2], axis=1)
            first = np.concatenate([[0], np.cumsum(n)[:-1]])
            w[first] = 1.0 / 3.0  # every triangle keeps its centroid
            pts = np.einsum("nk,nkd->nd", w, tri[owner])
            self._kd = (kdtree(pts), owner)
        return self._kd

    def _closest_numpy(self, p, k: int = 8):
        tree, owner = self._samples()
        k = min(k, tree.n)
        _, idx = tree.query(p, k=k, workers=-1)
        idx = np.asarray(idx).reshape(len(p), k)
        best_d = np.full(len(p), np.inf)
        best_cp = np.zeros((len(p), 3))
        best_f = np.zeros(len(p), dtype=np.int64)
        best_feat = np.zeros(len(p), dtype=np.int64)
        for j in range(k):
            f = owner[idx[:, j]]
            t = self._tri[f]
            cp, feat = closest_point_on_triangles(p, t[:, 0], t[:, 1], t[:, 2])
            d = np.linalg.norm(p - cp, axis=1)
            better = d < best_d
            best_d[better], best_cp[better], best_f[better], best_feat[better] = (
                d[better],
                cp[better],
                f[better],
                feat[better],
            )
        return best_d, best_cp, best_f, best_feat


def _rasterise(tri_W: np.ndarray, K, T_WC, H: int, W: int, near: float, chunk: int = 2_000_000) -> np.ndarray:
    """Z-buffer: for each triangle, the pixels in the bounding box of its (near-clipped)
    projection; a pixel's ray hits the triangle when the three edge triple products share a
    sign; its depth is the exact ray-plane z."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    tri = transform(invert(T_WC), tri_W)  # (F, 3, 3) in the camera frame
    z = tri[..., 2]
    tri = tri[(z > near).any(axis=1)]
    depth = np.full(H * W, np.inf)
    if not len(tri):
        return np.zeros((H, W))
    # Candidate polygon points: vertices in front of the near plane and edge crossings.
    a, b = tri, np.roll(tri, -1, axis=1)
    za, zb = a[..., 2] - near, b[..., 2] - near
    with np.errstate(divide="ignore", invalid="ignore"):
        t = za / (za - zb)
    cross = a + t[..., None] * (b - a)
    pts = np.concatenate([tri, cross], axis=1)
    ok = np.concatenate([tri[..., 2] >= near, (za * zb) < 0], axis=1)
    zz = np.where(ok, pts[..., 2], 1.0)
    u = np.where(ok, fx * pts[..., 0] / zz + cx, np.nan)
    v = np.where(ok, fy * pts[..., 1] / zz + cy, np.nan)
    u0 = np.clip(np.ceil(np.nanmin(u, axis=1)), 0, W)
    u1 = np.clip(np.floor(np.nanmax(u, axis=1)), -1, W - 1)
    v0 = np.clip(np.ceil(np.nanmin(v, axis=1)), 0, H)
    v1 = np.clip(np.floor(np.nanmax(v, axis=1)), -1, H - 1)
    bw = (u1 - u0 + 1).astype(np.int64)
    bh = (v1 - v0 + 1).astype(np.int64)
    vis = (bw > 0) & (bh > 0)
    tri, u0, v0, bw, bh = tri[vis], u0[vis].astype(np.int64), v0[vis].astype(np.int64), bw[vis], bh[vis]
    A, B, C = tri[:, 0], tri[:, 1], tri[:, 2]
    eab, ebc, eca = np.cross(A, B), np.cross(B, C), np.cross(C, A)
    n = np.cross(B - A, C - A)
    na = _dot(n, A)
    counts = bw * bh
    ends = np.cumsum(counts)
    start = 0
    while start < len(tri):
        stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + chunk, side="right"))
        stop = max(stop, start + 1)
        sl = slice(start, stop)
        cnt = counts[sl]
        owner = np.repeat(np.arange(start, stop), cnt)
        local = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        pu = u0[owner] + local % bw[owner]
        pv = v0[owner] + local // bw[owner]
        d = np.stack([(pu - cx) / fx, (pv - cy) / fy, np.ones(len(pu))], axis=1)
        s1, s2, s3 = _dot(d, eab[owner]), _dot(d, ebc[owner]), _dot(d, eca[owner])
        inside = ((s1 >= 0) & (s2 >= 0) & (s3 >= 0)) | ((s1 <= 0) & (s2 <= 0) & (s3 <= 0))
        nd = _dot(d, n[owner])
        with np.errstate(divide="ignore", invalid="ignore"):
            zhit = na[owner] / nd
        hit = inside & (nd != 0) & (zhit > near)
        np.minimum.at(depth, pv[hit] * W + pu[hit], zhit[hit])
        start = stop
    depth[~np.isfinite(depth)] = 0.0
    return depth.reshape(H, W)
