"""F0's view of the static detector: samples held until the decision on them is final (package docstring, step 5)."""

from __future__ import annotations

from typing import Any

import numpy as np

from estimators.static_detector import FinalDecisions


class StaticGate:
    """Holds samples until the static detector's decision on them is final, and erodes the static runs.

    F0 (M1) holds only while the unit is static. The detector's causal verdict
    ``static_now`` lags an abrupt start of motion (a take-off) by up to one
    window, so F0 is applied to the detector's *final* decisions instead
    (``W − 1`` samples late; the same decisions as the batch detector), with
    ``margin`` samples removed at both ends of every static run: the slow start
    and end of a turn sit inside a quiet window too (the positions trim the same
    amount for the same reason). The delay is ``W − 1 + margin`` samples.

    Where the data jump between two static samples the detector ends the run
    for the positions (a joined recording, a lost turn), but F0 keeps it whole:
    a step fault of a resting unit is such a jump, and F0 must test the first
    samples after it, not ``margin`` samples later.

    Samples are numbered by the detector's accepted-sample count; the caller
    pushes exactly the samples the detector accepted, with the decisions that
    became final while it fed them.
    """

    def __init__(self, margin: int) -> None:
        self.margin = int(margin)
        self._c0 = 0  # number of the first buffered sample
        self._t = np.zeros(0)
        self._x = np.zeros((0, 6))
        self._d0 = 0  # number of the first kept decision
        self._dec = np.zeros(0, dtype=bool)  # final static flag per decided sample
        self._brk = np.zeros(0, dtype=bool)  # a segment ends after this sample
        self._next = 0  # next sample to release

    def push(
        self, t_s: np.ndarray, accel: np.ndarray, gyro: np.ndarray, decisions: FinalDecisions
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Buffer samples and the decisions that became final; returns ``(t, accel, gyro, static)`` released."""
        if t_s.size:
            self._t = np.concatenate([self._t, t_s])
            self._x = np.concatenate([self._x, np.hstack([accel, gyro])])
        end = self._d0 + self._dec.size
        # Decisions already held (a checkpoint taken mid-stream) are skipped; a gap would misplace every flag.
        if decisions.start > end:
            raise ValueError(f"static decisions skip samples {end}…{decisions.start - 1}")
        skip = min(end - decisions.start, decisions.static.size)
        if skip < decisions.static.size:
            self._dec = np.concatenate([self._dec, decisions.static[skip:]])
            self._brk = np.concatenate([self._brk, decisions.brk[skip:]])
        return self._release()

    def _release(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        m, d0 = self.margin, self._d0
        end = d0 + self._dec.size
        upto = end - m
        brk_at = np.flatnonzero(self._brk[max(0, self._next - d0) :])
        if brk_at.size:
            upto = max(upto, self._next + int(brk_at[-1]) + 1)
        upto = min(upto, self._c0 + self._t.size)
        if upto <= self._next:
            return np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, dtype=bool)
        c = np.arange(self._next, upto)
        bad = np.concatenate([[0], np.cumsum(~self._dec)])
        brk = np.concatenate([[0], np.cumsum(self._brk)])
        lo, hi = c - m - d0, c + m - d0  # decision positions of the window [c − m, c + m]
        inside = (lo >= 0) & (hi < self._dec.size)
        lo_c, hi_c = np.clip(lo, 0, self._dec.size), np.clip(hi, -1, self._dec.size - 1)
        static = inside & (bad[hi_c + 1] - bad[lo_c] == 0) & (brk[hi_c] - brk[lo_c] == 0)
        i0, i1 = self._next - self._c0, upto - self._c0
        t, x = self._t[i0:i1], self._x[i0:i1]
        self._next = upto
        # Keep the samples not released and the decisions the next windows still look back on.
        self._t, self._x, self._c0 = self._t[i1:], self._x[i1:], upto
        keep_from = max(0, upto - m - d0)
        self._dec, self._brk, self._d0 = (
            self._dec[keep_from:],
            self._brk[keep_from:],
            d0 + keep_from,
        )
        return t, x[:, :3], x[:, 3:], static

    def state_dict(self) -> dict[str, Any]:
        return {"margin": self.margin, "c0": self._c0, "t": self._t, "x": self._x, "d0": self._d0,
                "dec": self._dec, "brk": self._brk, "next": self._next}  # fmt: skip

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> StaticGate:
        gate = cls(int(state["margin"]))
        gate._c0, gate._d0, gate._next = int(state["c0"]), int(state["d0"]), int(state["next"])
        gate._t = np.asarray(state["t"], float).reshape(-1)
        gate._x = np.asarray(state["x"], float).reshape(-1, 6)
        gate._dec = np.asarray(state["dec"], bool).reshape(-1)
        gate._brk = np.asarray(state["brk"], bool).reshape(-1)
        if gate._x.shape[0] != gate._t.size or gate._dec.size != gate._brk.size:
            raise ValueError("inconsistent static gate state")
        return gate
