"""Graph builder: turns a :class:`~fgnav.datasets.types.Flight` into GTSAM factors on keyframes.

Variables (``fgnav.keys``, ../shared/DESIGN.md section 3): per keyframe k ``X(k)`` Pose3
``world_T_body``, ``V(k)`` ``world_v_body`` [m/s], ``B(k)`` IMU bias; slow variables with random
walks between segments: ``S(j)`` SLAM alignment (``Similarity3`` ``slam_T_world``, a new chain per
SLAM session, or for seed 000's per-axis model a Vector6 ``[kx, ky, kz, ox, oy, oz]``: per-axis
scale and SLAM-origin offset, one chain per session), ``D(j)`` drag coefficient
(Vector1 ``k`` or Vector2 ``kx, ky``) [1/s], ``G(j)`` ground height (Vector1) [m].

The builder emits the graph per keyframe so that the same code feeds the batch solver (everything
at once) and the fixed-lag smoother (streamed in arrival order):

- :meth:`GraphBuilder.keyframe_chunk` gives, for keyframe k, the IMU factor from k-1, the new
  state values, the creation of slow variables whose segment starts at k (random-walk factor from
  the previous segment), the gauge/front-end priors, and the key timestamps.
- :meth:`GraphBuilder.measurement_factors` gives the factors of the measurements associated with
  keyframe k, each with its arrival time (a SLAM pose arrives at ``t + latency``).

Keyframes: fixed rate (``keyframe_hz``) anchored at the SLAM frame times and, with homography
factors (``fgnav.solvers.vision``), at the image times of the camera frames used, so that neither
needs a time shift; rangefinder and yaw readings are interpolated linearly to the keyframe time
from the two samples around it; the drag factor uses the mean accelerometer over the keyframe
interval. Everything not used is counted in :attr:`GraphBuilder.skipped` (and reported in
``Estimate.info``).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any

import gtsam
import numpy as np

from fgnav.datasets.errors import FgnavError, FlightDataError
from fgnav.datasets.geometry import GRAVITY, slerp_rotations, wrap_angle
from fgnav.datasets.range_limits import RANGE_LIMIT_TAGS
from fgnav.datasets.slam_gyro import META_KEY as SLAM_CHECK_META_KEY
from fgnav.datasets.slam_gyro import (
    apply_slam_check,
    check_extrinsic_mode,
    check_mirror_mode,
    check_modes,
)
from fgnav.datasets.types import Calibration, Flight, ImuSeries
from fgnav.factors.accel_drag import make_accel_drag_factor, mean_accel_noise
from fgnav.factors.slam_scale import (
    make_slam_axis_offset_factor,
    make_slam_position_factor,
    make_slam_rotation_factor,
)
from fgnav.factors.tilted_range import make_range_factor
from fgnav.factors.yaw import make_yaw_factor
from fgnav.keys import B, D, G, S, V, X
from fgnav.solvers.measurements import (
    MIN_ANCHOR_GAP_PERIODS,
    SlamAlignmentInit,
    associate,
    attitude_from_slam,
    attitude_track,
    fit_axis_scale,
    gyro_bias_from_slam,
    init_slam_alignment,
    mean_in_windows,
    omega_from_attitude,
    world_specific_accel,
)

if TYPE_CHECKING:
    from fgnav.solvers.flow import FlowFactorOptions
    from fgnav.solvers.vision import HomographyFactorOptions

log = logging.getLogger(__name__)

#: Drag coefficient used when no closed-form initial value is possible [1/s]; seed 000's
#: simulation uses kx = 0.3, ky = 0.2 and the simulator's default is (0.38, 0.42).
DEFAULT_DRAG_K = 0.3
#: Origin sigma [m] of the link from a SLAM session's last alignment to the session the health
#: check split off at a SLAM jump (the jump's size is unknown; rotation and scale walk on).
SLAM_JUMP_ORIGIN_SIGMA_M = 10.0
#: Relative sigma of the weak prior on a SLAM session's initial scale (closed-form fit).
WEAK_SCALE_PRIOR_REL = 0.5
#: ``flight.meta`` key of the terrain steps (times [s]) that cut the ground-height walk.
GROUND_STEPS_META_KEY = "ground_steps"
#: Index stride of the ground-height segments of successive ground epochs (terrain steps).
GROUND_EPOCH_STRIDE = 1_000_000
#: Integration noise of the preintegration (GTSAM examples use 1e-8) [m^2/s^2... per s].
PREINTEGRATION_INTEGRATION_COV = 1e-8
#: Initial-bias covariance used by GTSAM's CombinedImuFactor examples (biasAccOmegaInt).
BIAS_ACC_OMEGA_INIT_COV = 1e-5


ACCEL_HORIZONTAL_MODES = ("auto", "measured", "thrust-only")
"""Values of ``GraphOptions.accel_horizontal``."""
#: Keyframes whose mean specific force is within this angle of body +z (and above half of g)
#: enter the accelerometer check (in flight the Crazyflie's vibration offsets alone tilt it by up
#: to 30 deg; the drag factor's own gate is ``drag_max_tilt_deg``).
ACCEL_CHECK_MAX_TILT_DEG = 60.0
#: Centred moving average [s] of the velocity hint before the accelerometer check: velocities
#: differenced from 20 Hz SLAM positions or read from one flow window are noisy (0.1-0.2 m/s),
#: which would attenuate the fitted drag (errors in the regressor); drag is a slow signal.
ACCEL_CHECK_SMOOTH_S = 0.5


class ObservabilityError(FgnavError, ValueError):
    """The chosen sensor subset leaves part of the state unobservable."""


KEYFRAME_HZ_MAX = 1000.0
"""Highest keyframe rate the options take [Hz]: no IMU of the supported logs is faster (the
Crazyflie's about 1 kHz); 1e9 ran without end."""


@dataclass
class GraphOptions:
    """Options of the graph builder (sensor switches, noise, robust kernels, gating, priors).

    Noise values are one standard deviation. A TOML ``[graph]`` table fills it by name.

    Attributes:
        keyframe_hz: nominal keyframe rate [Hz] (keyframes also sit on SLAM frame times).
        gravity: magnitude of gravity [m/s^2].
        use_gyro: integrate the gyro; False replaces it by rates differentiated from the attitude
            stream (seed 000's sensor set: accelerometer + attitude + SLAM).
        use_slam, use_drag, use_range, use_yaw: measurement switches.
        use_homography: downward-camera homography factors (``fgnav.solvers.vision``); None
            ("auto"): on when the flight has images with intrinsics, a rangefinder that the graph
            uses (``use_range``) and an IMU, else off. The builder's ``options`` hold the
            resolved value.
        homography: options of the homography factors and their VO front-end
            (``vision.HomographyFactorOptions``, or a TOML table of them; None: defaults).
        use_flow: downward optical-flow factors (``fgnav.solvers.flow``: the readings of each
            keyframe window summed into one factor on ``X, V, G``); None ("auto"): on when the
            flight has a flow stream and a rangefinder the graph uses (``use_range``), else off.
            True without a rangefinder raises ``ObservabilityError`` (flow measures ``v / h``).
            The builder's ``options`` hold the resolved value.
        flow: options of the flow factors (``flow.FlowFactorOptions``, or a TOML table of them;
            None: defaults).
        use_frontend_priors: add the front-end priors given to the builder.
        slam_model: ``"sim3"`` (``Similarity3`` alignment per session) or ``"axis"`` (seed 000's
            per-axis scale, SLAM axes = world axes, with an estimated SLAM-origin offset so the
            world origin stays at the first keyframe); ``"auto"`` picks ``"axis"`` when the
            flight's metadata says the SLAM stream is per-axis.
        slam_sigma_m: SLAM position noise [m] (converted to SLAM units with the initial scale).
        use_slam_rotation: also use the SLAM orientation (fixes the yaw of the SLAM frame). None
            (default): on in the push-API online smoother (measured there: EuRoC MH_01 causal
            ATE 9.0 -> 7.1 cm, simulated two-turns 2.8 -> 2.5 cm, rectangle 3.8 -> 2.6 cm,
            figure8 5.8 -> 5.4 cm; used only once the SLAM-vs-gyro check has decided the
            file's rotation convention), off in the batch smoother and the prepared runner.
        slam_rotation: convention of the SLAM file's orientations (``datasets.slam_gyro``):
            ``"auto"`` (decided from the gyro; when the inverse fits and the stated one does not,
            one warning says so and the inverse is used), ``"as-is"`` or ``"inverse"``. A
            manifest's ``[slam] slam_rotation`` wins. The check also names a wrong ``body_T_cam``
            rotation.
        slam_extrinsic: a ``body_T_cam`` rotation the SLAM-vs-gyro check names wrong (more than
            5 deg from the one the gyro fits, fitting 1.5x worse): ``"auto"`` uses the fitted
            rotation (one warning says so; the push engine from its causal decision on),
            ``"as-is"`` keeps it (named only). EuRoC MH_01 with an identity rotation given:
            the fitted one is 0.55 deg from the true one.
        slam_mirror: a mirrored (left-handed) SLAM frame, tested when the SLAM-vs-gyro check
            names the inverse convention or a wrong ``body_T_cam`` rotation
            (:func:`fgnav.datasets.slam_gyro.check_mirror`): ``"auto"`` un-mirrors it when the
            flipped axis is identified and leaves the SLAM out when not (one line names
            ``slam-mirrored``); ``"off"`` does not test.
        slam_time_offset: SLAM clock offset, estimated from the gyro: ``"report"`` (logged only),
            ``"apply"`` (added to the SLAM times) or a number of seconds to add (not estimated).
            A manifest's ``[slam] slam_time_offset`` wins.
        slam_rot_sigma: SLAM orientation noise [rad].
        slam_segment_s: length of a SLAM-alignment segment [s] (random walk between segments:
            monocular scale drifts). Segments are counted from the session's first pose; a
            segment without a pose (a SLAM pause) has no variable, and the next segment's
            random walk runs from the last segment that has one over the whole elapsed time
            (sigma grows with the square root of the gap), so a pause of any length is no
            error and a long pause widens the walk by itself.
        slam_scale_rw: relative scale random walk [1/sqrt(s)].
        slam_rot_rw: rotation random walk of the SLAM frame [rad/sqrt(s)].
        slam_trans_rw_m: origin random walk of the SLAM frame [m/sqrt(s)]. 5e-3 since
            2026-12-04 (1e-2 before; ORB-SLAM3's map on MH_01 drifts by about 7e-3): batch ATE
            EuRoC MH_01 3.29 -> 2.79 cm, V1_02 ORB-SLAM2 / ORB-SLAM3 2.39 / 2.29 -> 1.88 /
            1.78 cm, simulated (seed 1, camera) two-turns / circle / rectangle / figure8
            0.30 / 0.26 / 0.27 / 0.32 -> 0.28 / 0.25 / 0.27 / 0.30 cm (7e-3: 3.04 / 2.03 /
            1.97 cm on the real flights). The push engine keeps 1e-2
            (``FixedLagOptions.slam_trans_rw_m``).
        drag_per_axis: estimate ``kx, ky`` instead of one ``k``.
        drag_model_sigma: drag-model error floor of the mean accelerometer [m/s^2].
        drag_sigma_from_data: raise that floor to the flight's measured scatter of the keyframe
            means (robust standard deviation of their deviation from a 0.5 s running median: rotor
            vibration and turbulence of a real vehicle; the simulator has none).
        drag_max_tilt_deg: skip the drag factor at keyframes whose mean specific force is more
            than this from body +z (not thrust-borne: carried, standing on the ground, touching
            down), counted as ``drag:not-thrust-borne``. Linear drag at 4 m/s and k = 0.4 1/s
            tilts it by 9 deg.
        drag_robust: robust kernel on the drag factor (as ``robust``).
        drag_k_init: initial drag k [1/s] (None: closed form from the initial velocities).
        drag_prior_sigma: prior on the first drag variable [1/s].
        drag_segment_s: drag segment length [s] (None: one variable for the flight).
        drag_rw: drag random walk [1/s/sqrt(s)].
        range_sigma: rangefinder noise [m]; range_max_tilt_deg: gate on the beam tilt [deg].
        ground_segment_s: ground-height segment length [s]; ground_rw: terrain walk [m/sqrt(s)]
            of the ground height under the rangefinder (it also absorbs a slow range bias). The
            default suits a flat floor or smooth ground (the simulator's, the Crazyflie flights'
            lab floor: 0.01 let the ground height wander by up to 4 cm over a 45 s flight, height
            RMSE 0.73-1.28 cm in batch against 0.61-0.72 cm at 0.002); raise it (0.01-0.05) over
            rough or sloping terrain.
        ground_prior_sigma: prior on the first ground height around its initial value [m].
        yaw_sigma: yaw noise [rad].
        robust: ``"huber"``, ``"cauchy"`` or ``"none"`` (range, SLAM, yaw, homography).
        robust_k: kernel width in whitened units (Huber 1.345: 95 % efficiency).
        interp_max_gap_s: largest gap between the two samples a range/yaw reading is interpolated
            from [s].
        slam_tolerance_s: largest time between a SLAM pose and its keyframe [s].
        prior_position_sigma [m], prior_yaw_sigma [rad], prior_rollpitch_sigma [rad],
        prior_velocity_sigma [m/s], prior_accel_bias_sigma [m/s^2], prior_gyro_bias_sigma
            [rad/s]: gauge and first-state priors (``prior_gyro_bias_sigma`` None: the
            calibration's ``imu_noise.gyro_bias_sigma``).
        initial_yaw: yaw of the first pose when neither attitude nor yaw streams exist [rad].
        gyro_bias_from_slam: initialise the gyro bias (and centre its prior) from SLAM orientation
            increments (see ``measurements.gyro_bias_from_slam``; uses the whole flight).
        drag_thrust_check: switch the drag factor off (logged, reason in ``Estimate.info`` under
            ``drag_disabled``) when the mean specific force of the flight is not within
            ``drag_thrust_max_angle_deg`` of body +z: the drag model assumes the thrust along body
            z (FLU), which an IMU frame used as body (EuRoC: x up) violates. False forces drag
            whenever ``use_drag`` is on.
        drag_thrust_max_angle_deg: largest angle between the mean normalised specific force and
            body +z for the drag model [deg].
        drag_accel_check: check that the accelerometer's horizontal channels can carry the
            drag model (``fgnav.solvers.accel_check``: the scatter of the keyframe-mean
            horizontal specific force about its best drag fit against what drag could explain at
            the flight's speeds, from the flow or SLAM initial velocities); "unusable": the drag
            factor stays out (``Estimate.info["drag_disabled"]``), "noisy": its noise floor is
            raised to that scatter. The decision is logged in one line and kept in
            ``info["accel_check"]``.
        accel_horizontal: horizontal specific force in the IMU prediction: ``"measured"`` (the
            accelerometer), ``"thrust-only"`` (body x, y replaced by 0: thrust along body z,
            rotor drag neglected, as the Crazyflie firmware's in-flight prediction) or ``"auto"``
            (thrust-only when the accelerometer check finds the horizontal channels unusable and
            no SLAM is in use: :mod:`fgnav.solvers.accel_check`).
        thrust_only_sigma: the neglected horizontal specific force of the thrust-only prediction
            [m/s^2] (rotor drag: about 0.2-0.4 m/s^2 RMS on the Crazyflie flights, from Vicon):
            white noise of that size per keyframe mean plus an accelerometer-bias random walk on
            body x, y reaching it in ``thrust_only_tau_s``.
        thrust_only_tau_s: time over which the neglected force changes [s] (0.5 s: the drag
            model's misfit that the bias walk carries turns with the body velocity, about 1 rad/s
            on traj3's circles). With 3 s the push engine's velocity overshot in steady fast
            flight (traj3 at 1.25 m/s: +8 % along the track, the filter's bias lagging the
            misfit; the batch, smoothing both sides, unaffected); the linear flow scale's 8 %
            under-read at those rates had hidden it (traj3 fixed-lag 0.065 m/s linear, 0.095
            with ``flow_rate_gain``). 3 s -> 0.5 s on the seven Crazyflie flights: fixed-lag
            velocity RMSE 0.057-0.096 -> 0.052-0.078 m/s (traj3 0.095 -> 0.068), batch
            0.028-0.048 -> 0.027-0.049 m/s (2026-12-02, cf17c).
        thrust_only_drag_sigma: drag dynamics of the thrust-only prediction [m/s^2]: the body x,
            y accelerometer bias (the negated specific force the prediction integrates) is tied
            to the rotor drag ``k u_xy`` at every keyframe by the drag factor with a zero
            measurement and this noise (drag variables ``D`` estimated from the flow/SLAM
            velocities), so the prediction decelerates as drag does and the tilt is observed
            through the velocity, as in the Crazyflie firmware's model; None: off (the bias walk
            alone absorbs the drag). Crazyflie flights (with the calibration's gyro-bias prior):
            velocity RMSE batch 0.045-0.104 -> 0.032-0.086, fixed-lag 0.082-0.116 -> 0.056-0.090
            m/s; simulated flowdeck (forced thrust-only) batch 0.033 -> 0.024, push 0.094 ->
            0.050 m/s. Independent of ``use_drag`` (that is the factor on the measured force).
        thrust_only_gyro_z_sigma: with a thrust-only IMU prediction and no yaw source (no yaw
            stream, no SLAM), the prior sigma of the gyro's body-z (yaw-rate) bias [rad/s], when
            below the calibration's (None: the calibration's). The yaw-rate bias is then seen only
            through the ``omega x u`` term of the horizontal body dynamics (``b_z |u|``: 2 mm/s^2
            at 2 mrad/s and 1 m/s), about 100x below the misfit of the thrust-only drag model
            (0.1-0.3 m/s^2); estimated, it followed that misfit: on the seven Crazyflie flights
            it moved to -3.5..+1.5 mrad/s, on 5 of 7 against the in-flight bias measured with
            Vicon, and the end yaw error grew (batch traj5 5.9 -> 9.8 deg, traj1 4.3 -> 6.5
            deg). Held at its prior mean (the firmware subtracts the bias measured at rest), the
            yaw is the integrated gyro's.
        contact_height_m: ground contact: when the rangefinder puts its sensor within this
            height of the ground on the two readings around a keyframe (a vehicle standing on
            the floor before take-off and after landing: the flow deck's time-of-flight reads
            12-25 mm there, below its 40 mm limit, and the flow is gated), the keyframe gets a
            zero-velocity factor (``contact_velocity_sigma``, robust), counted as ``contact``.
            None: off.
        contact_velocity_sigma: noise of the ground-contact zero velocity [m/s] (covers the
            first centimetres of a take-off).
        contact_range_sigma: at a ground-contact keyframe the range sensor also stands on the
            ground: a range factor of 0 m with this noise [m] (the vehicle's resting height; the
            flow deck's model height on the floor is -1 cm, against Vicon); None: none.
    """

    keyframe_hz: float = 20.0
    gravity: float = GRAVITY
    use_gyro: bool = True
    use_slam: bool = True
    use_drag: bool = True
    use_range: bool = True
    use_yaw: bool = True
    use_homography: bool | None = None
    homography: HomographyFactorOptions | dict[str, Any] | None = None
    use_flow: bool | None = None
    flow: FlowFactorOptions | dict[str, Any] | None = None
    use_frontend_priors: bool = True
    slam_model: str = "auto"
    slam_sigma_m: float = 0.01
    use_slam_rotation: bool | None = None
    slam_rotation: str = "auto"
    slam_time_offset: str | float = "report"
    slam_extrinsic: str = "auto"
    slam_mirror: str = "auto"
    slam_rot_sigma: float = 0.005
    slam_segment_s: float = 2.0
    slam_scale_rw: float = 1e-3
    slam_rot_rw: float = 2e-4
    slam_trans_rw_m: float = 5e-3
    drag_per_axis: bool = True
    drag_model_sigma: float = 0.05
    drag_sigma_from_data: bool = True
    drag_max_tilt_deg: float = 15.0
    drag_robust: bool = True
    drag_k_init: float | None = None
    drag_prior_sigma: float = 0.2
    drag_segment_s: float | None = None
    drag_rw: float = 1e-3
    range_sigma: float = 0.02
    range_max_tilt_deg: float = 35.0
    ground_segment_s: float = 5.0
    ground_rw: float = 0.002
    ground_prior_sigma: float = 1.0
    yaw_sigma: float = 0.03
    robust: str = "huber"
    robust_k: float = 1.345
    interp_max_gap_s: float = 0.15
    slam_tolerance_s: float = 0.005
    prior_position_sigma: float = 1e-3
    prior_yaw_sigma: float = 1e-3
    prior_rollpitch_sigma: float = 0.05
    prior_velocity_sigma: float = 1.0
    prior_accel_bias_sigma: float = 0.1
    prior_gyro_bias_sigma: float | None = None
    initial_yaw: float = 0.0
    gyro_bias_from_slam: bool = True
    drag_thrust_check: bool = True
    drag_thrust_max_angle_deg: float = 30.0
    drag_accel_check: bool = True
    accel_horizontal: str = "auto"
    thrust_only_sigma: float = 0.3
    thrust_only_tau_s: float = 0.5
    thrust_only_drag_sigma: float | None = 0.1
    thrust_only_gyro_z_sigma: float | None = 1e-4
    contact_height_m: float | None = 0.03
    contact_velocity_sigma: float = 0.1
    contact_range_sigma: float | None = 0.015

    def check(self) -> GraphOptions:
        if self.robust not in ("huber", "cauchy", "none"):
            raise FlightDataError(
                f"GraphOptions.robust={self.robust!r}: expected huber, cauchy or none"
            )
        if self.slam_model not in ("auto", "sim3", "axis"):
            raise FlightDataError(
                f"GraphOptions.slam_model={self.slam_model!r}: expected auto, sim3 or axis"
            )
        if isinstance(self.slam_rotation, bool):
            raise FlightDataError(
                f"GraphOptions.slam_rotation={self.slam_rotation!r}: it is now the SLAM file's "
                "rotation convention (auto, as-is, inverse); the SLAM orientation factor is "
                "use_slam_rotation"
            )
        check_modes(self.slam_rotation, self.slam_time_offset, "GraphOptions")
        check_extrinsic_mode(self.slam_extrinsic, "GraphOptions")
        check_mirror_mode(self.slam_mirror, "GraphOptions")
        if not 0 < self.keyframe_hz <= KEYFRAME_HZ_MAX:
            raise FlightDataError(
                f"GraphOptions.keyframe_hz={self.keyframe_hz}: expected > 0 and <= "
                f"{KEYFRAME_HZ_MAX:g} (a keyframe needs IMU samples between it and the next)"
            )
        if self.accel_horizontal not in ACCEL_HORIZONTAL_MODES:
            raise FlightDataError(
                f"GraphOptions.accel_horizontal={self.accel_horizontal!r}: expected one of "
                + ", ".join(ACCEL_HORIZONTAL_MODES)
            )
        if self.thrust_only_gyro_z_sigma is not None and not self.thrust_only_gyro_z_sigma > 0:
            raise FlightDataError(
                f"GraphOptions.thrust_only_gyro_z_sigma={self.thrust_only_gyro_z_sigma}: "
                "expected > 0 or None"
            )
        if not (self.thrust_only_sigma > 0 and self.thrust_only_tau_s > 0):
            raise FlightDataError(
                f"GraphOptions.thrust_only_sigma={self.thrust_only_sigma}, thrust_only_tau_s="
                f"{self.thrust_only_tau_s}: expected > 0"
            )
        # The [graph.flow] and [graph.homography] tables (keys, types, values), before any flight
        # is read (they were a TypeError or a cv2.error at the first factor).
        if self.flow is not None:
            from fgnav.solvers.flow import flow_options

            flow_options(self.flow)
        if self.homography is not None:
            from fgnav.solvers.vision import homography_options

            homography_options(self.homography)
        return self


@dataclass
class InitialGuess:
    """Initial values of the per-keyframe states and of the slow variables."""

    world_R_body: np.ndarray
    world_t_body: np.ndarray
    world_v_body: np.ndarray
    slam: dict[int, SlamAlignmentInit] = field(default_factory=dict)
    axis_scale: dict[int, np.ndarray] = field(default_factory=dict)  # per session [k, o]
    drag_k: np.ndarray | None = None
    ground_height: float | None = None


@dataclass
class KeyframeChunk:
    """What keyframe k adds to the graph (see module docstring)."""

    index: int
    t: float
    factors: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    timestamps: dict[int, float]


@dataclass
class MeasurementFactor:
    """One measurement factor attached to keyframe ``keyframe``, available at ``t_arrival``."""

    t_arrival: float
    keyframe: int
    kind: str
    factor: gtsam.NonlinearFactor
    keys: tuple[int, ...]


def _isotropic(dim: int, sigma: float) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Isotropic.Sigma(dim, float(sigma))


def declared_slam_model(flight: Flight) -> str:
    """The SLAM model the flight's SLAM input declares (``flight.meta["slam_model"]``, a fact of
    the input like its frame: ``"axis"`` for seed 000's per-axis SLAM, which the simulator's seed
    000 scenarios write), else ``"sim3"``. Never read from ground truth."""
    meta = flight.meta if isinstance(flight.meta, dict) else {}
    model = meta.get("slam_model", "sim3")
    if model not in ("sim3", "axis"):
        raise FlightDataError(f"{flight.name}: meta slam_model={model!r}: expected sim3 or axis")
    return model


def choose_slam_model(flight: Flight, slam_model: str) -> str:
    """``GraphOptions.slam_model`` resolved: ``"auto"`` is the flight's declared model
    (:func:`declared_slam_model`)."""
    return declared_slam_model(flight) if slam_model == "auto" else slam_model


def robust_noise(base: gtsam.noiseModel.Base, o: GraphOptions) -> gtsam.noiseModel.Base:
    """``base`` wrapped in the graph's robust kernel (``o.robust``: huber, cauchy or none, with
    ``o.robust_k``)."""
    if o.robust == "huber":
        return gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(o.robust_k), base
        )
    if o.robust == "cauchy":
        return gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Cauchy.Create(o.robust_k), base
        )
    return base


