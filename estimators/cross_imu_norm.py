"""Rotation-invariant cross-IMU check in flight: the norms of two IMUs of one vehicle (methods.md M1 carried into flight).

M1 rests on a magnitude being invariant under rotation. Two IMUs on one rigid
vehicle see the same motion: IMU 1 sits at the lever arm ``r`` (m, IMU 0's axes)
from IMU 0 and is mounted in any attitude ``R`` (IMU 1 ← IMU 0 axes), so::

    ω₁ = R ω₀,      f₁ = R (f₀ + ω̇ × r + ω × (ω × r))

and their norms do not depend on ``R``: ``|ω₁| = |ω₀|`` and ``|f₁| = |f₀ + L r|``
with ``L r = ω̇ × r + ω × (ω × r)``. A mounting change is no disagreement; a
scale or zero-signal fault of either unit on an axis that carries the specific
force (thrust) or the rotation shows at once, whatever the mounting.

The regression (squared norms, exactly linear in the unknowns)
--------------------------------------------------------------
Each unit's errors leave ``v₁ = R (M v + b₁)`` for a true ``v``: ``b`` the zero
signals, ``M`` the scale and non-orthogonality. So ``|v₁|² − |v₀|² = vᵀ Q v +
2 Δbᵀ v + c`` with ``Q = M₁ᵀM₁ − M₀ᵀM₀`` (symmetric, six numbers: the units'
scale and axis differences, a few 1e-3 for MEMS), ``Δb`` the zero-signal
difference in IMU 0's axes and ``c = |b₁|² − |b₀|²`` (plus the difference of the
units' noise powers). ``R`` has gone: the check needs no mounting. The
accelerometers add the lever arm, ``|f₁|² − |f₀|² ∋ 2 f₀·(L r) + |L r|²`` (neglected:
products of two errors), and by the identities ``f·(ω × (ω × r)) = r·(ω (ω·f) − |ω|² f)`` and
``f·(ω̇ × r) = r·(f × ω̇)`` every term is a known regressor times an unknown
constant. Dividing by ``2m``, ``m = max(|f₀|, f_floor)``, makes the statistic
m/s² (≈ ``|f₁| − |f₀|``; ``c`` is negligible against ``g²``)::

    y_a = (|f₁|² − |f₀|²) / 2m
    x_a = [ (ω (ω·f₀) − |ω|² f₀ + f₀ × ω̇) / m,  f₀ / m,  q(f₀) / 2m,  LᵀL / 2m ]    θ_a = [r, Δb, Q, ρ]

with ``q(v) = [vx², vy², vz², 2vxvy, 2vxvz, 2vyvz]`` (``vᵀQv = q(v)·Q``), and the
quadratic ``|L r|² / 2m = rᵀ (LᵀL / 2m) r`` (up to 0.05 m/s² in the simulated
flight's turns: ``|L r|`` reaches 1 m/s²) made linear by lifting: its six
products ``ρ = [rx², ry², rz², rxry, rxrz, ryrz]`` are unknowns of their own, with
the block mean of ``LᵀL / 2m`` (off-diagonal entries twice) as their regressors.
The fit stays an exact linear least squares (taking ``|L r|²`` off with the ``r``
found so far fed a wrong early ``r`` back into the fit for good). The gyro
likewise, ``m_g = max(|ω₀|, ω_floor)`` (rad/s), ``c`` kept (the norms are small
near rest)::

    y_g = (|ω₁|² − |ω₀|²) / 2m_g
    x_g = [ ω₀ / m_g,   1 / 2m_g,   q(ω₀) / 2m_g ]                              θ_g = [Δb, c, Q]

A fault is a change of ``Q`` or ``Δb``: the test is on the innovations against
the parameters learned before it (the fit absorbs a fault only as ``1/n`` of the
blocks since the start).

Samples are paired on IMU 0's clock: IMU 1 is interpolated linearly between its
two samples around each IMU 0 sample (not across a gap over ``max_pair_gap_s``).
``ω̇`` is the **central difference** of IMU 0's gyro, ``(ω_{k+1} − ω_{k−1})/(t_{k+1} − t_{k−1})``
(one-sided next to a gap over ``max_pair_gap_s``, zero between two; a sample
waits for its successor): a backward difference lags by half a sample, which in
the simulated turns (``ω̈`` ≈ 25 rad/s³) is 0.1 rad/s², 1e-2 m/s² at 8 cm. Its
per-sample noise ``σ_ω/Δt`` is large, but it enters only through block means,
where ``f₀ × ω̇`` telescopes to about ``f₀ × (ω_end − ω_start)/T`` while ``f₀`` is
steady: the block's noise is ``√2 σ_ω/T``. A block whose mean ``|ω|`` is below
``ω_floor`` (a vehicle at rest) leaves the lever arm out of its update: its
lever-arm regressors are that noise alone, and would walk ``r`` away.

Kernel, parameters, noise
-------------------------
The low-pass is a **boxcar of** ``block_s`` (1 s) decimated to one value per block:
blocks ``[jT, (j+1)T)`` on IMU 0's sample clock, each the mean of its paired
samples' ``y`` and ``x`` (the relation is linear, so the means obey it too).
``θ`` is estimated by recursive least squares over the blocks (covariance form,
Joseph update, prior ``θ ~ N(0, P₀)``; no forgetting), whose covariance ``P``
gives the lever arm's. The test statistic is the block's innovation
``e_j = y_j − x_jᵀ θ_{j−1}`` over its standard deviation ``√(x_jᵀ P x_j + σ̂²)``.
The block noise ``σ̂`` comes from the data: the innovations' first differences
``d_j = e_j/s_j − e_{j−1}/s_{j−1}`` (``var d = 2σ²``; slow model errors drop out), through
``σ̂ = max(med₉|d|, med₃₀₁|d|) / (0.6745 √2)``: medians of the last 9 and 301
blocks, so a step fault (one large difference) moves neither, while a noise rise
(motors starting) is followed within 5 s. ``s_j`` is the block's known noise scale: the
gyro statistic's noise is the units' noise along ``ω`` times ``|ω|/m_g`` (below ``ω_floor``
it shrinks with ``|ω|``), so ``s_j = rms(|ω|/m_g)`` over the block, and the block's noise
is ``σ̂ s_j`` (1 for the accelerometers, ``|f| ≥ f_floor``). Without it, and with a
slow median of 61 blocks, a calm stretch of flight taught a channel a noise too small for the
next turns: 3 false alarms in 100 simulated flight hours (two of the gyro, one of the
accelerometers, each with ``σ̂`` half its usual value). The test starts after ``warmup_blocks``.

Detector and its threshold (derivation)
---------------------------------------
Each channel runs a two-sided CUSUM on the standardized innovation ``z_j``
(``g⁺ = max(0, g⁺ + z − k)``, ``g⁻ = max(0, g⁻ − z − k)``, alarm at ``g > h``).
For i.i.d. ``z ~ N(μ, 1)`` Siegmund's approximation of a one-sided CUSUM's
average run length is (D. Siegmund, *Sequential Analysis*, 1985)::

    ARL(μ) = (exp(−2Δb) + 2Δb − 1) / (2Δ²),   Δ = μ − k,  b = h + 1.166   (b² at Δ = 0)

The check runs four one-sided CUSUMs (two channels, two signs), each a renewal
process alarming about once per ``ARL(0)`` blocks, so the false alarms per flight
hour are ``λ = 4 · (3600 / T) / ARL(0)``; ``h`` solves ``ARL(0) = 4 · 3600 / (T λ)``
(:func:`cusum_threshold`). At ``λ = 1e-4`` per flight hour (the default), ``k = 1``,
``T = 1 s``: ``h = 8.57``, and ``μ* = 2.90`` for a mean delay of 5 s (1e-3: 7.42 and 2.66).
A channel alarms once a flight (the fault stays); its CUSUMs then start again, for the plot.
The innovations are not quite i.i.d. (σ̂ is estimated, the parameters still settle), so
the rate holds as far as the simulated flights measure it (``benchmarks/bench_inflight.py``).

Minimum detectable fault
------------------------
The shift of the statistic (the norm difference) that the CUSUM detects within
``detect_within_s`` on average: ``μ*`` solves ``ARL(μ*) = detect_within_s / T``
and ``MDF = μ* σ̂`` (m/s² or rad/s; :func:`cusum_shift`). A scale fault ``e`` of
an axis carrying the specific force ``|f|`` moves ``y_a`` by ``e |f|`` (0.5 % in
hover: 0.049 m/s²); a zero signal ``b`` along the specific force by ``b``. A gyro
scale fault moves ``y_g`` by ``e ω_i²/|ω|`` on the axis turning, a gyro zero signal by
its component along the rotation: in hover, where the rates are small and turn about
every axis, the gyro norm says little of a zero signal.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import asdict, dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from estimators._typing import FloatArray
from estimators.session import ImuSession

SIEGMUND_CORRECTION = 1.166
"""``2 · 0.583``: the overshoot correction of Siegmund's ARL approximation (module docstring)."""

