"""A small trained map of the synthetic Atlanta building (a 32-wide network, 6 keyframes,
5 steps each), shared by the baked-field tests and the query service's end-to-end tests."""

from aisdf.mapping.frames import Frame
from aisdf.mapper.single import MappingPipeline
from aisdf.synthetic import SyntheticSequence


def train_small_map(measured: bool = True):
    """(sequence, the keyframes' frame dicts, the trained MappingPipeline). ``measured``: the
    mapper pools and sends measured points (protocol 1.5, the default)."""
    seq = SyntheticSequence(building="atlanta", n_frames=120, H=60, W=80, seed=1)
    # The paper's bounds: with surfel bounds (the mapper's default) this 30-step toy network's
    # fused field bakes with a 99th-percentile error of 5.5 cm against the exact fused answer
    # (0.16 cm for the network alone): min(network, surfel distance) switches back and forth where
    # the two nearly agree and their gradients do not, which the bake's block-centre check misses.
    # Left for the baked field's owner (closing note of 2026-12-02).
    p = MappingPipeline.from_settings("cpu", {"network": {"width": 32}, "n_rays": 20}, surfel_bounds=False,
                                      measured=measured)
    frames = []
    for i in range(0, 120, 20):
        f = seq.frame(i)
        frames.append(f)
        p.add_keyframe(Frame(f["frame_id"], f["stamp"], f["depth"], f["K"], f["T_WC"]))
        for _ in range(5):
            p.step()
    return seq, frames, p


def publish_until_baked(session, ns: str, snap, smap, timeout: float = 90.0) -> None:
    """Put the map (``smap``'s surfels first, then ``snap``'s weights) on ``ns`` with a plain
    Zenoh session, again every 2 s, until the query service there has baked version 1 with
    ``smap``'s surfels (the weights can arrive first and be baked alone)."""
    import time

    import stranger_client as sc
    from aisdf import protocol
    from aisdf.stack import wait_for

    def baked():
        if smap is not None:
            session.put(f"{ns}/map/surfels", protocol.pack(smap.to_msg()), encoding=sc.ENC)
            time.sleep(0.2)
        session.put(f"{ns}/map/weights", protocol.pack(snap.to_msg()), encoding=sc.ENC)
        status, msg = sc.request(session, f"{ns}/info/query", {"v": 1}, 2.0)
        return (status == "ok" and msg.get("baked_version") == 1
                and (smap is None or msg.get("baked_surfel_version") == smap.version))  # the surfels in it too

    wait_for(baked, timeout, period=2.0, what="the map to be baked")