def pim_params(
    noise: Any,
    gravity: float,
    gyro_noise_floor: float = 0.0,
    accel_nd: np.ndarray | None = None,
    accel_rw: np.ndarray | None = None,
) -> gtsam.PreintegrationCombinedParams:
    """IMU preintegration parameters (world z up) from the calibration's noise densities and
    random walks (``ImuNoise``); ``gyro_noise_floor``: least gyro noise density; ``accel_nd``,
    ``accel_rw``: per-axis accelerometer noise density and bias walk (e.g. the thrust-only
    prediction's, :func:`thrust_only_noise`) instead of the calibration's."""
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(gravity)
    gyro_nd = max(noise.gyro_noise_density, gyro_noise_floor)
    nd = np.full(3, noise.accel_noise_density) if accel_nd is None else np.asarray(accel_nd)
    rw = np.full(3, noise.accel_random_walk) if accel_rw is None else np.asarray(accel_rw)
    p.setGyroscopeCovariance(gyro_nd**2 * np.eye(3))
    p.setAccelerometerCovariance(np.diag(nd**2))
    p.setIntegrationCovariance(PREINTEGRATION_INTEGRATION_COV * np.eye(3))
    p.setBiasOmegaCovariance(noise.gyro_random_walk**2 * np.eye(3))
    p.setBiasAccCovariance(np.diag(rw**2))
    return p


