"""Bring-up: from any state to streaming, one step at a time (`BringUp`): quiesce (STOP, drain,
RESET), discover, check what was found, assign, configure, read the chips' calibration, check the
buses' capacity, start — and what a bus over its capacity needs (`capacity_remedy`).

The chips' own calibration (CAL_DATA) and the host's (``capsheet calibrate``'s file, rebased to
the chips') are applied here, to the feed every consumer reads.
"""

from __future__ import annotations

import logging
from collections import Counter

import numpy as np

from protocol.capacity import bus_load
from protocol.constants import nominal_sensitivity
from protocol.framing import DecodeError
from protocol.messages import (CAL_BLOCK_SIZE, CalBlock, CalImuData, CalImuRead, Capability,
                               Ack, Assign, CalData, CalRead, Config, ConfigImu, GetInfo, ImuBatch,
                               MsgType, Nack, Reset, SampleBatch, SnapshotFrames, Start, StatusBatch, Stop, Sync)

from host.session.errors import CapacityError, MismatchError
from host.session.registry import ChipRecord, Layout, node_for_link

__all__ = ["BringUp", "capacity_remedy"]

log = logging.getLogger("capsheet.host")

#: discovery: a round's window lasts until no new chip was heard for this long (s) ...
DISCOVER_QUIET_S = 0.25
#: ... and at most this many times the window asked for
DISCOVER_MAX_STRETCH = 20

#: (packed, IMU records) -> the frames a bus's load is counted in (docs/protocol.md §10, §16)
_FRAMING = {(False, False): "SAMPLE", (True, False): "SNAPSHOT", (False, True): "IMU_SAMPLE",
            (True, True): "SNAPSHOT_IMU"}


def capacity_remedy(kind: str, load: float, rate_hz: float, *, packed: bool, fd: bool = False,
                    bitrate: int | None = None, split: str | None = None, pack: str | None = None,
                    faster: bool = True, imu: bool = False) -> str:
    """What takes a bus at ``load`` (1.0 = full) back under its capacity, for what is already set:
    packing where it is not on (``pack``: how the command says so, e.g. with the gateways packing
    needs; ``imu``: the chips send IMU records, which a gateway packs into SNAPSHOT_IMU, §16.5),
    more gateways or buses (``split``), a faster link (``faster``), or the highest rate that fits.

    >>> capacity_remedy("serial", 2.5, 145.0, packed=True, bitrate=12_000_000)
    'use more gateways (a --port each; at least 3), a link faster than 12 Mbaud (--baud), or --rate 58 or lower'
    >>> capacity_remedy("serial", 1.5, 145.0, packed=False, imu=True).split(", ")[0]
    'use --packed (SNAPSHOT_IMU frames from the gateway)'
    """
    ways = []
    k = int(np.ceil(load - 1e-9))
    if kind == "serial":
        if not packed:
            ways.append(pack or f"--packed ({'SNAPSHOT_IMU' if imu else 'SNAPSHOT'} frames from the gateway)")
        ways.append(split or f"more gateways (a --port each; at least {k})")
        if faster:
            ways.append("a link faster than " + (f"{bitrate / 1e6:g} Mbaud" if bitrate else "this one") + " (--baud)")
    else:
        if not (fd and packed):
            ways.append(pack or f"CAN FD with packed {'SNAPSHOT_IMU ' if imu else ''}frames (--fd --packed)")
        ways.append(split or f"more buses (a --can each; at least {k})")
    ways.append(f"--rate {int(rate_hz / load):d} or lower")
    return "use " + ", ".join(ways[:-1]) + ", or " + ways[-1]


