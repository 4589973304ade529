"""`host.memory.fix_mmap_threshold`: after it, a large block freed and allocated again is
still served by its own mmap (glibc's ``mallinfo2().hblkhd`` counts it) instead of from the heap,
where its pages would stay resident after the next free. Each case in a fresh process: glibc's
threshold is process-wide and only moves up."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")

PROBE = textwrap.dedent("""
    import ctypes, sys
    libc = ctypes.CDLL("libc.so.6")
    class MallInfo2(ctypes.Structure):
        _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd",
                    "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")]
    libc.mallinfo2.restype = MallInfo2
    libc.malloc.restype = ctypes.c_void_p
    libc.malloc.argtypes = [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]
    SETUP
    size = 4 << 20
    libc.free(libc.malloc(size))         # glibc raises its threshold to 4 MiB here, unless fixed
    before = libc.mallinfo2().hblkhd
    p = libc.malloc(size)
    print(libc.mallinfo2().hblkhd - before)   # bytes mmapped for the second block
    libc.free(p)
""")


def _mmapped_bytes(setup: str, env=None) -> int:
    r = subprocess.run([sys.executable, "-c", PROBE.replace("SETUP", setup)], capture_output=True,
                       text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr
    return int(r.stdout.split()[-1])


def _glibc() -> bool:
    try:
        import ctypes
        ctypes.CDLL("libc.so.6").mallinfo2
    except (OSError, AttributeError):
        return False
    return True


@pytest.mark.skipif(not _glibc(), reason="needs glibc >= 2.33 (mallinfo2)")
def test_a_large_block_stays_mmapped_after_one_was_freed():
    assert _mmapped_bytes("pass") == 0  # glibc's dynamic threshold: the heap serves it
    assert _mmapped_bytes("from host.memory import fix_mmap_threshold; assert fix_mmap_threshold()") >= 4 << 20


@pytest.mark.skipif(not _glibc(), reason="needs glibc >= 2.33 (mallinfo2)")
def test_every_capsheet_command_fixes_it_and_a_users_choice_stands():
    import os
    via_cli = "from host.cli import main\ntry:\n    main(['--version'])\nexcept SystemExit:\n    pass"
    assert _mmapped_bytes(via_cli) >= 4 << 20
    env = dict(os.environ, MALLOC_MMAP_THRESHOLD_=str(64 << 20))  # the user's: above the block
    assert _mmapped_bytes(via_cli, env=env) == 0


# -- the probe's parts (host.memory.GcPauses, container_lengths) -------------------------------------

def test_gc_pauses_on_a_simulated_clock_are_counted_per_generation_with_their_longest():
    from host.memory import GcPauses
    now = [0.0]
    p = GcPauses(lambda: now[0])
    for gen, dt in ((0, 0.0001), (0, 0.0003), (2, 0.030), (1, 0.006), (2, 0.060)):
        p.on_gc("start", {"generation": gen})
        now[0] += dt
        p.on_gc("stop", {"generation": gen, "collected": 3})
        now[0] += 1.0
    p.on_gc("stop", {"generation": 2})  # a stop without its start (installed mid-collection): ignored
    d = p.as_dict()
    assert [d[f"gen{g}"]["count"] for g in range(3)] == [2, 1, 2]
    assert d["gen2"]["max_ms"] == 60.0 and d["gen2"]["total_ms"] == 90.0
    assert d["gen0"]["max_ms"] == 0.3 and d["gen0"]["collected"] == 6
    assert (d["gen2"]["at_least_5ms"], d["gen2"]["at_least_20ms"], d["gen2"]["at_least_50ms"]) == (2, 2, 1)
    assert (d["gen1"]["at_least_5ms"], d["gen1"]["at_least_20ms"]) == (1, 0)


def test_container_lengths_names_a_growing_field_even_when_the_collector_does_not_track_it():
    import gc

    from host.memory import container_lengths

    class Holder:
        def __init__(self):
            self.table = {}  # ints to floats: the collector does not track this dict itself

    h = Holder()
    for i in range(40):
        h.table[i] = float(i)
    assert not gc.is_tracked(h.table)
    before = container_lengths()
    for i in range(40, 100):
        h.table[i] = float(i)
    after = container_lengths()
    assert before[id(h.table)][0] == 40 and before[id(h.table)][1].endswith("Holder.table:dict")
    assert after[id(h.table)][0] == 100


def test_container_lengths_walks_past_a_dead_weak_proxy():
    """A weakref.proxy whose object is gone raises ReferenceError on any attribute access,
    ``isinstance`` included (CI met one a test had left in the heap); the walk goes past it."""
    import weakref

    from host.memory import container_lengths

    class Target:
        pass

    class Holder:
        def __init__(self):
            self.table = {}

    t = Target()
    h = Holder()
    h.table = {i: weakref.proxy(t) for i in range(20)}
    h.other = list(range(30))
    del t  # every proxy in the table is dead now
    found = container_lengths()
    assert found[id(h.table)][0] == 20
    assert found[id(h.other)][0] == 30


TRIM_PROBE = textwrap.dedent("""
    import ctypes, os
    from host.memory import trim
    libc = ctypes.CDLL("libc.so.6")
    libc.malloc.restype = ctypes.c_void_p
    libc.malloc.argtypes = [ctypes.c_size_t]
    libc.free.argtypes = [ctypes.c_void_p]
    def rss():
        return int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    blocks = [libc.malloc(512) for _ in range(200_000)]   # ~100 MB of small blocks in the heap
    for i, p in enumerate(blocks):
        if i % 64:
            libc.free(p)                                   # one in 64 stays: every page's neighbours free
    before = rss()
    released = TRIM
    print(before - rss(), released)
