"""Runs that many tests read, made once per test session, the work split among the pytest-xdist
workers that need them.

A conformance run in real time mostly waits (silences, heartbeats, re-announces: ~7-10 s of wall for
~0.15-0.3 s of CPU), so a set of them is made several at once, in threads: the real-time runs that
stay (test_checks.py's healthy chips over a pty and python-can, test_qemu.py's QEMU suites). The runs
whose subject is the checks' verdicts (the mutants, the healthy variants) are on the simulated clock
instead (host/conformance/simulated.py): a fraction of a second each, no set to share. The set used
to be made under one file lock by the first worker that needed it while every other worker that
reached one of its tests waited on the lock (with four workers, three of them idle for the whole
set). Here every worker that needs the set takes the runs no worker has taken yet (a claim file
created with ``O_EXCL``: exactly one worker makes each run), `at_once` at a time, writes each
result beside its claim, then waits for the runs the others took. The results are JSON, the same
whichever worker made them; a test asserts on its own run's result as before. `shared_once` is the
same for one result made in one piece (the first worker that asks makes it, the others wait).
"""

from __future__ import annotations

import json
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Callable

__all__ = ["session_root", "shared_runs", "shared_once"]


def session_root(tmp_path_factory) -> Path:
    """The test session's temporary directory, shared by its pytest-xdist workers (each worker's
    own base directory is a child of it)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def _claim(path: Path) -> bool:
    try:
        os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return False
    return True


def _wait_for(paths: dict, tag: str, timeout_s: float) -> None:
    end = time.monotonic() + timeout_s
    while True:
        missing = [key for key, path in paths.items() if not path.exists()]
        if not missing:
            return
        if time.monotonic() > end:
            raise RuntimeError(f"{tag}: no result of {', '.join(map(str, missing))} after {timeout_s:.0f} s "
                               f"(claimed by a worker that did not finish them)")
        time.sleep(0.2)


def _write(path: Path, result) -> None:
    tmp = path.with_name(f"{path.name}.{os.getpid()}")
    tmp.write_text(json.dumps(result))
    os.replace(tmp, path)


def shared_once(root: Path, tag: str, make: Callable[[], object], *, timeout_s: float = 1200.0):
    """``make()``'s JSON-serialisable result, made once per test session: by the first worker that
    asks, in its own thread (``make`` may use pytest fixtures), the others wait for it."""
    claim, done = root / f"{tag}.claim", root / f"{tag}.json"
    if _claim(claim):
        try:
            result = make()
        except BaseException as exc:  # the waiting workers say so too, instead of waiting out timeout_s
            _write(done, {"error": f"{type(exc).__name__}: {exc}"})
            raise
        _write(done, {"result": result})
    _wait_for({tag: done}, tag, timeout_s)
    doc = json.loads(done.read_text())
    if "error" in doc:
        raise RuntimeError(f"{tag}: the worker that made it failed: {doc['error']}")
    return doc["result"]


def shared_runs(root: Path, tag: str, jobs: dict[str, Callable[[int], object]], *, at_once: int,
                timeout_s: float = 1200.0) -> dict:
    """``{key: result}`` of every job: ``jobs[key](k)`` returns a JSON-serialisable result (``k``:
    the job's number in ``jobs``, the same in every worker, for names a run must not share, such
    as a virtual CAN channel). A job that raises gives ``{"error": "Type: message"}`` for its key,
    which the test that reads it reports (`result_of`); the other jobs go on. RuntimeError naming
    the missing runs if another worker's runs are not there within ``timeout_s`` (that worker died)."""
    d = root / f"{tag}-runs"
    d.mkdir(exist_ok=True)
    keys = list(jobs)

    def take(_thread: int) -> None:
        for i, key in enumerate(keys):
            if _claim(d / f"{i}.claim"):
                try:
                    result = jobs[key](i)
                except Exception as exc:  # noqa: BLE001 - the test that reads it says it
                    result = {"error": f"{type(exc).__name__}: {exc}"}
                _write(d / f"{i}.json", result)

    with ThreadPoolExecutor(at_once) as pool:
        list(pool.map(take, range(at_once)))
    _wait_for({key: d / f"{i}.json" for i, key in enumerate(keys)}, tag, timeout_s)
    return {key: json.loads((d / f"{i}.json").read_text()) for i, key in enumerate(keys)}


def result_of(results: dict, key: str):
    """``results[key]`` of `shared_runs`; the job's error as this test's failure."""
    got = results[key]
    assert not (isinstance(got, dict) and "error" in got), f"{key}: {got['error']}"
    return got
