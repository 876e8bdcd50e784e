"""The mutation check (``make mutation``; not part of ``make test``): does the suite fail when
the product breaks in the ways users would notice?

Each breakage below is one exact text replacement in one product file (the script stops if
the text is not there exactly once: a breakage that no longer applies is a finding, not a
pass). Each is applied in turn to a fresh copy of the tree in a temporary folder (the working
tree is never touched, so an interrupted run leaves nothing broken), and the tests that should
catch it run there (a narrowed selection of the default suite, with the copy's packages first
on ``PYTHONPATH``, so that the services the end-to-end tests start run the broken code too).
A breakage is caught when that selection fails. The table printed at the end says which were.

The copy is of the committed tree (``git archive HEAD``) by default, ``--worktree``: of the
working tree as it is (tracked and untracked files git does not ignore). ``--baseline``: first
run each selection on the unbroken copy (it must pass, else "caught" means nothing).
``--only NAME`` (repeatable): those breakages only; ``--list``: the names and exit.

Exit status: 0 when every breakage was caught, 1 otherwise. See docs/testing.md.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = {"aisdf": "shared/aisdf", "aisdf_frontend": "services/frontend", "aisdf_mapper": "services/mapper",
            "aisdf_query": "services/query"}


@dataclass(frozen=True)
class Breakage:
    name: str
    what: str
    path: str
    old: str
    new: str
    tests: tuple[str, ...]


BREAKAGES = [
    Breakage("fused-without-measured", "the fused answer ignores the measured points (1.4/1.5's rule gone)",
             "shared/aisdf/query/answer.py", "    sdf, grad, _ = fuse(sdf_i, grad_i, d_e, g_e, radius)\n",
             "    sdf, grad, _ = fuse(sdf_i, grad_i, d_e, g_e, radius)\n    measured = None\n",
             ("tests/mapper/test_pipeline.py::test_one_network_sends_its_measured_points_1_5",)),
    Breakage("fused-without-surfels", "the fused answer ignores the surfel map",
             "shared/aisdf/query/answer.py", "    if d_e is None:\n", "    if True:\n",
             ("tests/mapper/test_pipeline.py::test_one_network_sends_its_measured_points_1_5",)),
    Breakage("served-network-alone", "the served answer is the network alone (no surfels, no measured points)",
             "shared/aisdf/query/answer.py", '    points (``predicted_layout``; None: no prior)."""\n',
             '    points (``predicted_layout``; None: no prior)."""\n    return sdf_i, grad_i\n',
             ("tests/mapper/test_pipeline.py::test_one_network_sends_its_measured_points_1_5",
              "tests/mapper/test_pipeline.py::test_messages_and_query_engine_agree")),
    Breakage("demo-served-network-alone", "the same, against the demo's own test (a 75 s demo: minutes)",
             "shared/aisdf/query/answer.py", '    points (``predicted_layout``; None: no prior)."""\n',
             '    points (``predicted_layout``; None: no prior)."""\n    return sdf_i, grad_i\n',
             ("tests/e2e/test_e2e.py::test_demo_maps_the_synthetic_building",)),
    Breakage("submap-priors-empty", "surfel bounds off in submaps: every submap's prior holds no surfel",
             "shared/aisdf/structure/prior.py", "s = s[np.flatnonzero(d <= self.radius)]", "s = s[:0]",
             ("tests/structure/test_surfel_bounds.py",)),
    Breakage("surfel-bounds-ignored", "the trainer never tightens a bound with the surfel map",
             "shared/aisdf/mapping/trainer.py", "if cfg.surfel_bounds and self.bound_prior is not None:",
             "if False:", ("tests/mapping/test_trainer.py", "tests/structure/test_surfel_bounds.py")),
    Breakage("atlanta-vertical-off", "the Atlanta frame's vertical tilted by about 11 degrees at initialisation",
             "shared/aisdf/structure/atlanta.py", "        self.vertical = v\n        self.vertical_count = len(self._buffer)",
             "        self.vertical = unit(v + 0.2 * perpendicular(v))\n        self.vertical_count = len(self._buffer)",
             ("tests/structure/test_atlanta.py",)),
    Breakage("bake-stale-as-new", "a bake that lags the newest map reports the newest map's version",
             "shared/aisdf/query/engine.py", "        if req.source == \"fused\" and not req.exact and bk is not None:\n"
             "            state = bk.state\n",
             "        if req.source == \"fused\" and not req.exact and bk is not None:\n            state = newest\n",
             ("tests/query/test_baked.py",)),
    Breakage("fresh-under-load", "planners first gone: requests answered while others wait are freshened too",
             "shared/aisdf/query/engine.py", "            elif trails and not self.fresh_busy and self.waiting() > 0:",
             "            elif False:", ("tests/query/test_fresh.py", "tests/bench/test_load.py")),
    Breakage("new-space-not-first", "a re-bake no longer bakes the newly mapped space first",
             "shared/aisdf/query/baker.py", "        if previous is not None and st.submaps is not None and st.observed "
             "is not cur.state.observed:", "        if False:", ("tests/query/test_fresh.py",)),
    Breakage("dropped-acknowledgement", "the mapper adds a keyframe but never acknowledges it",
             "services/mapper/main.py", "            self.counts[\"accepted\"] += 1\n            ok.append(kf.frame_id)\n",
             "            self.counts[\"accepted\"] += 1\n",
             ("tests/services/test_reliable_delivery.py",)),
    Breakage("journal-without-fsync", "the keyframe journal is written without its fsync",
             "services/mapper/journal.py", "            os.fsync(self._f.fileno())", "            pass",
             ("tests/services/test_reliable_delivery.py",)),
    Breakage("no-deduplication", "the mapper adds a resent keyframe a second time",
             "services/mapper/main.py", "            if self.is_seen(kf.sensor, kf.frame_id):  # a resend",
             "            if False:  # a resend", ("tests/services/test_reliable_delivery.py",)),
    Breakage("acl-planner-answers-queries", "the access control gives planners the query service's rules on "
             "query/** (a planner can answer in its place)", "deploy/tls/router.json5",
             'rules: ["read-maps", "receive-maps", "ask-queries", "receive-answers", "watch-replicas"] },',
             'rules: ["read-maps", "receive-maps", "ask-queries", "receive-answers", "watch-replicas", "answer-queries", '
             '"hear-queries"] },',
             ("tests/services/test_tls_acl.py::test_only_the_query_identity_can_answer_planners",)),
    Breakage("acl-rule-removed", "the access control loses the rule that lets the frontend hear acknowledgements",
             "deploy/tls/router.json5", '"put-keyframes", "sub-acks", "hear-acks", "watch-mappers"',
             '"put-keyframes", "sub-acks", "watch-mappers"',
             ("tests/services/test_tls_acl.py::test_planner_gets_answers_and_reads_maps",)),
    Breakage("frontend-drain-forever", "the frontend ignores drain_timeout_s and waits for acknowledgements forever",
             "services/frontend/main.py", "sender.drain(cfg.drain_timeout_s, stop)", "sender.drain(1e9, stop)",
             ("tests/services/test_frontend.py",)),
    Breakage("internal-error-as-no-map", "the query service reports its internal errors as no_map",
             "services/query/main.py",
             '            log.exception("internal error answering a request")\n'
             '            self._reply_err(q, protocol.ProtocolError("internal",',
             '            log.exception("internal error answering a request")\n'
             '            self._reply_err(q, protocol.ProtocolError("no_map",',
             ("tests/services/test_sdf_client.py",)),
    Breakage("clearing-off", "free space never clears (the default turned off)",
             "shared/aisdf/mapper/coverage.py", "clear_free_space: bool = Field(True,",
             "clear_free_space: bool = Field(False,", ("tests/mapper/test_clearing.py",)),
    Breakage("clearing-keeps-pixels", "stored keyframes keep the pixels newer rays passed through",
             "shared/aisdf/mapper/clearing.py", "    raw[v[gone], u[gone]] = 0\n", "",
             ("tests/mapper/test_clearing.py",)),
    Breakage("clearing-holes-strict", "measured points behind a depth edge's hole band are never tested",
             "shared/aisdf/mapper/clearing.py", "    passed, confirmed = evidence.verdict(pts, holes=True)\n",
             "    passed, confirmed = evidence.verdict(pts)\n", ("tests/mapper/test_clearing.py",)),
    Breakage("clearing-holes-news", "clearing a real edge's voxels through a hole band counts as news",
             "shared/aisdf/mapper/clearing.py", "min_hits) & strict).sum())", "min_hits)).sum())",
             ("tests/mapper/test_clearing.py",)),
    Breakage("clearing-holes-pixels", "stored keyframes' pixels are cleared through windows with holes",
             "shared/aisdf/mapper/clearing.py", "return self.tested(points, holes)[0]",
             "return self.tested(points, True)[0]", ("tests/mapper/test_clearing.py",)),
    Breakage("clearing-one-pass", "one keyframe's rays remove a measured point (the default back to 1)",
             "shared/aisdf/mapper/coverage.py", "clear_passes: int = Field(2,", "clear_passes: int = Field(1,",
             ("tests/mapper/test_clearing.py",)),
    Breakage("clearing-no-reset", "a keyframe that measures a surface at a point does not reset its miss count",
             "shared/aisdf/structure/measured.py", "        self.misses[confirmed] = 0\n", "",
             ("tests/mapper/test_clearing.py",)),
    Breakage("measured-own-means", "measured points are the voxels' own means again (the noise tails off walls)",
             "shared/aisdf/structure/measured.py",
             "    return np.where(planar[:, None], own + np.einsum", "    return own + 0 * np.where(planar[:, None], own + np.einsum",
             ("tests/structure/test_measured_surface.py",)),
    Breakage("measured-stale-points", "the measured points are not updated around the voxels a keyframe changed",
             "shared/aisdf/structure/measured.py",
             "            self._voxel_pts[rows] = surface_points(",
             "            self._voxel_pts[rows] = self._voxel_pts[rows] + 0 * surface_points(",
             ("tests/structure/test_measured_surface.py",)),
    Breakage("late-surfels-none", "a wall seen before its direction was published never gets that keyframe's surfels",
             "shared/aisdf/structure/process.py", "        self.late = self._late(self._published() - before)",
             "        self.late = self._late(set())", ("tests/structure/test_late_surfels.py",)),
    Breakage("late-surfels-not-in-map", "late surfels are not merged into the global surfel map",
             "shared/aisdf/structure/process.py", "                self.map.add(s)\n                out.append((key, s))",
             "                out.append((key, s))", ("tests/structure/test_late_surfels.py",)),
    Breakage("repose-move-nothing", "a network moved with its keyframes stays where it was",
             "shared/aisdf/network.py", "    fix(net.layers[0], 0)\n", "    return\n",
             ("tests/test_network.py", "tests/mapper/test_repose.py")),
    Breakage("repose-no-distill", "a network started again after a correction learns nothing of the old field",
             "shared/aisdf/mapper/repose.py", 'if s.repose_networks == "move" and s.repose_distill_steps and',
             'if False and', ("tests/mapper/test_repose.py",)),
    Breakage("repose-atlanta-kept", "a pose correction leaves the Atlanta frame the drifting normals gave",
             "shared/aisdf/mapper/repose_rebuild.py",
             "        intake.structure.follow_corrections(frames, moved)  # the Atlanta frame turns with its keyframes\n",
             "", ("tests/mapper/test_repose.py",)),
    Breakage("repose-keeps-surfels", "a pose correction leaves the global surfels where the wrong poses put them",
             "shared/aisdf/mapper/repose_rebuild.py", "        rebuild_surfels(intake.structure, frames, moved)\n", "",
             ("tests/mapper/test_repose.py",)),
    Breakage("repose-keeps-measured", "a pose correction leaves the measured points where the wrong poses put them",
             "shared/aisdf/mapper/repose_rebuild.py", "        intake.measured = measured\n", "",
             ("tests/mapper/test_repose.py",)),
    Breakage("repose-new-floor-axes", "a keyframe fitted again after a correction boxes its tables along any direction",
             "shared/aisdf/structure/process.py", "floor_axes=self._floor_axes(own, late))", "floor_axes=None)",
             ("tests/mapper/test_repose.py",)),
    Breakage("layout-big-planes-only", "the layout prior takes only planes of 0.5 m^2 of surfels (a wall seen in pieces is left out)",
             "shared/aisdf/structure/layout.py", "    min_area: float = 0.1  #", "    min_area: float = 0.5  #",
             ("tests/structure/test_layout.py",)),
    Breakage("ros2-grid-ignores-baked-surfels", "the ROS 2 grid keeps samples of a bake that lacked the surfels it holds",
             "shared/aisdf/ros/outputs.py",
             "        surfels_baked = len(baked) < 3 or baked[2] is None or baked[2] >= smap.version\n",
             "        surfels_baked = True\n", ("tests/ros/test_ros2_outputs.py",)),
    Breakage("mapper-dir-unlocked", "two mappers may write one checkpoint directory",
             "services/mapper/main.py", "        if self.slot is None and cfg.checkpoint_dir:\n",
             "        if False:\n", ("tests/cluster/test_slots.py",)),
    Breakage("health-id-prefix", "aisdf-health --id matches a prefix (mapper-1 passes on mapper-10)",
             "shared/aisdf/ops.py", "if rid == id_prefix if exact else", "if rid.startswith(id_prefix) if exact else",
             ("tests/services/test_tls_acl.py",)),
    Breakage("cleared-not-republished", "a submap whose measured points were cleared waits for training",
             "shared/aisdf/submaps/publish.py", "if changed_only and not sm.measured_changed and (",
             "if changed_only and (", ("tests/mapper/test_clearing.py",)),
    Breakage("layout-in-observed", "the layout prior predicts surfaces in observed space too",
             "shared/aisdf/structure/layout.py", "    return q[(joined & ~seen).ravel()]", "    return q[joined.ravel()]",
             ("tests/structure/test_layout.py",)),
    Breakage("layout-runs-past-edges", "a plane runs on past where another surface meets it",
             "shared/aisdf/structure/layout.py", "        met = ndimage.binary_dilation(met)\n",
             "        met[:] = False\n", ("tests/structure/test_layout.py",)),
    Breakage("layout-not-baked", "the bake leaves the layout cap out (exact answers keep it)",
             "shared/aisdf/query/baker.py", "self.fuse_radius, layout=lay)", "self.fuse_radius, layout=None)",
             ("tests/query/test_layout_answer.py",)),
    Breakage("far-floor-off", "the served answer is no longer raised far from the measured points",
             "shared/aisdf/query/answer.py", "    use = np.isfinite(d_m) & np.isfinite(floor)",
             "    use = np.zeros(len(sdf), bool) & np.isfinite(floor)", ("tests/query/test_far_floor.py", "tests/query/test_changes.py")),
    Breakage("far-floor-ignores-surfels", "the floor rises past a nearer surfel to the nearest measured point",
             "shared/aisdf/query/answer.py", "    cands = [d_m, np.abs(np.asarray(d_e, np.float64))]\n",
             "    cands = [d_m, np.full(len(d_m), np.inf)]\n", ("tests/query/test_far_floor.py",)),
    Breakage("far-floor-unsupported-surfels", "every surfel bounds the floor, measured where it reaches or not",
             "shared/aisdf/query/answer.py", "    ask = np.isfinite(d_e) & (np.abs(d_e) < d_m) & (d_m > FLOOR_NEAR)\n",
             "    ask = np.zeros(len(d_e), bool)\n", ("tests/query/test_far_floor.py",)),
    Breakage("floor-support-not-rebaked", "the re-bake ignores measured points that only change a surfel's support",
             "shared/aisdf/query/baker.py", "points, grow, support=FLOOR_SUPPORT)",
             "points, grow)", ("tests/query/test_changes.py::test_measured_points_1_4_answers_bake_and_the_1_3_answer",)),
    Breakage("far-floor-raises-inside", "the floor raises points behind their nearest surfel (inside solids)",
             "shared/aisdf/query/answer.py", "behind=(np.asarray(d_e) < 0) & within)", "behind=np.zeros(len(d_e), bool))", ("tests/query/test_far_floor.py",)),
]


