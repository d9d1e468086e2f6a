"""``python -m ins_health.router --listen ENDPOINT``: the project's Zenoh router
(:mod:`protocols.zenoh_router`) under a name that holds installed from the wheel and in a checkout."""

from __future__ import annotations

import sys

from protocols.zenoh_router import main

__all__ = ["main"]

if __name__ == "__main__":
    sys.exit(main())
