"""The methods compared, and the replay that feeds them the same stream.

A *model* is one map built from the stream (a voxel map, or one trained network); a
*method* is a column of Table I: a model read one way. AiSDF "w/o" and "w." explicit
map are the same trained network, read alone or fused with its surfels
(``aisdf.structure.fusion.fuse``, the paper's Sec. IV-D); "served" is that network again,
read as the query service answers planners by default (``source: "fused"``, protocols 1.4
and 1.5): ``aisdf.query.answer.served_answer`` of the network, the signed distance to the
global surfels and the mapper's measured points (``measured_points()``), with the query
service's fuse radius and one search worker, as ``QueryEngine._network_answer`` composes
it. That is the exact composition (``exact: true`` in a request); by default the service
answers from its bake of that same field (``aisdf.baked``: trilinear within ``bake_tol``,
5 mm, where a block is refined): "baked" is that reply, from a ``QueryEngine`` holding the
map's messages (``map_messages``) that has baked it with its default settings (one full
bake per evaluation). The AiSDF model pools
measured points as the mapper does by default (``measured``: True), the other networks do
not (the paper's models; pooling changes no training, only the keyframe time and which
stored keyframes free-space clearing checks).

The voxel maps (``aisdf.bench.voxel.VoxelEsdf``, what Voxblox does): the paper's 5.5 cm,
and 5 cm and 2 cm, the sizes a team would run (``aisdf bench query`` compares the same two).

Two modes (``run_stream``):

* ``iterations`` (the paper's): every model sees every frame. The voxel map integrates
  every frame, as Voxblox does; a network gets the frames the service's keyframe
  selector (``aisdf.keyframes``) picks, each followed by iSDF's schedule
  (200 steps after the first keyframe, 60 after each later one, times the profile's
  ``schedule_scale``).
* ``realtime`` (iSDF's replay): each model has its own compute clock; the frame it gets
  next is the newest one whose time stamp the clock has passed, so frames that arrive
  while it computes are skipped. Networks train continuously between frames; the voxel
  map integrates the frames it gets. Keyframe selection runs on the frames a model sees.
  The clock is ``ComputeClock`` (wall time of the model's own work, times ``slowdown``;
  tests pass a fake timer).
"""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..structure.fusion import DEFAULT_FUSE_RADIUS, fused_sdf
from ..structure.measured import MeasuredPoints
from ..mapping.frames import Frame
from .runner import ComputeClock, Runner, VoxelRunner  # noqa: F401 - re-exported


@dataclass(frozen=True)
class ModelSpec:
    kind: str  # "voxel" | "neural"
    atlanta: bool = False
    surfel_mask: bool = False
    surfel_loss: bool = False
    surfel_bounds: bool = False  # beyond the paper (the mapper's default); the paper's tables go without
    measured: bool = False  # pool measured points (protocol 1.5, the mapper's default): the served answer uses them
    voxel_size: float = 0.055  # voxel maps: edge (m)


MODELS: dict[str, ModelSpec] = {
    "voxblox": ModelSpec("voxel"),  # the paper's 5.5 cm
    "voxel-5cm": ModelSpec("voxel", voxel_size=0.05),
    "voxel-2cm": ModelSpec("voxel", voxel_size=0.02),
    "isdf": ModelSpec("neural"),
    "aisdf": ModelSpec("neural", True, True, True, measured=True),
    "aisdf-mask": ModelSpec("neural", True, True, False),  # Table II: surfel mask only
    "aisdf-loss": ModelSpec("neural", True, False, True),  # Table II: surfel loss only
}

