"""Where a capsheet Zenoh session talks (host/publish/zenoh_session.py, docs/distribution.md): with no
endpoint every socket is on loopback and nothing scouts by multicast; config files and the
environment variables rmw_zenoh and Zenoh read are taken, and bad ones refused in one line."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

zenoh = pytest.importorskip("zenoh")

from host.publish.zenoh_session import (LOCAL_ENDPOINT, check_config_file, config_source,  # noqa: E402
                                        session_config)

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
LOOPBACK = {"127.0.0.1", "::1"}


def _probe(*kinds: str, env: dict | None = None) -> list[dict]:
    e = {k: v for k, v in os.environ.items() if not k.startswith("ZENOH")}
    e.update(env or {})
    out = subprocess.run([sys.executable, str(HERE / "socket_probe.py"), *kinds], capture_output=True, text=True,
                         timeout=60, cwd=ROOT, env=e)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _not_loopback(socks: list[dict]) -> list[dict]:
    """Sockets bound to anything but 127.0.0.1 / ::1 (a wildcard, a multicast group, an interface)."""
    return [s for s in socks if s["local"] not in LOOPBACK]


def test_the_socket_check_catches_multicast_scouting_and_the_wildcard():
    """The check below is not blind: Zenoh's peer mode scouting on lo holds a UDP socket on 0.0.0.0
    and one on the scouting group 224.0.0.224:7446."""
    bad = _not_loopback(_probe("multicast_on_lo"))
    assert {"0.0.0.0", "224.0.0.224"} <= {s["local"] for s in bad}, bad


def test_default_sessions_hold_loopback_sockets_only():
    """A publisher, an estimate worker, a view and a ROS 2 publisher with no endpoint: every socket
    on 127.0.0.1 / ::1, no UDP at all (no scouting), no multicast group, no wildcard."""
    socks = _probe("publisher", "worker", "view", "ros2")
    assert socks, "no socket at all: the probe read nothing"
    assert _not_loopback(socks) == []
    assert [s for s in socks if s["table"].startswith("udp")] == []
    # the fixed endpoint the machine's sessions meet at: listened on (by the first) and connected to
    port = int(LOCAL_ENDPOINT.rsplit(":", 1)[1])
    assert any(s["port"] == port or s["remote"] == "127.0.0.1" for s in socks), socks


PEER = textwrap.dedent("""
    import sys, time
    from host.cli.subscribe import open_session
    s = open_session(None)
    role, key = sys.argv[1], sys.argv[2]
    got = []
    if role == "sub":
        s.declare_subscriber(key, lambda smp: got.append(1))
        print("ready", flush=True)
        end = time.monotonic() + 20
        while time.monotonic() < end and len(got) < 5:
            time.sleep(0.05)
        print(len(got), flush=True)
    else:
        p = s.declare_publisher(key)
        end = time.monotonic() + 20
        while time.monotonic() < end:
            p.put(b"x"); time.sleep(0.05)
    s.close()
