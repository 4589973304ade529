"""The NUCLEO-G0B1RE port (firmware_ref/ports/nucleo-g0b1re/): its images build warning-free with the
Arm toolchain and fit the part, their vector tables boot from flash with the transport's interrupt
wired, and its calibration store (calstore.c, portable C) keeps every value through any power cut,
run on the host over a simulated flash. The image tests are SKIPPED, with the reason, where
arm-none-eabi-gcc is not installed; the store's need only a C compiler."""

from __future__ import annotations

import re
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
FW = ROOT / "firmware_ref"
PORT = FW / "ports" / "nucleo-g0b1re"

# STM32G0B1RET6, datasheet DS13560 ("Description", "Memory mapping"): 512 KiB flash at 0x08000000,
# 144 KiB SRAM at 0x20000000. The port keeps the last two 2 KiB flash pages for calibration.
FLASH_BASE = 0x0800_0000
FLASH_BYTES = 512 * 1024
CAL_PAGES_BYTES = 2 * 2048
SRAM_BASE = 0x2000_0000
SRAM_BYTES = 144 * 1024
IMAGES = ("vcp_6axis", "rs485_9axis", "can_6axis", "canfd_9axis")
# RM0444 NVIC vector table: IRQ 21 TIM16/FDCAN1 line 0, IRQ 28 USART2, IRQ 27 USART1; exception 2 NMI
VEC_NMI, VEC_FDCAN1, VEC_USART1, VEC_USART2 = 2, 16 + 21, 16 + 27, 16 + 28

NO_ARM = shutil.which("arm-none-eabi-gcc") is None
needs_arm = pytest.mark.skipif(NO_ARM, reason="board port: arm-none-eabi-gcc not installed "
                                              "(apt-get install gcc-arm-none-eabi libnewlib-arm-none-eabi)")


@pytest.fixture(scope="module")
def board_build(board_images):
    """The session's one ``make board`` (tests/firmware_ref/conftest.py): its OUT and its output."""
    out, rc, log = board_images
    assert rc == 0, log[-6000:]
    return out, log


@needs_arm
def test_every_image_builds_warning_free_and_fits_the_part(board_build):
    out, log = board_build
    assert "warning" not in log.lower()  # -Werror would have stopped it; no warning reaches the log either
    table = (out / "board-size.md").read_text()
    rows = {m[0]: (int(m[1]), int(m[2]), int(m[3]))
            for m in re.findall(r"^\| `capsheet_g0b1_(\w+)` \| [^|]+ \| (\d+) \| (\d+) \| (\d+) \|$", table, re.M)}
    assert sorted(rows) == sorted(IMAGES)
    for name, (flash, ram, stack) in rows.items():
        elf = out / "board" / f"capsheet_g0b1_{name}.elf"
        assert elf.exists() and (out / "board" / f"capsheet_g0b1_{name}.bin").exists()
        assert 4096 < flash <= FLASH_BYTES - CAL_PAGES_BYTES, (name, flash)
        assert 0 < ram and ram + stack <= SRAM_BYTES, (name, ram, stack)


def _symbols(elf: Path) -> dict[str, int]:
    nm = subprocess.run(["arm-none-eabi-nm", str(elf)], capture_output=True, text=True, check=True).stdout
    return {parts[2]: int(parts[0], 16) for parts in (line.split() for line in nm.splitlines()) if len(parts) == 3}


@needs_arm
@pytest.mark.parametrize("name", IMAGES)
def test_vector_table_boots_from_flash_with_the_transport_interrupt_wired(board_build, name):
    out, _ = board_build
    image = (out / "board" / f"capsheet_g0b1_{name}.bin").read_bytes()
    vectors = struct.unpack("<48I", image[:48 * 4])
    sym = _symbols(out / "board" / f"capsheet_g0b1_{name}.elf")
    sp, reset = vectors[0], vectors[1]
    assert SRAM_BASE < sp <= SRAM_BASE + SRAM_BYTES and sp % 8 == 0
    assert reset & 1 == 1, "a Cortex-M vector is a Thumb address (bit 0 set)"
    assert FLASH_BASE <= reset - 1 < FLASH_BASE + len(image)
    assert reset - 1 == sym["reset_handler"]
    spin = vectors[VEC_NMI]
    assert spin - 1 == sym["default_handler"]
    wired = {"vcp": {VEC_USART2}, "rs485": {VEC_USART1}, "can": {VEC_FDCAN1}, "canfd": {VEC_FDCAN1}}[name.split("_")[0]]
    for v in (VEC_FDCAN1, VEC_USART1, VEC_USART2):
        assert (vectors[v] != spin) == (v in wired), (name, v)
    handler = "fdcan1_irq" if VEC_FDCAN1 in wired else "usart_irq"
    assert vectors[next(iter(wired))] - 1 == sym[handler]
    # the image and its initialised data end below the calibration pages (the linker script asserts it too)
    assert sym["__image_end"] <= FLASH_BASE + FLASH_BYTES - CAL_PAGES_BYTES


