"""Which port is my sheet? The ports a machine has, and what answers on each (``capsheet ports``).

Listing: every serial port pyserial's ``serial.tools.list_ports`` sees (device, USB vendor:product,
serial number, description) and every CAN channel python-can's ``detect_available_configs`` finds
(`list_serial`, `list_can`), plus paths a user names (a pty, a symlink).

Probing, read-only: the probe opens the port as a session does (exclusively: a port another session
holds is reported as in use and not opened, `host.transport.portlock`), asks every node who it is
with the broadcast GET_INFO a host's discovery sends (docs/protocol.md §4.2: every chip and every
gateway node answers ANNOUNCE and INFO, a gateway GATEWAY_INFO as well, §4.16), and listens. It
never sends ASSIGN, CONFIG, START, STOP or RESET: a sheet that was streaming for another host goes
on streaming. What it hears is summed up by the sans-I/O `ProbeCollector` (events in, with the time
they were read; a `ProbeResult` out), so the summary is tested without a port.

A serial port is tried at the baud rates a gateway uses (`SERIAL_BAUDS`: the host's 3 Mbaud
default first, then 12 Mbaud, docs/protocol.md §10, then common slower ones) until one answers; a
pty ignores the baud rate and answers at the first. A path where nothing decodes is tried once more
as an SLCAN adapter at 1 Mbit/s (`SLCAN_BITRATE`): opening an SLCAN channel sends the adapter its
setup (close, bit rate, open), never a frame to the chips beyond GET_INFO. A CAN channel is probed
at the bit rate its interface is set to (SocketCAN: the system's ``ip link`` setting) or at
1 Mbit/s where python-can needs one.

Every port's probe is bounded by its time budget (`probe_port`'s ``budget_s``), split over its
attempts. `probe_ports` probes the ports at once, one thread and transport each, so a machine with
several silent ports waits one budget, not their sum; the paths that lead to the same device (a
symlink and its target, a pty and ``slcan:`` on it) are probed one after another in one thread,
since a probe holds its port exclusively. The results come back in the listing's order.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import asdict, dataclass, field

from protocol.framing import DecodeError
from protocol.messages import (SAMPLE_FORMAT_CODES, Announce, Capability, GatewayFlag, GatewayInfo, GetInfo, ImuBatch, Info,
                               SampleBatch, SampleFormat, SnapshotFrames, Sync)

__all__ = ["PortEntry", "ProbeResult", "ProbeCollector", "list_serial", "list_can", "probe_port", "probe_ports", "ask",
           "SERIAL_BAUDS", "SLCAN_BITRATE", "CAN_SKIPPED_INTERFACES"]

#: serial baud rates a probe tries, in order (a pty answers at the first)
SERIAL_BAUDS = (3_000_000, 12_000_000, 1_000_000, 921_600, 115_200)
#: the bit rate an SLCAN adapter (or a CAN interface that needs one) is probed at, bit/s
SLCAN_BITRATE = 1_000_000
#: python-can interfaces `list_can` does not ask: in-process or network buses that are no hardware
#: (``virtual``, ``udp_multicast``, capsheet's own), tty adapters found as serial ports already
#: (``slcan``, ``serial``, ``robotell``, ``seeedstudio``), and ``socketcand``, which listens 4 s
#: for network beacons
CAN_SKIPPED_INTERFACES = frozenset({"virtual", "udp_multicast", "capsheet_udp_multicast", "capsheet_slcan",
                                    "slcan", "serial", "robotell", "seeedstudio", "socketcand"})
#: how long a probe listens after the last new answer before it stops early, s
QUIET_S = 0.25
#: GET_INFO is asked this often while nothing answered (a chip may miss one while booting), s
ASK_EVERY_S = 0.3


@dataclass
class PortEntry:
    """One port or channel listed (and probed).

    Attributes
    ----------
    kind : str
        ``"serial"`` or ``"can"``.
    name : str
        What to give ``--port`` (a device path) or ``--can`` (``interface:channel``).
    target : str or None
        Where a path leads (symlinks followed), when it differs from ``name``.
    usb : str or None
        ``"vvvv:pppp"`` of a USB adapter.
    serial_number, description : str or None
        As ``list_ports`` reports them.
    source : str
        ``"list_ports"``, ``"python-can"`` or ``"argument"`` (a path given on the command line).
    probe : ProbeResult or None
        What answered (``--probe``).
    """

    kind: str
    name: str
    target: str | None = None
    usb: str | None = None
    serial_number: str | None = None
    description: str | None = None
    source: str = "argument"
    probe: "ProbeResult | None" = None

    def as_dict(self) -> dict:
        d = asdict(self)
        d["probe"] = None if self.probe is None else self.probe.as_dict()
        return d

    def line(self) -> str:
        """The port in one line (without its probe)."""
        s = self.name + (f" (-> {self.target})" if self.target else "")
        extra = [x for x in (f"USB {self.usb}" if self.usb else None,
                             f"serial number {self.serial_number}" if self.serial_number else None,
                             self.description if self.description and self.description != "n/a" else None) if x]
        return s + (": " + ", ".join(extra) if extra else "")


@dataclass
class ProbeResult:
    """What answered on one port (`ProbeCollector.result`).

    ``status``: ``"answered"`` (at least one chip or gateway node announced), ``"silent"`` (nothing
    capsheet decodes), ``"traffic"`` (capsheet frames but no node answered GET_INFO: SYNC or samples
    of a sheet streaming for a host that is gone), ``"in_use"`` (another session holds it: not
    probed), ``"error"`` (it could not be opened); ``detail`` says it in words.
    """

    status: str
    detail: str = ""
    chips: int = 0
    chip_uids: list = field(default_factory=list)  #: hex strings, sorted
    gateways: list = field(default_factory=list)  #: dicts: uid, flags, sample_format, links, sync_rate_hz
    firmware: list = field(default_factory=list)  #: "major.minor.patch" of the chips, sorted
    protocol: list = field(default_factory=list)  #: wire protocol versions (INFO protocol_version), sorted
    formats: list = field(default_factory=list)  #: sample formats heard or announced (SampleFormat names)
    capabilities: list = field(default_factory=list)  #: Capability names any chip has
    baud: int | None = None  #: the serial baud rate that answered
    bitrate: int | None = None  #: the CAN bit rate probed
    as_slcan: bool = False  #: a path that answered as an SLCAN adapter (give it as --can slcan:PATH)
    syncs: int = 0  #: SYNC frames heard (a gateway's own, or another host's)
    samples: int = 0  #: sample records heard (the sheet is streaming)
    undecodable: int = 0  #: framing errors
    bytes_in: int = 0
    elapsed_s: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self)

    def line(self) -> str:
        """The probe in one line."""
        if self.status != "answered":
            return self.detail
        parts = [f"{self.chips} chip{'s' if self.chips != 1 else ''}"]
        if self.chip_uids:
            parts[0] += (f" (ids {self.chip_uids[0]}" + (f" .. {self.chip_uids[-1]}" if self.chips > 1 else "") + ")")
        for g in self.gateways:
            what = [w for w in ("packs SNAPSHOT" if "PACKING" in g["flags"] else None,
                                f"SYNC source at {g['sync_rate_hz']} Hz" if "SYNC_SOURCE" in g["flags"] else None) if w]
            parts.append(f"gateway {g['uid']} (links {g['links']}, {g['sample_format']}"
                         + (", " + ", ".join(what) if what else "") + ")")
        if self.formats:
            parts.append("format " + "/".join(self.formats))
        if self.firmware:
            parts.append("firmware " + "/".join(self.firmware))
        if self.protocol:
            parts.append("protocol " + "/".join(self.protocol))
        if self.baud:
            parts.append(f"at {self.baud} baud")
        if self.as_slcan:
            parts.append(f"SLCAN adapter at {self.bitrate} bit/s (--can slcan:PATH)")
        elif self.bitrate:
            parts.append(f"at {self.bitrate} bit/s")
        if self.samples:
            parts.append("streaming (samples heard)")
        elif self.syncs:
            parts.append("SYNC heard")
        return ", ".join(parts)


class ProbeCollector:
    """Sans-I/O: the events a probe read, in order, with the time each read returned (``now``, s);
    what they say (`result`), and whether the port has gone quiet (`quiet`). A node answers GET_INFO
    with ANNOUNCE (its uid), then INFO (and a gateway GATEWAY_INFO) from the same node id: each
    INFO and GATEWAY_INFO belongs to the uid its node last announced (provisional node ids may
    repeat across chips; uids do not).

    >>> c = ProbeCollector()
    >>> c.feed([Announce(0x8001, uid=0xAB), Info(0x8001, fw_major=1, protocol_version=1)], now=0.1)
    >>> r = c.result(elapsed_s=0.4)
    >>> r.status, r.chips, r.chip_uids, r.firmware, r.protocol
    ('answered', 1, ['0x00000000000000AB'], ['1.0.0'], ['1'])
    >>> c.quiet(0.3), c.quiet(0.36)
    (False, True)
    """

    def __init__(self) -> None:
        self.node_uid: dict[int, int] = {}  # node -> the uid it last announced
        self.uids: set[int] = set()
        self.info: dict[int, Info] = {}  # uid -> INFO
        self.gw_runs: dict[int, dict] = {}  # uid -> (first_link, link_count) -> GATEWAY_INFO
        self.syncs = 0
        self.samples = 0
        self.undecodable = 0
        self.formats: set[str] = set()
        self.last_new: float | None = None  # when something new was last heard

    def feed(self, events, now: float) -> None:
        """Take one read's events."""
        for ev in events:
            if isinstance(ev, DecodeError):
                self.undecodable += 1
            elif isinstance(ev, Announce):
                self.node_uid[ev.node] = ev.uid
                if ev.uid not in self.uids:
                    self.uids.add(ev.uid)
                    self.last_new = now
            elif isinstance(ev, Info):
                uid = self.node_uid.get(ev.node)
                if uid is not None and uid not in self.info:
                    self.info[uid] = ev
                    self.last_new = now
            elif isinstance(ev, GatewayInfo):
                uid = self.node_uid.get(ev.node)
                runs = self.gw_runs.setdefault(uid if uid is not None else -ev.node, {})
                if (ev.first_link, ev.link_count) not in runs:
                    runs[(ev.first_link, ev.link_count)] = ev
                    self.last_new = now
            elif isinstance(ev, Sync):
                self.syncs += 1
            elif isinstance(ev, SampleBatch):
                self.samples += len(ev)
                self.formats.add(SampleFormat.ACCEL_12.name)
            elif isinstance(ev, ImuBatch):
                self.samples += len(ev)
                self.formats.add("IMU")
            elif isinstance(ev, SnapshotFrames):
                self.samples += len(ev)

    @property
    def answered(self) -> bool:
        return bool(self.uids)

    def quiet(self, now: float) -> bool:
        """Something answered and nothing new came for `QUIET_S`."""
        return self.last_new is not None and now - self.last_new >= QUIET_S

    def result(self, elapsed_s: float = 0.0, bytes_in: int = 0) -> ProbeResult:
        gateways = {u for u, i in self.info.items() if i.capabilities & Capability.GATEWAY} | set(self.gw_runs)
        chips = sorted(self.uids - gateways)
        infos = [self.info[u] for u in chips if u in self.info]
        gws = []
        for uid in sorted(gateways):
            for g in sorted(self.gw_runs.get(uid, {}).values(), key=lambda g: g.first_link) or [None]:
                fmt = "?" if g is None else (SampleFormat(g.sample_format).name
                                             if g.sample_format in SAMPLE_FORMAT_CODES
                                             else str(g.sample_format))
                gws.append({"uid": f"0x{uid:016X}" if uid >= 0 else f"node 0x{-uid:04X}",
                            "flags": [] if g is None else [f.name for f in GatewayFlag if f and f in g.flags],
                            "sample_format": fmt,
                            "links": "?" if g is None or not g.link_count else
                            f"{g.first_link}-{g.first_link + g.link_count - 1}",
                            "sync_rate_hz": 0 if g is None else g.sync_rate_hz})
        formats = set(self.formats) | {g["sample_format"] for g in gws if g["sample_format"] != "?"}
        caps = Capability(0)
        for i in infos:
            caps |= i.capabilities
        r = ProbeResult(
            status="answered" if (chips or gws) else ("traffic" if (self.syncs or self.samples) else "silent"),
            chips=len(chips), chip_uids=[f"0x{u:016X}" for u in chips], gateways=gws,
            firmware=sorted({f"{i.fw_major}.{i.fw_minor}.{i.fw_patch}" for i in infos}),
            protocol=sorted({str(i.protocol_version) for i in self.info.values()}),
            formats=sorted(formats), capabilities=[c.name for c in Capability if c and c in caps],
            syncs=self.syncs, samples=self.samples, undecodable=self.undecodable, bytes_in=bytes_in,
            elapsed_s=round(elapsed_s, 3))
        if r.status == "traffic":
            r.detail = (f"no node answered GET_INFO in {elapsed_s:.1f} s, but capsheet frames are on it ({r.syncs} "
                        f"SYNC, {r.samples} samples): a sheet streaming for a host that is gone?")
        elif r.status == "silent":
            r.detail = (f"nothing answered in {elapsed_s:.1f} s ({bytes_in} bytes"
                        + (f", {r.undecodable} undecodable" if r.undecodable else "") + ")")
        return r