MAD_TO_SIGMA = 1.0 / (0.6744897501960817 * math.sqrt(2.0))
"""Median of ``|d|``, ``d ~ N(0, 2σ²)``, to ``σ``."""

MIN_NOISE_SCALE = 1.0e-3
"""The least noise scale of a block (a gyro at rest: ``|ω|/m_g`` is its bias over ``ω_floor``)."""

NOISE_FLOOR_FRACTION = 1.0e-4
"""The block noise is taken as at least this fraction of the initial guess (1e-4: far below any sensor's)."""

NORM_STATE_VERSION = 1
"""Version of :meth:`CrossImuNorm.state_dict` (a checkpointed state of another version is not resumed)."""

MIN_RATE_HZ = 20.0
"""The least sample rate of either IMU the check compares. Each IMU's samples are snapshots taken at
its own instants, and IMU 1's are interpolated to IMU 0's: linear interpolation over a step ``Δt``
errs by up to ``|ω̈| Δt²/8`` in the rate, so the error grows with the square of the step. On
ArduPlane SITL's telemetry log (RAW_IMU and SCALED_IMU2 snapshots at 4.2 Hz) one manoeuvre put a
block's gyro norm difference 7 σ off and raised a false alarm when the check ran from the log's
start; at 20 Hz the same motion errs 23× less (``(20/4.2)²``)."""

N_ONE_SIDED = 4
"""One-sided CUSUMs the check runs: two channels, two signs (the false-alarm budget is shared)."""


class NormChannel(StrEnum):
    """What a channel compares."""

    ACCEL = "accel"
    GYRO = "gyro"


