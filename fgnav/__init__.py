"""fgnav: factor-graph smoothing back-end for multirotors flying without GPS."""

__version__ = "0.1.0"
