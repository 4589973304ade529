"""Shared pytest configuration. Hypothesis: a CI profile that is deterministic and bounded."""

import os

import pytest

from hypothesis import HealthCheck, settings

settings.register_profile("ci", max_examples=150, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("dev", max_examples=300, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


def _chip_class_params():
    from virtual_sheet.chip import ChipModel

    params = [pytest.param(ChipModel, id="python")]
    try:
        from firmware_ref.chip import CFirmwareChip
    except ImportError as exc:  # the cffi extension was not built (no compiler at install time)
        params.append(pytest.param(None, id="c", marks=pytest.mark.skip(reason=f"C firmware not built: {exc}")))
    else:
        params.append(pytest.param(CFirmwareChip, id="c"))
    return params


@pytest.fixture(params=_chip_class_params())
def chip_class(request):
    """The chip implementation under test: the Python model, then the C firmware (cffi)."""
    return request.param
