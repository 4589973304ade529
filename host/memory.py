"""glibc's allocator in processes that run for days.

glibc serves a large allocation (128 KiB and up, at first) with its own ``mmap`` and gives the pages
back at ``free``. But it *raises* that threshold to the size of every mmapped block freed (up to 32
MiB on 64-bit), so after a few megabyte-sized buffers come and go — an MCAP chunk and its zstd
context when a recording starts its next file, numpy temporaries — later ones of that size come
from the heap, whose free space is returned to the system only from its top: the resident size
steps up and stays. Measured with ``benchmarks/bench_soak.py --duration 420 --split-duration 100``
(14x14 at 145 Hz, recording, a file every 100 s): the host grew 94.7 → 128.9 MB, 5.3 MB over the
run after the warm-up; with the threshold fixed at glibc's default (environment
``MALLOC_MMAP_THRESHOLD_=131072``, the same as `fix_mmap_threshold`) 1.25 MB. ``MALLOC_ARENA_MAX=2``
alone did not help (+8.2 MB).

`fix_mmap_threshold` sets the threshold explicitly (``mallopt(M_MMAP_THRESHOLD, …)``), which also
turns the dynamic adjustment off (mallopt(3)). `host.cli.main` calls it for every command, unless
the user chose a threshold in the environment, and starts one `TrimThread` that gives freed pages
back once a minute. Elsewhere than glibc both do nothing.
"""

from __future__ import annotations

import ctypes
import os
import sys
import threading
import time

#: <malloc.h>
M_MMAP_THRESHOLD = -3
#: glibc's initial threshold, bytes: what `fix_mmap_threshold` keeps
MMAP_THRESHOLD = 128 * 1024
#: the environment variable through which a user sets the threshold themselves (mallopt(3))
ENV_VAR = "MALLOC_MMAP_THRESHOLD_"


def _glibc(name: str, restype, argtypes=None):
    """glibc's function ``name`` with its types set, or None off Linux or off glibc (musl has no
    libc.so.6) or when this glibc lacks it (mallinfo2 before 2.33)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = getattr(ctypes.CDLL("libc.so.6"), name)
    except (OSError, AttributeError):
        return None
    fn.restype = restype
    if argtypes is not None:
        fn.argtypes = argtypes
    return fn


def fix_mmap_threshold(threshold: int = MMAP_THRESHOLD) -> bool:
    """Fix glibc's mmap threshold at ``threshold`` bytes (module docstring). Returns whether it was
    set: False off glibc, or when the user set ``MALLOC_MMAP_THRESHOLD_`` (theirs stands)."""
    mallopt = None if ENV_VAR in os.environ else _glibc("mallopt", ctypes.c_int, [ctypes.c_int, ctypes.c_int])
    return mallopt is not None and bool(mallopt(M_MMAP_THRESHOLD, int(threshold)))


def trim() -> bool:
    """glibc's ``malloc_trim(0)``: give the system back the free pages of every arena, from
    anywhere in the heap, not only its top. Returns whether any memory was released (False off
    glibc). A few ms on a host's heap, without the interpreter lock (ctypes releases it)."""
    fn = _glibc("malloc_trim", ctypes.c_int, [ctypes.c_size_t])
    return fn is not None and bool(fn(0))


#: how often a long-running command gives freed memory back (`PeriodicTrim`), seconds
TRIM_EVERY_S = 60.0


class PeriodicTrim:
    """`trim` at most every ``every_s`` (sans-I/O: `poll` takes ``now``). A host's threads free
    what they allocated in their own arenas, and glibc keeps the free pages between the blocks in
    use: the soak benchmark's host rose 2.2 MB over its minutes 2–7 and held, while the heap in
    use did not grow (docs/benchmarks.md, "Long runs"). ``trims`` counts the calls, ``released``
    those that gave memory back."""

    def __init__(self, every_s: float = TRIM_EVERY_S, trim_fn=trim) -> None:
        if not every_s > 0:
            raise ValueError(f"Invalid every_s: {every_s!r} (need > 0)")
        self.every_s = float(every_s)
        self._trim = trim_fn
        self._next: float | None = None
        self.trims = 0
        self.released = 0

    def poll(self, now: float) -> bool:
        """Trim if ``every_s`` passed since the last (the first call only starts the clock);
        returns whether it trimmed."""
        if self._next is None:
            self._next = now + self.every_s
            return False
        if now < self._next:
            return False
        self._next = now + self.every_s
        self.trims += 1
        self.released += bool(self._trim())
        return True



