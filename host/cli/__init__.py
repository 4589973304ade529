"""The ``capsheet`` command line. Each subcommand lives in its own module, which exposes
``register(subparsers)``; this file only collects them, so a module that fails to import does not
take the others down with it (its error is shown when its subcommand is asked for)."""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from host.runtime import BLAS_THREAD_VARS, one_blas_thread  # noqa: F401 -- every command's, and the name tools use

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
    "host.cli.estimate",     # capsheet estimate (a recording offline, batched; --subscribe: a Zenoh worker)
    "host.cli.view",         # capsheet view (several sheets from Zenoh in one live scene)
    "host.cli.ports",        # capsheet ports (which port is my sheet: list, --probe)
    "host.cli.layout",       # capsheet layout {learn,check} (which chip is on which link, from the sheet)
]


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version("capture-sheet")
    except PackageNotFoundError:
        return "unknown (not installed)"


class _VersionAction(argparse.Action):
    """``--version``: the installed version, looked up only when asked (importlib.metadata and the
    package metadata scan cost every command's start ~15 ms otherwise)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS,
                 help="show the program's version number and exit"):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"capsheet {_version()}")
        parser.exit()


def asked_command(argv: list[str]) -> str | None:
    """The subcommand ``argv`` names, if it names one of `SUBCOMMAND_MODULES` first (the top-level
    parser takes no option with a value, so the first word that is not an option is the command);
    None otherwise (``--help``, ``--version``, nothing, a misspelt command)."""
    for word in argv:
        if word.startswith("-"):
            return None  # a top-level option first: the whole parser answers it
        return word if f"host.cli.{word}" in SUBCOMMAND_MODULES else None
    return None


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``capsheet`` parser with every subcommand; with ``command``, with that subcommand alone.

    A command's run builds its own subcommand only (`main`): registering a subcommand imports its
    module and what its options need (numpy, the session, the conformance checks, the sheet's
    shapes...), ~0.2 s of CPU for the twelve a run does not use, paid by every process started.
    ``--help``, ``--version`` and anything that is not a command get the whole parser, so what they
    print and refuse is the same."""
    from host.cli.argtypes import CliParser  # a bad value: one line, exit 2 (every subcommand's parser too)

    parser = CliParser(
        prog="capsheet",
        description="capsheet: 3D capture sheet toolkit — talk to sensor chips over serial or CAN, "
                    "run a virtual sheet, estimate the sheet's shape and its contacts.",
    )
    parser.add_argument("--version", action=_VersionAction)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMAND_MODULES if command is None else [f"host.cli.{command}"]:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:
                continue  # not built yet
            raise
        module.register(sub)
    return parser


#: the interpreter's switch interval while a command streams (`short_gil_switch`), seconds
STREAMING_SWITCH_INTERVAL_S = 0.0005


def short_gil_switch() -> float:
    """While this process streams, a thread waiting for the interpreter lock gets it within
    `STREAMING_SWITCH_INTERVAL_S` instead of Python's 5 ms; returns the interval it replaced.

    The host's SYNC thread wakes at each slot (6.9 ms at 145 Hz) and needs the lock to stamp and
    write the SYNC, while the receive threads decode and the main thread shapes snapshots (the fused
    estimator ~1.2 ms of mostly small numpy calls). With 5 ms it missed a slot whenever it waited
    too long: `capsheet demo --sensors accel+gyro+mag` beside two busy cores sent 121–139 SYNCs/s
    (38–146 slots missed in 6 s) and failed 3 of 9 runs; with 0.5 ms, 138–140/s and 6 of 6 passed
    (docs/motion.md). Real chips are owed the same punctual SYNC: the streaming commands set it
    (`capsheet host`, `capsheet demo`), not the library, whose users own their interpreter."""
    import sys
    old = sys.getswitchinterval()
    sys.setswitchinterval(min(old, STREAMING_SWITCH_INTERVAL_S))
    return old


def main(argv: list[str] | None = None) -> int:
    from host.memory import fix_mmap_threshold, process_trim
    fix_mmap_threshold()  # a host that runs for days: large buffers go back to the system at free
    process_trim()  # and freed pages between the blocks in use, once a minute (one thread a process)
    one_blas_thread()
    parser = build_parser(asked_command(sys.argv[1:] if argv is None else list(argv)))
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
