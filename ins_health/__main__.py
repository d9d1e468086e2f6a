"""``python -m ins_health``: the ``ins-health`` command (its console script calls :func:`main`)."""

from __future__ import annotations

import sys

from service.cli import main as _cli_main

__all__ = ["main"]


def main(argv: list[str] | None = None) -> int:
    """``ins-health`` as its own process: :func:`service.cli.main` with ``own_process``."""
    return _cli_main(argv, own_process=True)


if __name__ == "__main__":
    sys.exit(main())
