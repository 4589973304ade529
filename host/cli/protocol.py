"""``capsheet protocol``: spec helpers for chip vendors — decode/encode frames by hand, regenerate
the golden vectors and the DBC, print the capacity table. No port I/O here."""

from __future__ import annotations

import json
import sys


#: fields ``protocol encode`` fills with 0 when they are not given (bit fields: no bit set); every
#: other field must be given, so a forgotten one is never encoded as a silent 0
OPTIONAL_FIELDS = ("status", "flags", "detail")


def _parse_field(name: str, kind: str, text: str):
    """``text`` as the field's type (``int``: decimal or 0x.., ``float``, ``bytes``: hex)."""
    text = text.strip()
    try:
        if kind == "float":
            return float(text)
        if kind == "bytes":
            return bytes.fromhex(text)
        return int(text, 0)
    except ValueError:
        need = {"float": "a number", "bytes": "hex bytes"}.get(kind, "an integer (or 0x..)")
        raise ValueError(f"{name}={text!r}: need {need}") from None


def _hex_arg(text: str) -> bytes | None:
    try:
        return bytes.fromhex(text.replace(" ", ""))
    except ValueError:
        print(f"capsheet protocol decode: invalid hex {text!r} (need pairs of hex digits, e.g. '04 01 03')",
              file=sys.stderr)
        return None


def cmd_decode(args) -> int:
    from protocol.can import decode_can
    from protocol.framing import DecodeError, StreamDecoder
    if args.can_id is not None:
        try:
            can_id = int(args.can_id, 16)
        except ValueError:
            print(f"capsheet protocol decode: invalid --can-id {args.can_id!r} (need hex, e.g. 0A400001)",
                  file=sys.stderr)
            return 2
        if not 0 <= can_id < (1 << 29):
            print(f"capsheet protocol decode: invalid --can-id {args.can_id!r} (need a 29-bit identifier)",
                  file=sys.stderr)
            return 2
        data = _hex_arg(args.hex)
        if data is None:
            return 2
        ev = decode_can(can_id, data, is_fd=args.fd)
        print(ev)
        return 1 if isinstance(ev, DecodeError) else 0
    data = sys.stdin.buffer.read() if args.hex == "-" else _hex_arg(args.hex)
    if data is None:
        return 2
    dec = StreamDecoder()
    events = dec.feed(data)
    for ev in events:
        print(ev)
    if dec.pending_bytes:
        print(f"(incomplete frame pending: {dec.pending_bytes} bytes without a 0x00 delimiter)")
    print(f"frames={dec.stats.frames} errors={dict((k.name, v) for k, v in dec.stats.errors.items())}",
          file=sys.stderr)
    return 1 if dec.stats.error_count else 0


def cmd_encode(args) -> int:
    from protocol.can import to_can
    from protocol.framing import encode
    from protocol.messages import MESSAGE_TYPES, MsgType
    try:
        cls = MESSAGE_TYPES[MsgType[args.type.upper()]]
    except KeyError:
        print(f"capsheet protocol encode: unknown type {args.type!r}; one of: {', '.join(t.name for t in MsgType)}",
              file=sys.stderr)
        return 2
    import dataclasses
    prog, name = "capsheet protocol encode", cls.TYPE.name
    kinds = {f.name: str(f.type) for f in dataclasses.fields(cls)}
    listed = " ".join(f"{k}=" for k in kinds)
    try:
        fields = dict(kv.split("=", 1) for kv in args.fields)
    except ValueError:
        print(f"{prog}: fields are name=value pairs ({name}: {listed}), got {' '.join(args.fields)}", file=sys.stderr)
        return 2
    unknown = [k for k in fields if k not in kinds]
    if unknown:
        print(f"{prog}: {name} has no field {', '.join(unknown)} (its fields: {listed})", file=sys.stderr)
        return 2
    # node too where the message has a default one (SYNC: broadcast, node 0)
    optional = set(OPTIONAL_FIELDS) | {f.name for f in dataclasses.fields(cls)
                                       if f.name == "node" and f.default is not dataclasses.MISSING}
    missing = [k for k in kinds if k not in fields and k not in optional]
    if missing:
        print(f"{prog}: {name} needs {' '.join(k + '=' for k in missing)} too (every field but "
              f"{'/'.join(sorted(optional))}, which default to 0)", file=sys.stderr)
        return 2
    try:
        msg = cls(**{k: _parse_field(k, kinds[k], v) for k, v in fields.items()})
    except (TypeError, ValueError) as exc:
        print(f"{prog}: cannot build {name}: {exc}", file=sys.stderr)
        return 2
    print(f"message: {msg}")
    print(f"serial : {encode(msg).hex(' ')}")
    try:
        f = to_can(msg)
        print(f"can    : {f.arbitration_id:08X}#{f.data.hex().upper()}{'  (FD)' if f.is_fd else ''}")
    except ValueError as exc:
        print(f"can    : {exc}")
    return 0


