"""The ROS 2 services of ``aisdf ros2`` (over rmw_zenoh, :mod:`aisdf.ros.rmw_services`):

* ``/aisdf/get_distance_window`` (``aisdf/srv/GetDistanceWindow``, :mod:`aisdf.ros.interfaces`):
  the dense grid of distances (and gradients) over a box, as nvblox's
  ``get_esdf_and_gradient``, answered by one protocol 1.9 box request on ``query/sdf``. The
  array's dims are ``x``, ``y``, ``z`` and, with gradients, ``channel`` (distance, then the
  gradient's x, y, z), C order: sample (i, j, k) is at ``origin_m + voxel_size_m * (i, j, k)``.
* ``/aisdf/save_map`` (``std_srvs/srv/Trigger``): the running mapper's map written to a new
  folder ``map-<UTC date and time>`` in ``map_dir``; ``message`` is its path.
* ``/aisdf/load_map`` (``std_srvs/srv/Trigger``): the newest map folder in ``map_dir`` loaded
  into the running mapper (a new epoch; query services take it at once).

A failure is ``success: false`` with the reason in ``message``; the node goes on.
"""

from __future__ import annotations

import logging
import time
from datetime import datetime, timezone

import numpy as np

from .. import keys, mapfiles, protocol, query_messages, transport
from . import interfaces, outmsgs

log = logging.getLogger("aisdf.ros.outputs")


class MapServices:
    def __init__(self, cfg, session, node):
        self.cfg, self.session, self.node, self.ts = cfg, session, node, node.typestore
        base = cfg.node_name
        self.servers = [
            node.create_service(f"{base}/get_distance_window", interfaces.GET_DISTANCE_WINDOW, self.distance_window),
            node.create_service(f"{base}/save_map", interfaces.TRIGGER, self.save_map),
            node.create_service(f"{base}/load_map", interfaces.TRIGGER, self.load_map),
        ]

    def _response(self, srvtype: str, **values):
        return outmsgs.make(self.ts, interfaces.response_type(srvtype), **values)

    def distance_window(self, req):
        srv = interfaces.GET_DISTANCE_WINDOW
        try:
            lo = (req.aabb_min_m.x, req.aabb_min_m.y, req.aabb_min_m.z)
            size = (req.aabb_size_m.x, req.aabb_size_m.y, req.aabb_size_m.z)
            # voxel_size_m is a float32: 0.05 arrives as 0.0500000007, which would lose the far
            # face of a 4 m box; its shortest decimal is what the caller meant
            box = query_messages.Box.around(lo, size, float(f"{np.float32(req.voxel_size_m):.7g}"))
            ask = query_messages.SdfRequest(np.zeros((0, 3), np.float32), bool(req.gradient), box=box)
            rep = query_messages.SdfReply.from_msg(transport.query(
                self.session, keys.key(self.cfg.namespace, keys.QUERY_SDF), ask.to_msg(), self.cfg.timeout_s))
        except protocol.ProtocolError as e:
            return self._response(srv, success=False, message=f"{e.code}: {e.message}")
        except TimeoutError as e:
            return self._response(srv, success=False, message=f"no query service answered: {e}")
        grid = rep.grid("sdf")[..., None]
        if req.gradient:
            grid = np.concatenate([grid, rep.grid("gradient")], axis=-1)
        labels = ["x", "y", "z"] + (["channel"] if req.gradient else [])
        shape = grid.shape if req.gradient else grid.shape[:3]
        strides = np.cumprod(shape[::-1])[::-1]  # ROS's MultiArrayLayout: dim[i].stride = prod(size[i:])
        dims = [outmsgs.make(self.ts, "std_msgs/msg/MultiArrayDimension", label=lab, size=int(n), stride=int(s))
                for lab, n, s in zip(labels, shape, strides)]
        layout = outmsgs.make(self.ts, "std_msgs/msg/MultiArrayLayout", dim=dims, data_offset=0)
        data = outmsgs.make(self.ts, "std_msgs/msg/Float32MultiArray", layout=layout,
                            data=np.ascontiguousarray(grid, np.float32).reshape(-1))
        made_ns = time.time_ns() - int((rep.map_age_s or 0.0) * 1e9)
        origin = outmsgs.make(self.ts, "geometry_msgs/msg/Point", x=box.origin[0], y=box.origin[1], z=box.origin[2])
        return self._response(srv, success=True, message="", header=outmsgs.header(self.ts, self.cfg.frame_id, made_ns),
                              origin_m=origin, esdf_and_gradients=data, map_version=int(rep.map_version))

    def save_map(self, _req):
        folder = self.cfg.map_dir / f"map-{datetime.now(timezone.utc):%Y%m%d-%H%M%S}"
        try:
            path = mapfiles.save_map(self.session, self.cfg.namespace, folder)
        except (RuntimeError, ValueError, OSError) as e:
            log.warning("save_map failed: %s", e)
            return self._response(interfaces.TRIGGER, success=False, message=str(e))
        log.info("map saved to %s", path)
        return self._response(interfaces.TRIGGER, success=True, message=str(path))

    def load_map(self, _req):
        folder = mapfiles.newest_map(self.cfg.map_dir) if self.cfg.map_dir.is_dir() else None
        if folder is None:
            return self._response(interfaces.TRIGGER, success=False, message=f"no map folder in {self.cfg.map_dir}")
        try:
            rep = mapfiles.load_map(self.session, self.cfg.namespace, folder)
        except (RuntimeError, ValueError, OSError) as e:
            log.warning("load_map failed: %s", e)
            return self._response(interfaces.TRIGGER, success=False, message=str(e))
        log.info("map %s loaded: %s", folder, rep)
        return self._response(interfaces.TRIGGER, success=True,
                              message=f"{folder}: {rep.get('keyframes')} keyframes, map version {rep.get('version')}, "
                                      f"epoch {rep.get('epoch')}")

    def close(self) -> None:
        for s in self.servers:
            s.close()
        self.servers = []
