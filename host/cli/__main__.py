"""``python -m host.cli``: the same as the ``capsheet`` console script."""

import sys

from host.cli import main

sys.exit(main())
