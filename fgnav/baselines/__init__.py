"""Filter baselines: same inputs and same Estimate type as the smoothers."""
