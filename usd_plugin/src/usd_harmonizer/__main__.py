"""``python -m usd_harmonizer``: the same as ``usd-harmonize``."""

import sys

from .cli import main

sys.exit(main())