@dataclass(frozen=True)
class NormCheckConfig:
    """Settings of the cross-IMU norm check (module docstring).

    Attributes
    ----------
    block_s : boxcar length and decimation of the statistic, s.
    false_alarms_per_hour : the check's false-alarm rate (both channels together).
    k_sigma : CUSUM reference value, in standard deviations of a block (optimal for a shift of ``2k``).
    detect_within_s : mean detection delay that defines the minimum detectable fault, s.
    warmup_blocks : blocks before the test starts (the noise and the parameters settle).
    min_block_samples : paired samples a block needs to be used.
    max_pair_gap_s : IMU 1 is not interpolated across a gap longer than this, nor ``ω̇`` taken.
    max_pending : samples each stream may run ahead of the other (the oldest beyond are dropped, counted).
    f_floor_mps2, w_floor_rps : the divisors' floors ``f_floor``, ``ω_floor``.
    lever_prior_m, accel_bias_prior_mps2, gyro_bias_prior_rps, const_prior_rps2, quad_prior :
        prior standard deviations of the parameters.
    initial_noise_mps2, initial_noise_rps : the block noise assumed before any difference is seen.
    """

    block_s: float = 1.0
    false_alarms_per_hour: float = 1.0e-4
    k_sigma: float = 1.0
    detect_within_s: float = 5.0
    warmup_blocks: int = 20
    min_block_samples: int = 3
    max_pair_gap_s: float = 0.1
    max_pending: int = 8192
    f_floor_mps2: float = 1.0
    w_floor_rps: float = 0.05
    lever_prior_m: float = 0.3
    accel_bias_prior_mps2: float = 0.5
    gyro_bias_prior_rps: float = 0.1
    const_prior_rps2: float = 0.01
    quad_prior: float = 0.05
    initial_noise_mps2: float = 0.05
    initial_noise_rps: float = 0.01

    def __post_init__(self) -> None:
        for name in (
            "block_s",
            "false_alarms_per_hour",
            "k_sigma",
            "detect_within_s",
            "max_pair_gap_s",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"NormCheckConfig.{name} must be positive and finite, got {v!r}")
        if self.warmup_blocks < 2 or self.min_block_samples < 1 or self.max_pending < 2:
            raise ValueError(
                f"NormCheckConfig needs warmup_blocks >= 2, min_block_samples >= 1, max_pending >= 2, got "
                f"{self.warmup_blocks}, {self.min_block_samples}, {self.max_pending}"
            )

    @classmethod
    def for_rate(cls, rate_hz: float) -> NormCheckConfig:
        """The settings for a stream of ``rate_hz``: a block holds at least 8 samples (1 s from 8 Hz;
        a 4 Hz telemetry log's 1.9 s) and IMU 1 is interpolated across at most 2.5 sample periods
        (0.1 s from 25 Hz): one lost sample is bridged, not two."""
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"rate_hz must be positive and finite, got {rate_hz!r}")
        return cls(block_s=max(1.0, 8.0 / rate_hz), max_pair_gap_s=max(0.1, 2.5 / rate_hz))

    @property
    def threshold(self) -> float:
        """The CUSUM threshold ``h`` for :attr:`false_alarms_per_hour` (module docstring)."""
        return cusum_threshold(
            N_ONE_SIDED * 3600.0 / (self.block_s * self.false_alarms_per_hour), self.k_sigma
        )

    @property
    def mdf_sigmas(self) -> float:
        """The minimum detectable shift in block standard deviations (module docstring)."""
        return cusum_shift(self.detect_within_s / self.block_s, self.k_sigma, self.threshold)


def cusum_arl(mu: float, k: float, h: float) -> float:
    """Siegmund's average run length (blocks) of a one-sided CUSUM with reference ``k``, threshold ``h``
    on ``N(mu, 1)`` increments (module docstring)."""
    delta = mu - k
    b = h + SIEGMUND_CORRECTION
    if abs(delta) < 1e-9:
        return b * b
    x = 2.0 * delta * b
    return (math.exp(-x) + x - 1.0) / (2.0 * delta * delta)


def cusum_threshold(arl0_blocks: float, k: float) -> float:
    """The ``h`` whose in-control run length ``cusum_arl(0, k, h)`` is ``arl0_blocks``."""
    if not arl0_blocks > 1.0:
        raise ValueError(f"the in-control run length must exceed one block, got {arl0_blocks!r}")
    hi = 1.0
    while cusum_arl(0.0, k, hi) < arl0_blocks:
        hi = 2.0 * hi
    # scipy is imported here: the fleet imports this module's constants in every command.
    from scipy.optimize import brentq

    return float(brentq(lambda h: cusum_arl(0.0, k, h) - arl0_blocks, 0.0, hi))


def cusum_shift(delay_blocks: float, k: float, h: float) -> float:
    """The shift ``μ`` (standard deviations) a CUSUM detects in ``delay_blocks`` on average."""
    if not delay_blocks > 0.0:
        raise ValueError(f"the detection delay must be positive, got {delay_blocks!r}")
    hi = k + 1.0
    while cusum_arl(hi, k, h) > delay_blocks:
        hi = 2.0 * hi
    from scipy.optimize import brentq

    return float(brentq(lambda mu: cusum_arl(mu, k, h) - delay_blocks, k, hi))


@dataclass(frozen=True)
class NormAlarm:
    """A channel's CUSUM crossed its threshold: the norm difference moved.

    Attributes
    ----------
    channel : which norm.
    t_s : end of the block that crossed, s (IMU 0's clock).
    sign : +1 IMU 1's norm grew against IMU 0's, −1 it shrank.
    shift_si : mean innovation over the CUSUM's run (the size of the move), m/s² or rad/s.
    sigma_si : the block noise ``σ̂`` then.
    threshold : ``h``.
    mdf_si : the minimum detectable shift then.
    """

    channel: NormChannel
    t_s: float
    sign: int
    shift_si: float
    sigma_si: float
    threshold: float
    mdf_si: float


