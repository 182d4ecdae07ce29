"""Options the SLAM-and-range filters share (``msf-ekf``, ``ukf003``): one definition of the
option group, with the same keys in each filter's ``--config`` table."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class SlamRangeOptions:
    """SLAM, rangefinder and initial-uncertainty options of a filter with SLAM and range updates.

    Attributes:
        slam_position_sigma_m: SLAM position noise per pose [m]; the filters use ``s * sigma`` in
            SLAM units (a monocular SLAM's noise is geometric, so it scales with the map).
        slam_rotation_sigma: SLAM orientation noise per pose [rad].
        use_slam_rotation: also fuse the SLAM camera orientation.
        use_range: fuse the rangefinder when the flight has one.
        range_sigma: rangefinder noise [m].
        range_max_tilt_rad: no range update above this tilt [rad].
        initial_scale: initial ``s`` (SLAM units per metre); None: the filter's closed-form fit
            from the first seconds of SLAM and IMU (its module docstring).
        initial_scale_rel_sigma: initial relative standard deviation of ``s``; None: a multiple
            of the closed-form fit's standard error, at least the filter's
            ``MIN_SCALE_REL_SIGMA`` (30 % with ``initial_scale`` given).
        initial_velocity_sigma [m/s], initial_bias_sigma_gyro [rad/s],
            initial_bias_sigma_accel [m/s^2]: initial standard deviations.
        scale_walk: random walk of ``s`` [relative / sqrt(s)].
        gate: Mahalanobis gating of every update.
        slam_reset_s: when every SLAM pose has been gated for this long [s], the filter has
            diverged (a corrupted IMU sample, an IMU or SLAM gap): the next gated pose
            re-initialises the vehicle's position, velocity and attitude from the SLAM (counted
            in ``gating_resets``, said as a warning), as ``ekf004``'s ``slam_reset_s`` does.
    """

    slam_position_sigma_m: float = 0.015
    slam_rotation_sigma: float = 0.01
    use_slam_rotation: bool = True
    use_range: bool = True
    range_sigma: float = 0.03
    range_max_tilt_rad: float = float(np.deg2rad(35.0))
    initial_scale: float | None = None
    initial_scale_rel_sigma: float | None = None
    initial_velocity_sigma: float = 0.5
    initial_bias_sigma_gyro: float = 0.01
    initial_bias_sigma_accel: float = 0.2
    scale_walk: float = 1e-3
    gate: bool = True
    slam_reset_s: float = 1.0

    def check(self) -> None:
        """Raise ``ValueError`` naming the first invalid option (the sign rules of
        :func:`fgnav.config.option_value_problem` apply before)."""
        if self.initial_scale is not None and not self.initial_scale > 0:
            raise ValueError(
                f"{type(self).__name__}.initial_scale={self.initial_scale!r}: expected > 0 "
                "(SLAM units per metre) or unset (the closed-form fit)"
            )
