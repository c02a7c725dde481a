"""``python -m service.cli``: the ``teachpath`` command."""

import sys

from service.cli import main

sys.exit(main())
