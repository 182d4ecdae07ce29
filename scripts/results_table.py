"""Reproduce the README's results table: every method on the seeded simulated scenarios, on
EuRoC MH_01 (ORB-SLAM3 monocular run A + IMU) and on EuRoC V1_02 (IMU + the keyframes of an
ORB-SLAM2 and of an ORB-SLAM3 monocular run, with VINS-Mono and SVO 2 as reference rows), through
:func:`fgnav.compare.compare`.

    .venv/bin/python scripts/results_table.py [--out out/results] [--seed 1] [--no-euroc]
        [--only euroc-v102-orbslam2,euroc-v102-orbslam3]

Writes ``OUT/<flight>/`` (compare.json, report.md, figures) per flight and ``OUT/results.md``
(one table per flight plus the checks of issue 7: lowest ATE / velocity RMSE for batch, fixed-lag
against the causal filters), and prints ``results.md``.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path

from fgnav.datasets.load import load_flight
from fgnav.datasets.simulate import SimOptions, simulate

from fgnav.compare import compare
from fgnav.report import markdown_table

PROJECT_ROOT = Path(__file__).resolve().parents[1]
MANIFESTS = PROJECT_ROOT / "datasets" / "manifests"
EUROC_MANIFEST = MANIFESTS / "euroc_mh01_orbslam3.toml"
#: Real flights: name -> manifest (skipped with --no-euroc or when the manifest is absent).
EUROC_FLIGHTS = {
    "euroc-mh01": EUROC_MANIFEST,
    "euroc-v102-orbslam2": MANIFESTS / "euroc_v102_orbslam2_kf1.toml",
    "euroc-v102-orbslam3": MANIFESTS / "euroc_v102_orbslam3_kf2.toml",
}
SCENARIOS = ("two-turns", "circle", "rectangle", "figure8")


def _finite(x) -> bool:
    return x is not None and isinstance(x, float | int) and math.isfinite(x)


def checks(rows: list[dict]) -> list[str]:
    """Issue 7's claims, checked on one flight's rows (statements of what holds, not asserts)."""
    ok = {r["method"]: r for r in rows if r["status"] == "ok" and _finite(r.get("ate_rmse_m"))}
    out = []
    for key, label in (("ate_rmse_m", "ATE"), ("vel_rmse_mps", "velocity RMSE")):
        scored = {m: r[key] for m, r in ok.items() if _finite(r.get(key))}
        if "batch" in scored:
            best = min(scored, key=scored.get)
            verdict = "lowest" if best == "batch" else f"not lowest ({best}: {scored[best]:.4g})"
            out.append(f"batch {label}: {scored['batch']:.4g} -> {verdict}")
    # Own spans (each method from its first output) and the span every causal method covers.
    for key, label in (("ate_rmse_m", "ATE"), ("ate_common_m", "ATE on the common span")):
        causal = {
            m: r[key]
            for m, r in ok.items()
            if r["causal"] and m != "fixed-lag" and not m.startswith("ref:") and _finite(r.get(key))
        }
        fl = ok.get("fixed-lag", {}).get(key)
        if _finite(fl) and causal:
            beaten = [m for m, a in causal.items() if a < fl]
            out.append(
                f"fixed-lag {label} {fl:.4g}: "
                + ("beats every causal filter" if not beaten else f"beaten by {', '.join(beaten)}")
            )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="out/results")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-euroc", action="store_true")
    ap.add_argument("--no-images", action="store_true", help="skip seed 002's VO (faster)")
    ap.add_argument("--only", default=None, help="comma-separated flight names to run")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    out = Path(args.out)
    flights = [
        (sc, lambda sc=sc: simulate(sc, args.seed, SimOptions(images=not args.no_images)))
        for sc in SCENARIOS
    ]
    if not args.no_euroc:
        flights += [
            (name, lambda m=m: load_flight(m)) for name, m in EUROC_FLIGHTS.items() if m.is_file()
        ]
    if args.only:
        wanted = set(args.only.split(","))
        flights = [f for f in flights if f[0] in wanted]
    cmd = " ".join(sys.argv)
    lines = [f"# fgnav results (seed {args.seed}; SE(3) alignment; `{cmd}`)", ""]
    for name, make in flights:
        t0 = time.perf_counter()
        flight = make()
        res = compare(flight, progress=False)
        res.write(out / name, figures=True)
        rows = res.rows()
        lines += [f"## {name}", "", markdown_table(rows), ""]
        if res.skipped:
            lines += [f"- skipped {m}: {why}" for m, why in res.skipped.items()]
        if res.failed:
            lines += [f"- failed {m}: {why}" for m, why in res.failed.items()]
        lines += [f"- {c}" for c in checks(rows)]
        lines += [f"- wall time {time.perf_counter() - t0:.0f} s", ""]
        print(f"{name}: done in {time.perf_counter() - t0:.0f} s", flush=True)
    text = "\n".join(lines)
    (out / "results.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
