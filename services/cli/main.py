"""The ``thermofield`` command line: one sub-command module per job, sharing error handling."""

from __future__ import annotations

import argparse
import importlib
import sys
import traceback

from services.errors import InputError

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
]


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


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.handler(args) or 0
    except InputError as error:
        print(f"thermofield: error: {error}", file=sys.stderr)
        return 2
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
