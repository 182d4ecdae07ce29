"""Is the accelerometer's horizontal specific force usable for the rotor-drag model?

The drag model (``factors/accel_drag.py``) reads the keyframe mean of the horizontal specific
force ``f_xy`` as ``-k u_xy + b`` (``u`` the body velocity). On many small quadrotors the
horizontal channels are dominated by rotor vibration: on the Crazyflie flow-deck flights of
``../shared/data/real/crazyflie_util_flowdeck`` (README: measured facts) their keyframe means
wander by 1-5 m/s^2 in flight, offsets that are absent on the ground, while drag there is about
0.2 m/s^2; a linear drag fit on the Vicon velocity explains < 2 % of their variance. Such an
accelerometer makes a drag factor (and the horizontal part of the IMU prediction) wrong, not
merely noisy.

:func:`check_horizontal_accel` compares the **scatter the drag model cannot explain** with **what
drag could explain**:

1. Fit ``f_a = -k_a u_a + b_a`` per horizontal axis ``a`` by least squares over the keyframes,
   ``k_a`` clipped to ``[0, k_max]`` (a negative or huge drag coefficient explains nothing
   physical), ``b_a`` the mean of ``f_a + k_a u_a`` (accelerometer bias).
2. ``residual`` = RMS over keyframes and axes of ``f - (-k u + b)`` [m/s^2], minus (in quadrature)
   the white accelerometer noise of a keyframe mean (``white_sigma``, from the noise density).
3. ``signal`` = ``k_max`` times the RMS horizontal body speed [m/s^2] (the largest drag signal a
   plausible coefficient gives at this flight's speeds), at least ``signal_floor``.
4. ``ratio = residual / signal``. Decisions:

   - ``ratio > unusable_ratio``: **unusable**: the drag factor stays out; an IMU prediction
     without SLAM may then use the thrust axis only (``GraphOptions.accel_horizontal``).
     With SLAM the measured prediction stays: the check cannot tell an accelerometer dominated
     by vibration (the Crazyflie's 1-3 m/s^2) from a drag model that does not fit (wind; a
     hexacopter whose thrust is off body z), and SLAM positions observe what a wrong horizontal
     force does to velocity and tilt. Measured 2026-12-07, push engine / batch: simulated
     hover (60 s, gusts; ratio 1.2-1.5, residual 0.08 m/s^2) thrust-only 3.68 cm and SLAM scale
     +50 %, measured 1.94 cm and +0.5 % (batch, 30 s: 6.43 cm, +527 % against 0.76 cm,
     +1.3 %); EuRoC MH_01 in a FLU body (ratio 3.4-4.4, the Firefly carried and tilted on the
     floor) 0.312 / 0.153 m against 0.045 / 0.028 m.
   - ``weigh_ratio < ratio <= unusable_ratio``: **noisy**: drag stays in with its noise floor
     raised to ``residual`` (it weighs itself by its own misfit).
   - else **usable**.

Measured (keyframes at 20 Hz whose mean specific force is within 60 deg of body +z and above
g / 2; true body velocities): simulated two-turns, flowdeck, figure8, circle, rectangle (seed 1):
ratio 0.01-0.03; the seven Crazyflie flights: 3.2-10 (residual 1.5-3 m/s^2 against at most
0.3-0.5 m/s^2 of drag). The batch graph runs it on its velocity hint (flow dead reckoning or SLAM
initial values, 0.5 s moving average), the push engine on its own states (first on 0.5 s, then
every 5 keyframes). Tests: ``tests/solvers/test_accel_check.py``,
``tests/solvers/test_crazyflie_real.py``.

Not a test of the vertical channel (height comes from the rangefinder on these vehicles), nor of
the gyro.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

#: Largest plausible linear drag coefficient [1/s] (multirotors: 0.1-0.6; DESIGN.md 4.1: k = 0.4
#: tilts the specific force by 9 deg at 4 m/s).
K_MAX = 0.6
#: Smallest drag signal the ratio is taken against [m/s^2] (a hover: any scatter above this
#: counts against the accelerometer).
SIGNAL_FLOOR = 0.05
UNUSABLE_RATIO = 1.0
WEIGH_RATIO = 0.25
#: Fewest keyframes for a decision.
MIN_KEYFRAMES = 20


@dataclass(frozen=True)
class AccelLimits:
    """The check's limits (module docstring): ``k_max`` largest plausible drag coefficient
    [1/s], ``signal_floor`` smallest drag signal [m/s^2], ``unusable_ratio`` and
    ``weigh_ratio`` the decision thresholds on ``ratio``, ``min_keyframes`` fewest keyframes
    for a decision."""

    k_max: float = K_MAX
    signal_floor: float = SIGNAL_FLOOR
    unusable_ratio: float = UNUSABLE_RATIO
    weigh_ratio: float = WEIGH_RATIO
    min_keyframes: int = MIN_KEYFRAMES


@dataclass(frozen=True)
class AccelCheck:
    """Outcome of :func:`check_horizontal_accel`.

    Attributes:
        decision: ``"usable"``, ``"noisy"``, ``"unusable"`` or ``"undecided"`` (too few keyframes).
        ratio: unexplained scatter over the drag signal a plausible coefficient could give.
        residual: RMS [m/s^2] of the horizontal specific force about its best drag fit (white
            noise of the keyframe means removed).
        signal: ``k_max`` x RMS horizontal body speed [m/s^2] (at least the floor).
        k: fitted drag coefficients per axis [1/s] (clipped to ``[0, k_max]``).
        bias: fitted offsets per axis [m/s^2].
        rms_f: RMS horizontal specific force [m/s^2].
        rms_u: RMS horizontal body speed [m/s].
        n: keyframes used.
        k_max: the largest plausible drag coefficient the check allowed [1/s] (``AccelLimits``).
    """

    decision: str
    ratio: float
    residual: float
    signal: float
    k: tuple[float, float]
    bias: tuple[float, float]
    rms_f: float
    rms_u: float
    n: int
    k_max: float = K_MAX

    @property
    def drag_on(self) -> bool:
        """The drag factor may be used (usable or noisy; undecided counts as usable)."""
        return self.decision != "unusable"

    def line(self) -> str:
        """One line stating the decision and its figures."""
        what = {
            "usable": "drag on",
            "noisy": f"drag on, noise floor raised to {self.residual:.2f} m/s^2",
            "unusable": "drag off (accelerometer unusable for drag)",
            "undecided": "drag on (too few keyframes to check)",
        }[self.decision]
        return (
            f"{what}: horizontal specific force scatter about its best drag fit "
            f"{self.residual:.2f} m/s^2 vs at most {self.signal:.2f} m/s^2 drag could explain "
            f"(k <= {self.k_max:g} 1/s at {self.rms_u:.2f} m/s RMS): ratio {self.ratio:.2f} "
            f"(fit k {self.k[0]:.2f}, {self.k[1]:.2f} 1/s, offsets {self.bias[0]:+.2f}, "
            f"{self.bias[1]:+.2f} m/s^2; {self.n} keyframes)"
        )

    def as_dict(self) -> dict:
        return {**asdict(self), "line": self.line()}

    @classmethod
    def undecided(cls, n: int) -> AccelCheck:
        """The outcome with too few keyframes (``n`` of them): no figures."""
        nan2 = (math.nan, math.nan)
        return cls("undecided", math.nan, math.nan, math.nan, nan2, nan2, math.nan, math.nan, n)


def check_horizontal_accel(
    f_xy: np.ndarray,
    u_xy: np.ndarray,
    white_sigma: float = 0.0,
    limits: AccelLimits = AccelLimits(),
) -> AccelCheck:
    """Decide whether the horizontal specific force can feed the drag model (module docstring).

    Args:
        f_xy: (N, 2) keyframe means of the horizontal specific force (body x, y) [m/s^2].
        u_xy: (N, 2) horizontal body velocity at those keyframes [m/s] (an estimate: initial
            values, flow dead reckoning, or the online smoother's states).
        white_sigma: white-noise standard deviation of one keyframe mean [m/s^2].
        limits: the check's limits (:class:`AccelLimits`).
    """
    f = np.asarray(f_xy, float).reshape(-1, 2)
    u = np.asarray(u_xy, float).reshape(-1, 2)
    ok = np.all(np.isfinite(f), axis=1) & np.all(np.isfinite(u), axis=1)
    f, u = f[ok], u[ok]
    n = len(f)
    if n < limits.min_keyframes:
        return AccelCheck.undecided(n)
    k = np.zeros(2)
    b = np.zeros(2)
    for a in range(2):
        uc = u[:, a] - u[:, a].mean()
        fc = f[:, a] - f[:, a].mean()
        den = float(uc @ uc)
        k[a] = float(np.clip(-(fc @ uc) / den, 0.0, limits.k_max)) if den > 1e-12 else 0.0
        b[a] = float(np.mean(f[:, a] + k[a] * u[:, a]))
    res = f + k * u - b
    res_ms = float(np.mean(np.sum(res**2, axis=1)))
    rms_u = math.sqrt(float(np.mean(np.sum(u**2, axis=1))))
    rms_f = math.sqrt(float(np.mean(np.sum(f**2, axis=1))))
    return _verdict(res_ms, rms_u, rms_f, k, b, n, white_sigma, limits)


def _verdict(res_ms, rms_u, rms_f, k, b, n, white_sigma, limits: AccelLimits) -> AccelCheck:
    """The check's figures and decision from the drag fit's mean squared residual [m^2/s^4] and
    the RMS velocity and specific force (module docstring)."""
    residual = math.sqrt(max(res_ms - 2.0 * white_sigma**2, 0.0))
    signal = max(limits.k_max * rms_u, limits.signal_floor)
    ratio = residual / signal
    if ratio > limits.unusable_ratio:
        decision = "unusable"
    elif ratio > limits.weigh_ratio:
        decision = "noisy"
    else:
        decision = "usable"
    return AccelCheck(
        decision=decision,
        ratio=ratio,
        residual=residual,
        signal=signal,
        k=(float(k[0]), float(k[1])),
        bias=(float(b[0]), float(b[1])),
        rms_f=rms_f,
        rms_u=rms_u,
        n=n,
        k_max=float(limits.k_max),
    )


#: A row value above this (specific force [m/s^2], speed [m/s]) is no measurement: left out
#: like a non-finite one.
ROW_MAX = 1e6


class RunningAccelCheck:
    """:func:`check_horizontal_accel` over the last ``capacity`` keyframe rows, kept as running
    sums (the push engine runs the check every few keyframes on a sliding window: the sums make
    each decision O(1) instead of a pass over the window). Row: ``(f_x, f_y, u_x, u_y,
    white_sigma)``; the white sigma of the check is the RMS of the (finite) rows' (as the push
    engine gave it). Rows with a non-finite value are kept in the window but left out, as
    :func:`check_horizontal_accel` leaves them out. The sums are recomputed from the rows every
    ``capacity`` additions (no drift of the add-and-subtract). Same decisions and figures as
    :func:`check_horizontal_accel` on the window's rows to rounding (about 1e-12 relative;
    ``tests/solvers/test_accel_check.py``)."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        self._rows = np.zeros((self.capacity, 5))
        self._ok = np.zeros(self.capacity, bool)
        self._n = 0  # rows in the window
        self._i = 0  # next slot
        self._adds = 0
        self._ref: list[float] | None = None  # the shift of the sums (f_x, f_y, u_x, u_y)
        self._clear_sums()

    def _clear_sums(self) -> None:
        self.n_ok = 0
        self.s_f = [0.0, 0.0]
        self.s_u = [0.0, 0.0]
        self.s_ff = [0.0, 0.0]
        self.s_uu = [0.0, 0.0]
        self.s_fu = [0.0, 0.0]
        self.s_w2 = 0.0

    def _account(self, row, sign: float) -> None:
        fx, fy, ux, uy, ws = row
        ref = self._ref
        self.n_ok += int(sign)
        # The two axes written out (the same operations in the same order as a loop over
        # them; this runs twice per keyframe).
        f, u = fx - ref[0], ux - ref[2]
        s_f, s_u, s_ff, s_uu, s_fu = self.s_f, self.s_u, self.s_ff, self.s_uu, self.s_fu
        s_f[0] += sign * f
        s_u[0] += sign * u
        s_ff[0] += sign * f * f
        s_uu[0] += sign * u * u
        s_fu[0] += sign * f * u
        f, u = fy - ref[1], uy - ref[3]
        s_f[1] += sign * f
        s_u[1] += sign * u
        s_ff[1] += sign * f * f
        s_uu[1] += sign * u * u
        s_fu[1] += sign * f * u
        self.s_w2 += sign * ws * ws

    def _reseed(self) -> None:
        """Sums from the rows, about their mean (shifted sums: no cancellation of large
        means against small scatter)."""
        ok = np.flatnonzero(self._ok[: self._n])
        self._clear_sums()
        self._ref = self._rows[ok, :4].mean(axis=0).tolist() if len(ok) else [0.0] * 4
        for j in ok:
            self._account(self._rows[j].tolist(), 1.0)

    def __len__(self) -> int:
        return self._n

    def append(self, row) -> None:
        """One keyframe's ``(f_x, f_y, u_x, u_y, white_sigma)``; the oldest row leaves when
        the window is full."""
        row = [float(x) for x in row]
        if len(row) != 5:
            raise ValueError(f"RunningAccelCheck.append: 5 values, got {len(row)}")
        i = self._i
        if self._n == self.capacity and self._ok[i]:
            self._account(self._rows[i].tolist(), -1.0)
        # (a diverged estimate's velocities of 1e120 m/s overflowed the squares in check())
        ok = all(math.isfinite(x) and abs(x) < ROW_MAX for x in row)
        if ok and self._ref is None:
            self._ref = row[:4]
        self._rows[i] = row
        self._ok[i] = ok
        if ok:
            self._account(row, 1.0)
        self._i = (i + 1) % self.capacity
        self._n = min(self._n + 1, self.capacity)
        self._adds += 1
        if self._adds % self.capacity == 0:
            self._reseed()

    def rows(self) -> np.ndarray:
        """The window's rows, oldest first."""
        if self._n < self.capacity:
            return self._rows[: self._n].copy()
        return np.roll(self._rows, -self._i, axis=0)

    def check(self, limits: AccelLimits = AccelLimits()) -> AccelCheck:
        """:func:`check_horizontal_accel` on the window (white sigma: the RMS of the rows')."""
        n = self.n_ok
        if n < limits.min_keyframes:
            return AccelCheck.undecided(n)
        white_sigma = math.sqrt(max(self.s_w2, 0.0) / n)
        ref = self._ref
        k = [0.0, 0.0]
        b = [0.0, 0.0]
        res_sum = 0.0
        f2 = u2 = 0.0  # sums of the raw f^2 and u^2 over both axes
        for a in range(2):
            mu_f, mu_u = self.s_f[a] / n, self.s_u[a] / n  # shifted means
            den = self.s_uu[a] - n * mu_u * mu_u  # sum of (u - mean u)^2
            cross = self.s_fu[a] - n * mu_u * mu_f  # sum of (f - mean f)(u - mean u)
            ff = self.s_ff[a] - n * mu_f * mu_f
            k[a] = min(max(-cross / den, 0.0), limits.k_max) if den > 1e-12 else 0.0
            b[a] = (mu_f + ref[a]) + k[a] * (mu_u + ref[2 + a])
            res_sum += ff + 2.0 * k[a] * cross + k[a] * k[a] * max(den, 0.0)
            # sum x^2 = sum (x - r)^2 + 2 r sum (x - r) + n r^2
            f2 += self.s_ff[a] + 2.0 * ref[a] * self.s_f[a] + n * ref[a] ** 2
            u2 += self.s_uu[a] + 2.0 * ref[2 + a] * self.s_u[a] + n * ref[2 + a] ** 2
        return _verdict(
            max(res_sum, 0.0) / n,
            math.sqrt(max(u2, 0.0) / n),
            math.sqrt(max(f2, 0.0) / n),
            k,
            b,
            n,
            white_sigma,
            limits,
        )