# ------------------------------------------------------------------------------------------------
# listing
# ------------------------------------------------------------------------------------------------

def list_serial() -> list[PortEntry]:
    """Every serial port pyserial's ``list_ports`` sees, in its order."""
    from serial.tools import list_ports
    out = []
    for p in list_ports.comports():
        out.append(PortEntry("serial", p.device, usb=f"{p.vid:04x}:{p.pid:04x}" if p.vid is not None else None,
                             serial_number=p.serial_number or None, description=p.description or None,
                             source="list_ports"))
    return out


def list_can() -> list[PortEntry]:
    """Every CAN channel python-can's ``detect_available_configs`` finds on the interfaces that can
    say (`CAN_SKIPPED_INTERFACES` are not asked); ``[]`` without python-can."""
    try:
        import can
        from can.interfaces import VALID_INTERFACES
    except ImportError:
        return []
    quiet = logging.getLogger("can")
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)  # interfaces whose vendor library is missing say so on import
    try:
        configs = can.detect_available_configs(interfaces=sorted(set(VALID_INTERFACES) - CAN_SKIPPED_INTERFACES))
    except Exception:  # noqa: BLE001 - a vendor driver's failure lists nothing, not a traceback
        configs = []
    finally:
        quiet.setLevel(level)
    out, seen = [], set()
    for c in configs:
        name = f"{c.get('interface')}:{c.get('channel')}"
        if name not in seen:
            seen.add(name)
            out.append(PortEntry("can", name, source="python-can"))
    return out


