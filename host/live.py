"""The live 3D view: the sheet in Foxglove (or any Foxglove WebSocket client), from foxglove-sdk.

`SceneChannels` turns estimates and contacts into Foxglove's own schemas (protobuf, registered by
foxglove-sdk): ``/sheet/scene`` a `foxglove.SceneUpdate` (entity ``lattice``: one line list, two
points per link, coloured per vertex; entity ``contacts``: a sphere per contact, its diameter the
contact's, and a text with its force), ``/sheet/joints`` a `foxglove.PointCloud` of the joints and
``/tf`` a `foxglove.FrameTransform` ``world`` -> ``sheet``. Colours (docs/recording.md):

* ``error`` (demo): joint error vs the virtual truth, % of side, 0 (blue) .. 2 % (red);
* ``displacement`` (tactile): normal displacement from rest, 0 .. max of the frame (blue .. red);
* ``links`` (default, a real sheet): valid links green, missing/invalid links red (drawn along
  the chord between their estimated joints).

`LiveServer` serves a context on ``ws://127.0.0.1:8765`` with the Foxglove WebSocket protocol
(subprotocol ``foxglove.sdk.v1``). Open it in Foxglove: *Open connection* -> *Foxglove WebSocket*
-> ``ws://localhost:8765``, then add a *3D* panel (fixed frame ``world``) and a *Plot* panel.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SceneChannels", "LiveServer", "colours", "COLOUR_MODES", "ERROR_FULL_SCALE_PCT"]

COLOUR_MODES = ("error", "displacement", "links")
#: % of side shown as full red in ``error`` mode
ERROR_FULL_SCALE_PCT = 2.0
_OK = (0.15, 0.75, 0.3, 1.0)
_MISSING = (0.9, 0.1, 0.1, 1.0)


def colours(values: np.ndarray, full_scale: float) -> np.ndarray:
    """RGBA in 0..1 for ``values`` (any shape) on a blue -> red ramp, 0 .. ``full_scale``; NaN grey.

    >>> colours(np.array([0.0, 1.0, np.nan]), 1.0)[:, :3].round(2).tolist()
    [[0.1, 0.2, 0.9], [0.9, 0.15, 0.1], [0.5, 0.5, 0.5]]
    """
    v = np.asarray(values, dtype=float)
    x = np.clip(v / full_scale if full_scale > 0 else np.zeros_like(v), 0.0, 1.0)
    lo, hi = np.array([0.1, 0.2, 0.9]), np.array([0.9, 0.15, 0.1])
    rgb = lo + x[..., None] * (hi - lo)
    rgb = np.where(np.isnan(v)[..., None], 0.5, rgb)
    return np.concatenate([rgb, np.ones(v.shape + (1,))], axis=-1)


class SceneChannels:
    """The 3D channels of one context (`foxglove.Context`) for a lattice.

    Parameters
    ----------
    context : foxglove.Context
    lattice : protocol.lattice.Lattice
    colour_by : {"error", "displacement", "links"}
    """

    def __init__(self, context, lattice, colour_by: str = "links") -> None:
        from foxglove.channels import FrameTransformChannel, PointCloudChannel, SceneUpdateChannel

        if colour_by not in COLOUR_MODES:
            raise ValueError(f"Invalid colour_by: {colour_by!r} (need one of {COLOUR_MODES})")
        self.lattice = lattice
        self.colour_by = colour_by
        self.scene = SceneUpdateChannel("/sheet/scene", context=context)
        self.cloud = PointCloudChannel("/sheet/joints", context=context)
        self.tf = FrameTransformChannel("/tf", context=context)
        self._ends = np.asarray(lattice.endpoints)

    def log_transform(self, t_ns: int) -> None:
        from foxglove.messages import FrameTransform, Quaternion, Timestamp, Vector3
        self.tf.log(FrameTransform(timestamp=_ts(t_ns, Timestamp), parent_frame_id="world", child_frame_id="sheet",
                                   translation=Vector3(x=0, y=0, z=0), rotation=Quaternion(x=0, y=0, z=0, w=1)),
                    log_time=t_ns)

    def link_colours(self, valid: np.ndarray, error: np.ndarray | None = None,
                     displacement: np.ndarray | None = None) -> np.ndarray:
        """RGBA per line-list vertex, shape (2 * n_links, 4), for the configured mode."""
        a, b = self._ends[:, 0], self._ends[:, 1]
        if self.colour_by == "error" and error is not None:
            per_joint = colours(np.asarray(error, dtype=float).ravel(), ERROR_FULL_SCALE_PCT)
        elif self.colour_by == "displacement" and displacement is not None:
            d = np.abs(np.asarray(displacement, dtype=float).ravel())
            per_joint = colours(d, float(np.nanmax(d)) if np.isfinite(d).any() and np.nanmax(d) > 0 else 1.0)
        else:
            per_joint = None
        if per_joint is None:
            c = np.where(np.asarray(valid, dtype=bool)[:, None], _OK, _MISSING)
            return np.repeat(c, 2, axis=0)
        out = np.empty((2 * a.shape[0], 4))
        out[0::2], out[1::2] = per_joint[a], per_joint[b]
        out[0::2][~valid] = out[1::2][~valid] = _MISSING  # missing links stay visible, in red
        return out

    def log_lattice(self, joints: np.ndarray, valid: np.ndarray, t_ns: int, *, error=None, displacement=None) -> None:
        """The lattice (line list) and the joints (point cloud) of one estimate; joints (rows, cols, 3) m."""
        from foxglove.messages import (Color, LinePrimitive, LinePrimitiveLineType, PackedElementField,
                                       PackedElementFieldNumericType, Point3, PointCloud, SceneEntity,
                                       SceneUpdate, Timestamp)

        if not (self.scene.has_sinks() or self.cloud.has_sinks()):
            return
        P = np.asarray(joints, dtype=float).reshape(-1, 3)
        ts = _ts(t_ns, Timestamp)
        cols = self.link_colours(np.asarray(valid, dtype=bool), error, displacement)
        pts = P[self._ends.ravel()]
        line = LinePrimitive(type=LinePrimitiveLineType.LineList, thickness=2.0, scale_invariant=True,
                             points=[Point3(x=x, y=y, z=z) for x, y, z in pts.tolist()],
                             colors=[Color(r=r, g=g, b=b_, a=al) for r, g, b_, al in cols.tolist()])
        self.scene.log(SceneUpdate(entities=[SceneEntity(timestamp=ts, frame_id="sheet", id="lattice", lines=[line])]),
                       log_time=t_ns)
        f32 = PackedElementFieldNumericType.Float32
        self.cloud.log(PointCloud(timestamp=ts, frame_id="sheet", point_stride=12,
                                  fields=[PackedElementField(name=n, offset=4 * k, type=f32)
                                          for k, n in enumerate("xyz")],
                                  data=P.astype("<f4").tobytes()), log_time=t_ns)

    def log_contacts(self, contacts: list[dict], t_ns: int) -> None:
        """Contacts as spheres (diameter 2 radius, at least 5 mm) with a text label ``#id F N``."""
        from foxglove.messages import (Color, Pose, Quaternion, SceneEntity, SceneUpdate, SpherePrimitive,
                                       TextPrimitive, Timestamp, Vector3)

        if not self.scene.has_sinks():
            return
        spheres, texts = [], []
        for c in contacts:
            if c.get("position") is None:  # e.g. a true contact known only by its lattice index
                continue
            x, y, z = (float(v) for v in c["position"])
            d = max(0.005, 2 * float(c.get("radius_m", 0.0)))
            pose = Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(x=0, y=0, z=0, w=1))
            spheres.append(SpherePrimitive(pose=pose, size=Vector3(x=d, y=d, z=d),
                                           color=Color(r=1.0, g=0.6, b=0.0, a=0.8)))
            tpose = Pose(position=Vector3(x=x, y=y, z=z + d), orientation=Quaternion(x=0, y=0, z=0, w=1))
            texts.append(TextPrimitive(pose=tpose, billboard=True, font_size=14, scale_invariant=True,
                                       color=Color(r=1, g=1, b=1, a=1),
                                       text=f"#{c.get('id', '?')} {float(c['force_n']):.2f} N"))
        self.scene.log(SceneUpdate(entities=[SceneEntity(timestamp=_ts(t_ns, Timestamp), frame_id="sheet",
                                                         id="contacts", spheres=spheres, texts=texts)]),
                       log_time=t_ns)


def _ts(t_ns: int, Timestamp):
    return Timestamp(int(t_ns // 1_000_000_000), int(t_ns % 1_000_000_000))


class LiveServer:
    """A Foxglove WebSocket server (foxglove-sdk) for one context, on localhost by default.

    Parameters
    ----------
    context : foxglove.Context
    port : int
        TCP port; 0 picks a free one (see `port`).
    host : str
        Interface to listen on; the default serves this machine only.
    """

    def __init__(self, context, port: int = 8765, host: str = "127.0.0.1", name: str = "capsheet") -> None:
        import foxglove

        if not 0 <= int(port) <= 65535:
            raise ValueError(f"Invalid port: {port!r} (need 0..65535)")
        try:
            self._server = foxglove.start_server(name=name, host=host, port=int(port), context=context)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error types (address in use, ...)
            raise OSError(f"Cannot start the live view on {host}:{port}: {exc}") from exc
        self.host = host
        self.port = int(self._server.port)

    @property
    def url(self) -> str:
        return f"ws://{'localhost' if self.host in ('127.0.0.1', '::1') else self.host}:{self.port}"

    def stop(self) -> None:
        self._server.stop()