class TrimThread:
    """A `PeriodicTrim` polled by a daemon thread of its own: the one periodic trim of every
    command, started where the command line starts (`host.cli.main`) rather than polled from each
    command's loop. It wakes once per ``trimmer.every_s``; ``malloc_trim`` runs without the
    interpreter lock (ctypes releases it), so a streaming thread is not held up by it.

    ``clock`` and ``wait`` are arguments so that a test can drive it without sleeping."""

    def __init__(self, trimmer: PeriodicTrim | None = None, *, clock=time.monotonic) -> None:
        self.trimmer = trimmer if trimmer is not None else PeriodicTrim()
        self._clock = clock
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def run(self, wait=None) -> None:
        """The thread's loop: poll, then wait ``every_s`` (``wait(seconds) -> stop?``), until stopped."""
        wait = self._stop.wait if wait is None else wait
        self.trimmer.poll(self._clock())  # starts its clock
        while not wait(self.trimmer.every_s):
            self.trimmer.poll(self._clock())

    def start(self) -> "TrimThread":
        if self._thread is None:
            self._thread = threading.Thread(target=self.run, name="capsheet-trim", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()


_process_trim: tuple[int, TrimThread] | None = None  # (the pid that started it, the thread)
_process_trim_lock = threading.Lock()


def process_trim() -> TrimThread:
    """The process's one `TrimThread`, started at the first call and returned again after.

    `host.cli.main` calls it as each command starts: a program (or a test) that runs many commands
    in one interpreter gets one trim thread, not one per command (66 had piled up in one test
    worker). A forked child, which has no copy of the thread, starts its own."""
    global _process_trim
    with _process_trim_lock:
        pid = os.getpid()
        if _process_trim is None or _process_trim[0] != pid or not _process_trim[1].alive:
            _process_trim = (pid, TrimThread().start())
        return _process_trim[1]

# -- what grows, and what the cyclic collector costs: a probe cheap enough for a live host ---------

#: the environment variable that starts `MemoryProbe` in ``capsheet host``: ``PATH[,EVERY_S]``
PROBE_ENV_VAR = "CAPSHEET_MEMORY_PROBE"


class _MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                               "fsmblks", "uordblks", "fordblks", "keepcost")]


def mallinfo2() -> dict | None:
    """glibc's heap statistics in bytes (mallinfo2(3)): ``arena`` (main heap from sbrk),
    ``hblkhd`` (in mmapped blocks), ``uordblks`` (in use), ``fordblks`` (free in the heap, kept),
    ``keepcost`` (releasable from the top). None off glibc or before 2.33."""
    fn = _glibc("mallinfo2", _MallInfo2)  # one class: a new ctypes class per call is a cycle only gen 2 frees
    if fn is None:
        return None
    mi = fn()
    return {n: int(getattr(mi, n)) for n in ("arena", "hblkhd", "uordblks", "fordblks", "keepcost")}


