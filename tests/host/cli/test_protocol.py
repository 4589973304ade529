"""`capsheet protocol`: what a chip vendor types to check bytes by hand."""

import subprocess
import sys


def run(*args, input=None):
    return subprocess.run([sys.executable, "-m", "host.cli", "protocol", *args], capture_output=True, text=True,
                          input=input, timeout=60)


def test_encode_prints_the_golden_serial_and_can_bytes():
    out = run("encode", "SAMPLE", "node=1", "counter=0", "x=0", "y=0", "z=1024")
    assert out.returncode == 0, out.stderr
    assert "04 01 03 01 01 01 01 01 01 01 04 04 16 2e 00" in out.stdout
    assert "08310001#00000000000004" in out.stdout


def test_decode_reports_damage_and_exits_non_zero():
    good = "04 01 03 01 01 01 01 01 01 01 04 04 16 2e 00"
    out = run("decode", good)
    assert out.returncode == 0 and "Sample(node=1, counter=0, x=0, y=0, z=1024" in out.stdout
    bad = run("decode", good.replace("16 2e", "16 2f"))
    assert bad.returncode == 1 and "BAD_CRC" in bad.stderr


def test_encode_refuses_an_out_of_range_field_with_its_name():
    out = run("encode", "SYNC", "counter=70000")
    assert out.returncode == 2 and "Invalid counter: 70000" in out.stderr


def test_capacity_table_matches_the_spec():
    out = run("capacity")
    assert out.returncode == 0
    assert "| classic CAN 1 Mbit/s, 29-bit id | SAMPLE (7 B) | 123-150 bits | 6,667–8,130 | 45–56 |" in out.stdout
    spec = open("docs/protocol.md", encoding="utf-8").read()
    assert "| UART 8N1 3 Mbaud | SAMPLE per chip | 15 B | 20,000 | 137 |" in spec
    assert "| UART 8N1 3 Mbaud | SAMPLE per chip | 15 B | 20,000 | 137 |" in out.stdout
