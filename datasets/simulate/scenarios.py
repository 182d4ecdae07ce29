"""Reference trajectories of the simulated flights (world frame, z up, metres, radians).

Each scenario is a smooth position ``world_p_ref(t)`` and yaw ``yaw_ref(t)`` reference plus the
defaults it needs (duration, wind, SLAM model). Velocity and acceleration of the reference are
central differences of the analytic position (step ``_DIFF_STEP_S``), which the vehicle's
controller uses as feed-forward. The vehicle's true trajectory is what the controller flies, not
the reference itself.

Scenarios (sources: the seed papers in ../shared/seeds/):

- ``circle`` (seed 000, sec. 4): circle of radius 2 m at 1.5 m, 1 m/s, initial body velocity
  ``u = 0.2, v = -0.2`` m/s; SLAM with per-axis scale ``kx = 0.3, ky = 0.2`` (``kz`` 0.25,
  configurable) and the camera at the body origin, i.e. ``slam_t_cam = diag(K) world_t_body``.
- ``two-turns`` (seed 002, sec. IV-A): hover at 3.5 m, then climb to 4 m while making two turns of
  1.1 m radius (path ~13.8 m), hover again; yaw turns with the path.
- ``hover`` (seed 004, position-hold test): 60 s hold at 1.5 m in gusty wind.
- ``vertical`` (seed 004, scale estimation with vertical motion): up/down between 1 m and 3 m.
- ``rectangle`` (seed 004, scale estimation with horizontal motion): 4 m x 3 m rectangle at 1.5 m,
  two laps, stop at every corner.
- ``figure8`` (seed 003: speeds up to 4 m/s): figure eight of 10 m x 6 m at 3 m, up to ~3.9 m/s
  and ~17 degrees of tilt.
- ``flowdeck`` (issue 17: a Crazyflie with a flow deck, as the UTIL flights): 2 s hover at 0.5 m,
  then a Lissajous curve in a 3 m x 2.4 m box with the height between 0.4 m and 1.3 m, speeds up
  to ~1.4 m/s, yaw swinging +-0.5 rad; the only scenario with the optical-flow stream on by
  default (``SimOptions.flow_rate_hz``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: Step of the central differences that give the reference velocity and acceleration [s].
_DIFF_STEP_S = 1e-3


def smoothstep5(x: np.ndarray) -> np.ndarray:
    """Quintic smoothstep ``6x^5 - 15x^4 + 10x^3`` on [0, 1], clamped outside (C2 continuous)."""
    x = np.clip(np.asarray(x, float), 0.0, 1.0)
    return x**3 * (10.0 - 15.0 * x + 6.0 * x * x)


def ramped_time(t: np.ndarray, ramp_s: float) -> np.ndarray:
    """Integral of ``smoothstep5(t / ramp_s)``: a clock that starts at rate 0 and reaches rate 1
    after ``ramp_s`` seconds (so a motion ``f(ramped_time(t))`` starts from rest smoothly)."""
    x = np.asarray(t, float) / ramp_s
    xc = np.clip(x, 0.0, 1.0)
    inside = xc**6 - 3.0 * xc**5 + 2.5 * xc**4
    return ramp_s * np.where(x <= 1.0, inside, 0.5 + (x - 1.0))


@dataclass(frozen=True)
class Reference:
    """A reference sampled at times ``t`` (world frame).

    Attributes:
        t: (N,) time [s].
        world_p: (N, 3) position [m]; world_v (N, 3) [m/s]; world_a (N, 3) [m/s^2].
        yaw: (N,) yaw [rad] (unwrapped); yaw_rate (N,) [rad/s].
    """

    t: np.ndarray
    world_p: np.ndarray
    world_v: np.ndarray
    world_a: np.ndarray
    yaw: np.ndarray
    yaw_rate: np.ndarray


@dataclass(frozen=True)
class Scenario:
    """One simulated flight plan and its defaults.

    Attributes:
        name: scenario name (key of ``SCENARIOS``).
        description: one line, with the source paper.
        duration: default duration [s].
        position: ``t (N,) -> world_p (N, 3)`` [m], smooth (C2).
        yaw: ``t (N,) -> yaw (N,)`` [rad], smooth, unwrapped.
        body_v0: initial velocity in body [m/s] replacing the reference's, or None.
        wind_mean: mean wind in world [m/s].
        gust_std: standard deviation of the gusts (per horizontal axis) [m/s].
        slam_axis_scale: per-axis SLAM scale ``(kx, ky, kz)`` of seed 000, or None for a
            similarity (one scale, rotation and translation).
        body_t_cam: camera lever arm in body [m] replacing the default, or None.
        flow_rate_hz: default rate of the optical-flow stream [Hz] (0: no flow sensor).
    """

    name: str
    description: str
    duration: float
    position: Callable[[np.ndarray], np.ndarray]
    yaw: Callable[[np.ndarray], np.ndarray]
    body_v0: tuple[float, float, float] | None = None
    wind_mean: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gust_std: float = 0.0
    slam_axis_scale: tuple[float, float, float] | None = None
    body_t_cam: tuple[float, float, float] | None = None
    flow_rate_hz: float = 0.0

    def reference(self, t: np.ndarray) -> Reference:
        """Sample the reference and its derivatives at times ``t`` [s]."""
        t = np.asarray(t, float)
        h = _DIFF_STEP_S
        p0, pp, pm = self.position(t), self.position(t + h), self.position(t - h)
        y0, yp, ym = self.yaw(t), self.yaw(t + h), self.yaw(t - h)
        return Reference(
            t=t,
            world_p=p0,
            world_v=(pp - pm) / (2.0 * h),
            world_a=(pp - 2.0 * p0 + pm) / (h * h),
            yaw=y0,
            yaw_rate=(yp - ym) / (2.0 * h),
        )


def _stack(x, y, z) -> np.ndarray:
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1).astype(float)


# ---------------------------------------------------------------------------------------------
# circle (seed 000)
# ---------------------------------------------------------------------------------------------
CIRCLE_RADIUS_M = 2.0
CIRCLE_ALTITUDE_M = 1.5
CIRCLE_RATE_RAD_S = 0.5
CIRCLE_RAMP_S = 3.0


def _circle_position(t):
    th = -0.5 * math.pi + CIRCLE_RATE_RAD_S * ramped_time(t, CIRCLE_RAMP_S)
    return _stack(CIRCLE_RADIUS_M * np.cos(th), CIRCLE_RADIUS_M * np.sin(th), CIRCLE_ALTITUDE_M)


# ---------------------------------------------------------------------------------------------
# two-turns (seed 002): 2 turns of radius R -> 4 pi R = 13.8 m
# ---------------------------------------------------------------------------------------------
TWO_TURNS_RADIUS_M = 1.1
TWO_TURNS_Z0_M = 3.5
TWO_TURNS_Z1_M = 4.0
TWO_TURNS_HOVER_S = 3.0
TWO_TURNS_MOVE_S = 22.0


def _two_turns_progress(t):
    return smoothstep5((np.asarray(t, float) - TWO_TURNS_HOVER_S) / TWO_TURNS_MOVE_S)


def _two_turns_angle(t):
    return 4.0 * math.pi * _two_turns_progress(t)


def _two_turns_position(t):
    s = _two_turns_progress(t)
    th = 4.0 * math.pi * s
    r = TWO_TURNS_RADIUS_M
    z = TWO_TURNS_Z0_M + (TWO_TURNS_Z1_M - TWO_TURNS_Z0_M) * s
    return _stack(r * np.sin(th), r - r * np.cos(th), z)


# ---------------------------------------------------------------------------------------------
# hover, vertical, rectangle (seed 004)
# ---------------------------------------------------------------------------------------------
HOVER_ALTITUDE_M = 1.5
VERTICAL_LOW_M = 1.0
VERTICAL_HIGH_M = 3.0
VERTICAL_PERIOD_S = 8.0
VERTICAL_RAMP_S = 2.0
RECT_CORNERS_M = ((0.0, 0.0), (4.0, 0.0), (4.0, 3.0), (0.0, 3.0))
RECT_ALTITUDE_M = 1.5
RECT_EDGE_S = 4.0
RECT_PAUSE_S = 1.0


def _vertical_position(t):
    amp = 0.5 * (VERTICAL_HIGH_M - VERTICAL_LOW_M)
    tau = ramped_time(t, VERTICAL_RAMP_S)
    z = VERTICAL_LOW_M + amp * (1.0 - np.cos(2.0 * math.pi * tau / VERTICAL_PERIOD_S))
    return _stack(0.0, 0.0, z)


def _rectangle_position(t):
    t = np.asarray(t, float)
    seg = RECT_EDGE_S + RECT_PAUSE_S
    lap = seg * len(RECT_CORNERS_M)
    tl = np.mod(np.maximum(t, 0.0), lap)
    i = np.minimum((tl // seg).astype(int), len(RECT_CORNERS_M) - 1)
    s = smoothstep5((tl - i * seg - RECT_PAUSE_S) / RECT_EDGE_S)
    c = np.asarray(RECT_CORNERS_M)
    a, b = c[i], c[(i + 1) % len(c)]
    xy = a + (b - a) * s[..., None]
    return _stack(xy[..., 0], xy[..., 1], RECT_ALTITUDE_M)


# ---------------------------------------------------------------------------------------------
# figure8 (seed 003: up to 4 m/s)
# ---------------------------------------------------------------------------------------------
FIG8_A_M = 5.0
FIG8_B_M = 3.0
FIG8_ALTITUDE_M = 3.0
FIG8_RATE_RAD_S = 0.5
FIG8_RAMP_S = 4.0
FIG8_YAW_AMP_RAD = 0.3


def _figure8_angle(t):
    return FIG8_RATE_RAD_S * ramped_time(t, FIG8_RAMP_S)


def _figure8_position(t):
    th = _figure8_angle(t)
    return _stack(FIG8_A_M * np.sin(th), FIG8_B_M * np.sin(2.0 * th), FIG8_ALTITUDE_M)


# ---------------------------------------------------------------------------------------------
# flowdeck (issue 17: Crazyflie with a flow deck, low over the floor)
# ---------------------------------------------------------------------------------------------
FLOWDECK_HOVER_S = 2.0
FLOWDECK_RAMP_S = 3.0
FLOWDECK_A_M = 1.5
FLOWDECK_B_M = 1.2
FLOWDECK_RATE_RAD_S = 0.6
FLOWDECK_Z0_M = 0.85
FLOWDECK_DZ_M = 0.45
FLOWDECK_HOVER_Z_M = 0.5
FLOWDECK_YAW_AMP_RAD = 0.5


def _flowdeck_clock(t):
    return FLOWDECK_RATE_RAD_S * ramped_time(
        np.maximum(np.asarray(t, float) - FLOWDECK_HOVER_S, 0.0), FLOWDECK_RAMP_S
    )


def _flowdeck_position(t):
    th = _flowdeck_clock(t)
    # Height: from the hover height towards the mean over the ramp, then a slow swing.
    blend = smoothstep5((np.asarray(t, float) - FLOWDECK_HOVER_S) / FLOWDECK_RAMP_S)
    z = (1.0 - blend) * FLOWDECK_HOVER_Z_M + blend * (
        FLOWDECK_Z0_M - FLOWDECK_DZ_M * np.cos(0.37 * th)
    )
    return _stack(FLOWDECK_A_M * np.sin(th), FLOWDECK_B_M * np.sin(1.5 * th), z)


def _flowdeck_yaw(t):
    return FLOWDECK_YAW_AMP_RAD * np.sin(0.5 * _flowdeck_clock(t))


def _zero_yaw(t):
    return np.zeros_like(np.asarray(t, float))


SCENARIO_TABLE: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario(
            "circle",
            "seed 000: circle r=2 m at 1.5 m, 1 m/s, u0=0.2 v0=-0.2 m/s, per-axis SLAM scale",
            40.0,
            _circle_position,
            _zero_yaw,
            body_v0=(0.2, -0.2, 0.0),
            slam_axis_scale=(0.3, 0.2, 0.25),
            body_t_cam=(0.0, 0.0, 0.0),
        ),
        Scenario(
            "two-turns",
            "seed 002: hover at 3.5 m, two turns of 1.1 m radius climbing to 4 m (13.8 m path)",
            TWO_TURNS_MOVE_S + 2.0 * TWO_TURNS_HOVER_S,
            _two_turns_position,
            _two_turns_angle,
        ),
        Scenario(
            "hover",
            "seed 004: 60 s position hold at 1.5 m in gusty wind",
            60.0,
            lambda t: _stack(0.0, 0.0, np.full_like(np.asarray(t, float), HOVER_ALTITUDE_M)),
            _zero_yaw,
            wind_mean=(1.0, -0.5, 0.0),
            gust_std=0.8,
        ),
        Scenario(
            "vertical",
            "seed 004: vertical-only motion between 1 m and 3 m (scale estimation)",
            30.0,
            _vertical_position,
            _zero_yaw,
        ),
        Scenario(
            "rectangle",
            "seed 004: horizontal 4 m x 3 m rectangle at 1.5 m, two laps (scale estimation)",
            2.0 * len(RECT_CORNERS_M) * (RECT_EDGE_S + RECT_PAUSE_S) + RECT_PAUSE_S,
            _rectangle_position,
            _zero_yaw,
        ),
        Scenario(
            "figure8",
            "seed 003: figure eight 10 m x 6 m at 3 m, up to ~3.9 m/s",
            40.0,
            _figure8_position,
            lambda t: FIG8_YAW_AMP_RAD * np.sin(_figure8_angle(t)),
        ),
        Scenario(
            "flowdeck",
            "issue 17: Crazyflie-like flight with a flow deck, 0.4-1.3 m over the floor in a "
            "3 x 2.4 m box, up to ~1.4 m/s; optical flow on (100 Hz)",
            40.0,
            _flowdeck_position,
            _flowdeck_yaw,
            flow_rate_hz=100.0,
        ),
    )
}

#: Names of the available scenarios.
SCENARIOS: tuple[str, ...] = tuple(SCENARIO_TABLE)
