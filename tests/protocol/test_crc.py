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
