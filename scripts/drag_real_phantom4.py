"""Rotor-drag model on a real flight: DJI Phantom 4 RTK, straight line, Xsens IMU.

Steps (numbers printed; a figure saved):

1. Read ``StraightLine/path_1`` (:func:`fgnav.datasets.phantom4.read_phantom4`), fit the IMU-to-
   airframe rotation from the Xsens attitude vs the DJI attitude (world yaw-only alignment), and
   check the two clocks by cross-correlating tilt angles.
2. Regress the body-axes specific force, averaged over each 0.1 s ground-truth interval, on the
   ground-truth body velocity: ``f_a = -k u_a + b_a`` jointly on x-y, and per axis. Report k with
   its standard error (plain and corrected for residual autocorrelation), R^2, residual std.
3. Identify k and the biases on the first half of the flight; on the second half estimate the
   velocity from the IMU, the attitude and the drag model alone with a small GTSAM graph
   (velocity-increment factors from the IMU + ``fgnav.factors.accel_drag`` factors), and compare
   with integrating the IMU without drag. Both start from the RTK velocity and the same bias.

Usage::

    .venv/bin/python scripts/drag_real_phantom4.py [--imu IMU_1.csv] [--out out/drag_phantom4.png]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import gtsam
import numpy as np
from fgnav.datasets.frames import tilt_angle
from fgnav.datasets.geometry import quat_wxyz_to_matrix, so3_log
from fgnav.datasets.phantom4 import (
    PX4_DEFAULT_MCOEF,
    DragFit,
    drag_samples,
    estimate_body_R_imu,
    fit_linear_drag,
    read_phantom4,
    with_body_axes,
)
from fgnav.datasets.time_offset import estimate_time_offset
from fgnav.datasets.ulog import interpolate_attitude
from fgnav.factors.accel_drag import make_accel_drag_factor
from matplotlib.figure import Figure

from fgnav.keys import B, D, V, X

ROOT = Path(__file__).resolve().parents[1]
FOLDER = (
    ROOT.parent / "shared" / "data" / "real" / "ansfl_phantom4_rtk_mimu" / "StraightLine" / "path_1"
)
#: Earth gravity [m/s^2] (standard gravity; the site is near sea level).
GRAVITY = 9.80665
#: Ground-truth period: the accelerometer is averaged over it [s].
WINDOW_S = 0.1
#: Clock-offset search half-width [s].
MAX_CLOCK_OFFSET_S = 1.0
#: Prior sigmas of the validation graph: initial velocity (RTK, 0.1 m/s resolution) [m/s];
#: accelerometer bias around the first-half estimate [m/s^2]; pose (attitude given) [rad, m];
#: gyro bias (unused by these factors) [rad/s].
SIGMA_V0 = 0.05
SIGMA_ACCEL_BIAS = 0.1
SIGMA_POSE_FIXED = 1e-6
SIGMA_GYRO_BIAS = 1e-3
#: Attitude error budget for the velocity increments: DJI attitude resolution 0.1 deg and
#: interpolation; 0.5 deg of tilt error leaks g * 0.5 deg = 0.086 m/s^2 [rad].
SIGMA_ATTITUDE = np.deg2rad(0.5)


def velocity_increments(flight, t_keys: np.ndarray, imu_shift_s: float):
    """Per interval [t_k, t_k+1): ``S_k = sum R_i f_i dt`` and ``M_k = sum R_i dt`` (world axes),
    with the attitude slerped at the IMU times; ``dv = S_k - M_k b_a + g_vec T``."""
    t_imu = flight.imu.t + imu_shift_s
    gt = flight.ground_truth
    sel = (t_imu >= t_keys[0]) & (t_imu < t_keys[-1])
    t = t_imu[sel]
    R = quat_wxyz_to_matrix(interpolate_attitude(gt, t))
    dt = np.gradient(t)
    Rf = np.einsum("nij,nj->ni", R, flight.imu.body_accel[sel]) * dt[:, None]
    Rdt = R * dt[:, None, None]
    idx = np.searchsorted(t_keys, t, side="right") - 1
    n = len(t_keys) - 1
    S = np.zeros((n, 3))
    M = np.zeros((n, 3, 3))
    np.add.at(S, idx, Rf)
    np.add.at(M, idx, Rdt)
    counts = np.bincount(idx, minlength=n)
    return S, M, counts


def accel_noise_discrete(flight) -> float:
    """Std of one accelerometer sample about its 0.1 s moving mean (vibration + noise) [m/s^2]."""
    n = max(int(WINDOW_S * flight.imu.rate_hz), 1)
    a = flight.imu.body_accel
    smooth = np.column_stack([np.convolve(a[:, i], np.ones(n) / n, "same") for i in range(3)])
    return float(np.std((a - smooth)[n:-n]))


def fit_bias_3d(S, M, dv_truth, T) -> np.ndarray:
    """Accelerometer bias (3,) from ``dv_truth = S - M b + g T`` over the intervals (least sq.)."""
    g = np.array([0.0, 0.0, -GRAVITY])
    A = -M.reshape(-1, 3)
    y = (dv_truth - S - g * T[:, None]).reshape(-1)
    return np.linalg.lstsq(A, y, rcond=None)[0]


def integrate_imu(v0, S, M, b, T) -> np.ndarray:
    """Velocities at the keys from the IMU alone: ``v_k+1 = v_k + S_k - M_k b + g T_k``."""
    g = np.array([0.0, 0.0, -GRAVITY])
    dv = S - np.einsum("nij,j->ni", M, b) + g * T[:, None]
    return np.vstack([v0, v0 + np.cumsum(dv, axis=0)])


def drag_graph_velocity(gt_half, samples, S, M, T, fit: DragFit, bias3, sigma_inc, v0):
    """Batch LM over velocities with IMU increments and drag factors; attitude fixed from
    ``gt_half``; bias and k with priors from the first half. Returns (N, 3) velocities."""
    g = np.array([0.0, 0.0, -GRAVITY])
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    n = len(gt_half.t)
    bias0 = gtsam.imuBias.ConstantBias(bias3, np.zeros(3))
    graph.add(
        gtsam.PriorFactorConstantBias(
            B(0),
            bias0,
            gtsam.noiseModel.Diagonal.Sigmas(
                np.r_[np.full(3, SIGMA_ACCEL_BIAS), np.full(3, SIGMA_GYRO_BIAS)]
            ),
        )
    )
    values.insert(B(0), bias0)
    graph.add(
        gtsam.PriorFactorVector(
            D(0), np.array([fit.k]), gtsam.noiseModel.Isotropic.Sigma(1, fit.k_se_autocorr)
        )
    )
    values.insert(D(0), np.array([fit.k]))
    graph.add(gtsam.PriorFactorVector(V(0), v0, gtsam.noiseModel.Isotropic.Sigma(3, SIGMA_V0)))
    drag_noise = gtsam.noiseModel.Isotropic.Sigma(2, fit.residual_std)
    pose_noise = gtsam.noiseModel.Isotropic.Sigma(6, SIGMA_POSE_FIXED)
    R_all = gt_half.world_R_body()
    v_init = integrate_imu(v0, S, M, bias3, T)
    for k in range(n):
        pose = gtsam.Pose3(gtsam.Rot3(R_all[k]), np.zeros(3))
        values.insert(X(k), pose)
        graph.add(gtsam.PriorFactorPose3(X(k), pose, pose_noise))
        values.insert(V(k), v_init[k])
        graph.add(
            make_accel_drag_factor(
                X(k), V(k), B(0), D(0), samples.mean_body_accel[k, :2], drag_noise
            )
        )
    for k in range(n - 1):
        Sk, Mk, Tk = S[k], M[k], T[k]
        noise = gtsam.noiseModel.Isotropic.Sigma(3, sigma_inc[k])

        def inc_error(this, vals, H, k=k, Sk=Sk, Mk=Mk, Tk=Tk):
            b = vals.atConstantBias(B(0)).accelerometer()
            e = vals.atVector(V(k + 1)) - vals.atVector(V(k)) - (Sk - Mk @ b + g * Tk)
            if H is not None:
                H[0] = -np.eye(3)
                H[1] = np.eye(3)
                H[2] = np.hstack([Mk, np.zeros((3, 3))])
            return e

        graph.add(gtsam.CustomFactor(noise, [V(k), V(k + 1), B(0)], inc_error))
    params = gtsam.LevenbergMarquardtParams()
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    vel = np.array([result.atVector(V(k)) for k in range(n)])
    return vel, float(result.atVector(D(0))[0]), result.atConstantBias(B(0)).accelerometer()


def rmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1))))


def describe(name: str, fit: DragFit) -> str:
    return (
        f"{name:22s} k = {fit.k:+.3f} 1/s  SE {fit.k_se:.3f} "
        f"(autocorr-corrected {fit.k_se_autocorr:.3f}, rho1 {fit.rho1:.2f})  "
        f"bias {np.array2string(fit.bias, precision=3)} m/s^2  "
        f"R^2 {fit.r2:.2f}  resid std {fit.residual_std:.3f} m/s^2  n {fit.n}  "
        f"u in [{fit.velocity_range[0]:.2f}, {fit.velocity_range[1]:.2f}] m/s"
    )


def holds(fit: DragFit) -> bool:
    """The drag model is supported on an axis when k is positive and significant (> 3 corrected
    standard errors)."""
    return fit.k > 0 and fit.k > 3.0 * fit.k_se_autocorr


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", type=Path, default=FOLDER)
    parser.add_argument("--imu", default="IMU_1.csv", help="IMU file (IMU_1.csv ... or IMUAvg.csv)")
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "drag_phantom4.png")
    args = parser.parse_args()

    # 1. Data, mount, clocks. The mount is fitted on IMU_1's attitude: IMUAvg's Euler yaw is the
    # mean of wrapped angles and jumps (see the reader's meta["euler_yaw_jumps"]).
    raw_ref = read_phantom4(args.folder, "IMU_1.csv")
    mount = estimate_body_R_imu(raw_ref)
    print(f"data: {args.folder} (IMU file {args.imu})")
    print(
        f"IMU-to-airframe rotation (rotation vector, deg): "
        f"{np.array2string(np.degrees(so3_log(mount.body_R_imu)), precision=2)}; "
        f"Xsens-to-DJI world yaw {np.degrees(so3_log(mount.gt_world_R_imu_world))[2]:+.1f} deg; "
        "attitude residual RMS "
        f"{mount.residual_rms_deg:.2f} deg over {mount.samples} samples (the mount's yaw is weakly "
        "determined on one heading; its effect on f_x is second order)"
    )
    raw = read_phantom4(args.folder, args.imu) if args.imu != "IMU_1.csv" else raw_ref
    flight = with_body_axes(raw, mount.body_R_imu)
    gt = flight.ground_truth
    clock = estimate_time_offset(
        gt.t,
        tilt_angle(gt.world_R_body()),
        raw_ref.attitude.t,
        tilt_angle(quat_wxyz_to_matrix(raw_ref.attitude.world_q_body_wxyz)),
        MAX_CLOCK_OFFSET_S,
        min_overlap_s=10.0,
    )
    shift = clock.offset_s
    print(
        f"clock check (tilt cross-correlation): t_gt = t_imu {shift:+.3f} s "
        f"(r = {clock.correlation:.3f}); applied to the IMU"
    )

    # 2. Identification on the whole flight.
    samples = drag_samples(flight, WINDOW_S, shift)
    fits = {
        "joint x-y (one k)": fit_linear_drag(samples, (0, 1)),
        "x (forward)": fit_linear_drag(samples, (0,)),
        "y (left)": fit_linear_drag(samples, (1,)),
    }
    print("\nregression f_a = -k u_a + b_a on 10 Hz interval means (whole flight):")
    for name, fit in fits.items():
        print("  " + describe(name, fit))
    fx, fy = fits["x (forward)"], fits["y (left)"]
    print(f"  for reference, PX4 EKF2_MCOEF default: {PX4_DEFAULT_MCOEF} 1/s")
    print("verdict:")
    print(
        f"  x (forward): {'k significant' if holds(fx) else 'MODEL DOES NOT HOLD'}: "
        f"k = {fx.k:.3f} +- {fx.k_se_autocorr:.3f} 1/s; "
        f"it explains R^2 = {fx.r2:.2f} of the variance"
    )
    if not holds(fy):
        print(
            f"  y (left): MODEL DOES NOT HOLD on this flight: k = {fy.k:+.3f} "
            f"+- {fy.k_se_autocorr:.3f} 1/s; lateral velocity spans only "
            f"[{fy.velocity_range[0]:.2f}, {fy.velocity_range[1]:.2f}] m/s (too little excitation; "
            "wind or heading error can dominate)"
        )
    half_t = 0.5 * (gt.t[0] + gt.t[-1])
    first = fit_linear_drag(samples.select(samples.t < half_t), (0,))
    second = fit_linear_drag(samples.select(samples.t >= half_t), (0,))
    print("  halves (x): " + describe("first half", first))
    print("              " + describe("second half", second))
    if abs(first.k - second.k) > 3.0 * np.hypot(first.k_se_autocorr, second.k_se_autocorr):
        print("  the halves disagree beyond 3 SE: k is not stable over this flight")
    elif not holds(second):
        print(
            "  second half: constant speed, k is not identifiable there (k and bias trade off); "
            "the identification relies on the acceleration phase"
        )

    # 3. Velocity on the second half from IMU + attitude + drag (k, bias from the first half).
    key_sel = gt.t >= half_t
    gt2 = gt.select(key_sel)
    t_keys = gt2.t
    s2 = drag_samples(flight, WINDOW_S, shift)
    s2 = s2.select(np.isin(s2.t, t_keys))
    if len(s2.t) != len(t_keys):
        raise SystemExit("internal: interval means missing on the second half")
    S, M, counts = velocity_increments(flight, t_keys, shift)
    T = np.diff(t_keys)
    gt1 = gt.select(gt.t < half_t)
    S1, M1, _ = velocity_increments(flight, gt1.t, shift)
    bias3 = fit_bias_3d(S1, M1, np.diff(gt1.world_v_body, axis=0), np.diff(gt1.t))
    sigma_a = accel_noise_discrete(flight)
    dt_imu = 1.0 / flight.imu.rate_hz
    sigma_inc = np.sqrt((sigma_a * dt_imu) ** 2 * counts + (GRAVITY * SIGMA_ATTITUDE * T) ** 2)
    v0 = gt2.world_v_body[0]
    v_imu = integrate_imu(v0, S, M, bias3, T)
    v_graph, k_post, b_post = drag_graph_velocity(gt2, s2, S, M, T, first, bias3, sigma_inc, v0)
    u_drag_x = -(s2.mean_body_accel[:, 0] - first.bias[0]) / first.k
    truth = gt2.world_v_body
    u_truth = np.einsum("nji,nj->ni", gt2.world_R_body(), truth)
    print(
        f"\nvelocity on the second half ({t_keys[0]:.1f}-{t_keys[-1]:.1f} s, {len(t_keys)} keys); "
        f"from the first half: k = {first.k:.3f} 1/s, accel bias (body, from RTK velocity "
        f"increments) {np.array2string(bias3, precision=3)} m/s^2:"
    )
    res = {
        "IMU integration, zero bias": integrate_imu(v0, S, M, np.zeros(3), T),
        "IMU integration, first-half bias": v_imu,
        "GTSAM graph: IMU + drag factors": v_graph,
    }
    for name, v in res.items():
        print(
            f"  {name:34s} horizontal RMSE {rmse(v[:, :2], truth[:, :2]):.3f} m/s, "
            f"3-D RMSE {rmse(v, truth):.3f} m/s, final horizontal error "
            f"{np.linalg.norm(v[-1, :2] - truth[-1, :2]):.3f} m/s"
        )
    print(
        f"  {'drag model alone, u_x = -(f_x-b)/k':34s} forward-velocity RMSE "
        f"{rmse(u_drag_x[:, None], u_truth[:, :1]):.3f} m/s"
    )
    print(
        f"  graph posterior k = {k_post:.3f} 1/s, "
        f"accel bias {np.array2string(b_post, precision=3)} m/s^2"
    )
    print(
        "  (graph: fgnav.factors.accel_drag factors + IMU velocity-increment CustomFactors, "
        "gtsam.LevenbergMarquardtOptimizer)"
    )

    offset_second = float(np.mean(s2.mean_body_accel[:, 0] - first.predict(u_truth)[:, 0]))
    err_graph = rmse(v_graph[:, :2], truth[:, :2])
    err_imu = rmse(v_imu[:, :2], truth[:, :2])
    print("\nconclusion:")
    if err_graph < err_imu:
        print(
            f"  the drag model helps: horizontal velocity RMSE {err_graph:.2f} m/s with drag vs "
            f"{err_imu:.2f} m/s by IMU integration alone"
        )
    else:
        print(
            "  THE DRAG MODEL DOES NOT HOLD WELL ENOUGH ON THIS FLIGHT TO AID VELOCITY: with k "
            f"and bias from the first half, IMU + drag gives {err_graph:.2f} m/s horizontal RMSE "
            f"on the second half vs {err_imu:.2f} m/s for IMU integration with the same bias. "
            "At constant speed the forward specific force departs from the first-half model by "
            f"{offset_second:+.2f} m/s^2 on average (= {offset_second / first.k:+.2f} m/s of "
            "velocity at that k), so a fixed k and bias do not carry over (wind: airspeed is not "
            "ground speed; or accelerometer drift)."
        )

    # Figure.
    fig = Figure(figsize=(10, 9))
    ax = fig.subplots(3, 1)
    ax[0].scatter(
        samples.body_velocity[:, 0], samples.mean_body_accel[:, 0], s=6, label="x (forward)"
    )
    ax[0].scatter(samples.body_velocity[:, 1], samples.mean_body_accel[:, 1], s=6, label="y (left)")
    u = np.linspace(samples.body_velocity[:, :2].min(), samples.body_velocity[:, :2].max(), 10)
    ax[0].plot(u, -fx.k * u + fx.bias[0], "k-", label=f"x fit k={fx.k:.2f} 1/s, R^2={fx.r2:.2f}")
    ax[0].set_xlabel("body velocity [m/s]")
    ax[0].set_ylabel("specific force [m/s^2]")
    ax[0].legend(fontsize=8)
    ax[0].set_title(f"Phantom 4 straight line ({args.imu}): rotor drag f = -k u + b")
    ax[1].plot(samples.t, samples.mean_body_accel[:, 0], lw=0.8, label="f_x measured (0.1 s mean)")
    ax[1].plot(
        samples.t, fx.predict(samples.body_velocity)[:, 0], label="-k u_x + b (whole-flight fit)"
    )
    ax[1].set_ylabel("m/s^2")
    ax[1].legend(fontsize=8)
    ax[2].plot(t_keys, np.linalg.norm(truth[:, :2], axis=1), "k", label="RTK")
    ax[2].plot(
        t_keys, np.linalg.norm(v_imu[:, :2], axis=1), label="IMU integration (first-half bias)"
    )
    ax[2].plot(t_keys, np.linalg.norm(v_graph[:, :2], axis=1), label="IMU + drag (GTSAM)")
    ax[2].set_xlabel("time [s]")
    ax[2].set_ylabel("horizontal speed [m/s]")
    ax[2].legend(fontsize=8)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"\nfigure: {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