def argument_entry(path: str) -> PortEntry:
    """A path named on the command line, with what ``list_ports`` knows of its device."""
    target = os.path.realpath(path)
    e = PortEntry("serial", path, target=target if target != path else None, source="argument")
    try:
        from serial.tools import list_ports
        for p in list_ports.comports():
            if os.path.realpath(p.device) == target:
                e.usb = f"{p.vid:04x}:{p.pid:04x}" if p.vid is not None else None
                e.serial_number, e.description = p.serial_number or None, p.description or None
    except Exception:  # noqa: BLE001
        pass
    return e


# ------------------------------------------------------------------------------------------------
# probing (I/O)
# ------------------------------------------------------------------------------------------------

def ask(transport, budget_s: float, clock=time.monotonic) -> ProbeCollector:
    """Ask GET_INFO (again every `ASK_EVERY_S` while nothing answered) and collect until the answers
    stop (`QUIET_S`) or ``budget_s`` is spent."""
    c = ProbeCollector()
    t0 = clock()
    next_ask = t0
    while True:
        now = clock()
        if now - t0 >= budget_s or c.quiet(now):
            break
        if now >= next_ask and not c.answered:
            transport.send(GetInfo(0))
            next_ask = now + ASK_EVERY_S
        c.feed(transport.recv(min(0.05, max(0.0, budget_s - (now - t0)))), clock())
    return c


