"""vpffd_addon.pointcache (NumPy only): PC2 and MDD files as Blender's Mesh Cache modifier reads
them, validation, and atomic writes."""
import os
import struct

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vpffd_addon import pointcache as pc

pytestmark = pytest.mark.core


def _frames(rng, F=3, V=7):
    return rng.normal(0.0, 2.0, (F, V, 3))


def test_pc2_layout_and_round_trip(tmp_path):
    frames = _frames(np.random.default_rng(1))
    path = tmp_path / "a.pc2"
    assert pc.write_pc2(path, frames, start_frame=12, sample_rate=0.5) == str(path)
    raw = path.read_bytes()
    assert len(raw) == 32 + 3 * 7 * 12
    assert struct.unpack("<12siiffi", raw[:32]) == (b"POINTCACHE2\0", 1, 7, 12.0, 0.5, 3)
    np.testing.assert_array_equal(np.frombuffer(raw[32:], "<f4").reshape(3, 7, 3),
                                  frames.astype(np.float32))
    back, start, rate = pc.read_pc2(path)
    assert back.dtype == np.float32 and (start, rate) == (12.0, 0.5)
    np.testing.assert_array_equal(back, frames.astype(np.float32))
    assert pc.cache_info(path, "pc2") == {"format": "PC2", "frames": 3, "points": 7,
                                          "start_frame": 12.0, "sample_rate": 0.5}


def test_mdd_layout_and_round_trip(tmp_path):
    frames = _frames(np.random.default_rng(2), F=4, V=5)
    path = tmp_path / "a.mdd"
    pc.write_mdd(path, frames, fps=24, start_frame=6)
    raw = path.read_bytes()
    assert len(raw) == 8 + 4 * 4 + 4 * 5 * 12
    assert struct.unpack(">ii", raw[:8]) == (4, 5)
    times = np.frombuffer(raw[8:24], ">f4")
    np.testing.assert_array_equal(times, (np.arange(6, 10) / 24).astype(np.float32))
    np.testing.assert_array_equal(np.frombuffer(raw[24:], ">f4").reshape(4, 5, 3),
                                  frames.astype(np.float32))
    back, t = pc.read_mdd(path)
    np.testing.assert_array_equal(back, frames.astype(np.float32))
    np.testing.assert_array_equal(t, times)
    info = pc.cache_info(path, "MDD")
    assert (info["frames"], info["points"]) == (4, 5) and info["start_time"] == np.float32(0.25)


@settings(max_examples=25, deadline=None)
@given(F=st.integers(1, 4), V=st.integers(1, 30), seed=st.integers(0, 2 ** 31))
def test_round_trip_is_exact_for_float32(tmp_path_factory, F, V, seed):
    frames = np.random.default_rng(seed).normal(0, 100, (F, V, 3)).astype(np.float32)
    d = tmp_path_factory.mktemp("rt")
    pc.write_pc2(d / "x.pc2", frames)
    pc.write_mdd(d / "x.mdd", frames, 30.0)
    assert np.array_equal(pc.read_pc2(d / "x.pc2")[0], frames)
    assert np.array_equal(pc.read_mdd(d / "x.mdd")[0], frames)


@pytest.mark.parametrize("bad, match", [
    (np.zeros((0, 4, 3)), "empty"),
    (np.zeros((2, 0, 3)), "no points"),
    (np.zeros((2, 4)), r"shape \(F, V, 3\)"),
    (np.zeros((2, 4, 2)), r"shape \(F, V, 3\)"),
    (np.array([[[0, 0, np.nan]]]), "non-finite"),
    (np.array([[[0, np.inf, 0]]]), "non-finite"),
    (np.array([[[1e39, 0, 0]]]), "float32 range"),
    (np.array([[["a", "b", "c"]]]), "numbers"),
])
def test_bad_frames_are_refused_before_anything_is_written(tmp_path, bad, match):
    for write in (lambda p: pc.write_pc2(p, bad), lambda p: pc.write_mdd(p, bad, 24)):
        with pytest.raises(ValueError, match=match):
            write(tmp_path / "x.cache")
    assert os.listdir(tmp_path) == []


def test_bad_header_values_are_refused(tmp_path):
    f = np.zeros((1, 2, 3))
    for kw, match in (({"sample_rate": 0}, "sample rate"), ({"sample_rate": np.nan}, "sample rate"),
                      ({"start_frame": np.inf}, "start frame")):
        with pytest.raises(ValueError, match=match):
            pc.write_pc2(tmp_path / "x.pc2", f, **kw)
    for fps in (0, -24, np.nan):
        with pytest.raises(ValueError, match="fps"):
            pc.write_mdd(tmp_path / "x.mdd", f, fps)
    with pytest.raises(ValueError, match="does not exist"):
        pc.write_pc2(tmp_path / "nowhere" / "x.pc2", f)
    with pytest.raises(ValueError, match="folder"):
        pc.write_pc2(tmp_path, f)
    assert os.listdir(tmp_path) == []


def test_interrupted_writes_leave_the_old_file_untouched(tmp_path):
    path = tmp_path / "a.pc2"
    pc.write_pc2(path, np.ones((2, 3, 3)))
    before = path.read_bytes()

    with pytest.raises(RuntimeError):
        with pc.PC2Writer(path, 3, 5) as w:
            w.write_frame(np.zeros((3, 3)))
            raise RuntimeError("cancelled")
    w2 = pc.MDDWriter(tmp_path / "a.mdd", 3, [0.0, 1.0])
    w2.write_frame(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="1 of 2 frames were not written"):
        w2.commit()
    w3 = pc.PC2Writer(path, 3, 2)
    w3.write_frame(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        w3.write_frame(np.full((3, 3), np.nan))
    w3.abort()
    w3.abort()
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["a.pc2"], "no temporary files are left"

    with pc.PC2Writer(path, 3, 1, start_frame=4) as w:
        w.write_frame(np.full((3, 3), 2.0))
        with pytest.raises(ValueError, match="already written"):
            w.write_frame(np.zeros((3, 3)))
    frames, start, _ = pc.read_pc2(path)
    assert start == 4.0 and frames.shape == (1, 3, 3) and (frames == 2).all()
    assert sorted(os.listdir(tmp_path)) == ["a.pc2"]


def test_broken_files_are_reported(tmp_path):
    good = tmp_path / "good.pc2"
    pc.write_pc2(good, np.ones((2, 3, 3)))
    raw = good.read_bytes()
    cases = {
        "short.pc2": (raw[:20], "ends inside the PC2 header"),
        "truncated.pc2": (raw[:-4], "needs"),
        "magic.pc2": (b"POINTCACHE3\0" + raw[12:], "not a PC2 file"),
        "text.pc2": (b"hello, this is certainly not a point cache file", "not a PC2 file"),
    }
    for name, (data, match) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(ValueError, match=match):
            pc.read_pc2(tmp_path / name)
        with pytest.raises(ValueError):
            pc.cache_info(tmp_path / name, "PC2")
    with pytest.raises(ValueError):
        pc.read_mdd(good)                      # a PC2 file is not an MDD file
    with pytest.raises(ValueError, match="unknown cache format"):
        pc.cache_info(good, "OBJ")
