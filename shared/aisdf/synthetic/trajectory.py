"""A smooth camera path through a scene's free space. Pure numpy (+ scipy's Dijkstra).

Planned in the canonical frame: a 2D occupancy grid at camera height marks cells whose
3D clearance (``scene.sdf`` over the height range) exceeds ``clearance + margin``;
waypoints spread over the free space are joined into a closed tour by grid shortest
paths (penalised near obstacles), smoothed on the loop, and walked at ``speed`` m/s.
The camera yaws with the path direction, turned ``inward_deg`` towards the loop's inside
(where the furniture is), plus a slow +-``sweep_deg`` sweep, rate-limited to
``max_yaw_rate``, pitches down by ``pitch_deg`` (+- a slow wobble), and its y axis (down)
stays in the vertical plane through the view direction, i.e. roughly along -up.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from .primitives import polygon_area
from .scene import Scene

_UP = np.array([0.0, 0.0, 1.0])


def _free_grid(scene: Scene, heights: np.ndarray, cell: float):
    poly = scene.room.polygon
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    xs, ys = np.arange(lo[0] + cell / 2, hi[0], cell), np.arange(lo[1] + cell / 2, hi[1], cell)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    xy = np.c_[gx.ravel(), gy.ravel()]
    clear = np.full(len(xy), np.inf)
    for z in heights:
        clear = np.minimum(clear, scene.sdf(scene.to_world(np.c_[xy, np.full(len(xy), z)])))
    return xy, clear.reshape(gx.shape)


def _grid_graph(ok: np.ndarray, clear: np.ndarray, cell: float):
    nx, ny = ok.shape
    ids = np.arange(nx * ny).reshape(nx, ny)
    rows, cols, w = [], [], []
    for dx, dy in ((1, 0), (0, 1), (1, 1), (1, -1)):
        a = ids[max(0, -dx) : nx - max(0, dx), max(0, -dy) : ny - max(0, dy)]
        b = ids[max(0, dx) : nx - max(0, -dx) or None, max(0, dy) : ny - max(0, -dy) or None]
        m = ok.ravel()[a] & ok.ravel()[b]
        length = cell * np.hypot(dx, dy)
        # Prefer the middle of free space: cost grows as clearance shrinks.
        pen = 1.0 + 0.5 / np.minimum(clear.ravel()[a[m]], clear.ravel()[b[m]])
        rows.append(a[m]), cols.append(b[m]), w.append(length * pen)
    n = nx * ny
    g = coo_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    return g.tocsr()


def _loop_path(scene: Scene, rng: np.random.Generator, heights: np.ndarray, clearance: float,
               n_waypoints: int, cell: float = 0.05, margin: float = 0.15) -> np.ndarray:
    """Closed polyline (P, 2) through free space, canonical frame."""
    xy, clear = _free_grid(scene, heights, cell)
    ok = clear > clearance + margin
    if ok.sum() < 10:
        raise ValueError(f"no free space with clearance {clearance + margin} m at camera height")
    graph = _grid_graph(ok, clear, cell)
    flat = clear.ravel()
    # Waypoints: farthest-point sampling over well-clear cells, from a random start.
    pool = np.flatnonzero(flat > min(clearance + 2 * margin + 0.2, np.quantile(flat[ok.ravel()], 0.7)))
    pool = pool if len(pool) >= n_waypoints else np.flatnonzero(ok.ravel())
    wp = [int(rng.choice(pool))]
    dmin = np.full(len(pool), np.inf)
    for _ in range(n_waypoints - 1):
        dmin = np.minimum(dmin, np.linalg.norm(xy[pool] - xy[wp[-1]], axis=1))
        wp.append(int(pool[np.argmax(dmin)]))
    # Tour order: by angle around the free space's centroid.
    cen = xy[ok.ravel()].mean(axis=0)
    wp = np.array(wp)[np.argsort(np.arctan2(*(xy[wp] - cen)[:, ::-1].T))]
    dist, pred = dijkstra(graph, directed=False, indices=wp, return_predecessors=True)
    path = []
    for i in range(len(wp)):
        a, b = wp[i], wp[(i + 1) % len(wp)]
        if not np.isfinite(dist[i, b]):
            raise ValueError("free space at camera height is not connected")
        seg = [b]
        while seg[-1] != a:
            seg.append(pred[i, seg[-1]])
        path.extend(seg[::-1][:-1])
    return xy[np.array(path)]


def _resample_closed(path: np.ndarray, ds: float) -> np.ndarray:
    """Closed polyline resampled at equal arc-length steps of about ``ds`` (exactly
    length / n), so that sample k sits at arc length k * length / n."""
    closed = np.vstack([path, path[:1]])
    s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))]
    q = np.linspace(0.0, s[-1], max(int(round(s[-1] / ds)), 8), endpoint=False)
    return np.c_[np.interp(q, s, closed[:, 0]), np.interp(q, s, closed[:, 1])]


def _loop_length(loop: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.roll(loop, -1, axis=0) - loop, axis=1)))


def _rate_limit(x: np.ndarray, max_step: float) -> np.ndarray:
    y = np.empty_like(x)
    y[0] = x[0]
    for i in range(1, len(x)):
        y[i] = y[i - 1] + np.clip(x[i] - y[i - 1], -max_step, max_step)
    return y


def look_rotation(yaw: np.ndarray, pitch: np.ndarray) -> np.ndarray:
    """(n, 3, 3) camera-to-canonical rotations: z forward at ``yaw`` (from +x, about +z) and
    ``pitch`` (positive = down), x = right, y = down in the vertical plane."""
    z = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), -np.sin(pitch)], axis=-1)
    x = np.cross(z, _UP)
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=-1)


def make_trajectory(
    scene: Scene, n_frames: int, seed: int = 0, *, fps: float = 30.0, speed: float = 0.4,
    height: tuple[float, float] = (1.2, 1.5), clearance: float = 0.4, pitch_deg: float = 20.0,
    sweep_deg: float = 35.0, inward_deg: float = 35.0, max_yaw_rate: float = 25.0, n_waypoints: int = 6,
) -> np.ndarray:
    """(n_frames, 4, 4) T_WC: a smooth loop at ``height`` m above the floor, frames
    1/``fps`` s apart, at ``speed`` m/s, keeping ``scene.sdf >= clearance`` at the camera
    centre, yaw rate <= ``max_yaw_rate`` deg/s (pitch wobble adds < 5 deg/s)."""
    rng = np.random.default_rng([seed, 3])
    zs = np.linspace(height[0], height[1], 4)
    base = _resample_closed(_loop_path(scene, rng, zs, clearance, n_waypoints), 0.02)
    t = np.arange(n_frames) / fps
    z = np.mean(height) + (height[1] - height[0]) / 2 * 0.8 * np.sin(2 * np.pi * t / 12.0 + rng.uniform(0, 6.3))
    u0 = rng.uniform(0, 1)  # start, as a fraction of the loop
    for sigma in (0.5, 0.25, 0.12, 0.06, 0.0):  # smoothing (m); less if it cuts a corner
        sm = gaussian_filter1d(base, sigma / 0.02, axis=0, mode="wrap") if sigma > 0 else base
        sm = _resample_closed(sm, 0.02)
        ds = _loop_length(sm) / len(sm)
        u = (u0 * len(sm) + speed * t / ds) % len(sm)  # position in samples along the loop
        i0, f = np.floor(u).astype(int) % len(sm), (u - np.floor(u))[:, None]
        p = np.c_[(1 - f) * sm[i0] + f * sm[(i0 + 1) % len(sm)], z]
        if np.all(scene.sdf(scene.to_world(p)) >= clearance):
            break
    else:
        raise RuntimeError("could not keep the clearance")
    # Heading along the loop, turned towards its inside, plus a slow sweep; rate-limited.
    tang = np.roll(sm, -5, axis=0) - np.roll(sm, 5, axis=0)
    head = np.unwrap(np.arctan2(tang[:, 1], tang[:, 0]))
    last = head[-1] + np.angle(np.exp(1j * (head[0] - head[-1])))
    head_t = np.unwrap(np.interp(u, np.arange(len(sm) + 1), np.r_[head, last]))
    inward = np.radians(inward_deg) * np.sign(polygon_area(sm))  # CCW loop: inside is left
    yaw = head_t + inward + np.radians(sweep_deg) * np.sin(2 * np.pi * t / 14.0 + rng.uniform(0, 6.3))
    yaw = _rate_limit(yaw, np.radians(max_yaw_rate) / fps * 0.9)
    yaw = gaussian_filter1d(yaw, 0.3 * fps, mode="nearest")
    pitch = np.radians(pitch_deg + 4.0 * np.sin(2 * np.pi * t / 9.0 + rng.uniform(0, 6.3)))
    T = np.tile(np.eye(4), (n_frames, 1, 1))
    T[:, :3, :3] = look_rotation(yaw, pitch)
    T[:, :3, 3] = p
    return scene.T_W_canon[None] @ T


# ------------------------------------------------------------------ a walk through a floor plan


def _walk_plan(plan, speed: float, spin_deg: float, spin_rate: float):
    """Key times (K,), canonical positions (K, 2) and the heading wanted after each key
    (None while moving: the direction of motion), plus the spin intervals per room."""
    pts: list[np.ndarray] = [np.asarray(plan.start, dtype=float)]
    spins: list[tuple[int, str]] = []  # (index of the look point in pts, room)
    for i, v in enumerate(plan.visits):
        pts += [np.asarray(p, dtype=float) for p in plan.route.get(i, ())]
        pts += [v.corridor, v.door, v.look]
        spins.append((len(pts) - 1, v.room))
        pts += [v.door, v.corridor]
    pts += [np.asarray(p, dtype=float) for p in plan.route.get(-1, ())] + [np.asarray(plan.end, dtype=float)]
    spin_at = dict(spins)
    times, where, spin_windows = [0.0], [pts[0]], {}
    for k in range(1, len(pts)):
        seg = float(np.linalg.norm(pts[k] - pts[k - 1]))
        if seg < 1e-9:
            continue
        times.append(times[-1] + seg / speed)
        where.append(pts[k])
        if k in spin_at:
            t0 = times[-1]
            times.append(t0 + spin_deg / spin_rate)
            where.append(pts[k])
            spin_windows[spin_at[k]] = (t0, times[-1])
    return np.array(times), np.array(where), spin_windows


def walk_duration(plan, speed: float = 0.6, spin_deg: float = 540.0, spin_rate: float = 45.0) -> float:
    """Seconds ``make_walk`` takes through ``plan`` with these settings."""
    return float(_walk_plan(plan, speed, spin_deg, spin_rate)[0][-1])


def make_walk(
    scene: Scene, plan, n_frames: int, seed: int = 0, *, fps: float = 30.0, speed: float = 0.6,
    spin_deg: float = 540.0, spin_rate: float = 45.0, height: float = 1.35, pitch_deg: float = 15.0,
    sweep_deg: float = 25.0, max_yaw_rate: float = 45.0, clearance: float = 0.25,
) -> tuple[np.ndarray, dict[str, tuple[float, float]], float]:
    """A walk through ``plan`` (a ``buildings.FloorPlan``): along the corridor, into each
    room through its door to its look point, a turn of ``spin_deg`` degrees there at
    ``spin_rate`` deg/s (ending towards the door), and back out, at ``speed`` m/s.

    Returns (poses (n_frames, 4, 4) T_WC for t = i / ``fps`` s, the visits {room: (t_in,
    t_out)}: the stream times between which the camera is inside that room's region, and
    the walk's duration in s). Frames after the walk's end hold its last pose. The camera
    faces where it walks, with a slow +-``sweep_deg`` sweep, yaw rate at most
    ``max_yaw_rate`` deg/s, pitched ``pitch_deg`` down (+- 4 degrees), at ``height`` m
    (+- 0.1 m); its centre keeps ``scene.sdf >= clearance`` (checked: RuntimeError if not).
    """
    rng = np.random.default_rng([seed, 5])
    key_t, key_xy, spin_windows = _walk_plan(plan, speed, spin_deg, spin_rate)
    duration = float(key_t[-1])
    dt = 1.0 / fps
    t = np.arange(n_frames) * dt
    # Fine time grid for the yaw filter.
    fine_dt = min(dt, 0.05)
    tf = np.arange(0.0, duration + fine_dt, fine_dt)
    xy = np.c_[np.interp(tf, key_t, key_xy[:, 0]), np.interp(tf, key_t, key_xy[:, 1])]
    vel = np.gradient(xy, fine_dt, axis=0)
    moving = np.linalg.norm(vel, axis=1) > 1e-3
    head = np.arctan2(vel[:, 1], vel[:, 0])
    spin_sign = {}
    want = np.empty(len(tf))
    prev = float(head[np.argmax(moving)]) if moving.any() else 0.0
    for i in range(len(tf)):
        room = next((r for r, (a, b) in spin_windows.items() if a <= tf[i] <= b), None)
        if room is not None:
            a, b = spin_windows[room]
            s = spin_sign.setdefault(room, 1.0 if len(spin_sign) % 2 == 0 else -1.0)
            if i == 0 or not (a <= tf[i - 1] <= b):
                base = prev
                spin_sign[room + "_base"] = base
            want[i] = spin_sign[room + "_base"] + s * np.radians(spin_deg) * (tf[i] - a) / (b - a)
        elif moving[i]:
            want[i] = prev + np.angle(np.exp(1j * (head[i] - prev)))  # nearest equivalent heading
        else:
            want[i] = prev
        prev = want[i]
    phase = rng.uniform(0, 2 * np.pi, 3)
    in_spin = np.zeros(len(tf), bool)
    for a, b in spin_windows.values():
        in_spin |= (tf >= a) & (tf <= b)
    sweep = np.radians(sweep_deg) * np.sin(2 * np.pi * tf / 8.0 + phase[0]) * ~in_spin
    yaw = _rate_limit(want + gaussian_filter1d(sweep, 0.5 / fine_dt), np.radians(max_yaw_rate) * fine_dt * 0.9)
    yaw = gaussian_filter1d(yaw, 0.25 / fine_dt, mode="nearest")
    # Sample the fine grid at the frame times.
    t = np.minimum(t, duration)  # held after the end
    yaw_t = np.interp(t, tf, yaw)
    pos = np.c_[np.interp(t, key_t, key_xy[:, 0]), np.interp(t, key_t, key_xy[:, 1])]
    z = height + 0.1 * np.sin(2 * np.pi * t / 11.0 + phase[1])
    pitch = np.radians(pitch_deg + 4.0 * np.sin(2 * np.pi * t / 9.0 + phase[2]))
    T = np.tile(np.eye(4), (n_frames, 1, 1))
    T[:, :3, :3] = look_rotation(yaw_t, pitch)
    T[:, :3, 3] = np.c_[pos, z]
    T_W = scene.T_W_canon[None] @ T
    if n_frames and np.min(scene.sdf(T_W[:, :3, 3])) < clearance:
        raise RuntimeError(f"the walk comes within {np.min(scene.sdf(T_W[:, :3, 3])):.3f} m of a surface")
    # Visits: when the camera centre is inside each room's region (fine grid, whole walk).
    tv = np.arange(0.0, duration + fine_dt, fine_dt)
    pv = np.c_[np.interp(tv, key_t, key_xy[:, 0]), np.interp(tv, key_t, key_xy[:, 1])]
    reg = plan.region_of(pv)
    visits = {}
    for v in plan.visits:
        inside = np.flatnonzero(reg == plan.names.index(v.room))
        if len(inside):
            visits[v.room] = (float(tv[inside[0]]), float(tv[inside[-1]]))
    return T_W, visits, duration
