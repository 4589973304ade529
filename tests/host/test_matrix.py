"""The feature x transport matrix, in the spirit of python-can's ``back2back_test.py``:
every feature of the command line over every transport it applies to, through the real CLI in
subprocesses, against a virtual sheet (tests/host/matrix_sheet.py) behind

* ``memory``: an in-memory link, opened by name (``--port memory://NAME``);
* ``pty``: a serial gateway on a real pseudo-terminal;
* ``slcan``: an SLCAN adapter emulated on a pty, python-can's ``slcan`` interface name;
* ``virtual``: python-can's in-process ``virtual`` bus;
* ``udp_multicast``: python-can's ``udp_multicast`` on loopback.

``memory`` and ``virtual`` reach only their own process, so their sheet runs in the command's
process (``python -m tests.host.matrix_sheet -- capsheet ARGS``); the others run the sheet in one
process and ``python -m host.cli`` in another, as a user does. A batch's ``pty``, ``slcan`` and
``udp_multicast`` sheets are served by one process (``matrix_sheet --many``: a device, port and
thread each, each stopped when its command ends; udp_multicast's each on a multicast group of its
own, from the process's id and the sheet's number, where the machine's pid_max leaves room for
them: else a process each, as before).

Each transport's stream run (``capsheet host``: the stream, record-replay, can-log and live cells)
starts an interpreter as a user does. The batch's other commands, and its shared sheets, are forked
from one server per worker that has imported what they import (tests/host/matrix_fork.py): each is
a process of its own on the real transport, with its own exit status, stdout and stderr, and none
pays an interpreter's start and its imports again. The healthy chip's conformance run and the
mutant's are each split into runs at once that together run the same checks (`HEALTHY_ONLY`,
`MUTANT_ONLY`): the full run was ~12 s of the chip's own periods and silences.

The features (rows of the table in docs/host.md, which `test_the_docs_table_is_this_matrix` holds to
`CELLS` and `NOT_APPLICABLE`): stream; ``--record`` then ``replay`` identical; ``--can-log`` decoded
by the cantools command line; ``conformance`` PASS on a healthy chip and FAIL on a mutant; ``calibrate
--write-chips`` read back; ``--calibration`` changes the estimate by what the chips' errors predict
(``host``, and ``demo``); ``tactile`` on a port; ``--live`` serving a Foxglove client.

Assertions are on what is delivered and reported, never a rate or a latency. To stay fast the runs
of one transport are made once per test session (`Batch`: whichever worker needs them first makes
them, under a file lock in the session's temporary directory, and the other finds them there) and
start together (one sheet each; a ``udp_multicast`` sheet on a group of its own,
tests/host/matrix_sheet.py's ``udp_group``: sheets isolated to their groups do not hear each other).
Under ``make test`` (pytest-xdist, ``--dist loadgroup``) the matrix is meant to be one group, run by one
worker in order; with pytest 9.2 and pytest-xdist 3.8 the group is not honoured (docs/testing.md), the
cells are spread over the workers, and a cell whose transport's runs another worker is making waits
on the lock: each transport's runs are still made once.
"""

from __future__ import annotations

import asyncio
import atexit
import base64
import contextlib
import fcntl
import json
import re
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.host.matrix_fork import Forker
from tests.host.matrix_sheet import fits_udp_groups


pytestmark = pytest.mark.xdist_group("matrix")

ROOT = Path(__file__).resolve().parents[2]
PY = sys.executable
ENV = dict(os.environ, PYTHONUNBUFFERED="1")
TRANSPORTS = ("memory", "pty", "slcan", "virtual", "udp_multicast")
IN_PROCESS = ("memory", "virtual")  #: reach only their own process: the sheet runs in the command's
CAN = ("slcan", "virtual", "udp_multicast")
#: a batch's sheets in one process (`Sheets`); udp_multicast's where each gets a group of its own
BATCH_SHEETS = 9  #: the sheets of a batch (`Batch`: one per run)
SHARED_SHEETS = ("pty", "slcan", *(("udp_multicast",) if fits_udp_groups(BATCH_SHEETS) else ()))
#: a batch's commands but its stream run forked from one interpreter (tests/host/matrix_fork.py)
FORK = True
LATTICE = "3x3"
L = 0.01
SEED = 5  #: the chip errors of the streaming sheet (realistic, noise-free: every snapshot alike)
MUTANT = "counter_off_by_one"  #: breaks §5.1 on any transport (tests/host/conformance/mutants.py)
MUTANT_FAILS = {24, 25, 26, 27}  #: tests/host/conformance/test_mutants.py's EXPECTED for it
#: The healthy chip's conformance run, in three runs at once on three sheets of the same kind:
#: together every check of the chip profile (the cell holds them to it), each about a third of the
#: full run's waiting (~12 s: the chip's own periods and the silences it must keep): the re-announce
#: periods of check 8; check 9's next announce, the heartbeats of check 11 and the streaming checks;
#: the silences of checks 6, 15 and 19 and the damaged input of 21. A check runs in one of the three;
#: 39, 40 and 41 judge every frame a run received, so each run has them and no frame goes unjudged.
HEALTHY_ONLY = ("8,25,26,30,39,40,41",
                "9,11,24,27,29,39,40,41",
                "2,3,4,5,6,7,10,12,13,14,15,16,17,18,19,20,21,22,23,28,31,32,39,40,41,42,43,44,45")
