"""What a frame's result depends on, as one key made from `FrameInputs`' own fields: two frames
with matching keys give the same result, so a caller may keep the result it shows instead of
evaluating again (docs/architecture.md, "A new setting").

The key is made from `dataclasses.fields(FrameInputs)`, so a field added to `FrameInputs` is in it
without further ado. Values are kept, not copied (FrameInputs' arrays are not changed once made):
arrays are compared by content, numbers and strings by value, a `Lattice` by what the core uses of
it (shape, interpolation, rest box), a `Cage` (large; the caller keeps one per rest state) and any
other object by identity. `matches` answers "changed or not" as cheaply as it can: everything but
the arrays first, then the arrays from the smallest (the lattice's points: what changes when only
the lattice moves) to the largest, each by identity, then shape and type, then a sample of the
content, then the content in blocks, stopping at the first difference (`arrays.same_array`).
"""
import dataclasses

import numpy as np

from .arrays import same_array
from .frame import FrameInputs
from .lattice import Lattice


class _Same:
    """An object compared by identity (it is kept, so its id is not reused while compared)."""
    __slots__ = ("obj",)

    def __init__(self, obj):
        self.obj = obj

    def __eq__(self, other):
        return isinstance(other, _Same) and other.obj is self.obj

    __hash__ = None


def _token(value, arrays):
    """A comparable stand-in for `value`; arrays go to `arrays` (compared apart, by content) and
    are stood in for by their place there."""
    if value is None or isinstance(value, (bool, int, float, str, np.generic)):
        return value
    if isinstance(value, np.ndarray):
        arrays.append(value)
        return ("array", len(arrays) - 1)
    if isinstance(value, (list, tuple)):
        return tuple(_token(v, arrays) for v in value)
    if isinstance(value, Lattice):
        return ("Lattice", value.shape, value.interpolation, value.lo.tobytes(), value.hi.tobytes())
    if isinstance(value, (type, np.dtype)):
        return ("dtype", np.dtype(value).str)
    return _Same(value)


class FrameKey:
    """The key of one `FrameInputs` (and of `extra`: values outside the core that change what the
    caller shows, e.g. where the solve runs). `a.matches(b)`: the same inputs."""
    __slots__ = ("values", "arrays")

    def __init__(self, inputs, extra=()):
        arrays = []
        self.values = tuple(_token(getattr(inputs, f.name), arrays)
                            for f in dataclasses.fields(FrameInputs)) + (_token(tuple(extra), arrays),)
        self.arrays = arrays

    def matches(self, other):
        """Whether `other` (a FrameKey) was made from the same inputs."""
        if other is None or self.values != other.values:
            return False            # the arrays' places differ too when their number does
        pairs = sorted(zip(self.arrays, other.arrays), key=lambda ab: ab[0].size)
        return all(same_array(a, b) for a, b in pairs)
