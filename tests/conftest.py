"""Shared pytest configuration. Hypothesis: a CI profile that is deterministic and bounded. The
order of the session: the long tests first (see `pytest_collection_modifyitems`)."""

import os

import pytest

from hypothesis import HealthCheck, settings

from tests import zenoh_meeting

settings.register_profile("ci", max_examples=150, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow])
settings.register_profile("dev", max_examples=300, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

# every default Zenoh session of this worker (in its process and in every process it starts) meets at
# a loopback port of the worker's own, not at 7447 with the other workers' (tests/zenoh_meeting.py)
zenoh_meeting.install()


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


#: Test files whose tests take seconds to a minute each (real processes, ptys and buses, runs of a
#: fixed duration), in the order they start. ``make test`` spreads the session over two workers
#: (pytest-xdist, ``--dist loadgroup``), which hand out the tests in collection order: started
#: last, a minute-long test keeps one worker busy while the other has nothing left to do. Started
#: first, the short tests fill in around them at the end. The order decides nothing a test checks.
LONG_FIRST = (
    "tests/host/test_matrix.py",
    "tests/host/test_long_run.py",
    "tests/host/cli/test_calibrate_imu.py",
    "tests/host/cli/test_estimate_workers.py",
    "tests/host/test_imu_cli.py",
    "tests/host/cli/test_virtual.py",
    "tests/host/cli/test_tactile.py",
    "tests/host/cli/test_calibrate.py",
    "tests/host/cli/test_publish_ros2.py",
    "tests/host/cli/test_publish.py",
    "tests/host/cli/test_host.py",
    "tests/host/cli/test_demo.py",
    "tests/host/cli/test_host_processes.py",
    "tests/host/test_capture.py",
    "tests/host/cli/",
)


def pytest_collection_modifyitems(session, config, items):
    """The tests of `LONG_FIRST` first (in its order), then the rest in collection order: a stable
    sort, the same on every worker (xdist checks that the workers' collections are identical)."""
    def rank(item) -> int:
        path = item.nodeid.split("::", 1)[0]
        return next((k for k, prefix in enumerate(LONG_FIRST) if path.startswith(prefix)), len(LONG_FIRST))
    items[:] = sorted(items, key=rank)
