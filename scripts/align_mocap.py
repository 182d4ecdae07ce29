"""Clock offset between a PX4 ULog and an OptiTrack/Motive take of the same motion.

Two independent signals are cross-correlated: the tilt angle (PX4 ``vehicle_attitude`` vs mocap
orientation) and the angular-rate magnitude (PX4 gyro vs differentiated mocap orientation). Then
the fixed world and body rotations between the two attitude sources are fitted at that offset and
the attitude residual is printed, with and without the offset.

Usage::

    .venv/bin/python scripts/align_mocap.py [LOG.ulg MOCAP.csv]

Defaults to ``../shared/data/real/px4_fmuv5_quad_handheld_optitrack``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from fgnav.datasets.frames import align_rotation_sequences, tilt_angle
from fgnav.datasets.geometry import quat_wxyz_to_matrix
from fgnav.datasets.time_offset import body_rate_magnitude, estimate_time_offset, read_motive_csv
from fgnav.datasets.ulog import interpolate_attitude, read_ulog

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
HANDHELD = DATA / "px4_fmuv5_quad_handheld_optitrack"
#: Search window for the offset [s] around the difference of the two recordings' start times.
MAX_OFFSET_S = 10.0
#: Moving average applied to the angular-rate magnitudes (mocap differentiation noise) [s].
RATE_SMOOTH_S = 0.05


def attitude_residual_deg(flight, mocap, offset_s: float, stride: int = 5) -> tuple[float, float]:
    """RMS attitude residual and RMS tilt difference [deg] after fitting fixed world/body
    rotations, with mocap times shifted by ``offset_s``."""
    t = mocap.t + offset_s
    sel = np.flatnonzero((t > flight.attitude.t[0]) & (t < flight.attitude.t[-1]))[::stride]
    R_px4 = quat_wxyz_to_matrix(interpolate_attitude(flight.attitude, t[sel]))
    R_mocap = mocap.world_R_body()[sel]
    a_R_b, y_R_x, resid = align_rotation_sequences(R_px4, R_mocap)
    tilt_diff = tilt_angle(R_px4) - tilt_angle(a_R_b @ R_mocap @ y_R_x)
    return float(np.degrees(np.sqrt(np.mean(resid**2)))), float(
        np.degrees(np.sqrt(np.mean(tilt_diff**2)))
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("ulog", nargs="?", default=HANDHELD / "log008.ulg", type=Path)
    parser.add_argument(
        "mocap", nargs="?", default=HANDHELD / "optitrack_take_2023-04-16.csv", type=Path
    )
    args = parser.parse_args()
    flight = read_ulog(args.ulog)
    take = read_motive_csv(args.mocap)
    mocap = take.trajectory
    print(
        f"mocap: rigid body {take.rigid_body!r} of {list(take.rigid_bodies)}, "
        f"{len(mocap)} frames at {take.frame_rate_hz:.0f} Hz, {take.skipped_rows} untracked frames"
    )
    guess = flight.attitude.t[0] - mocap.t[0]
    tilt = estimate_time_offset(
        flight.attitude.t,
        tilt_angle(quat_wxyz_to_matrix(flight.attitude.world_q_body_wxyz)),
        mocap.t,
        tilt_angle(mocap.world_R_body()),
        MAX_OFFSET_S,
        initial_offset_s=guess,
    )
    t_mid, rate = body_rate_magnitude(mocap.t, mocap.world_q_body_wxyz)
    rate_res = estimate_time_offset(
        flight.imu.t,
        np.linalg.norm(flight.imu.body_omega, axis=1),
        t_mid,
        rate,
        MAX_OFFSET_S,
        initial_offset_s=guess,
        smooth_s=RATE_SMOOTH_S,
    )
    print("offset convention: t_ulog = t_mocap + offset (ULog time = seconds since PX4 boot)")
    print(f"tilt angle     : offset {tilt.offset_s:.4f} s  (correlation {tilt.correlation:.4f})")
    print(
        f"angular rate   : offset {rate_res.offset_s:.4f} s  "
        f"(correlation {rate_res.correlation:.4f})"
    )
    print(f"difference     : {1e3 * abs(tilt.offset_s - rate_res.offset_s):.1f} ms")
    offset = 0.5 * (tilt.offset_s + rate_res.offset_s)
    print(
        f"mocap t=0 is {offset - flight.attitude.t[0]:.3f} s after the first vehicle_attitude "
        f"sample and {offset - flight.imu.t[0]:.3f} s after the first IMU sample"
    )
    for label, off in (("with offset", offset), ("offset - 0.5 s", offset - 0.5)):
        rms, tilt_rms = attitude_residual_deg(flight, mocap, off)
        print(
            f"attitude after fixed-rotation fit, {label:14s}: "
            f"RMS {rms:.2f} deg, tilt RMS {tilt_rms:.2f} deg"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
