"""End drift of the smoothers on the Crazyflie flow-deck flights split into its yaw part and its
speed part (analysis with Vicon; nothing here feeds an estimator).

    .venv/bin/python scripts/crazyflie_drift_parts.py [LOG ...] [--methods batch,fixed-lag]

Per flight and method, with the start pose known (the estimate turned and moved to the truth's
first yaw and position, as ``start_drift_pct``), from the estimate's horizontal velocity
integrated over the truth's time stamps: the drift as is (``drift``, % of the path; close to
``start_drift_pct``, which uses the positions), with the estimate's velocity turned by its yaw
error at each time (``true yaw``: what is left is the speed and the lag), and with its speed
replaced by the truth's (``true speed``: what is left is the heading); the estimate's yaw error at
the end [deg], and the raw gyro's (the body rate integrated from the truth's first attitude with
no bias: the yaw a filter without a yaw source can at best keep). ``speed scale``: least-squares
ratio of the estimated to the true speed above 0.5 m/s.
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path

import numpy as np
from fgnav.datasets.geometry import quat_wxyz_to_matrix, wrap_angle, yaw_of
from fgnav.datasets.load import load_flight

from fgnav.eval.metrics import associate
from fgnav.methods import METHODS

DEFAULT_DIR = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / ("crazyflie_util_flowdeck")
)


def default_logs() -> list[Path]:
    """The shared flow-deck logs, in flight-number order."""
    return sorted(DEFAULT_DIR.glob("0425-traj*"), key=lambda p: int(p.name[9:]))


def _rz(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def gyro_end_yaw_error(flight) -> float:
    """Yaw error [deg] at the truth's last time of the body rate integrated (zero-order hold, no
    bias) from the truth's first attitude."""
    gt = flight.ground_truth
    imu = flight.imu
    t, w = np.asarray(imu.t, float), np.asarray(imu.body_omega, float)
    s = (t >= gt.t[0]) & (t <= gt.t[-1])
    t, w = t[s], w[s]
    R = quat_wxyz_to_matrix(gt.world_q_body_wxyz[0])
    for i in range(len(t) - 1):
        phi = w[i] * (t[i + 1] - t[i])
        a = float(np.linalg.norm(phi))
        K = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]])
        if a > 0:
            K = K / a
            R = R @ (np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K)
    return math.degrees(
        float(wrap_angle(yaw_of(R) - yaw_of(quat_wxyz_to_matrix(gt.world_q_body_wxyz[-1]))))
    )


def parts(est, flight) -> dict[str, float]:
    gt_all = flight.ground_truth
    a = associate(est.trajectory, gt_all)
    idx, gt = a.est_index, a.gt
    tr = est.trajectory
    ye = np.array([yaw_of(quat_wxyz_to_matrix(q)) for q in tr.world_q_body_wxyz[idx]])
    yt = np.array([yaw_of(quat_wxyz_to_matrix(q)) for q in gt.world_q_body_wxyz])
    d0 = float(wrap_angle(yt[0] - ye[0]))
    v = (_rz(np.array(d0)) @ tr.world_v_body[idx][:, :2].T).T
    vt = gt.world_v_body[:, :2]
    err = wrap_angle(yt - (ye + d0))
    dt = np.diff(gt.t)
    path = float(np.sum(np.linalg.norm(np.diff(gt.world_t_body[:, :2], axis=0), axis=1)))

    def drift(vel: np.ndarray) -> float:
        d = np.sum(0.5 * (vel[1:] - vt[1:] + vel[:-1] - vt[:-1]) * dt[:, None], axis=0)
        return 100.0 * float(np.linalg.norm(d)) / path

    v_yaw = np.einsum("nij,nj->ni", _rz(err), v)
    sp, spt = np.linalg.norm(v, axis=1), np.linalg.norm(vt, axis=1)
    v_speed = v * (spt / np.maximum(sp, 1e-9))[:, None]
    return {
        "drift": drift(v),
        "true_yaw": drift(v_yaw),
        "true_speed": drift(v_speed),
        "end_yaw_deg": -math.degrees(float(err[-1])),
        "scale": speed_scale(v, vt),
        "path_m": path,
    }


def speed_scale(v: np.ndarray, vt: np.ndarray) -> float:
    """Least-squares ratio of the estimated horizontal speed (of ``v``, (N, 2) [m/s]) to the true
    one (of ``vt``) over the samples where the truth is above 0.5 m/s and the estimate finite."""
    sp, spt = np.linalg.norm(v, axis=1), np.linalg.norm(vt, axis=1)
    m = (spt > 0.5) & np.isfinite(sp)
    return float(np.sum(sp[m] * spt[m]) / np.sum(spt[m] ** 2))


def parse_table_args(argv: list[str] | None, doc: str, option: str, default: str):
    """Command line of a drift-parts table script: ``LOG ...`` (default: :func:`default_logs`) and
    one comma-separated ``option``; logging set to errors only. ``(logs, option values)``."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("logs", nargs="*", type=Path)
    ap.add_argument(option, default=default)
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    values = getattr(a, option.lstrip("-").replace("-", "_")).split(",")
    return a.logs or default_logs(), values


def parts_cells(r: dict[str, float]) -> list[str]:
    """The ``drift``, ``true yaw`` and ``true speed`` cells [%] of a row from :func:`parts`."""
    return [f"{r['drift']:.2f}", f"{r['true_yaw']:.2f}", f"{r['true_speed']:.2f}"]


def print_row(*cells: str) -> None:
    """One row of a Markdown table, flushed (each row of these tables takes minutes)."""
    print("| " + " | ".join(cells) + " |", flush=True)


def print_header(*columns: str) -> None:
    """Markdown table header: ``columns``, the first two left-aligned, the others right."""
    print_row(*columns)
    print("|:--|:--|" + "--:|" * (len(columns) - 2))


def main(argv: list[str] | None = None) -> int:
    logs, methods = parse_table_args(argv, __doc__, "--methods", "batch,fixed-lag")
    print_header(
        "flight",
        "method",
        "drift [%]",
        "true yaw [%]",
        "true speed [%]",
        "end yaw err [deg]",
        "raw gyro end yaw err [deg]",
        "speed scale",
    )
    for p in logs:
        f = load_flight(p)
        g = gyro_end_yaw_error(f)
        for m in methods:
            r = parts(METHODS[m].run(f, {}), f)
            end_yaw = [f"{r['end_yaw_deg']:+.1f}", f"{g:+.1f}"]
            print_row(p.name[5:], m, *parts_cells(r), *end_yaw, f"{r['scale']:.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
