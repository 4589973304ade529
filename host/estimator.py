"""Alias of `host.analysis.estimator`, kept because other tools import ``host.estimator``.

The module object is the same (``host.estimator is host.analysis.estimator``), so monkeypatching,
private helpers and ``isinstance`` checks behave exactly as on the real module.
"""

import sys

from host.analysis import estimator as _estimator

sys.modules[__name__] = _estimator
