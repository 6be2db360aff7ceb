"""Whether two arrays hold the same values, as cheaply as it can be told: what a frame's change
key (`frame_key.py`) and the pipeline's kept measurements (`frame.py`) compare their inputs by."""
import numpy as np

#: Elements compared at a time: a change is usually found in the first block, and a block's
#: comparison allocates no more than this many booleans.
BLOCK = 1 << 16
#: About how many elements, evenly spaced, are compared before the blocks: a mesh that deforms
#: differs in most of its positions, but not always in the first block (an Armature that bends
#: only the top of a mesh numbered from the bottom).
SAMPLES = 512


def same_array(a, b):
    """Whether arrays `a` and `b` hold the same values (same shape and dtype; NaN never equals):
    identity first, then shapes, then about `SAMPLES` elements spread over them, then the content
    block by block, stopping at a difference."""
    if a is b:
        return True
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    fa, fb = a.reshape(-1), b.reshape(-1)
    step = max(1, fa.size // SAMPLES)
    if step > 1 and not np.array_equal(fa[::step], fb[::step]):
        return False
    for start in range(0, fa.size, BLOCK):
        if not np.array_equal(fa[start:start + BLOCK], fb[start:start + BLOCK]):
            return False
    return True
