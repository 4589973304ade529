"""The Zenoh security configurations docs/distribution.md prints ("Security"), run as printed on
loopback: the certificates made by its openssl script, a router (a Python Zenoh session in router
mode from the router file) and clients opened the way ``--zenoh-config`` opens them."""

from __future__ import annotations

import re
import shutil
import socket
import subprocess
import time
from pathlib import Path

import pytest

zenoh = pytest.importorskip("zenoh")

from host.publish.zenoh_session import open_session  # noqa: E402
from tests import zenoh_meeting  # noqa: E402

DOC = Path(__file__).resolve().parents[3] / "docs" / "distribution.md"
BLOCK = re.compile(r"<!-- tested: (\S+) -->\n```\w+\n(.*?)```", re.S)


@pytest.fixture(autouse=True)
def _own_endpoints(monkeypatch):
    """The sessions here are opened from config files with their own endpoints: the worker's meeting
    point (tests/zenoh_meeting.py, applied last) would replace them."""
    monkeypatch.delenv(zenoh_meeting.VAR, raising=False)


def blocks() -> dict[str, str]:
    return dict(BLOCK.findall(DOC.read_text()))


def test_the_page_prints_every_tested_configuration():
    assert set(blocks()) == {"make-certs", "router-tls", "client-tls", "router-usrpwd", "client-usrpwd", "router-acl"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A directory with the page's certificates (its script, run by bash) and ``users.txt``."""
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    d = tmp_path_factory.mktemp("zenoh-site")
    out = subprocess.run(["bash", "-e", "-c", blocks()["make-certs"]], cwd=d, capture_output=True, text=True,
                         timeout=60, env={"PATH": "/usr/bin:/bin", "ROUTER_SAN": "IP:127.0.0.1"})
    assert out.returncode == 0, out.stderr
    (d / "users.txt").write_text("capsheet:change-me\n")
    return d


def _config(site: Path, name: str, ports: tuple[int, int], *, drop: tuple[str, ...] = (), text: str | None = None) -> str:
    """The page's ``name`` block with this test's paths and ports, lines containing ``drop`` left out."""
    t = blocks()[name] if text is None else text
    t = "\n".join(line for line in t.splitlines() if not any(d in line for d in drop))
    t = t.replace('"certs/', f'"{site}/certs/').replace('"users.txt"', f'"{site}/users.txt"')
    for host in ("192.168.1.10", "router.local"):
        t = t.replace(f"{host}:7447", f"127.0.0.1:{ports[0]}").replace(f"{host}:7448", f"127.0.0.1:{ports[1]}")
    path = site / f"{name}-{ports[0]}-{abs(hash(drop)) % 10**6}.json5"
    path.write_text(t)
    return str(path)


def _router(site: Path, name: str):
    ports = (_free_port(), _free_port())
    return zenoh.open(zenoh.Config.from_file(_config(site, name, ports))), ports


def _wait(pred, timeout_s: float = 5.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


def _delivers(sender, receiver, key: str = "capsheet/s/estimate", payload: bytes = b"e") -> bool:
    """Whether ``sender``'s puts reach ``receiver`` (a few tries: a new subscription takes a moment
    to propagate)."""
    got = []
    sub = receiver.declare_subscriber(key, lambda s: got.append(bytes(s.payload.to_bytes())))
    try:
        for _ in range(10):
            sender.put(key, payload)
            if _wait(lambda: payload in got, 0.3):
                return True
        return False
    finally:
        sub.undeclare()


def test_tls_with_a_private_ca_and_client_certificates(site):
    router, ports = _router(site, "router-tls")
    try:
        client = open_session(None, _config(site, "client-tls", ports))
        try:
            assert _delivers(client, router)
        finally:
            client.close()
        # trusting only the system's CAs: the router's certificate is not accepted
        with pytest.raises(OSError, match="cannot open a Zenoh session"):
            open_session(None, _config(site, "client-tls", ports, drop=("root_ca_certificate",))).close()
        # no client certificate while the router asks for one (mutual TLS)
        with pytest.raises(OSError, match="cannot open a Zenoh session"):
            open_session(None, _config(site, "client-tls", ports, drop=("connect_certificate",
                                                                         "connect_private_key"))).close()
    finally:
        router.close()


def test_user_and_password(site):
    router, ports = _router(site, "router-usrpwd")
    try:
        client = open_session(None, _config(site, "client-usrpwd", ports))
        try:
            assert _delivers(client, router)
        finally:
            client.close()
        wrong = blocks()["client-usrpwd"].replace("change-me", "guess")
        with pytest.raises(OSError, match="cannot open a Zenoh session"):
            open_session(None, _config(site, "client-usrpwd", ports, text=wrong)).close()
        with pytest.raises(OSError, match="cannot open a Zenoh session"):
            open_session(None, _config(site, "client-usrpwd", ports, drop=("usrpwd",))).close()
    finally:
        router.close()


def test_access_control_keeps_a_session_without_credentials_out_of_capsheet_keys(site):
    router, ports = _router(site, "router-acl")
    anon_file = site / f"anonymous-{ports[1]}.json5"
    anon_file.write_text(f'{{ mode: "client", connect: {{ endpoints: ["tcp/127.0.0.1:{ports[1]}"] }},'
                         f' scouting: {{ multicast: {{ enabled: false }} }} }}')
    sessions, key = [], "capsheet/s/estimate"
    try:
        host = open_session(None, _config(site, "client-tls", ports))
        view = open_session(None, _config(site, "client-tls", ports))
        anon = open_session(None, str(anon_file))  # it may connect: it has no certificate, no rights
        sessions += [host, view, anon]
        seen = {"view": [], "anon": []}
        for name, sess in (("view", view), ("anon", anon)):
            sessions.insert(0, sess.declare_subscriber(key, lambda smp, n=name: seen[n].append(bytes(smp.payload.to_bytes()))))
        sessions.insert(0, host.declare_queryable("capsheet/s/info", lambda q: q.reply("capsheet/s/info", b"{}")))
        assert _delivers(host, view, payload=b"ready")  # the sheets' own processes: through the same router
        for _ in range(3):
            anon.put(key, b"forged")
        time.sleep(0.3)
        host.put(key, b"after")  # once the view has this, the forged ones had their chance
        assert _wait(lambda: b"after" in seen["view"])
        time.sleep(0.3)
        assert b"forged" not in seen["view"]  # anonymous estimates reach nobody
        assert set(seen["anon"]) <= {b"forged"}  # and it read none of the sheet's (only its own, locally)
        assert [r for r in anon.get("capsheet/s/info", timeout=1.0) if r.ok is not None] == []
        assert [r for r in view.get("capsheet/s/info", timeout=2.0) if r.ok is not None] != []
    finally:
        for s in sessions:
            s.close() if isinstance(s, zenoh.Session) else s.undeclare()
        router.close()
