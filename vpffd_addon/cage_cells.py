"""A cage's cells as a flat list of ints, the form they are saved in (a mesh's custom property
holds them: operators/cage.py): [n_cells, n_faces, n, v..., n, v..., ...], each cell its faces,
each face its loop of point indices."""


def encode_cells(cells):
    """Cells (tuples of face loops) -> flat list of ints (see the module's words)."""
    out = [len(cells)]
    for faces in cells:
        out.append(len(faces))
        for f in faces:
            out.append(len(f))
            out.extend(int(v) for v in f)
    return out


def decode_cells(flat):
    """Inverse of `encode_cells`: a list of tuples of face loops; raises ValueError on a damaged
    list."""
    flat = [int(x) for x in flat]
    try:
        cells, k = [], 1
        for _ in range(flat[0]):
            n_faces, k = flat[k], k + 1
            faces = []
            for _ in range(n_faces):
                n, k = flat[k], k + 1
                faces.append(tuple(flat[k:k + n]))
                if len(faces[-1]) != n:
                    raise IndexError
                k += n
            cells.append(tuple(faces))
    except IndexError:
        raise ValueError("the cage's cell list is damaged") from None
    return cells