def probe_port(entry: PortEntry, budget_s: float = 2.0, clock=time.monotonic) -> ProbeResult:
    """Probe one port or channel (module docstring), within ``budget_s`` seconds of listening."""
    from host.transport.portlock import holders, in_use_message, is_device_path
    from host.transport.ports import PortInUseError, SerialTransport, TransportError

    t0 = clock()
    if entry.kind == "serial":
        if is_device_path(entry.name):
            found = holders(entry.name)
            if found:
                return ProbeResult("in_use", in_use_message(entry.name, found) + ": not probed")
        per_try = max(0.4, budget_s / 3)
        last: ProbeResult | None = None
        bytes_in = 0
        for baud in SERIAL_BAUDS:
            left = budget_s - (clock() - t0)
            if left <= 0.05:
                break
            try:
                t = SerialTransport(entry.name, baudrate=baud, reconnect=False)
            except PortInUseError as exc:
                return ProbeResult("in_use", f"{exc}: not probed")
            except TransportError as exc:
                return ProbeResult("error", str(exc))
            try:
                c = ask(t, min(per_try, left), clock)
                bytes_in += t.stats.bytes_in
            except TransportError as exc:
                return ProbeResult("error", str(exc))
            finally:
                t.close()
            r = c.result(clock() - t0, bytes_in)
            if r.status != "silent":
                r.baud = baud
                return r
            last = r
            if not is_device_path(entry.name) or _is_pty(entry.name):
                break  # a URL or a pty ignores the baud rate: one try says it all
        left = budget_s - (clock() - t0)
        if is_device_path(entry.name) and left > 0.2:
            r = _probe_can(f"slcan:{entry.name}", left, clock, t0, slcan=True)
            if r.status in ("answered", "traffic"):
                return r
        return last if last is not None else ProbeResult("silent", f"nothing answered in {budget_s:.1f} s")
    return _probe_can(entry.name, budget_s, clock, t0)


