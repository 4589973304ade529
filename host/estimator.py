"""The old import path of `host.analysis.estimator`, kept because other tools import ``host.estimator``:
its public names (``__all__``), re-exported. The module is `host.analysis.estimator`; patch or
introspect that one."""

from host.analysis.estimator import *  # noqa: F401,F403 - the re-export is the point
from host.analysis.estimator import __all__  # noqa: F401