@dataclass(frozen=True)
class ChannelBlock:
    """One channel's view of one block: innovation, its standard deviation, both CUSUMs, whether tested."""

    innovation_si: float
    innovation_sd_si: float
    sigma_si: float
    cusum_pos: float
    cusum_neg: float
    tested: bool


@dataclass(frozen=True)
class NormBlock:
    """One evaluated block: both channels, the lever arm found so far, the alarms it raised.

    Attributes
    ----------
    t_s : end of the block, s.
    samples : paired samples in it.
    accel, gyro : the channels.
    lever_arm_m : (3,) ``r`` estimated after the block, m, IMU 0's axes.
    lever_arm_sd_m : (3,) its standard deviations (√diag of the RLS covariance).
    alarms : alarms raised at this block.
    """

    t_s: float
    samples: int
    accel: ChannelBlock
    gyro: ChannelBlock
    lever_arm_m: FloatArray
    lever_arm_sd_m: FloatArray
    alarms: tuple[NormAlarm, ...] = ()


class _Channel:
    """RLS over block means, the noise from the innovations' differences, a two-sided CUSUM (module docstring)."""

    def __init__(
        self,
        channel: NormChannel,
        prior_sd: ArrayLike,
        initial_noise: float,
        cfg: NormCheckConfig,
        threshold: float,
    ) -> None:
        self.channel = channel
        sd = np.asarray(prior_sd, float)
        self.theta = np.zeros(sd.size)
        self.cov = np.diag(sd**2)
        self.cfg = cfg
        self.h = threshold
        self.initial_noise = initial_noise
        self.fast: deque[float] = deque(maxlen=9)
        self.slow: deque[float] = deque(maxlen=301)
        self.last_e: float | None = None
        self.blocks = 0
        self.tested = 0
        self.g_pos = self.g_neg = 0.0
        self.run_pos: list[float] = [0.0, 0.0]  # blocks, sum of innovations since g⁺ last left zero
        self.run_neg: list[float] = [0.0, 0.0]
        self.alarmed = False

    _SCALARS = ("last_e", "blocks", "tested", "g_pos", "g_neg", "alarmed")

    def state_dict(self) -> dict[str, Any]:
        return {
            "theta": self.theta.copy(),
            "cov": self.cov.copy(),
            "fast": list(self.fast),
            "slow": list(self.slow),
            "run_pos": list(self.run_pos),
            "run_neg": list(self.run_neg),
            **{k: getattr(self, k) for k in self._SCALARS},
        }

    def load_state(self, state: dict[str, Any]) -> None:
        theta = np.array(state["theta"], float).reshape(-1)
        cov = np.array(state["cov"], float)
        if theta.shape != self.theta.shape or cov.shape != self.cov.shape:
            raise ValueError(
                f"a {self.channel.value} channel of {self.theta.size} parameters, got {theta.shape}"
            )
        self.theta, self.cov = theta, cov
        self.fast.extend(float(v) for v in state["fast"])
        self.slow.extend(float(v) for v in state["slow"])
        self.run_pos = [float(v) for v in state["run_pos"]]
        self.run_neg = [float(v) for v in state["run_neg"]]
        self.last_e = None if state["last_e"] is None else float(state["last_e"])
        self.blocks, self.tested = int(state["blocks"]), int(state["tested"])
        self.g_pos, self.g_neg = float(state["g_pos"]), float(state["g_neg"])
        self.alarmed = bool(state["alarmed"])

    @property
    def sigma(self) -> float:
        if not self.slow:
            return self.initial_noise
        # Noise-free data (a simulation) would leave no innovation variance and a singular update.
        floor = NOISE_FLOOR_FRACTION * self.initial_noise
        return max(
            float(np.median(self.fast)) * MAD_TO_SIGMA,
            float(np.median(self.slow)) * MAD_TO_SIGMA,
            floor,
        )

    def mdf(self) -> float:
        return self.cfg.mdf_sigmas * self.sigma

    def block(
        self, y: float, x: FloatArray, t_s: float, scale: float = 1.0
    ) -> tuple[ChannelBlock, NormAlarm | None]:
        """One block's mean ``y`` and regressors ``x``; ``scale``: its noise against a block at full
        rate (the gyro's ``rms(|ω|/m_g)``, module docstring)."""
        scale = max(scale, MIN_NOISE_SCALE)
        sigma = self.sigma * scale
        r = sigma * sigma
        px = self.cov @ x
        s = float(x @ px) + r
        e = y - float(x @ self.theta)
        gain = px / s
        self.theta = self.theta + gain * e
        # Joseph form: the covariance stays symmetric and positive through thousands of updates.
        a = np.eye(x.size) - np.outer(gain, x)
        self.cov = a @ self.cov @ a.T + r * np.outer(gain, gain)
        if self.last_e is not None:
            d = abs(e / scale - self.last_e)
            self.fast.append(d)
            self.slow.append(d)
        self.last_e = e / scale
        self.blocks += 1
        sd = math.sqrt(s)
        alarm = None
        testing = self.blocks > self.cfg.warmup_blocks
        if testing:
            self.tested += 1
            z = e / sd
            k = self.cfg.k_sigma
            self.g_pos, self.run_pos = _cusum_step(self.g_pos, z - k, e, self.run_pos)
            self.g_neg, self.run_neg = _cusum_step(self.g_neg, -z - k, e, self.run_neg)
            crossed = 1 if self.g_pos > self.h else -1 if self.g_neg > self.h else 0
            if crossed:
                run = self.run_pos if crossed > 0 else self.run_neg
                if not self.alarmed:
                    alarm = NormAlarm(
                        self.channel, t_s, crossed, run[1] / run[0], sigma, self.h, self.mdf()
                    )
                # One alarm a channel a flight: the fault stays; the CUSUMs start again for the plot.
                self.alarmed = True
                self.g_pos = self.g_neg = 0.0
                self.run_pos, self.run_neg = [0.0, 0.0], [0.0, 0.0]
        return ChannelBlock(e, sd, sigma, self.g_pos, self.g_neg, testing), alarm


