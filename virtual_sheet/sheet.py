"""The virtual sheet: a scene, a sensor model and one chip per link, with ground truth.

`VirtualSheet` is sans-I/O: it owns the chips and answers "what does chip k read at time t"; the
gateways (`virtual_sheet.gateway`) move frames between the chips and a host, and the devices
(`virtual_sheet.devices`) put a gateway behind a pty, a python-can bus or an SLCAN adapter.

* **Chips.** Link ``k`` carries the chip with uid ``uids[k]`` (64-bit, unique, drawn from
  ``seed`` by MT19937). The chip does not know its link until the host assigns it one; the host
  learns ``uid -> link`` from the layout file (`write_layout`) or works it out.
* **Chips.** ``engine="array"`` (default for the Python model): every chip's state in one
  `chiparray.ChipArray`, SYNC answered in one numpy step; ``engine="chips"``: one object per chip
  (``chip_factory``, e.g. the C firmware; what the array is checked against, frame for frame).
* **Readings.** At every SYNC the sheet evaluates the scene at the SYNC's time (time-varying
  scenes are solved at ``scene_rate_hz`` steps, the readings held in between; each step is solved
  once and kept — a periodic scene's ``period_s * scene_rate_hz`` steps, `precompute` does them
  all before streaming — so a moving scene costs nothing per SYNC once seen),
  takes the ideal specific force of every link (`geometry.ideal_readings`) and turns it into ADC
  counts with the sensor model (`sensor.SensorModel`: noise, per-chip bias, scale, misalignment,
  saturation). One evaluation serves every chip that answers that SYNC.
* **Ground truth.** `truth(counter)` gives the joints the readings of that SYNC counter came from
  (the last 65536 counters are kept: the counter is 16 bits); `link_of_uid` the physical layout.

Layout file (written by `write_layout`, read by the host to assign link addresses). CSV, one chip
per line after a header, uid in hex with ``0x``, link the lattice address (docs/design.md link order)::

    uid,link
    0x3A9F0C12D4E5B601,0
    0x91B2C3D4E5F60718,1

If the path ends in ``.json`` it is JSON instead::

    {"format": "capsheet-layout", "version": 1, "rows": 14, "cols": 14,
     "chips": [{"uid": "0x3A9F0C12D4E5B601", "link": 0}, ...]}
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from pathlib import Path
from typing import Any, Callable

import numpy as np

from protocol.constants import ADC_MAX, ADC_MIN, G0, SampleStatus
from protocol.lattice import Lattice
from protocol.layout import save_layout
from .chip import ChipModel

#: SYNC times kept for the truth (`VirtualSheet.truth_time`): 28 s at 145 Hz, far more than any
#: snapshot stays in flight
SYNC_TIMES_KEPT = 4096
from .arrival import SyncArrival
from .chiparray import ChipArray
from .faults import DriftingSensor, FaultSpec, FaultStats, wrap_chip
from .geometry import ideal_readings
from .sensor import SensorModel
from .sensor import check_readings
from .imu import SENSOR_SETS, GyroModel, ImuArray, MagModel
from .imu_source import MOTION_SHAPES, ImuSource
from .motion import make_motion_scene
from .shapes import SCENES, SHAPES, StaticScene, make_scene

__all__ = ["VirtualSheet", "make_uids"]


def make_uids(n: int, seed: int) -> list[int]:
    """``n`` distinct non-zero 64-bit uids, deterministic from ``seed`` (MT19937)."""
    g = np.random.Generator(np.random.MT19937([seed, 0x0D1D]))
    out: list[int] = []
    seen: set[int] = set()
    while len(out) < n:
        for u in g.integers(1, 1 << 63, size=n, dtype=np.int64).tolist():
            u = (u << 1) | (len(out) & 1)  # use the top bit too
            if u and u not in seen:
                seen.add(u)
                out.append(u)
                if len(out) == n:
                    break
    return out


class VirtualSheet:
    """A simulated capture sheet (module docstring).

    Parameters
    ----------
    shape : str
        A scene (`shapes.SCENES`: grow, tilt, press) or a static shape (`shapes.SHAPES`).
    lattice : str or (rows, cols) or Lattice
        Joints, e.g. ``"14x14"``.
    link_length : float
        Metres.
    shape_params : dict, optional
        Passed to `shapes.make_scene`.
    scene : Scene, optional
        Use this scene instead of ``shape`` (anything with ``joints(t_s)``).
    noise : float
        Sensor noise, % of g per axis (ignored when ``sensor`` is given).
    sensor : SensorModel, optional
        The full sensor model (bias, scale, misalignment, range ...).
    seed : int
        Seeds uids, per-chip errors and noise.
    transport : {"serial", "can"}
        Frame type the chips speak.
    fd : bool
        CAN FD chips.
    chip_factory : callable, optional
        ``factory(uid, sensor, transport=, fd=, calibration=, seed=)`` -> chip; default
        `ChipModel` (the C firmware: ``firmware_ref.chip.CFirmwareChip``).
    faults : FaultSpec or str, optional
        Chip faults (dead, babbling, drifting) are applied here; stream faults by the gateway.
    scene_rate_hz : float
        How often a time-varying scene is re-solved.
    engine : {"array", "chips"}, optional
        Chips as one vectorised `ChipArray` or one object each; default "array" for the Python
        model, "chips" when ``chip_factory`` is given.
    sensors : {"accel", "accel+gyro", "accel+gyro+mag"}
        The chips' sensors (docs/protocol.md §16). A moving scene of `imu_source.MOTION_SHAPES`
        (carry, wave, elbow, tap, flat_turn, tumble) or a static shape can carry any; the chips then read
        the phase-1 models (`imu.ImuArray`: ICM-42688-P gyroscope, LIS3MDL magnetometer in Earth's
        field, the accelerometer of ``sensor``/``noise``) through an `imu_source.ImuSource`.
    shuffle_ids : bool
        Put the seed's uids on links in a seeded random order (`make_uids`' order otherwise): a
        sheet whose layout a host must learn (``capsheet layout learn``); only `layout` tells it.
    sync_arrival : bool
        The chips sample a SYNC at its estimated arrival (`arrival.SyncArrival`: a read that came
        late is put one SYNC period after the previous SYNC's arrival) instead of when the gateway
        read it: a pty read late on a loaded machine is a delay no wire adds (docs/motion.md).
    """

    def __init__(self, shape: str = "gaussian", lattice: Any = "14x14", *, link_length: float = 0.01,
                 shape_params: dict | None = None, scene=None, noise: float = 0.0,
                 sensor: SensorModel | None = None, seed: int = 0, transport: str = "serial",
                 fd: bool = False, chip_factory: Callable[..., Any] | None = None,
                 faults: FaultSpec | str | None = None, scene_rate_hz: float = 50.0,
                 engine: str | None = None, sensors: str = "accel", sync_arrival: bool = True,
                 shuffle_ids: bool = False) -> None:
        if isinstance(lattice, Lattice):
            self.lattice = lattice
        elif isinstance(lattice, str):
            self.lattice = Lattice.parse(lattice)
        else:
            self.lattice = Lattice(*lattice)
        rows, cols = self.lattice.rows, self.lattice.cols
        self.shape = shape
        self.sensors = sensors
        if sensors not in SENSOR_SETS:
            raise ValueError(f"Invalid sensors: {sensors!r} (expected one of {', '.join(SENSOR_SETS)})")
        self.sensor_model = sensor if sensor is not None else SensorModel(noise_pct_g=noise, chip_seed=seed)
        self.imu_source: ImuSource | None = None
        if scene is None and (shape in MOTION_SHAPES or sensors != "accel"):
            if shape in MOTION_SHAPES or shape in ("grow", "board"):  # grow, board: exact kinematics too
                motion = make_motion_scene(shape, rows, cols, link_length, **(shape_params or {}))
            elif shape in SHAPES:
                motion = make_motion_scene("rest", rows, cols, link_length, shape=shape, **(shape_params or {}))
            else:
                raise ValueError(f"Invalid shape {shape!r} for {sensors} chips: a moving scene "
                                 f"({', '.join(MOTION_SHAPES)}) or a static shape ({', '.join(SHAPES)})")
            cs = seed
            gyro = GyroModel.part("icm42688p", chip_seed=cs) if "gyro" in sensors else None
            mag = MagModel.part("lis3mdl", chip_seed=cs) if "mag" in sensors else None
            self.imu_source = ImuSource(motion, ImuArray(self.lattice.n_links, accel=self.sensor_model, gyro=gyro,
                                                         mag=mag, seed=seed))
            scene = motion
        if scene is None and shape not in SCENES and shape not in SHAPES:
            raise ValueError(f"Unknown scene {shape!r}; scenes: {', '.join(SCENES)}; moving (for 6/9-axis "
                             f"chips too): {', '.join(MOTION_SHAPES)}; static shapes: {', '.join(SHAPES)}")
        self.scene = scene if scene is not None else make_scene(shape, rows, cols, link_length,
                                                                **(shape_params or {}))
        self.static = isinstance(self.scene, StaticScene)
        self.seed = seed
        self.transport = transport
        self.fd = fd
        self.scene_rate_hz = float(scene_rate_hz)
        self.faults = FaultSpec.parse(faults) if isinstance(faults, str) or faults is None else faults
        self.fault_stats = FaultStats()
        n = self.n_links = self.lattice.n_links
        self.uids = make_uids(n, seed)
        if shuffle_ids:  # the same uids on other links: a host that knew this seed's layout knows nothing
            order = np.random.Generator(np.random.MT19937([seed, 0x5AF1E])).permutation(n)
            self.uids = [self.uids[k] for k in order.tolist()]
        self.link_of_uid = {u: k for k, u in enumerate(self.uids)}
        self._noise_rng = np.random.Generator(np.random.MT19937([seed, 0x401CE]))
        self._lock = threading.Lock()
        self._joint_cache: tuple[float, np.ndarray, np.ndarray] | None = None  # (t_q, joints, readings)
        self._scenes: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}  # scene step -> (t_q, joints, readings)
        self._period_steps = self._scene_period_steps()
        # (now_s, counts (n, 3) int64, status (n,) int64, counts as tuples or None, status list or None)
        self._cache: tuple = (None, None, None, None, None)
        self._fast: tuple | None = None  # `_sample`: (model, chip errors, buffer, {step: (readings, Mᵀ f)})
        self._no_status = np.zeros(n, dtype=np.int64)  # every link OK (shared, read-only)
        self._no_status.setflags(write=False)
        #: counter -> when its SYNC reached the chips, the newest `SYNC_TIMES_KEPT` (a day-long run
        #: would otherwise hold every counter: 65536 floats and ints, ~6 MB); older ones cut, counted
        self.sync_times: OrderedDict[int, float] = OrderedDict()
        self.sync_times_cut = 0
        #: when each SYNC reached the chips, from when it was read (None: when it was read)
        self.sync_arrival: SyncArrival | None = SyncArrival() if sync_arrival else None
        self._read_at: tuple[float, float] | None = None  # (read time, arrival) of the newest SYNC
        offset, sens = self.sensor_model.stored_calibration(n)  # what the chips hold before CAL_WRITE
        q4 = np.clip(np.rint(offset * 16), -32768, 32767).astype(int).tolist()
        cal = [tuple(zip(q4[k], sens[k].tolist())) for k in range(n)]
        if engine is None:
            engine = "chips" if chip_factory is not None and chip_factory is not ChipModel else "array"
        if engine not in ("array", "chips"):
            raise ValueError(f"Invalid engine: {engine!r} (expected 'array' or 'chips')")
        if engine == "array" and chip_factory not in (None, ChipModel):
            raise ValueError("engine='array' runs the Python chip model; give engine='chips' for chip_factory")
        self.engine_name = engine  #: "array" (one `ChipArray`, `array`) or "chips" (one object per chip, `chips`)
        self.chip_factory = chip_factory or ChipModel
        self.reply_delay_s = [0.0] * n
        self.chips = []
        self.array: ChipArray | None = None
        if engine == "array":
            drift = {}
            for k in self.faults.drift_chip:
                if 0 <= k < n:
                    drift[k] = DriftingSensor(self._source(k), self.faults.drift, self.fault_stats)
                    self.reply_delay_s[k] = self.faults.drift_late_ms / 1e3
            self.array = ChipArray(self.uids, self._batch_source, transport=transport, fd=fd, calibrations=cal,
                                   sensors=drift, faults=self.faults, fault_stats=self.fault_stats,
                                   imu_sensors=sensors, imu=self._batch_imu if sensors != "accel" else None)
            self.chips = self.array.chips
            return
        for k, uid in enumerate(self.uids):
            src: Callable = self._source(k)
            if k in self.faults.drift_chip:
                src = DriftingSensor(src, self.faults.drift, self.fault_stats)
                self.reply_delay_s[k] = self.faults.drift_late_ms / 1e3
            extra = {} if sensors == "accel" else {"sensors": sensors, "imu": self._imu_scalar(k)}
            chip = self.chip_factory(uid, src, transport=transport, fd=fd, calibration=cal[k], seed=seed + k, **extra)
            self.chips.append(wrap_chip(chip, k, self.faults, self.fault_stats, can=transport == "can"))

    # ------------------------------------------------------------------ readings
    def _batch_imu(self, now_s: float, idx: np.ndarray, gyro_range, mag_range):
        """The chip array's IMU source: gyroscope and magnetometer counts at the chips' ranges and
        ``time_us``, at the instant the accelerometer of the same SYNC was read."""
        _a, _s, g, m, t = self.imu_source.read(self._sample_time(now_s), idx, gyro_range, mag_range)
        return g, m, t

    def _sample_time(self, now_s: float) -> float:
        """When the chips sample for a call at ``now_s``: the arrival of the SYNC read at ``now_s``
        (`record_sync`), else ``now_s``."""
        r = self._read_at
        return r[1] if r is not None and r[0] == now_s else now_s

    def _imu_scalar(self, k: int):
        idx = np.array([k])

        def source(now_s: float, gyro_range: int, mag_range: int, _idx=idx):
            g, m, t = self._batch_imu(now_s, _idx, gyro_range, mag_range)
            return tuple(g[0].tolist()), (None if m is None else tuple(m[0].tolist())), int(t[0])
        return source

    def _source(self, k: int) -> Callable[[float], tuple]:
        def source(now_s: float, _k=k):
            t = self._sample_time(now_s)
            c = self._cache
            if c[0] != t:
                c = self._refresh(t)
            if c[3] is None:
                c = self._lists()
            return c[3][_k], c[4][_k]
        return source

    def _batch_source(self, now_s: float, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The `chiparray.BatchSensor`: counts and status of chips ``idx`` (distinct, ascending, as
        the chip array passes them) at ``now_s``; every chip: the cached arrays themselves (read-only)."""
        t = self._sample_time(now_s)
        c = self._cache
        if c[0] != t:
            c = self._refresh(t)
        if idx.size == self.n_links:
            return c[1], c[2]
        if idx.size and int(idx[-1]) - int(idx[0]) + 1 == idx.size:  # a gateway's block: views, no copies
            return c[1][idx[0]:idx[-1] + 1], c[2][idx[0]:idx[-1] + 1]
        return c[1][idx], c[2][idx]

    def _lists(self):
        with self._lock:
            c = self._cache
            if c[3] is None:
                c = self._cache = (c[0], c[1], c[2], [tuple(r) for r in c[1].tolist()], c[2].tolist())
            return c

    def _scene_period_steps(self) -> int | None:
        if self.static:
            return None
        period = getattr(self.scene, "period_s", None)
        if period is None:
            return None
        steps = period * self.scene_rate_hz
        return int(round(steps)) if abs(steps - round(steps)) < 1e-9 and round(steps) >= 1 else None

    def precompute(self) -> int:
        """Solve every step of a periodic scene now (before streaming); returns how many. A
        non-periodic scene is solved as it goes (each step once)."""
        if self.imu_source is not None:
            return self.imu_source.precompute()
        if self._period_steps is None:
            return 0
        for i in range(self._period_steps):
            self._scene_step(i / self.scene_rate_hz)
        return self._period_steps

    def _scene_time(self, t_s: float) -> float:
        if self.static:
            return 0.0
        return math.floor(t_s * self.scene_rate_hz) / self.scene_rate_hz

    def _step_key(self, tq: float) -> int:
        if self.static:
            return 0
        key = int(round(tq * self.scene_rate_hz))
        if self._period_steps is not None:
            key %= self._period_steps
        return key

    def _scene_step(self, tq: float) -> tuple[float, np.ndarray, np.ndarray]:
        """``(tq, joints, ideal readings)`` of scene time ``tq`` (a step), solved once and kept."""
        key = self._step_key(tq)
        e = self._scenes.get(key)
        if e is None:
            t_solve = key / self.scene_rate_hz if not self.static else 0.0
            joints = np.asarray(self.scene.joints(t_solve), dtype=float)
            joints.setflags(write=False)
            e = (t_solve, joints, ideal_readings(joints))
            if len(self._scenes) >= 4096 and self._period_steps is None:
                self._scenes.clear()  # bounded: a long non-periodic run re-solves old steps
            self._scenes[key] = e
        return e

    def specific_force(self, t_s: float) -> np.ndarray:
        """Every link's specific force at ``t_s`` (m/s², sensor frame, shape (n_links, 3)): what a
        perfect accelerometer on it reads, before the sensor model."""
        return np.asarray(self._geometry(t_s)[2], dtype=float)

    def _geometry(self, t_s: float) -> tuple[float, np.ndarray, np.ndarray]:
        tq = self._scene_time(t_s)
        jc = self._joint_cache
        if jc is None or jc[0] != tq:
            _t, joints, readings = self._scene_step(tq)
            jc = self._joint_cache = (tq, joints, readings)
        return jc

    def _refresh(self, now_s: float):
        with self._lock:
            c = self._cache
            if c[0] == now_s:
                return c
            if self.imu_source is not None:  # a moving sheet: the accelerometers read its truth
                every = np.arange(self.n_links)
                counts, status = self.imu_source.read(now_s, every)[:2]
                stale = self.imu_source.mark_read(now_s, every)  # a repeated instant: no new conversion
                if stale.any():
                    status = status | np.where(stale, int(SampleStatus.STALE), 0)
                counts.setflags(write=False)
                status.setflags(write=False)
                c = self._cache = (now_s, counts, status, None, None)
                return c
            tq, _joints, readings = self._geometry(now_s)
            m = self.sensor_model
            if m.motion_accel_mps2 is None:
                counts, status = self._sample(m, tq, readings)
            else:
                counts, status = m.sample(readings, self._noise_rng if m.noise_pct_g > 0 else None)
            counts, status = np.asarray(counts, dtype=np.int64), np.asarray(status, dtype=np.int64)
            counts.setflags(write=False)
            if status.flags.writeable:
                status.setflags(write=False)
            c = self._cache = (now_s, counts, status, None, None)
            return c

    def _sample(self, m: SensorModel, tq: float, readings: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`SensorModel.sample` of ``readings`` (scene step ``tq``), the same numbers from the same
        noise draws, with what does not change per SYNC kept: the chip errors, and per scene step
        the readings in the chips' own (misaligned) axes. Per SYNC: noise, scale, round, clip."""
        fast = self._fast
        if fast is None or fast[0] is not m:
            fast = self._fast = (m, m.chip_errors(self.n_links), np.empty((self.n_links, 3)), {})
        _m, e, buf, steps = fast
        key = self._step_key(tq)
        f = steps.get(key)
        if f is None or f[0] is not readings:
            fm = np.einsum("nij,ni->nj", e.misalignment, check_readings(readings))  # Mᵀ f, as sample()
            if len(steps) >= 4096:
                steps.clear()
            f = steps[key] = (readings, fm)
        fm = f[1]
        if m.noise_pct_g > 0:  # normal(0, s) draws loc + s * z: the same z, in the same order
            self._noise_rng.standard_normal(out=buf)
            buf *= m.noise_std_mps2
            buf += fm
        else:
            np.copyto(buf, fm)
        buf /= G0
        buf *= e.sensitivity
        buf += e.offset_counts
        np.rint(buf, out=buf)
        if buf.max() < ADC_MAX and buf.min() > ADC_MIN:  # nothing at a limit: nothing to clip
            return buf.astype(np.int64), self._no_status
        np.minimum(buf, ADC_MAX, out=buf)  # np.clip, without its per-call overhead
        np.maximum(buf, ADC_MIN, out=buf)
        counts = buf.astype(np.int64)
        at = (counts == ADC_MIN) | (counts == ADC_MAX)
        saturated = at[:, 0] | at[:, 1] | at[:, 2]  # .any(axis=1), a reduction slow on 3 columns
        return counts, saturated.astype(np.int64) * int(SampleStatus.SATURATED)

    def counts_at(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """One fresh draw of every link's ``(counts (n, 3), status (n,))`` at ``t_s`` (tests)."""
        _tq, _j, readings = self._geometry(t_s)
        m = self.sensor_model
        return m.sample(readings, self._noise_rng if m.noise_pct_g > 0 else None)

    # ------------------------------------------------------------------ truth
    def record_sync(self, counter: int, now_s: float) -> None:
        """Called by the gateways when they read a SYNC (at ``now_s``), before its chips answer: its
        arrival (`sync_arrival`) is when they sample, and what `truth` takes."""
        c = counter & 0xFFFF
        a = now_s if self.sync_arrival is None else self.sync_arrival.arrival(c, now_s)
        self._read_at = (now_s, a)
        st = self.sync_times
        st[c] = a
        st.move_to_end(c)  # a counter seen again after a wrap is the newest
        if len(st) > SYNC_TIMES_KEPT:
            st.popitem(last=False)
            self.sync_times_cut += 1

    def truth_time(self, counter: int) -> float:
        """Scene time of the readings answering SYNC ``counter`` (KeyError if never seen)."""
        if self.imu_source is not None:  # the grid instant the chips read (`imu_source.ImuSource`)
            return self.imu_source.time_of(self.sync_times[counter & 0xFFFF])
        return self._scene_time(self.sync_times[counter & 0xFFFF])

    def truth(self, counter: int) -> np.ndarray:
        """Joints ``(rows, cols, 3)``, metres, that the SYNC ``counter``'s readings came from."""
        return self.joints_at_scene_time(self.truth_time(counter))

    def joints_at_scene_time(self, tq: float) -> np.ndarray:
        """Joints ``(rows, cols, 3)`` of scene step ``tq`` (a `truth_time`), exactly as the chips'
        readings were made from them (the same solved step)."""
        if self.imu_source is not None:
            return self.imu_source.joints_at(tq)
        return self._scene_step(tq)[1].copy()

    def joints(self, t_s: float = 0.0) -> np.ndarray:
        """Joints at scene time ``t_s`` (as the chips see them)."""
        return self.joints_at_scene_time(self._scene_time(t_s))

    # ------------------------------------------------------------------ layout
    @property
    def layout(self) -> dict[int, int]:
        """``{uid: link}``: which chip sits on which link."""
        return dict(self.link_of_uid)

    def chip_of_link(self, link: int):
        return self.chips[link]

    def calibration(self) -> tuple[np.ndarray, np.ndarray]:
        """True per-chip ``(offset_counts (n, 3), sensitivity (n, 3))`` (what CAL_DATA reports)."""
        return self.sensor_model.true_calibration(self.n_links)

    def write_layout(self, path: str | Path) -> Path:
        """Write the ``uid -> link`` layout (module docstring for the format)."""
        return save_layout(path, {u: k for k, u in enumerate(self.uids)}, self.lattice.rows, self.lattice.cols)

    def split(self, n_buses: int) -> list[range]:
        """Contiguous link blocks, one per bus (links ``b*n/N .. (b+1)*n/N - 1`` on bus b)."""
        if not 1 <= n_buses <= self.n_links:
            raise ValueError(f"Invalid bus count {n_buses} (need 1..{self.n_links})")
        edges = [round(b * self.n_links / n_buses) for b in range(n_buses + 1)]
        return [range(edges[b], edges[b + 1]) for b in range(n_buses)]

    def __repr__(self) -> str:
        return (f"VirtualSheet({self.shape!r}, {self.lattice.rows}x{self.lattice.cols}, "
                f"{self.n_links} chips, transport={self.transport!r})")
