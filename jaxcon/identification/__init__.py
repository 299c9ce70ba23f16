"""Fitting physical parameters to observed motion (`jc.fit`), the experiments the tests and the bench fit,
and the gradient-growth study behind windowed losses."""
