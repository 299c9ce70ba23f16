"""jaxcon.bench.throughput.batched_throughput: rows are consistent and the batch really holds different systems."""
import numpy as np

from jaxcon.bench.throughput import _batch, batched_throughput


def test_rows():
    rows = batched_throughput((1, 8), steps=20, repeats=2)
    # on CPU batched_rollout runs in pieces by default, so the one-piece program (an accelerator's) is a row too
    assert [(r["batch"], r["mode"]) for r in rows] == [(b, m) for b in (1, 8) for m in ("vmap", "batched_rollout",
                                                                                          "one_piece", "reference")]
    for r in rows:
        assert r["particles"] == 2 and r["run_s"] > 0 and r["compile_s"] > 0 and r["devices"] >= 1
        assert np.isclose(r["particle_steps_per_s"], r["batch"] * 2 * 20 / r["run_s"])
        assert np.isclose(r["system_steps_per_s"], r["batch"] * 20 / r["run_s"])
        k = r["kernels"]
        assert k["total"] == k["fusion"] + k["copy"] + k["other"] and k["fusion"] > 0
    # the reference line only exists where it computes the same thing (PGS on the double pendulum)
    assert {r["mode"] for r in batched_throughput((2,), steps=5, repeats=1, scene="cloth")} == {"vmap",
                                                                                              "batched_rollout",
                                                                                              "one_piece"}


def test_batch_has_distinct_initial_angles():
    _, state = _batch("double_pendulum", 100, np.float64)
    assert state.x.shape == (100, 3, 2)
    assert len(np.unique(np.round(np.asarray(state.x[:64, 2, 0]), 12))) == 64
