"""Pure numerics of ins-health: no I/O, no event loop, no clocks, no logging.

The conventions contract (units, frames, error model, parameter order) is
:mod:`estimators.conventions`; every module refers to it. Each module implements
one method of ``docs/methods.md`` and cites its equations.
"""