def cmd_vectors(args) -> int:
    from protocol.vectors import build_vectors, write_vectors
    if args.write:
        for p in write_vectors():
            print(f"wrote {p}")
    else:
        print(json.dumps(build_vectors(), indent=1))
    return 0


def cmd_dbc(args) -> int:
    from protocol.dbc import dbc_text, write_dbc
    if args.write:
        print(f"wrote {write_dbc()}")
    else:
        sys.stdout.write(dbc_text())
    return 0


def cmd_capacity(args) -> int:
    from protocol.capacity import buses_needed, capacity_table
    rows = capacity_table(args.rate)
    if args.lattice is not None:
        lat = args.lattice
        n = lat.n_links
        print(f"A {lat.rows}x{lat.cols} sheet ({n} chips) at {args.rate:g} Hz needs (worst case per bus):")
        print("| link | carries | chips per bus | buses needed |")
        print("|---|---|---|---|")
        for r, k in buses_needed(n, args.rate):
            need = "none fits at this rate" if k < 0 else f"{k}"
            print(f"| {r.link} | {r.carries} | {r.chips_at_rate[0]:,} | {need} |")
        return 0
    print(f"| link | carries | one frame | frames/s | chips at {args.rate:g} Hz |")
    print("|---|---|---|---|---|")
    for r in rows:
        f = r.frames_per_s
        fps = f"{f[0]:,.0f}" if round(f[0]) == round(f[1]) else f"{f[0]:,.0f}–{f[1]:,.0f}"
        chips = f"{r.chips_at_rate[0]:,}" if r.chips_at_rate[0] == r.chips_at_rate[1] else \
            f"{r.chips_at_rate[0]:,}–{r.chips_at_rate[1]:,}"
        print(f"| {r.link} | {r.carries} | {r.frame} | {fps} | {chips} |")
    return 0


def register(sub) -> None:
    from host.cli import argtypes as T
    p = sub.add_parser("protocol", help="wire protocol helpers: decode/encode frames, vectors, DBC, capacity",
                       description="Wire protocol v1 helpers (docs/protocol.md). No port is opened.")
    ps = p.add_subparsers(dest="protocol_command", metavar="ACTION", required=True)
    d = ps.add_parser("decode", help="decode serial wire bytes (hex, or - for raw stdin) or one CAN frame")
    d.add_argument("hex", help="hex bytes, e.g. '04 01 03 01 01 01 01 01 01 01 04 04 16 2e 00', or - for stdin")
    d.add_argument("--can-id", help="decode as one CAN frame with this identifier (hex)")
    d.add_argument("--fd", action="store_true", help="the CAN frame is CAN FD")
    d.set_defaults(func=cmd_decode)
    e = ps.add_parser("encode", help="build one message and print its serial and CAN bytes",
                      description="Example: capsheet protocol encode SAMPLE node=1 counter=0 x=0 y=0 z=1024")
    e.add_argument("type", help="message type name, e.g. SAMPLE, SYNC, ASSIGN")
    e.add_argument("fields", nargs="*", help="field=value pairs incl. node= (ints accept 0x..)")
    e.set_defaults(func=cmd_encode)
    v = ps.add_parser("vectors", help="print (or --write) the golden vectors of tests/vectors/")
    v.add_argument("--write", action="store_true")
    v.set_defaults(func=cmd_vectors)
    b = ps.add_parser("dbc", help="print (or --write) protocol/capsheet.dbc")
    b.add_argument("--write", action="store_true")
    b.set_defaults(func=cmd_dbc)
    c = ps.add_parser("capacity", help="chips per bus at a sample rate, from the frame sizes")
    c.add_argument("--rate", type=T.rate, default=145.0, help="samples per second per chip (default 145)")
    c.add_argument("--lattice", type=T.lattice, default=None, metavar="ROWSxCOLS",
                   help="say how many buses of each kind a sheet of this size needs")
    c.set_defaults(func=cmd_capacity)