# ---- the calibration store on a simulated flash ------------------------------------------------------

HARNESS = r"""
#include <setjmp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include "calstore.h"

#define PAGE 2048u
static uint8_t mem[2][PAGE];
static long budget;          /* programs left before the power goes (-1: never) */
static long programs;
static int fail_erase;
static jmp_buf power_cut;

static int32_t erase(void *ctx, uint8_t page) {
    (void)ctx;
    if (fail_erase) return -1;
    memset(mem[page], 0xFF, PAGE);
    return 0;
}
/* like a STM32G0: one aligned double word, only onto an erased one */
static int32_t program(void *ctx, uint8_t page, uint32_t off, uint32_t lo, uint32_t hi) {
    unsigned i;
    (void)ctx;
    if (off % 8u || off >= PAGE) return -1;
    for (i = 0; i < 8u; i++) if (mem[page][off + i] != 0xFF) return -2;
    programs++;
    if (budget == 0) {              /* the power goes half-way: only the first word made it */
        memcpy(&mem[page][off], &lo, 4);
        longjmp(power_cut, 1);
    }
    if (budget > 0) budget--;
    memcpy(&mem[page][off], &lo, 4);
    memcpy(&mem[page][off + 4], &hi, 4);
    return 0;
}
static const calstore_flash_t flash = {NULL, {mem[0], mem[1]}, PAGE, erase, program};

/* the store sequence: lines "key aux bits" on stdin after the command line */
static int n_ops; static unsigned op_key[4096], op_aux[4096], op_bits[4096];

static int32_t do_store(calstore_t *cs, int i) {
    if (op_key[i] < 3u) {
        capsheet_cal_t c;
        uint32_t bits = op_bits[i];
        c.axis = (uint8_t)op_key[i]; c.flags = 1u; c.offset_q4 = (int16_t)(uint16_t)op_aux[i];
        memcpy(&c.sensitivity, &bits, 4);
        return calstore_cal_store(cs, (uint8_t)op_key[i], &c);
    }
    return calstore_imu_store(cs, (uint8_t)(op_key[i] - 3u), op_bits[i]);
}

static void dump(calstore_t *cs) {
    unsigned k;
    for (k = 0; k < 3u + CAPSHEET_IMU_CAL_COUNT; k++) {
        if (k < 3u) {
            capsheet_cal_t c; uint32_t bits;
            if (calstore_cal_load(cs, (uint8_t)k, &c) != 0) { printf(" -"); continue; }
            memcpy(&bits, &c.sensitivity, 4);
            printf(" %u:%u", (unsigned)(uint16_t)c.offset_q4, (unsigned)bits);
        } else {
            uint32_t bits;
            if (calstore_imu_load(cs, (uint8_t)(k - 3u), &bits) != 0) { printf(" -"); continue; }
            printf(" 0:%u", (unsigned)bits);
        }
    }
    printf("\n");
}

int main(int argc, char **argv) {
    calstore_t cs;
    long cut, cuts;
    int i;
    while (n_ops < 4096 && scanf("%u %u %u", &op_key[n_ops], &op_aux[n_ops], &op_bits[n_ops]) == 3) n_ops++;
    if (argc > 1 && strcmp(argv[1], "erase-fails") == 0) {
        /* fill the live page, then every erase fails: stores report it, loads keep the old values */
        memset(mem, 0xFF, sizeof mem);
        budget = -1;
        calstore_init(&cs, &flash);
        for (i = 0; i < n_ops; i++) {
            int32_t rc;
            if (i == n_ops - 1) fail_erase = 1;
            rc = do_store(&cs, i);
            printf("store %d %d\n", i, (int)rc);
        }
        calstore_init(&cs, &flash);
        dump(&cs);
        return 0;
    }
    /* every power cut: store ops until the cut, then boot again and load every key */
    cuts = argc > 1 ? atol(argv[1]) : 0;
    for (cut = 0; cut <= cuts; cut++) {
        volatile int done = 0;
        memset(mem, 0xFF, sizeof mem);
        budget = cut < cuts ? cut : -1;
        programs = 0;
        calstore_init(&cs, &flash);
        if (setjmp(power_cut) == 0) {
            for (i = 0; i < n_ops; i++) {
                if (do_store(&cs, i) != 0) { printf("error %d\n", i); return 1; }
                done = i + 1;
            }
        }
        calstore_init(&cs, &flash);
        printf("%ld %d %ld", cut, (int)done, programs);
        dump(&cs);
    }
    return 0;
}
"""

