"""``python -m usdfiber``: the same as the ``usdfiber`` command."""
import sys

from usdfiber.cli import main

sys.exit(main())
