"""Reproduce seed 002's visual-odometry results (Paz & Nesmachnow, Figs. 11, 13 and 14).

On the simulated ``two-turns`` flight (seed 002 sec. IV-A: hover at 3.5 m, two turns of ~1.1 m
radius while climbing to 4 m, 13.8 m of path, downward camera over a noise carpet):

1. seed 002's ``[q, h]`` EKF (``fgnav.frontends.attitude_ekf``) on the simulated IMU, yaw and
   rangefinder: quaternion and height against the truth (Fig. 11);
2. homography VO dead reckoning from the EKF attitude and height, with orthogonal rectification
   (the paper's proposal) and without (the "traditional" odometry), with OpenCV's free
   decomposition (the paper's Algorithm 2) and with fgnav's attitude-aided level decomposition:
   final and maximum horizontal position error and their % of the path (Figs. 13-14; the paper:
   2.5 cm vs 8 cm, 0.18 % vs 0.57 % of 13.8 m).

The VO starts from the true initial pose (Algorithm 1: "initialise R_0^n and t_0^n"). Errors are
horizontal (x, y), as in Figs. 13-14, at the image times, without any alignment.

Usage::

    .venv/bin/python scripts/reproduce_seed002.py [--seed 2] [--out out/seed002] [--truth-inputs]

``--truth-inputs`` feeds the VO the true attitude and height instead of the EKF's (isolates the
vision part). Plots (PNG) are written to ``--out`` and their paths printed.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from fgnav.datasets.geometry import make_pose, yaw_of  # noqa: E402
from fgnav.datasets.simulate import simulate  # noqa: E402
from fgnav.datasets.types import AttitudeSeries  # noqa: E402

from fgnav.estimate import TimeSeries  # noqa: E402
from fgnav.frontends.attitude_ekf import attitude_errors_rad, run_attitude_ekf  # noqa: E402
from fgnav.frontends.homography_vo import HomographyVOOptions, run  # noqa: E402

PROJECT_ROOT = Path(__file__).resolve().parents[1]
#: Seed 002's reported VO errors (sec. IV-C, Fig. 14): rectified vs. traditional.
PAPER = {
    "rectified_m": 0.025,
    "traditional_m": 0.08,
    "rectified_pct": 0.18,
    "traditional_pct": 0.57,
    "path_m": 13.8,
}
#: Seconds skipped before the EKF error statistics (the paper's Fig. 11 shows a start transient).
EKF_SETTLE_S = 1.0

VARIANTS = {
    "rectified (paper)": HomographyVOOptions(rectify=True, decomposition="opencv"),
    "traditional (paper)": HomographyVOOptions(rectify=False, decomposition="opencv"),
    "rectified + level decomposition": HomographyVOOptions(rectify=True, decomposition="attitude"),
    "traditional + level decomposition": HomographyVOOptions(
        rectify=False, decomposition="attitude"
    ),
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--out", type=Path, default=PROJECT_ROOT / "out" / "seed002")
    ap.add_argument(
        "--truth-inputs",
        action="store_true",
        help="feed the VO the true attitude and height instead of the EKF's",
    )
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    flight = simulate("two-turns", seed=args.seed)
    print(
        f"simulated two-turns seed {args.seed}: {len(flight.images)} images "
        f"{flight.images.camera.width}x{flight.images.camera.height}, "
        f"{time.perf_counter() - t0:.1f} s"
    )
    gt = flight.ground_truth
    ground = float(flight.meta["truth"]["ground_height"])

    # 1. Seed 002's EKF (Fig. 11).
    t0 = time.perf_counter()
    ekf = run_attitude_ekf(flight)
    print(f"EKF over {len(ekf.t)} IMU samples: {time.perf_counter() - t0:.1f} s")
    q_true = gt.world_q_body_wxyz[np.searchsorted(gt.t, ekf.t)]
    q_est = ekf.world_q_body_wxyz * np.sign(np.sum(ekf.world_q_body_wxyz * q_true, axis=1))[:, None]
    h_true = gt.world_t_body[np.searchsorted(gt.t, ekf.t), 2] - ground
    settled = (ekf.t >= ekf.t[0] + EKF_SETTLE_S) & np.isfinite(ekf.height)
    angle, yaw_err = attitude_errors_rad(ekf.world_q_body_wxyz, q_true)
    print(
        f"EKF vs truth after {EKF_SETTLE_S:.0f} s: attitude error RMS "
        f"{np.degrees(np.sqrt(np.mean(angle[settled] ** 2))):.2f} deg (max "
        f"{np.degrees(angle[settled].max()):.2f}), yaw RMS "
        f"{np.degrees(np.sqrt(np.mean(yaw_err[settled] ** 2))):.2f} deg, max |dq| "
        f"{np.abs(q_est - q_true)[settled].max():.4f}, height RMS "
        f"{np.sqrt(np.mean((ekf.height - h_true)[settled] ** 2)) * 100:.1f} cm (max "
        f"{np.abs(ekf.height - h_true)[settled].max() * 100:.1f} cm)"
    )

    if args.truth_inputs:
        attitude = AttitudeSeries(t=gt.t, world_q_body_wxyz=gt.world_q_body_wxyz)
        height = TimeSeries(t=gt.t, value=gt.world_t_body[:, 2] - ground)
        source = "true attitude and height"
    else:
        ok = np.isfinite(ekf.height)
        attitude = ekf.attitude_series()
        height = TimeSeries(t=ekf.t[ok], value=ekf.height[ok])
        source = "EKF attitude and height"

    # 2. VO variants (Figs. 13-14).
    k_img = np.searchsorted(gt.t, flight.images.t)
    T0 = make_pose(gt.world_R_body()[k_img[0]], gt.world_t_body[k_img[0]])
    path = float(np.sum(np.linalg.norm(np.diff(gt.world_t_body[k_img], axis=0), axis=1)))
    print(
        f"\nVO from {source}; truth path {path:.2f} m (paper {PAPER['path_m']} m); "
        "horizontal error, no alignment"
    )
    print(
        f"{'variant':36s} {'final [cm]':>10s} {'max [cm]':>9s} {'final %':>8s} {'max %':>6s} "
        f"{'yaw end [deg]':>13s} {'valid pairs':>11s} {'s':>5s}"
    )
    results = {}
    for name, opts in VARIANTS.items():
        t0 = time.perf_counter()
        res = run(flight, attitude=attitude, height=height, options=opts, initial_world_T_body=T0)
        dt = time.perf_counter() - t0
        traj = res.estimate.trajectory
        k = np.searchsorted(gt.t, traj.t)
        e_xy = np.linalg.norm(traj.world_t_body[:, :2] - gt.world_t_body[k, :2], axis=1)
        yaw_true = yaw_of(gt.world_R_body()[k])
        yaw_end = np.degrees(np.angle(np.exp(1j * (res.yaw.yaw[-1] - yaw_true[-1]))))
        results[name] = (traj, e_xy, res.yaw, k)
        print(
            f"{name:36s} {e_xy[-1] * 100:10.1f} {e_xy.max() * 100:9.1f} "
            f"{e_xy[-1] / path * 100:8.2f} {e_xy.max() / path * 100:6.2f} {yaw_end:13.2f} "
            f"{res.counts['valid_pairs']:5d}/{res.counts['pairs']:<5d} {dt:5.1f}"
        )
    print(
        f"{'paper: rectified / traditional':36s} {PAPER['rectified_m'] * 100:10.1f} "
        f"{PAPER['traditional_m'] * 100:9.1f} {PAPER['rectified_pct']:8.2f} "
        f"{PAPER['traditional_pct']:6.2f}  (final; max not reported)"
    )
    r_fin = results["rectified (paper)"][1][-1]
    u_fin = results["traditional (paper)"][1][-1]
    verdict = "helps" if r_fin < u_fin else "does not help"
    print(
        f"\nRectification {verdict} here: final error {r_fin * 100:.1f} cm vs {u_fin * 100:.1f} cm "
        f"({(r_fin / u_fin - 1) * 100:+.0f} %); paper: 2.5 vs 8 cm (-69 %)."
    )

    # Plots.
    paths = []
    fig, ax = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    tt = gt.t[k_img]
    ax[0].plot(tt, gt.world_t_body[k_img, 0], "k--", label="truth")
    ax[1].plot(tt, gt.world_t_body[k_img, 1], "k--")
    ax[2].plot(tt, np.degrees(np.unwrap(yaw_of(gt.world_R_body()[k_img]))), "k--")
    for name, color in (
        ("traditional (paper)", "tab:blue"),
        ("rectified (paper)", "tab:red"),
        ("rectified + level decomposition", "tab:green"),
    ):
        traj, _, yaw, _ = results[name]
        ax[0].plot(traj.t, traj.world_t_body[:, 0], color=color, label=name)
        ax[1].plot(traj.t, traj.world_t_body[:, 1], color=color)
        ax[2].plot(yaw.t, np.degrees(np.unwrap(yaw.yaw)), color=color)
    ax[0].set_ylabel("x [m]")
    ax[1].set_ylabel("y [m]")
    ax[2].set_ylabel("yaw [deg]")
    ax[2].set_xlabel("t [s]")
    ax[0].legend(fontsize=8)
    fig.suptitle(f"Seed 002 Fig. 13: VO with and without rectification ({source})")
    p = args.out / "fig13_vo_xy_yaw.png"
    fig.savefig(p, dpi=110)
    paths.append(p)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(9, 4))
    for name, (traj, e_xy, _, _) in results.items():
        ax.plot(traj.t, e_xy * 100, label=name)
    ax.set_xlabel("t [s]")
    ax.set_ylabel("horizontal error [cm]")
    ax.legend(fontsize=8)
    ax.set_title("Seed 002 Fig. 14: absolute VO position error")
    p = args.out / "fig14_vo_error.png"
    fig.savefig(p, dpi=110)
    paths.append(p)
    plt.close(fig)

    fig, ax = plt.subplots(5, 1, figsize=(9, 9), sharex=True)
    for i in range(4):
        ax[i].plot(ekf.t, q_true[:, i], "k--")
        ax[i].plot(ekf.t, q_est[:, i], "r")
        ax[i].set_ylabel(f"q{i}")
    ax[4].plot(ekf.t, h_true, "k--", label="truth")
    ax[4].plot(ekf.t, ekf.height, "r", label="EKF")
    ax[4].set_ylabel("h [m]")
    ax[4].set_xlabel("t [s]")
    ax[4].legend(fontsize=8)
    fig.suptitle("Seed 002 Fig. 11: EKF quaternion and height")
    p = args.out / "fig11_ekf.png"
    fig.savefig(p, dpi=110)
    paths.append(p)
    plt.close(fig)
    for p in paths:
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
