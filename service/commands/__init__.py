"""CLI subcommands, one module each.

Each module defines ``register(subparsers)`` which adds its parser and sets
``func`` (called with the parsed ``argparse.Namespace``, returns the exit status).
:mod:`service.cli` discovers the modules of this package, so a new command is a
new module and nothing else.
"""