def probe_ports(entries, budget_s: float = 2.0, probe=probe_port):
    """Probe every entry at once (module docstring) and yield ``(entry, result)`` in the entries'
    order, each as soon as it and every entry before it are done. ``probe(entry, budget_s=...)``
    is `probe_port` (a test's stand-in otherwise). A probe that raises is its entry's ``"error"``
    result (``"probe failed: ..."``), not the others' end. The threads are daemons: an interrupt
    (the caller's KeyboardInterrupt) ends the command without waiting for the ports' budgets.
    """
    entries = list(entries)
    results: list = [None] * len(entries)
    done = [threading.Event() for _ in entries]
    groups: dict = {}  # one device -> the indices of its entries, in order
    for i, e in enumerate(entries):
        groups.setdefault(_device_key(e), []).append(i)

    def work(indices):
        for i in indices:
            try:
                results[i] = probe(entries[i], budget_s=budget_s)
            except Exception as exc:  # noqa: BLE001 - one port's failure is its result, not the others'
                results[i] = ProbeResult("error", f"probe failed: {exc}")
            finally:
                done[i].set()

    for k, indices in enumerate(groups.values()):
        threading.Thread(target=work, args=(indices,), name=f"probe-{k}", daemon=True).start()
    for i, e in enumerate(entries):
        while not done[i].wait(0.2):  # in slices: the main thread stays interruptible (Ctrl-C)
            pass
        yield e, results[i]


def _device_key(entry: PortEntry):
    """What a probe of ``entry`` opens exclusively: the device a path leads to (an SLCAN channel's
    too), or the CAN channel's name.

    >>> import os
    >>> _device_key(PortEntry("can", "slcan:/dev/ttyACM0@115200")) == _device_key(PortEntry("serial", "/dev/ttyACM0"))
    True
    >>> _device_key(PortEntry("can", "socketcan:can0"))
    ('channel', 'socketcan:can0')
    """
    name = entry.name
    if entry.kind == "can":
        channel = name.partition(":")[2].split("@")[0]
        if "/" not in channel:
            return ("channel", name)
        name = channel
    if "://" in name:
        return ("url", name)
    return ("device", os.path.realpath(name))


def _is_pty(path: str) -> bool:
    try:
        return os.major(os.stat(path).st_rdev) in range(136, 144)  # Unix98 pty slaves (devices.txt)
    except OSError:
        return False


def _probe_can(spec: str, budget_s: float, clock, t0: float, slcan: bool = False) -> ProbeResult:
    """Probe ``spec`` for ``budget_s`` from now; the result's time is counted from ``t0``."""
    from host.transport.ports import CanTransport, PortInUseError, TransportError
    start = clock()
    interface = spec.partition(":")[0]
    bitrate = SLCAN_BITRATE if interface in ("slcan", "capsheet_slcan") else None
    kw = {"sleep_after_open": 0.05, "drain_quiet_s": 0.02} if bitrate else {}
    try:
        t = CanTransport(spec, bitrate=bitrate, reconnect=False, **kw)
    except PortInUseError as exc:
        return ProbeResult("in_use", f"{exc}: not probed")
    except TransportError as exc:
        return ProbeResult("error", str(exc))
    try:
        c = ask(t, budget_s - (clock() - start), clock)
        r = c.result(clock() - t0, t.stats.bytes_in)
        fd_frames = t.stats.errors.get("FD_ON_CLASSIC", 0)
    except TransportError as exc:
        return ProbeResult("error", str(exc))
    finally:
        t.close()
    r.bitrate = bitrate
    r.as_slcan = slcan
    if fd_frames and r.status == "silent":
        r.status, r.detail = "traffic", f"CAN FD frames heard ({fd_frames}): probe and run with --fd"
    return r
