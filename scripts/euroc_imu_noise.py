"""In-flight IMU noise of a EuRoC flight measured against its ground truth (analysis with the
truth; nothing here feeds an estimator).

    .venv/bin/python scripts/euroc_imu_noise.py [MANIFEST] [--windows 0.05,0.1,0.2,0.5,1]

The calibration that EuRoC ships (and ORB-SLAM3's ``EuRoC.yaml``, which the manifests read) gives
the ADIS16448's noise densities at rest (accelerometer 2.0e-3 m/s^2/sqrt(Hz), gyro 1.7e-4
rad/s/sqrt(Hz)). What an estimator meets in flight is larger: rotor vibration, scale-factor and
misalignment errors, g-sensitivity. Over windows of ``T`` seconds while the body moves (truth speed
above 0.1 m/s), the IMU's velocity change ``sum R_k (f_k - b_a,k) dt + g T`` (truth attitude and
accelerometer bias) is compared with the truth's ``v(t + T) - v(t)``, and the gyro's rotation
``prod Exp((w_k - b_g,k) dt)`` (truth gyro bias) with the truth's ``R(t)^T R(t + T)``; the
per-axis RMS of the differences divided by ``sqrt(T)`` is the equivalent white-noise density.
The truth (the ASL pose, velocity and biases at 200 Hz) has errors of its own that these
differences include, so the figures are upper bounds; a density that grows with ``T`` is error
that is not white (bias, scale). Needs a ground truth with velocity and biases (EuRoC's
``state_groundtruth_estimate0``, as V1_02's).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np
from fgnav.datasets.load import load_flight
from scipy.spatial.transform import Rotation, Slerp

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "datasets" / "manifests" / "euroc_v102_orbslam2_kf1.toml"
GRAVITY = np.array([0.0, 0.0, -9.81])


def window_errors(flight, window_s: float, min_speed: float = 0.1) -> dict[str, np.ndarray]:
    """Per-axis RMS of the IMU's velocity change [m/s] and rotation [rad] against the truth's
    over windows of ``window_s`` seconds (body moving), and the number of windows."""
    gt, imu = flight.ground_truth, flight.imu
    if gt.world_v_body is None or gt.accel_bias is None or gt.gyro_bias is None:
        raise SystemExit(f"{flight.name}: the ground truth has no velocity and biases")
    gt_t = np.asarray(gt.t)
    t = np.asarray(imu.t)
    keep = (t > gt_t[0] + 1.0) & (t < gt_t[-1] - 1.0)
    t, f, w = t[keep], np.asarray(imu.body_accel)[keep], np.asarray(imu.body_omega)[keep]

    def at(x) -> np.ndarray:
        x = np.asarray(x, float)
        return np.stack([np.interp(t, gt_t, x[:, i]) for i in range(x.shape[1])], 1)

    v, ba, bg = at(gt.world_v_body), at(gt.accel_bias), at(gt.gyro_bias)
    q = np.asarray(gt.world_q_body_wxyz, float)[:, [1, 2, 3, 0]]
    R = Slerp(gt_t, Rotation.from_quat(q))(t)
    dt = np.diff(t)
    dv = np.einsum("nij,nj->ni", R.as_matrix()[:-1], f[:-1] - ba[:-1]) + GRAVITY
    cum_v = np.r_[np.zeros((1, 3)), np.cumsum(dv * dt[:, None], 0)]
    n = max(1, int(round(window_s / np.median(dt))))
    i0 = np.arange(0, len(t) - n - 1, n)
    i0 = i0[np.linalg.norm(v[i0], axis=1) > min_speed]
    e_v = (cum_v[i0 + n] - cum_v[i0]) - (v[i0 + n] - v[i0])
    steps = Rotation.from_rotvec((w[:-1] - bg[:-1]) * dt[:, None])
    e_r = []
    for i in i0:
        r = Rotation.identity()
        for j in range(i, i + n):
            r = r * steps[j]
        e_r.append(((R[i].inv() * R[i + n]).inv() * r).as_rotvec())
    return {
        "accel": np.sqrt(np.mean(e_v**2, 0)),
        "gyro": np.sqrt(np.mean(np.asarray(e_r) ** 2, 0)),
        "n": np.array(len(i0)),
        "T": np.array(n * np.median(dt)),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("manifest", nargs="?", type=Path, default=DEFAULT)
    ap.add_argument("--windows", default="0.05,0.1,0.2,0.5,1")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    flight = load_flight(a.manifest)
    noise = flight.calib.imu_noise
    print(
        f"{flight.name}: calib.imu_noise (the manifest's, if it sets them) accel "
        f"{noise.accel_noise_density:.3g} m/s^2/sqrt(Hz), gyro "
        f"{noise.gyro_noise_density:.3g} rad/s/sqrt(Hz)"
    )
    print(
        "| window [s] | windows | accel density x, y, z [m/s^2/sqrt(Hz)] | RMS | "
        "gyro density x, y, z [rad/s/sqrt(Hz)] | RMS |"
    )
    print("|--:|--:|:--|--:|:--|--:|")
    for w in (float(x) for x in a.windows.split(",")):
        r = window_errors(flight, w)
        da, dg = r["accel"] / np.sqrt(r["T"]), r["gyro"] / np.sqrt(r["T"])
        rms = lambda x: float(np.sqrt(np.mean(x**2)))  # noqa: E731
        print(
            f"| {float(r['T']):.3f} | {int(r['n'])} | {', '.join(f'{x:.4f}' for x in da)} | "
            f"{rms(da):.4f} | {', '.join(f'{x:.5f}' for x in dg)} | {rms(dg):.5f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