def copy_tree(dest: Path, worktree: bool) -> None:
    if worktree:
        files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard", "-z"], cwd=ROOT, check=True,
                               capture_output=True).stdout.decode().split("\0")
        for f in filter(None, files):
            src = ROOT / f
            if src.is_file():
                (dest / f).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, dest / f)
    else:
        archive = subprocess.run(["git", "archive", "HEAD"], cwd=ROOT, check=True, capture_output=True).stdout
        subprocess.run(["tar", "-x", "-C", str(dest)], input=archive, check=True)
    shim = dest / ".mutation-packages"  # the copy's packages, found before the editable install's
    shim.mkdir()
    for name, rel in PACKAGES.items():
        (shim / name).symlink_to(dest / rel, target_is_directory=True)


def stale(root: Path, b: Breakage) -> str | None:
    """Why breakage ``b`` no longer applies to the tree at ``root`` (None: it applies)."""
    n = (root / b.path).read_text().count(b.old)
    if n != 1:
        return f"breakage {b.name}: the text to replace occurs {n} times in {b.path} (expected once)"
    return None


def apply(dest: Path, b: Breakage) -> None:
    why = stale(dest, b)
    if why:
        raise SystemExit(f"{why}; update the breakage to the product as it is now")
    path = dest / b.path
    path.write_text(path.read_text().replace(b.old, b.new))


