"""``python -m torchcal.cli``: the same as ``python -m torchcal``."""

import sys

from torchcal.cli._main import main

sys.exit(main())
