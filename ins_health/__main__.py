"""``python -m ins_health``: the ``ins-health`` command (its console script calls :func:`main`)."""

from __future__ import annotations

import sys

from service.cli import main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(main())
