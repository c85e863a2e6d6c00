"""``python -m beacon_torch``: the ``beacon-torch`` command."""

import sys

from beacon_torch.cli import main

sys.exit(main())
