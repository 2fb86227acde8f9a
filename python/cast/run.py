"""``python -m cast.run module:Class``: the Python component runner."""

from __future__ import annotations

import sys

from cast.client.runner import main

if __name__ == "__main__":
    sys.exit(main())
