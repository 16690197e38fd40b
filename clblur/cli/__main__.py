"""``python -m clblur.cli``."""

import sys

from clblur.cli import main

sys.exit(main())
