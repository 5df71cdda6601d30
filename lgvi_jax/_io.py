"""Atomic file writes that respect the user's umask.

Every result file of the library and the command line goes through :func:`atomic_write`:
the content is written to a temporary file in the destination folder and renamed over the
destination, so an interrupted run never leaves a truncated file behind. The temporary file
of :func:`tempfile.mkstemp` is created with mode ``0o600``; before the rename it gets the
mode an ordinary ``open(path, "w")`` would have given, ``0o666 & ~umask``, so that a
colleague or a web server can read the results wherever the user's umask allows it.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

__all__ = [
    "TEMP_SUFFIX",
    "atomic_open",
    "atomic_write",
    "atomic_write_bytes",
    "atomic_write_json",
    "atomic_write_text",
    "current_umask",
    "default_file_mode",
    "read_npz",
    "save_npz_atomic",
]

#: Suffix of the temporary files (``.<name>.<random>.tmp``): a crash can leave one behind,
#: and a sweep's ``--resume`` removes them.
TEMP_SUFFIX = ".tmp"

_UMASK_LOCK = threading.Lock()


def current_umask() -> int:
    """The process's umask. POSIX can only read it by setting it; the set-and-restore is
    done under a lock (threads of this module cannot interleave) and takes microseconds.
    On Linux, ``/proc/self/status`` gives it without touching it, and is preferred."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _UMASK_LOCK:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def default_file_mode() -> int:
    """The mode ``open(path, "w")`` gives a new file: ``0o666 & ~umask``."""
    return 0o666 & ~current_umask()


@contextlib.contextmanager
def atomic_open(path: Path | str, mode: str = "w", **kwargs: Any) -> Iterator[IO]:
    """``with atomic_open(path, "w") as fh: ...``: write a temporary file beside ``path``
    and rename it over ``path`` when the block ends without an exception (the temporary
    file is removed otherwise). The file ends with mode ``0o666 & ~umask``; the folder is
    created if needed. ``mode`` is ``"w"`` or ``"wb"``; ``kwargs`` go to :func:`os.fdopen`
    (e.g. ``newline=""``)."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_open: mode must be 'w' or 'wb', got {mode!r}")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=TEMP_SUFFIX)
    try:
        with os.fdopen(fd, mode, **kwargs) as fh:
            yield fh
            fh.flush()
            os.fchmod(fh.fileno(), default_file_mode())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write(path: Path | str, write: Callable[[IO[bytes]], Any]) -> None:
    """Call ``write(fh)`` on a binary file handle and move the result to ``path``
    atomically (see :func:`atomic_open`)."""
    with atomic_open(path, "wb") as fh:
        write(fh)


def atomic_write_bytes(path: Path | str, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically, mode ``0o666 & ~umask``."""
    atomic_write(path, lambda fh: fh.write(data))


def atomic_write_text(path: Path | str, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically, mode ``0o666 & ~umask``."""
    atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: Path | str, obj: Any, *, indent: int = 1) -> None:
    """Write ``obj`` as JSON (and a final newline) to ``path`` atomically."""
    atomic_write_text(path, json.dumps(obj, indent=indent) + "\n")


def save_npz_atomic(path: Path | str, arrays: dict[str, Any]) -> None:
    """``numpy.savez`` of ``arrays`` to ``path`` atomically, mode ``0o666 & ~umask``."""
    import numpy as np

    atomic_write(path, lambda fh: np.savez(fh, **arrays))


def read_npz(path: Path | str) -> dict[str, Any]:
    """Every array of the ``.npz`` file ``path``, read in full (so a truncated or corrupt
    member is found now, not on first use). Raises ``ValueError`` with a one-line reason
    that does not repeat the path (the caller names the file): not an ``.npz`` archive,
    truncated or corrupt, or holding pickled objects. ``OSError`` (no such file,
    permission) propagates."""
    import zipfile
    import zlib

    import numpy as np

    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(6)
    if head.startswith(b"\x93NUMPY"):
        raise ValueError("is a single .npy array, not an .npz archive")
    if not head.startswith(b"PK"):
        kind = "empty" if not head else "not an .npz archive (not a zip file)"
        raise ValueError(f"is {kind}")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except zipfile.BadZipFile as err:
        raise ValueError(f"is truncated or corrupt ({err})") from None
    except ValueError as err:
        if "pickle" in str(err):
            raise ValueError("holds Python objects (pickled data), not numeric arrays") from None
        raise ValueError(f"is corrupt ({err})") from None
    except (EOFError, zlib.error, KeyError, NotImplementedError) as err:
        raise ValueError(f"is truncated or corrupt ({type(err).__name__}: {err})") from None
