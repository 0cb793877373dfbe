"""Deterministic, atomic ``.npz`` files: same arrays -> same bytes, and never a half-written file.

``numpy.savez`` stamps each member with the current time, so two runs with the same seed would give
different bytes. We write the zip ourselves with a fixed timestamp, into a temporary file that is
renamed over the target only when complete; large arrays go to the file in slices, never copied whole.
"""
from __future__ import annotations

import contextlib
import io
import os
import tempfile
import zipfile

import numpy as np

from .errors import BodySchemaInputError

_EPOCH = (1980, 1, 1, 0, 0, 0)
STREAM_BYTES = 1 << 24  # arrays larger than this are written in slices of this size


@contextlib.contextmanager
def atomic_writer(path: str):
    """A binary file on a temp name in ``path``'s folder, renamed over ``path`` when the block completes (removed if
    it raises), so ``path`` is never half-written."""
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=os.path.basename(path))
    try:
        with os.fdopen(fd, "wb") as fh:
            yield fh
        os.chmod(tmp, default_file_mode())  # mkstemp makes 0600; a data file is readable like open() makes it
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str, payload: bytes) -> None:
    """Write ``payload`` to ``path`` via a temp file in the same folder and ``os.replace``."""
    with atomic_writer(path) as fh:
        fh.write(payload)


def default_file_mode() -> int:
    """The mode ``open()`` gives a new file under the process's umask (0644 under the usual 022), for files first
    written to a ``mkstemp`` name (0600: another user, e.g. a controller's, could not read them)."""
    return 0o666 & ~_umask()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _write_member(archive: zipfile.ZipFile, info: zipfile.ZipInfo, array: np.ndarray) -> None:
    """``array`` as ``numpy.save`` writes it; a large plain array in slices of ``STREAM_BYTES`` straight from its
    memory (never a whole copy), the bytes ``numpy.lib.format.write_array`` gives."""
    if array.nbytes <= STREAM_BYTES or array.dtype.hasobject or array.dtype.kind in "USV" \
            or not array.flags.c_contiguous:
        member = io.BytesIO()
        np.lib.format.write_array(member, array, allow_pickle=False)
        archive.writestr(info, member.getvalue())
        return
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, np.lib.format.header_data_from_array_1_0(array))
    raw = array.reshape(-1).view(np.uint8)
    info.file_size = header.tell() + raw.size  # as writestr sets it: the same local header, zip64 when needed
    with archive.open(info, mode="w") as dest:
        dest.write(header.getvalue())
        for start in range(0, raw.size, STREAM_BYTES):
            dest.write(raw[start:start + STREAM_BYTES])


def save_npz(path: str, **arrays) -> None:
    """Save arrays (numeric, bool, or strings) as an uncompressed, byte-deterministic npz, written to a temp file
    member by member (no copy of the whole archive in memory) and renamed over ``path``."""
    with atomic_writer(path) as fh, zipfile.ZipFile(fh, "w", compression=zipfile.ZIP_STORED) as archive:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_EPOCH)
            info.external_attr = 0o644 << 16
            _write_member(archive, info, np.asarray(arrays[name]))


def load_npz(path: str, required: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Load an npz without pickles; refuse a missing file, a broken file or missing arrays clearly."""
    if not os.path.isfile(path):
        raise BodySchemaInputError(f"file {path!r} does not exist")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except Exception as err:
        raise BodySchemaInputError(f"file {path!r} is not a readable .npz archive ({err})") from None
    missing = [name for name in required if name not in arrays]
    if missing:
        raise BodySchemaInputError(f"file {path!r} lacks arrays {missing}; it has {sorted(arrays)}")
    return arrays