KEYS = 3 + 33  # three accelerometer axes, 33 gyro/mag elements (docs/protocol.md §17.1)
PAGE_RECORDS = 2048 // 8 - 1  # a page's double words less its header


def _harness(tmp_path: Path) -> Path:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("calibration store: no host C compiler")
    src = tmp_path / "calstore_harness.c"
    src.write_text(HARNESS)
    exe = tmp_path / "calstore_harness"
    strict = "-std=c99 -Wall -Wextra -Werror -pedantic -Wconversion -Wsign-conversion".split()
    subprocess.run([cc, *strict, "-O1", f"-I{FW / 'include'}", f"-I{PORT}", str(src), str(PORT / "calstore.c"),
                    "-o", str(exe)], check=True, capture_output=True, text=True)
    return exe


def _ops(seed: int, n: int, keys: list[int]) -> list[tuple[int, int, int]]:
    rng = np.random.Generator(np.random.MT19937(seed))
    return [(int(k), int(rng.integers(0, 65536)) if k < 3 else 0, int(rng.integers(0, 2**32)))
            for k in rng.choice(keys, size=n)]


def _model(ops, upto: int) -> list[str]:
    """Each key's value after the first `upto` stores, as the harness prints it ('-': never stored)."""
    state = ["-"] * KEYS
    for key, aux, bits in ops[:upto]:
        state[key] = f"{aux}:{bits}"
    return state


def _run(exe: Path, ops, *args: str) -> list[str]:
    stdin = "".join(f"{k} {a} {b}\n" for k, a, b in ops)
    r = subprocess.run([str(exe), *args], input=stdin, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-2000:]
    return r.stdout.splitlines()


def test_calibration_store_loads_every_value_it_stored_across_page_compactions(tmp_path):
    exe = _harness(tmp_path)
    ops = _ops(seed=1, n=3 * PAGE_RECORDS + 40, keys=list(range(KEYS)))  # three compactions and more
    (line,) = _run(exe, ops, "0")
    cut, done, programs, *values = line.split()
    assert int(done) == len(ops)
    assert values == _model(ops, len(ops))
    # a compaction rewrites at most every key once: the programs stay within stores + KEYS per page filled
    assert len(ops) < int(programs) <= len(ops) + (KEYS + 1) * 4


def test_a_power_cut_at_any_programming_leaves_each_key_old_or_new_never_garbage(tmp_path):
    exe = _harness(tmp_path)
    # few keys, many stores: the page fills and compacts twice; cut at every double word programmed
    ops = _ops(seed=2, n=2 * PAGE_RECORDS + 20, keys=[0, 1, 2, 3, 20, 35])
    total = int(_run(exe, ops, "0")[0].split()[2])
    lines = _run(exe, ops, str(total))
    assert len(lines) == total + 1
    for line in lines[:-1]:
        cut, done, _, *values = line.split()
        done = int(done)
        before, after = _model(ops, done), _model(ops, done + 1)
        for k in range(KEYS):
            assert values[k] in (before[k], after[k]), (cut, done, k, values[k], before[k], after[k])
    # no cut: everything
    assert lines[-1].split()[3:] == _model(ops, len(ops))


def test_a_failed_erase_is_reported_and_the_stored_values_survive(tmp_path):
    exe = _harness(tmp_path)
    ops = _ops(seed=3, n=PAGE_RECORDS + 1, keys=[0, 4, 9])  # the last store needs a fresh page
    lines = _run(exe, ops, "erase-fails")
    assert [line.split()[2] for line in lines[:-1]] == ["0"] * PAGE_RECORDS + ["-3"]  # CALSTORE_ERR_FLASH
    assert lines[-1].split() == _model(ops, PAGE_RECORDS)