def _cusum_step(g: float, step: float, e: float, run: list[float]) -> tuple[float, list[float]]:
    g = g + step
    if g <= 0.0:
        return 0.0, [0.0, 0.0]
    return g, [run[0] + 1.0, run[1] + e]


N_QUAD = 6
"""Entries of the symmetric ``Q`` (module docstring)."""
N_ACCEL = 6 + N_QUAD
"""Accelerometer regressors summed as such: lever arm (3), zero-signal difference (3), ``Q``."""
N_GYRO = 4 + N_QUAD
"""Gyro regressors: zero-signal difference (3), constant, ``Q``."""
N_SUMS = 3 + N_ACCEL + N_GYRO + N_QUAD
"""Per block: ``y_a``, ``x_a``, ``y_g``, ``x_g``, ``LᵀL / 2m``, ``(|ω|/m_g)²`` (the sums a block keeps)."""
_GYRO_AT = 1 + N_ACCEL
_LTL_AT = 2 + N_ACCEL + N_GYRO
_W2_AT = _GYRO_AT + 5
_SCALE_AT = _LTL_AT + N_QUAD
_RHO_WEIGHTS = np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])
"""``rᵀAr = ρ · (A's diagonal, 2 × its upper entries)``."""


@dataclass
class _Counts:
    paired: int = 0
    unpaired: int = 0
    blocks_skipped: int = 0


class _Blocks:
    """The blocks' parameters and channels, shared by the streaming and the batch paths."""

    def __init__(self, cfg: NormCheckConfig) -> None:
        self.cfg = cfg
        h = cfg.threshold
        self.accel = _Channel(
            NormChannel.ACCEL,
            [cfg.lever_prior_m] * 3
            + [cfg.accel_bias_prior_mps2] * 3
            + [cfg.quad_prior] * N_QUAD
            + [cfg.lever_prior_m**2] * N_QUAD,
            cfg.initial_noise_mps2,
            cfg,
            h,
        )
        self.gyro = _Channel(
            NormChannel.GYRO,
            [cfg.gyro_bias_prior_rps] * 3 + [cfg.const_prior_rps2] + [cfg.quad_prior] * N_QUAD,
            cfg.initial_noise_rps,
            cfg,
            h,
        )
        self.counts = _Counts()

    def close(self, index: int, n: int, sums: FloatArray) -> NormBlock | None:
        if n < self.cfg.min_block_samples:
            self.counts.blocks_skipped += 1
            return None
        mean = sums / n
        t_end = (index + 1) * self.cfg.block_s
        x_a = np.concatenate([mean[1:_GYRO_AT], mean[_LTL_AT:_SCALE_AT] * _RHO_WEIGHTS])
        # |ω| of the block (the gyro's q(ω)/2m_g diagonal sums to |ω|/2 above the floor): a vehicle
        # at rest has lever-arm regressors of pure ω̇ noise, which would walk r away (errors in variables).
        if 2.0 * float(mean[_W2_AT : _W2_AT + 3].sum()) < self.cfg.w_floor_rps:
            x_a[:3] = 0.0
            x_a[N_ACCEL:] = 0.0
        acc, a_alarm = self.accel.block(float(mean[0]), x_a, t_end)
        gyr, g_alarm = self.gyro.block(
            float(mean[_GYRO_AT]),
            mean[_GYRO_AT + 1 : _LTL_AT],
            t_end,
            math.sqrt(float(mean[_SCALE_AT])),
        )
        return NormBlock(
            t_end,
            n,
            acc,
            gyr,
            self.accel.theta[:3].copy(),
            np.sqrt(np.diag(self.accel.cov)[:3]),
            tuple(a for a in (a_alarm, g_alarm) if a is not None),
        )


