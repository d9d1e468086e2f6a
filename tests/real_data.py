"""The real data the tests read: ``shared/`` beside the repository, and the skip when it is absent.

A fresh clone has no ``../shared``: the tests that read it are skipped, the
reason naming the missing path (``pytest -ra`` prints it); with the folder
present, as in CI, they all run. The folder is found relative to this file,
never by an absolute machine path.
"""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[2] / "shared"
DATA = SHARED / "data"
XSENS = DATA / "measured" / "xsens-multiposition"
LOGS = DATA / "logs"
FIELD = DATA / "field"
MPU6050 = FIELD / "mpu6050-multiposition"
MPU6050_SESSION = MPU6050 / "example_data_calibration.csv"
REAL_BIN = LOGS / "ardupilot-test.BIN"
REAL_TLOG = LOGS / "ardupilot-sitl-vtol.tlog"


def needs(path: Path) -> pytest.MarkDecorator:
    """A mark that skips the test (or module, as ``pytestmark``) when ``path`` does not exist.

    The mark is evaluated before the test's fixtures are set up, so a
    module-scoped fixture that reads the data is never built in a clone
    without it.
    """
    return pytest.mark.skipif(
        not path.exists(),
        reason=f"real data absent: {path} (the shared/ folder beside the repository)",
    )
