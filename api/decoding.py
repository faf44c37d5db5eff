"""Uploads are decoded in processes of their own, never on the API's event loop nor in its memory.

Decoding an upload (OpenCV for images, Open3D for meshes) can take seconds and hold the interpreter lock
(Open3D does), and a file built to lie about its size can make a library allocate gigabytes. So each
upload's decoding runs in a child process forked from a forkserver (about 15 ms; the decoding libraries
are loaded in the forkserver once), at most ``decode_processes`` at once, its data segment capped at
``decode_memory_bytes`` beyond what it had when forked (``RLIMIT_DATA``), and killed after
``decode_timeout_s``. Whatever goes wrong in it (a library's exception, a failed allocation, a crash, the
time) is answered as a problem naming the upload: 413 for a declared size over a limit, else 422. The
API process keeps only the upload's bytes.

Written here rather than using ``concurrent.futures.ProcessPoolExecutor``: a pool's worker that crashes
breaks the whole pool, failing the other uploads it was decoding; a process per upload isolates them.
"""

from __future__ import annotations

import asyncio
import multiprocessing
import os
import signal
from collections.abc import Callable
from typing import Any

from fastapi.concurrency import run_in_threadpool

from api.problems import RETRY_AFTER_S, Problem
from services.errors import InputError
from services.formats.limits import DeclaredSizeError

# loaded once in the forkserver, so that a child starts with them (open3d and numba take a second each to
# import); the service's main module too, which a child imports again as multiprocessing's "__mp_main__"
_PRELOAD = ["numpy", "cv2", "tifffile", "plyfile", "numba", "open3d", "services.inspection.inspect",
            "api.routers.parts", "api.routers.calibrations", "services.cli.main"]


class DecoderPool:
    """At most ``processes`` decodings at once, each in a child process capped at ``memory_bytes`` of data
    and ``timeout_s`` seconds."""

    def __init__(self, processes: int, memory_bytes: int, timeout_s: float) -> None:
        self.memory_bytes, self.timeout_s = memory_bytes, timeout_s
        self._slots = asyncio.Semaphore(processes)
        self._context = multiprocessing.get_context("forkserver")
        self._context.set_forkserver_preload(_PRELOAD)

    def start(self) -> None:
        """Start the forkserver now (it loads the decoding libraries, seconds) rather than on the first upload."""
        from multiprocessing import forkserver

        forkserver.ensure_running()

    async def run(self, function: Callable[..., Any], *args: Any, source: str) -> Any:
        """``function(*args)`` in a child process; its ``InputError`` is raised again here (a
        ``DeclaredSizeError`` as such), anything else that goes wrong becomes an ``InputError`` naming
        ``source``. ``function`` and its arguments and result must pickle."""
        async with self._slots:
            kind, value = await run_in_threadpool(self._run_in_child, function, args)
        if kind == "ok":
            return value
        if kind == "declared":
            raise DeclaredSizeError(value)
        if kind == "input":
            raise InputError(value)
        if kind == "unavailable":
            raise Problem(503, "decoding-unavailable", f"{source}: cannot be decoded now ({value}); retry shortly.",
                          {"Retry-After": str(RETRY_AFTER_S)})
        raise InputError(f"{source}: cannot be decoded ({value})")

    def _run_in_child(self, function: Callable[..., Any], args: tuple) -> tuple[str, Any]:
        receiver, sender = self._context.Pipe(duplex=False)
        process = self._context.Process(target=_decode, args=(sender, function, args, self.memory_bytes),
                                        daemon=True, name="thermofield-decode")
        try:
            process.start()
        except (OSError, RuntimeError) as error:  # no process to be had (out of memory or processes): the server's
            receiver.close()                       # fault, not the upload's
            sender.close()
            return "unavailable", f"no decoding process could be started: {type(error).__name__}: {error}"
        sender.close()
        try:
            if not receiver.poll(self.timeout_s):
                return "failed", f"it took longer than {self.timeout_s:g} s"
            return receiver.recv()
        except EOFError:  # the child died without answering: killed for its memory, or a library crashed
            process.join(5)
            code = process.exitcode
            reason = f"signal {signal.Signals(-code).name}" if code is not None and code < 0 else f"exit code {code}"
            return "failed", (f"the decoder stopped ({reason}) within the memory limit of "
                              f"{self.memory_bytes:,} bytes")
        finally:
            receiver.close()
            if process.is_alive():
                process.kill()
            process.join(5)


def _decode(sender, function: Callable[..., Any], args: tuple, memory_bytes: int) -> None:
    """The child: cap the data segment, run ``function``, send ``(kind, value)`` back."""
    import resource

    _, hard = resource.getrlimit(resource.RLIMIT_DATA)
    limit = _data_bytes() + memory_bytes
    resource.setrlimit(resource.RLIMIT_DATA, (limit if hard == resource.RLIM_INFINITY else min(limit, hard), hard))
    try:
        answer = ("ok", function(*args))
    except DeclaredSizeError as error:
        answer = ("declared", str(error))
    except InputError as error:
        answer = ("input", str(error))
    except MemoryError:
        answer = ("failed", f"it needs more than the memory limit of {memory_bytes:,} bytes")
    except Exception as error:  # any library's error on user data (cv2.error, RuntimeError of Open3D, ...)
        detail = str(error).strip().splitlines()
        answer = ("failed", f"{type(error).__name__}" + (f": {detail[-1][:200]}" if detail else ""))
    try:
        sender.send(answer)
    finally:
        sender.close()
        os._exit(0)  # no interpreter teardown: the forkserver's modules need none


def _data_bytes() -> int:
    """This process's data segment (``VmData``), which ``RLIMIT_DATA`` bounds."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmData:"):
                return int(line.split()[1]) * 1024
    return 0
