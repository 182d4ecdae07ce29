"""``python -m fgnav ...``: the same as the ``fgnav`` command."""

import sys

from fgnav.cli import main

sys.exit(main())
