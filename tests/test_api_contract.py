"""The calls of shared/API.md, as written there (the user-facing contract)."""
import json
import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import optax  # noqa: F401  (part of the contract's imports)

import jaxcon as jc
from jaxcon.bench.cli import main


def test_readme_tour_runs_as_written():
    """README.md's first python block, executed top to bottom as it stands (its diagnose line used to pair the
    pendulum's trajectory with the model `jc.build` had replaced, and `positions`, `observed` and `batch` were
    never defined)."""
    text = open(os.path.join(os.path.dirname(__file__), "..", "README.md")).read()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    ns = {}
    exec(compile(code, "README.md (tour)", "exec"), ns)
    assert ns["traj"].contact_n.shape[0] == 120                     # the last trajectory is the billiards break
    assert ns["report"].violation.shape == (480,) and not bool(ns["report"].diverged)
    result = ns["result"]
    np.testing.assert_allclose(np.asarray(result.model.rest_length), [0.32, 0.28, 0.3], rtol=1e-3)
    assert result.converged and result.reason == "tolerance"
    assert ns["trajs"].x.shape == (8, 60, 4, 2) and np.isfinite(np.asarray(ns["g_rest"])).all()


def test_api_md_calls_work_as_written():
    model, state = jc.scenes.pendulum(length=1.0, mass=1.0, angle=0.3)
    model, state = jc.scenes.double_pendulum(lengths=(1.0, 1.0), masses=(1.0, 1.0), angles=(1.5708, 1.5708))
    model, state = jc.scenes.chain(n_links=50, length=5.0, mass=0.5, end_mass=10.0, angle=1.5708, kind="rod")
    assert np.isclose(1 / float(model.inv_mass[-1]) / (1 / float(model.inv_mass[1])), 1000.0)
    model, state = jc.scenes.chain(n_links=50, length=5.0, mass=0.5, end_mass=10.0, angle=1.5708, kind="rope")
    model, state = jc.scenes.cloth(nx=32, ny=32, size=1.0, mass=1.0)
    assert model.dim == 3 and model.n_particles == 1024 and int((model.inv_mass == 0).sum()) == 2

    positions = jnp.array([[0.0, 0.0], [0.5, 0.0], [1.0, 0.0], [1.5, 0.0]])
    masses = jnp.array([1.0, 1.0, 1.0, 1.0])
    model, state = jc.build(positions, masses, rods=[(0, 1), (1, 2)], ropes=[(2, 3)], fixed=[0],
                            rest_lengths=None, velocities=None, gravity=None)
    np.testing.assert_allclose(np.asarray(model.rest_length), [0.5, 0.5, 0.5])

    solver = jc.PGS(iterations=10, beta=0.2, warm_start=True)
    state = jc.step(model, state, solver, dt=1 / 240)
    final, traj = jc.rollout(model, state, solver, dt=1 / 240, steps=480)
    assert traj.x.shape == (480, 4, 2) and traj.v.shape == (480, 4, 2) and traj.lam.shape == (480, 3)
    assert model.rest_length.shape == (3,) and model.inv_mass.shape == (4,)
    model2 = model.replace(rest_length=model.rest_length * 1.01)
    assert model2.topology == model.topology

    observed = traj.x[:240] + 0.001

    def loss(rest_length, beta):
        _, tr = jc.rollout(model.replace(rest_length=rest_length), state,
                           jc.PGS(iterations=10, beta=beta), dt=1 / 240, steps=240)
        return jnp.mean((tr.x - observed) ** 2)
    g_rest, g_beta = jax.grad(loss, argnums=(0, 1))(model.rest_length, 0.2)
    assert g_rest.shape == (3,) and np.isfinite(np.asarray(g_rest)).all() and np.isfinite(float(g_beta))
    assert float(jnp.max(jnp.abs(g_rest))) > 0

    batch = model.rest_length * jnp.array([[0.9], [1.0], [1.1]])
    finals, trajs = jax.vmap(lambda L: jc.rollout(model.replace(rest_length=L), state, solver, 1 / 240, 240))(batch)
    assert trajs.x.shape == (3, 240, 4, 2) and finals.x.shape == (3, 4, 2)


def test_demo_runs(capsys):
    assert main(["demo", "--small"]) == 0
    out = capsys.readouterr().out
    for name in ("pendulum", "double_pendulum", "chain_20_1000to1", "cloth_8x8", "compile s", "max viol", "E drift",
                 "system identification", "beta: true 0.2"):
        assert name in out
    suited, compared = out.split("for comparison")
    # each scene names the solver that suits it, and that solver holds the constraints
    for scene, solver in (("pendulum", "RATTLE()"), ("chain_20_1000to1", "Direct(substeps=4)"),
                          ("cloth_8x8", "XPBD(substeps=20)")):
        row = next(line for line in suited.splitlines() if line.startswith(scene + " "))
        assert solver in row, row
        assert float(row.split()[-2]) < 0.05, row          # max viol
    # plain PGS(10) on the 1000:1 chain is labelled as the failure it is
    row = next(line for line in compared.splitlines() if line.startswith("chain_20_1000to1"))
    assert "FAILS: stretched" in row, row
    row = next(line for line in compared.splitlines() if line.startswith("pendulum "))
    assert row.endswith("holds"), row