def run_tests(dest: Path, tests: tuple[str, ...], timeout: float, log: Path) -> tuple[int, int | None]:
    """(pytest's exit status, tests run); 124 when the selection ran past ``timeout``."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(dest / ".mutation-packages"),
                                                        os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep),
           "PYTHONDONTWRITEBYTECODE": "1"}
    check = subprocess.run([sys.executable, "-c", "import aisdf, aisdf_query; print(aisdf.__file__)"], cwd=dest,
                           env=env, capture_output=True, text=True, check=True).stdout.strip()
    if not Path(check).resolve().is_relative_to(dest.resolve()):
        raise SystemExit(f"the copy's packages are not the ones imported ({check}): the check would test the "
                         "working tree")
    cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *tests]  # the copy's pyproject
    with open(log, "w") as out:
        try:
            rc = subprocess.run(cmd, check=False, cwd=dest, env=env, stdout=out, stderr=subprocess.STDOUT, timeout=timeout,
                                start_new_session=True).returncode
        except subprocess.TimeoutExpired:
            rc = 124
    text = log.read_text()
    ran = None
    for line in reversed(text.splitlines()):
        if " in " in line and ("passed" in line or "failed" in line or "error" in line):
            ran = sum(int(w) for w, k in zip(line.split(), line.split()[1:])
                      if w.isdigit() and k.rstrip(",") in ("passed", "failed", "errors", "error"))
            break
    return rc, ran


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--only", action="append", metavar="NAME", help="run only this breakage (repeatable)")
    p.add_argument("--list", action="store_true", help="list the breakages and exit")
    p.add_argument("--worktree", action="store_true", help="copy the working tree, not HEAD")
    p.add_argument("--baseline", action="store_true", help="first run every selection unbroken (must pass)")
    p.add_argument("--timeout", type=float, default=300.0, help="seconds per selection (default 300)")
    p.add_argument("--keep", action="store_true", help="keep the temporary folder (its logs) and say where")
    args = p.parse_args(argv)
    if args.list:
        for b in BREAKAGES:
            print(f"{b.name:28s} {b.path}: {b.what}\n{'':28s} tests: {' '.join(b.tests)}")
        return 0
    chosen = [b for b in BREAKAGES if not args.only or b.name in args.only]
    unknown = set(args.only or ()) - {b.name for b in BREAKAGES}
    if unknown:
        p.error(f"unknown breakage(s): {', '.join(sorted(unknown))}")
    tmp = Path(tempfile.mkdtemp(prefix="aisdf-mutation-"))
    rows, t_all = [], time.monotonic()
    try:
        if args.baseline:
            base = tmp / "baseline"
            base.mkdir()
            copy_tree(base, args.worktree)
            selection = tuple(dict.fromkeys(t for b in chosen for t in b.tests))
            t0 = time.monotonic()
            rc, ran = run_tests(base, selection, args.timeout * 2, tmp / "baseline.log")
            print(f"baseline (unbroken): {ran} tests, exit status {rc}, {time.monotonic() - t0:.0f} s", flush=True)
            if rc != 0:
                print((tmp / "baseline.log").read_text()[-3000:])
                print("the unbroken tree fails its selections: fix that first")
                return 2
        for b in chosen:
            dest = tmp / b.name
            dest.mkdir()
            copy_tree(dest, args.worktree)
            apply(dest, b)
            t0 = time.monotonic()
            rc, ran = run_tests(dest, b.tests, args.timeout, tmp / f"{b.name}.log")
            dt = time.monotonic() - t0
            caught = rc not in (0, 5)  # 5: no test collected, which catches nothing
            rows.append((b, ran, caught, rc, dt))
            print(f"{b.name}: {'caught' if caught else 'NOT CAUGHT'} ({ran} tests, exit {rc}, {dt:.0f} s)", flush=True)
            if not args.keep:
                shutil.rmtree(dest, ignore_errors=True)
    finally:
        if not args.keep:
            shutil.rmtree(tmp, ignore_errors=True)
    print()
    print("| breakage | file | tests run | caught | seconds |\n|---|---|---:|---|---:|")
    for b, ran, caught, rc, dt in rows:
        print(f"| {b.name} | {b.path} | {ran if ran is not None else '?'} | "
              f"{'yes' if caught else 'NO'}{'' if rc in (0, 1) else f' (exit {rc})'} | {dt:.0f} |")
    n = sum(r[2] for r in rows)
    print(f"\n{n} of {len(rows)} breakages caught, {time.monotonic() - t_all:.0f} s in all"
          + (f"; logs in {tmp}" if args.keep else ""))
    return 0 if n == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
