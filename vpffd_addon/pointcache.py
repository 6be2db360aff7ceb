"""Point caches that Blender's Mesh Cache modifier reads: PC2 and MDD (NumPy only, no bpy).

Both hold F frames of V points as float32 (x, y, z), frame after frame:

* **PC2** (little-endian), a 32-byte header, then F x V x 3 float32::

      char[12] "POINTCACHE2\\0" | int32 version (1) | int32 points V | float32 start frame
      float32 sample rate (frames per sample) | int32 samples F

* **MDD** (big-endian), an 8-byte header, F float32 time stamps in seconds, then F x V x 3
  float32::

      int32 frames F | int32 points V | float32 times[F]

Blender's Mesh Cache modifier (``MOD_meshcache_pc2.cc``, ``MOD_meshcache_mdd.cc``) rejects a file
whose point count differs from the mesh's, or whose frame count is not positive; with Time Mode
*Frame* it reads frame index ``frame_scale * scene_frame - frame_start`` (clamped to the file), so
the header's start frame, sample rate and the MDD times only matter in its other time modes.

Writers are atomic: data goes to a temporary file in the destination folder, which replaces the
destination (``os.replace``) only once every frame is written and flushed. A failed or cancelled
write removes the temporary file, so nothing half-written ever carries the final name, and an
existing file under that name is left as it was. `PC2Writer` and `MDDWriter` stream frames one at
a time (a bake need not hold every frame in memory); `write_pc2` and `write_mdd` write an array.
"""
import os
import secrets

import numpy as np

__all__ = ["PC2Writer", "MDDWriter", "write_pc2", "read_pc2", "write_mdd", "read_mdd",
           "cache_info"]

PC2_MAGIC = b"POINTCACHE2\0"
PC2_VERSION = 1
_PC2_HEADER = np.dtype([("magic", "S12"), ("version", "<i4"), ("points", "<i4"),
                        ("start", "<f4"), ("rate", "<f4"), ("samples", "<i4")])
_MDD_HEADER = np.dtype([("frames", ">i4"), ("points", ">i4")])
_PC2_FLOAT = np.dtype("<f4")
_MDD_FLOAT = np.dtype(">f4")
_INT32_MAX = 2 ** 31 - 1
_F32_MAX = float(np.finfo(np.float32).max)


# ---------------------------------------------------------------------------------- validation

def _check_count(value, what):
    try:
        n = int(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be an integer, got {value!r}") from None
    if n != value or n < 1:
        raise ValueError(f"{what} must be an integer >= 1, got {value!r}")
    if n > _INT32_MAX:
        raise ValueError(f"{what} {n} does not fit the file format (at most {_INT32_MAX})")
    return n


def _check_real(value, what, positive=False):
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number, got {value!r}") from None
    if not np.isfinite(x) or abs(x) > _F32_MAX:
        raise ValueError(f"{what} must be a finite float32 number, got {value!r}")
    if positive and not x > 0.0:
        raise ValueError(f"{what} must be > 0, got {value!r}")
    return x


def _check_coords(coords, n_points, what="frame"):
    """`coords` as a C-contiguous (V, 3) float32 array, or ValueError naming the problem."""
    c = np.asarray(coords)
    if c.dtype.kind not in "fiub":
        raise ValueError(f"{what} must hold numbers, got dtype {c.dtype}")
    if c.shape != (n_points, 3):
        raise ValueError(f"{what} must have shape ({n_points}, 3), got {c.shape}")
    bad = ~np.isfinite(c).all(axis=1) if c.dtype.kind == "f" else np.zeros(len(c), bool)
    if bad.any():
        raise ValueError(f"{what} has non-finite coordinates at {int(bad.sum())} points "
                         f"(first: point {int(np.flatnonzero(bad)[0])})")
    big = (np.abs(c) > _F32_MAX).any(axis=1)
    if big.any():
        raise ValueError(f"{what} has coordinates beyond float32 range at {int(big.sum())} points")
    return np.ascontiguousarray(c, dtype=np.float32)


def _check_frames(frames):
    """`frames` as an (F, V, 3) array (F, V >= 1), or ValueError."""
    f = np.asarray(frames)
    if f.ndim != 3 or f.shape[2] != 3:
        raise ValueError(f"frames must have shape (F, V, 3), got {f.shape}")
    if f.shape[0] == 0:
        raise ValueError("frames is empty: a cache needs at least one frame")
    if f.shape[1] == 0:
        raise ValueError("frames has no points: a cache needs at least one point")
    return f


# ------------------------------------------------------------------------------- atomic writes

class _AtomicWriter:
    """Writes a file through a temporary sibling that replaces `path` on `commit()`."""

    _float = None  # dtype of the coordinates on disk

    def __init__(self, path, n_points, n_frames):
        self.path = os.path.abspath(os.fspath(path))
        self.n_points = _check_count(n_points, "point count")
        self.n_frames = _check_count(n_frames, "frame count")
        self.frames_written = 0
        folder, name = os.path.split(self.path)
        if not name:
            raise ValueError(f"{path!r} names a folder, not a file")
        if os.path.isdir(self.path):
            raise ValueError(f"{self.path} is a folder, not a file")
        if not os.path.isdir(folder):
            raise ValueError(f"folder {folder} does not exist")
        self._fh = None
        self.tmp_path = None
        for _ in range(100):
            tmp = os.path.join(folder, f".{name}.{secrets.token_hex(4)}.tmp")
            try:
                # Mode 0o666 filtered by the umask, like any ordinary new file.
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0),
                             0o666)
            except FileExistsError:
                continue
            self.tmp_path = tmp
            self._fh = os.fdopen(fd, "wb")
            break
        else:
            raise OSError(f"could not create a temporary file in {folder}")
        try:
            self._write_header()
        except BaseException:
            self.abort()
            raise

    @property
    def closed(self):
        return self._fh is None

    def _write_header(self):
        raise NotImplementedError

    def write_frame(self, coords):
        """Append one frame: `coords` (V, 3), any real dtype, stored as float32."""
        if self._fh is None:
            raise ValueError("the writer is closed")
        if self.frames_written >= self.n_frames:
            raise ValueError(f"all {self.n_frames} frames are already written")
        c = _check_coords(coords, self.n_points, f"frame {self.frames_written}")
        try:
            self._fh.write(c.astype(self._float, copy=False).tobytes())
        except BaseException:
            self.abort()
            raise
        self.frames_written += 1

    def commit(self):
        """Flush the complete file to disk and move it to `path` (replacing what was there).
        Returns `path`. Raises ValueError (and discards the file) if frames are missing."""
        if self._fh is None:
            raise ValueError("the writer is closed")
        if self.frames_written != self.n_frames:
            missing = self.n_frames - self.frames_written
            self.abort()
            raise ValueError(f"{missing} of {self.n_frames} frames were not written; "
                             "nothing was saved")
        try:
            self._fh.flush()
            os.fsync(self._fh.fileno())
            self._fh.close()
            self._fh = None
            os.replace(self.tmp_path, self.path)
            self.tmp_path = None
        except BaseException:
            self.abort()
            raise
        return self.path

    def abort(self):
        """Discard the temporary file; `path` is left as it was. Safe to call twice."""
        if self._fh is not None:
            try:
                self._fh.close()
            except OSError:
                pass
            self._fh = None
        if self.tmp_path is not None:
            try:
                os.remove(self.tmp_path)
            except FileNotFoundError:
                pass
            self.tmp_path = None

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.commit()
        else:
            self.abort()
        return False

    def __del__(self):  # a writer dropped without commit leaves no temporary file behind
        try:
            self.abort()
        except Exception:
            pass


