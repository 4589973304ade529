"""Physical and ADC constants shared by the protocol, the chips and the host (docs/protocol.md §5).

A chip's accelerometer is read as three 12-bit two's-complement ADC counts. The full-scale range is
set by CONFIG's ``range`` code; the nominal sensitivity follows from it. Per-chip calibration
(offset, sensitivity) refines the nominal values (CAL_WRITE / CAL_DATA).
"""

from __future__ import annotations

from enum import IntEnum, IntFlag

__all__ = ["G0", "ADC_BITS", "ADC_MIN", "ADC_MAX", "Range", "SampleStatus", "nominal_sensitivity",
           "counts_to_si", "si_to_counts"]

#: Standard gravity, m/s² (CGPM 1901). Readings are specific force: flat and top face up reads +G0 on z.
G0 = 9.80665

ADC_BITS = 12  #: width of one axis sample on the wire
ADC_MIN = -(1 << (ADC_BITS - 1))  #: -2048
ADC_MAX = (1 << (ADC_BITS - 1)) - 1  #: +2047


class Range(IntEnum):
    """Full-scale range code of CONFIG (docs/protocol.md §4.11)."""

    G2 = 0  #: ±2 g, 1024 counts/g (default: tilt sensing)
    G4 = 1  #: ±4 g, 512 counts/g
    G8 = 2  #: ±8 g, 256 counts/g
    G16 = 3  #: ±16 g, 128 counts/g

    @property
    def full_scale_g(self) -> int:
        return 2 << int(self)


class SampleStatus(IntFlag):
    """The 4 status bits carried with every sample (docs/protocol.md §5.2)."""

    OK = 0
    SATURATED = 0x1  #: at least one axis hit the ADC limit (-2048 or +2047)
    SELF_TEST = 0x2  #: self-test excitation was on: the reading is not gravity
    STALE = 0x4  #: no fresh conversion since the last SYNC; the previous value is repeated
    INVALID = 0x8  #: no data (ADC fault, or a gateway that heard nothing from this chip)


def nominal_sensitivity(range_code: int = Range.G2) -> float:
    """Nominal sensitivity in counts per g for a range code: ``2048 / full_scale_g``.

    >>> nominal_sensitivity(Range.G2)
    1024.0
    """
    return float(1 << (ADC_BITS - 1)) / Range(range_code).full_scale_g


def counts_to_si(counts, offset=0.0, sensitivity=nominal_sensitivity()):
    """ADC counts -> specific force in m/s²: ``(counts - offset) / sensitivity * G0``.

    Works on scalars and numpy arrays alike (``offset``/``sensitivity`` broadcast per axis).
    """
    return (counts - offset) / sensitivity * G0


def si_to_counts(accel, offset=0.0, sensitivity=nominal_sensitivity()):
    """Specific force in m/s² -> ideal (unrounded, unclipped) ADC counts; inverse of `counts_to_si`."""
    return accel / G0 * sensitivity + offset
