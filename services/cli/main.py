"""The ``thermofield`` command line: one sub-command module per job, sharing error handling.

Sub-command modules are imported only when their command runs, so ``thermofield --help`` imports no
science and each command pays only for what it uses.
"""

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

# command: (module defining ``register(subparsers)``, which adds its command(s) and sets ``handler``; help)
COMMANDS = {
    "reconstruct": ("services.cli.reconstruct", "decode a structured-light capture and triangulate a point cloud"),
    "fuse": ("services.cli.fusion", "give each point of a cloud its temperature from calibrated thermal frames"),
    "field": ("services.cli.fusion",
              "reconstruct a structured-light capture and fuse thermal frames into a temperature field"),
    "patterns": ("services.cli.patterns", "write the projector patterns and their sequence.json"),
    "serve": ("services.cli.service", "the embedded service: API, in-process worker, simulated gateway, SQLite, "
                                      "artifact directory, Rerun proxy"),
    "api": ("services.cli.service", "the HTTP API alone (scaled out: jobs go to RabbitMQ)"),
    "worker": ("services.cli.service", "Dramatiq worker processes (spawned) consuming RabbitMQ"),
    "maintenance": ("services.cli.service", "apply the artifact retention policy and expire idempotency keys once "
                                            "(the service does it every THERMOFIELD_MAINTENANCE_INTERVAL_S)"),
    "apikey": ("services.cli.service", "manage API keys"),
    "calibrate": ("services.cli.calibrate", "calibrate cameras, the projector and the infrared camera"),
    "simulate": ("services.cli.simulate", "render simulated camera frames of a scene lit by the projector's sequence"),
    "gateway": ("services.cli.gateway",
                "run the device gateway: the station's camera, thermal camera and projector behind HTTP"),
    "demo": ("services.cli.demo", "start the embedded service, scan the simulated hot part over HTTP, print the field"),
    "register": ("services.cli.register", "register an infrared image to a visible image by mutual information"),
    "inspect": ("services.cli.inspect",
                "cold-equivalent dimensions, deviation from the nominal part and a verdict from a temperature field"),
    "rig": ("services.cli.rig", "rig files: import another program's calibration"),
    "thermal": ("services.cli.thermal", "thermal files: convert a radiometric file (FLIR R-JPEG, TIFF, PNG) to "
                                        "degrees C"),
}
# Exit codes: 0 done; 2 the user's to fix (usage, as argparse exits, and bad input: a missing, unreadable,
# corrupt or unwritable file, a full disk); 1 an internal error or a failed check (`worker --check`); 130 Ctrl-C.
BAD_INPUT = 2
# Commands that run services: their logs (and their children's) are for the operator and stay on stderr.
SERVICE_COMMANDS = frozenset({"serve", "api", "worker", "gateway", "demo"})


class _Commands:
    """The sub-parsers action, giving every command its help from :data:`COMMANDS`."""

    def __init__(self, subparsers: argparse._SubParsersAction) -> None:
        self._subparsers = subparsers

    def add_parser(self, name: str, **kwargs) -> argparse.ArgumentParser:
        return self._subparsers.add_parser(name, help=COMMANDS[name][1], **kwargs)


def _chosen_command(argv: list[str]) -> str | None:
    """The command named in ``argv`` (its first word that is one), if any."""
    return next((word for word in argv if word in COMMANDS), None)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser, with the full options of the command in ``argv`` (all commands when None)."""
    parser = argparse.ArgumentParser(
        prog="thermofield",
        description="3D temperature fields by structured light and infrared fusion.",
    )
    parser.add_argument("--debug", action="store_true", help="show a traceback on internal errors")
    subparsers = _Commands(parser.add_subparsers(dest="command", required=True, metavar="COMMAND"))
    chosen = list(COMMANDS) if argv is None else [_chosen_command(argv)]
    loaded = {COMMANDS[name][0] for name in chosen if name is not None}
    for module_name in dict.fromkeys(module for module, _ in COMMANDS.values()):
        if module_name in loaded:
            importlib.import_module(module_name).register(subparsers)
        else:
            for name, (module, _) in COMMANDS.items():
                if module == module_name:
                    subparsers.add_parser(name)
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
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    quiet = not args.debug and args.command not in SERVICE_COMMANDS
    with _quiet_libraries() if quiet else contextlib.nullcontext():
        return _run(args, _options(parser))


def _options(parser: argparse.ArgumentParser) -> dict[str, str]:
    """Each parameter (an argparse ``dest``) of every loaded command to the option that sets it."""
    options = {}
    for action in parser._actions:  # argparse keeps no public list of a parser's actions
        if isinstance(action, argparse._SubParsersAction):
            for subparser in action.choices.values():
                options.update(_options(subparser))
        elif action.option_strings:
            options.setdefault(action.dest, max(action.option_strings, key=len))
    return options


def _message(error: InputError, options: dict[str, str]) -> str:
    """The error as the user of the command line reads it: a use case's parameter named by its option."""
    text = str(error)
    if error.parameter and error.parameter in options and text.startswith(f"{error.parameter}:"):
        return options[error.parameter] + text[len(error.parameter):]
    return text


def _run(args: argparse.Namespace, options: dict[str, str] | None = None) -> int:
    try:
        return args.handler(args) or 0
    except InputError as error:
        print(f"thermofield: error: {_message(error, options or {})}", file=sys.stderr)
        return BAD_INPUT
    except OSError as error:  # a path the command reads or writes: name it, no traceback; bad input too
        if args.debug:
            traceback.print_exc()
        what = describe_os_error(error.filename, error, "access it") if error.filename else f"{error.strerror or error}"
        print(f"thermofield: error: {what}", file=sys.stderr)
        return BAD_INPUT
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
