"""Array type aliases of the estimators, stated once so every signature reads the same.

Units and shapes are the docstrings' business (:mod:`estimators.conventions`);
these aliases pin the element type only. Arrays built by the estimators are
float64 (``np.asarray(x, dtype=float)``), boolean masks are ``bool_`` and index
arrays are ``intp`` (what ``np.flatnonzero`` and ``np.argsort`` return).
"""

from __future__ import annotations

from typing import Any, TypeAlias, TypeVar

import numpy as np
from numpy.typing import NDArray

FloatArray: TypeAlias = NDArray[np.float64]
"""A float64 array (samples, vectors, matrices, parameter vectors)."""

BoolArray: TypeAlias = NDArray[np.bool_]
"""A boolean mask over samples or parameters."""

IntArray: TypeAlias = NDArray[np.intp]
"""An array of integers: indices, counts, run lengths."""

StateArray: TypeAlias = NDArray[np.int8]
"""Per-sample monitor states (int8 codes of an ``IntEnum``, e.g. F0's OK / FAIL / NOT_APPLICABLE)."""

ArrayT = TypeVar("ArrayT", bound=np.ndarray[Any, Any])
"""Any array type, for functions that return an array of the type they were given."""
