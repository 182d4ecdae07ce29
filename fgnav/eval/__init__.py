"""Evaluation: trajectory alignment, metrics (ATE, RPE, scale, velocity, yaw, NEES), reports.

``plots`` imports matplotlib and is not imported here (import ``fgnav.eval.plots`` explicitly).
"""

from fgnav.eval.align import Alignment, Association, align, associate
from fgnav.eval.metrics import Metrics, evaluate, format_table, slam_scale_vs_truth
from fgnav.eval.outputs import write_estimate

__all__ = [
    "Alignment",
    "Association",
    "Metrics",
    "align",
    "associate",
    "evaluate",
    "format_table",
    "slam_scale_vs_truth",
    "write_estimate",
]
