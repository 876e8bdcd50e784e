"""The structure part of AiSDF, one keyframe at a time, its stages in order:

1. ``atlanta_init``: the vertical and the first horizontal directions from a keyframe's
   normals (paper Sec. III-B, initialisation).
2. ``atlanta``: the global Atlanta frame, refined and extended keyframe after keyframe.
3. ``surfel_image``: per keyframe, points, normals and the pixels' planar regions.
4. ``surfel_fit``: planes and rectangles fitted to those regions.
5. ``surfels``: Atlanta-aware surfels of a keyframe and its surfel mask (Sec. III-C).
6. ``surfel_map``: the global planar map: surfels merged across keyframes, realigned
   when the Atlanta frame moves (beyond the paper).
7. ``fusion``: answers from the network and the surfel map together (Sec. IV-D).
8. ``measured``: the keyframes' depth pixels pooled into voxels, and an answer that also
   uses them (beyond the paper; scored by ``aisdf bench scaling``, not served yet).

``surfel_types`` (the ``Surfels`` arrays) and ``surfel_config`` hold the shared data and
settings; ``process.Structure`` runs stages 1-6 for each keyframe (the mapper's pipeline
calls it). Pure numpy, no torch, no Zenoh.
"""

from __future__ import annotations


def __getattr__(name: str):
    # Lazy: aisdf.mapping.frames imports surfel_types from here, and process imports frames.
    if name == "Structure":
        from .process import Structure

        return Structure
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["Structure"]
