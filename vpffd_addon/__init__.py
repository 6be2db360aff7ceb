"""VP-FFD core: Blender-exact lattice deformation with exact volume preservation (NumPy only).

    import vpffd_addon as vp
    lat = vp.Lattice((4, 4, 4), interpolation="BSPLINE", bounds=((-1,) * 3, (1,) * 3))
    b = vp.bind(lat, verts, tris)          # verts (V, 3) in lattice space, tris (F, 3)
    sol = b.solve(points, axes="XY")       # points (N, 3): the moved lattice
    sol.verts, sol.volume, sol.plain_volume

Method: Hahmann et al., "Volume Preserving FFD for Programmable Graphics Hardware" (2011).
"""
from . import compiled, outside
from .bases import INTERPOLATIONS
from .binder import bind
from .binding import Binding
from .cage import Cage, box_cage, extrude
from .cage_binding import CageBinding
from .fit import fit_lattice
from .frame import FrameInputs, FrameResult, Pipeline
from .jacobian import jacobian_det
from .mesh import Topology
from .outside import outside_factor
from .lattice import Lattice
from .pointcache import read_mdd, read_pc2, write_mdd, write_pc2
from .shapes import box, icosphere
from .solve import Solution
from .volume import signed_volume

__all__ = ["INTERPOLATIONS", "OUTSIDE_MODES", "Binding", "Cage", "CageBinding", "FrameInputs", "FrameResult", "Lattice", "Pipeline", "Solution", "Topology", "bind", "box", "box_cage", "extrude", "icosphere",
           "jacobian_det", "outside_factor", "read_mdd", "read_pc2", "signed_volume", "write_mdd", "write_pc2"]
#: The names of the lattice's Outside modes (`outside.MODES` is the table).
OUTSIDE_MODES = outside.names("lattice")
__version__ = "0.1.0"
