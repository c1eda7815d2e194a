"""``python -m idas_sumo.cli``: the ``idas-sumo`` command."""

import sys

from idas_sumo.cli import main

sys.exit(main())
