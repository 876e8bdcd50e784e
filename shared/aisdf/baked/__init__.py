"""The baked field: a sampled copy of an SDF (the query service bakes the fused map) over
observed space, answered by interpolation in constant time per point.

Layout (sparse blocks, two levels, coarse to fine)
--------------------------------------------------
Space is cut into cubic blocks of edge ``block`` (20 cm; aligned with the observed-space
grid). A block is *baked* when it holds observed space; nothing else is evaluated. Every
baked block has the **coarse** level: value and gradient at its 8 corners (spacing
``block``; corners are shared between neighbouring blocks). The bake then evaluates the
field at the centre of every block and compares it with the coarse interpolant there:
where they differ by more than ``tol`` (object edges and corners, curved surfaces, the
distance field's ridges) the block gets the **fine** level, value and gradient on an
``(nf+1)^3`` lattice (spacing ``block / nf``, 10 cm), together with its 26 neighbours (so
that the level blend below is complete on every refined block). Flat walls and smooth
free space stay coarse: a plane's SDF is exact at any spacing. ``near_surface`` also
refines every block a surface may cross (``min |f| < block*sqrt(3)/2 + band`` at its
corners). Measured on the demo office (``aisdf bench query``), refining on the centre
check needs fewer evaluations than a near-surface band for the same accuracy.

Interpolation (C^1, exact on linear fields)
-------------------------------------------
In a cell, the tensor-product cubic Hermite interpolant of the 8 corners' values and
gradients (cross derivatives zero)::

    f(x) = sum_i [ f_i A_i(x) + h (g_i . B_i(x)) ]

with A_i = prod_k a(t_k) and B_i,k = b(t_k) prod_(j != k) a(t_j), a and b the cubic
Hermite bases of a value and a slope. It interpolates value and gradient at every sample,
reproduces any linear field exactly (a plane's SDF), and is C^1 across cells and blocks
(a face's values and normal derivatives depend on that face's corners only). It uses the
stored gradients as ∇-SDF's gradient-augmented trilinear interpolation does, with cubic
instead of linear weights: on the demo office at 10 cm it is 2.6x more accurate (mean
difference to the network 0.085 cm against 0.223 cm). The gradient returned is the
interpolant's exact gradient.

The two levels are blended with a weight alpha that is 1 on refined blocks and 0 on every
face shared with a coarse-only block (alpha is 1 at a block corner none of whose 8
blocks is a baked coarse-only one, else 0, blended with the Hermite value basis, i.e.
smoothstep), so the whole field is C^1 across level borders too:
``f = alpha f_fine + (1 - alpha) f_coarse``.

Points outside every baked block are reported as not covered; the caller answers them
another way (the query service: the network).

Re-baking what changed (submaps)
--------------------------------
``bake(..., previous=old, dirty=fn)`` bakes a new field reusing the samples of an older
bake on the same lattice (same block and fine spacing, origins a whole number of blocks
apart) wherever ``dirty(points)`` says the field cannot have changed: coarse corners,
block centres (kept in ``centres``) and fine lattice points are copied, only the rest is
evaluated. The layout (which blocks, which are refined, the blend weights) is recomputed
from the values as in a full bake, so the result equals a full bake of the new field
whenever ``dirty`` is right (a sample is reused only where the old and new fields agree).
The query service passes the union of the extended boxes of the submaps that changed and
the surroundings of the surfels that changed: the evaluations follow what changed, not
the size of the building.

Modules: ``field`` (the lookup: the interpolation kernels, compiled by numba, and
:class:`BakedField`), ``build`` (:func:`bake` and :class:`BakeConfig`: what is sampled).
"""

from .build import BakeConfig, bake
from .field import BakedField

__all__ = ["BakeConfig", "BakedField", "bake"]
