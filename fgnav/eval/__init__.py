"""Evaluation: trajectory alignment, metrics (ATE, RPE, scale, velocity, yaw, NEES), reports."""
