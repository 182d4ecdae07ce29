"""The comparison table and ``report.md`` of ``fgnav compare``, made from the ``compare.json`` dict.

Both the printed table and the Markdown report are formatted from the rows of
``compare.json`` (``data["table"]``) with the same :data:`COLUMNS`, so every number in
``report.md`` is the JSON value formatted with its column's format (a test checks it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class Column:
    """One column of the comparison table.

    Attributes:
        title: header text (with the unit).
        key: key of the row dict in ``compare.json``.
        fmt: format of a number (None: text); a missing value (None/NaN) prints ``-``.
    """

    title: str
    key: str
    fmt: str | None = None


#: Columns of the comparison table (printed, ``report.md``), in order.
COLUMNS: tuple[Column, ...] = (
    Column("method", "method"),
    Column("causal", "causal"),
    Column("alignment", "alignment"),
    Column("ATE [m]", "ate_rmse_m", "{:.3f}"),
    Column("ATE common [m]", "ate_common_m", "{:.3f}"),
    Column("ATE 4-DoF [m]", "ate_4dof_m", "{:.3f}"),
    Column("RPE [%]", "rpe_pct", "{:.2f}"),
    Column("scale err [%]", "scale_final_abs_err_pct", "{:.2f}"),
    Column("vel RMSE [m/s]", "vel_rmse_mps", "{:.3f}"),
    Column("yaw RMSE [deg]", "yaw_rmse_deg", "{:.2f}"),
    Column("NEES", "nees_pos", "{:.2f}"),
    Column("time/update p50 [ms]", "latency_p50_ms", "{:.3f}"),
    Column("x real time", "times_real_time", "{:.1f}"),
    Column("flag", "flag"),
)

#: Text of a value that is not available (no truth, no covariance, nothing timed ...).
MISSING = "-"


def format_cell(value: Any, column: Column) -> str:
    """The text of one table cell (``-`` for None/NaN; ``yes``/``no`` for booleans)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return MISSING
    if isinstance(value, bool):
        return "yes" if value else "no"
    if column.fmt is None:
        return str(value)
    return column.fmt.format(value)


def table_cells(rows: Sequence[Mapping[str, Any]]) -> list[list[str]]:
    """The formatted cells of the rows (one list per row, :data:`COLUMNS` order)."""
    out = []
    for row in rows:
        cells = [format_cell(row.get(c.key), c) for c in COLUMNS]
        if row.get("status") == "failed":
            cells[3:] = ["failed"] + [MISSING] * (len(COLUMNS) - 4)
        out.append(cells)
    return out


def format_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """Fixed-width text table of the rows (header first)."""
    cells = table_cells(rows)
    header = [c.title for c in COLUMNS]
    widths = [max([len(h), *(len(r[i]) for r in cells)]) for i, h in enumerate(header)]

    def line(parts: list[str]) -> str:
        return "  ".join(
            p.ljust(w) if i < 3 else p.rjust(w)
            for i, (p, w) in enumerate(zip(parts, widths, strict=True))
        ).rstrip()

    return "\n".join([line(header), *(line(r) for r in cells)])


def markdown_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """The rows as a GitHub Markdown table (numbers right-aligned)."""
    header = "| " + " | ".join(c.title for c in COLUMNS) + " |"
    align = "|" + "|".join(":--" if i < 3 else "--:" for i in range(len(COLUMNS))) + "|"
    body = ["| " + " | ".join(r) + " |" for r in table_cells(rows)]
    return "\n".join([header, align, *body])


def _fmt(x: Any, fmt: str = "{:.4g}") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return MISSING
    if isinstance(x, float):
        return fmt.format(x)
    return str(x)


#: Figures of the report: key in ``data["figures"]`` -> caption.
FIGURE_CAPTIONS: dict[str, str] = {
    "top_view": "Top view of every trajectory against the truth (aligned as in the table)",
    "errors": "Position, velocity and yaw error over time",
    "scale": "SLAM scale estimate over time (truth at the session's end dashed)",
    "drag": "Rotor-drag coefficient k over time (truth dashed)",
    "latency": "Time per update",
}


