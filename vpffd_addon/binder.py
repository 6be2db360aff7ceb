"""`bind`: a triangle mesh bound to a `Lattice` or to a `Cage`, whichever it is given."""
import numpy as np

from .binding import bind_lattice
from .cage import Cage
from .cage_binding import bind_cage
from .lattice import Lattice


def bind(lattice, rest_verts, tris, influence=None, dtype=np.float64, depth=None, outside="FOLLOW",
         topology=None, use_compiled=True, measured_in=None):
    """Bind a triangle mesh to `lattice` (a `Lattice`, or a `Cage` of any topology).

    rest_verts: (V, 3) vertex positions in lattice space. tris: (F, 3) vertex indices.
    influence: (V,) per-vertex factor on the displacement (vertex-group weight * strength); default 1.
    dtype: float64 (exact to ~1e-15) or float32 (half the memory traffic; Blender stores float32).
    Returns a `Binding`. Open meshes are allowed (`is_closed` False); their volume is measured
    about the lattice centre. A closed mesh's islands are measured about their own bounding-box
    centres (the same volume, without the rounding of coordinates far from the lattice).

    For a `Cage` only: depth, the number of refinement levels (default 3; each level halves the
    cells, so the embedding approaches the limit region); outside, what vertices outside the
    region do: "FOLLOW" (move with the closest point of the region's boundary) or "STAY".
    Returns a `cage_binding.CageBinding` then, with the same methods.

    topology: a `Topology` of `tris` from an earlier bind (checked to match), so that binding the
    same mesh at new positions (it moved through the lattice) only re-embeds them. The layout of
    the result depends only on the arguments, never on an earlier binding.

    use_compiled: lay a lattice binding out with the compiled kernels once `compiled.load()`
    succeeded (the same arrays, bit for bit, in less time); False: NumPy, the reference.
    measured_in: for a closed mesh bound to a `Lattice` with its `topology`, a
    `volume.MeasuredIn`: the rest volume is then measured in the space of its points (the
    object's own, of which `rest_verts` are an affine image) and scaled into lattice space, or
    taken from its sums where they are known (a mesh that only moved); the bind fills them in.
    """
    if isinstance(lattice, Cage):
        if measured_in is not None:
            raise ValueError("measured_in applies to a Lattice only")
        return bind_cage(lattice, rest_verts, tris, influence, dtype, 3 if depth is None else depth,
                         outside, topology=topology)
    if not isinstance(lattice, Lattice):
        raise ValueError(f"bind needs a vpffd_addon.Lattice or Cage, got {type(lattice).__name__}")
    return bind_lattice(lattice, rest_verts, tris, influence, dtype, depth, topology, use_compiled, measured_in)