#: The mutant's run, in two runs at once: discovery, the checks it fails (each waits out its answer
#: with the right counter), and one it passes; check 1 (discovery) runs in both
MUTANT_ONLY = ("1,24,25,29", "1,26,27")

#: feature -> what its cell asserts (the rows of the docs table)
CELLS = {
    "stream": "`capsheet host`: every chip found and streaming, >= 95 % of link samples valid, no error",
    "record-replay": "`--record` then `capsheet replay`: every recorded snapshot replayed identical",
    "can-log": "`--can-log` decoded by `python -m cantools decode`: every line, Rx and Tx",
    "conformance": "`capsheet conformance`: PASS on a healthy chip, FAIL exactly 24-27 on a mutant",
    "calibrate": "`capsheet calibrate --write-chips`: every chip written and read back",
    "calibration-host": "`capsheet host --calibration`: applied once, the estimate changes as the chips' errors predict",
    "calibration-demo": "`capsheet demo --calibration`: the estimate's error is what the calibration predicts",
    "tactile": "`capsheet tactile` on a port: rest learned, frames estimated and recorded",
    "live": "`--live`: a Foxglove WebSocket client receives snapshots and estimates",
}
#: (feature, transport) -> why the cell does not apply
NOT_APPLICABLE = {
    ("can-log", "memory"): "a serial link carries no CAN frames (`--can-log` says so and logs nothing)",
    ("can-log", "pty"): "a serial link carries no CAN frames (`--can-log` says so and logs nothing)",
    **{("calibration-demo", t): "`capsheet demo` runs its own virtual sheet on a pty" for t in TRANSPORTS if t != "pty"},
}


class Proc:
    """A subprocess whose stdout and stderr are read by threads (it never blocks on a full pipe)."""

    def __init__(self, argv: list[str], *, stdin: bool = False) -> None:
        self.argv = argv
        self.p = subprocess.Popen(argv, cwd=ROOT, env=ENV, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                  stdin=subprocess.PIPE if stdin else subprocess.DEVNULL)
        self.out: list[str] = []
        self.err: list[str] = []
        self._threads = [threading.Thread(target=lambda s=s, sink=sink: sink.extend(iter(s.readline, "")), daemon=True)
                         for s, sink in ((self.p.stdout, self.out), (self.p.stderr, self.err))]
        for t in self._threads:
            t.start()

    def wait_line(self, needle: str, timeout_s: float = 60.0, stream: str = "out") -> str:
        sink = self.out if stream == "out" else self.err
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            for line in list(sink):
                if needle in line:
                    return line
            if self.p.poll() is not None and not any(t.is_alive() for t in self._threads):
                break
            time.sleep(0.02)
        raise AssertionError(f"{self.argv[2:6]} never printed {needle!r}: {''.join(self.out)} {''.join(self.err)}")

    def wait(self, timeout_s: float = 240.0) -> int:
        try:
            rc = self.p.wait(timeout_s)
        finally:
            if self.p.poll() is None:
                self.p.kill()
                self.p.wait(10)
        for t in self._threads:
            t.join(10)
        return rc

    def stop(self) -> None:
        if self.p.poll() is None:
            if self.p.stdin is not None:
                try:
                    self.p.stdin.close()
                except OSError:
                    pass
            try:
                self.p.wait(20)
            except subprocess.TimeoutExpired:
                self.p.kill()
        self.wait(10)

    @property
    def stdout(self) -> str:
        return "".join(self.out)

    @property
    def stderr(self) -> str:
        return "".join(self.err)


def sheet_options(transport: str, layout: Path, sheet: list[str]) -> list[str]:
    """tests/host/matrix_sheet.py's options for a sheet on ``transport`` writing ``layout``."""
    return ["--transport", transport, "--layout-out", str(layout), *sheet]


