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
from fgnav.datasets.geometry import quat_wxyz_to_matrix, so3_log
from fgnav.datasets.time_offset import align_mocap, read_motive_csv
from fgnav.datasets.ulog import interpolate_attitude, read_ulog

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
HANDHELD = DATA / "px4_fmuv5_quad_handheld_optitrack"
#: Search window for the offset [s] around the difference of the two recordings' start times.
MAX_OFFSET_S = 10.0


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
    al = align_mocap(flight, mocap, MAX_OFFSET_S)
    print("offset convention: t_ulog = t_mocap + offset (ULog time = seconds since PX4 boot)")
    print(
        f"tilt angle     : offset {al.tilt.offset_s:.4f} s  (correlation {al.tilt.correlation:.4f})"
    )
    print(
        f"angular rate   : offset {al.rate.offset_s:.4f} s  (correlation {al.rate.correlation:.4f})"
    )
    print(f"difference     : {1e3 * abs(al.tilt.offset_s - al.rate.offset_s):.1f} ms")
    print(
        f"mocap t=0 is {al.offset_s - flight.attitude.t[0]:.3f} s after the first vehicle_attitude "
        f"sample and {al.offset_s - flight.imu.t[0]:.3f} s after the first IMU sample"
    )
    print(
        f"rigid body -> vehicle body rotation (rotation vector, deg): "
        f"{np.array2string(np.degrees(so3_log(al.rb_R_body.T)), precision=1)}"
    )
    for label, off in (("with offset", al.offset_s), ("offset - 0.5 s", al.offset_s - 0.5)):
        rms, tilt_rms = attitude_residual_deg(flight, mocap, off)
        print(
            f"attitude after fixed-rotation fit, {label:14s}: "
            f"RMS {rms:.2f} deg, tilt RMS {tilt_rms:.2f} deg"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
