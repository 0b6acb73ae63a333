"""``python -m lfsim.cli``: the ``lfsim`` command."""

import sys

from . import main

sys.exit(main())
