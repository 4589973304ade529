"""Where a capsheet Zenoh session may talk: the configuration every publisher, worker and view opens
(docs/distribution.md "Where Zenoh talks, and how to secure it").

* **No endpoint, no config file**: peer mode kept on this machine. Every socket is bound to
  127.0.0.1; multicast scouting is off (no 224.0.0.224 socket, no UDP socket on 0.0.0.0). The
  processes of one machine find each other through one fixed loopback endpoint, `LOCAL_ENDPOINT`
  (``tcp/127.0.0.1:7447``, zenohd's and rmw_zenohd's port): every session tries to listen there
  (the first one that starts gets it; the others keep trying in the background, so when it ends
  another takes its place) and connects to it (retrying until it answers). Each also listens on a
  random loopback port, which the one on the fixed port passes on (Zenoh's gossip, over the
  sessions already open): the peers then connect to each other directly. A zenohd or rmw_zenohd
  running on this machine's port 7447 is the one they all connect to.
* Every default session (with or without an ENDPOINT) takes messages of at most `MAX_MESSAGE_BYTES`
  (Zenoh's own default: 1 GiB, held in memory before capsheet sees it).
* **An ENDPOINT** (``--publish zenoh:ENDPOINT``, ``--subscribe zenoh:ENDPOINT``, ``[view]
  endpoint``): client mode, connected to that router only, multicast scouting off (``ros2``: peer
  mode connected to it, listening on a random loopback port, as rmw_zenoh's default session is).
* **A Zenoh config file** (JSON5, the format every Zenoh tool reads): ``--zenoh-config FILE``, else
  the file ``ZENOH_SESSION_CONFIG_URI`` names (as rmw_zenoh reads it), else ``ZENOH_CONFIG`` (as
  Zenoh's own tools read it). The file is the whole configuration (mode, endpoints, TLS, user and
  password, access control); an ENDPOINT given as well replaces its ``connect/endpoints``.
* ``ZENOH_CONFIG_OVERRIDE`` (as rmw_zenoh reads it): ``key=json5_value`` pairs separated by ``;``,
  applied last, e.g. ``ZENOH_CONFIG_OVERRIDE='mode="client";connect/endpoints=["tcp/10.0.0.2:7447"]'``.
"""

from __future__ import annotations

import json
import os
import stat

__all__ = ["LOCAL_ENDPOINT", "ENV_URI", "ENV_ZENOH", "ENV_OVERRIDE", "MAX_CONFIG_BYTES", "MAX_MESSAGE_BYTES",
           "session_config",
           "open_session", "config_source", "check_config_file"]

#: the loopback endpoint the sessions of one machine meet at when no endpoint is given
LOCAL_ENDPOINT = "tcp/127.0.0.1:7447"
#: rmw_zenoh's variable: a Zenoh config file for the session
ENV_URI = "ZENOH_SESSION_CONFIG_URI"
#: Zenoh's own tools' variable: a Zenoh config file
ENV_ZENOH = "ZENOH_CONFIG"
#: rmw_zenoh's variable: ``key=value;key=value`` applied over whatever config
ENV_OVERRIDE = "ZENOH_CONFIG_OVERRIDE"
#: the largest message a default session takes from the network: Zenoh's default is 1 GiB, which it
#: assembles in memory before any check of ours runs; capsheet's largest payload (a 32,767-link
#: snapshot with every IMU field) is 1.4 MB
MAX_MESSAGE_BYTES = 16 << 20
#: a Zenoh config file larger than this is refused unread (Zenoh's own DEFAULT_CONFIG.json5, every
#: option commented, is about 40 KB)
MAX_CONFIG_BYTES = 1 << 20


