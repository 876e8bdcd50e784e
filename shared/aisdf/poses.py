"""Pose corrections (protocol 1.11, docs/protocol.md "Pose corrections"): a SLAM system whose
loop closure (a jump of ``map -> odom``, a re-optimised trajectory) moves keyframes already
sent tells the mapper their new poses, and the map follows::

    from aisdf.poses import send_corrections
    reply = send_corrections(session, "aisdf", "depth", {17: T_WC_17, 18: T_WC_18})
    reply["reposed"], reply["unknown"]     # moved; not in the map (left as they are)

``session`` is an open Zenoh session (``aisdf.transport.open_session``). The mapper applies
the batch between two training steps and answers once the corrected map is published: about
a second for a few keyframes of a small map, tens of seconds for half of a 400-keyframe map on
2 cores (docs/experiments/pose-corrections.md); give a large batch a larger ``timeout``.
A mapper before 1.11 has no ``control/mapper/poses``: nobody answers and this raises
``TimeoutError``; the map keeps the poses the keyframes came with.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from . import keys, protocol, transport


def corrections_message(sensor: str, corrections: Mapping[int, np.ndarray]) -> dict:
    """The PoseCorrections message of ``{frame_id: T_WC (4, 4)}``, checked as the mapper
    checks it (ProtocolError for a malformed one: nothing is sent)."""
    ids = [int(i) for i in corrections]
    T = np.stack([np.asarray(corrections[i], np.float64).reshape(4, 4) for i in corrections]) if ids else \
        np.zeros((0, 4, 4))
    msg = protocol.PoseCorrections(str(sensor), ids, T).to_msg()
    protocol.PoseCorrections.from_msg(msg)
    return msg


def send_corrections(session, namespace: str, sensor: str, corrections: dict[int, np.ndarray],
                     timeout: float = 10.0) -> dict:
    """Send new camera-to-world poses for keyframes (sensor, frame_id) already sent and return
    the mapper's reply (``PosesApplied``: ``reposed``, ``unknown``, ``unchanged``, ``submaps``,
    ``version``, ``epoch``, ``seconds``). Raises ``aisdf.codec.ProtocolError`` for a malformed
    request (found here before sending, or the mapper's ``bad_request``) and ``TimeoutError``
    when no mapper answers within ``timeout`` (none running, or one before protocol 1.11)."""
    msg = corrections_message(sensor, corrections)
    reply = transport.query(session, keys.key(namespace, keys.CONTROL_POSES), msg, timeout)
    return protocol.PosesApplied.from_msg(reply).to_msg()