class GcPauses:
    """Pause times of Python's cyclic collector, per generation, from ``gc.callbacks``.

    Sans-I/O: `on_gc` is the callback (``phase`` "start"/"stop", ``info["generation"]``) and reads
    ``clock()`` (seconds); `install` / `remove` hook it into ``gc.callbacks``. Bounded: per
    generation a count, the total and the largest pause, and counts of pauses of at least each of
    `LONG_S` (no list of pauses is kept).
    """

    #: pauses at least this long are counted apart (seconds)
    LONG_S = (0.005, 0.020, 0.050)

    def __init__(self, clock) -> None:
        self.clock = clock
        self.count = [0, 0, 0]
        self.total_s = [0.0, 0.0, 0.0]
        self.max_s = [0.0, 0.0, 0.0]
        self.at_least = [[0] * len(self.LONG_S) for _ in range(3)]
        self.collected = [0, 0, 0]
        self._t0: float | None = None

    def on_gc(self, phase: str, info: dict) -> None:
        if phase == "start":
            self._t0 = self.clock()
            return
        if phase != "stop" or self._t0 is None:
            return
        g = min(max(int(info.get("generation", 0)), 0), 2)
        dt = self.clock() - self._t0
        self._t0 = None
        self.count[g] += 1
        self.total_s[g] += dt
        self.max_s[g] = max(self.max_s[g], dt)
        self.collected[g] += int(info.get("collected", 0))
        for i, lim in enumerate(self.LONG_S):
            if dt >= lim:
                self.at_least[g][i] += 1

    def install(self) -> None:
        import gc
        if self.on_gc not in gc.callbacks:
            gc.callbacks.append(self.on_gc)

    def remove(self) -> None:
        import gc
        if self.on_gc in gc.callbacks:
            gc.callbacks.remove(self.on_gc)

    def as_dict(self) -> dict:
        return {f"gen{g}": {"count": self.count[g], "total_ms": round(1e3 * self.total_s[g], 2),
                            "max_ms": round(1e3 * self.max_s[g], 3), "collected": self.collected[g],
                            **{f"at_least_{int(lim * 1e3)}ms": self.at_least[g][i]
                               for i, lim in enumerate(self.LONG_S)}}
                for g in range(3)}


def type_counts(top: int | None = None) -> dict[str, int]:
    """Objects the cyclic collector tracks, by type name (containers only: ints, floats, strs and
    bytes are not tracked, their growth shows in `sys.getallocatedblocks`). Walks the heap: tens of
    ms on a host's heap, so a probe does it every few minutes, not per snapshot."""
    import gc
    from collections import Counter
    c = Counter(type(o).__qualname__ for o in gc.get_objects())
    return dict(c.most_common(top))


_SIZED = (dict, list, set, bytearray)


def container_lengths(min_len: int = 16) -> dict[int, tuple[int, str]]:
    """Every dict, list, set, deque and bytearray with at least ``min_len`` items that the
    collector tracks *or* that a tracked object refers to (a dict of only ints and floats is not
    tracked itself), by ``id``: (length, "owner type.container type"). Two calls a few minutes
    apart name the structures that grow. Walks the heap: a probe's job, not a live path's.
    Types are taken with ``type()``, never ``isinstance``: a dead ``weakref.proxy`` raises
    ReferenceError on any attribute access, ``__class__`` included."""
    import gc
    from collections import deque
    sized = _SIZED + (deque,)

    def length(x) -> int:
        return len(x) if issubclass(type(x), sized) else -1

    out: dict[int, tuple[int, str]] = {}
    for o in gc.get_objects():
        owner = type(o).__qualname__
        if length(o) >= min_len:
            out[id(o)] = (len(o), f"-.{owner}")
        if issubclass(type(o), (list, tuple, set, frozenset)):
            continue  # their items are tracked themselves, or atoms
        for r in gc.get_referents(o):
            if not gc.is_tracked(r) and length(r) >= min_len:
                out[id(r)] = (len(r), f"{owner}.{_field_name(o, r)}{type(r).__qualname__}"[:120])
            elif issubclass(type(r), dict) and gc.is_tracked(r):  # an instance's __dict__: its fields
                for k, v in r.items():
                    if length(v) >= min_len:
                        out[id(v)] = (len(v), f"{owner}.{k}:{type(v).__qualname__}"[:120])
    return out


