"""Front-ends from the seed papers: they turn raw series into measurements, priors and initial
values."""
