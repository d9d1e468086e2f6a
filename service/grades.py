"""One vocabulary for a sensor's grade in every command: the sensor classes of the nominal passports
(:class:`estimators.nominal_passport.SensorClass`: ``consumer_mems``, ``industrial_mems``,
``tactical``, ``navigation``).

``replay --grade`` names the class whose nominal passport applies, ``calibrate --grade`` the class
whose tolerance floors a passport gets (:class:`estimators.conventions.Grade`: both MEMS classes
take the MEMS floors), ``simulate --grade`` the class whose error preset is simulated (the
simulator has presets for ``consumer_mems`` and ``navigation``). ``mems``, the earlier spelling of
``calibrate`` and ``simulate``, is still taken, as ``consumer_mems``, with a note on stderr.
The names are stated here, not imported: building the parser must not load scipy
(``tests/test_cli_startup.py`` checks they agree).
"""

from __future__ import annotations

import sys

SENSOR_CLASSES = ("consumer_mems", "industrial_mems", "tactical", "navigation")
"""The values of :class:`estimators.nominal_passport.SensorClass`, the default first."""
OLD_SPELLINGS = {"mems": "consumer_mems"}
"""Earlier spellings still taken, and what they are taken as."""
FLOOR_GRADE = {
    "consumer_mems": "mems",
    "industrial_mems": "mems",
    "tactical": "tactical",
    "navigation": "navigation",
}
"""The :class:`estimators.conventions.Grade` value (tolerance floors, simulator presets) of each class."""
SIMULATED = ("consumer_mems", "navigation")
"""The classes the simulator has an error preset for (``estimators.sim.GRADES``)."""


def grade_name(value: str, *, what: str = "--grade") -> str:
    """``value`` in the one vocabulary: an earlier spelling is taken, with a note on stderr."""
    new = OLD_SPELLINGS.get(value)
    if new is None:
        return value
    print(f"ins-health: {what} {value} is spelled {new} now; taken as {new}", file=sys.stderr)
    return new