class PC2Writer(_AtomicWriter):
    """Stream a PC2 file: ``with PC2Writer(path, V, F, start_frame, sample_rate) as w:
    w.write_frame(coords)`` F times. Leaving the block with an exception, or with frames missing,
    writes nothing under `path`."""

    _float = _PC2_FLOAT

    def __init__(self, path, n_points, n_frames, start_frame=0.0, sample_rate=1.0):
        self.start_frame = _check_real(start_frame, "start frame")
        self.sample_rate = _check_real(sample_rate, "sample rate", positive=True)
        super().__init__(path, n_points, n_frames)

    def _write_header(self):
        head = np.zeros((), _PC2_HEADER)
        head["magic"], head["version"], head["points"] = PC2_MAGIC, PC2_VERSION, self.n_points
        head["start"], head["rate"] = self.start_frame, self.sample_rate
        head["samples"] = self.n_frames
        self._fh.write(head.tobytes())


class MDDWriter(_AtomicWriter):
    """Stream an MDD file: ``with MDDWriter(path, V, times) as w: w.write_frame(coords)`` once per
    time stamp (`times`: (F,) seconds, non-decreasing)."""

    _float = _MDD_FLOAT

    def __init__(self, path, n_points, times):
        t = np.asarray(times, dtype=np.float64).ravel()
        if t.size == 0:
            raise ValueError("times is empty: a cache needs at least one frame")
        if not np.isfinite(t).all() or (np.abs(t) > _F32_MAX).any():
            raise ValueError("times must be finite float32 numbers")
        if (np.diff(t) < 0).any():
            raise ValueError("times must not decrease")
        self.times = t.astype(np.float32)
        super().__init__(path, n_points, t.size)

    def _write_header(self):
        head = np.zeros((), _MDD_HEADER)
        head["frames"], head["points"] = self.n_frames, self.n_points
        self._fh.write(head.tobytes())
        self._fh.write(self.times.astype(_MDD_FLOAT).tobytes())


# ------------------------------------------------------------------------------- whole arrays

def write_pc2(path, frames, start_frame=0.0, sample_rate=1.0):
    """Write `frames` (F, V, 3) to the PC2 file `path`, atomically. Returns the absolute path.

    `start_frame` and `sample_rate` (frames per sample, > 0) go in the header. Raises ValueError
    for an empty array, a wrong shape, or non-finite coordinates (before anything is written)."""
    f = _check_frames(frames)
    coords = [_check_coords(f[i], f.shape[1], f"frame {i}") for i in range(f.shape[0])]
    with PC2Writer(path, f.shape[1], f.shape[0], start_frame, sample_rate) as w:
        for c in coords:
            w.write_frame(c)
    return w.path