def saturated_pim_params(
    base: gtsam.PreintegrationCombinedParams,
    body_omega: np.ndarray,
    body_accel: np.ndarray,
    flags: np.ndarray,
    dt: np.ndarray,
    sigma_rel: float,
) -> gtsam.PreintegrationCombinedParams:
    """Preintegration parameters of a keyframe interval holding saturated IMU samples (issue 18).

    A sample pinned at its rail (``flags``: :data:`fgnav.health.SAT_GYRO_BITS`,
    :data:`~fgnav.health.SAT_ACCEL_BITS`) under-reports the true value by an unknown amount,
    taken as ``sigma_rel`` x the rail (the sample's ``|value|``) and the same over the interval
    (a manoeuvre beyond the rail lasts longer than a sample): the preintegrated rotation
    (velocity) of that axis gets the variance ``e^2`` with ``e = sigma_rel sum |value_i| dt_i``
    over its pinned samples, added to the white-noise density as ``e^2 / T`` over the interval's
    length ``T`` (GTSAM integrates a density ``Q`` to the variance ``Q T``). The interval's IMU
    factor is thereby down-weighted on the pinned axes only; the others keep the calibration's
    noise. A dead accelerometer's samples (:data:`~fgnav.health.DEAD_ACCEL_BIT`, reading
    exactly 0) miss about ``g`` on every axis: ``e = sigma_rel g sum dt_i``.

    Args:
        base: the interval's parameters without saturation (not changed).
        body_omega, body_accel: (n, 3) the samples integrated over the interval.
        flags: (n,) their saturation bits.
        dt: (n,) the time each sample holds within the interval [s].
        sigma_rel: the excess's sigma relative to the rail.

    Returns:
        ``base`` itself when no sample is flagged, else a copy with the inflated covariances.
    """
    flags = np.asarray(flags)
    if not flags.any():
        return base
    from fgnav.health import DEAD_ACCEL_BIT, SAT_ACCEL_BITS, SAT_GYRO_BITS

    dt = np.asarray(dt, float)
    span = float(dt.sum())
    if span <= 0:
        return base
    extra = []
    for bits, v in ((SAT_GYRO_BITS, body_omega), (SAT_ACCEL_BITS, body_accel)):
        v = np.abs(np.asarray(v, float))
        e = [
            sigma_rel * float((v[(flags & b) != 0, i] * dt[(flags & b) != 0]).sum())
            for i, b in enumerate(bits)
        ]
        extra.append(np.square(e) / span)
    dead = (flags & DEAD_ACCEL_BIT) != 0
    if dead.any():
        # A dead accelerometer (reading exactly 0): the specific force it missed is of the
        # order of gravity on every axis, over the dead samples' time.
        e = sigma_rel * abs(float(base.n_gravity[2])) * float(dt[dead].sum())
        extra[1] = extra[1] + e * e / span
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(-float(base.n_gravity[2]))
    p.deserialize(base.serialize())
    p.setGyroscopeCovariance(base.getGyroscopeCovariance() + np.diag(extra[0]))
    p.setAccelerometerCovariance(base.getAccelerometerCovariance() + np.diag(extra[1]))
    return p