class Sheets:
    """Several sheets served by one ``matrix_sheet --many`` process (pty, slcan, udp_multicast):
    ``specs`` is ``{name: (transport, layout, sheet options)}``. Forked by ``forker`` if given
    (tests/host/matrix_fork.py: the sheets' imports made once a worker), else an interpreter."""

    def __init__(self, tmp: Path, specs: dict[str, tuple[str, Path, list[str]]],
                 forker: "Forker | None" = None) -> None:
        path = tmp / "sheets.json"
        path.write_text(json.dumps([{"name": name, "argv": sheet_options(*spec)} for name, spec in specs.items()]))
        self.forked = None
        if forker is not None:
            self.forked = forker.run("sheets", ["--many", str(path)], sheet=True, tmp=tmp, stdin_fifo=True)
            self.stdin = self.forked.open_stdin()
        else:
            self.proc = Proc([PY, "-m", "tests.host.matrix_sheet", "--many", str(path)], stdin=True)
            self.stdin = self.proc.p.stdin

    def ports(self, name: str) -> list[str]:
        line = (self.forked or self.proc).wait_line(f"PORTS {name} ")
        return json.loads(line.split(" ", 2)[2])

    def _alive(self) -> bool:
        return not self.forked.exited() if self.forked is not None else self.proc.p.poll() is None

    def stop(self, name: str) -> None:
        """Stop ``name``'s sheet (its command has ended); the others keep serving."""
        if self._alive():
            try:
                self.stdin.write(f"stop {name}\n")
                self.stdin.flush()
            except OSError:
                pass

    def close(self) -> None:
        if self.forked is None:
            self.proc.stop()
            return
        try:
            self.stdin.close()  # the sheets stop, and the process ends
        except OSError:
            pass
        self.forked.wait(30)


class Job:
    """``capsheet ARGS`` against a sheet of its own on ``transport`` (in ``shared``, a `Sheets`
    process, if given: its sheet is named ``name`` there). ``{port}`` in ARGS becomes the port
    arguments, ``{layout}`` the layout the sheet wrote."""

    def __init__(self, transport: str, tmp: Path, name: str, args: list[str], sheet: list[str],
                 shared: "Sheets | None" = None, forker: "Forker | None" = None) -> None:
        layout = tmp / f"{name}-layout.csv"
        self.name = name
        self.shared = shared
        args = [str(layout) if a == "{layout}" else a for a in args]
        sheet_argv = [PY, "-m", "tests.host.matrix_sheet", *sheet_options(transport, layout, sheet)]
        self.sheet = None
        self.in_process = transport in IN_PROCESS  #: the sheet's PORT line comes first on stdout
        self.rc: int | None = None
        if self.in_process:
            self.proc = (forker.run(name, sheet_argv[3:] + ["--", *args], sheet=True, tmp=tmp) if forker is not None
                         else Proc(sheet_argv + ["--", *args]))
            return
        if shared is not None:
            ports = shared.ports(name)
        else:
            self.sheet = Proc(sheet_argv, stdin=True)
            ports = json.loads(self.sheet.wait_line("PORT ").split(" ", 1)[1])
        argv = [a for arg in args for a in (ports if arg == "{port}" else [arg])]
        self.proc = forker.run(name, argv, tmp=tmp) if forker is not None else Proc([PY, "-m", "host.cli", *argv])

    def finish(self, timeout_s: float = 240.0) -> "Job":
        try:
            self.rc = self.proc.wait(timeout_s)
        finally:
            if self.sheet is not None:
                self.sheet.stop()
            if self.shared is not None:
                self.shared.stop(self.name)
        return self

    @property
    def stdout(self) -> str:
        return self.proc.stdout.split("PORT ", 1)[-1].split("\n", 1)[-1] if self.in_process else self.proc.stdout

    @property
    def stderr(self) -> str:
        return self.proc.stderr

    def json(self) -> dict:
        out = self.stdout
        return json.loads(out[out.index("{"):])


# ---------------------------------------------------------------------------------------------------
# what the chips' errors predict (computed here, from the virtual sheet's own model)
# ---------------------------------------------------------------------------------------------------

def realistic_sheet():
    from virtual_sheet.sensor import chip_error_model
    from virtual_sheet.sheet import VirtualSheet
    return VirtualSheet("gaussian", LATTICE, seed=SEED, sensor=chip_error_model("realistic", chip_seed=SEED))


def truth_calibration(sheet):
    """The chips' true errors as a calibration file would hold them (relative to the nominal
    conversion the uncalibrated chips report): ``r = s ⊙ (Mᵀ f) + b``."""
    from scipy.spatial.transform import Rotation

    from host.analysis.calibration import Calibration
    from protocol.constants import G0
    e = sheet.sensor_model.chip_errors(sheet.n_links)
    rows, cols = sheet.lattice.rows, sheet.lattice.cols
    return Calibration(rows, cols, bias=e.offset_counts * G0 / 1024.0, scale=e.sensitivity / 1024.0,
                       misalignment=Rotation.from_matrix(e.misalignment).as_rotvec())


def nominal_readings(sheet) -> np.ndarray:
    """What the chips send (noise-free, quantised) converted as an uncalibrated chip's CAL_DATA says."""
    from protocol.constants import counts_to_si
    counts, _status = sheet.counts_at(0.0)
    return counts_to_si(counts.astype(float), 0.0, 1024.0)


