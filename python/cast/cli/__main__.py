"""``python -m cast.cli``."""

import sys

from cast.cli.main import main

sys.exit(main())
