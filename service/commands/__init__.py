"""CLI subcommands, one module each.

Each module defines ``register(subparsers)`` which adds its parser and sets
``func`` (called with the parsed ``argparse.Namespace``, returns the exit status).
:mod:`service.cli` discovers the modules of this package, so a new command is a
new module and nothing else. Every module is imported to build the parser, so
at module level a command imports only light modules (the standard library,
numpy, ``estimators.conventions``, ``service.cli``); scipy, matplotlib, zenoh
and pymavlink are imported inside the function that runs the command
(``tests/test_cli_startup.py``, ``benchmarks/bench_startup.py``).
"""
