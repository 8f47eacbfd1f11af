"""``python -m torchraster ...``: the same command line as ``torchraster``."""

import sys

from .cli import main

sys.exit(main())