class GraphBuilder:
    """Factor graph of one flight, built keyframe by keyframe.

    Args:
        flight: the flight (``check()`` is called).
        options: builder options.
        priors: optional front-end priors (``fgnav.frontends.priors.FrontendPriors``) with
            ``velocity`` and ``slam_scale`` attributes, used when ``use_frontend_priors``.
    """

    def __init__(self, flight: Flight, options: GraphOptions | None = None, priors: Any = None):
        self.options = (options or GraphOptions()).check()
        if self.options.use_slam:
            # SLAM rotation convention and clock offset against the gyro (whole flight).
            flight = apply_slam_check(
                flight,
                self.options.slam_rotation,
                self.options.slam_time_offset,
                self.options.slam_extrinsic,
                self.options.slam_mirror,
            )
        self.flight = flight.check()
        self.priors = priors if self.options.use_frontend_priors else None
        self.skipped: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        o = self.options
        if flight.imu is None:
            raise ObservabilityError(
                f"{flight.name}: no IMU stream; the graph needs the IMU between keyframes"
            )
        self._row_index: dict[str, dict[int, list[int]]] = {}
        self._noise_cache: dict[tuple[int, float, bool], gtsam.noiseModel.Base] = {}
        self._drag_noise: dict[int, gtsam.noiseModel.Base] = {}
        self.body_T_cam = np.asarray(flight.calib.body_T_cam, float)
        self.body_T_range = np.asarray(flight.calib.body_T_range, float)
        self._accel_sigma: float | None = None
        self.slam_model = self._choose_slam_model()
        self.drag_disabled = self._drag_model_invalid()
        if self.drag_disabled is not None:
            log.warning("%s: drag factor off: %s", flight.name, self.drag_disabled)
            self.options = o = replace(o, use_drag=False)
        from fgnav.solvers.flow import resolve_use_flow
        from fgnav.solvers.vision import resolve_use_homography

        #: why a flow stream (flow left to "auto") has no height source, else None (health:
        #: flow-no-height)
        self.flow_no_height: str | None = None
        if (
            o.use_flow is None
            and flight.flow is not None
            and len(flight.flow)
            and not (o.use_range and flight.range is not None)
        ):
            self.flow_no_height = (
                "no rangefinder stream" if flight.range is None else "use_range is off"
            )
            log.warning(
                "%s: an optical-flow stream and no height source (%s): the flow measures "
                "velocity over height and gives no metric velocity without one; it is not used, "
                "the horizontal velocity and the height are dead-reckoned (they drift)",
                flight.name,
                self.flow_no_height,
            )
        o = self.options = replace(
            o,
            use_homography=resolve_use_homography(flight, o.use_homography, o.use_range),
            use_flow=resolve_use_flow(flight, o.use_flow, o.use_range),
        )
        check_observability(flight, o, self.slam_model)
        self.vision = None
        if o.use_homography:
            from fgnav.solvers.vision import HomographyFactors, homography_options

            self.vision = HomographyFactors(flight, homography_options(o.homography), self._skip)
        self.imu = self._imu_used()
        slam_t = flight.slam.t if (o.use_slam and flight.slam is not None) else None
        t0, t1 = float(self.imu.t[0]), float(self.imu.t[-1])
        if slam_t is not None:
            flight.require_overlap("imu", "slam")
        if slam_t is not None and o.slam_model != "axis":
            # Start at the first SLAM frame: before it nothing but the IMU constrains the state.
            t0 = max(t0, float(slam_t[0]))
        from fgnav.solvers.measurements import keyframe_times

        anchors = slam_t
        if self.vision is not None:
            # SLAM frames first: images too close to a SLAM frame would take its keyframe.
            images_t = self.vision.anchor_times(slam_t, MIN_ANCHOR_GAP_PERIODS / o.keyframe_hz)
            anchors = np.union1d(images_t, [] if slam_t is None else slam_t)
        self.t_kf = keyframe_times(t0, t1, o.keyframe_hz, anchors)
        self.K = len(self.t_kf)
        self.pim_params = self._pim_params()
        # IMU samples pinned at a rail (the imu-saturation detector, sample by sample): their
        # keyframe intervals' IMU factors are down-weighted (saturated_pim_params).
        from fgnav.health import HealthOptions, imu_saturation_flags

        self._sat_sigma_rel = HealthOptions().saturation_sigma_rel
        self.imu_saturation = imu_saturation_flags(
            self.imu.t, self.imu.body_omega, self.imu.body_accel
        )
        if self.imu_saturation.any():
            n_flagged = np.r_[0, np.cumsum(self.imu_saturation != 0)]
            i0 = np.maximum(np.searchsorted(self.imu.t, self.t_kf[:-1], side="right") - 1, 0)
            i1 = np.searchsorted(self.imu.t, self.t_kf[1:], side="left")
            n_sat = int((n_flagged[np.maximum(i1, i0)] > n_flagged[i0]).sum())
            self._count("imu-saturated-intervals", n_sat)
            log.warning(
                "%s: IMU factors of %d keyframe intervals down-weighted (samples pinned at a rail)",
                flight.name,
                n_sat,
            )
        body_T_cam = np.asarray(flight.calib.body_T_cam, float)
        self.gyro_bias0 = np.zeros(3)
        if self.use_slam and o.gyro_bias_from_slam:
            self.gyro_bias0 = gyro_bias_from_slam(self.imu, flight.slam, body_T_cam)
            log.info(
                "initial gyro bias from SLAM orientations: %s rad/s", np.round(self.gyro_bias0, 4)
            )
        if flight.attitude is None and self.use_slam and self.slam_model == "sim3":
            self.R_imu = attitude_from_slam(
                self.imu, flight.slam, body_T_cam, self.imu.t, self._initial_yaw()
            )
        else:
            self.R_imu = attitude_track(self.imu, flight.attitude, self.imu.t, self._initial_yaw())
        self.R_kf = slerp_rotations(self.imu.t, self.R_imu, self.t_kf)
        self._prepare_slam()
        self._prepare_range()
        self._prepare_contact()
        self._prepare_yaw()
        self._prepare_drag()
        self.ground_segment = self._ground_segments() if self.use_range else None
        if self.vision is not None:
            self.vision.associate(self.t_kf)
        self.flow = None
        if o.use_flow:
            from fgnav.solvers.flow import FlowFactors, flow_options

            self.flow = FlowFactors(flight, flow_options(o.flow), self._skip)
            self.flow.associate(self.t_kf, self.R_kf)
        self._flow_velocity: np.ndarray | None = None
        self.accel_check = None
        self.thrust_only = o.accel_horizontal == "thrust-only"
        if (o.use_drag and o.drag_accel_check) or o.accel_horizontal == "auto":
            self._decide_accel()
        if self.thrust_only:
            a = np.array(self.imu.body_accel, float)
            a[:, :2] = 0.0
            self.imu = ImuSeries(self.imu.t, self.imu.body_omega, a)
            self.pim_params = self._pim_params()
        angle, _ = self._thrust_angle()
        self.drag_dynamics = bool(
            self.thrust_only
            and o.thrust_only_drag_sigma is not None
            and angle is not None
            and angle <= o.drag_thrust_max_angle_deg
        )
        self.drag_segment = self._segments(o.drag_segment_s) if self.drag_vars else None

    # ------------------------------------------------------------------------------------------
    # Setup
    # ------------------------------------------------------------------------------------------

    def _drag_model_invalid(self) -> str | None:
        """Why the rotor-drag model does not apply to this flight's body frame (None: it does, or
        the check is off): the mean normalised specific force must be near body +z."""
        o = self.options
        if not (o.use_drag and o.drag_thrust_check):
            return None
        angle, mean_dir = self._thrust_angle()
        if angle is None or angle <= o.drag_thrust_max_angle_deg:
            return None
        return (
            f"the mean specific force is {angle:.0f} deg from body +z (direction "
            f"{np.round(mean_dir, 2).tolist()}); the drag model needs the thrust along body z "
            "(FLU body frame); set graph.drag_thrust_check = false to force it"
        )

    def _thrust_angle(self) -> tuple[float | None, np.ndarray]:
        """Angle [deg] between the flight's mean normalised specific force and body +z, and that
        direction (None when no sample is thrust-borne)."""
        a = np.asarray(self.flight.imu.body_accel, float)
        norm = np.linalg.norm(a, axis=1)
        ok = norm > 0.5 * self.options.gravity
        if not ok.any():
            return None, np.zeros(3)
        mean_dir = (a[ok] / norm[ok, None]).mean(axis=0)
        mean_dir /= max(float(np.linalg.norm(mean_dir)), 1e-12)
        return math.degrees(math.acos(float(np.clip(mean_dir[2], -1.0, 1.0)))), mean_dir

    def _choose_slam_model(self) -> str:
        return choose_slam_model(self.flight, self.options.slam_model)

    def _skip(self, reason: str, n: int = 1) -> None:
        if n:
            self.skipped[reason] = self.skipped.get(reason, 0) + int(n)

    def _count(self, kind: str, n: int = 1) -> None:
        self.counts[kind] = self.counts.get(kind, 0) + int(n)

    def _initial_yaw(self) -> float:
        f = self.flight
        if f.yaw is not None and self.options.use_yaw:
            return float(f.yaw.yaw[0])
        return self.options.initial_yaw

    def _imu_used(self) -> ImuSeries:
        f = self.flight
        if self.options.use_gyro:
            return f.imu
        if f.attitude is None:
            raise ObservabilityError(
                f"{f.name}: use_gyro=false needs an attitude stream to replace the gyro"
            )
        return ImuSeries(f.imu.t, omega_from_attitude(f.attitude, f.imu.t), f.imu.body_accel)

    def _pim_params(self) -> gtsam.PreintegrationCombinedParams:
        n = self.flight.calib.imu_noise
        # Rates differentiated from the attitude stream are much noisier than a gyro.
        floor = 0.0 if self.options.use_gyro else 1e-2
        acc_nd = np.full(3, n.accel_noise_density)
        acc_rw = np.full(3, n.accel_random_walk)
        if getattr(self, "thrust_only", False):
            acc_nd[:2], acc_rw[:2] = thrust_only_noise(
                self.options.thrust_only_sigma,
                self.options.thrust_only_tau_s,
                self.options.keyframe_hz,
                n.accel_noise_density,
                n.accel_random_walk,
            )
        return pim_params(n, self.options.gravity, floor, acc_nd, acc_rw)

    def _kf_half_windows(self) -> np.ndarray:
        """Half-width [s] (K,) of each keyframe's IMU window: half the shorter of its two
        neighbouring intervals (the end keyframes: half their one interval; a lone keyframe:
        half the keyframe period)."""
        period = np.diff(self.t_kf)
        if self.K > 1:
            return 0.5 * np.concatenate(
                [[period[0]], np.minimum(period[1:], period[:-1]), [period[-1]]]
            )
        return np.array([0.5 / self.options.keyframe_hz])

    def _kf_accel_means(self, half: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Mean measured specific force (K, 3) over each keyframe's window (``half``: its
        half-widths, default :meth:`_kf_half_windows`) and the sample counts (K,)."""
        if half is None:
            half = self._kf_half_windows()
        return mean_in_windows(self.imu.t, self.imu.body_accel, self.t_kf, half)

    def _velocity_hint(self) -> np.ndarray | None:
        """(K, 3) body velocity from the flow windows (dead reckoning) or the SLAM initial
        values; None without either."""
        if self.flow is not None:
            if self._flow_velocity is None:
                self._flow_velocity = self.flow.velocity_hint(
                    self.R_kf, self.imu.t, self.imu.body_omega, self.gyro_bias0
                )
            return self._flow_velocity
        if self.use_slam:
            g = self.initial_guess()
            return np.einsum("nji,nj->ni", g.world_R_body, g.world_v_body)
        return None

    def _decide_accel(self) -> None:
        """The accelerometer check (``drag_accel_check``, ``accel_horizontal``): drag off or
        down-weighted, thrust-only prediction; one log line."""
        from fgnav.solvers.accel_check import check_horizontal_accel

        o = self.options
        angle, _ = self._thrust_angle()
        if angle is None or angle > o.drag_thrust_max_angle_deg:
            return  # thrust not along body z: neither model applies (see _drag_model_invalid)
        u = self._velocity_hint()
        if u is None:
            return
        means, counts = self._kf_accel_means()
        norm = np.linalg.norm(means, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_tilt = means[:, 2] / norm
        ok = (
            (counts > 0)
            & (norm > 0.5 * o.gravity)
            & (cos_tilt >= math.cos(math.radians(ACCEL_CHECK_MAX_TILT_DEG)))
        )
        n_med = float(np.median(counts[ok])) if ok.any() else 1.0
        white = self.imu_accel_sigma() / math.sqrt(max(n_med, 1.0))
        u = _moving_average(u[:, :2], max(1, int(round(ACCEL_CHECK_SMOOTH_S * o.keyframe_hz))))
        chk = check_horizontal_accel(means[ok, :2], u[ok], white)
        self.accel_check = chk
        if chk.decision == "undecided":
            return
        if o.accel_horizontal == "auto" and chk.decision == "unusable" and not self.use_slam:
            # (with SLAM the measured prediction stays: module docstring of accel_check)
            self.thrust_only = True
        if o.use_drag and o.drag_accel_check:
            if chk.decision == "unusable":
                self.drag_disabled = "accelerometer check: " + chk.line()
                self.options = replace(self.options, use_drag=False)
            elif chk.decision == "noisy":
                self.drag_sigma = max(self.drag_sigma, chk.residual)
        # A usable accelerometer is the nominal case (INFO); drag off, or on with a raised
        # noise floor, is said as a warning.
        log.log(
            logging.INFO if chk.decision == "usable" else logging.WARNING,
            "%s: %s%s",
            self.flight.name,
            chk.line(),
            "; IMU prediction thrust-only (body x, y specific force 0)" if self.thrust_only else "",
        )

    def _ground_segments(self) -> np.ndarray:
        """Ground-height segment index per keyframe: one per ``ground_segment_s``, counted anew
        (``epoch * GROUND_EPOCH_STRIDE``) after each terrain step the flight declares
        (``flight.meta["ground_steps"]``, times [s]; the batch's health check finds them), where
        the ground's random walk is cut: the first segment of an epoch takes a prior."""
        seg = self._segments(self.options.ground_segment_s)
        steps = np.sort(np.asarray(self.flight.meta.get(GROUND_STEPS_META_KEY, ()), float))
        if steps.size:
            seg = seg + GROUND_EPOCH_STRIDE * np.searchsorted(steps, self.t_kf, side="right")
        self._ground_set = {int(j) for j in seg}
        return seg

    def _segments(self, seg_s: float | None) -> np.ndarray:
        if seg_s is None or seg_s <= 0:
            return np.zeros(self.K, dtype=int)
        return np.floor((self.t_kf - self.t_kf[0]) / seg_s + 1e-9).astype(int)

    @property
    def use_slam(self) -> bool:
        return self.options.use_slam and self.flight.slam is not None

    @property
    def use_range(self) -> bool:
        return self.options.use_range and self.flight.range is not None

    @property
    def use_yaw(self) -> bool:
        return self.options.use_yaw and self.flight.yaw is not None

    @property
    def use_drag(self) -> bool:
        """The drag factor on the measured horizontal specific force."""
        return self.options.use_drag

    @property
    def drag_vars(self) -> bool:
        """Drag variables ``D``: for the drag factor, or for the thrust-only prediction's drag
        dynamics (``thrust_only_drag_sigma``)."""
        return self.options.use_drag or getattr(self, "drag_dynamics", False)

    def _prepare_slam(self) -> None:
        self.slam_assoc = None
        self.slam_sessions: list[int] = []
        self.slam_chain: np.ndarray | None = None
        self.slam_chain_prev: dict[int, tuple[int, int]] = {}
        self.slam_jump_keys: set[int] = set()
        if not self.use_slam:
            return
        slam = self.flight.slam
        a = associate(slam.t, self.t_kf, self.options.slam_tolerance_s, one_per_keyframe=True)
        for k, v in a.skipped.items():
            self._skip(f"slam:{k}", v)
        self.slam_assoc = a
        self.slam_sessions = [int(s) for s in dict.fromkeys(slam.session.tolist())]
        # SLAM alignment variable of each association: session chain and segment within it.
        seg_s = self.options.slam_segment_s
        chain = np.zeros(len(a.meas_index), dtype=int)
        # One chain per session (a map reset declared by the input: a new scale and origin,
        # for seed 000's per-axis model too).
        sess = slam.session[a.meas_index]
        for s in self.slam_sessions:
            m = sess == s
            if not m.any():
                continue
            t_first = slam.t[a.meas_index[m][0]]
            seg = np.floor((slam.t[a.meas_index[m]] - t_first) / seg_s + 1e-9).astype(int)
            chain[m] = seg
        self.slam_chain = chain
        self.slam_latency = slam.latency if slam.latency is not None else np.zeros(len(slam))
        # Variable index per (session, segment): contiguous integers in order of appearance.
        self.slam_var: dict[tuple[int, int], int] = {}
        for i, c in zip(a.meas_index, chain, strict=True):
            key = (int(slam.session[i]), int(c))
            if key not in self.slam_var:
                self.slam_var[key] = len(self.slam_var)
        # Chain predecessor of each segment: the session's previous segment that has a pose
        # (segments without one, SLAM pauses, are skipped), and the segments elapsed since it.
        last: dict[int, tuple[int, int]] = {}
        for (sess, seg), j in sorted(self.slam_var.items()):
            if sess in last:
                seg_prev, j_prev = last[sess]
                self.slam_chain_prev[j] = (j_prev, seg - seg_prev)
            last[sess] = (seg, j)
        # A session the health check split off at a SLAM jump (a relocalisation in the same
        # map: id ``parent + JUMP_SESSION_BASE * n``) continues its parent's chain: its first
        # segment walks from the parent's last one in rotation and scale over the time between
        # them, its origin free (``slam_jump_keys``; the jump is the origin's).
        from fgnav.health import JUMP_SESSION_BASE

        if self.slam_model == "sim3":
            first: dict[int, tuple[int, int]] = {}
            for (sess, seg), j in sorted(self.slam_var.items()):
                first.setdefault(sess, (seg, j))
            for sess, (_seg, j) in first.items():
                parent = sess - JUMP_SESSION_BASE
                if sess < JUMP_SESSION_BASE or parent not in last:
                    continue
                m = slam.session[a.meas_index]
                t_gap = float(slam.t[a.meas_index[m == sess][0]]) - float(
                    slam.t[a.meas_index[m == parent][-1]]
                )
                n_seg = max(1, int(math.ceil(t_gap / seg_s - 1e-9)))
                self.slam_chain_prev[j] = (last[parent][1], n_seg)
                self.slam_jump_keys.add(j)

    def _interp_stream(self, t: np.ndarray, x: np.ndarray, name: str) -> tuple[np.ndarray, ...]:
        """Linear interpolation of a scalar stream to the keyframe times from the two samples
        around each keyframe (gap <= interp_max_gap_s). Returns (keyframes, values, arrival, i0)."""
        j = np.searchsorted(t, self.t_kf, side="left")
        ok = (j > 0) & (j < len(t))
        exact = (j < len(t)) & (np.abs(t[np.minimum(j, len(t) - 1)] - self.t_kf) < 1e-9)
        jj = np.clip(j, 1, len(t) - 1)
        gap = t[jj] - t[jj - 1]
        ok &= gap <= self.options.interp_max_gap_s
        ok |= exact
        kf = np.flatnonzero(ok)
        jj = jj[kf]
        ex = exact[kf]
        i0 = np.where(ex, np.minimum(j[kf], len(t) - 1), jj - 1)
        i1 = np.where(ex, i0, jj)
        w = np.where(ex, 0.0, (self.t_kf[kf] - t[i0]) / np.maximum(t[i1] - t[i0], 1e-12))
        vals = (1 - w) * x[i0] + w * x[i1]
        n_no = self.K - len(kf)
        if n_no:
            self._skip(f"{name}:keyframes-without-bracketing-samples", n_no)
        return kf, vals, t[i1], i0, i1

    def _prepare_range(self) -> None:
        self.range_kf = np.array([], dtype=int)
        if not self.use_range:
            return
        from fgnav.factors.tilted_range import gate_range, range_clamps

        f = self.flight
        rng = f.range
        kf, vals, arr, i0, i1 = self._interp_stream(rng.t, rng.range, "range")
        body_T_range = np.asarray(f.calib.body_T_range, dtype=float)
        keep = []
        max_tilt = math.radians(self.options.range_max_tilt_deg)
        clamps = range_clamps(rng.range, f.calib.range_min)
        for n, k in enumerate(kf):
            ok = True
            for i in (i0[n], i1[n]):
                good, reason = gate_range(
                    float(rng.range[i]),
                    self.R_kf[k],
                    body_T_range,
                    f.calib.range_min,
                    f.calib.range_max,
                    max_tilt,
                    clamps,
                )
                if not good:
                    # (at the sensor's floor or maximum: range:at-min, range:at-max)
                    tag = _reason_tag(reason)
                    self._skip(f"range:{tag}" if tag in RANGE_LIMIT_TAGS else f"range:gated:{tag}")
                    ok = False
                    break
            keep.append(ok)
        keep = np.asarray(keep, dtype=bool)
        self.range_kf, self.range_val, self.range_arrival = kf[keep], vals[keep], arr[keep]
        self._count("range-samples", len(rng))

    def _prepare_contact(self) -> None:
        """Keyframes on the ground (``contact_height_m``): both raw range readings around the
        keyframe put the range sensor that close to the ground (attitude at the keyframe)."""
        self.contact_kf = np.array([], dtype=int)
        self.contact_arrival = np.array([])
        h_max = self.options.contact_height_m
        if not self.use_range or h_max is None:
            return
        rng = self.flight.range
        if len(rng) < 2:
            return
        T = np.asarray(self.flight.calib.body_T_range, float)
        j = np.clip(np.searchsorted(rng.t, self.t_kf, side="left"), 1, len(rng) - 1)
        gap_ok = (rng.t[j] - rng.t[j - 1]) <= self.options.interp_max_gap_s
        cos_beam = -np.einsum("nij,j->ni", self.R_kf, T[:3, 2])[:, 2]
        low = np.ones(self.K, bool)
        for i in (j - 1, j):
            low &= rng.range[i] * cos_beam <= h_max
        inside = (self.t_kf >= rng.t[0]) & (self.t_kf <= rng.t[-1])
        kf = np.flatnonzero(low & gap_ok & inside)
        self.contact_kf = kf
        self.contact_arrival = rng.t[j[kf]]

    def _prepare_yaw(self) -> None:
        self.yaw_kf = np.array([], dtype=int)
        if not self.use_yaw:
            return
        y = self.flight.yaw
        kf, vals, arr, _, _ = self._interp_stream(y.t, np.unwrap(y.yaw), "yaw")
        self.yaw_kf, self.yaw_val, self.yaw_arrival = kf, wrap_angle(vals), arr
        self._count("yaw-samples", len(y))

    def _prepare_drag(self) -> None:
        if not self.use_drag:
            return
        half = self._kf_half_windows()
        o = self.options
        means, counts = self._kf_accel_means(half)
        self.drag_mean = means[:, :2]
        n_none = int((counts == 0).sum())
        self._skip("drag:keyframes-without-imu-samples", n_none)
        # Thrust-borne gate: the mean specific force near body +z.
        norm = np.linalg.norm(means, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            cos_tilt = means[:, 2] / norm
        tilted = (counts > 0) & ~(cos_tilt >= math.cos(math.radians(o.drag_max_tilt_deg)))
        self._skip("drag:not-thrust-borne", int(tilted.sum()))
        counts = np.where(tilted, 0, counts)
        self.drag_count = counts
        self.drag_arrival = self.t_kf + half
        self.drag_sigma = float(o.drag_model_sigma)
        if o.drag_sigma_from_data:
            self.drag_sigma = max(self.drag_sigma, self._drag_scatter(counts > 0))
            self._count("drag-model-sigma-mm/s2", int(round(1000 * self.drag_sigma)))

    def _drag_scatter(self, ok: np.ndarray) -> float:
        """Robust standard deviation [m/s^2] of the keyframe-mean specific force xy about its
        0.5 s running median (both axes pooled), over the keyframes ``ok``; minus the part the
        accelerometer noise density explains."""
        idx = np.flatnonzero(ok)
        if len(idx) < 10:
            return 0.0
        half_n = max(1, int(round(0.25 * self.options.keyframe_hz)))
        x = self.drag_mean[idx]
        pad = np.pad(x, ((half_n, half_n), (0, 0)), mode="edge")
        win = np.lib.stride_tricks.sliding_window_view(pad, 2 * half_n + 1, axis=0)
        dev = x - np.median(win, axis=-1)
        mad = float(np.median(np.abs(dev - np.median(dev, axis=0))))
        scatter = 1.4826 * mad
        n = float(np.median(self.drag_count[idx]))
        white = self.imu_accel_sigma() / math.sqrt(max(n, 1.0))
        return math.sqrt(max(scatter**2 - white**2, 0.0))

    # ------------------------------------------------------------------------------------------
    # Noise models
    # ------------------------------------------------------------------------------------------

    def _noise(self, dim: int, sigma: float, robust: bool = True) -> gtsam.noiseModel.Base:
        """Isotropic noise model (robust per ``options.robust`` when ``robust``), cached: the
        measurement factors of a flight share a few noise models (immutable in GTSAM)."""
        key = (dim, float(sigma), robust)
        model = self._noise_cache.get(key)
        if model is None:
            model = _isotropic(dim, sigma)
            if robust:
                model = self._robust(model)
            self._noise_cache[key] = model
        return model

    def _robust(self, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
        return robust_noise(base, self.options)

    def imu_accel_sigma(self) -> float:
        """Discrete-time standard deviation of one accelerometer sample [m/s^2]."""
        if self._accel_sigma is None:
            rate = self.imu.rate_hz
            self._accel_sigma = self.flight.calib.imu_noise.accel_noise_density * math.sqrt(rate)
        return self._accel_sigma

    # ------------------------------------------------------------------------------------------
    # Initial values
    # ------------------------------------------------------------------------------------------

    def initial_guess(self, t_limit: float | None = None) -> InitialGuess:
        """Initial states at the keyframes (non-causal: uses the whole flight).

        Rotations from the attitude track; positions from the SLAM stream through the closed-form
        alignment of each session (IMU prediction where no SLAM pose exists); velocities from
        central differences of the positions; biases zero; drag k and ground height closed form.
        """
        K = self.K
        pos = np.full((K, 3), np.nan)
        guess = InitialGuess(self.R_kf.copy(), pos, np.zeros((K, 3)))
        f = self.flight
        body_t_cam = np.asarray(f.calib.body_T_cam, float)[:3, 3]
        if self.use_slam and self.slam_model == "sim3":
            a = self.slam_assoc
            slam = f.slam
            for s in self.slam_sessions:
                m = slam.session[a.meas_index] == s
                if not m.any():
                    continue
                init = self.init_session(s, t_limit)
                rows = a.meas_index[m]
                kfs = a.keyframe[m]
                world_t_cam = (
                    init.slam_R_world.T @ (slam.slam_t_cam[rows] - init.slam_t_world).T
                ).T / init.scale
                p = world_t_cam - np.einsum("nij,j->ni", self.R_kf[kfs], body_t_cam)
                if np.isfinite(pos).any():
                    # Later session: start at the last position of the previous one.
                    prev = _fill_positions(pos[: kfs[0]], self.t_kf[: kfs[0]])
                    offset = prev[-1] - p[0] if len(prev) else -p[0]
                else:
                    # First session: the world origin at the first body position.
                    offset = -p[0]
                init.slam_t_world = init.slam_t_world - init.scale * init.slam_R_world @ offset
                pos[kfs] = p + offset
                guess.slam[s] = init
        elif self.use_slam and self.slam_model == "axis":
            # Per session [k, o] (SLAM = diag(k) world_t_cam + o): the first session's origin at
            # the world's; a later one's placed so that it starts at the previous one's last
            # position, its scale its own fit (the previous session's when it has too little
            # motion for one).
            a = self.slam_assoc
            slam = f.slam
            guess.axis_scale = {}
            k_prev = None
            for s in self.slam_sessions:
                m = slam.session[a.meas_index] == s
                if not m.any():
                    continue
                try:
                    k = self.init_axis_scale(t_limit, session=s)
                except FlightDataError:
                    k = None
                if k is None or not np.all(np.isfinite(k) & (k > 0)):
                    k = k_prev if k_prev is not None else self.init_axis_scale(t_limit)
                rows, kfs = a.meas_index[m], a.keyframe[m]
                p = slam.slam_t_cam[rows] / k - np.einsum("nij,j->ni", self.R_kf[kfs], body_t_cam)
                offset = np.zeros(3)
                if np.isfinite(pos).any():
                    prev = _fill_positions(pos[: kfs[0]], self.t_kf[: kfs[0]])
                    offset = prev[-1] - p[0] if len(prev) else -p[0]
                pos[kfs] = p + offset
                guess.axis_scale[s] = np.r_[k, -k * offset]
                k_prev = k
        if not np.isfinite(pos).any() and self.vision is not None:
            pos = self.vision.initial_positions(self.t_kf)
            if pos is None:
                pos = np.full((K, 3), np.nan)
        flow_dr = None
        if not np.isfinite(pos).any() and self.flow is not None:
            flow_dr = self._flow_dead_reckoning()
            if flow_dr is not None:
                pos = flow_dr[0]
        if not np.isfinite(pos).any():
            pos[0] = 0.0
        pos = _fill_positions(pos, self.t_kf)
        guess.world_t_body = pos
        if K > 2:
            guess.world_v_body = np.gradient(pos, self.t_kf, axis=0)
        if flow_dr is not None:
            guess.world_v_body[:, :2] = flow_dr[1][:, :2]
        if self.drag_vars:
            guess.drag_k = self.init_drag_k(guess)
        if self.use_range and len(self.range_kf):
            guess.ground_height = self.init_ground(guess)
        return guess

    def _flow_dead_reckoning(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Initial positions and world velocities (K, 3) from the flow windows' velocities
        (``FlowFactors.velocity_hint``, gaps interpolated, zero before the first and after the
        last) through the attitude track, the height from the gated range readings (the first at
        z = 0); None without a flow velocity."""
        u = self._velocity_hint()
        if u is None:
            return None
        ok = np.all(np.isfinite(u[:, :2]), axis=1)
        if not ok.any():
            return None
        t = self.t_kf
        ub = np.zeros((self.K, 3))
        for a in range(2):
            ub[:, a] = np.interp(t, t[ok], u[ok, a], left=0.0, right=0.0)
        v = np.einsum("nij,nj->ni", self.R_kf, ub)
        v[:, 2] = 0.0
        pos = np.zeros((self.K, 3))
        if self.K > 1:
            dt = np.diff(t)[:, None]
            pos[1:] = np.cumsum(0.5 * (v[1:] + v[:-1]) * dt, axis=0)
        if self.use_range and len(self.range_kf):
            T = np.asarray(self.flight.calib.body_T_range, float)
            R = self.R_kf[self.range_kf]
            beam_z = np.einsum("nij,j->ni", R, T[:3, :3] @ np.array([0.0, 0.0, 1.0]))[:, 2]
            lever_z = np.einsum("nij,j->ni", R, T[:3, 3])[:, 2]
            z = -self.range_val * beam_z - lever_z
            z = np.interp(t, t[self.range_kf], z)
            pos[:, 2] = z - z[0]
            if self.K > 2:
                v[:, 2] = np.gradient(pos[:, 2], t)
        return pos, v

    def init_session(self, session: int, t_limit: float | None = None) -> SlamAlignmentInit:
        """Closed-form alignment of one SLAM session from the poses that have arrived by
        ``t_limit`` (arrival = image time + latency; None: all)."""
        slam = self.flight.slam
        m = slam.session == session
        if t_limit is not None:
            m &= slam.t + self.slam_latency <= t_limit
        sl = slam.select(m)
        im = (self.imu.t >= sl.t[0] - 1.0) & (self.imu.t <= sl.t[-1] + 1.0)
        prior_scale = self._prior_scale(session)
        init = init_slam_alignment(
            sl,
            self.imu.select(im),
            self.R_imu[im],
            np.asarray(self.flight.calib.body_T_cam, float),
            self.options.gravity,
        )
        if prior_scale is not None:
            init.scale = prior_scale
        log.info(
            "SLAM session %d: initial scale %.4g SLAM units/m from %d acceleration pairs "
            "(excitation %.3f m)",
            session,
            init.scale,
            init.n_pairs,
            init.excitation,
        )
        return init

    def prior_scale_sigma_rel(self, key: int) -> float | None:
        """Relative sigma of a front-end SLAM scale prior for SLAM-alignment key ``key`` (None:
        no front-end scale for its session, or not a SLAM key)."""
        p = self.priors
        if p is None or chr(gtsam.Symbol(key).chr()) != "s" or self.slam_model != "sim3":
            return None
        inv = {j: sess_seg for sess_seg, j in self.slam_var.items()}
        sess_seg = inv.get(int(gtsam.Symbol(key).index()))
        if sess_seg is None:
            return None
        s = self._prior_scale(sess_seg[0])
        sig = (getattr(p, "slam_scale_sigma", None) or {}).get(sess_seg[0])
        if s is None or sig is None or not s > 0:
            return None
        self._count("frontend-scale-prior")
        return float(sig) / s

    def _prior_scale(self, session: int) -> float | None:
        p = self.priors
        if p is None:
            return None
        scales = getattr(p, "slam_scale", None) or {}
        v = scales.get(session) if isinstance(scales, dict) else None
        return None if v is None else float(np.atleast_1d(v)[0])

    def init_axis_scale(
        self, t_limit: float | None = None, session: int | None = None
    ) -> np.ndarray:
        """Per-axis SLAM scale ``[kx, ky, kz]`` by least squares of second differences."""
        return self.init_axis_fit(t_limit, session)[0]

    def init_axis_fit(
        self, t_limit: float | None = None, session: int | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per-axis SLAM scale ``[kx, ky, kz]`` by least squares of second differences (0.5 s
        half-width, 0.1 s step) and the relative standard error of each axis (inflated by
        ``sqrt(10)`` for the overlap of neighbouring second differences; inf for an axis without
        motion, which starts at the mean of the others); of one SLAM session's poses when
        given (a map reset has its own scale), else of all."""
        slam = self.flight.slam
        m = np.ones(len(slam), bool) if t_limit is None else slam.t <= t_limit
        if session is not None:
            m &= slam.session == session
        world_a = world_specific_accel(self.imu, self.R_imu, self.options.gravity)
        k, rel_se, _ = fit_axis_scale(slam.t[m], slam.slam_t_cam[m], self.imu.t, world_a)
        if not np.isfinite(rel_se).all():
            # An axis without acceleration (e.g. z at constant altitude) is not seen by second
            # differences; the absolute per-axis factors still fix it, from this initial value.
            log.info(
                "per-axis SLAM scale init %s: axis %s without enough motion starts at the mean of "
                "the others",
                np.round(k, 4),
                "".join("xyz"[i] for i in np.flatnonzero(~np.isfinite(rel_se))),
            )
        log.info("per-axis SLAM scale init %s (rel. s.e. %s)", np.round(k, 4), np.round(rel_se, 3))
        return k, rel_se

    def init_drag_k(self, guess: InitialGuess) -> np.ndarray:
        """Closed-form drag from ``f_xy = -k u_xy`` with the initial body velocities."""
        n = 2 if self.options.drag_per_axis else 1
        if self.options.drag_k_init is not None:
            return np.full(n, float(self.options.drag_k_init))
        if not self.use_drag:  # drag dynamics only: no usable accelerometer to fit k on
            return np.full(n, DEFAULT_DRAG_K)
        u = np.einsum("nji,nj->ni", guess.world_R_body, guess.world_v_body)[:, :2]
        f = self.drag_mean
        ok = np.all(np.isfinite(f), axis=1) & (self.drag_count > 0)
        if n == 1:
            den = float((u[ok] ** 2).sum())
            k = np.array([-(f[ok] * u[ok]).sum() / den]) if den > 0 else np.array([np.nan])
        else:
            den = (u[ok] ** 2).sum(axis=0)
            k = np.where(den > 0, -(f[ok] * u[ok]).sum(axis=0) / np.where(den > 0, den, 1), np.nan)
        k = np.where(np.isfinite(k) & (k > 0), k, DEFAULT_DRAG_K)
        return k

    def init_ground(self, guess: InitialGuess) -> float:
        """Ground height from the first gated range reading and the initial pose."""
        k = int(self.range_kf[0])
        T = np.asarray(self.flight.calib.body_T_range, float)
        R = guess.world_R_body[k]
        z_sensor = guess.world_t_body[k, 2] + (R @ T[:3, 3])[2]
        beam = R @ T[:3, :3] @ np.array([0.0, 0.0, 1.0])
        return float(z_sensor + self.range_val[0] * beam[2])

    # ------------------------------------------------------------------------------------------
    # Factors
    # ------------------------------------------------------------------------------------------

    def preintegrate(
        self, k: int, bias: gtsam.imuBias.ConstantBias, k_from: int | None = None
    ) -> gtsam.PreintegratedCombinedMeasurements:
        """Preintegrated IMU from keyframe ``k_from`` (default k-1) to k (zero-order hold on each
        sample), with the bias estimate ``bias``."""
        ta, tb = self.t_kf[k - 1 if k_from is None else k_from], self.t_kf[k]
        t = self.imu.t
        n = len(t)
        # Samples i0 <= i < i1 start before tb; sample i holds from max(t[i], ta) to
        # min(t[i+1], tb) (tb after the last sample).
        i0 = max(int(np.searchsorted(t, ta, side="right")) - 1, 0)
        i1 = max(int(np.searchsorted(t, tb, side="left")), i0)
        if i1 <= i0:
            return gtsam.PreintegratedCombinedMeasurements(self.pim_params, bias)
        s0 = np.maximum(t[i0:i1], ta)
        s1 = np.minimum(t[i0 + 1 : i1 + 1], tb) if i1 < n else np.r_[t[i0 + 1 : i1], tb]
        w, a = self.imu.body_omega[i0:i1], self.imu.body_accel[i0:i1]
        params = self.pim_params
        flags = self.imu_saturation[i0:i1]
        if flags.any():
            params = saturated_pim_params(params, w, a, flags, s1 - s0, self._sat_sigma_rel)
        pim = gtsam.PreintegratedCombinedMeasurements(params, bias)
        dt = (s1 - s0).tolist()
        for j, d in enumerate(dt):
            if d > 0:
                pim.integrateMeasurement(a[j], w[j], d)
        return pim

    def slam_key(self, assoc_row: int) -> int:
        slam = self.flight.slam
        i = self.slam_assoc.meas_index[assoc_row]
        return S(self.slam_var[(int(slam.session[i]), int(self.slam_chain[assoc_row]))])

    def first_prior_factors(
        self, guess_R: np.ndarray, guess_t: np.ndarray, guess_v: np.ndarray
    ) -> gtsam.NonlinearFactorGraph:
        """Gauge and first-state priors on keyframe 0."""
        o = self.options
        g = gtsam.NonlinearFactorGraph()
        yaw_sigma = o.prior_yaw_sigma
        pos_sigma = o.prior_position_sigma
        if self.use_yaw or (self.use_slam and self.slam_model == "axis"):
            yaw_sigma = max(yaw_sigma, 1.0)
        sig = np.array(
            [
                o.prior_rollpitch_sigma,
                o.prior_rollpitch_sigma,
                yaw_sigma,
                pos_sigma,
                pos_sigma,
                pos_sigma,
            ]
        )
        # The Pose3 prior is in body axes; near level flight body z is the yaw axis.
        g.add(
            gtsam.PriorFactorPose3(
                X(0),
                gtsam.Pose3(gtsam.Rot3(guess_R), guess_t),
                gtsam.noiseModel.Diagonal.Sigmas(sig),
            )
        )
        v_sigma = o.prior_velocity_sigma
        v0 = guess_v
        pv = self._prior_velocity(0)
        if pv is not None:
            v0, v_sigma = pv
        g.add(gtsam.PriorFactorVector(V(0), np.asarray(v0, float), _isotropic(3, v_sigma)))
        g.add(
            gtsam.PriorFactorConstantBias(
                B(0),
                self.initial_bias(),
                gtsam.noiseModel.Diagonal.Sigmas(
                    np.r_[
                        [o.prior_accel_bias_sigma] * 3,
                        gyro_bias_prior_sigmas(
                            o,
                            self.flight.calib,
                            self.thrust_only and not self.use_yaw and not self.use_slam,
                        ),
                    ]
                ),
            )
        )
        return g

    def initial_bias(self) -> gtsam.imuBias.ConstantBias:
        """Initial IMU bias (and mean of its first prior): zero accelerometer bias, gyro bias from
        the SLAM orientations when ``gyro_bias_from_slam`` (else zero)."""
        return gtsam.imuBias.ConstantBias(np.zeros(3), self.gyro_bias0)

    def _prior_velocity(self, k: int) -> tuple[np.ndarray, float] | None:
        p = self.priors
        if p is None or getattr(p, "velocity", None) is None:
            return None
        vel = p.velocity
        t = np.asarray(vel.t)
        i = int(np.argmin(np.abs(t - self.t_kf[k])))
        if abs(t[i] - self.t_kf[k]) > 0.5 / self.options.keyframe_hz:
            return None
        sigma = (
            float(np.max(vel.sigma[i]))
            if getattr(vel, "sigma", None) is not None
            else self.options.prior_velocity_sigma
        )
        return np.asarray(vel.value[i], float), sigma

    def keyframe_chunk(
        self,
        k: int,
        pose: gtsam.Pose3,
        velocity: np.ndarray,
        bias: gtsam.imuBias.ConstantBias,
        slow_values: dict[int, Any],
        pim: gtsam.PreintegratedCombinedMeasurements | None = None,
        with_first_priors: bool = True,
    ) -> KeyframeChunk:
        """Factors and values that keyframe k adds.

        Args:
            k: keyframe index.
            pose, velocity, bias: initial values of ``X(k)``, ``V(k)``, ``B(k)``.
            slow_values: initial values of the slow variables first used at keyframe k (keys from
                :meth:`new_slow_keys`).
            pim: preintegration from k-1 (computed with a zero bias when None).
            with_first_priors: add the gauge priors at k == 0.
        """
        t = float(self.t_kf[k])
        g = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        # Keyword arguments pick the overload at once: positionally, pybind tries Values.insert's
        # overloads in order, and ConstantBias is the 44th (~90 us against ~20 us).
        vals.insert(X(k), pose3=pose)
        vals.insert(V(k), vector=np.asarray(velocity, float))
        vals.insert(B(k), constant_bias=bias)
        stamps = {X(k): t, V(k): t, B(k): t}
        if k == 0:
            if with_first_priors:
                g.push_back(
                    self.first_prior_factors(pose.rotation().matrix(), pose.translation(), velocity)
                )
        else:
            if pim is None:
                pim = self.preintegrate(k, gtsam.imuBias.ConstantBias())
            g.add(gtsam.CombinedImuFactor(X(k - 1), V(k - 1), X(k), V(k), B(k - 1), B(k), pim))
            pv = self._prior_velocity(k)
            if pv is not None:
                g.add(gtsam.PriorFactorVector(V(k), pv[0], _isotropic(3, pv[1])))
                self._count("frontend-velocity-prior")
        for key, value in slow_values.items():
            vals.insert(key, value)
            stamps[key] = t
            g.push_back(
                self.slow_factors(
                    key,
                    value,
                    chain_start=self.slow_chain_previous(key) is None,
                    scale_sigma_rel=self.prior_scale_sigma_rel(key),
                )
            )
        return KeyframeChunk(k, t, g, vals, stamps)

    def new_slow_keys(self, k: int) -> list[int]:
        """Slow variables whose first use is at keyframe k (SLAM alignment, drag, ground)."""
        out = []
        if self.drag_vars and (k == 0 or self.drag_segment[k] != self.drag_segment[k - 1]):
            out.append(D(int(self.drag_segment[k])))
        if self.use_range and (k == 0 or self.ground_segment[k] != self.ground_segment[k - 1]):
            out.append(G(int(self.ground_segment[k])))
        return out

    def _rows_at(self, name: str, keyframe_of_row: np.ndarray, k: int) -> list[int]:
        """Rows of a stream's association whose keyframe is k (index built once per stream)."""
        index = self._row_index.get(name)
        if index is None:
            index = {}
            for r, kk in enumerate(np.asarray(keyframe_of_row, int).tolist()):
                index.setdefault(kk, []).append(r)
            self._row_index[name] = index
        return index.get(k, [])

    def slow_dims(self) -> dict[str, int]:
        """Tangent dimension of each slow-variable symbol used by this graph."""
        out: dict[str, int] = {}
        if self.use_slam:
            out["s"] = 7 if self.slam_model == "sim3" else 6
        if self.drag_vars:
            out["d"] = 2 if self.options.drag_per_axis else 1
        if self.use_range:
            out["g"] = 1
        return out

    def slam_session_segment(self, key: int) -> tuple[int, int] | None:
        """``(session, segment)`` of a SLAM-alignment key (None: not one of this graph)."""
        if not self.use_slam or chr(gtsam.Symbol(key).chr()) != "s":
            return None
        j = int(gtsam.Symbol(key).index())
        for sess_seg, jj in self.slam_var.items():
            if jj == j:
                return sess_seg
        return None

    def slam_keys_at(self, k: int) -> list[int]:
        """SLAM alignment keys used by the SLAM measurements of keyframe k."""
        if not self.use_slam:
            return []
        rows = self._rows_at("slam", self.slam_assoc.keyframe, k)
        return [self.slam_key(int(r)) for r in rows]

    def slow_chain_previous(self, key: int) -> int | None:
        """The previous variable of a slow key's random-walk chain, or None at a chain start."""
        sym = gtsam.Symbol(key)
        c, j = chr(sym.chr()), int(sym.index())
        if j == 0:
            return None
        if c == "s":
            prev = self.slam_chain_prev.get(j)
            return None if prev is None else S(prev[0])
        if c == "g" and j - 1 not in self._ground_set:
            return None  # the first segment after a terrain step
        return gtsam.symbol(c, j - 1)

    def slam_walk_s(self, key: int) -> float:
        """Time the random walk of a SLAM-alignment key runs over [s]: one segment, or every
        segment since the chain's previous variable across a SLAM pause."""
        prev = self.slam_chain_prev.get(int(gtsam.Symbol(key).index()))
        return self.options.slam_segment_s * (prev[1] if prev is not None else 1)

    def slow_factors(
        self,
        key: int,
        value: Any,
        chain_start: bool,
        scale_sigma_rel: float | np.ndarray | None = None,
    ) -> gtsam.NonlinearFactorGraph:
        """Prior (``chain_start``: around ``value``) or random-walk factor from the previous
        segment of a new slow variable.

        Args:
            key: the new slow variable.
            value: its initial value.
            chain_start: True for a prior, False for a random walk from the previous segment.
            scale_sigma_rel: relative sigma of a SLAM scale prior (default: weak, 50 %); for the
                per-axis model a scalar or one per axis.
        """
        o = self.options
        g = gtsam.NonlinearFactorGraph()
        c = chr(gtsam.Symbol(key).chr())
        prev = None if chain_start else self.slow_chain_previous(key)
        if c == "d":
            dim = 2 if o.drag_per_axis else 1
            if prev is None:
                g.add(
                    gtsam.PriorFactorVector(
                        key, np.asarray(value, float), _isotropic(dim, o.drag_prior_sigma)
                    )
                )
            else:
                sig = o.drag_rw * math.sqrt(o.drag_segment_s or 1.0)
                g.add(gtsam.BetweenFactorVector(prev, key, np.zeros(dim), _isotropic(dim, sig)))
        elif c == "g":
            if prev is None:
                g.add(
                    gtsam.PriorFactorVector(
                        key, np.asarray(value, float), _isotropic(1, o.ground_prior_sigma)
                    )
                )
            else:
                sig = o.ground_rw * math.sqrt(o.ground_segment_s)
                g.add(gtsam.BetweenFactorVector(prev, key, np.zeros(1), _isotropic(1, sig)))
        elif c == "s" and self.slam_model == "axis":
            # Vector6 [k (3), o (3)]: per-axis scale and SLAM-origin offset [SLAM units].
            a = np.asarray(value, float)
            k_max = float(np.max(a[:3]))
            if prev is None:
                # scale_sigma_rel: scalar, or one per axis.
                rel = WEAK_SCALE_PRIOR_REL if scale_sigma_rel is None else scale_sigma_rel
                sig = np.r_[np.broadcast_to(rel, 3) * np.abs(a[:3]), [10.0 * k_max] * 3]
                g.add(gtsam.PriorFactorVector(key, a, gtsam.noiseModel.Diagonal.Sigmas(sig)))
            else:
                # Relative random walk of every axis (the same drift as the Sim(3) scale) and an
                # origin walk of slam_trans_rw_m metres.
                dt = math.sqrt(self.slam_walk_s(key))
                sig = np.r_[
                    o.slam_scale_rw * dt * np.abs(a[:3]), [o.slam_trans_rw_m * dt * k_max] * 3
                ]
                g.add(
                    gtsam.BetweenFactorVector(
                        prev, key, np.zeros(6), gtsam.noiseModel.Diagonal.Sigmas(sig)
                    )
                )
        elif c == "s":
            if prev is None:
                # Weak prior: the closed-form initial value, 0.3 rad, 10 m, 50 % in scale.
                rel = WEAK_SCALE_PRIOR_REL if scale_sigma_rel is None else scale_sigma_rel
                sig = np.array([0.3, 0.3, 0.3, 10.0, 10.0, 10.0, rel])
                g.add(
                    gtsam.PriorFactorSimilarity3(key, value, gtsam.noiseModel.Diagonal.Sigmas(sig))
                )
            else:
                dt = math.sqrt(self.slam_walk_s(key))
                # Similarity3 tangent [omega, u, lambda]; u is the GTSAM translation t / s... in
                # world-scaled units (t = slam_t_world / s) [m].
                trans = o.slam_trans_rw_m * dt
                if int(gtsam.Symbol(key).index()) in self.slam_jump_keys:
                    trans = SLAM_JUMP_ORIGIN_SIGMA_M  # the jump moved the map's origin
                sig = np.array([o.slam_rot_rw * dt] * 3 + [trans] * 3 + [o.slam_scale_rw * dt])
                g.add(
                    gtsam.BetweenFactorSimilarity3(
                        prev, key, gtsam.Similarity3(), gtsam.noiseModel.Diagonal.Sigmas(sig)
                    )
                )
        return g

    def rebuild_prior(self, key: int, value: Any, sigma_rel: float) -> gtsam.NonlinearFactorGraph:
        """Prior on a slow variable when a smoother is rebuilt: ``sigma_rel`` of its magnitude
        (drag, scale), or the ground prior sigma for the ground height."""
        g = gtsam.NonlinearFactorGraph()
        c = chr(gtsam.Symbol(key).chr())
        if c == "s" and self.slam_model == "sim3":
            sig = np.array([0.05, 0.05, 0.05, 0.5, 0.5, 0.5, sigma_rel])
            g.add(gtsam.PriorFactorSimilarity3(key, value, gtsam.noiseModel.Diagonal.Sigmas(sig)))
            return g
        v = np.asarray(value, float)
        if c == "g":
            sig = np.full(v.shape, self.options.range_sigma * 5.0)
        elif c == "s":
            # Per-axis alignment [k, o]: relative on k, 0.5 m on the origin.
            k_max = float(np.max(v[:3]))
            sig = np.r_[np.maximum(np.abs(v[:3]) * sigma_rel, 1e-3), [0.5 * k_max] * 3]
        else:
            sig = np.maximum(np.abs(v) * sigma_rel, 1e-3)
        g.add(gtsam.PriorFactorVector(key, v, gtsam.noiseModel.Diagonal.Sigmas(sig)))
        return g

    def drag_start_value(self) -> np.ndarray:
        """Drag k of a new chain when nothing better is known [1/s]."""
        n = 2 if self.options.drag_per_axis else 1
        k0 = self.options.drag_k_init if self.options.drag_k_init is not None else DEFAULT_DRAG_K
        return np.full(n, float(k0))

    def ground_start_value(self, world_T_body: gtsam.Pose3 | None, t: float) -> float:
        """Ground height from the last raw range reading at or before ``t`` and a pose (causal)."""
        rng = self.flight.range
        if rng is None or world_T_body is None:
            return 0.0
        i = int(np.searchsorted(rng.t, t, side="right")) - 1
        if i < 0:
            return 0.0
        T = np.asarray(self.flight.calib.body_T_range, float)
        R = world_T_body.rotation().matrix()
        z_sensor = world_T_body.translation()[2] + (R @ T[:3, 3])[2]
        beam = R @ T[:3, :3] @ np.array([0.0, 0.0, 1.0])
        return float(z_sensor + rng.range[i] * beam[2])

    def measurement_factors(
        self,
        k: int,
        slam_init_scale: dict[int, float] | None = None,
        kinds: tuple[str, ...] | None = None,
    ) -> list[MeasurementFactor]:
        """Factors of the measurements associated with keyframe k, with arrival times.

        Args:
            k: keyframe index.
            slam_init_scale: initial scale per SLAM variable key (converts the SLAM noise in
                metres into SLAM units).
            kinds: only these kinds (``"drag"``, ``"slam"``, ``"range"``, ``"contact"``,
                ``"yaw"``, ``"homography"``, ``"flow"``); None: all.
        """
        o = self.options
        f = self.flight
        out: list[MeasurementFactor] = []
        want = (lambda kind: True) if kinds is None else (lambda kind: kind in kinds)
        if self.use_drag and self.drag_count[k] > 0 and want("drag"):
            n_acc = int(self.drag_count[k])
            noise = self._drag_noise.get(n_acc)
            if noise is None:
                noise = mean_accel_noise(self.imu_accel_sigma(), n_acc, self.drag_sigma)
                if o.drag_robust:
                    noise = self._robust(noise)
                self._drag_noise[n_acc] = noise
            dk = D(int(self.drag_segment[k]))
            fac = make_accel_drag_factor(X(k), V(k), B(k), dk, self.drag_mean[k], noise)
            out.append(
                MeasurementFactor(
                    float(self.drag_arrival[k]), k, "drag", fac, (X(k), V(k), B(k), dk)
                )
            )
        if getattr(self, "drag_dynamics", False) and want("drag"):
            # Thrust-only prediction: the body x, y accelerometer bias (the negated specific
            # force it integrates) is the rotor drag k u_xy: the drag factor, measurement 0.
            dk = D(int(self.drag_segment[k]))
            noise = _isotropic(2, o.thrust_only_drag_sigma)
            fac = make_accel_drag_factor(X(k), V(k), B(k), dk, np.zeros(2), noise)
            out.append(
                MeasurementFactor(
                    float(self.t_kf[k]), k, "drag-dynamics", fac, (X(k), V(k), B(k), dk)
                )
            )
        if self.use_slam and want("slam"):
            slam = f.slam
            for r in self._rows_at("slam", self.slam_assoc.keyframe, k):
                i = int(self.slam_assoc.meas_index[r])
                sk = self.slam_key(int(r))
                arrival = float(slam.t[i] + self.slam_latency[i])
                if self.slam_model == "axis":
                    scale = slam_init_scale.get(sk, 1.0) if slam_init_scale else 1.0
                    scale = float(np.max(np.atleast_1d(scale)[:3]))
                    noise = self._noise(3, o.slam_sigma_m * scale)
                    fac = make_slam_axis_offset_factor(
                        X(k), sk, slam.slam_t_cam[i], noise, self.body_T_cam[:3, 3]
                    )
                else:
                    scale = slam_init_scale.get(sk, 1.0) if slam_init_scale else 1.0
                    noise = self._noise(3, o.slam_sigma_m * scale)
                    fac = make_slam_position_factor(
                        X(k), sk, slam.slam_t_cam[i], self.body_T_cam, noise
                    )
                out.append(MeasurementFactor(arrival, k, "slam", fac, (X(k), sk)))
                if o.use_slam_rotation and self.slam_model == "sim3":
                    from fgnav.datasets.geometry import quat_wxyz_to_matrix

                    noise = self._noise(3, o.slam_rot_sigma)
                    fac = make_slam_rotation_factor(
                        X(k),
                        sk,
                        quat_wxyz_to_matrix(slam.slam_q_cam_wxyz[i]),
                        self.body_T_cam,
                        noise,
                    )
                    out.append(MeasurementFactor(arrival, k, "slam-rotation", fac, (X(k), sk)))
        if self.use_range and want("range"):
            for n in self._rows_at("range", self.range_kf, k):
                gk = G(int(self.ground_segment[k]))
                noise = self._noise(1, o.range_sigma)
                fac = make_range_factor(
                    X(k), gk, float(self.range_val[n]), self.body_T_range, noise
                )
                out.append(
                    MeasurementFactor(float(self.range_arrival[n]), k, "range", fac, (X(k), gk))
                )
        if len(self.contact_kf) and want("contact"):
            for n in self._rows_at("contact", self.contact_kf, k):
                noise = self._noise(3, o.contact_velocity_sigma)
                fac = gtsam.PriorFactorVector(V(k), np.zeros(3), noise)
                arrival = float(self.contact_arrival[n])
                out.append(MeasurementFactor(arrival, k, "contact", fac, (V(k),)))
                if o.contact_range_sigma is not None:
                    gk = G(int(self.ground_segment[k]))
                    fac = make_range_factor(
                        X(k), gk, 0.0, self.body_T_range, self._noise(1, o.contact_range_sigma)
                    )
                    out.append(MeasurementFactor(arrival, k, "contact", fac, (X(k), gk)))
        if self.use_yaw and want("yaw"):
            for n in self._rows_at("yaw", self.yaw_kf, k):
                noise = self._noise(1, o.yaw_sigma)
                fac = make_yaw_factor(X(k), float(self.yaw_val[n]), noise)
                out.append(MeasurementFactor(float(self.yaw_arrival[n]), k, "yaw", fac, (X(k),)))
        if self.vision is not None and want("homography"):
            ground_key = lambda kf: G(int(self.ground_segment[kf]))  # noqa: E731
            for arrival, fac, keys in self.vision.factors_at(k, ground_key, self._robust):
                out.append(MeasurementFactor(arrival, k, "homography", fac, keys))
        if self.flow is not None and want("flow") and k in self.flow.by_keyframe:
            keys = (X(k), V(k), G(int(self.ground_segment[k])))
            res = self.flow.factor_at(
                k,
                keys,
                self.imu.t,
                self.imu.body_omega,
                self.gyro_bias0,
                self.R_kf[k],
                self._robust,
            )
            if res.factor is not None:
                out.append(MeasurementFactor(res.arrival, k, "flow", res.factor, keys))
        return out

    # ------------------------------------------------------------------------------------------
    # Whole graph (batch)
    # ------------------------------------------------------------------------------------------

    def slow_initial_values(self, guess: InitialGuess) -> dict[int, Any]:
        """Initial value of every slow variable of the flight."""
        from fgnav.factors.slam_scale import make_slam_T_world

        out: dict[int, Any] = {}
        if self.drag_vars:
            for j in np.unique(self.drag_segment):
                out[D(int(j))] = np.asarray(guess.drag_k, float)
        if self.use_range:
            z = guess.ground_height if guess.ground_height is not None else 0.0
            for j in np.unique(self.ground_segment):
                out[G(int(j))] = np.array([z])
        if self.use_slam:
            if self.slam_model == "axis":
                # Each session's [k, o] (see initial_guess).
                for (sess, _seg), j in self.slam_var.items():
                    out[S(j)] = np.asarray(guess.axis_scale[sess], float)
            else:
                for (sess, _seg), j in self.slam_var.items():
                    init = guess.slam[sess]
                    out[S(j)] = make_slam_T_world(init.scale, init.slam_R_world, init.slam_t_world)
        return out

    def slam_noise_scales(self, slow: dict[int, Any]) -> dict[int, float]:
        out = {}
        for key, v in slow.items():
            if chr(gtsam.Symbol(key).chr()) == "s":
                out[key] = float(np.max(v[:3])) if isinstance(v, np.ndarray) else float(v.scale())
        return out

    def build(
        self, guess: InitialGuess | None = None, progress: Callable[[int], None] | None = None
    ) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The whole flight's graph and initial values (batch)."""
        guess = guess or self.initial_guess()
        slow = self.slow_initial_values(guess)
        scales = self.slam_noise_scales(slow)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        created: set[int] = set()
        bias0 = self.initial_bias()
        for k in range(self.K):
            keys = [kk for kk in self.new_slow_keys(k) + self.slam_keys_at(k) if kk not in created]
            keys = list(dict.fromkeys(keys))
            created.update(keys)
            pose = gtsam.Pose3(gtsam.Rot3(guess.world_R_body[k]), guess.world_t_body[k])
            chunk = self.keyframe_chunk(
                k, pose, guess.world_v_body[k], bias0, {kk: slow[kk] for kk in keys}
            )
            graph.push_back(chunk.factors)
            values.insert(chunk.values)
            for m in self.measurement_factors(k, scales):
                graph.add(m.factor)
                self._count(m.kind)
            if progress is not None:
                progress(k)
        return graph, values

    def report(self) -> dict[str, Any]:
        """Counts of used and skipped measurements and the options (for ``Estimate.info``)."""
        return {
            "keyframes": int(self.K),
            "slam_model": self.slam_model if self.use_slam else None,
            "drag_disabled": self.drag_disabled,
            "accel_check": self.accel_check.as_dict() if self.accel_check is not None else None,
            "accel_horizontal": "thrust-only" if self.thrust_only else "measured",
            "factors": dict(self.counts),
            "skipped": dict(self.skipped),
            "homography": self.vision.report() if self.vision is not None else None,
            "flow": self.flow.report() if self.flow is not None else None,
            "flow_no_height": self.flow_no_height,
            "slam_gyro_check": self.flight.meta.get(SLAM_CHECK_META_KEY),
            "options": asdict(self.options),
        }


def _reason_tag(reason: str) -> str:
    """Short tag of a gate reason (its text before the first digit or colon)."""
    head = reason.split(":")[0]
    for i, ch in enumerate(head):
        if ch.isdigit():
            head = head[:i]
            break
    return "-".join(head.split()) or "other"


def _fill_positions(pos: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Fill NaN rows by linear interpolation in time (held at the ends)."""
    out = pos.copy()
    ok = np.all(np.isfinite(pos), axis=1)
    if not ok.any():
        return np.zeros_like(pos)
    for a in range(3):
        out[:, a] = np.interp(t, t[ok], pos[ok, a])
    return out


def check_observability(flight: Flight, options: GraphOptions, slam_model: str) -> None:
    """Raise :class:`ObservabilityError` naming what the chosen sensor subset cannot observe."""
    o = options
    has_slam = o.use_slam and flight.slam is not None
    has_range = o.use_range and flight.range is not None
    has_homography = o.use_homography and flight.images is not None
    has_flow = bool(o.use_flow) and flight.flow is not None
    if o.use_slam and flight.slam is None:
        log.info("%s: no SLAM stream; SLAM factors off", flight.name)
    if o.use_range and flight.range is None:
        log.info("%s: no rangefinder stream; range factors off", flight.name)
    if not (has_slam or has_homography or has_flow or o.use_drag):
        raise ObservabilityError(
            f"{flight.name}: horizontal velocity and position are unobservable with this sensor "
            "set (IMU only); enable slam, homography, flow or drag"
        )
    if has_flow and not has_range:
        raise ObservabilityError(
            f"{flight.name}: optical flow without a rangefinder measures only velocity / height: "
            "the metric velocity is unobservable; enable range"
        )
    if has_flow and not (has_slam or has_homography):
        log.info(
            "%s: horizontal velocity from optical flow and the rangefinder; no position source, "
            "so positions are dead-reckoned from it and drift",
            flight.name,
        )
    elif not (has_slam or has_homography):
        log.warning(
            "%s: no position source (SLAM, or camera with rangefinder): positions are "
            "dead-reckoned from the IMU with drag-model velocity; drift grows without bound%s",
            flight.name,
            "" if has_range else ", and height and vertical velocity are unobservable (no range)",
        )
    if has_homography and not has_range:
        raise ObservabilityError(
            f"{flight.name}: homography motion without a rangefinder has no metric height: the "
            "translation scale is unobservable; enable range"
        )
    if has_slam and slam_model == "axis" and not o.use_drag and flight.imu is None:
        raise ObservabilityError(
            f"{flight.name}: per-axis SLAM scale is unobservable without the accelerometer or drag"
        )
    if o.use_yaw and flight.yaw is None and not has_slam:
        log.warning(
            "%s: no yaw stream and no SLAM: world yaw is held by the first-pose prior only",
            flight.name,
        )


def gyro_bias_prior_sigma(options: GraphOptions, calib: Calibration) -> float:
    """Sigma of the prior on the first gyro bias [rad/s]: ``prior_gyro_bias_sigma``, or the
    calibration's ``imu_noise.gyro_bias_sigma`` when that option is None."""
    if options.prior_gyro_bias_sigma is not None:
        return float(options.prior_gyro_bias_sigma)
    return float(calib.imu_noise.gyro_bias_sigma)


def gyro_bias_prior_sigmas(
    options: GraphOptions, calib: Calibration, yaw_rate_unobserved: bool
) -> np.ndarray:
    """(3,) sigmas of the prior on the first gyro bias [rad/s]: :func:`gyro_bias_prior_sigma` on
    every axis, body z lowered to ``thrust_only_gyro_z_sigma`` when ``yaw_rate_unobserved`` (a
    thrust-only prediction with no yaw source; see that option)."""
    s = gyro_bias_prior_sigma(options, calib)
    z = s
    if yaw_rate_unobserved and options.thrust_only_gyro_z_sigma is not None:
        z = min(s, float(options.thrust_only_gyro_z_sigma))
    return np.array([s, s, z])


def thrust_only_noise(
    sigma: float, tau_s: float, keyframe_hz: float, accel_nd: float, accel_rw: float
) -> tuple[float, float]:
    """(noise density [m/s^2/sqrt(Hz)], bias random walk [m/s^3/sqrt(Hz)]) of the body x, y
    specific force in a thrust-only IMU prediction (``GraphOptions.accel_horizontal``): the
    neglected drag ``sigma`` as white noise of a keyframe mean (``sigma / sqrt(keyframe_hz)``) and
    as a bias walk reaching ``sigma`` in ``tau_s`` (``sigma / sqrt(tau_s)``); never below the
    accelerometer's own figures."""
    return (
        max(accel_nd, sigma / math.sqrt(keyframe_hz)),
        max(accel_rw, sigma / math.sqrt(tau_s)),
    )


def _moving_average(x: np.ndarray, n: int) -> np.ndarray:
    """Centred moving average of (K, d) over ``n`` samples, NaN-aware (NaN where the window has
    no finite sample)."""
    x = np.asarray(x, float)
    if n <= 1 or len(x) == 0:
        return x.copy()
    ok = np.isfinite(x)
    num = np.where(ok, x, 0.0)
    kernel = np.ones(n)
    out = np.empty_like(x)
    for a in range(x.shape[1]):
        s = np.convolve(num[:, a], kernel, mode="same")
        c = np.convolve(ok[:, a].astype(float), kernel, mode="same")
        with np.errstate(invalid="ignore", divide="ignore"):
            out[:, a] = np.where(c > 0, s / c, np.nan)
    return out
