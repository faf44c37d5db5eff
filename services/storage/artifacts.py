"""A content-addressed artifact store in a directory: each blob is named by its SHA-256.

Layout: ``ROOT/sha256/ab/abcdef...`` (two-character fan-out). Blobs are immutable;
writing the same content twice stores it once. Every write goes to a temporary
file that is renamed into place, so a reader never sees a partial blob and a
crash never corrupts a stored one.
"""

from __future__ import annotations

import errno
import hashlib
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor, wait
from contextlib import contextmanager
from functools import cache
from pathlib import Path

_DIGEST = re.compile(r"^[0-9a-f]{64}$")
_CHUNK = 1 << 20
_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EROFS)


class StorageFull(OSError):
    """The store's disk is full or read-only: the blob was not stored (and no part of it is visible); retrying
    helps only once space is freed."""


class ArtifactStore:
    """Blobs under ``root`` addressed by their SHA-256 hex digest."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)
        self._objects = self.root / "sha256"
        self._incoming = self.root / "incoming"
        self._objects.mkdir(parents=True, exist_ok=True)
        self._incoming.mkdir(parents=True, exist_ok=True)

    def path(self, digest: str) -> Path:
        """Where the blob ``digest`` lives; ``KeyError`` if it is not stored."""
        if not _DIGEST.match(digest):
            raise KeyError(f"{digest!r} is not a SHA-256 hex digest")
        path = self._objects / digest[:2] / digest
        if not path.is_file():
            raise KeyError(f"artifact {digest} is not in the store at {self.root}")
        return path

    def exists(self, digest: str) -> bool:
        try:
            self.path(digest)
        except KeyError:
            return False
        return True

    def put_bytes(self, data: bytes) -> str:
        """Store ``data``; return its digest. :class:`StorageFull` when the disk cannot take it."""
        with self._storing():
            with self._temporary() as (handle, temporary):
                handle.write(data)
            return self._commit(temporary, hashlib.sha256(data).hexdigest())

    def put_file(self, source: str | Path) -> str:
        """Copy the file ``source`` into the store (streaming); return its digest."""
        hasher = hashlib.sha256()
        with self._storing():
            with open(source, "rb") as reader, self._temporary() as (handle, temporary):
                while chunk := reader.read(_CHUNK):
                    hasher.update(chunk)
                    handle.write(chunk)
            return self._commit(temporary, hasher.hexdigest())

    def free_bytes(self) -> int:
        """Space left for new blobs on the store's file system."""
        return shutil.disk_usage(self.root).free

    def writable(self) -> bool:
        """Whether a blob could be written now (a temporary file can be created and removed)."""
        try:
            with self._temporary() as (_, temporary):
                pass
            temporary.unlink()
        except OSError:
            return False
        return True

    def blobs(self) -> Iterator[tuple[str, Path]]:
        """Every stored blob as (digest, path), and every temporary file a crash left in ``incoming/``
        (as ("", path)), for the retention sweep."""
        for path in self._objects.glob("??/*"):
            if _DIGEST.match(path.name):
                yield path.name, path
        for path in self._incoming.glob("*.part"):
            yield "", path

    def read_bytes(self, digest: str) -> bytes:
        return self.path(digest).read_bytes()

    def _temporary(self):
        return _TemporaryFile(self._incoming)

    @contextmanager
    def _storing(self) -> Iterator[None]:
        try:
            yield
        except StorageFull:
            raise
        except OSError as error:
            if error.errno not in _FULL:
                raise
            raise StorageFull(error.errno, f"the artifact store at {self.root} cannot take more data "
                                           f"({error.strerror})") from None

    def _commit(self, temporary: Path, digest: str) -> str:
        target = self._objects / digest[:2] / digest
        try:
            if target.is_file():
                temporary.unlink()
            else:
                target.parent.mkdir(exist_ok=True)  # may fail on a full disk too: then no .part is left behind
                temporary.replace(target)
        except BaseException:
            temporary.unlink(missing_ok=True)
            raise
        return digest


class ArtifactWriter:
    """Stores blobs on background threads while the caller goes on computing; :meth:`digests` waits for them.

    A scan's artifacts are about 100 MB: hashing, writing and syncing them takes longer than the fusion that
    follows the capture, and hashlib and file writes release the GIL, so they overlap with it. Each blob is
    stored by :meth:`ArtifactStore.put_bytes` (atomic, :class:`StorageFull` on a full disk, raised by
    :meth:`digests`). Leaving the ``with`` block waits for every write, also on an error; a blob whose job
    then fails is unreferenced and goes with the retention sweep. The threads are the process's
    (:data:`WRITER_THREADS` of them, started on first use), not one pool per writer.
    """

    def __init__(self, store: ArtifactStore) -> None:
        self.store = store
        self._pending: dict[str, Future[str]] = {}
        self._makers: list[Future[None]] = []

    def __enter__(self) -> ArtifactWriter:
        return self

    def __exit__(self, *exc_info: object) -> None:
        wait(self._makers)  # then every blob, the makers' included
        wait(list(self._pending.values()))

    def put(self, files: Mapping[str, bytes]) -> None:
        """Start storing each named blob."""
        for name, content in files.items():
            self._pending[name] = _writer_threads().submit(self.store.put_bytes, content)

    def put_made(self, make: Callable[[], Mapping[str, bytes]]) -> None:
        """Start making the named blobs (e.g. encoding them) and storing each, all in the background."""
        def made_and_stored() -> None:
            self.put(make())
        self._makers.append(_writer_threads().submit(made_and_stored))

    def digests(self) -> dict[str, str]:
        """Wait for every write; the digest of each named blob. Raises the first write's error."""
        for maker in self._makers:
            maker.result()
        return {name: future.result() for name, future in self._pending.items()}


WRITER_THREADS = 2


@cache
def _writer_threads() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=WRITER_THREADS, thread_name_prefix="artifact-writer")


class _TemporaryFile:
    """A file in ``directory`` that is flushed to disk on success and removed on failure."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory

    def __enter__(self):
        descriptor, name = tempfile.mkstemp(dir=self.directory, suffix=".part")
        self.path = Path(name)
        self.handle = os.fdopen(descriptor, "wb")
        return self.handle, self.path

    def __exit__(self, exc_type, exc, traceback) -> None:
        try:
            if exc_type is None:
                self.handle.flush()
                os.fsync(self.handle.fileno())
            self.handle.close()  # closing flushes the buffer, which fails again on a full disk
        except BaseException:
            self.handle.close()
            self.path.unlink(missing_ok=True)
            raise
        if exc_type is not None:
            self.path.unlink(missing_ok=True)

