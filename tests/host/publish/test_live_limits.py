"""The live view server's edges (host/publish/live.py): it keeps answering after running out of file
descriptors, serves at most ``max_clients`` at once, refuses browser origins not allowed, and
serves TLS (``wss://``) when given a certificate. Each answer read here is the HTTP status line of
a real WebSocket handshake with foxglove-sdk's server behind the relay."""

from __future__ import annotations

import shutil
import socket
import ssl
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

foxglove = pytest.importorskip("foxglove")

from host.publish.live import LiveServer, tls_context  # noqa: E402

ROOT = Path(__file__).resolve().parents[3]


def _handshake(origin: str | None = None) -> bytes:
    return (b"GET / HTTP/1.1\r\nHost: localhost\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
            b"Sec-WebSocket-Protocol: foxglove.sdk.v1\r\n"
            + (b"Origin: " + origin.encode() + b"\r\n" if origin else b"") + b"\r\n")


def _status(sock, timeout_s: float = 10.0) -> str:
    """The first line the server answers ('' if it closes or says nothing in time)."""
    sock.settimeout(timeout_s)
    buf = b""
    try:
        while b"\r\n" not in buf:
            chunk = sock.recv(4096)
            if not chunk:
                break
            buf += chunk
    except (TimeoutError, socket.timeout, ConnectionError, ssl.SSLError):
        pass
    return buf.split(b"\r\n", 1)[0].decode("latin-1")


def _open(port: int, origin: str | None = None):
    s = socket.create_connection(("127.0.0.1", port), timeout=10)
    s.sendall(_handshake(origin))
    return s


@pytest.fixture
def server_factory():
    made = []

    def make(**kw):
        srv = LiveServer(foxglove.Context(), port=0, **kw)
        made.append(srv)
        return srv
    yield make
    for srv in made:
        srv.stop()


def test_at_most_max_clients_are_served_at_once_and_a_freed_slot_serves_the_next(server_factory):
    srv = server_factory(max_clients=2)
    a, b = _open(srv.port), _open(srv.port)
    try:
        assert _status(a).startswith("HTTP/1.1 101") and _status(b).startswith("HTTP/1.1 101")
        c = _open(srv.port)
        assert _status(c).startswith("HTTP/1.1 503")
        c.close()
        a.close()
        end = time.monotonic() + 10
        while True:  # the relay notices a's end within its pump's 0.2 s select
            d = _open(srv.port)
            st = _status(d)
            d.close()
            if st.startswith("HTTP/1.1 101") or time.monotonic() > end:
                break
            time.sleep(0.2)
        assert st.startswith("HTTP/1.1 101"), st
        assert srv.relay.refused["busy"] >= 1
    finally:
        b.close()


def test_an_origin_not_allowed_is_refused_and_a_client_without_one_is_served(server_factory):
    srv = server_factory(allowed_origins=["https://app.foxglove.dev"])
    for origin, status in (("https://evil.example", "HTTP/1.1 403"), ("https://app.foxglove.dev", "HTTP/1.1 101"),
                           (None, "HTTP/1.1 101")):
        s = _open(srv.port, origin)
        try:
            assert _status(s).startswith(status), origin
        finally:
            s.close()
    assert srv.relay.refused["origin"] == 1


def test_any_origin_is_served_by_default(server_factory):
    srv = server_factory()
    s = _open(srv.port, "https://evil.example")
    try:
        assert _status(s).startswith("HTTP/1.1 101")
    finally:
        s.close()


@pytest.fixture(scope="module")
def cert(tmp_path_factory):
    if shutil.which("openssl") is None:
        pytest.skip("openssl is not installed")
    d = tmp_path_factory.mktemp("live-tls")
    out = subprocess.run(["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes",
                          "-days", "2", "-keyout", str(d / "k.pem"), "-out", str(d / "c.pem"), "-subj", "/CN=localhost",
                          "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1"], capture_output=True, timeout=60)
    assert out.returncode == 0, out.stderr
    return d / "c.pem", d / "k.pem"


def test_tls_serves_wss_and_a_plain_client_gets_no_handshake(server_factory, cert):
    srv = server_factory(tls_cert=str(cert[0]), tls_key=str(cert[1]))
    assert srv.url.startswith("wss://localhost:")
    ctx = ssl.create_default_context(cafile=str(cert[0]))
    with socket.create_connection(("127.0.0.1", srv.port), timeout=10) as raw:
        with ctx.wrap_socket(raw, server_hostname="localhost") as s:
            s.sendall(_handshake())
            assert _status(s).startswith("HTTP/1.1 101")
    plain = _open(srv.port)
    try:
        assert not _status(plain, 3.0).startswith("HTTP/1.1 101")
    finally:
        plain.close()


def test_a_certificate_that_does_not_load_is_one_line_naming_it(tmp_path, cert):
    bad = tmp_path / "bad.pem"
    bad.write_text("not a certificate")
    with pytest.raises(ValueError, match="bad.pem"):
        tls_context(str(bad), str(cert[1]))
    with pytest.raises(ValueError, match="both"):
        tls_context(str(cert[0]), None)


# The server in a process of its own whose descriptors run out: it fills them after starting,
# then frees them when told (a line on stdin).
EMFILE = textwrap.dedent("""
    import os, resource, sys
    resource.setrlimit(resource.RLIMIT_NOFILE, (256, 256))
    import foxglove
    from host.publish.live import LiveServer
    srv = LiveServer(foxglove.Context(), port=0)
    print(srv.port, flush=True)
    hog = []
    while True:
        try:
            hog.append(os.open("/dev/null", os.O_RDONLY))
        except OSError:
            break
    print("full", len(hog), flush=True)
    sys.stdin.readline()
    for fd in hog:
        os.close(fd)
    print("freed", flush=True)
    sys.stdin.readline()
    print("accept_errors", srv.relay.accept_errors, flush=True)
    srv.stop()
""")


def test_the_server_answers_again_once_descriptors_free_up_after_running_out():
    p = subprocess.Popen([sys.executable, "-c", EMFILE], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, cwd=ROOT)
    client = None
    try:
        port = int(p.stdout.readline())
        assert p.stdout.readline().startswith("full")
        client = _open(port)  # waits in the backlog: accept() fails with EMFILE meanwhile
        assert _status(client, 1.0) == ""
        p.stdin.write("\n")
        p.stdin.flush()
        assert p.stdout.readline().strip() == "freed"
        assert _status(client, 15.0).startswith("HTTP/1.1 101")
        again = _open(port)
        assert _status(again).startswith("HTTP/1.1 101")
        again.close()
        p.stdin.write("\n")
        p.stdin.flush()
        errors = int(p.stdout.readline().split()[1])
        assert errors >= 1  # it did run out, and counted it
        p.wait(20)
    finally:
        if client is not None:
            client.close()
        if p.poll() is None:
            p.kill()
            p.wait(10)
    assert "Traceback" not in p.stderr.read()