""")


@pytest.mark.skipif(not _glibc(), reason="glibc's malloc_trim")
def test_trim_gives_back_the_free_pages_between_blocks_in_use():
    """After freeing 63 of every 64 small blocks the heap's free pages stay resident (glibc returns
    only its top by itself); `host.memory.trim` gives them back. Measured in a fresh process."""
    def run(expr: str) -> tuple[int, str]:
        r = subprocess.run([sys.executable, "-c", TRIM_PROBE.replace("TRIM", expr)], capture_output=True,
                           text=True, timeout=120)
        assert r.returncode == 0, r.stderr
        freed, released = r.stdout.split()
        return int(freed), released
    kept, _ = run("None")
    freed, released = run("trim()")
    assert kept < 4 << 20 and freed > 60 << 20 and released == "True", (kept, freed, released)


def test_periodic_trim_on_a_simulated_clock_trims_once_per_period():
    from host.memory import PeriodicTrim
    calls = []
    pt = PeriodicTrim(every_s=60.0, trim_fn=lambda: calls.append(1) or len(calls) % 2 == 1)
    assert not pt.poll(1000.0)  # the first call starts the clock
    done = [t for t in (1000.0 + 0.5 * k for k in range(1, 2 * 600 + 1)) if pt.poll(t)]  # 10 minutes
    assert done == [1000.0 + 60.0 * k for k in range(1, 11)]
    assert pt.trims == len(calls) == 10 and pt.released == 5
    with pytest.raises(ValueError, match="every_s"):
        PeriodicTrim(every_s=0)


def test_the_trim_thread_trims_once_per_period_on_a_simulated_clock_until_stopped():
    # the loop of the one trim every command starts (host.cli.main), driven by a fake wait: each
    # wait advances the clock by what it was asked and says "stop" after 10 minutes
    from host.memory import PeriodicTrim, TrimThread
    now, calls, waits = [0.0], [], []

    def wait(seconds):
        waits.append(seconds)
        now[0] += seconds
        return now[0] > 600.0

    TrimThread(PeriodicTrim(every_s=60.0, trim_fn=lambda: calls.append(now[0]) or True),
               clock=lambda: now[0]).run(wait)
    assert calls == [60.0 * k for k in range(1, 11)]
    assert waits == [60.0] * 11


def test_every_command_starts_one_trim_thread_and_no_loop_polls_its_own():
    import ast
    from pathlib import Path
    cli = Path(__file__).resolve().parents[2] / "host" / "cli"
    started = [p.name for p in cli.glob("*.py") if "process_trim" in p.read_text() or "TrimThread" in p.read_text()]
    assert started == ["__init__.py"]
    assert not [p.name for p in cli.glob("*.py") if "PeriodicTrim" in p.read_text()]
    tree = ast.parse((cli / "__init__.py").read_text())
    main = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "main")
    assert "process_trim()" in ast.unparse(main)


def test_commands_run_in_one_interpreter_share_one_trim_thread():
    import threading

    from host.cli import main
    from host.memory import process_trim
    for _ in range(5):  # each starts where a command starts, before its arguments are read
        try:
            main(["protocol", "--help"])
        except SystemExit as done:  # argparse's --help
            assert done.code == 0
    trims = [t for t in threading.enumerate() if t.name == "capsheet-trim"]
    assert len(trims) == 1 and process_trim().alive
    assert process_trim() is process_trim()