def render_report(data: Mapping[str, Any]) -> str:
    """``report.md`` text from the ``compare.json`` dict (figures linked by relative path)."""
    fl = data["flight"]
    lines = [f"# fgnav compare: {fl['name']}", ""]
    lines += [
        f"- source: `{fl['source']}`" + (" (synthetic)" if fl.get("synthetic") else ""),
        f"- duration: {_fmt(fl.get('duration_s'), '{:.1f}')} s; streams: "
        + ", ".join(
            f"{name} ({_fmt(s.get('rate_hz'), '{:.0f}')} Hz, {s['n']})"
            for name, s in fl["streams"].items()
        ),
    ]
    truth = data["truth"]
    if truth["ground_truth"]:
        lines.append(
            "- ground truth: yes; metrics after the alignment stated per row (DESIGN.md sec. 9)"
        )
    else:
        lines.append("- ground truth: none; accuracy metrics are not available (`-`)")
    if truth.get("slam_scale"):
        scales = ", ".join(
            f"session {sid}: {_fmt(s, '{:.6g}')}" for sid, s in truth["slam_scale"].items()
        )
        lines.append(
            f"- true SLAM scale [SLAM units per metre] ({truth['slam_scale_source']}): {scales}"
        )
    elif truth.get("slam_scale_source"):
        lines.append(f"- true SLAM scale: not available ({truth['slam_scale_source']})")
    if truth.get("drag_k") is not None:
        lines.append(f"- true drag k [1/s]: {truth['drag_k']}")
    lines += ["", "## Results", "", markdown_table(data["table"]), ""]
    lines += [
        "ATE: RMSE of the position error after alignment; ATE common: the same over the span "
        "every causal method covers"
        + (
            f" (from {_fmt(data.get('common_span_start_rel_s'), '{:.1f}')} s after the flight's "
            "start to the end, each method aligned over it: a filter that emits nothing before "
            "its initialisation is otherwise scored over a shorter, easier span)"
            if data.get("common_span_start_rel_s") is not None
            else ""
        )
        + "; RPE: mean relative translation error "
        f"per distance over {_fmt(data.get('rpe_delta_m'), '{:g}')} m segments; scale err: largest "
        "|final scale error| over SLAM sessions; NEES: mean position NEES (3 for a consistent "
        "estimator); time/update p50: median wall time of one update; x real time: flight "
        "duration / run time; flag: why the estimate is implausible (`non-finite`, `speed`, "
        "`ate`, see below). `-`: not available for that method (no flag).",
        "",
    ]
    flags = data.get("flags") or {}
    if flags:
        b = data.get("flag_bounds") or {}
        lines += [
            "## Implausible estimates",
            "",
            "Flagged after scoring (information only: the numbers are as computed): non-finite "
            f"values, speeds above {_fmt(b.get('max_speed_mps'), '{:g}')} m/s over "
            f"{_fmt(b.get('speed_span_s'), '{:g}')} s spans, or an ATE above the larger of "
            f"{_fmt(b.get('ate_min_m'), '{:g}')} m and "
            f"{_fmt(100 * b.get('ate_path_fraction', math.nan), '{:g}')} % of the true path.",
            "",
        ]
        lines += [f"- **{name}**: {'; '.join(reasons)}" for name, reasons in flags.items()]
        lines.append("")
    only = [r["method"] for r in data["table"] if r.get("positions_only")]
    if only:
        lines += [
            f"{', '.join(only)}: another system's trajectory, scored on its positions only (its "
            "body frame is not known to be the flight's; the EuRoC V1_02 references' "
            "orientations are of another one): RPE, yaw RMSE and NEES, which use the "
            "orientations, are left out (`-`).",
            "",
        ]
    ft = data.get("flow_table")
    if ft:
        lines += [
            "## Flow-and-range figures (issue 17)",
            "",
            ft["markdown"],
            "",
            "One 4-DoF (yaw + translation) alignment per trajectory for the velocity (100 ms "
            "trailing averages), height and ATE; end drift: horizontal distance at the end with "
            "the start pose known (first yaw and position from the truth), as a percentage of the "
            "truth's horizontal path. Goals: velocity <= 0.08 m/s, height <= 1.5 cm, end drift "
            "<= 1 %, smoothers better than cf-ekf and ekf-flow002 on every figure:",
            "",
            ft["goals_markdown"],
            "",
        ]
    skipped = data.get("skipped") or {}
    failed = {n: m for n, m in data["methods"].items() if m["status"] == "failed"}
    if skipped or failed:
        lines += ["## Methods not in the results", ""]
        for name, reason in skipped.items():
            lines.append(f"- **{name}** (skipped): {reason}")
        for name, m in failed.items():
            lines.append(f"- **{name}** (failed): `{m['error']}`")
        lines.append("")
    figures = data.get("figures") or {}
    if figures:
        lines += ["## Figures", ""]
        for key, rel in figures.items():
            caption = FIGURE_CAPTIONS.get(key, key)
            if key == "top_view" and not truth["ground_truth"]:
                caption = "Top view of every trajectory (no ground truth: not aligned)"
            lines += [f"### {caption}", "", f"![{caption}]({rel})", ""]
    fig_errors = data.get("figure_errors") or {}
    for key, err in fig_errors.items():
        lines.append(f"- figure {key} not drawn: {err}")
    if fig_errors:
        lines.append("")
    lines += ["## Per method", ""]
    for name, m in data["methods"].items():
        head = f"### {name}"
        lines += [head, "", f"{m['description']}", ""]
        if m["status"] == "failed":
            lines += [f"Failed after {_fmt(m['wall_s'], '{:.2f}')} s: `{m['error']}`", ""]
            continue
        est = m["estimate"]
        wall = (
            f"computed before the comparison, scored in {_fmt(m['wall_s'], '{:.2f}')} s"
            if m.get("reused")
            else f"wall {_fmt(m['wall_s'], '{:.2f}')} s incl. scoring"
        )
        lines.append(
            f"- {est['n_states']} states, run time {_fmt(est['runtime_s'], '{:.2f}')} s "
            f"({wall}); outputs: `{m['output']}`"
        )
        defaults = (est.get("info") or {}).get("compare_defaults")
        if defaults:
            lines.append(f"- options filled in by compare: {defaults}")
        for sid, s in (est.get("slam_scale") or {}).items():
            sig = s.get("sigma")
            sig_txt = f" +/- {_fmt(sig, '{:.2g}')}" if sig is not None else ""
            err = (m.get("metrics") or {}).get("scale_final_err_pct", {}).get(sid)
            err_txt = f" (error {_fmt(err, '{:+.2f}')} %)" if err is not None else ""
            lines.append(
                f"- SLAM scale session {sid}: {_fmt(s['s'], '{:.6g}')}{sig_txt} SLAM units per "
                f"metre{err_txt}"
            )
        if est.get("drag_k_per_s") is not None:
            ks = ", ".join(_fmt(k, "{:.4g}") for k in est["drag_k_per_s"])
            lines.append(f"- drag k: [{ks}] 1/s")
        if m.get("evaluation_error"):
            lines.append(f"- not scored: {m['evaluation_error']}")
        lines.append("")
    timings = data.get("timings") or {}
    if timings:
        lines += [
            "## Timings",
            "",
            ", ".join(f"{k}: {_fmt(v, '{:.2f}')} s" for k, v in timings.items()),
            "",
        ]
    return "\n".join(lines).rstrip() + "\n"


def write_report(data: Mapping[str, Any], path: str | Path) -> Path:
    """Write :func:`render_report` of ``data`` to ``path``."""
    path = Path(path)
    path.write_text(render_report(data))
    return path
