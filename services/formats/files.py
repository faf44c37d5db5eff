"""Writing output files atomically, with one clear error naming the file when the disk says no.

Every writer of the project's files goes through :func:`atomic_output`: the content
is written to a temporary name beside the target and renamed into place, so a
reader never sees half a file; on any failure (missing directory, no permission,
disk full, an encoder that refuses) the temporary file is removed and an
``InputError`` names the file the user asked for.
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from services.errors import InputError


def describe_os_error(path: str | Path, error: OSError, action: str = "write the file") -> str:
    """``path: cannot <action> (reason)`` for an ``OSError`` met on ``path``."""
    path = Path(path)
    if error.errno == errno.ENOENT and not path.parent.is_dir():
        reason = f"the directory {path.parent} does not exist"
    elif error.errno in (errno.ENOSPC, errno.EDQUOT):
        reason = f"no space left on the device holding {path.parent}"
    elif error.errno in (errno.EEXIST, errno.ENOTDIR):  # mkdir or open through a file
        reason = "a file is in the way of a directory"
    elif error.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        reason = f"permission denied ({error.strerror.lower()})"
    else:
        reason = (error.strerror or str(error)).lower()
    return f"{path}: cannot {action} ({reason})"


def output_directory(path: str | Path) -> Path:
    """Create the output directory ``path`` and its parents if they are missing; return it.

    The files written into it go through :func:`atomic_output`, which names any file it cannot write.

    Raises
    ------
    InputError
        Naming ``path`` (or the part of it at fault), when it cannot be created: a file in the way,
        no permission, a read-only or full disk.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{path}: cannot create the directory (a file is in the way of a directory)")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise InputError(describe_os_error(error.filename or path, error, "create the directory")) from None
    return path


@contextmanager
def atomic_output(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix, so encoders pick the format); rename it to
    ``path`` when the block succeeds, remove it when it fails.

    Raises
    ------
    InputError
        Naming ``path``, when its directory is missing or writing fails (permission, disk full).
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise InputError(f"{path}: cannot write the file (the directory {path.parent} does not exist)")
    temporary = path.with_name(f"{path.stem}.part{os.getpid()}{path.suffix}")
    try:
        yield temporary
        temporary.replace(path)
    except OSError as error:
        _remove(temporary)
        raise InputError(describe_os_error(path, error)) from None
    except BaseException:
        _remove(temporary)
        raise


def _remove(path: Path) -> None:
    with contextlib.suppress(OSError):  # e.g. on a read-only disk, where nothing was written either
        path.unlink(missing_ok=True)


def write_text_atomically(path: str | Path, text: str) -> Path:
    """Write beside the target and rename, so a reader never sees half a file."""
    path = Path(path)
    with atomic_output(path) as temporary:
        temporary.write_text(text)
    return path