class CrossImuNorm:
    """The per-sample (streaming) path: two IMUs' samples as they come, O(1) work per sample.

    Each IMU's samples are given in its own time order (:meth:`add`, slot 0 or 1).
    IMU 0's samples wait until IMU 1 has a sample at or after them, then are paired
    and summed into their block; a block is evaluated when a later block's first
    paired sample arrives (the block still open at the end is not). Scalars only on
    the per-sample path (no array per sample). :func:`cross_imu_norm_batch` is the
    same on whole arrays.
    """

    def __init__(self, config: NormCheckConfig = NormCheckConfig()) -> None:
        self.config = config
        self._blocks = _Blocks(config)
        self._pending0: deque[tuple[float, ...]] = deque()
        self._buf1: deque[tuple[float, ...]] = deque()
        # IMU 0's last two samples: the newer waits for its successor (central difference).
        self._prev0: tuple[float, ...] | None = None
        self._cur0: tuple[float, ...] | None = None
        self._index: int | None = None
        self._n = 0
        self._sums = [0.0] * N_SUMS

    @property
    def counts(self) -> _Counts:
        return self._blocks.counts

    def state_dict(self) -> dict[str, Any]:
        """Everything :meth:`from_state` needs to go on exactly where this check is (for checkpoints):
        the settings, the samples waiting to be paired, the open block, both channels."""
        return {
            "version": NORM_STATE_VERSION,
            "config": asdict(self.config),
            "pending0": [list(x) for x in self._pending0],
            "buf1": [list(x) for x in self._buf1],
            "prev0": None if self._prev0 is None else list(self._prev0),
            "cur0": None if self._cur0 is None else list(self._cur0),
            "index": self._index,
            "n": self._n,
            "sums": list(self._sums),
            "counts": asdict(self.counts),
            "accel": self._blocks.accel.state_dict(),
            "gyro": self._blocks.gyro.state_dict(),
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> CrossImuNorm:
        """Restore from :meth:`state_dict`; ``ValueError`` for another version or a malformed state."""
        version = state.get("version") if isinstance(state, dict) else None
        if version != NORM_STATE_VERSION:
            raise ValueError(
                f"cross-IMU norm state version {version!r} is not {NORM_STATE_VERSION}"
            )
        try:
            out = cls(NormCheckConfig(**state["config"]))
            out._pending0.extend(tuple(float(v) for v in x) for x in state["pending0"])
            out._buf1.extend(tuple(float(v) for v in x) for x in state["buf1"])
            out._prev0 = None if state["prev0"] is None else tuple(float(v) for v in state["prev0"])
            out._cur0 = None if state["cur0"] is None else tuple(float(v) for v in state["cur0"])
            out._index = None if state["index"] is None else int(state["index"])
            out._n = int(state["n"])
            out._sums = [float(v) for v in state["sums"]]
            if len(out._sums) != N_SUMS:
                raise ValueError(f"{N_SUMS} sums, got {len(out._sums)}")
            out._blocks.counts = _Counts(**{k: int(v) for k, v in state["counts"].items()})
            out._blocks.accel.load_state(state["accel"])
            out._blocks.gyro.load_state(state["gyro"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(
                f"cross-IMU norm state is malformed: {type(exc).__name__}: {exc}"
            ) from None
        return out

    def lever_arm(self) -> tuple[FloatArray, FloatArray]:
        """``r`` (3,) m and its covariance (3, 3), m², IMU 0's axes."""
        return self._blocks.accel.theta[:3].copy(), self._blocks.accel.cov[:3, :3].copy()

    def tested_s(self) -> float:
        """Time the test ran on (blocks past the warm-up), s."""
        return self._blocks.accel.tested * self.config.block_s

    def mdf(self) -> tuple[float, float]:
        """The minimum detectable shift of ``|f₁| − |f₀|`` (m/s²) and ``|ω₁| − |ω₀|`` (rad/s) now."""
        return self._blocks.accel.mdf(), self._blocks.gyro.mdf()

    def add(
        self, slot: int, t_s: ArrayLike, accel_mps2: ArrayLike, gyro_rps: ArrayLike
    ) -> list[NormBlock]:
        """One IMU's samples (slot 0: IMU 0, 1: IMU 1; time order, SI); the blocks they completed."""
        if slot not in (0, 1):
            raise ValueError(f"slot must be 0 or 1, got {slot!r}")
        t = np.asarray(t_s, float).reshape(-1).tolist()
        a = np.asarray(accel_mps2, float).reshape(-1, 3).tolist()
        g = np.asarray(gyro_rps, float).reshape(-1, 3).tolist()
        if not len(t) == len(a) == len(g):
            raise ValueError(
                f"t_s, accel_mps2 and gyro_rps need one row per sample, got {len(t)}, {len(a)}, {len(g)}"
            )
        cap = self.config.max_pending
        out: list[NormBlock] = []
        if slot == 1:
            for ti, ai, gi in zip(t, a, g, strict=True):
                self._buf1.append((ti, *ai, *gi))
            while len(self._buf1) > cap:
                self._buf1.popleft()
        else:
            for ti, ai, gi in zip(t, a, g, strict=True):
                self._take0((ti, *ai, *gi))
            while len(self._pending0) > cap:
                self._pending0.popleft()
                self.counts.unpaired += 1
        self._pair(out)
        return out

    def _take0(self, nxt: tuple[float, ...]) -> None:
        """IMU 0's newest sample: the one before it gets its central difference and waits for pairing."""
        cur, prev = self._cur0, self._prev0
        self._prev0, self._cur0 = cur, nxt
        if cur is None:
            return
        gap = self.config.max_pair_gap_s
        lo = prev if prev is not None and 0.0 < cur[0] - prev[0] <= gap else cur
        hi = nxt if 0.0 < nxt[0] - cur[0] <= gap else cur
        dt = hi[0] - lo[0]
        if dt > 0.0:
            wd = ((hi[4] - lo[4]) / dt, (hi[5] - lo[5]) / dt, (hi[6] - lo[6]) / dt)
        else:
            wd = (0.0, 0.0, 0.0)
        self._pending0.append((*cur, *wd))

    def _pair(self, out: list[NormBlock]) -> None:
        buf1 = self._buf1
        gap = self.config.max_pair_gap_s
        while self._pending0 and buf1 and buf1[-1][0] >= self._pending0[0][0]:
            s0 = self._pending0.popleft()
            t0 = s0[0]
            while len(buf1) >= 2 and buf1[1][0] <= t0:
                buf1.popleft()
            lo = buf1[0]
            if lo[0] > t0:
                self.counts.unpaired += 1
                continue
            if lo[0] == t0:
                v1 = lo[1:7]
            else:
                hi = buf1[1]
                span = hi[0] - lo[0]
                if span > gap:
                    self.counts.unpaired += 1
                    continue
                w = (t0 - lo[0]) / span
                v1 = tuple(p + w * (q - p) for p, q in zip(lo[1:7], hi[1:7], strict=True))
            self.counts.paired += 1
            self._sample(s0, v1, out)

    def _sample(self, s0: tuple[float, ...], v1: tuple[float, ...], out: list[NormBlock]) -> None:
        t0, fx, fy, fz, wx, wy, wz, dx, dy, dz = s0
        cfg = self.config
        index = math.floor(t0 / cfg.block_s)
        if self._index is None:
            self._index = index
        elif index != self._index:
            block = self._blocks.close(self._index, self._n, np.array(self._sums))
            if block is not None:
                out.append(block)
            self._index, self._n, self._sums = index, 0, [0.0] * N_SUMS
        ff = fx * fx + fy * fy + fz * fz
        m = max(math.sqrt(ff), cfg.f_floor_mps2)
        f1 = v1[0] * v1[0] + v1[1] * v1[1] + v1[2] * v1[2]
        ww = wx * wx + wy * wy + wz * wz
        wf = wx * fx + wy * fy + wz * fz
        mg = max(math.sqrt(ww), cfg.w_floor_rps)
        w1 = v1[3] * v1[3] + v1[4] * v1[4] + v1[5] * v1[5]
        h = 0.5 / m
        hg = 0.5 / mg
        # L = [ω̇]× + ω ωᵀ − |ω|² I, and LᵀL / 2m for the lifted quadratic term.
        l00, l01, l02 = wx * wx - ww, wx * wy - dz, wx * wz + dy
        l10, l11, l12 = wy * wx + dz, wy * wy - ww, wy * wz - dx
        l20, l21, l22 = wz * wx - dy, wz * wy + dx, wz * wz - ww
        row = (
            (f1 - ff) * h,
            (wx * wf - ww * fx + fy * dz - fz * dy) / m,
            (wy * wf - ww * fy + fz * dx - fx * dz) / m,
            (wz * wf - ww * fz + fx * dy - fy * dx) / m,
            fx / m,
            fy / m,
            fz / m,
            fx * fx * h,
            fy * fy * h,
            fz * fz * h,
            fx * fy / m,
            fx * fz / m,
            fy * fz / m,
            (w1 - ww) * hg,
            wx / mg,
            wy / mg,
            wz / mg,
            hg,
            wx * wx * hg,
            wy * wy * hg,
            wz * wz * hg,
            wx * wy / mg,
            wx * wz / mg,
            wy * wz / mg,
            (l00 * l00 + l10 * l10 + l20 * l20) * h,
            (l01 * l01 + l11 * l11 + l21 * l21) * h,
            (l02 * l02 + l12 * l12 + l22 * l22) * h,
            (l00 * l01 + l10 * l11 + l20 * l21) * h,
            (l00 * l02 + l10 * l12 + l20 * l22) * h,
            (l01 * l02 + l11 * l12 + l21 * l22) * h,
            ww / (mg * mg),
        )
        sums = self._sums
        for j in range(N_SUMS):
            sums[j] += row[j]
        self._n += 1


def paired_rows(
    t0_s: FloatArray,
    accel0_mps2: FloatArray,
    gyro0_rps: FloatArray,
    t1_s: FloatArray,
    accel1_mps2: FloatArray,
    gyro1_rps: FloatArray,
    config: NormCheckConfig,
) -> tuple[FloatArray, FloatArray]:
    """The batch path's per-sample stage: IMU 0's paired sample times (P,) and their rows (P, N_SUMS)
    ``[y_a, x_a, y_g, x_g]`` (module docstring), vectorized."""
    t0 = np.asarray(t0_s, float)
    f = np.asarray(accel0_mps2, float).reshape(-1, 3)
    w = np.asarray(gyro0_rps, float).reshape(-1, 3)
    t1 = np.asarray(t1_s, float)
    v1 = np.hstack(
        [np.asarray(accel1_mps2, float).reshape(-1, 3), np.asarray(gyro1_rps, float).reshape(-1, 3)]
    )
    gap = config.max_pair_gap_s
    step = np.diff(t0)
    near = (step > 0.0) & (step <= gap)
    k = np.arange(t0.size)
    lo_k = np.where(np.concatenate([[False], near]), k - 1, k)
    hi_k = np.where(np.concatenate([near, [False]]), k + 1, k)
    span0 = t0[hi_k] - t0[lo_k]
    wd = (w[hi_k] - w[lo_k]) / np.where(span0 > 0.0, span0, 1.0)[:, None]
    # IMU 0's last sample waits for its successor, as on the streaming path.
    t0, f, w, wd = t0[:-1], f[:-1], w[:-1], wd[:-1]
    lo = np.searchsorted(t1, t0, side="right") - 1
    hi = np.minimum(lo + 1, t1.size - 1)
    lo_c = np.maximum(lo, 0)
    exact = (lo >= 0) & (t1[lo_c] == t0)
    inside = (lo >= 0) & (lo + 1 < t1.size)
    span = t1[hi] - t1[lo_c]
    paired = exact | (inside & (span <= gap))
    weight = np.where(exact | ~paired, 0.0, (t0 - t1[lo_c]) / np.where(span > 0, span, 1.0))
    p1 = v1[lo_c] + weight[:, None] * (v1[hi] - v1[lo_c])
    t0, f, w, wd, p1 = t0[paired], f[paired], w[paired], wd[paired], p1[paired]
    ff = np.einsum("ij,ij->i", f, f)
    m = np.maximum(np.sqrt(ff), config.f_floor_mps2)
    ww = np.einsum("ij,ij->i", w, w)
    wf = np.einsum("ij,ij->i", w, f)
    mg = np.maximum(np.sqrt(ww), config.w_floor_rps)
    f1 = np.einsum("ij,ij->i", p1[:, :3], p1[:, :3])
    w1 = np.einsum("ij,ij->i", p1[:, 3:], p1[:, 3:])
    lever = w * wf[:, None] - ww[:, None] * f + np.cross(f, wd)
    ell = _cross_matrix(wd) + w[:, :, None] * w[:, None, :] - ww[:, None, None] * np.eye(3)
    ltl = np.einsum("nki,nkj->nij", ell, ell)
    ltl6 = ltl[:, [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]] / (2.0 * m[:, None])
    rows = np.column_stack(
        [
            (f1 - ff) / (2.0 * m),
            lever / m[:, None],
            f / m[:, None],
            _quad(f) / (2.0 * m[:, None]),
            (w1 - ww) / (2.0 * mg),
            w / mg[:, None],
            0.5 / mg,
            _quad(w) / (2.0 * mg[:, None]),
            ltl6,
            ww / mg**2,
        ]
    )
    return t0, rows


def _cross_matrix(v: FloatArray) -> FloatArray:
    """(N, 3, 3) ``[v]×``."""
    out = np.zeros((v.shape[0], 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def _quad(v: FloatArray) -> FloatArray:
    """(N, 6) ``q(v)`` (module docstring)."""
    x, y, z = v[:, 0], v[:, 1], v[:, 2]
    return np.column_stack([x * x, y * y, z * z, 2.0 * x * y, 2.0 * x * z, 2.0 * y * z])


@dataclass(frozen=True)
class NormTrace:
    """The check over a whole flight (:func:`cross_imu_norm_batch`).

    Attributes
    ----------
    blocks : the evaluated blocks, in order.
    threshold : ``h``.
    paired, unpaired : IMU 0 samples paired with IMU 1, and not.
    tested_s : time the test ran on, s.
    mdf_mps2, mdf_rps : the minimum detectable shifts at the end.
    lever_arm_m, lever_arm_cov_m2 : ``r`` (3,) and its covariance (3, 3) at the end.
    alarms : every block's alarms, in order.
    """

    blocks: tuple[NormBlock, ...]
    threshold: float
    paired: int
    unpaired: int
    tested_s: float
    mdf_mps2: float
    mdf_rps: float
    lever_arm_m: FloatArray
    lever_arm_cov_m2: FloatArray
    alarms: tuple[NormAlarm, ...] = field(default_factory=tuple)


def cross_imu_norm_batch(
    t0_s: ArrayLike,
    accel0_mps2: ArrayLike,
    gyro0_rps: ArrayLike,
    t1_s: ArrayLike,
    accel1_mps2: ArrayLike,
    gyro1_rps: ArrayLike,
    config: NormCheckConfig = NormCheckConfig(),
) -> NormTrace:
    """The batch path (replay): both IMUs' whole records (each in time order, SI) at once.

    The per-sample stage is vectorized (:func:`paired_rows`, block sums by
    ``np.add.reduceat``); the blocks go through the same recursion as
    :class:`CrossImuNorm`, whose results it reproduces (its test oracle). It has no
    ``max_pending`` limit: it sees both records whole.
    """
    t0, rows = paired_rows(
        np.asarray(t0_s, float),
        np.asarray(accel0_mps2, float),
        np.asarray(gyro0_rps, float),
        np.asarray(t1_s, float),
        np.asarray(accel1_mps2, float),
        np.asarray(gyro1_rps, float),
        config,
    )
    n0 = max(int(np.asarray(t0_s).size) - 1, 0)  # the last one still waits (paired_rows)
    blocks_state = _Blocks(config)
    blocks_state.counts.paired = int(t0.size)
    blocks_state.counts.unpaired = n0 - int(t0.size)
    out: list[NormBlock] = []
    if t0.size:
        index = np.floor(t0 / config.block_s).astype(np.int64)
        starts = np.flatnonzero(np.concatenate([[True], index[1:] != index[:-1]]))
        sums = np.add.reduceat(rows, starts, axis=0)
        counts = np.diff(np.append(starts, t0.size))
        # The last block is still open, as the streaming path leaves it.
        for j in range(starts.size - 1):
            block = blocks_state.close(int(index[starts[j]]), int(counts[j]), sums[j])
            if block is not None:
                out.append(block)
    acc = blocks_state.accel
    return NormTrace(
        tuple(out),
        acc.h,
        blocks_state.counts.paired,
        blocks_state.counts.unpaired,
        acc.tested * config.block_s,
        acc.mdf(),
        blocks_state.gyro.mdf(),
        acc.theta[:3].copy(),
        acc.cov[:3, :3].copy(),
        tuple(a for b in out for a in b.alarms),
    )


def cross_imu_norm_sessions(
    imu0: ImuSession, imu1: ImuSession, config: NormCheckConfig = NormCheckConfig()
) -> NormTrace:
    """:func:`cross_imu_norm_batch` of two IMUs' sessions (both triads needed)."""
    a0, g0, a1, g1 = imu0.accel_mps2, imu0.gyro_rps, imu1.accel_mps2, imu1.gyro_rps
    if a0 is None or g0 is None or a1 is None or g1 is None:
        raise ValueError("the cross-IMU norm check needs both triads of both IMUs")
    return cross_imu_norm_batch(imu0.t_s, a0, g0, imu1.t_s, a1, g1, config)
