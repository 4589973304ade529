"""The C firmware builds warning-free under the strict flags (64- and 32-bit), and its decoders
survive arbitrary input under AddressSanitizer + UndefinedBehaviorSanitizer.

These run `make -C firmware_ref ...` in a subprocess (each into its own build directory), so they
need a C compiler and make; they are skipped, saying so, when there is none.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

FW = Path(__file__).resolve().parents[2] / "firmware_ref"

pytestmark = pytest.mark.skipif(shutil.which("make") is None or shutil.which("cc") is None,
                                reason="needs make and a C compiler (cc)")


def _make(target: str, out: Path, *extra: str, timeout: float = 120) -> str:
    proc = subprocess.run(["make", "-C", str(FW), target, f"OUT={out}", *extra], capture_output=True, text=True,
                          timeout=timeout)
    assert proc.returncode == 0, f"make {target} failed:\n{proc.stdout}\n{proc.stderr}"
    return proc.stdout + proc.stderr


def _asan_works(tmp: Path) -> bool:
    src = tmp / "probe.c"
    src.write_text("int main(void){return 0;}\n")
    r = subprocess.run(["cc", "-fsanitize=address,undefined", str(src), "-o", str(tmp / "probe")],
                       capture_output=True, timeout=60)
    return r.returncode == 0 and subprocess.run([str(tmp / "probe")], timeout=30).returncode == 0


def test_strict_c99_build_64_and_32_bit(tmp_path):
    out = _make("check", tmp_path)
    assert "selftest: ok (64-bit)" in out
    # a chip image without the node -> host decoders (-DCAPSHEET_CHIP_ONLY=1) sends the very same frames
    # as the default build for tens of thousands of script steps (tests/chip_trace.c; cmp in the Makefile)
    m = re.search(r"chip_only: (\d+) frames sent, (\d+) frames received, identical", out)
    assert m and int(m.group(1)) > 10000 and int(m.group(2)) > 10000, out
    # 32-bit needs gcc-multilib; the target says SKIPPED when the toolchain cannot link -m32
    assert "selftest: ok (32-bit)" in out or "check32: SKIPPED" in out


def test_decoders_and_chip_survive_arbitrary_input_under_asan_and_ubsan(tmp_path):
    if not _asan_works(tmp_path):
        pytest.skip("the C compiler cannot build with -fsanitize=address,undefined")
    out = _make("asan", tmp_path, timeout=240)
    assert "random: 200000 inputs ok" in out
    corpus = list((FW / "tests" / "corpus").iterdir())
    assert corpus and f"replay: {len(corpus)} files ok" in out


def _strict_flags() -> list[str]:
    line = next(ln for ln in (FW / "Makefile").read_text().splitlines() if ln.startswith("STRICT"))
    return line.split(":=", 1)[1].split()


@pytest.mark.parametrize("use", ["ignored", "tested"])
def test_a_caller_that_ignores_a_fallible_result_fails_the_strict_build(tmp_path, use):
    # CAPSHEET_WARN_UNUSED (include/capsheet_fw.h) under the Makefile's strict flags (-Werror); a
    # cast to (void) does not silence GCC, only testing the result does
    call = {"ignored": "    (void)capsheet_can_fd_length(n);\n    return 0;",
            "tested": "    return capsheet_can_fd_length(n) < 0;"}[use]
    src = tmp_path / "caller.c"
    src.write_text(f'#include "capsheet_fw.h"\nint caller(size_t n);\nint caller(size_t n)\n{{\n{call}\n}}\n')
    proc = subprocess.run(["cc", *_strict_flags(), f"-I{FW / 'include'}", "-c", str(src), "-o", str(tmp_path / "caller.o")],
                          capture_output=True, text=True, timeout=60)
    if use == "tested":
        assert proc.returncode == 0, proc.stderr
    else:
        assert proc.returncode != 0 and "warn_unused_result" in proc.stderr, proc.stderr
