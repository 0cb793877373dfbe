"""Deterministic, atomic ``.npz`` files: same arrays -> same bytes, and never a half-written file.

``numpy.savez`` stamps each member with the current time, so two runs with the same seed would give
different bytes. We write the zip ourselves with a fixed timestamp, into a temporary file that is
renamed over the target only when complete.
"""
from __future__ import annotations

import io
import os
import tempfile
import zipfile

import numpy as np

from .errors import BodySchemaInputError

_EPOCH = (1980, 1, 1, 0, 0, 0)


def atomic_write_bytes(path: str, payload: bytes) -> None:
    """Write ``payload`` to ``path`` via a temp file in the same folder and ``os.replace``."""
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=os.path.basename(path))
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; a data file is readable like open() makes it
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def save_npz(path: str, **arrays) -> None:
    """Save arrays (numeric, bool, or strings) as an uncompressed, byte-deterministic npz."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_STORED) as archive:
        for name in sorted(arrays):
            member = io.BytesIO()
            np.lib.format.write_array(member, np.asarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_EPOCH)
            info.external_attr = 0o644 << 16
            archive.writestr(info, member.getvalue())
    atomic_write_bytes(path, buffer.getvalue())


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
