"""The correction's settings in lattice space, where the solve works: the directions it may move
along and where pinned vertices go. World-space choices (World axes, a pin Empty's motion) become
lattice-space ones here; the Blender layer only reads the matrices."""
import numpy as np

from .linalg3 import affine, affine_inverse, inv3, matmul4


def directions(axes, space, lattice_matrix):
    """(axes string, directions (m, 3) float64 or None) for the solve: `axes` ("XYZ", ..., or
    "NONE") along the lattice's own axes (`space` "LATTICE") or the world's ("WORLD");
    lattice_matrix: (4, 4) the lattice object's world matrix."""
    if axes == "NONE":
        return "", None
    if space == "LATTICE":
        return axes, None
    # A world displacement e is inv(M3) e in lattice space (not unit length under scale: the
    # solver normalises; the volume is exact along any direction).
    inv = inv3(np.asarray(lattice_matrix, np.float64)[:3, :3])
    world = np.eye(3)[["XYZ".index(c) for c in axes]]
    return "", world @ inv.T


def pin_targets(pins, positions, lattice_matrix, target_matrix, target_rest, mesh_rest):
    """[(vertex, target (3,) in lattice space)] for the pinned vertices `pins` (k,) int, following
    the pin Empty: the Empty's motion since Bind carries each pinned vertex from where it reaches
    the slot. positions: (V, 3) what reaches the slot (object space); matrices (4, 4): the lattice
    object's world matrix now, the Empty's now and at Bind, the mesh object's at Bind."""
    pins = np.asarray(pins, np.int64)
    if len(pins) == 0:
        return []
    carry = matmul4(affine_inverse(np.asarray(lattice_matrix, np.float64)),
                    np.asarray(target_matrix, np.float64),
                    affine_inverse(np.asarray(target_rest, np.float64).reshape(4, 4)),
                    np.asarray(mesh_rest, np.float64).reshape(4, 4))
    targets = affine(np.asarray(positions)[pins].astype(np.float64), carry)
    return list(zip(pins.tolist(), targets))
