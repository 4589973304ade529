"""`protocol.crc`: CRC-16/CCITT-FALSE, the catalogue's check value and residue, and the vectorised
form against the byte-wise one."""

from protocol.crc import CRC_CHECK, crc16_ccitt_false, crc16_rows


def test_crc_check_value_from_the_catalogue():
    assert crc16_ccitt_false(b"123456789") == CRC_CHECK == 0x29B1
    # residue: the CRC over data + its own CRC (MSB first) is zero
    assert crc16_ccitt_false(b"123456789\x29\xb1") == 0


def test_vectorised_crc_agrees_with_binascii_row_by_row():
    import numpy as np
    rng = np.random.Generator(np.random.MT19937(7))
    rows = rng.integers(0, 256, size=(200, 13), dtype=np.uint8)
    assert crc16_rows(rows).tolist() == [crc16_ccitt_false(r.tobytes()) for r in rows]


def test_the_table_is_the_polynomial_byte_by_byte():
    # CRC_TABLE[b]: the register (init 0) after byte b; for b = 1 that is the polynomial itself
    from protocol.crc import CRC_POLY, CRC_TABLE
    assert CRC_TABLE[0] == 0 and CRC_TABLE[1] == CRC_POLY == 0x1021 and CRC_TABLE[2] == 0x2042
    assert CRC_TABLE.dtype.name == "uint16" and len(CRC_TABLE) == 256
    assert not CRC_TABLE.flags.writeable


def test_rows_of_any_integer_type_and_no_columns():
    import numpy as np
    rows = np.frombuffer(b"123456789" * 3, np.uint8).reshape(3, 9)
    assert crc16_rows(rows.astype(np.int64)).tolist() == [CRC_CHECK] * 3  # bytes held in int64
    assert crc16_rows(np.zeros((2, 0), np.uint8)).tolist() == [0xFFFF] * 2  # the init, nothing fed


def test_vectorised_crc_by_position_tables_and_by_bytes_agree_with_binascii_at_every_length():
    """Rows up to 64 bytes go by per-position tables (one gather), longer ones byte by byte:
    both agree with binascii at every length around the boundary, on random bytes and on the
    all-0x00 and all-0xFF rows (the tables' extremes)."""
    import numpy as np
    rng = np.random.Generator(np.random.MT19937(11))
    for m in list(range(1, 70)) + [200]:
        rows = np.concatenate([rng.integers(0, 256, size=(20, m), dtype=np.uint8),
                               np.zeros((1, m), np.uint8), np.full((1, m), 0xFF, np.uint8)])
        assert crc16_rows(rows).tolist() == [crc16_ccitt_false(r.tobytes()) for r in rows], m
