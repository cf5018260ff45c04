"""Atomic file writes: a reader (or an interrupted run) never sees a half-written result.

Every result, dataset, checkpoint side file and figure the package writes goes through
`atomic_path`: the bytes land in a temporary file in the target's folder, which `os.replace`
then moves onto the target in one step.
"""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path


def _umask() -> int:
    """The process's file-creation mask (reading it means setting it; restored at once)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str = ""):
    """Yield a temporary path in `path`'s folder; on success move it onto `path` (os.replace).

    Readers never see a half-written file; on error the temporary file is removed. The file
    gets the permissions a plain `open` would give it (0o666 less the umask), not mkstemp's
    private 0o600, so results stay readable by the other users of a shared machine.
    """
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=suffix, dir=folder)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write `text` to `path` atomically (see `atomic_path`); returns the path."""
    with atomic_path(path, suffix=Path(path).suffix) as tmp:
        Path(tmp).write_text(text)
    return Path(path)


def write_bytes_atomic(path: str | os.PathLike, payload: bytes) -> Path:
    """Write `payload` to `path` atomically (see `atomic_path`); returns the path."""
    with atomic_path(path, suffix=Path(path).suffix) as tmp:
        Path(tmp).write_bytes(payload)
    return Path(path)
