"""Per-flight summary of Crazyflie SD-card logs: streams (mean rate, duration, samples), what the
reader left out by reason, and the downward sensors against the Vicon truth.

    .venv/bin/python scripts/crazyflie_summary.py [LOG ...]

Without arguments: the seven UTIL logs in ../shared/data/real/crazyflie_util_flowdeck. Prints a
markdown table per part (streams; skipped; ToF and flow vs Vicon, see
``fgnav.datasets.downward_check``).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from fgnav.datasets.crazyflie import read_crazyflie
from fgnav.datasets.downward_check import flow_vs_truth, range_vs_truth

DEFAULT_DIR = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / ("crazyflie_util_flowdeck")
)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="*", type=Path)
    args = ap.parse_args(argv)
    logs = args.logs or sorted(DEFAULT_DIR.glob("0425-traj*"), key=lambda p: int(p.name[9:]))
    streams = [
        "| flight | read [s] | "
        + " | ".join(f"{s} n / Hz / s" for s in ("imu", "flow", "range", "ground_truth"))
        + " |"
    ]
    skipped = ["| flight | imu | flow dt one loop (after gap) | range | ground truth |"]
    fits = [
        "| flight | ToF scale | ToF offset [mm] | ToF noise [mm] | flow px/rad x, y | "
        "flow resid [px] | lag-1 | after-gap resid (one loop / step) | after-gap motion "
        "[loops] |"
    ]
    for p in logs:
        t0 = time.perf_counter()
        f = read_crazyflie(p)
        dt_read = time.perf_counter() - t0
        cells = []
        for s in (f.imu, f.flow, f.range, f.ground_truth):
            cells.append(f"{len(s)} / {(len(s) - 1) / s.duration:.1f} / {s.duration:.1f}")
        streams.append(f"| {f.name} | {dt_read:.2f} | " + " | ".join(cells) + " |")

        def skips(d: dict) -> str:
            return (
                ", ".join(
                    f"{k.removeprefix('skipped_')} {v}"
                    for k, v in d.items()
                    if k.startswith("skipped") and v
                )
                or "none"
            )

        skipped.append(
            f"| {f.name} | {skips(f.meta['imu'])} | {f.meta['flow']['dt_one_loop_after_gap']} | "
            f"{skips(f.meta['range'])} | {skips(f.meta['ground_truth'])} |"
        )
        r = range_vs_truth(f)
        w = flow_vs_truth(f)
        step = np.diff(f.flow.t, prepend=f.flow.t[0] - f.flow.dt[0])
        alt = flow_vs_truth(f, dt=step)
        fits.append(
            f"| {f.name} | {r.scale:.4f} | {r.offset_fixed_scale * 1e3:.1f} | {r.noise * 1e3:.1f} "
            f"| {w.pixels_per_rad[0]:.1f}, {w.pixels_per_rad[1]:.1f} | {w.residual_std:.3f} | "
            f"{w.lag1:.2f} | {w.residual_std_after_gap:.3f} / {alt.residual_std_after_gap:.3f} | "
            f"{w.after_gap_interval_ratio:.2f} |"
        )
    for table in (streams, skipped, fits):
        print(table[0])
        print("|" + "---|" * (table[0].count("|") - 1))
        print("\n".join(table[1:]))
        print()


if __name__ == "__main__":
    main()
