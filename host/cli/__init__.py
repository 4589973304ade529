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
    from host.cli.argtypes import CliParser  # a bad value: one line, exit 2 (every subcommand's parser too)

    parser = CliParser(
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


#: environment variables through which a user chooses the BLAS / OpenMP thread count themselves
BLAS_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def one_blas_thread() -> bool:
    """Run BLAS single-threaded unless the user chose a thread count (any of `BLAS_THREAD_VARS`).

    capsheet's matrices are small (a few hundred rows): a BLAS thread pool only adds hand-offs, and
    OpenBLAS's idle workers spin on the other cores, which the live path's I/O threads, the virtual
    sheet and ``capsheet estimate --jobs`` need (offline 14x14 estimation ran at ~400 snapshots per
    CPU-second with two OpenBLAS threads per worker, ~1,050 with one). Parallel work is done by
    processes. Libraries already loaded are limited through threadpoolctl; the environment variables
    are set for those loaded later (scipy's own OpenBLAS) and for child processes. Returns whether
    it limited anything."""
    if any(v in os.environ for v in BLAS_THREAD_VARS):
        return False
    for v in BLAS_THREAD_VARS:
        os.environ[v] = "1"
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - a declared dependency; the variables still apply
        return True
    threadpool_limits(limits=1, user_api="blas")
    return True


def main(argv: list[str] | None = None) -> int:
    from host.memory import fix_mmap_threshold
    fix_mmap_threshold()  # a host that runs for days: large buffers go back to the system at free
    one_blas_thread()
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
