"""capsheet wire protocol v1 — sans-I/O (docs/protocol.md is the normative spec).

Bytes in, events out: nothing here opens a port or imports pyserial or python-can.

* `protocol.messages` — the message dataclasses and payload layouts (§4, §5)
* `protocol.framing`  — serial framing: `encode`, `StreamDecoder` (§6)
* `protocol.can`      — CAN identifiers and payloads: `to_can`, `from_can`, `decode_can` (§7)
* `protocol.dbc`      — the DBC, generated from the messages (§7.3)
* `protocol.state`    — the chip state machine tables (§8)
* `protocol.lattice`  — link addressing (docs/design.md link order)
* `protocol.capacity` — chips per bus from the frame sizes (§10)
"""

from .can import CanFrame, decode_can, from_can, to_can
from .constants import G0, Range, SampleStatus
from .framing import DecodeError, ErrorReason, SampleBatch, StreamDecoder, decode_frame, encode
from .lattice import Lattice
from . import messages as _messages
from .messages import *  # noqa: F401,F403

__all__ = ["CanFrame", "decode_can", "from_can", "to_can", "G0", "Range", "SampleStatus", "DecodeError",
           "ErrorReason", "SampleBatch", "StreamDecoder", "decode_frame", "encode", "Lattice"]
__all__ += _messages.__all__
