"""Continual SDF training: iSDF's loop with AiSDF's switches. Arrays in, arrays out.

    trainer = Trainer(training_config("cpu"))
    trainer.add_keyframe(Frame(frame_id, stamp, depth, K, T_WC))
    info = trainer.step()            # loss terms, point counts, timings_ms
    d = trainer.sdf(points_W)        # (N,) float32
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable

import numpy as np
import torch

from .. import network
from .bounds import batch_bounds, tighten_bounds
from .config import TrainingConfig
from .frames import Frame, KeyframeStore
from .losses import training_loss
from .sampling import SURFEL, sample_batch

CHECKPOINT_FORMAT = "aisdf-trainer-checkpoint"
CHECKPOINT_VERSION = 2  # 2: keyframes sent as <u2 are written raw (depth_raw, depth_scale; depth None); 1 still loads


def resolve_device(name: str) -> torch.device:
    """"auto" -> cuda when available, else cpu."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


class Trainer:
    """Keyframe store + SDF network + AdamW; ``step()`` is one iteration on a replay window."""

    def __init__(self, cfg: TrainingConfig | None = None):
        self.cfg = cfg = cfg or TrainingConfig()
        if cfg.torch_threads:
            torch.set_num_threads(cfg.torch_threads)
        self.device = resolve_device(cfg.device)
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(cfg.seed)
            self.net = network.SDFNetwork(cfg.network).to(self.device)
        self.optimizer = torch.optim.AdamW(self.net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        self.rng = np.random.default_rng(cfg.seed)
        self.store = KeyframeStore(cfg.window_size, cfg.max_keyframes, cfg.max_depth)
        self._steps = 0
        self._store_size = (0, 0)  # (keyframes, dropped) at the last step: a change is a new keyframe
        self._newest_step = 0  # step count when the newest keyframe was first trained on
        # With cfg.surfel_bounds: points (M, 3) float64 -> (distance (M,), unit direction from the
        # nearest surface point (M, 3)) to known surface (the global surfel map); set by the pipeline.
        self.bound_prior: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None

    # ------------------------------------------------------------------ state
    @property
    def steps(self) -> int:
        return self._steps

    @property
    def n_keyframes(self) -> int:
        return len(self.store)

    @property
    def dropped_keyframes(self) -> int:
        return self.store.dropped

    @property
    def keyframes(self) -> list[Frame]:
        return [k.frame for k in self.store.keyframes]

    def add_keyframe(self, frame: Frame) -> list[int]:
        """Store a keyframe (depth cleaned, normals computed); returns frame_ids dropped for memory."""
        return self.store.add(frame)

    def remove_keyframe(self, key: tuple[str, int]) -> bool:
        """Remove the keyframe (sensor, frame_id) from the store (the map's bound on
        keyframes); the rate does not take it for a new keyframe. True when it was there."""
        n = len(self.store)
        synced = self._store_size == (n, self.store.dropped)
        self.store.keyframes = [k for k in self.store.keyframes if k.frame.key != key]
        if len(self.store) == n:
            return False
        if synced:
            self._store_size = (len(self.store), self.store.dropped)
        return True

    # ------------------------------------------------------------------ training
    def learning_rate(self) -> float:
        """The rate of the next step: ``lr``, or with ``lr_settle`` a rate that halves its
        excess over ``lr_settle`` every ``lr_halflife_steps`` steps since the newest keyframe
        (or since the first step), once the network has had ``lr_settle_after`` steps per
        keyframe it holds: learn fast while new views arrive or while it is short of steps,
        then settle (a constant rate keeps the field jittering by about a centimetre)."""
        cfg = self.cfg
        size = (len(self.store), self.store.dropped)
        if size != self._store_size:
            self._store_size, self._newest_step = size, self._steps
        if cfg.lr_settle is None or self._steps < cfg.lr_settle_after * len(self.store):
            return cfg.lr  # the paper's constant rate; or a network still short of steps for its keyframes
        since = self._steps - (self._newest_step if cfg.lr_decay_from == "keyframe" else 0)
        return cfg.lr_settle + (cfg.lr - cfg.lr_settle) * 0.5 ** (since / cfg.lr_halflife_steps)

    def relearn(self) -> None:
        """The rate goes back up as for a new keyframe (``learning_rate``), and settles again:
        after the network was moved (a pose correction), so that it follows what is left."""
        self._store_size, self._newest_step = (len(self.store), self.store.dropped), self._steps

    def _sync(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)

    def step(self, extra_timings_ms: dict[str, float] | None = None) -> dict:
        """One iteration. Returns loss terms, counts, the window's frame_ids and ``timings_ms``
        (sampling, bound, forward [network, its gradient and the loss], backward [backprop and
        AdamW], total = their sum plus any ``extra_timings_ms`` merged in)."""
        if not len(self.store):
            raise RuntimeError("step() needs at least one keyframe")
        cfg, dev = self.cfg, self.device
        t0 = time.perf_counter()
        idx = self.store.window(self.rng, cfg.replay_uniform)
        batch = sample_batch([self.store.keyframes[i] for i in idx], cfg, self.rng)
        pts = torch.from_numpy(batch.points_W).to(dev)
        z, D = torch.from_numpy(batch.z).to(dev), torch.from_numpy(batch.ray_depth).to(dev)
        kind, target = torch.from_numpy(batch.kind).to(dev), torch.from_numpy(batch.target).to(dev)
        slot = torch.from_numpy(batch.slot).to(dev)
        self._sync()
        t1 = time.perf_counter()
        b, g = batch_bounds(pts, z, D, kind, target, cfg.bound_method, cfg.bound_chunk)
        trunc = None
        if cfg.surfel_bounds and self.bound_prior is not None:
            b, g, by_prior = tighten_bounds(b, g, batch, self.bound_prior)
            if cfg.surfel_trunc_distance > cfg.trunc_distance:
                trunc = torch.where(by_prior, cfg.surfel_trunc_distance, cfg.trunc_distance).to(b.dtype)
        self._sync()
        t2 = time.perf_counter()
        info: dict = {"step": self._steps + 1, "window": [self.store.keyframes[i].frame.frame_id for i in idx]}
        if len(batch):
            f, grad = network.sdf_and_grad(self.net, pts, create_graph=True)
            loss, terms, per_frame = training_loss(f, grad, b, g, kind, slot, len(idx), cfg, trunc)
            self._sync()
            t3 = time.perf_counter()
            self.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            lr = self.learning_rate()
            for group in self.optimizer.param_groups:
                group["lr"] = lr
            self.optimizer.step()
            self._sync()
            self.store.update_losses(idx, per_frame)
        else:  # every frame of the window without a valid pixel: nothing to learn from
            t3 = time.perf_counter()
            terms = {k: float("nan") for k in ("sdf", "eikonal", "grad", "surfel", "loss")}
        t4 = time.perf_counter()
        self._steps += 1
        timings = {"sampling": t1 - t0, "bound": t2 - t1, "forward": t3 - t2, "backward": t4 - t3}
        timings = {k: v * 1000.0 for k, v in timings.items()}
        timings.update(extra_timings_ms or {})
        timings["total"] = float(sum(timings.values()))
        n_surfel = int((batch.kind == SURFEL).sum())
        info.update(terms)
        info.update({"n_points": len(batch), "n_surfel_points": n_surfel, "timings_ms": timings})
        return info

    def train_keyframe(self, frame: Frame, n_steps: int | None = None) -> list[dict]:
        """Add a keyframe, then run iSDF's schedule (200 steps after the first, 60 after others)."""
        first = self.n_keyframes == 0 and self._steps == 0
        self.add_keyframe(frame)
        n = n_steps if n_steps is not None else (self.cfg.steps_first_frame if first else self.cfg.steps_per_keyframe)
        return [self.step() for _ in range(n)]

    # ------------------------------------------------------------------ queries
    def sdf(self, points: np.ndarray, chunk: int = 65536) -> np.ndarray:
        """SDF (N,) float32 at world points (N, 3)."""
        p = np.asarray(points, np.float32).reshape(-1, 3)
        out = []
        with torch.no_grad():
            for c in np.array_split(p, max(1, -(-len(p) // chunk))):
                out.append(self.net(torch.from_numpy(c).to(self.device)).cpu().numpy())
        return np.concatenate(out) if out else np.zeros(0, np.float32)

    def sdf_grad(self, points: np.ndarray, chunk: int = 65536) -> tuple[np.ndarray, np.ndarray]:
        """SDF (N,) and its autograd gradient (N, 3), float32."""
        p = np.asarray(points, np.float32).reshape(-1, 3)
        fs, gs = [np.zeros(0, np.float32)], [np.zeros((0, 3), np.float32)]
        for c in np.array_split(p, max(1, -(-len(p) // chunk))):
            f, g = network.sdf_and_grad(self.net, torch.from_numpy(c).to(self.device))
            fs.append(f.cpu().numpy())
            gs.append(g.cpu().numpy())
        return np.concatenate(fs), np.concatenate(gs)

    def model_spec(self) -> dict:
        return network.model_spec(self.net)

    def state_numpy(self) -> dict[str, np.ndarray]:
        return network.state_to_numpy(self.net)

    # ------------------------------------------------------------------ restart survival
    def checkpoint(self) -> dict:
        """Everything to resume: config, weights, AdamW state, keyframes, loss estimates, counters,
        the sampling generator. Plain types and numpy arrays only."""
        return {
            "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION,
            "config": self.cfg.model_dump(mode="json"), "model": self.model_spec(), "state": self.state_numpy(),
            "optimizer": self.optimizer_numpy(),
            "keyframes": [k.frame_dict() for k in self.store.keyframes],
            "losses": [k.loss for k in self.store.keyframes],
            "steps": self._steps, "dropped": self.store.dropped,
            "rng": json.dumps(self.rng.bit_generator.state), "lr_state": self.lr_state(),
        }

    def optimizer_numpy(self) -> dict:
        """The AdamW state as plain types and numpy arrays (for checkpoints)."""
        return _optimizer_to_numpy(self.optimizer.state_dict())

    def resume(self, optimizer: dict, steps: int, rng_state: dict, lr_state: list[int] | None) -> None:
        """Continue where a checkpoint stopped: AdamW state (``optimizer_numpy``'s), step
        count, the sampling generator's state and the learning-rate schedule's."""
        self.optimizer.load_state_dict(_optimizer_from_numpy(optimizer))
        self._steps = int(steps)
        self.rng.bit_generator.state = rng_state
        self.load_lr_state(lr_state)

    def lr_state(self) -> list[int]:
        return [*self._store_size, self._newest_step]

    def load_lr_state(self, v: list[int] | None) -> None:
        if v is not None:
            self._store_size, self._newest_step = (int(v[0]), int(v[1])), int(v[2])

    @classmethod
    def from_checkpoint(cls, d: dict, **config_overrides) -> "Trainer":
        """Resume from ``checkpoint()``; ``config_overrides`` (e.g. device) replace saved config fields."""
        if d.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"not a trainer checkpoint (format {d.get('format')!r})")
        if int(d.get("version", 0)) > CHECKPOINT_VERSION:
            raise ValueError(f"checkpoint version {d['version']} is newer than this build's {CHECKPOINT_VERSION}")
        t = cls(TrainingConfig.model_validate({**d["config"], **config_overrides}))
        network.load_numpy_state(t.net, d["state"])
        t.optimizer.load_state_dict(_optimizer_from_numpy(d["optimizer"]))
        for fd, loss in zip(d["keyframes"], d["losses"]):
            t.store.add(Frame.from_dict(fd))
            t.store.keyframes[-1].loss = None if loss is None else float(loss)
        t.store.dropped = int(d["dropped"])
        t._steps = int(d["steps"])
        t.rng.bit_generator.state = json.loads(d["rng"])
        t.load_lr_state(d.get("lr_state"))
        return t


def _optimizer_to_numpy(sd: dict) -> dict:
    state = {
        str(k): {n: (v.detach().cpu().numpy() if torch.is_tensor(v) else v) for n, v in s.items()}
        for k, s in sd["state"].items()
    }
    groups = [{n: (list(v) if isinstance(v, tuple) else v) for n, v in g.items()} for g in sd["param_groups"]]
    return {"state": state, "param_groups": groups}


def _optimizer_from_numpy(d: dict) -> dict:
    state = {
        int(k): {n: (torch.from_numpy(np.array(v)) if isinstance(v, np.ndarray) else v) for n, v in s.items()}
        for k, s in d["state"].items()
    }
    groups = [{n: (tuple(v) if n == "betas" else v) for n, v in g.items()} for g in d["param_groups"]]
    return {"state": state, "param_groups": groups}
