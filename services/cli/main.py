"""The ``thermofield`` command line: one sub-command module per job, sharing error handling."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import os
import sys
import traceback
import warnings

# Third-party libraries do not write to the user's terminal: OpenCV's own log ("[ERROR:0@0.9] global
# loadsave.cpp ..."), set before any module imports cv2; the rest is quieted per command below.
os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")

from services.errors import InputError  # noqa: E402
from services.formats.files import describe_os_error  # noqa: E402

# Each module defines ``register(subparsers)``, which adds its sub-command(s) and sets ``handler``.
COMMAND_MODULES = [
    "services.cli.reconstruct",
    "services.cli.fusion",
    "services.cli.patterns",
    "services.cli.service",
    "services.cli.calibrate",
    "services.cli.simulate",
    "services.cli.gateway",
    "services.cli.demo",
    "services.cli.register",
    "services.cli.inspect",
    "services.cli.rig",
]
# Commands that run services: their logs (and their children's) are for the operator and stay on stderr.
SERVICE_COMMANDS = frozenset({"serve", "api", "worker", "gateway", "demo"})


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="thermofield",
        description="3D temperature fields by structured light and infrared fusion.",
    )
    parser.add_argument("--debug", action="store_true", help="show a traceback on internal errors")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module_name in COMMAND_MODULES:
        importlib.import_module(module_name).register(subparsers)
    return parser


@contextlib.contextmanager
def _quiet_libraries():
    """Send what C libraries write straight to file descriptor 2 (libpng's "libpng error: ...", native
    logs) to /dev/null, Python warnings and library log records nowhere; our own messages go to
    ``sys.stderr``, which is pointed at the real terminal."""
    sys.stderr.flush()
    terminal = os.dup(2)
    with open(os.devnull, "wb") as devnull:
        os.dup2(devnull.fileno(), 2)
    saved_stderr = sys.stderr
    if _writes_to_fd2(saved_stderr):
        sys.stderr = os.fdopen(os.dup(terminal), "w", buffering=1, errors="replace")
    logging.getLogger().addHandler(logging.NullHandler())
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        if sys.stderr is not saved_stderr:
            sys.stderr.flush()
            sys.stderr.close()
            sys.stderr = saved_stderr
        os.dup2(terminal, 2)
        os.close(terminal)


def _writes_to_fd2(stream) -> bool:
    try:
        return stream.fileno() == 2
    except (AttributeError, OSError, ValueError):  # io.UnsupportedOperation is an OSError
        return False


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    quiet = not args.debug and args.command not in SERVICE_COMMANDS
    with _quiet_libraries() if quiet else contextlib.nullcontext():
        return _run(args)


def _run(args: argparse.Namespace) -> int:
    try:
        return args.handler(args) or 0
    except InputError as error:
        print(f"thermofield: error: {error}", file=sys.stderr)
        return 2
    except OSError as error:  # a file the command reads or writes: name it, no traceback
        if args.debug:
            traceback.print_exc()
        what = describe_os_error(error.filename, error, "use") if error.filename else f"{error.strerror or error}"
        print(f"thermofield: error: {what}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("thermofield: interrupted", file=sys.stderr)
        return 130
    except Exception as error:  # a bug, not bad input: say so plainly
        if args.debug:
            traceback.print_exc()
        print(f"thermofield: internal error: {type(error).__name__}: {error} (run with --debug for details)",
              file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
