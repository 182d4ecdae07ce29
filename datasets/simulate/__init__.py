"""Flight simulator: ground truth for every sensor (see issue 3)."""
