"""Independent references the benchmarks and tests compare with: SciPy ODE solutions in reduced
coordinates, MuJoCo (optional) and a plain scatter-add PGS."""
