"""Alias of `host.analysis.calibration`, the name other tools import (``from host.calibration
import fit_board_poses, Calibration``).

The module object is the same (``host.calibration is host.analysis.calibration``), as
`host.estimator` is for `host.analysis.estimator`.
"""

import sys

from host.analysis import calibration as _calibration

sys.modules[__name__] = _calibration
