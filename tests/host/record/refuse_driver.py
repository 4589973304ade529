"""Run capsheet command lines one after another, each in a child forked from this process (its
imports made once), and print one JSON line per command: exit code, seconds, the child's peak RSS
(``os.wait4``'s rusage, measured by the kernel) and what it wrote to stderr.

    python refuse_driver.py COMMANDS.json       # [[name, [argv...]], ...]
"""

import json
import os
import signal
import sys
import tempfile
import time
import traceback

#: a command that has not ended after this many seconds is killed (SIGALRM) and reported as such
TIME_LIMIT_S = 60


def run(argv: list[str]) -> tuple[int, float, int, str]:
    err = tempfile.TemporaryFile()
    t0 = time.monotonic()
    pid = os.fork()
    if pid == 0:  # the child: stderr to the file, stdout away, the command, its exit code
        code = 99
        try:
            os.dup2(err.fileno(), 2)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 1)
            signal.alarm(TIME_LIMIT_S)
            from host.cli import main
            try:
                code = main(argv)
                code = 0 if code is None else int(code)
            except SystemExit as exc:
                if isinstance(exc.code, str):
                    print(exc.code, file=sys.stderr)
                    code = 1
                else:
                    code = 0 if exc.code is None else int(exc.code)
        except BaseException:  # noqa: BLE001 -- reported as it is: the test fails on it
            traceback.print_exc()
            code = 99
        finally:
            sys.stderr.flush()
            sys.stdout.flush()
            os._exit(code)
    _, status, usage = os.wait4(pid, 0)
    seconds = time.monotonic() - t0
    code = os.waitstatus_to_exitcode(status)
    err.seek(0)
    return code, seconds, usage.ru_maxrss, err.read().decode(errors="replace")


def main() -> None:
    import numpy  # noqa: F401 -- the heavy imports once, in the parent: each child is the command alone
    import foxglove  # noqa: F401
    import host.analysis.estimator  # noqa: F401
    import host.cli  # noqa: F401
    import host.cli.demo  # noqa: F401
    import host.cli.estimate  # noqa: F401
    import host.cli.host  # noqa: F401
    import host.cli.replay  # noqa: F401
    import host.cli.view  # noqa: F401
    import host.record.recording  # noqa: F401
    import host.record.replay  # noqa: F401
    from host.cli import build_parser
    build_parser()  # every command's registration imported once
    for name, argv in json.load(open(sys.argv[1])):
        code, seconds, rss_kb, err = run(argv)
        print(json.dumps({"name": name, "argv": argv, "exit": code, "seconds": round(seconds, 3),
                          "maxrss_mb": round(rss_kb / 1024, 1), "stderr": err}), flush=True)


if __name__ == "__main__":
    main()
