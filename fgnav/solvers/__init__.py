"""Graph builder and solvers (batch and iSAM2 fixed-lag)."""