def _field_name(owner, value) -> str:
    """``"name:"`` of the attribute of ``owner`` that is ``value`` ("" if none is): Python 3.11
    keeps an instance's attributes without a dict, so its referents come without their names."""
    try:
        for k, v in vars(owner).items():
            if v is value:
                return f"{k}:"
    except (TypeError, ReferenceError):  # no __dict__, or a dead weakref.proxy
        pass
    return ""


class MemoryProbe:
    """Every ``every_s`` a JSON line to ``path``: resident size, glibc heap (`mallinfo2`), Python's
    allocated blocks, tracked objects by type (the ``top`` most numerous, and the ``top`` largest
    changes since the previous line), the collector's counts and its pauses (`GcPauses`), whether
    objects were frozen. For attributing growth in a long run (``benchmarks/bench_soak.py --probe``)."""

    def __init__(self, path: str, every_s: float = 120.0, top: int = 25, extra=None) -> None:
        import time
        self.path, self.every_s, self.top = path, float(every_s), int(top)
        self.extra = extra  # () -> dict: the owner's counters, in every line
        self._lens: dict[int, tuple[int, str]] = {}
        self.pauses = GcPauses(time.perf_counter)
        self._prev: dict[str, int] = {}
        self._stop = None
        self._thread = None

    def line(self, t_s: float) -> dict:
        import gc
        counts = type_counts()
        diff = {k: counts.get(k, 0) - self._prev.get(k, 0) for k in set(counts) | set(self._prev)}
        changed = dict(sorted(((k, v) for k, v in diff.items() if v), key=lambda kv: -abs(kv[1]))[:self.top])
        self._prev = counts
        lens = container_lengths()
        grew = sorted(((n - self._lens[i][0], n, what) for i, (n, what) in lens.items()
                       if i in self._lens and self._lens[i][1] == what and n != self._lens[i][0]),
                      key=lambda g: -abs(g[0]))[:self.top]
        new_big = sorted(((n, what) for i, (n, what) in lens.items() if i not in self._lens and n >= 1000),
                         reverse=True)[:self.top]
        self._lens = lens
        rss = None
        try:
            with open("/proc/self/status") as f:
                rss = next((int(s.split()[1]) for s in f if s.startswith("VmRSS:")), None)
        except OSError:
            pass
        return {"t_s": round(t_s, 1), "rss_kb": rss, "mallinfo2": mallinfo2(),
                "allocated_blocks": sys.getallocatedblocks(), "gc_count": list(gc.get_count()),
                "gc_frozen": gc.get_freeze_count(), "tracked": sum(counts.values()),
                "top": dict(sorted(counts.items(), key=lambda kv: -kv[1])[:self.top]),
                "changed": changed, "containers_grew": [list(g) for g in grew],
                "containers_new_large": [list(g) for g in new_big],
                "largest_containers": sorted(lens.values(), reverse=True)[:10],
                "gc_pauses": self.pauses.as_dict(), **({"extra": self.extra()} if self.extra else {})}

    def start(self) -> None:
        import json
        import threading
        import time
        self.pauses.install()
        self._stop = threading.Event()
        t0 = time.monotonic()

        def loop():
            with open(self.path, "a") as f:
                while True:
                    f.write(json.dumps(self.line(time.monotonic() - t0)) + "\n")
                    f.flush()
                    if self._stop.wait(self.every_s):
                        break
        self._thread = threading.Thread(target=loop, name="capsheet-memory-probe", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        if self._stop is not None:
            self._stop.set()
            self._thread.join(5.0)
        self.pauses.remove()


def probe_from_env(extra=None) -> MemoryProbe | None:
    """A started `MemoryProbe` if ``CAPSHEET_MEMORY_PROBE=PATH[,EVERY_S]`` is set, else None."""
    spec = os.environ.get(PROBE_ENV_VAR)
    if not spec:
        return None
    path, _, every = spec.partition(",")
    try:
        probe = MemoryProbe(path, float(every) if every else 120.0, extra=extra)
    except ValueError:
        print(f"{PROBE_ENV_VAR}={spec!r}: expected PATH[,EVERY_S]; no probe", file=sys.stderr)
        return None
    probe.start()
    return probe
