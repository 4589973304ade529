"""The ``capsheet`` command line. Each subcommand lives in its own module, which exposes
``register(subparsers)``; this file only collects them, so a module that fails to import does not
take the others down with it (its error is shown when its subcommand is asked for)."""

from __future__ import annotations

import argparse
import importlib
import os
import sys

#: modules that provide subcommands, in the order `capsheet --help` lists them
SUBCOMMAND_MODULES = [
    "host.cli.demo",         # capsheet demo
    "host.cli.host",         # capsheet host
    "host.cli.virtual",      # capsheet virtual
    "host.cli.paper",        # capsheet paper {solvability,gaussian,noise}
    "host.cli.tactile",      # capsheet tactile
    "host.cli.calibrate",    # capsheet calibrate (per-chip bias, scale, misalignment)
    "host.cli.conformance",  # capsheet conformance
    "host.cli.protocol",     # capsheet protocol (spec helpers: vectors, dbc, capacity)
    "host.cli.replay",       # capsheet replay (a recording through decoder, aggregator, estimator)
    "host.cli.estimate",     # capsheet estimate (a recording offline, batched)
]


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("capture-sheet")
    except PackageNotFoundError:
        return "unknown (not installed)"



def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="capsheet",
        description="capsheet: 3D capture sheet toolkit — talk to sensor chips over serial or CAN, "
                    "run a virtual sheet, estimate the sheet's shape and its contacts.",
    )
    parser.add_argument("--version", action="version", version=f"capsheet {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:
                continue  # not built yet
            raise
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader went away (`capsheet protocol vectors | head`): stop quietly
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())  # so the interpreter's final flush does not fail too
        except (OSError, ValueError):
            pass
        return 141  # as a shell reports a command ended by SIGPIPE


if __name__ == "__main__":
    sys.exit(main())