class BringUp:
    """The steps from any state to streaming, for one `host.session.core.Host` (module docstring); each
    is also a `Host` method of the same name.

    Attributes
    ----------
    stale_frames : int
        Frames drained (discarded) by `quiesce`.
    discarding : bool
        `quiesce` is draining: what arrives now is counted and dropped (the receive path asks).
    calibration_reads : int
        `read_calibration` calls completed.
    capacity_report : list of dict
        What `bring_up`'s `check_capacity` found, one dict per bus.
    """

    def __init__(self, host) -> None:
        self.host = host
        self.stale_frames = 0
        self.discarding = False
        self.calibration_reads = 0
        self.capacity_report: list[dict] = []
        self._stale_chip_frames = 0  # of them, frames of chips (not SYNC, not undecodable)
        self._host_calibration = None  # as given to `set_calibration`
        self._live_calibration = None  # ... rebased to the chips' own calibration

    def bring_up(self, discover_timeout_s: float = 0.5, discover_rounds: int = 3, *, reset: bool = True,
                 strict: bool = False, capacity: str = "refuse", packed: bool = False) -> dict:
        """`Host.bring_up`."""
        host = self.host
        if reset:
            self.quiesce()
        found = self.discover(discover_timeout_s, discover_rounds)
        self.check_discovery(strict=strict)
        host.gateway_nodes.assign()
        self.assign()
        n_cfg = self.configure()
        if host.imu_config is not None:
            self.configure_imu()
        n_cal = self.read_calibration()
        n_imu_cal = self.read_imu_calibration() if host.imu_config is not None else None
        self.capacity_report = self.check_capacity(capacity, packed=packed)
        n_start = host.start()
        out = {"discovered": len(found), "assigned": len(host.registry.assigned()), "configured": n_cfg,
               "calibrated": n_cal, "started": n_start, "gateways": len(host.gateway_nodes.by_uid)}
        if n_imu_cal is not None:  # a 6/9-axis bring-up: chips whose §17 calibration was read
            out["imu_calibrated"] = n_imu_cal
        return out

    # -- quiesce ---------------------------------------------------------------------------
    def count_stale(self, events: list) -> None:
        """What arrived while `discarding`: counted, dropped."""
        for ev in events:
            k = len(ev) if isinstance(ev, (SampleBatch, ImuBatch, StatusBatch, SnapshotFrames)) else 1
            self.stale_frames += k
            if not isinstance(ev, (Sync, DecodeError)):
                self._stale_chip_frames += k

    def quiesce(self, quiet_s: float = 0.1, max_s: float = 3.0, reset: bool = True) -> int:
        """`Host.quiesce`."""
        host = self.host
        host.open()
        host.streaming.clear()
        host.awaiting_stream = True  # a following host takes no samples until it streams again
        before = self.stale_frames
        self.discarding = True
        try:
            for _ in range(2):  # STOP twice: a frame lost to a full buffer does not leave a chip streaming
                host.commands.broadcast(Stop(0))
                host.idle(0.01)
            t_end = host.now() + max_s
            last_n, last_t = self._stale_chip_frames, host.now()
            while host.now() < t_end:
                host.idle(min(0.01, quiet_s / 4))
                if self._stale_chip_frames != last_n:
                    last_n, last_t = self._stale_chip_frames, host.now()
                elif host.now() - last_t >= quiet_s:
                    break
            host.commands.drop_answers()
        finally:
            self.discarding = False
            host.sync_driver.listen_from(host.now())  # what is heard from here on counts (check_sync_source)
        if reset:
            host.registry.forget()
            host.gateway_nodes.forget()
            host.commands.broadcast(Reset(0))
        drained = self.stale_frames - before
        if drained:
            log.info("bring-up: drained %d stale frames left by a previous session", drained)
        return drained

    # -- discover, check -------------------------------------------------------------------
    def discover(self, timeout_s: float = 0.5, rounds: int = 2) -> dict[int, ChipRecord]:
        """`Host.discover`."""
        host, reg = self.host, self.host.registry
        host.open()
        for _ in range(rounds):
            host.commands.broadcast(GetInfo(0))
            start = host.now()
            with reg.lock:
                last = sum(1 for r in reg.chips.values() if r.info is not None)
            # before any chip was heard, the question is the last thing heard: like an answer it is
            # given DISCOVER_QUIET_S at least (a loaded machine's sheet may not answer a 50 ms window)
            deadline = start + (timeout_s if last else max(timeout_s, DISCOVER_QUIET_S))
            while host.now() < deadline:
                host.idle(0.01)
                with reg.lock:
                    layout = reg.layout
                    if layout is not None and all(u in reg.chips and reg.chips[u].info is not None
                                                  for u in layout.links):
                        return dict(reg.chips)
                    known = sum(1 for r in reg.chips.values() if r.info is not None)
                if known != last:
                    # answers still coming in: the window lasts until they stop for DISCOVER_QUIET_S
                    # (at most DISCOVER_MAX_STRETCH windows). 8,064 chips answer with 16,128 frames;
                    # on a loaded machine the host read them for longer than 0.5 s, and the chips
                    # whose answers it had not read by then were "missing" (1-2 in 3 of 8 runs)
                    last = known
                    deadline = max(deadline, min(host.now() + DISCOVER_QUIET_S,
                                                 start + DISCOVER_MAX_STRETCH * timeout_s))
        with reg.lock:
            return dict(reg.chips)

    def check_discovery(self, strict: bool = True) -> None:
        """`Host.check_discovery`."""
        host, reg = self.host, self.host.registry
        for bus, t in enumerate(host.transports):
            n_fd = t.stats.errors.get("FD_ON_CLASSIC", 0)
            if n_fd:
                raise MismatchError(f"{t.name} carries CAN FD frames ({n_fd} seen) but was opened for classic "
                                    f"CAN: add --fd")
        if reg.cross_bus_uids:
            # a chip sits behind one gateway: the same uids on two ports are one gateway opened twice
            # (or two sheets whose uids collide), never one lattice
            uid, buses = min(reg.cross_bus_uids.items())
            names = " and ".join(host.transports[b].name for b in sorted(buses))
            raise MismatchError(f"{len(reg.cross_bus_uids)} chip(s) answer on more than one port, e.g. uid "
                                f"0x{uid:016X} on {names}: the ports reach the same chips (one gateway "
                                f"named twice?); give each gateway of the sheet once")
        if reg.layout is None or not reg.chips:
            return  # no chip answered at all: the port (or the sheet's power), not the layout: the caller says so
        with reg.lock:
            found = set(reg.chips)
            missing = sorted(((k, u) for u, k in reg.layout.links.items() if u not in found))
            unknown = sorted(found - set(reg.layout.links))
        # a port none of whose chips is in the layout: a gateway of another sheet (or a layout
        # for another lattice): said beside whichever mismatch is raised
        hint = ""
        if unknown and len(host.transports) > 1:
            with reg.lock:
                per_port = Counter(reg.chips[u].bus for u in unknown)
                alien = [host.transports[b].name for b, c in sorted(per_port.items())
                         if c == sum(1 for r in reg.chips.values() if r.bus == b)]
            if alien:
                hint = (f"; none of the chips on {', '.join(alien)} is in the layout (a gateway of another "
                        f"sheet, or a layout for another lattice?)")
        for k, u in missing:
            host.report("missing_chip", f"layout chip 0x{u:016X} (link {k}) did not answer", quiet=True,
                        link=k, uid=u)
        if missing:
            names = ", ".join(f"link {k} (uid 0x{u:016X})" for k, u in missing[:5])
            more = f" and {len(missing) - 5} more" if len(missing) > 5 else ""
            msg = f"{len(missing)} layout chip(s) never answered: {names}{more}{hint}"
            if strict:
                raise MismatchError(msg + " (check the layout file; --allow-missing streams without them)")
            log.warning("%s", msg)
        if unknown:
            names = ", ".join(f"uid 0x{u:016X} (on {host.transports[reg.chips[u].bus].name}, node "
                              f"0x{reg.chips[u].node:04X})" for u in unknown[:5])
            more = f" and {len(unknown) - 5} more" if len(unknown) > 5 else ""
            msg = f"{len(unknown)} announcing chip(s) are not in the layout: {names}{more}{hint}"
            if strict:
                raise MismatchError(msg + " (wrong layout file? --allow-missing streams without them)")
            log.warning("%s", msg)

    # -- assign, configure, calibrate, start -----------------------------------------------
    def assign(self, layout: Layout | None = None, uids=None) -> dict[int, ChipRecord]:
        """`Host.assign`."""
        host, reg = self.host, self.host.registry
        lattice = host.lattice
        if layout is not None:
            reg.layout = layout
        with reg.lock:
            if reg.layout is None:
                runs = {}
                for b in {rec.bus for rec in reg.chips.values()}:
                    on_bus = host.gateway_nodes.runs_on(b)
                    if on_bus:
                        runs.update({u: on_bus for u, rec in reg.chips.items() if rec.bus == b})
                reg.layout = Layout.auto(list(reg.chips), lattice, runs=runs)
            links = reg.layout.links
            todo = {}
            for uid, rec in reg.chips.items():
                if uids is not None and uid not in uids:
                    continue
                link = links.get(uid)
                if link is None:
                    if uid not in reg.unknown_chips:
                        reg.unknown_chips.add(uid)
                        host.report("unknown_chip", f"chip 0x{uid:016X} is not in the layout", uid=uid,
                                    quiet=len(reg.unknown_chips) > 1)
                    continue
                if link >= lattice.n_links:
                    raise ValueError(f"Layout puts chip 0x{uid:016X} on link {link}, but lattice "
                                     f"{lattice.rows}x{lattice.cols} has {lattice.n_links} links")
                rec.link = link
                todo[uid] = link

        def build(uid, attempt):
            rec = reg.chips.get(uid)
            if rec is None:  # its record was dropped during the round (a gateway node's INFO came late)
                return []
            new = node_for_link(rec.link)
            msgs = [(rec.bus, Assign(rec.node, new_node=new, link=rec.link, uid_low=uid & 0xFFFFFFFF))]
            if attempt and rec.node != new:  # the ACK may have been lost: ask the new node too
                msgs.append((rec.bus, Assign(new, new_node=new, link=rec.link, uid_low=uid & 0xFFFFFFFF)))
            return msgs

        by_new = {node_for_link(link): uid for uid, link in todo.items()}

        def match(bus, msg):
            if msg.command != MsgType.ASSIGN:
                return None
            if isinstance(msg, Ack):
                return by_new.get(msg.node)
            return reg.uid_at(bus, msg.node)

        answers, _ = host.commands.round(todo, build, match, "ASSIGN")
        with reg.lock:
            for uid, msg in answers.items():
                if isinstance(msg, Ack) and uid in reg.chips:
                    reg.assigned_to(reg.chips[uid], msg.node)
        # outside the registry's lock: a receive thread holds the feed's and then takes the
        # registry's (tests/host/session/test_lock_order.py)
        self.apply_map()
        return dict(reg.chips)

    def configure(self, uids=None) -> int:
        """`Host.configure`."""
        host = self.host
        ok = host.commands.simple_round(
            lambda r: Config(r.node, rate_hz=max(1, min(4000, round(host.rate_hz))), range=host.range_code,
                             filter=host.filter_code, heartbeat_ms=host.heartbeat_ms), MsgType.CONFIG, "CONFIG", uids)
        for rec in ok:
            rec.configured = True
        return len(ok)

    def configure_imu(self, uids=None) -> int:
        """`Host.configure_imu`."""
        host = self.host
        fmt, gr, mr, fl = host.imu_config
        ok = host.commands.simple_round(lambda r: ConfigImu(r.node, fmt, gr, mr, fl), MsgType.CONFIG_IMU,
                                        "CONFIG_IMU", uids)
        host.aggregator.gyro_range, host.aggregator.mag_range = gr, mr
        host.aggregator.imu_format = fmt
        return len(ok)

    def read_calibration(self, uids=None) -> int:
        """`Host.read_calibration`."""
        host, reg = self.host, self.host.registry
        chips = reg.by_node(uids)
        got: dict[tuple[int, int], dict[int, CalData]] = {k: {} for k in chips}
        scale = float(1 << int(host.range_code))
        for axis in range(3):
            def match(bus, msg, axis=axis):
                if isinstance(msg, CalData) and msg.axis == axis:
                    return (bus, msg.node)
                if isinstance(msg, Nack) and msg.command == MsgType.CAL_READ:
                    return (bus, msg.node)
                return None
            answers, _ = host.commands.round(chips, lambda key, _a, axis=axis: [(key[0], CalRead(key[1], axis))],
                                             match, f"CAL_READ axis {axis}")
            for key, msg in answers.items():
                if isinstance(msg, CalData):
                    got[key][axis] = msg
        n_ok = 0
        with reg.lock:
            for key, axes in got.items():
                rec = chips[key]
                for axis, cal in axes.items():
                    rec.offset[axis] = cal.offset_q4 / 16.0 / scale
                    rec.sensitivity[axis] = cal.sensitivity / scale
                rec.calibrated = len(axes) == 3
                n_ok += rec.calibrated
        self.apply_calibration()  # outside the registry's lock, as in `assign`
        self.calibration_reads += 1
        return n_ok

    def read_imu_calibration(self, uids=None) -> int:
        """`Host.read_imu_calibration`."""
        host, reg = self.host, self.host.registry
        chips = reg.by_node(uids)

        def elements(rec) -> list[tuple[int, int]]:
            caps = rec.info.capabilities if rec.info is not None else 0
            return [(b, i) for b in CalBlock if caps & (Capability.GYRO if b <= CalBlock.GYRO_G_SENS else Capability.MAG)
                    for i in range(CAL_BLOCK_SIZE[b])]

        want = {k: elements(rec) for k, rec in chips.items()}
        got: dict[tuple[int, int], dict] = {k: {} for k in chips}
        for step in range(max((len(e) for e in want.values()), default=0)):
            todo = {k: rec for k, rec in chips.items() if step < len(want[k])}

            def build(key, _a, step=step):
                b, i = want[key][step]
                return [(key[0], CalImuRead(key[1], b, i))]

            def match(bus, msg, step=step):
                if isinstance(msg, CalImuData) or (isinstance(msg, Nack) and msg.command == MsgType.CAL_IMU_READ):
                    return (bus, msg.node)
                return None
            answers, _ = host.commands.round(todo, build, match, f"CAL_IMU_READ element {step}")
            for key, msg in answers.items():
                if isinstance(msg, CalImuData) and (msg.block, msg.index) == want[key][step]:
                    got[key][msg.block, msg.index] = (msg.value, msg.flags & 1)
        with reg.lock:
            for key, rec in chips.items():
                rec.imu_cal = got[key]
        return sum(1 for k in chips if want[k] and len(got[k]) == len(want[k]))

    def calibration_summary(self) -> dict:
        """`Host.calibration_summary`."""
        nominal = nominal_sensitivity(self.host.range_code)
        own = nom = 0
        for rec in self.host.registry.assigned():
            if not rec.calibrated:
                continue
            plain = bool(np.all(np.asarray(rec.offset) == 0) and np.allclose(rec.sensitivity, nominal, rtol=1e-6))
            nom += plain
            own += not plain
        return {"own": own, "nominal": nom}

    def start_chips(self, uids=None) -> int:
        """START the assigned chips (of ``uids``); those that ACK are marked started at that time.
        Returns the ACK count."""
        host = self.host
        ok = host.commands.simple_round(lambda r: Start(r.node), MsgType.START, "START", uids)
        t_ack = host.now()
        for rec in ok:
            rec.started = True
            rec.started_at = t_ack
        return len(ok)

    def check_capacity(self, action: str = "refuse", packed: bool = False) -> list[dict]:
        """`Host.check_capacity` (the message names the frames counted: `_FRAMING`)."""
        if action not in ("refuse", "warn", "off"):
            raise ValueError(f"Invalid capacity action: {action!r} (need 'refuse', 'warn' or 'off')")
        host = self.host
        imu_fmt = host.imu_config[0] if host.imu_config is not None else 0  # IMU records: larger (§16)
        report = []
        if action == "off":
            return report
        per_bus = Counter(r.bus for r in host.registry.assigned())
        packed_any = packed
        for bus, t in enumerate(host.transports):
            cap = t.capabilities
            n = per_bus.get(bus, 0)
            packed = packed_any or host.gateway_nodes.packing(bus)
            fmt = imu_fmt or host.gateway_nodes.sample_format(bus)  # a gateway packing IMU records it set itself
            if n == 0:
                continue
            if cap.kind == "memory" or (cap.kind == "can" and cap.bitrate is None
                                        and getattr(t, "interface", "") == "virtual"):
                continue
            if cap.kind == "serial":
                load = bus_load(n, host.rate_hz, kind="serial", bitrate=cap.bitrate or 3_000_000, packed=packed,
                                fmt=fmt)
            else:
                load = bus_load(n, host.rate_hz, kind="can", bitrate=cap.bitrate or 1_000_000, fd=cap.fd,
                                data_bitrate=cap.data_bitrate or 8_000_000, packed=packed, fmt=fmt)
            row = {"bus": t.name, "chips": n, "load_pct": round(100 * load, 1)}
            report.append(row)
            what = (f"{t.name}: {n} chips at {host.rate_hz:g} Hz need {100 * load:.0f} % of the bus "
                    f"({'packed ' if packed else 'per-chip '}{_FRAMING[packed, bool(fmt)]} frames)")
            if load > 1.0:
                remedy = capacity_remedy(cap.kind, load, host.rate_hz, packed=packed, fd=bool(cap.fd),
                                         bitrate=cap.bitrate, imu=bool(fmt))
                if action == "refuse":
                    raise CapacityError(f"over capacity: {what}; {remedy}")
                log.warning("over capacity: %s; %s", what, remedy)
            elif load > 0.8:
                log.warning("near capacity: %s", what)
        return report

    # -- what the chips said, to the feed --------------------------------------------------
    def apply_map(self) -> None:
        """The assigned chips' node -> link map to the aggregator (and their calibration)."""
        lut, unassigned = self.host.registry.node_map()
        self.host.feed.set_map(lut, unassigned)
        self.apply_calibration()

    def apply_calibration(self) -> None:
        """The chips' own calibration (CAL_DATA) to the aggregator's conversion of counts, and the
        host's calibration (`set_calibration`) rebased to it, to the feed's correction."""
        host = self.host
        n = host.lattice.n_links
        off = np.zeros((n, 3))
        sens = np.full((n, 3), nominal_sensitivity(host.range_code))
        cal = self._host_calibration
        with host.registry.lock:  # the records read at one time; the feed's lock taken after this one
            for rec in host.registry.assigned():
                off[rec.link] = rec.offset
                sens[rec.link] = rec.sensitivity
            chips = None if cal is None else host.registry.chip_calibration(host.range_code)
        host.feed.set_calibration(off, sens)
        live = None if cal is None else cal.rebased(*chips)
        self._live_calibration = live
        host.feed.set_correction(None if live is None else live.apply)

    def set_calibration(self, calibration) -> None:
        """`Host.set_calibration`."""
        lattice = self.host.lattice
        if calibration is not None and calibration.n_links != lattice.n_links:
            raise MismatchError(f"the calibration is for {calibration.rows}x{calibration.cols} joints "
                                f"({calibration.n_links} links), the lattice has {lattice.n_links} links")
        self._host_calibration = calibration
        self.apply_calibration()

    @property
    def calibration(self):
        """`Host.calibration`."""
        return self._live_calibration