""")


def test_two_default_sessions_on_one_machine_still_meet(tmp_path):
    """Without multicast the processes of one machine find each other at the fixed loopback endpoint."""
    e = {k: v for k, v in os.environ.items() if not k.startswith("ZENOH")}
    key = f"capsheet/meet{os.getpid()}/estimate"
    sub = subprocess.Popen([sys.executable, "-c", PEER, "sub", key], stdout=subprocess.PIPE, text=True, cwd=ROOT,
                           env=e)
    pub = None
    try:
        assert sub.stdout.readline().strip() == "ready"
        pub = subprocess.Popen([sys.executable, "-c", PEER, "pub", key], cwd=ROOT, env=e)
        got = int(sub.stdout.readline().strip() or 0)
        assert got >= 5
    finally:
        for p in (sub, pub):
            if p is not None:
                p.kill()
                p.wait(10)


def _json5(path: Path, text: str) -> str:
    path.write_text(text)
    return str(path)


def test_a_config_file_is_the_whole_config_and_an_endpoint_replaces_its_connect(tmp_path):
    f = _json5(tmp_path / "z.json5", '{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:9"] },'
               ' // a comment: JSON5\n scouting: { multicast: { enabled: false } } }')
    conf = session_config(None, f, environ={})
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:9"]
    conf = session_config("tcp/127.0.0.1:12", f, environ={})
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:12"]


def test_the_environment_names_the_config_as_rmw_zenoh_and_zenoh_read_it(tmp_path):
    a = _json5(tmp_path / "a.json5", '{ mode: "client" }')
    b = _json5(tmp_path / "b.json5", '{ mode: "router" }')
    assert config_source(None, {"ZENOH_SESSION_CONFIG_URI": a, "ZENOH_CONFIG": b}) == (a, "ZENOH_SESSION_CONFIG_URI")
    assert config_source(None, {"ZENOH_CONFIG": b}) == (b, "ZENOH_CONFIG")
    assert config_source("x", {"ZENOH_SESSION_CONFIG_URI": a})[1] == "--zenoh-config"
    assert config_source(None, {"ZENOH_SESSION_CONFIG_URI": "file://" + a})[0] == a
    conf = session_config(None, None, environ={"ZENOH_SESSION_CONFIG_URI": b})
    assert json.loads(conf.get_json("mode")) == "router"
    conf = session_config(None, None, environ={"ZENOH_CONFIG_OVERRIDE": 'mode="client";connect/endpoints=["tcp/127.0.0.1:5"]'})
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:5"]


def test_the_default_config_says_loopback_and_no_multicast():
    conf = session_config(None, None, environ={})
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    listen = json.loads(conf.get_json("listen/endpoints"))
    assert all(e.startswith("tcp/127.0.0.1:") for e in listen), listen
    conf = session_config("tcp/10.1.2.3:7447", None, environ={})
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("mode")) == "client"
    for endpoint in (None, "tcp/10.1.2.3:7447"):  # Zenoh's own default takes 1 GiB messages
        conf = session_config(endpoint, None, environ={})
        assert json.loads(conf.get_json("transport/link/rx/max_message_size")) == 16 << 20


@pytest.mark.parametrize("make, says", [
    (lambda d: "/dev/zero", "not a regular file"),
    (lambda d: str(d), "not a regular file"),
    (lambda d: str(d / "missing.json5"), "No such file"),
    (lambda d: _json5(d / "big.json5", "{" + " " * (1 << 20) + "}"), "bytes, more than"),
])
def test_a_config_that_is_not_a_small_regular_file_is_refused_unread(tmp_path, make, says):
    with pytest.raises(ValueError, match=says):
        check_config_file(make(tmp_path))


def test_a_fifo_config_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match="not a regular file"):
        session_config(None, str(fifo), environ={})


@pytest.mark.parametrize("text", ['{ mode: ', '{ mode: "sideways" }', '[1, 2]', '{ a: ' * 200 + '1' + ' }' * 200])
def test_a_broken_config_file_is_one_line_naming_the_file(tmp_path, text):
    f = _json5(tmp_path / "bad.json5", text)
    with pytest.raises(ValueError) as exc:
        session_config(None, f, environ={})
    assert str(f) in str(exc.value) and "\n" not in str(exc.value)


def test_cli_bad_zenoh_config_is_a_usage_error(tmp_path):
    """``capsheet view --zenoh-config /dev/zero``: exit 2, one line, no traceback."""
    robot = tmp_path / "robot.toml"
    robot.write_text('[[sheet]]\nname = "a"\ntranslation = [0, 0, 0]\nrpy_deg = [0, 0, 0]\n')
    for bad in ("/dev/zero", str(tmp_path)):
        out = subprocess.run([sys.executable, "-m", "host.cli", "view", "--config", str(robot), "--zenoh-config", bad,
                              "--duration", "0.1"], capture_output=True, text=True, timeout=60, cwd=ROOT)
        assert out.returncode == 2, out.stderr
        assert "not a regular file" in out.stderr and "Traceback" not in out.stderr
    env = {**os.environ, "ZENOH_SESSION_CONFIG_URI": _json5(tmp_path / "b.json5", "{ mode: ")}
    out = subprocess.run([sys.executable, "-m", "host.cli", "view", "--config", str(robot), "--duration", "0.1"],
                         capture_output=True, text=True, timeout=60, cwd=ROOT, env=env)
    assert out.returncode == 2 and "ZENOH_SESSION_CONFIG_URI" in out.stderr and "Traceback" not in out.stderr, out.stderr