# Table I columns: method -> (model, view).
METHODS: dict[str, tuple[str, str]] = {
    "voxblox": ("voxblox", "voxel"),
    "voxel-5cm": ("voxel-5cm", "voxel"),
    "voxel-2cm": ("voxel-2cm", "voxel"),
    "isdf": ("isdf", "implicit"),
    "aisdf": ("aisdf", "implicit"),
    "aisdf+explicit": ("aisdf", "fused"),
    "aisdf-served": ("aisdf", "served"),
    "aisdf-served-noprior": ("aisdf", "served-noprior"),
    "aisdf-baked": ("aisdf", "baked"),
}
LABELS: dict[str, str] = {
    "voxblox": "Voxblox-like TSDF/ESDF 5.5 cm", "voxel-5cm": "Voxel TSDF/ESDF 5 cm",
    "voxel-2cm": "Voxel TSDF/ESDF 2 cm", "isdf": "iSDF", "aisdf": "AiSDF (w/o explicit map)",
    "aisdf+explicit": "AiSDF (w. explicit map)", "aisdf-served": "AiSDF served (default answer)",
    "aisdf-served-noprior": "AiSDF served, no layout prior",
    "aisdf-baked": "AiSDF served, baked",
}
# Table II rows: (surfel mask, surfel loss) -> model; both off is iSDF, both on AiSDF.
ABLATION: list[tuple[tuple[bool, bool], str]] = [
    ((False, False), "isdf"), ((True, False), "aisdf-mask"), ((False, True), "aisdf-loss"), ((True, True), "aisdf"),
]


def atlanta_available() -> str | None:
    """None when the Atlanta module imports, else why not."""
    try:
        from .. import structure  # noqa: F401
    except Exception as e:  # noqa: BLE001 - any import failure makes the AiSDF models unavailable
        return f"{type(e).__name__}: {e}"
    return None


