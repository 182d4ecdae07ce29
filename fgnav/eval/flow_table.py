"""Figures and goals of a flow-and-range flight (issue 17): the table of ``fgnav compare`` on a
flight with optical flow and ``scripts/crazyflie_table.py``.

Per method (:func:`flow_figures`, from :func:`fgnav.eval.metrics.flow_flight_figures`): the
horizontal velocity RMSE of 100 ms trailing averages [m/s], the height RMSE [m] and the ATE [m]
after one 4-DoF (yaw + translation) alignment of the whole trajectory, and the horizontal drift at
the end of the flight with the start pose known (the estimate placed at the truth's first yaw and
position, nothing else) as a percentage of the truth's horizontal path.

Goals (:data:`GOALS`, issue 17): velocity <= 0.08 m/s, height <= 1.5 cm, end drift <= 1 % of the
distance flown, and the smoothers better than both filters (``cf-ekf``, ``ekf-flow002``) on every
figure (:func:`check_goals`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from fgnav.datasets.types import Trajectory
from fgnav.estimate import Estimate
from fgnav.eval.metrics import flow_flight_figures

#: (figure key, title, format) of the table's columns.
COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("hvel100_rmse_mps", "hor. velocity RMSE, 100 ms [m/s]", "{:.3f}"),
    ("height_rmse_m", "height RMSE [cm]", "{:.2f}"),
    ("ate_m", "ATE 4-DoF [m]", "{:.3f}"),
    ("start_drift_pct", "end drift, start known [% of path]", "{:.2f}"),
)
#: Goal per figure (upper bound), issue 17.
GOALS: dict[str, float] = {
    "hvel100_rmse_mps": 0.08,
    "height_rmse_m": 0.015,
    "start_drift_pct": 1.0,
}
SMOOTHERS = ("batch", "fixed-lag")
FILTERS = ("cf-ekf", "ekf-flow002")


def flow_figures(est: Estimate, truth: Trajectory) -> dict[str, float]:
    """The table's figures of one estimate (module docstring) plus the raw velocity RMSE, the
    end drift after the 4-DoF alignment and the path length."""
    fig = flow_flight_figures(est, truth)
    fig["hvel100_rmse_mps"] = flow_flight_figures(est, truth, velocity_average_s=0.1)[
        "hvel_rmse_mps"
    ]
    return fig


def _cell(key: str, fmt: str, value: Any) -> str:
    if value is None or not math.isfinite(float(value)):
        return "-"
    if key == "height_rmse_m":
        value = 100.0 * float(value)
    return fmt.format(float(value))


def check_goals(rows: Mapping[str, Mapping[str, float]]) -> list[dict[str, Any]]:
    """Every goal of every smoother row present: ``{"method", "goal", "value", "bound", "met"}``
    (``goal`` a figure key with its bound, or ``"better than <filter>: <key>"``)."""
    out: list[dict[str, Any]] = []
    for m in SMOOTHERS:
        if m not in rows:
            continue
        r = rows[m]
        for key, bound in GOALS.items():
            v = float(r.get(key, math.nan))
            out.append(
                {
                    "method": m,
                    "goal": key,
                    "value": v,
                    "bound": bound,
                    "met": bool(math.isfinite(v) and v <= bound),
                }
            )
        for f in FILTERS:
            if f not in rows:
                continue
            for key, _, _ in COLUMNS:
                v, b = float(r.get(key, math.nan)), float(rows[f].get(key, math.nan))
                out.append(
                    {
                        "method": m,
                        "goal": f"better than {f}: {key}",
                        "value": v,
                        "bound": b,
                        "met": bool(math.isfinite(v) and (not b <= v)),
                    }
                )
    return out


def markdown_table(
    rows: Mapping[str, Mapping[str, float]], order: Sequence[str] | None = None
) -> str:
    """The rows as a markdown table (module docstring's columns)."""
    head = "| method | " + " | ".join(t for _, t, _ in COLUMNS) + " |"
    lines = [head, "|:--|" + "--:|" * len(COLUMNS)]
    for m in order or rows:
        if m not in rows:
            continue
        cells = [_cell(k, f, rows[m].get(k)) for k, _, f in COLUMNS]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def goals_markdown(goals: Sequence[Mapping[str, Any]]) -> str:
    """The goal checks as lines: met / not met with value and bound."""
    out = []
    for g in goals:
        flag = "met" if g["met"] else "NOT met"
        out.append(
            f"- {g['method']}: {g['goal']} {g['value']:.4g} (bound {g['bound']:.4g}): {flag}"
        )
    return "\n".join(out)