def test_bench_writes_json(tmp_path, capsys):
    path = tmp_path / "bench.json"
    assert main(["bench", "--small", "--repeats", "1", "--out", str(path), "--f32-only"]) == 0
    data = json.loads(path.read_text())
    rows = data["results"]
    assert {r["case"] for r in rows} == {"double_pendulum", "chain_20", "cloth_8x8"}
    # --f32-only skips the float64 runs, although the suite runs with x64 on (they ran before 2026-11-25)
    assert {r["dtype"] for r in rows} == {"float32"} and "double_pendulum_best" not in data
    for r in rows:
        assert r["median_s_per_step"] > 0 and r["compile_s"] > 0 and np.isfinite(r["max_violation"])
        assert 0 < r["min_s_per_step"] <= r["median_s_per_step"]
        assert r["host_steal"] is None or 0 <= r["host_steal"] <= 1
    dp = [r for r in rows if r["case"] == "double_pendulum"][0]
    assert dp["position_error_at_1s"] < 0.05
    assert "cpu" in data["machine"]
    xp = data["xpbd_cloth"]
    assert xp["case"] == "cloth_8x8" and xp["ns_per_constraint_iteration_recording"] > 0
    assert 0 < xp["max_violation"] < 0.05
    assert 0 < xp["min_ns_per_constraint_iteration_recording"] <= xp["ns_per_constraint_iteration_recording"]
    assert data["host_steal"] is None or 0 <= data["host_steal"] <= 1
    gc = data["gradient_compile"]
    for impl in ("jaxcon", "jaxcon_unrolled", "plain"):
        assert gc[f"{impl}_trace_s"] > 0 and gc[f"{impl}_compile_s"] > 0 and gc[f"{impl}_run_s"] > 0
        assert gc[f"{impl}_stablehlo_ops"] > 0
    assert gc["layout"] == "compact"          # the small bench's 4x4 cloth has 8 colours of at most 16 rods
    assert gc["trace_plus_compile_ratio"] > 0 and gc["runtime_cost"] > 0
    # the compact program is the smaller one: a fact of the traced program, not a timing
    assert gc["jaxcon_stablehlo_ops"] < gc["jaxcon_unrolled_stablehlo_ops"]
    assert {r["batch"] for r in data["batched"]} >= {1, 64}
    assert {r["mode"] for r in data["batched"]} == {"vmap", "batched_rollout", "one_piece", "reference"}
    assert all(r["particle_steps_per_s"] > 0 and r["devices"] >= 1 for r in data["batched"])
    dp = [r for r in data["batched"] if r["scene"] == "double_pendulum"]
    assert all(r["vs_reference"] > 0 and r["kernels"]["total"] > 0 and r["kernels_vs_reference"] > 0 for r in dp)


def test_bench_best_double_pendulum_row():
    """The bench's float64 row for the 1e-5 m target: RATTLE(3), dt 1/260 reaches it (accuracy, not timing)."""
    from jaxcon.bench.suite import _best_double_pendulum
    row = _best_double_pendulum(1)
    assert row["dt"] == 1 / 260 and row["position_error_at_1s"] < 1e-5
    assert row["ms_per_sim_s_final_state_only"] > 0 and row["ms_per_sim_s_recording"] > 0


def test_steal_fraction():
    """The bench's host-steal reading: the steal share of the CPU ticks between two /proc/stat readings, and
    None when a reading is missing or spans too few ticks to mean anything."""
    from jaxcon.bench.timing import _cpu_jiffies, steal_fraction
    assert steal_fraction((10, 1000), (40, 1200)) == 30 / 200
    assert steal_fraction((10, 1000), (10, 1100)) == 0.0
    assert steal_fraction((10, 1000), (12, 1010)) is None        # 10 ticks: too short to tell
    assert steal_fraction(None, (12, 1200)) is None
    now = _cpu_jiffies()
    if now is not None:                                          # Linux
        steal, total = now
        assert 0 <= steal <= total


def test_bench_emitters_runs_each_setting_in_its_own_child(tmp_path):
    """`bench --emitters`' plumbing on its smallest case: each child runs under the XLA_FLAGS of its setting (the
    suite's own flag is replaced, not inherited), on the CPU at XLA's default effort without the suite's
    persistent cache, and the two settings compute the same pendulum to rounding."""
    from jaxcon.bench import emitters
    out = emitters.main(repeats=1, rounds=1, out_path=str(tmp_path / "e.json"), cases=("double_pendulum_480",))
    child = out["children"]
    assert emitters.FLAG in child["elemental"]["xla_flags"].split()
    assert "xla_cpu_use_fusion_emitters" not in child["fusion"]["xla_flags"]
    for c in child.values():     # not the suite's settings: XLA's default effort, no persistent cache, the CPU
        assert c["backend"] == "cpu" and not c["disable_most_optimizations"] and not c["compilation_cache_dir"]
    (row,) = out["cases"]
    assert row["compile_s_fusion"] > 0 and row["compile_s_elemental"] > 0 and row["run_s_elemental"] > 0
    assert row["max_abs_diff"] < 1e-4                 # float32 positions of bobs 1 m from the pivot
    assert json.loads((tmp_path / "e.json").read_text())["cases"][0]["case"] == "double_pendulum_480"
    with pytest.raises(ValueError, match="`cases`: unknown"):
        emitters.main(cases=("pendulum",))