class NeuralRunner(Runner):
    """``aisdf.mapper.single.MappingPipeline`` with the service's keyframe selector in front."""

    TRAINER_KEYS = ("sampling", "bound", "forward", "backward", "total")

    def __init__(self, name, clock, spec: ModelSpec, preset: str, training: dict, keyframes: dict | None = None):
        from ..keyframes import KeyframeConfig, KeyframeSelector

        from ..mapper.single import MappingPipeline

        super().__init__(name, clock)
        self.spec = spec
        # measured: only AiSDF's model pools measured points (protocol 1.5, beyond the paper), for
        # the served answer; the paper's columns read the network and its surfels alone.
        self.pipe = MappingPipeline.from_settings(preset, training=training, atlanta=spec.atlanta,
                                                  surfel_mask=spec.surfel_mask, surfel_loss=spec.surfel_loss,
                                                  surfel_bounds=spec.surfel_bounds, measured=spec.measured)
        self.selector = KeyframeSelector(KeyframeConfig(**(keyframes or {})))
        self._ms: dict[str, list[float]] = defaultdict(list)  # the pipeline's own per-module timings
        self._wall: dict[str, list[float]] = defaultdict(list)  # measured here: whole step / keyframe add
        self.keyframe_ids: list[int] = []
        self.layout_prior = True  # the served answer caps at the predicted layout, as the query service does

    def see(self, frame, train):
        added = False
        with self.clock.measure():
            if self.selector.is_keyframe(frame["stamp"], frame["depth"], frame["K"], frame["T_WC"]):
                t = time.perf_counter()
                try:
                    self.pipe.add_keyframe(Frame(frame["frame_id"], frame["stamp"], frame["depth"], frame["K"],
                                                 frame["T_WC"]))
                    added = True
                    self._wall["keyframe_wall"].append(1e3 * (time.perf_counter() - t))
                except ValueError:  # too few valid pixels: the service drops it too
                    self.rejected += 1
        self.frames_seen += 1
        self.seen_ids.append(frame["frame_id"])
        if added:
            self.keyframes += 1
            self.keyframe_ids.append(frame["frame_id"])
            if train:
                for _ in range(self.pipe.trainer.cfg.steps_for_keyframe(self.keyframes - 1)):
                    self.step()

    def step(self):
        if self.pipe.n_keyframes == 0:
            return False
        t = time.perf_counter()
        with self.clock.measure():
            info = self.pipe.step()
        self._wall["step_wall"].append(1e3 * (time.perf_counter() - t))
        self.steps += 1
        for k, v in info.get("timings_ms", {}).items():
            self._ms[k].append(float(v))
        return True

    def timings(self) -> dict:
        """Mean ms per module: trainer modules per step; others (Atlanta frame, surfels) per
        keyframe; ``sum`` adds the module means as the paper's Table III does; ``step_wall``
        and ``keyframe_wall``: measured around ``pipeline.step()`` / ``add_keyframe()``."""
        out = {k: round(float(np.mean(v)), 3) for k, v in self._ms.items() if v and k != "total"}
        out["sum"] = round(float(sum(out.values())), 3)
        out.update({k: round(float(np.mean(v)), 3) for k, v in self._wall.items() if v})
        return out

    def surfels(self):
        s = self.pipe.surfels()
        return s if s is not None and len(s) else None

    def query(self, view, points, grad=True):
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if grad:
            f, g = self.pipe.trainer.sdf_grad(p)
        else:
            f, g = self.pipe.sdf(p), None
        f = f.astype(np.float64)
        g = None if g is None else g.astype(np.float64)
        if view == "fused":
            f, g = fused_sdf(p, f, g, self.surfels(), DEFAULT_FUSE_RADIUS)
        elif view == "served":
            f, g = self.served(p, f, g)
        elif view == "served-noprior":
            prior, self.layout_prior = self.layout_prior, False
            try:
                f, g = self.served(p, f, g)
            finally:
                self.layout_prior = prior
        elif view == "baked":
            return self.baked(p, grad)
        return f, g

    def engine(self):
        """A query engine (CPU, one bake thread, otherwise its defaults) holding the map as
        the mapper publishes it now, baked; made again when the map changed."""
        from .. import protocol
        from ..query.engine import QueryEngine

        key = (self.keyframes, self.steps)
        if getattr(self, "_engine_key", None) != key:
            eng = QueryEngine(device="cpu", bake_threads=1)
            for k, data in self.pipe.map_messages(1, changed_only=False, epoch=1):
                eng.take(k, protocol.unpack(data))
            t = time.perf_counter()
            eng.bake_now()
            self._wall["bake_wall"].append(1e3 * (time.perf_counter() - t))
            self._engine, self._engine_key = eng, key
        return self._engine

    def baked(self, p: np.ndarray, grad: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """The query service's default reply (``source: "fused"``, not exact): the bake where
        it covers, the exact composition elsewhere."""
        from ..query_messages import SdfRequest

        rep = self.engine().answer_sdf(SdfRequest(np.asarray(p, np.float32), gradient=grad))
        return rep.sdf.astype(np.float64), None if rep.gradient is None else rep.gradient.astype(np.float64)

    def measured(self) -> MeasuredPoints | None:
        """The measured points the mapper publishes with its map (None: it pools none), as the
        query service holds them."""
        if self.pipe.measured is None:
            return None
        return MeasuredPoints(self.pipe.measured_points())

    def layout(self):
        """The predicted layout points the query service derives from this map (protocol 1.13,
        ``aisdf.structure.layout``: its surfels and observed space), or None (no prior, as
        ``layout_prior`` False, or nothing predicted); made again when the map changed."""
        from .. import protocol
        from ..query.answer import predicted_layout
        from ..query.engine import QueryEngine

        if not self.layout_prior or self.pipe.structure is None:
            return None
        key = (self.keyframes, self.steps)
        if getattr(self, "_layout_key", None) != key:
            # from the map as the service receives it (its surfels, observed space and bounds)
            eng = QueryEngine(device="cpu", bake=False)
            for k, data in self.pipe.map_messages(1, changed_only=False, epoch=1):
                eng.take(k, protocol.unpack(data))
            self._layout = None if eng.state is None else predicted_layout(eng.state)
            self._layout_key = key
        return self._layout

    def served(self, p: np.ndarray, f: np.ndarray, g: np.ndarray | None,
               radius: float = DEFAULT_FUSE_RADIUS) -> tuple[np.ndarray, np.ndarray | None]:
        """The query service's default answer from the network's ``f``/``g`` at ``p``
        (``QueryEngine._network_answer``, source "fused"): ``served_answer`` of the network,
        the signed distance to the global surfels and the measured points; the network alone
        when there are neither."""
        from ..query.answer import served_answer
        from ..structure.surfel_map import explicit_sdf

        s, measured, layout = self.surfels(), self.measured(), self.layout()
        if s is None and measured is None:
            return f, g
        d_e = g_e = None
        if s is not None:
            d_e, g_e, _ = explicit_sdf(p, s)
            d_e, g_e = d_e.astype(np.float32), g_e.astype(np.float32)
        sf, sg = served_answer(p, f.astype(np.float32), None if g is None else g.astype(np.float32), d_e, g_e,
                               measured, radius, layout=layout)
        return sf.astype(np.float64), None if sg is None else sg.astype(np.float64)

    def estimated_up(self) -> np.ndarray | None:
        """The Atlanta frame's vertical, when estimated (sign as the module gives it)."""
        st = self.pipe.structure
        frame = None if st is None else st.atlanta_frame()
        return None if frame is None else np.asarray(frame.vertical, dtype=np.float64)

    def summary(self, up: np.ndarray | None = None):
        out = {**super().summary(), "timings_ms": self.timings(), "describe": self.pipe.describe()}
        if self.spec.atlanta:
            s = self.surfels()
            out["surfels"] = 0 if s is None else len(s)
            v = self.estimated_up()
            out["estimated_up"] = None if v is None else v.round(4).tolist()
            if v is not None and up is not None:  # axial angle to the scene's up
                c = abs(float(v @ up)) / (np.linalg.norm(v) * np.linalg.norm(up))
                out["up_error_deg"] = round(float(np.degrees(np.arccos(min(c, 1.0)))), 3)
        return out


def make_runner(model: str, scene, clock: ComputeClock, preset: str, training: dict,
                keyframes: dict | None = None) -> Runner:
    spec = MODELS[model]
    if spec.kind == "voxel":
        return VoxelRunner(model, clock, scene.bounds, scene.max_depth, spec.voxel_size)
    return NeuralRunner(model, clock, spec, preset, training, keyframes)


def checkpoint_indices(n_frames: int, n_checkpoints: int) -> list[int]:
    """Frame indices (sorted, unique, last = n - 1) at equal shares of the sequence."""
    k = max(1, int(n_checkpoints))
    return sorted({max(0, int(round(n_frames * (j + 1) / k)) - 1) for j in range(k)})


def run_stream(frames, runners: Sequence[Runner], mode: str, checkpoints: Sequence[int],
               on_checkpoint: Callable[[int, float, list[dict]], None], progress=None, every: int = 5) -> list[dict]:
    """Replay ``frames`` (``len``, ``frame(i)``) through every runner in lockstep.

    ``on_checkpoint(i, stream_time_s, seen)`` is called after frame ``i`` for every ``i`` in
    ``checkpoints``, with every ``every``-th stream frame so far (the evaluation draws its
    points from those). Returns that list at the end."""
    if mode not in ("iterations", "realtime"):
        raise ValueError(f"mode must be iterations or realtime, not {mode!r}")
    n = len(frames)
    cps = set(checkpoints)
    seen: list[dict] = []
    nxt = frames.frame(0)
    t0 = nxt["stamp"]
    dt = None
    for i in range(n):
        frame = nxt
        nxt = frames.frame(i + 1) if i + 1 < n else None
        if nxt is not None:
            dt = nxt["stamp"] - frame["stamp"]
        next_rel = (nxt["stamp"] if nxt is not None else frame["stamp"] + (dt or 1 / 30)) - t0
        if i % every == 0:
            seen.append({k: frame[k] for k in ("frame_id", "depth", "K", "T_WC")})
        for r in runners:
            if mode == "iterations":
                r.see(frame, train=True)
                continue
            if r.clock.t >= next_rel:  # busy while this frame was the newest: skipped
                continue
            r.see(frame, train=False)
            while r.clock.t < next_rel:
                if not r.step():  # nothing to train (voxel map, or no keyframe yet): wait for the next frame
                    r.clock.t = next_rel
        if i in cps:
            on_checkpoint(i, float(frame["stamp"] - t0), seen)
        if progress is not None:
            progress.update(1, {r.name: r.steps if r.steps else r.frames_seen for r in runners})
    return seen