def side_pct(a: np.ndarray, b: np.ndarray) -> float:
    """Mean joint distance of ``a`` from ``b`` after the rigid overlay, % of the side."""
    from host.analysis.estimator import overlay_error
    rows, cols = a.shape[:2]
    return 100.0 * float(np.mean(overlay_error(a, b))) / (L * (max(rows, cols) - 1))


def last_complete_estimate(rec) -> np.ndarray:
    """Joints of the last recorded estimate made of a complete snapshot."""
    complete = {int(c) for c, ok in zip(rec.counter, rec.complete) if ok}
    k = max(i for i, c in enumerate(rec.estimates["counter"]) if int(c) in complete)
    return rec.estimates["joints"][k].astype(float)


def shape_of(readings: np.ndarray) -> np.ndarray:
    from host.analysis.estimator import estimate
    r, c = (int(x) for x in LATTICE.split("x"))
    return estimate(readings, r, c, L).joints


# ---------------------------------------------------------------------------------------------------
# the runs of one transport
# ---------------------------------------------------------------------------------------------------

LIVE_TOPICS = ("/capsheet/snapshot", "/capsheet/estimate")


async def _live_client(url: str, want: int = 2, timeout_s: float = 60.0) -> dict:
    """Subscribe to `LIVE_TOPICS` and return ``{topic: [decoded messages]}`` (``want`` each): JSON, or
    protobuf decoded with the schema the server advertised (not capsheet's own code)."""
    import struct

    import websockets
    async with websockets.connect(url, subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
        channels: dict = {}
        got: dict = {t: [] for t in LIVE_TOPICS}
        subscribed: dict = {}
        end = time.monotonic() + timeout_s
        while time.monotonic() < end and not all(len(v) >= want for v in got.values()):
            try:
                m = await asyncio.wait_for(ws.recv(), 1.0)
            except asyncio.TimeoutError:
                continue
            if isinstance(m, str):
                msg = json.loads(m)
                if msg.get("op") == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
                    new = [t for t in LIVE_TOPICS if t in channels and t not in subscribed.values()]
                    if new:
                        subs = [{"id": len(subscribed) + k + 1, "channelId": channels[t]["id"]} for k, t in enumerate(new)]
                        subscribed.update({s["id"]: t for s, t in zip(subs, new)})
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            elif m[0] == 0x01:
                sid, _ts = struct.unpack_from("<IQ", m, 1)
                ch = channels[subscribed[sid]]
                got[subscribed[sid]].append(_decode_advertised(ch, m[13:]))
        return got


def _decode_advertised(ch: dict, payload: bytes):
    if ch["encoding"] != "protobuf":
        return json.loads(payload)
    import base64

    from google.protobuf import descriptor_pb2, descriptor_pool, json_format, message_factory
    pool = descriptor_pool.DescriptorPool()
    for fd in descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(ch["schema"])).file:
        pool.Add(fd)
    msg = message_factory.GetMessageClass(pool.FindMessageTypeByName(ch["schemaName"])).FromString(payload)
    return json_format.MessageToDict(msg, preserving_proto_field_name=True)  # shared between workers as JSON


class Done:
    """A finished run, as the cells see it (`Job` s are made into these to be shared)."""

    def __init__(self, name: str, rc: int, stdout: str, stderr: str) -> None:
        self.name, self.rc, self.stdout, self.stderr = name, rc, stdout, stderr

    def json(self) -> dict:
        out = self.stdout
        return json.loads(out[out.index("{"):])


