"""Dataset readers shared by the frontend and the benchmark.

``open_dataset(kind, path, **opts)`` returns a ``Dataset``: ``len(ds)``, ``ds.frame(i)`` ->
``{frame_id, stamp, depth (H, W) float32 metres 0 = invalid, K (3, 3), T_WC (4, 4)}``,
``ds.K``, ``ds.name``, ``ds.H``, ``ds.W``, ``ds.mesh_path`` / ``ds.gt_mesh()``.
``detect(path)`` guesses the kind. Kinds (``READERS``): see each module's docstring.
"""

from __future__ import annotations

from pathlib import Path

from .base import DataMissingError, Dataset, data_root, require_data
from .generic import GenericDataset, write_generic
from .layout import LayoutRoomDataset
from .mesh import MeshRenderDataset
from .redwood import RedwoodDataset
from .replica import ReplicaCADDataset, ReplicaDataset
from .scannet import ScanNetDataset
from .sevenscenes import SevenScenesDataset
from .tum import TUMDataset

# Plain registry; ``detect`` tries the kinds in this order (most specific layouts first).
READERS: dict[str, type[Dataset]] = {
    "generic": GenericDataset,
    "scannet": ScanNetDataset,
    "replicacad": ReplicaCADDataset,
    "replica": ReplicaDataset,
    "tum": TUMDataset,
    "7scenes": SevenScenesDataset,
    "redwood": RedwoodDataset,
    "layout": LayoutRoomDataset,
    "mesh": MeshRenderDataset,
}
ALIASES: dict[str, str] = {"3dmatch": "7scenes", "icl-nuim": "redwood", "icl": "redwood", "render": "mesh"}


def detect(path) -> str:
    """The kind of the dataset at ``path`` (first reader in ``READERS`` that recognises it)."""
    p = Path(path)
    if not p.exists():
        raise DataMissingError(f"{p} does not exist")
    for kind, cls in READERS.items():
        if cls.sniff(p):
            return kind
    raise ValueError(f"cannot tell the dataset format of {p}; pass the kind ({', '.join(READERS)})")


def open_dataset(kind: str | None, path, **opts) -> Dataset:
    """Open ``path`` with reader ``kind`` (``None`` or ``"auto"``: ``detect``)."""
    if kind in (None, "auto"):
        kind = detect(path)
    kind = ALIASES.get(kind, kind)
    if kind not in READERS:
        raise ValueError(f"unknown dataset kind {kind!r}; known: {', '.join([*READERS, *ALIASES])}")
    if not Path(path).exists():
        raise DataMissingError(f"{path} does not exist")
    return READERS[kind](path, **opts)


__all__ = [
    "READERS",
    "ALIASES",
    "Dataset",
    "DataMissingError",
    "data_root",
    "require_data",
    "detect",
    "open_dataset",
    "write_generic",
    "GenericDataset",
    "LayoutRoomDataset",
    "MeshRenderDataset",
    "RedwoodDataset",
    "ReplicaCADDataset",
    "ReplicaDataset",
    "ScanNetDataset",
    "SevenScenesDataset",
    "TUMDataset",
]
