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


def test_capacity_for_a_lattice_says_how_many_buses_of_each_kind():
    out = run("capacity", "--lattice", "14x14", "--rate", "145")
    assert out.returncode == 0, out.stderr
    assert "A 14x14 sheet (364 chips) at 145 Hz" in out.stdout
    # 45 chips per classic bus at 145 Hz (the spec's table): ceil(364 / 45) = 9 buses
    assert "| classic CAN 1 Mbit/s, 29-bit id | SAMPLE (7 B) | 45 | 9 |" in out.stdout
    # 137 chips per 3 Mbaud UART, per chip: 3 UARTs; one 12 Mbaud UART (551 chips) suffices
    assert "| UART 8N1 3 Mbaud | SAMPLE per chip | 137 | 3 |" in out.stdout
    assert "| UART 8N1 12 Mbaud | SAMPLE per chip | 551 | 1 |" in out.stdout


def test_bad_values_are_one_line_errors_with_exit_2():
    for args, needle in ((("decode", "zz"), "invalid hex 'zz'"),
                         (("decode", "00", "--can-id", "xyz"), "invalid --can-id 'xyz'"),
                         (("capacity", "--rate", "0"), "--rate: invalid value '0': need a number > 0"),
                         (("capacity", "--rate", "nan"), "--rate: invalid value 'nan'"),
                         (("capacity", "--rate", "-5"), "--rate: invalid value '-5'"),
                         (("capacity", "--lattice", "14by14"), "--lattice: invalid value '14by14': need ROWSxCOLS")):
        out = run(*args)
        assert out.returncode == 2, (args, out.stderr)
        assert needle in out.stderr and "Traceback" not in out.stderr, (args, out.stderr)


def test_a_closed_pipe_is_not_a_traceback():
    """`capsheet protocol vectors | head -1`: the reader goes away after one line."""
    p = subprocess.Popen([sys.executable, "-m", "host.cli", "protocol", "vectors"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    p.stdout.readline()
    p.stdout.close()  # as head does
    err = p.stderr.read().decode()
    assert p.wait(timeout=60) in (0, 141)
    assert "Traceback" not in err and "BrokenPipe" not in err, err


def test_capacity_lists_the_imu_formats_with_the_buses_a_14x14_sheet_needs(capsys):
    """v1.2 (docs §16.6): per-chip and packed rows for 6- and 9-axis chips. Expected values by hand:
    classic CAN, worst case 160 bits per 8-byte frame (§10): 6-axis 2 frames -> 1e6 / 320 / 145 = 21.5
    chips, 9-axis 3 frames -> 14.4; UART 8N1: IMU_SAMPLE is 23 (29) bytes on the wire (§16.3), so
    3e5 / 23 / 145 = 89.9 and 1.2e6 / 29 / 145 = 285.4 chips."""
    from host.cli import main
    assert main(["protocol", "capacity", "--lattice", "14x14", "--rate", "145"]) == 0
    rows = {tuple(c.strip() for c in line.split("|")[1:3]): line.split("|")[3:5]
            for line in capsys.readouterr().out.splitlines() if line.startswith("| ")}

    def row(link, carries):
        per, need = rows[(link, carries)]
        return int(per.replace(",", "")), int(need)
    assert row("classic CAN 1 Mbit/s, 29-bit id", "6-axis: IMU_GYRO + IMU_ACCEL (2 × 8 B)") == (21, 18)
    assert row("classic CAN 1 Mbit/s, 29-bit id", "9-axis: IMU_GYRO + IMU_MAG + IMU_ACCEL (3 × 8 B)") == (14, 26)
    assert row("UART 8N1 3 Mbaud", "6-axis: IMU_SAMPLE per chip") == (89, 5)
    assert row("UART 8N1 12 Mbaud", "9-axis: IMU_SAMPLE per chip") == (285, 2)
    assert row("UART 8N1 12 Mbaud", "6-axis: SNAPSHOT_IMU (packed)")[1] == 1
    assert row("classic CAN 1 Mbit/s, 29-bit id", "SAMPLE (7 B)") == (45, 9)  # today's rows unchanged