class Batch:
    """Every run one transport's cells look at, made once per session and shared by its cells
    (`Batch.load` finds it where another worker made it)."""

    @classmethod
    def load(cls, transport: str, root: Path) -> "Batch":
        """The batch of ``transport`` under ``root`` (the session's temporary directory): made
        here under a file lock unless a worker made it already."""
        tmp = root / f"matrix-{transport}"
        with open(root / f"matrix-{transport}.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            done = tmp / "runs.json"
            if not done.exists():
                tmp.mkdir(parents=True, exist_ok=True)
                # udp_multicast: the machine-wide lock of its tests (tests/host/udp_lock.py): a plain
                # python-can bus in tests/host/transport/test_udp_multicast.py hears every group, this
                # batch's too (the matrix and that file's group start together under ``make test``)
                from tests.host.udp_lock import udp_multicast_lock
                with udp_multicast_lock() if transport == "udp_multicast" else contextlib.nullcontext():
                    b = cls(transport, tmp)
                done.write_text(json.dumps({"jobs": {k: [j.rc, j.stdout, j.stderr] for k, j in b.jobs.items()},
                                            "live": b.live if isinstance(b.live, dict) else repr(b.live)}))
        doc = json.loads(done.read_text())
        b = cls.__new__(cls)
        b.transport, b.tmp = transport, tmp
        b.cal_path = tmp / "truth-cal.json"
        b.jobs = {k: Done(k, *v) for k, v in doc["jobs"].items()}
        b.live = doc["live"]
        return b

    def __init__(self, transport: str, tmp: Path) -> None:
        self.transport, self.tmp = transport, tmp
        sheet = realistic_sheet()
        self.cal_path = tmp / "truth-cal.json"
        truth_calibration(sheet).save(self.cal_path)
        can_log = ["--can-log", str(tmp / "stream.log")] if transport in CAN else []
        streaming = ["--chip-errors", "realistic", "--seed", str(SEED)]
        # the deadline: a sample held back by a loaded machine (a sheet's thread, the host's reader,
        # late by up to 3 s) still counts as delivered: the stream cell's completeness is of what
        # the transport delivers, not of how soon (a run on a quiet machine is the same either way)
        host = ["host", "{port}", "--lattice", LATTICE, "--layout", "{layout}", "--rate", "30", "--deadline-ms", "3000",
                "--duration", "1.5", "--json", "-q", "--live-rate", "20", "--link-length", str(L)]
        chip = ["--rows", "2", "--cols", "2", "--shape", "flat", "--noise", "0.5"]
        specs = [
            ("stream", [*host, "--record", str(tmp / "stream.mcap"), "--live", "0", *can_log], streaming),
            # its cell compares complete snapshots and their estimates, not how many came in time (the
            # stream run holds completeness): a run whose sheet a loaded machine held back past the
            # deadline is no failure of --calibration
            ("calibration", [*host, "--record", str(tmp / "calibrated.mcap"), "--calibration", str(self.cal_path),
                             "--min-complete", "0"], streaming),
            # the host-side slack of the timing checks is generous: the transport is under test here,
            # the chip's timing is tests/host/conformance's, and the machine may be loaded
            *((f"conformance{k}", ["conformance", "{port}", "--slack-ms", "40", "--only", only], chip)
              for k, only in enumerate(HEALTHY_ONLY)),
            *((f"mutant{k}", ["conformance", "{port}", "--slack-ms", "40", "--only", only], [*chip, "--mutant", MUTANT])
              for k, only in enumerate(MUTANT_ONLY)),
            ("calibrate", ["calibrate", "{port}", "--lattice", LATTICE, "--layout", "{layout}", "--out",
                           str(tmp / "fitted-cal.json"), "--write-chips", "--poses", "6", "--samples", "10",
                           "--window", "8", "--rate", "50", "--timeout", "150", "-q"],
             ["--board", "0.6", "--chip-errors", "realistic", "--noise", "0.1", "--seed", "7"]),
            ("tactile", ["tactile", "{port}", "--lattice", LATTICE, "--layout", "{layout}", "--rate", "30", "--learn-s",
                         "0.7", "--duration", "1.5", "--record", str(tmp / "tactile.mcap"), "--out",
                         str(tmp / "tactile.png"), "-q"], ["--shape", "flat", "--noise", "0.1"]),
        ]
        assert len(specs) == BATCH_SHEETS, len(specs)
        self.jobs: dict[str, Job] = {}
        self.live: dict | BaseException | None = None
        self._live_thread = None
        forker = _forker(tmp.parent) if FORK else None
        shared = (Sheets(tmp, {name: (transport, tmp / f"{name}-layout.csv", sheet_args)
                               for name, _args, sheet_args in specs}, forker) if transport in SHARED_SHEETS else None)
        try:
            for name, args, sheet_args in specs:
                # the stream run: this transport's command started as a user starts it; the others
                # forked from one interpreter that has imported what they import (matrix_fork.py)
                job = Job(transport, tmp, name, args, sheet_args, shared, None if name == "stream" else forker)
                self.jobs[name] = job
                if name == "stream":
                    self._watch_live(job)
            for name in self.jobs:
                self._finish(name)
        finally:
            if shared is not None:
                shared.close()

    def _finish(self, name: str) -> None:
        job = self.jobs[name]
        if job.rc is None:
            job.finish()
            if name == "stream" and self._live_thread is not None:
                self._live_thread.join(90)

    def _watch_live(self, job: Job) -> None:
        def client() -> None:
            try:
                url = job.proc.wait_line("live 3D view on ", 120, stream="err").split(" on ", 1)[1].split()[0]
                self.live = asyncio.run(_live_client(url))
            except BaseException as exc:  # noqa: BLE001 - reported by the cell
                self.live = exc
        self._live_thread = threading.Thread(target=client, daemon=True)
        self._live_thread.start()


_BATCHES: dict[str, Batch] = {}
_FORKERS: list[Forker] = []


def _forker(tmp: Path) -> Forker:
    """This process's `Forker`, started by the first batch it makes and kept for the others (its
    imports paid once a worker, not once a batch); closed, and waited for, when this process ends."""
    if not (_FORKERS and _FORKERS[-1].alive()):
        if not _FORKERS:
            atexit.register(_close_forkers)
        _FORKERS.append(Forker(PY, ROOT, ENV, tmp))
    return _FORKERS[-1]


def _close_forkers() -> None:
    for f in _FORKERS:
        f.close()


@pytest.fixture
def batch(request, tmp_path_factory):
    transport = request.param
    if transport == "udp_multicast":
        _udp_available()
    if transport not in _BATCHES:
        base = tmp_path_factory.getbasetemp()
        root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base  # shared by the workers
        _BATCHES[transport] = Batch.load(transport, root)
    return _BATCHES[transport]


def _udp_available() -> None:
    try:
        import can
        b = can.Bus(interface="udp_multicast", channel="239.74.163.2")
        b.shutdown()
    except Exception as exc:  # noqa: BLE001 - no multicast route on this machine
        pytest.skip(f"udp_multicast not available here: {exc}")




def cells(feature: str):
    """pytest params for ``feature`` over every transport (not applicable ones skipped, with why)."""
    out = []
    for t in TRANSPORTS:
        marks = []
        if (feature, t) in NOT_APPLICABLE:
            marks.append(pytest.mark.skip(reason=f"not applicable: {NOT_APPLICABLE[(feature, t)]}"))
        out.append(pytest.param(t, id=t, marks=marks))
    return out


def _ok(job) -> None:
    assert "Traceback" not in job.stderr, job.stderr[-4000:]
    assert job.rc == 0, f"{job.name}: exit {job.rc}\n{job.stdout[-3000:]}\n{job.stderr[-4000:]}"


# ---------------------------------------------------------------------------------------------------
# the cells
# ---------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("batch", cells("stream"), indirect=True)
def test_stream(batch):
    job = batch.jobs["stream"]
    _ok(job)
    doc = job.json()
    s = doc["summary"]
    # every chip's calibration read: its own or the nominal values it reports
    m = re.search(r"12 chips found, 12 assigned, 12 configured, (\d+) calibrated"
                  r"(?: \((\d+) nominal: no calibration of their own\))?, 12 started", job.stderr)
    assert m and int(m[1]) + int(m[2] or 0) == 12, job.stderr[-3000:]
    assert s["snapshots"] >= 10 and s["valid_links_pct"] >= 95.0, s
    assert s["errors"] == {} and s["foreign_syncs"] == 0 and doc["buses"][0]["capture_errors"] == 0, doc


def _here(capsys, argv: list[str]) -> tuple[int, str, str]:
    """``capsheet ARGV`` through its entry point in this process: (exit status, stdout, stderr). The
    root logging handlers a command sets are put back (as tests/host/cli/conftest.py's ``cli_here``)."""
    import logging

    from host.cli import main
    root = logging.getLogger()
    handlers, level, switch = list(root.handlers), root.level, sys.getswitchinterval()
    capsys.readouterr()
    try:
        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    finally:
        root.handlers[:] = handlers
        root.setLevel(level)
        sys.setswitchinterval(switch)
    got = capsys.readouterr()
    return code, got.out, got.err


@pytest.mark.parametrize("batch", cells("record-replay"), indirect=True)
def test_record_replay(batch, capsys):
    """The recording made on the transport, replayed by ``capsheet replay`` through its entry point
    in this process (what is under test per transport is the recording; replay runs through a real
    process in tests/host/test_imu_cli.py's 6-axis recording and tests/host/record/test_untrusted_files.py)."""
    _ok(batch.jobs["stream"])
    code, stdout, stderr = _here(capsys, ["replay", str(batch.tmp / "stream.mcap"), "--json", "-q", "--no-estimate"])
    assert code == 0, stderr
    r = json.loads(stdout)
    recorded = batch.jobs["stream"].json()["aggregator"]["emitted"]
    assert r["recorded_snapshots"] == recorded >= 10
    assert r["snapshots_identical"] == r["snapshots_compared"] == recorded, r
    assert all(not e for e in r["decode_errors"].values()), r["decode_errors"]


def _cantools(capsys, monkeypatch, argv: list[str], stdin: str) -> tuple[int, str, str]:
    """``cantools ARGV`` (``python -m cantools``, run by runpy as the interpreter runs it) in this process,
    reading ``stdin``: (exit status, stdout, stderr). A process of its own took ~2 s of CPU, most of
    it importing every cantools subcommand, and proved nothing more about the log it decodes."""
    import io
    import runpy

    monkeypatch.setattr(sys, "argv", ["cantools", *argv])
    monkeypatch.setattr(sys, "stdin", io.StringIO(stdin))
    capsys.readouterr()
    try:
        runpy.run_module("cantools", run_name="__main__", alter_sys=True)
        code = 0
    except SystemExit as exc:  # its errors: sys.exit("error: ...")
        code = exc.code if isinstance(exc.code, int) else 1
        print(exc.code, file=sys.stderr)
    got = capsys.readouterr()
    return code, got.out, got.err


@pytest.mark.parametrize("batch", cells("can-log"), indirect=True)
def test_can_log_decoded_by_cantools(batch, capsys, monkeypatch):
    from protocol.dbc import DBC_ID_MASK, DBC_PATH
    job = batch.jobs["stream"]
    _ok(job)
    log = (batch.tmp / "stream.log").read_text()
    lines = [ln for ln in log.splitlines() if ln.strip()]
    code, stdout, stderr = _cantools(capsys, monkeypatch,
                                     ["decode", "--single-line", "-m", hex(DBC_ID_MASK), str(DBC_PATH)], log)
    assert code == 0, stderr
    decoded = [ln for ln in stdout.splitlines() if ln.strip()]
    assert len(decoded) == len(lines) and not [ln for ln in decoded if "Unknown frame" in ln or "::" not in ln]
    logged = int(job.stderr.split("logged ", 1)[1].split(" CAN frames", 1)[0])
    assert logged == len(lines) > 100
    tx = [ln for ln in decoded if ") can0 " in ln and " T " in ln]
    rx = [ln for ln in decoded if " R " in ln]
    assert sum(" SYNC(" in ln for ln in tx) >= 10 and sum(" SAMPLE(" in ln for ln in rx) >= 100
    assert not [ln for ln in rx if " SYNC(" in ln]  # an echo of the host's own SYNC is its Tx, not an Rx


def _outcomes(job) -> dict[int, str]:
    """``{check: PASS/FAIL/SKIP/LOST}`` of a conformance run's report."""
    return {int(ln.split()[1]): ln.split()[0] for ln in job.stdout.splitlines()
            if ln[:4] in ("PASS", "FAIL", "SKIP", "LOST")}


@pytest.mark.parametrize("batch", cells("conformance"), indirect=True)
def test_conformance_passes_a_healthy_chip_and_fails_a_mutant(batch):
    from host.conformance.runner import select
    kind = "can" if batch.transport in CAN else "serial"
    every = {c.number for c in select(None, "chip") if c.transport in (None, kind)}  # what a full run runs
    healthy = [batch.jobs[f"conformance{k}"] for k in range(len(HEALTHY_ONLY))]
    outcome: dict[int, str] = {}
    for job in healthy:
        _ok(job)
        assert " 0 failed" in job.stdout and "LOST" not in job.stdout, job.stdout
        for check, verdict in _outcomes(job).items():
            assert outcome.setdefault(check, verdict) == verdict, (check, job.stdout)
    assert set(outcome) == every, sorted(every ^ set(outcome))  # the runs together: the whole suite
    passed = {k for k, v in outcome.items() if v == "PASS"}
    assert {1, 15, 24, 25, 26, 27, 29, 39, 40} <= passed, outcome
    if batch.transport in CAN:
        assert {22, 41} <= passed, outcome
    mutant: dict[int, str] = {}
    for k in range(len(MUTANT_ONLY)):
        job = batch.jobs[f"mutant{k}"]
        assert job.rc == 1 and "Traceback" not in job.stderr, job.stdout + job.stderr
        for check, verdict in _outcomes(job).items():
            assert mutant.setdefault(check, verdict) == verdict, (check, job.stdout)
    assert mutant == {1: "PASS", 24: "FAIL", 25: "FAIL", 26: "FAIL", 27: "FAIL", 29: "PASS"}, mutant
    assert {k for k, v in mutant.items() if v == "FAIL"} == MUTANT_FAILS


@pytest.mark.parametrize("batch", cells("calibrate"), indirect=True)
def test_calibrate_writes_the_chips_and_reads_them_back(batch):
    job = batch.jobs["calibrate"]
    _ok(job)
    assert "12 chips written, 12 read back and verified, 0 refused, 0 axis mismatches" in job.stderr, job.stderr


@pytest.mark.parametrize("batch", cells("calibration-host"), indirect=True)
def test_host_calibration_changes_the_estimate_by_what_the_chip_errors_predict(batch):
    """The same realistic, noise-free chips streamed without and with ``--calibration`` (their true
    errors): the calibrated snapshots are the uncalibrated ones corrected exactly once, and the
    estimate moves by what estimating the sheet's own readings with and without the errors gives."""
    from host.analysis.calibration import Calibration
    from host.record.recording import read
    for name in ("stream", "calibration"):
        _ok(batch.jobs[name])
    raw, fixed = read(batch.tmp / "stream.mcap"), read(batch.tmp / "calibrated.mcap")
    cal = Calibration.load(batch.cal_path)
    assert "host_calibration.json" in fixed.attachments and "host_calibration.json" not in raw.attachments
    for rec in (raw, fixed):  # what the cell compares: a complete snapshot, and an estimate of one
        complete = {int(c) for c, ok in zip(rec.counter, rec.complete) if ok}
        assert complete & {int(c) for c in rec.estimates["counter"]}, (len(rec), len(complete))
    # noise-free static chips: every complete snapshot alike, an estimate of one with every link
    r_raw, r_fixed = (rec.readings[np.flatnonzero(rec.complete)[-1]].astype(float) for rec in (raw, fixed))
    np.testing.assert_allclose(r_fixed, cal.apply(r_raw), rtol=0, atol=2e-5)
    sheet = realistic_sheet()
    r = nominal_readings(sheet)
    np.testing.assert_allclose(r_raw, r, rtol=0, atol=2e-5)  # what the chips send, converted as they say
    predicted = side_pct(shape_of(r), shape_of(cal.apply(r)))
    measured = side_pct(*(last_complete_estimate(rec) for rec in (raw, fixed)))
    assert predicted > 0.2  # the errors matter: the cell can tell applied from not applied
    assert abs(measured - predicted) <= 0.1 * predicted, (measured, predicted)


@pytest.mark.parametrize("transport", cells("calibration-demo"))
def test_demo_calibration_changes_the_estimate_by_what_it_predicts(transport, tmp_path):
    """``capsheet demo`` (ideal chips) with a calibration of realistic chip errors applied: its error
    against the truth is what estimating the truth's readings corrected by that calibration gives,
    far from the ideal chips' own (the demo once estimated from the aggregator's queue, past the
    correction: 0.038 % with it, 0.036 % without)."""
    from host.analysis.calibration import Calibration
    from virtual_sheet.geometry import ideal_readings
    from virtual_sheet.sheet import VirtualSheet
    cal_path = truth_calibration(realistic_sheet()).save(tmp_path / "cal.json")
    # 1 s at 30 Hz: ~30 snapshots of a sheet whose every snapshot is alike (noise 0, static), for
    # the one estimate compared with the truth the cell needs
    out = subprocess.run([PY, "-m", "host.cli", "demo", "--shape", "gaussian", "--lattice", LATTICE, "--noise", "0",
                          "--rate", "30", "--duration", "1", "--target", "50", "--min-complete", "0", "--json",
                          "--calibration", str(cal_path), "--out", str(tmp_path / "demo.png")],
                         cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert out.returncode == 0 and "Traceback" not in out.stderr, out.stderr[-3000:]
    result = json.loads(out.stdout)
    truth = VirtualSheet("gaussian", LATTICE, seed=1).joints(0.0)
    cal = Calibration.load(cal_path)
    ideal = ideal_readings(truth)
    floor = side_pct(shape_of(ideal), truth)
    predicted = side_pct(shape_of(cal.apply(ideal)), truth)
    assert predicted > 5 * floor + 0.2
    assert result["compared_with_truth"] >= 1
    assert abs(result["mean_error_pct_side"] - predicted) <= 0.1 * predicted, (result["mean_error_pct_side"], predicted)


@pytest.mark.parametrize("batch", cells("tactile"), indirect=True)
def test_tactile_on_a_port(batch):
    from host.record.recording import read
    job = batch.jobs["tactile"]
    _ok(job)
    rec = read(batch.tmp / "tactile.mcap")
    n_est = len(rec.estimates["counter"])
    assert n_est >= 1 and len(rec.contacts) == n_est  # every frame's estimate and contacts recorded
    assert len(rec) >= n_est and len(rec.raw[0]) >= 1  # every snapshot the host emitted, and the raw input
    assert (batch.tmp / "tactile.png").stat().st_size > 10_000


@pytest.mark.parametrize("batch", cells("live"), indirect=True)
def test_live_serves_a_foxglove_client(batch):
    _ok(batch.jobs["stream"])
    got = batch.live
    assert isinstance(got, dict) and all(len(got[t]) >= 2 for t in LIVE_TOPICS), got
    snap = got["/capsheet/snapshot"][-1]  # the chips' counts (capsheet.v2.Snapshot), 12 links
    assert snap["n_links"] == 12 and len(snap["counts"]) == 12 * 3
    assert len(base64.b64decode(snap["status"])) == 12
    assert len(got["/capsheet/estimate"][-1]["joints"]) == 3 * 3 * 3


def test_the_docs_table_is_this_matrix():
    """docs/host.md's matrix table lists every cell: the runs here, the others with their reason."""
    text = (ROOT / "docs/host.md").read_text()
    table = text.split("<!-- matrix -->", 2)[1]
    rows = {ln.split("|")[1].strip().strip("`"): [c.strip() for c in ln.split("|")[2:-1]]
            for ln in table.splitlines() if ln.startswith("| ") and not ln.startswith("| feature")}
    assert set(rows) == set(CELLS)
    for feature, cols in rows.items():
        assert len(cols) == len(TRANSPORTS) + 1, (feature, cols)
        for t, cell in zip(TRANSPORTS, cols):
            reason = NOT_APPLICABLE.get((feature, t))
            assert (cell == f"n/a: {reason}") if reason else cell == "runs", (feature, t, cell)
