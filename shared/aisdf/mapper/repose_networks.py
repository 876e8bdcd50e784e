"""A submap's network after its keyframes moved (step 4 of :mod:`aisdf.mapper.repose`): the
rigid motion of the points it learnt from, the network moved with it, or started again and
taught the old field warped by the correction (distillation)."""

from __future__ import annotations


import numpy as np
import torch

MOVE_MIN_POINTS = 50  # a submap whose box holds fewer of its keyframes' points is not moved but reset
DISTIL_BATCH = 1024  # points a distillation step (distill_network)
DISTIL_LR = 1e-3


def fit_rigid(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """The rigid 4x4 ``T`` nearest to carrying the points ``P`` (N, 3) onto ``Q`` (least
    squares, Kabsch)."""
    p0, q0 = P.mean(0), Q.mean(0)
    U, _, Vt = np.linalg.svd((P - p0).T @ (Q - q0))
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, q0 - R @ p0
    return T


def submap_pairs(pipe, c, held: list, before: dict, after: dict) -> list[tuple[np.ndarray, np.ndarray]]:
    """What the submap ``c``'s network learnt, and where a correction put it: for each keyframe
    it held (``held``), its observed points (``SubmapPipeline._ray_points``) at the old pose and
    at the new one (the same for a keyframe not moved), those inside its extended box at both."""
    pairs = []
    for k in held:
        if k in before and k in after:
            p, q = before[k], after[k]
        elif k in pipe.frames:
            p = q = pipe._ray_points(pipe.frames[k])[0]
        else:
            continue
        inside = pipe.grid.inside(c, p) & pipe.grid.inside(c, q)  # learnt there, and still in its box
        if inside.any():
            pairs.append((p[inside], q[inside]))
    return pairs


def submap_motion(pairs: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray | None, float]:
    """How a correction moved what a submap's network learnt (``submap_pairs``): the rigid motion
    (``fit_rigid``) of all the points, and what it leaves: the largest over the keyframes of
    the 95th percentile of their points' distance from where the motion puts them (so that one
    keyframe moved far among many still is not hidden). (None, inf) with fewer than
    ``MOVE_MIN_POINTS`` points."""
    if sum(len(p) for p, _ in pairs) < MOVE_MIN_POINTS:
        return None, float("inf")
    T = fit_rigid(np.concatenate([p for p, _ in pairs]), np.concatenate([q for _, q in pairs]))
    left = max(float(np.percentile(np.linalg.norm(p @ T[:3, :3].T + T[:3, 3] - q, axis=1), 95)) for p, q in pairs)
    return T, left


def distill_network(pipe, c, net, old_net, pairs, steps: int, seed: int = 0) -> float:
    """Teaches the fresh ``net`` of submap ``c`` what ``old_net`` learnt, at the places a
    correction moved it to: a point ``x`` of the box is given ``old_net(x - d(x))``, ``d`` the
    displacement of the moved observed points nearest to ``x`` (``pairs``, inverse-distance
    weighted over 8), so a map that no one rigid motion corrects (drift that grew along the
    walk) is warped point by point. ``steps`` steps of Adam on an L1 loss, 1,024 points each,
    drawn about the observed surfaces (5 cm) and along the observed rays (15 cm). Returns the
    last steps' mean loss (m). Training then goes on from the corrected keyframes."""
    from scipy.spatial import cKDTree

    P = np.concatenate([p for p, _ in pairs])
    Q = np.concatenate([q for _, q in pairs])
    rng = np.random.default_rng(seed)
    n = steps * DISTIL_BATCH
    surf = Q[3::4] if len(Q) >= 4 else Q  # _ray_points: 4 per ray, the last on the surface
    x = np.concatenate([surf[rng.integers(len(surf), size=n // 2)] + rng.normal(0, 0.05, (n // 2, 3)),
                        Q[rng.integers(len(Q), size=n - n // 2)] + rng.normal(0, 0.15, (n - n // 2, 3))])
    x = x[pipe.grid.inside(c, x)]
    if len(x) < DISTIL_BATCH:
        return float("nan")
    rng.shuffle(x)
    dist, nn = cKDTree(Q).query(x, k=min(8, len(Q)))
    dist, nn = np.atleast_2d(dist.T).T, np.atleast_2d(nn.T).T
    w = 1.0 / np.maximum(dist, 1e-3)
    d = np.einsum("nk,nkj->nj", w / w.sum(1, keepdims=True), (Q - P)[nn])
    dev = next(net.parameters()).device
    with torch.no_grad():
        y = torch.cat([old_net(torch.as_tensor(x[i:i + 65536] - d[i:i + 65536], dtype=torch.float32, device=dev))
                       for i in range(0, len(x), 65536)])
    xt = torch.as_tensor(x, dtype=torch.float32, device=dev)
    opt = torch.optim.Adam(net.parameters(), lr=DISTIL_LR)
    losses = []
    for i in range(0, len(x) - DISTIL_BATCH + 1, DISTIL_BATCH):
        loss = (net(xt[i:i + DISTIL_BATCH]) - y[i:i + DISTIL_BATCH]).abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    return float(np.mean(losses[-10:]))


def reset_network(pipe, sm) -> None:
    """A fresh network for the submap (its configuration: seed and encoding centre), new
    AdamW state and step count, the same keyframe store."""
    from ..mapping.trainer import Trainer

    old = sm.trainer
    tr = Trainer(old.cfg)
    pipe._attach_prior(sm.cell, tr)
    tr.store = old.store
    sm.trainer = tr
