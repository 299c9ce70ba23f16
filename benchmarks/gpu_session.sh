#!/usr/bin/env bash
# The GPU checks (the batch in one piece; the grid at 1e5 particles; the disc box),
# in one call on a lent GPU machine, each part under its own time limit. Logs go to $OUT (or ./gpu_out).
#
#   bash benchmarks/gpu_session.sh            # on the GPU machine, from the repository root
#   SMALL=1 bash benchmarks/gpu_session.sh    # the same parts at toy sizes (a dry run on the CPU)
#
# Needs jax with a GPU plugin, chex and optax; jaxcon is taken from the working tree (PYTHONPATH), not installed.
set -u
OUT=${OUT:-gpu_out}
mkdir -p "$OUT"
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
if [ -n "${SMALL:-}" ]; then
  BATCH="64 256"; GRID="256"; BOX="64"; BOXS=1; BILL="64"; T=${T:-1}
else
  BATCH="16384 131072 1048576"; GRID="16384 100489"; BOX="1024 4096 16384"; BOXS=8; BILL="1024 16384"; T=${T:-1}
fi
part() {   # part NAME SECONDS COMMAND...: run with a time limit, log to $OUT/NAME.log
  local name=$1 limit=$2; shift 2
  echo "=== $name (limit ${limit} s) $(date +%T)"
  timeout "$((limit * T))" "$@" > "$OUT/$name.log" 2>&1
  echo "--- $name: exit $? $(date +%T)"
  grep -E "FAILED|ERROR|passed|failed" "$OUT/$name.log" | tail -n 20; tail -n 25 "$OUT/$name.log"
}
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm --format=csv 2>/dev/null
python3 -c "import jax, jaxlib; print('jax', jax.__version__, 'jaxlib', jaxlib.__version__, jax.devices())"
part batched 150 python3 -m jaxcon bench --batched $BATCH --repeats 5 --out "$OUT/bench_gpu.json"
part grid 80 python3 -m jaxcon bench --contact-grid $GRID
part box 100 python3 benchmarks/gpu_extra.py box $BOXS $BOX
part billiards 50 python3 benchmarks/gpu_extra.py billiards $BILL
part sweeps 60 python3 benchmarks/gpu_sweeps.py $BATCH
# a GPU subset of the suite (x64, as the suite runs). -v names each failure as it happens: on the H200 a run cut
# off at its limit ended before pytest's summary, and its one failure went unnamed; these files took 213 s on an
# H200 with 8 workers (2026-11-27; docs/batching.md, "The tests on a GPU")
XLA_PYTHON_CLIENT_PREALLOCATE=false part tests 280 python3 -m pytest -v --tb=line -n 8 -p no:cacheprovider \
  -p no:benchmark tests/test_batching.py tests/test_contacts_piles.py tests/test_core.py
