"""The Crazyflie flow-deck table of issue 17: every UTIL flight, batch and fixed-lag (push engine)
with IMU + flow + range (no Vicon used), beside cf-ekf and ekf-flow002; drag on vs off for the
smoothers on every flight and on simulated two-turns; the goals checked.

    .venv/bin/python scripts/crazyflie_table.py [LOG ...] [--out out/crazyflie] [--no-sim]

Figures per method (``fgnav.eval.flow_table``): horizontal velocity RMSE of 100 ms averages,
height RMSE, ATE after one 4-DoF alignment, end drift with the start pose known (% of the truth's
horizontal path). "drag on" is the default configuration (the drag factor on, subject to the
accelerometer check); "drag off" is ``[graph] use_drag = false``. Writes ``crazyflie_table.md``
and ``crazyflie_table.json`` to ``--out``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from pathlib import Path

from fgnav.datasets.load import load_flight

from fgnav.eval.flow_table import (
    COLUMNS,
    FILTERS,
    SMOOTHERS,
    check_goals,
    flow_figures,
    goals_markdown,
    markdown_table,
)
from fgnav.methods import METHODS

DEFAULT_DIR = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / ("crazyflie_util_flowdeck")
)
DRAG_OFF = {"graph": {"use_drag": False}}
#: Tolerance of "never worse with drag on" (relative; the same graph gives equal figures).
DRAG_TOL = 0.01


def run(flight, method: str, config: dict) -> tuple[dict, float, dict]:
    t0 = time.perf_counter()
    est = METHODS[method].run(flight, config)
    wall = time.perf_counter() - t0
    info = est.info if isinstance(est.info, dict) else {}
    return flow_figures(est, flight.ground_truth), wall, info


def drag_line(info: dict) -> str:
    chk = info.get("accel_check")
    return chk["line"] if isinstance(chk, dict) else str(info.get("drag"))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="*", type=Path)
    ap.add_argument("--out", type=Path, default=Path("out/crazyflie"))
    ap.add_argument("--no-sim", action="store_true", help="skip simulated two-turns")
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.ERROR)
    logs = a.logs or sorted(DEFAULT_DIR.glob("0425-traj*"), key=lambda p: int(p.name[9:]))
    out: dict = {"flights": {}, "drag": {}}
    md = ["# Crazyflie flow-deck flights (UTIL, 2022-04-25): IMU + flow + range", ""]
    all_goals = []
    for p in logs:
        f = load_flight(p)
        rows, walls, drag = {}, {}, {}
        for m in SMOOTHERS + FILTERS:
            rows[m], walls[m], info = run(f, m, {})
            if m in SMOOTHERS:
                drag[m] = {"on": rows[m], "decision": drag_line(info)}
                drag[m]["off"], _, _ = run(f, m, DRAG_OFF)
        goals = check_goals(rows)
        all_goals += [{"flight": f.name, **g} for g in goals]
        out["flights"][f.name] = {"rows": rows, "wall_s": walls, "goals": goals}
        out["drag"][f.name] = drag
        md += [
            f"## {f.name} (path {rows['batch']['path_m']:.1f} m)",
            "",
            markdown_table(rows, SMOOTHERS + FILTERS),
            "",
            goals_markdown(goals),
            "",
        ]
        print(
            f"{f.name}: "
            + "; ".join(
                f"{m} " + " ".join(f"{rows[m][k]:.3f}" for k, _, _ in COLUMNS) for m in rows
            ),
            flush=True,
        )
    if not a.no_sim:
        from fgnav.datasets.simulate import SimOptions, simulate

        f = simulate("two-turns", seed=1, options=SimOptions(images=False))
        drag = {}
        for m in SMOOTHERS:
            on, _, info = run(f, m, {})
            off, _, _ = run(f, m, DRAG_OFF)
            drag[m] = {"on": on, "off": off, "decision": drag_line(info)}
        out["drag"]["sim:two-turns seed 1"] = drag
    # Drag on vs off.
    md += [
        "## Drag on vs off",
        "",
        "| flight | method | ATE on / off [m] | velocity on / off [m/s] | never worse | decision |",
        "|:--|:--|--:|--:|:--|:--|",
    ]
    never_worse = True
    for name, d in out["drag"].items():
        for m, r in d.items():
            on, off = r["on"], r["off"]
            ok = all(
                on[k] <= off[k] * (1 + DRAG_TOL) + 1e-9
                for k in ("ate_m", "hvel100_rmse_mps")
                if math.isfinite(off[k])
            )
            r["never_worse"] = ok
            never_worse &= ok
            md.append(
                f"| {name} | {m} | {on['ate_m']:.4f} / {off['ate_m']:.4f} | "
                f"{on['hvel100_rmse_mps']:.4f} / {off['hvel100_rmse_mps']:.4f} | "
                f"{'yes' if ok else 'NO'} | {r['decision'][:90]} |"
            )
    n_met = sum(g["met"] for g in all_goals)
    md += [
        "",
        f"Goals met: {n_met} of {len(all_goals)}; drag never worse: "
        f"{'yes' if never_worse else 'no'}.",
        "",
    ]
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "crazyflie_table.md").write_text("\n".join(md) + "\n")
    (a.out / "crazyflie_table.json").write_text(json.dumps(out, indent=1, default=float) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
