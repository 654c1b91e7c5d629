"""``python -m torchcal``: the same as the ``torchcal`` command."""

import sys

from torchcal._entry import main

sys.exit(main())
