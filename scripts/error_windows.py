"""Position error over time of the methods of a ``fgnav compare`` output, and their ATE on one
common span (issue 15: a filter that emits nothing before its scale fit is scored over a shorter
span than a smoother that emits from its start).

    .venv/bin/fgnav compare MANIFEST --out D --methods fixed-lag,fixed-lag@lag,ukf003,msf-ekf \
        --no-figures
    .venv/bin/python scripts/error_windows.py MANIFEST D [--window 5] [--methods a,b]

Prints, per method: the ATE as ``fgnav compare`` scores it (SE(3) alignment over the method's own
samples), the ATE on the common span (from the latest first sample of the methods listed to the
end, each method aligned over that span) and the ATE after ``--late`` seconds (aligned there:
the start left out); then the RMSE per window of ``--window`` seconds (own-span alignment).
Times are seconds from the first IMU sample. Reads ``D/<method>/estimate.tum`` (``@`` in a
method name is ``_`` in its directory).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from fgnav.datasets.load import load_flight
from fgnav.datasets.tum import read_tum

from fgnav.eval.align import align, associate


def _rmse_cm(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2)) * 100.0) if e.size else float("nan")


def _errors(t: np.ndarray, x: np.ndarray, g: np.ndarray, lo: float) -> tuple[np.ndarray, ...]:
    k = t >= lo
    al = align(x[k], g[k], "se3")
    return t[k], np.linalg.norm(g[k] - al.apply_positions(x[k]), axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("manifest")
    ap.add_argument("out", help="the fgnav compare output directory")
    ap.add_argument("--methods", default="fixed-lag,fixed-lag@lag,ukf003,msf-ekf")
    ap.add_argument("--window", type=float, default=5.0, help="window length [s]")
    ap.add_argument("--late", type=float, default=20.0, help="start of the late span [s]")
    args = ap.parse_args()
    flight = load_flight(args.manifest)
    gt, t0 = flight.ground_truth, float(flight.imu.t[0])
    data = {}
    for m in args.methods.split(","):
        path = Path(args.out) / m.replace("@", "_") / "estimate.tum"
        if not path.is_file():
            print(f"{m}: no {path}")
            continue
        est = read_tum(path)
        a = associate(est, gt)
        data[m] = (est.t[a.est_index] - t0, est.world_t_body[a.est_index], a.gt.world_t_body)
    if not data:
        return
    t_c = max(float(d[0][0]) for d in data.values())
    print(f"common span {t_c:.1f} s - end; late span {args.late:.1f} s - end")
    own = {}
    for m, (t, x, g) in data.items():
        own[m] = _errors(t, x, g, -np.inf)
        _, e_c = _errors(t, x, g, t_c)
        _, e_l = _errors(t, x, g, args.late)
        print(
            f"{m:14s} own span {t[0]:5.1f}-{t[-1]:5.1f} s: ATE {_rmse_cm(own[m][1]):6.2f} cm "
            f"(n={t.size}) | common span {_rmse_cm(e_c):6.2f} cm (n={e_c.size}) | "
            f"late {_rmse_cm(e_l):6.2f} cm"
        )
    w = args.window
    end = max(float(d[0][-1]) for d in data.values())
    print("window [s]  " + " ".join(f"{m[:13]:>13s}" for m in own) + "   (RMSE [cm])")
    for lo in np.arange(0.0, end + w, w):
        cells = []
        for t, e in own.values():
            k = (t >= lo) & (t < lo + w)
            cells.append(f"{_rmse_cm(e[k]):13.2f}" if k.any() else f"{'-':>13s}")
        if any(c.strip() != "-" for c in cells):
            print(f"{lo:5.0f}-{lo + w:<5.0f} " + " ".join(cells))


if __name__ == "__main__":
    main()
