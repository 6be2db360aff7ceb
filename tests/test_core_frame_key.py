"""The change key (`vpffd_addon/frame_key.py`): made from FrameInputs' own fields, so changing any
field, one added later included, changes the key; the same values in new arrays (the next update's
reads) keep it, so an unchanged frame is not solved again."""
import dataclasses

import numpy as np
import pytest

import vpffd_addon as vp
from vpffd_addon.arrays import BLOCK, same_array
from vpffd_addon.frame_key import FrameKey

pytestmark = pytest.mark.core


def _inputs():
    """FrameInputs with every optional field set (arrays where a field takes one)."""
    lat = vp.Lattice((3, 3, 3), bounds=((-1,) * 3, (1,) * 3))
    v, t = vp.icosphere(2, 0.8)
    n = len(lat.rest_points)
    rng = np.random.default_rng(0)
    return vp.FrameInputs(
        positions=v, tris=t, lattice=lat, points=lat.rest_points * 0.9, matrix=np.eye(4),
        weights=rng.random(len(v)), lattice_weights=rng.random(n), strength=0.8, correct=True,
        axes="XY", directions=np.eye(3)[:2], volume_scale=1.1, mobility=rng.random(n),
        pins=[(3, np.array([0.1, 0.2, 0.3]))], islands=True, cage_depth=2, cage_outside="STAY",
        dtype=np.float32, backend="CPU", outside="FALLOFF", falloff=0.4,
        target_volumes=np.array([2.0]))


def _changed(name, value):
    """Another value for field `name`: the last element of an array changed (a difference the
    first block of a comparison does not see), another number, string, type or model."""
    if isinstance(value, np.ndarray):
        out = value.copy()
        out.reshape(-1)[-1] += 1
        return out
    if isinstance(value, bool):
        return not value
    if isinstance(value, (int, float)):
        return value + 1
    if isinstance(value, str):
        return value + "Z"
    if value is np.float32:
        return np.float64
    if isinstance(value, vp.Lattice):
        return vp.Lattice(value.shape, bounds=(value.lo, value.hi + 0.5))
    if isinstance(value, list):
        return [(k, p + 1) for k, p in value]
    raise AssertionError(f"FrameInputs.{name}: no changed value known for a {type(value).__name__} "
                         "(add one here so that the new field's change is checked)")


def _fresh(value):
    """The same value as a new object (as the next update reads it from Blender)."""
    if isinstance(value, np.ndarray):
        return value.copy()
    if isinstance(value, list):
        return [(k, p.copy()) for k, p in value]
    if isinstance(value, vp.Lattice):
        return vp.Lattice(value.shape, value.interpolation, bounds=(value.lo.copy(), value.hi.copy()))
    return value


@pytest.mark.parametrize("name", [f.name for f in dataclasses.fields(vp.FrameInputs)])
def test_changing_any_field_changes_the_key(name):
    base = _inputs()
    key = FrameKey(base)
    value = getattr(base, name)
    assert value is not None, f"_inputs() leaves {name} unset: set it so its change is checked"
    assert key.matches(FrameKey(dataclasses.replace(base, **{name: _fresh(value)})))
    changed = FrameKey(dataclasses.replace(base, **{name: _changed(name, value)}))
    assert not key.matches(changed) and not changed.matches(key)
    if name not in ("positions", "tris", "lattice", "points", "matrix"):    # required fields
        unset = FrameKey(dataclasses.replace(base, **{name: None}))
        assert not key.matches(unset)


def test_extra_values_and_a_cage_by_identity():
    base = _inputs()
    assert FrameKey(base, ("CPU",)).matches(FrameKey(base, ("CPU",)))
    assert not FrameKey(base, ("CPU",)).matches(FrameKey(base, ("GPU",)))
    cage = vp.box_cage((1, 1, 1))
    other = vp.box_cage((1, 1, 1))
    with_cage = dataclasses.replace(base, lattice=cage, points=cage.rest_points)
    assert FrameKey(with_cage).matches(FrameKey(dataclasses.replace(with_cage)))
    assert not FrameKey(with_cage).matches(FrameKey(dataclasses.replace(with_cage, lattice=other)))


def test_same_array_finds_a_difference_in_any_block_and_in_shape_or_type():
    a = np.arange(3 * BLOCK + 5, dtype=np.float32)
    assert same_array(a, a.copy())
    for where in (0, BLOCK - 1, BLOCK, 2 * BLOCK + 7, len(a) - 1):
        b = a.copy()
        b[where] = -1
        assert not same_array(a, b), where
    assert not same_array(a, a.astype(np.float64))
    assert not same_array(a[:-1], a[1:])
    assert not same_array(a.reshape(-1, 1)[:9], a[:9])
    nan = np.array([np.nan])
    assert not same_array(nan, nan.copy())        # NaN never matches: such a frame solves again
