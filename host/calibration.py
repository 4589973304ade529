"""The old import path of `host.analysis.calibration`, the name other tools import (``from
host.calibration import fit_board_poses, Calibration``): its public names (``__all__``),
re-exported. The module is `host.analysis.calibration`."""

from host.analysis.calibration import *  # noqa: F401,F403 - the re-export is the point
from host.analysis.calibration import __all__  # noqa: F401