def write_mdd(path, frames, fps, start_frame=0.0):
    """Write `frames` (F, V, 3) to the MDD file `path`, atomically. Returns the absolute path.

    Frame i is stamped ``(start_frame + i) / fps`` seconds (`fps` > 0). Raises ValueError as
    `write_pc2` does."""
    f = _check_frames(frames)
    fps = _check_real(fps, "fps", positive=True)
    start = _check_real(start_frame, "start frame")
    coords = [_check_coords(f[i], f.shape[1], f"frame {i}") for i in range(f.shape[0])]
    times = (start + np.arange(f.shape[0], dtype=np.float64)) / fps
    with MDDWriter(path, f.shape[1], times) as w:
        for c in coords:
            w.write_frame(c)
    return w.path


# ------------------------------------------------------------------------------------- reading

def _read_exact(fh, n, path, what):
    data = fh.read(n)
    if len(data) != n:
        raise ValueError(f"{path}: file ends inside the {what} ({len(data)} of {n} bytes)")
    return data


def _pc2_header(fh, path, size):
    raw = _read_exact(fh, _PC2_HEADER.itemsize, path, "PC2 header")
    head = np.frombuffer(raw, _PC2_HEADER)[0]
    if raw[:12] != PC2_MAGIC:
        raise ValueError(f"{path} is not a PC2 file (no 'POINTCACHE2' header)")
    points, samples = int(head["points"]), int(head["samples"])
    if points < 1 or samples < 1:
        raise ValueError(f"{path}: PC2 header holds {points} points and {samples} samples "
                         "(both must be >= 1)")
    expected = _PC2_HEADER.itemsize + 12 * points * samples
    if size != expected:
        raise ValueError(f"{path}: PC2 file is {size} bytes; its header ({samples} samples of "
                         f"{points} points) needs {expected}")
    return points, samples, float(head["start"]), float(head["rate"])


def _mdd_header(fh, path, size):
    raw = _read_exact(fh, _MDD_HEADER.itemsize, path, "MDD header")
    head = np.frombuffer(raw, _MDD_HEADER)[0]
    frames, points = int(head["frames"]), int(head["points"])
    if frames < 1 or points < 1:
        raise ValueError(f"{path}: MDD header holds {frames} frames and {points} points "
                         "(both must be >= 1); is it an MDD file?")
    expected = _MDD_HEADER.itemsize + 4 * frames + 12 * points * frames
    if size != expected:
        raise ValueError(f"{path}: MDD file is {size} bytes; its header ({frames} frames of "
                         f"{points} points) needs {expected}")
    return frames, points


def _read_coords(fh, dtype, frames, points, path):
    n = frames * points * 3
    data = np.frombuffer(_read_exact(fh, 4 * n, path, "coordinates"), dtype)
    return data.astype(np.float32).reshape(frames, points, 3)


def read_pc2(path):
    """Read a PC2 file: ``(frames (F, V, 3) float32, start_frame, sample_rate)``.
    Raises ValueError when the file is not a complete PC2 file."""
    path = os.fspath(path)
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        points, samples, start, rate = _pc2_header(fh, path, size)
        frames = _read_coords(fh, _PC2_FLOAT, samples, points, path)
    return frames, start, rate


def read_mdd(path):
    """Read an MDD file: ``(frames (F, V, 3) float32, times (F,) float32 seconds)``.
    Raises ValueError when the file is not a complete MDD file."""
    path = os.fspath(path)
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        frames, points = _mdd_header(fh, path, size)
        times = np.frombuffer(_read_exact(fh, 4 * frames, path, "MDD times"), _MDD_FLOAT)
        coords = _read_coords(fh, _MDD_FLOAT, frames, points, path)
    return coords, times.astype(np.float32)


def cache_info(path, fmt):
    """Header of an existing cache without reading its coordinates: ``{'format', 'frames',
    'points'}`` plus ``start_frame`` and ``sample_rate`` for PC2, ``start_time`` (seconds, first
    frame) for MDD. `fmt` is 'PC2' or 'MDD'. Raises ValueError when `path` is not a complete file
    of that format (e.g. before overwriting it), OSError when it cannot be read."""
    fmt = str(fmt).upper()
    if fmt not in ("PC2", "MDD"):
        raise ValueError(f"unknown cache format {fmt!r}; expected 'PC2' or 'MDD'")
    path = os.fspath(path)
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        if fmt == "PC2":
            points, samples, start, rate = _pc2_header(fh, path, size)
            return {"format": "PC2", "frames": samples, "points": points,
                    "start_frame": start, "sample_rate": rate}
        frames, points = _mdd_header(fh, path, size)
        start_time = float(np.frombuffer(_read_exact(fh, 4, path, "MDD times"), _MDD_FLOAT)[0])
        return {"format": "MDD", "frames": frames, "points": points, "start_time": start_time}