def check_config_file(path: str) -> str:
    """``path`` if it names a readable regular file of at most `MAX_CONFIG_BYTES`; ValueError (one line)
    otherwise. A FIFO or a device (``/dev/zero``) is refused before it is read."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise ValueError(f"Zenoh config {path}: {exc.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"Zenoh config {path}: not a regular file")
    if st.st_size > MAX_CONFIG_BYTES:
        raise ValueError(f"Zenoh config {path}: {st.st_size} bytes, more than a config's {MAX_CONFIG_BYTES}")
    if not os.access(path, os.R_OK):
        raise ValueError(f"Zenoh config {path}: not readable")
    return path


def config_source(config_file: str | None = None, environ=None) -> tuple[str | None, str]:
    """``(file or None, where it came from)``: ``--zenoh-config``, else `ENV_URI`, else `ENV_ZENOH`."""
    env = os.environ if environ is None else environ
    if config_file:
        return config_file, "--zenoh-config"
    for var in (ENV_URI, ENV_ZENOH):
        value = env.get(var, "")
        if value:
            return (value[len("file://"):] if value.startswith("file://") else value), var
    return None, "capsheet's default"


def _overrides(text: str) -> list[tuple[str, str]]:
    out = []
    for item in filter(None, (s.strip() for s in text.split(";"))):
        key, eq, value = item.partition("=")
        if not eq or not key.strip():
            raise ValueError(f"{ENV_OVERRIDE}: {item!r} is not key=value")
        out.append((key.strip(), value.strip()))
    return out


def session_config(endpoint: str | None = None, config_file: str | None = None, *, ros2: bool = False,
                   environ=None):
    """The `zenoh.Config` for a session (module docstring). ValueError, one line naming the file or
    variable, for a config that cannot be used."""
    import zenoh

    env = os.environ if environ is None else environ
    path, source = config_source(config_file, env)
    if path is not None:
        check_config_file(path)
        try:
            conf = zenoh.Config.from_file(path)
        except zenoh.ZError as exc:
            raise ValueError(f"Zenoh config {path} ({source}): {str(exc).splitlines()[0] if str(exc) else 'invalid'}") \
                from None
        if endpoint is not None:
            conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    else:
        conf = zenoh.Config()
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("transport/link/rx/max_message_size", str(MAX_MESSAGE_BYTES))
        if endpoint is None:
            conf.insert_json5("mode", '"peer"')
            # the fixed endpoint: whoever gets it serves the others; the rest retry in the background
            conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0",
                                                              f"{LOCAL_ENDPOINT}#exit_on_failure=false"]))
            conf.insert_json5("connect/endpoints", json.dumps([LOCAL_ENDPOINT]))
            conf.insert_json5("connect/exit_on_failure", "false")
        elif ros2:  # rmw_zenoh's default session: a peer connected to the router, listening on loopback
            conf.insert_json5("mode", '"peer"')
            conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
            conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
        else:
            conf.insert_json5("mode", '"client"')
            conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    for key, value in _overrides(env.get(ENV_OVERRIDE, "")):
        try:
            conf.insert_json5(key, value)
        except zenoh.ZError as exc:
            raise ValueError(f"{ENV_OVERRIDE}: {key}={value}: {str(exc).splitlines()[0] if str(exc) else 'refused'}") \
                from None
    return conf


def describe(endpoint: str | None, config_file: str | None = None, environ=None) -> str:
    """Where the session talks, for messages: ``peer mode on loopback (tcp/127.0.0.1:7447)`` ..."""
    path, source = config_source(config_file, environ)
    if path is not None:
        return f"Zenoh config {path} ({source})" + (f", connected to {endpoint}" if endpoint else "")
    return endpoint or f"peer mode on loopback ({LOCAL_ENDPOINT})"


def open_session(endpoint: str | None = None, config_file: str | None = None, *, ros2: bool = False):
    """A Zenoh session as `session_config` says: ValueError (one line) when the config cannot be used
    (a usage error), OSError (one line) when the session cannot be opened."""
    import zenoh

    conf = session_config(endpoint, config_file, ros2=ros2)
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        detail = str(exc).split(" at /")[0].strip()
        if endpoint is not None and config_source(config_file)[0] is None:
            raise OSError(f"cannot reach the Zenoh router at {endpoint}: {detail}") from None
        raise OSError(f"cannot open a Zenoh session ({describe(endpoint, config_file)}): {detail}") from None
