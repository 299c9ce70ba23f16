export PYTHONPATH=$PWD PYTHONUNBUFFERED=1
python3 -c "import jax; print(jax.devices())"
HLO_DIR=$OUT timeout 150 python3 benchmarks/gpu_sweeps.py 131072 16384 1048576 2>&1 | tee $OUT/sweeps.log | grep -v Warn
timeout 60 python3 -m jaxcon bench --batched 1048576 --repeats 3 --out '' 2>&1 | tee $OUT/batched1m.log | tail -6
