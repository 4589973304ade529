"""Open Zenoh sessions in this process and print, as one JSON line, the sockets the process holds
(read from /proc/self/net/{tcp,tcp6,udp,udp6}, kept when their inode is one of /proc/self/fd's).

    python socket_probe.py KIND [KIND ...]

KIND: ``publisher`` (host.publish.zenoh_pub.ZenohPublisher, no endpoint), ``worker`` (the session
``capsheet estimate --subscribe`` opens), ``view`` (``capsheet view``'s), ``ros2``
(host.publish.ros2.Ros2Publisher, no endpoint), or ``multicast_on_lo``: Zenoh's peer mode scouting
by multicast on ``lo``, which a socket check has to catch.
"""

import ipaddress
import json
import os
import sys
import time


def _addr(text: str) -> str:
    ip, port = text.split(":")
    raw = bytes.fromhex(ip)
    if len(raw) == 4:
        a = ipaddress.IPv4Address(raw[::-1])
    else:  # four little-endian 32-bit words
        a = ipaddress.IPv6Address(b"".join(raw[i:i + 4][::-1] for i in range(0, 16, 4)))
    return f"{a}|{int(port, 16)}"


def sockets() -> list[dict]:
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            link = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            inodes.add(link[8:-1])
    out = []
    for table in ("tcp", "tcp6", "udp", "udp6"):
        with open(f"/proc/self/net/{table}") as fh:
            for line in fh.read().splitlines()[1:]:
                f = line.split()
                if f[9] in inodes:
                    local, remote = _addr(f[1]), _addr(f[2])
                    out.append({"table": table, "local": local.split("|")[0], "port": int(local.split("|")[1]),
                                "remote": remote.split("|")[0], "state": f[3]})
    return out


def main() -> None:
    import zenoh

    from protocol.lattice import Lattice

    held = []
    for kind in sys.argv[1:]:
        if kind == "publisher":
            from host.publish.zenoh_pub import ZenohPublisher
            held.append(ZenohPublisher("probe", None, Lattice(3, 3), 0.01))
        elif kind == "worker" or kind == "view":
            from host.cli.subscribe import open_session
            held.append(open_session(None))
        elif kind == "ros2":
            from host.publish.ros2 import Ros2Publisher
            held.append(Ros2Publisher("probe", None))
        elif kind == "multicast_on_lo":
            conf = zenoh.Config()
            conf.insert_json5("mode", '"peer"')
            conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
            conf.insert_json5("scouting/multicast/interface", '"lo"')
            held.append(zenoh.open(conf))
    time.sleep(0.5)  # scouting and listeners start in the background
    print(json.dumps(sockets()), flush=True)
    for h in held:
        h.close()


if __name__ == "__main__":
    main()
