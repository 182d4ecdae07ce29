"""Where the push engine's keyframe updates spend their time (issue 15 profile).

Replays a flight through the push-API smoother (``fgnav.solvers.online``) with the smoother's
window and the ``CustomFactor`` callbacks instrumented, and prints per keyframe update, by kind
(plain, relinearising, marginalising, the slowest 1 %): the thread CPU time and wall latency,
the time in ``TimeOrderedSmoother.update`` and in the marginalisation, the number and time of
the Python factor callbacks, iSAM2's relinearised and re-eliminated variables and cliques
(``ISAM2Result``), and the covariance and estimate reads. ``--probe`` also times, every 50th
update, a re-elimination from the window's oldest key and one from its newest (nothing added
or relinearised; these extra updates change the run a little).

    .venv/bin/python scripts/profile_online.py figure8 [--duration 60]
    .venv/bin/python scripts/profile_online.py datasets/manifests/euroc_mh01_orbslam3.toml \\
        [--position-threshold 0.003] [--slam-scale-rw none] [--no-ballast] [--probe]

``figure8`` is the flight of ``scripts/bench_online.py`` (no camera). The instrumentation
adds a few per cent; compare runs made back to back, and read the thread CPU time when the
machine is loaded.

Measured 2026-12-03 (load 3-5, 180 s figure8): defaults CPU p99 4.8-5.4 ms; 3 mm position
threshold without ballast 20-21 ms (relinearising updates: 182 callbacks, 68 variables
relinearised, 131 re-eliminated: iSAM2's batch path relinearised every factor), with ballast
13.1-13.5 ms (91 callbacks). ``--probe`` (60 s): re-eliminating from the oldest key 16.6 ms CPU
without ballast, 2.5 ms with it; from the newest 0.3 ms.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import gtsam
import numpy as np

import fgnav.solvers.online as online
from fgnav.eval.metrics import evaluate, slam_scale_vs_truth
from fgnav.solvers import window
from fgnav.solvers.fixed_lag import FixedLagOptions
from fgnav.solvers.graph import GraphOptions

#: per-update fields: name -> scale for printing (1e3: seconds shown as ms)
FIELDS = {
    "cpu": 1e3,
    "lat": 1e3,
    "upd": 1e3,
    "marg": 1e3,
    "cb_n": 1,
    "cb_ms": 1e3,
    "relin": 1,
    "reelim": 1,
    "cliques": 1,
    "cov": 1e3,
    "read": 1e3,
}


def _n(x) -> int:
    return x if isinstance(x, int) else len(x)


class Profiler:
    """Instruments ``TimeOrderedSmoother``, ``OnlineSmoother`` and ``gtsam.CustomFactor``
    (class attributes, restored by ``close``); ``rows``: one dict of ``FIELDS`` per keyframe
    update; ``probes``: ``(from_oldest, cpu_s, wall_s, n_reeliminated)``."""

    def __init__(self, probe: bool = False) -> None:
        self.rows: list[dict] = []
        self.probes: list[tuple] = []
        self.probe = probe
        self._cur: dict = {}
        self._cb = [0, 0.0]
        self._saved: list[tuple] = []
        tos, osm = window.TimeOrderedSmoother, online.OnlineSmoother
        custom = gtsam.CustomFactor
        cb, cur, prof = self._cb, self._cur, self

        def wrap(fn):
            def timed(this, values, H):
                t = time.perf_counter()
                out = fn(this, values, H)
                cb[0] += 1
                cb[1] += time.perf_counter() - t
                return out

            return timed

        update, marginalize = tos.update, tos._marginalize
        covariances = tos.marginalCovariances
        close_kf, read = osm._close_keyframe, osm._read

        def p_update(self, *a, **k):
            c0, t0 = list(cb), time.perf_counter()
            out = update(self, *a, **k)
            cur["upd"] = cur.get("upd", 0) + time.perf_counter() - t0
            cur["cb_n"] = cur.get("cb_n", 0) + cb[0] - c0[0]
            cur["cb_ms"] = cur.get("cb_ms", 0) + cb[1] - c0[1]
            res = self.getISAM2Result()
            cur["relin"] = cur.get("relin", 0) + _n(res.getVariablesRelinearized())
            cur["reelim"] = cur.get("reelim", 0) + _n(res.getVariablesReeliminated())
            cur["cliques"] = _n(res.getCliques())
            if prof.probe and self._n_updates % 50 == 0 and self._blocks:
                prof._probe(self)
            return out

        def p_marginalize(self):
            t0, n = time.perf_counter(), len(self._stamp)
            marginalize(self)
            if len(self._stamp) != n:
                cur["marg"] = cur.get("marg", 0) + time.perf_counter() - t0

        def p_covariances(self, keys):
            t0 = time.perf_counter()
            out = covariances(self, keys)
            cur["cov"] = cur.get("cov", 0) + time.perf_counter() - t0
            return out

        def p_close_kf(self, t_k):
            cur["cpu0"] = time.thread_time()
            return close_kf(self, t_k)

        def p_read(self, k, wall0):
            t0 = time.perf_counter()
            read(self, k, wall0)
            cur["read"] = time.perf_counter() - t0
            cur["lat"] = self.latency[-1]
            cur["cpu"] = time.thread_time() - cur.pop("cpu0", time.thread_time())
            cur["qr"] = self.factorization != self.options.factorization.upper()
            prof.rows.append(dict(cur))
            cur.clear()

        for owner, name, new in (
            (tos, "update", p_update),
            (tos, "_marginalize", p_marginalize),
            (tos, "marginalCovariances", p_covariances),
            (osm, "_close_keyframe", p_close_kf),
            (osm, "_read", p_read),
            (gtsam, "CustomFactor", lambda noise, keys, fn: custom(noise, keys, wrap(fn))),
        ):
            self._saved.append((owner, name, getattr(owner, name)))
            setattr(owner, name, new)

    def _probe(self, sm) -> None:
        oldest = min(self._blocks_keys(sm, min(sm._blocks)), key=lambda k: gtsam.Symbol(k).index())
        newest = max(sm._stamp, key=lambda k: (sm._stamp[k], gtsam.Symbol(k).index()))
        for from_oldest, key in ((True, oldest), (False, newest)):
            c0, w0 = time.thread_time(), time.perf_counter()
            res = sm.isam.update(
                gtsam.NonlinearFactorGraph(),
                gtsam.Values(),
                [],
                sm._groups,
                None,
                window._key_list([key]),
            )
            self.probes.append(
                (
                    from_oldest,
                    time.thread_time() - c0,
                    time.perf_counter() - w0,
                    _n(res.getVariablesReeliminated()),
                )
            )

    @staticmethod
    def _blocks_keys(sm, block: float) -> list[int]:
        return list(sm._blocks[block])

    def close(self) -> None:
        for owner, name, old in reversed(self._saved):
            setattr(owner, name, old)
        self._saved = []

    def table(self) -> dict[str, dict[str, float]]:
        """Mean of each field per kind of update (after the QR start)."""
        rows = [r for r in self.rows if not r.get("qr")]
        if not rows:
            return {}
        a = {f: np.array([r.get(f, 0.0) for r in rows], float) for f in FIELDS}
        slow = a["cpu"] >= np.percentile(a["cpu"], 99)
        kinds = {
            "all": np.ones(len(rows), bool),
            "plain": (a["relin"] == 0) & (a["marg"] == 0),
            "relinearising": a["relin"] > 0,
            "marginalising": a["marg"] > 0,
            "slowest 1% (CPU)": slow,
        }
        out = {}
        for kind, m in kinds.items():
            if m.any():
                out[kind] = {"n": int(m.sum())} | {
                    f: float(a[f][m].mean() * s) for f, s in FIELDS.items()
                }
        out["all"]["cpu_p50"] = float(np.percentile(a["cpu"], 50) * 1e3)
        out["all"]["cpu_p99"] = float(np.percentile(a["cpu"], 99) * 1e3)
        return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flight", help="figure8 (the benchmark's simulated flight) or a manifest")
    ap.add_argument("--duration", type=float, default=180.0, help="figure8 only [s]")
    ap.add_argument("--position-threshold", type=float, default=None)
    ap.add_argument("--slam-scale-rw", default=None, help="a float or 'none' (default: options')")
    ap.add_argument("--no-ballast", action="store_true", help="no ballast with the threshold")
    ap.add_argument("--probe", action="store_true")
    ap.add_argument("--json", action="store_true", help="print the table as JSON")
    args = ap.parse_args()
    kw: dict = {}
    if args.position_threshold:
        kw["relinearize_threshold_position"] = args.position_threshold
    if args.slam_scale_rw is not None:
        kw["slam_scale_rw"] = None if args.slam_scale_rw == "none" else float(args.slam_scale_rw)
    if args.no_ballast:
        online.BALLAST_WITH_POSITION_THRESHOLD = 0.0
    if args.flight == "figure8":
        from fgnav.datasets.simulate.options import SimOptions
        from fgnav.datasets.simulate.simulator import simulate

        sim = SimOptions(
            duration=args.duration,
            images=False,
            image_rate_hz=30.0,
            slam_rate_hz=20.0,
            range_rate_hz=50.0,
        )
        flight = simulate("figure8", seed=0, options=sim)
        opts = FixedLagOptions(lag_s=2.0, graph=GraphOptions(keyframe_hz=20.0), **kw)
    else:
        from fgnav.datasets.load import load_flight

        flight = load_flight(Path(args.flight))
        opts = FixedLagOptions(**kw)
    prof = Profiler(probe=args.probe)
    try:
        w0, c0 = time.perf_counter(), time.process_time()
        est = online.replay_online(flight, opts)
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    finally:
        prof.close()
    m = evaluate(est, flight.ground_truth, alignment="se3")
    span = float(flight.imu.t[-1] - flight.imu.t[0])
    lat = np.asarray(est.update_latency) * 1e3
    summary = {
        "options": kw,
        "ate_cm": m.ate_rmse_m * 100,
        "nees_pos": m.nees_pos,
        "p50_ms": float(np.percentile(lat, 50)),
        "p99_ms": float(np.percentile(lat, 99)),
        "x_real_time_wall": span / wall,
        "x_real_time_cpu": span / cpu,
        "solver_failures": est.info["solver_failures"],
    }
    if flight.slam is not None and est.slam_scale is not None and args.flight != "figure8":
        s_true = slam_scale_vs_truth(flight.slam, flight.ground_truth, flight.calib.body_T_cam)
        summary["final_scale_error_pct"] = (est.slam_scale[0] / s_true[0] - 1) * 100
    table = prof.table()
    if args.json:
        print(json.dumps({"summary": summary, "table": table, "probes": prof.probes}))
        return
    print(
        " ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in summary.items())
    )
    print("per update, after the QR start (times in ms):")
    for kind, row in table.items():
        print(
            f"  {kind:18s} "
            + " ".join(f"{f}={v}" if f == "n" else f"{f}={v:.2f}" for f, v in row.items())
        )
    for from_oldest in (True, False):
        p = np.array([q[1:] for q in prof.probes if q[0] == from_oldest])
        if p.size:
            print(
                f"probe: re-eliminating from the {'oldest' if from_oldest else 'newest'} key: "
                f"CPU {np.median(p[:, 0]) * 1e3:.2f} ms, wall {np.median(p[:, 1]) * 1e3:.2f} ms, "
                f"{p[:, 2].mean():.0f} variables (n={len(p)})"
            )


if __name__ == "__main__":
    main()
