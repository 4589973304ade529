"""The NUCLEO-G0B1RE images (``make -C firmware_ref board``), built once per test session and shared
by the files that look at them (test_board_port.py: the build's warnings, sizes and vector tables;
test_board_emulated.py: the images run in an emulated Cortex-M0+). They built the same images twice
before, one build per module.

Under pytest-xdist the workers share the build: whichever needs it first makes it under a file lock
in the session's temporary directory (shared by the workers), the other finds it there, with the
build's own output (test_board_port.py checks that it is warning-free)."""

from __future__ import annotations

import fcntl
import json
import os
import subprocess
from pathlib import Path

import pytest

FW = Path(__file__).resolve().parents[2] / "firmware_ref"


@pytest.fixture(scope="session")
def board_images(tmp_path_factory) -> tuple[Path, int, str]:
    """``(OUT, make's exit status, make's stdout + stderr)`` of one ``make board OUT=...`` this session;
    the images are under ``OUT / "board"``."""
    base = tmp_path_factory.getbasetemp()
    root = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    out = root / "board-images"
    with open(root / "board-images.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        done = root / "board-images.json"
        if not done.exists():
            out.mkdir(exist_ok=True)
            r = subprocess.run(["make", "-C", str(FW), "board", f"OUT={out}"], capture_output=True, text=True,
                               timeout=600)
            done.write_text(json.dumps({"rc": r.returncode, "log": r.stdout + r.stderr}))
    doc = json.loads(done.read_text())
    return out, doc["rc"], doc["log"]
