"""Batched rollouts: the batch-minor layout equals jax.vmap of rollout for every solver, gradients through it are
exact, and the batch is sharded over every device (checked with 4 forced host devices in a subprocess)."""
import json
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.core import batch

# RATTLE with a fixed sweep count: to a tolerance, a batch-minor system stops when every copy has converged and
# vmap's batched predicate runs every sweep, so the two agree to the tolerance, not bitwise
SOLVERS = [jc.PGS(), jc.PGS(stabilization="split"), jc.Jacobi(), jc.XPBD(), jc.Penalty(substeps=30), jc.Direct(),
           jc.SoftStep(), jc.RATTLE(10, tolerance=0.0)]


def _states(state, B, seed=1):
    rng = np.random.default_rng(seed)
    states = jax.tree.map(lambda a: jnp.broadcast_to(a, (B,) + a.shape) + 0, state)
    return states.replace(v=states.v + 0.1 * rng.normal(size=states.v.shape))


def _scenes():
    rng = np.random.default_rng(0)
    # compact by default (the vmap reference); batched_rollout's batch-minor copies use the strided,
    # parity-split blocks of its unrolled layout, so the comparison spans both layouts
    yield "cloth", jc.scenes.cloth(4, 4)
    yield "rope_chain", jc.scenes.chain(5, kind="rope")
    # an irregular graph: gather blocks, rods and two ropes, one starting stretched 5% past its rest length and
    # one 5% short of it (slack for the 12 steps in every solver). A rope near its rest length (C ~ 0) is where a
    # slack rope's rigid speculative row meets a taut one's soft row (SoftStep, as Box2D): the layouts' rounding
    # of |d| picked a branch each there (seen: 2e-5 apart), so neither starts near it, and SoftStep's stretched
    # rope stays taut (PGS's goes slack, where its two layouts agree bitwise)
    x0 = rng.normal(size=(7, 3))
    rods, ropes = [(0, 3), (3, 5), (5, 1), (1, 6), (2, 4), (4, 0)], [(6, 2), (5, 2)]
    rest = ([np.linalg.norm(x0[i] - x0[j]) for i, j in rods]
            + [f * np.linalg.norm(x0[i] - x0[j]) for (i, j), f in zip(ropes, (0.95, 1.05))])
    yield "graph", jc.build(x0, np.ones(7), rods=rods, ropes=ropes, fixed=[0], rest_lengths=rest)


@pytest.mark.parametrize("solver", SOLVERS, ids=lambda s: type(s).__name__ + getattr(s, "stabilization", "")[:5])
def test_batched_rollout_equals_vmap_of_rollout(solver):
    for name, (model, state) in _scenes():
        if name == "rope_chain" and not isinstance(solver, jc.PGS):    # the graph has a rope for the others
            continue
        states = _states(state, 5)
        ref = jax.vmap(lambda s: jc.rollout(model, s, solver, 1 / 240, 12, save_every=3))(states)
        # chunking splits the batch before any solver sees it: one solver checks it (chunks of 2, 2 and 1)
        chunks = (None, 2) if solver is SOLVERS[0] else (None,)
        for chunk in chunks:
            got = jc.batched_rollout(model, states, solver, 1 / 240, 12, save_every=3, chunk=chunk)
            # XPBD and Penalty reassociate a sum in the batch-minor layout: equal to rounding. Direct (batched with
            # vmap) solves the over-constrained cloth's regularised, ill-conditioned system (condition ~1e8) with a
            # batched LU whose rounding differs from the unbatched one.
            tol = 1e-6 if isinstance(solver, jc.Direct) else 1e-9
            for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(got)):
                assert a.shape == b.shape and a.dtype == b.dtype
                np.testing.assert_allclose(b, a, rtol=tol, atol=tol, err_msg=f"{name}, chunk {chunk}")


def test_batch_minor_topology_is_a_batch_of_disjoint_copies():
    model, _ = jc.scenes.cloth(4, 4)
    assert model.topology.compact        # a small cloth is compact; its batch-minor copies are unrolled
    t, B = model.topology.unrolled, 3
    tb = batch.batch_minor_topology(model.topology, B)
    assert tb.view == t.view + (B,) and tb.n == 16 * B and tb.m == t.m * B and tb.n_colours == t.n_colours
    for b, bb in zip(t.blocks, tb.blocks):
        assert bb.size == b.size * B and bb.strided == b.strided
    # copy c of constraint k joins copy c of its particles
    assert np.array_equal(tb.i.reshape(t.m, B), t.i[:, None] * B + np.arange(B))


def test_gradient_through_batched_rollout_is_exact():
    model, state = jc.scenes.cloth(4, 4)
    states = _states(state, 4)

    def loss(rest, beta, run):
        final, tr = run(model.replace(rest_length=rest), jc.PGS(10, beta=beta))
        return jnp.mean(tr.x ** 2) + jnp.mean(final.lam ** 2)

    fast = lambda m, s: jc.batched_rollout(m, states, s, 1 / 240, 12)    # noqa: E731
    ref = lambda m, s: jax.vmap(lambda o: jc.rollout(m, o, s, 1 / 240, 12))(states)     # noqa: E731
    g_fast = jax.grad(loss, argnums=(0, 1))(model.rest_length, 0.2, fast)
    g_ref = jax.grad(loss, argnums=(0, 1))(model.rest_length, 0.2, ref)
    for a, b in zip(g_fast, g_ref):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-14)
    # and against float64 central differences in beta
    eps = 1e-6
    fd = (loss(model.rest_length, 0.2 + eps, fast) - loss(model.rest_length, 0.2 - eps, fast)) / (2 * eps)
    np.testing.assert_allclose(g_fast[1], fd, rtol=1e-6)


def test_default_chunk_follows_the_backend():
    class Dev:
        def __init__(self, platform):
            self.platform = platform
    assert batch.default_chunk([Dev("cpu")]) == batch.CPU_CHUNK
    assert batch.default_chunk([Dev("gpu"), Dev("gpu")]) is None      # never chunk a batch on an accelerator


def test_batched_rollout_refuses_devices_and_mesh_together():
    model, state = jc.scenes.pendulum()
    states = _states(state, 2)
    mesh = jax.sharding.Mesh(np.array(jax.devices()), ("batch",))
    with pytest.raises(ValueError, match="`devices` or `mesh`"):
        jc.batched_rollout(model, states, jc.PGS(), 1 / 240, 3, devices=jax.devices(), mesh=mesh)
    with pytest.raises(TypeError, match="`mesh` must be a jax.sharding.Mesh"):
        jc.batched_rollout(model, states, jc.PGS(), 1 / 240, 3, mesh="batch")


@pytest.mark.parametrize("devices, match", [
    ("cpu", "got 'cpu'"),                               # was AttributeError: 'numpy.str_' ... 'platform'
    (["cpu"], r"`devices\[0\]` is 'cpu'"),
    ([0], r"`devices\[0\]` is 0"),
    (jax.devices()[0], "got CpuDevice|got .*Device"),
    ([], "empty"),
    (jax.devices()[:1] * 2, "twice"),
])
def test_batched_rollout_devices_must_be_jax_devices(devices, match):
    model, state = jc.scenes.pendulum()
    with pytest.raises((TypeError, ValueError), match="batched_rollout: `devices`.*" + match):
        jc.batched_rollout(model, _states(state, 2), jc.PGS(), 1 / 240, 3, devices=devices)


def test_what_jax_devices_returns_is_accepted_as_devices():
    for devices in (jax.devices(), jax.local_devices(), tuple(jax.local_devices())):
        mesh = batch._mesh(devices, None)
        assert list(mesh.devices.flat) == list(devices)


def test_batched_contact_impulses_must_share_the_batch():
    """States whose contact impulses hold another batch size gave a reshape TypeError deep inside."""
    model, state = jc.scenes.falling_chain(2)
    states = _states(state, 4)
    for name in ("contact_n", "contact_t"):
        short = states.replace(**{name: getattr(states, name)[:3]})
        with pytest.raises(ValueError, match=rf"`states.{name}` must have the batch of `states.x` \(4 initial "
                                             r"states\).*got shape \(3,"):
            jc.batched_rollout(model, short, jc.PGS(), 1 / 240, 3)
    with pytest.raises(ValueError, match=r"`states.lam` must have the batch .*got a scalar"):
        jc.batched_rollout(model, states.replace(lam=jnp.zeros(())), jc.PGS(), 1 / 240, 3)


SHARDED = textwrap.dedent("""
    import json, os
    os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=4"
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp, numpy as np, jaxcon as jc
    from jaxcon.identification.fit import shard_batch

    out = {"devices": jax.local_device_count()}
    model, state = jc.scenes.double_pendulum(angles=(0.5, 0.5))
    for B in (10,):     # 10 does not divide over 4 devices: padded, then cut (the 2-device mesh below divides it)
        rng = np.random.default_rng(1)
        states = jax.tree.map(lambda a: jnp.broadcast_to(a, (B,) + a.shape) + 0, state)
        states = states.replace(v=states.v + 0.1 * rng.normal(size=states.v.shape))
        for solver in (jc.PGS(), jc.Direct()):                                  # batch-minor, vmap-batched
            one = jc.batched_rollout(model, states, solver, 1 / 240, 12, devices=jax.devices()[:1])
            every = jc.batched_rollout(model, states, solver, 1 / 240, 12)
            key = f"{B}_{type(solver).__name__}"
            out[key + "_err"] = max(float(jnp.max(jnp.abs(a - b))) for a, b in
                                    zip(jax.tree.leaves(one), jax.tree.leaves(every)))
            out[key + "_spans"] = len(every[0].x.sharding.device_set)
            out[key + "_shape"] = list(every[1].x.shape)
    mesh = jax.sharding.Mesh(np.array(jax.devices()[:2]), ("batch",))
    two = jc.batched_rollout(model, states, jc.PGS(), 1 / 240, 12, mesh=mesh)
    one = jc.batched_rollout(model, states, jc.PGS(), 1 / 240, 12, devices=jax.devices()[:1])
    out["mesh_spans"] = len(two[0].x.sharding.device_set)
    out["mesh_err"] = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(two)))

    # a batched fit runs data-parallel on every device and gives the single-device answer
    chain, c0 = jc.scenes.chain(4, 1.0, 0.4, angle=0.8)
    rng = np.random.default_rng(0)
    cs = jax.tree.map(lambda a: jnp.broadcast_to(a, (4,) + a.shape) + 0, c0)
    cs = cs.replace(v=cs.v + 0.3 * rng.normal(size=cs.v.shape))
    true = chain.replace(rest_length=chain.rest_length * jnp.array([1.05, 0.95, 1.02, 0.98]))
    _, tr = jc.batched_rollout(true, cs, jc.PGS(10), 1 / 240, 60)
    res = jc.fit(chain, cs, jc.PGS(10), 1 / 240, tr.x, params=("rest_length",), progress=False)
    out["fit"] = np.asarray(res.model.rest_length).tolist()
    out["fit_data_spans"] = len(shard_batch((tr.x, cs), 4)[0].sharding.device_set)
    print(json.dumps(out))
""")


@pytest.fixture(scope="module")
def sharded():
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    res = subprocess.run([sys.executable, "-c", SHARDED], capture_output=True, text=True, env=env, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    return json.loads(res.stdout.strip().splitlines()[-1])


def test_batched_rollout_shards_the_batch_over_every_device(sharded):
    assert sharded["devices"] == 4
    for B, solver in ((10, "PGS"), (10, "Direct")):
        assert sharded[f"{B}_{solver}_err"] < 1e-12, sharded
        assert sharded[f"{B}_{solver}_spans"] == 4
        assert sharded[f"{B}_{solver}_shape"] == [B, 12, 3, 2]
    assert sharded["mesh_spans"] == 2 and sharded["mesh_err"] < 1e-12


def test_batched_fit_runs_on_every_device_and_matches_one_device(sharded):
    assert sharded["fit_data_spans"] == 4
    model, _ = jc.scenes.chain(4, 1.0, 0.4, angle=0.8)
    true = np.asarray(model.rest_length) * np.array([1.05, 0.95, 1.02, 0.98])
    np.testing.assert_allclose(sharded["fit"], true, rtol=1e-6)


def test_batch_minor_reference_is_the_same_pgs():
    """The bench's reference line (a plain batch-minor PGS) computes what jc.PGS computes."""
    from jaxcon.bench.references.batch_minor_pgs import chain_pgs_rollout
    for model, state in (jc.scenes.double_pendulum(angles=(0.5, 0.5)), jc.scenes.chain(7, angle=0.7)):
        states = _states(state, 4)
        ref = jax.vmap(lambda s: jc.rollout(model, s, jc.PGS(10, beta=0.2), 1 / 240, 50, save_every=50)[0])(states)
        x, v, lam = jax.jit(lambda s: chain_pgs_rollout(s.x, s.v, s.lam, np.asarray(model.inv_mass), model.rest_length,
                                                        model.gravity, 0.2, 1 / 240, 50, 10))(states)
        for a, b in ((x, ref.x), (v, ref.v), (lam, ref.lam)):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)


def test_vmap_of_grad_through_batched_rollout():
    """Gradients for a batch of parameter sets (vmap of grad) through a batched rollout equal the per-set ones."""
    model, state = jc.scenes.double_pendulum(angles=(0.5, 0.5))
    states = _states(state, 3)

    def loss(beta):
        final, _ = jc.batched_rollout(model, states, jc.PGS(10, beta=beta), 1 / 240, 20, save_every=20)
        return jnp.mean(final.x ** 2)

    betas = jnp.array([0.1, 0.2, 0.3])
    together = jax.vmap(jax.grad(loss))(betas)
    one_by_one = jnp.stack([jax.grad(loss)(b) for b in betas])
    np.testing.assert_allclose(together, one_by_one, rtol=1e-10)
    assert np.all(np.isfinite(np.asarray(together))) and float(jnp.max(jnp.abs(together))) > 0


def _two_link(kind, dim=2):
    """A double pendulum (fixed pivot, two links) in `dim` dimensions, its second link a rod or a rope."""
    x = np.array([[0.0, 0.0, 0.0], [0.7, -0.6, 0.1], [1.2, -1.3, -0.2]])[:, :dim]
    links = [(0, 1), (1, 2)]
    return jc.build(x, np.array([1.0, 1.0, 2.0]), rods=links if kind == "rod" else links[:1],
                    ropes=[] if kind == "rod" else links[1:], fixed=[0])


@pytest.mark.parametrize("solver, kind, dim", [(jc.PGS(), "rod", 2), (jc.PGS(), "rope", 2), (jc.PGS(), "rod", 3),
                                               (jc.PGS(stabilization="split"), "rope", 2),
                                               (jc.PGS(warm_start=False), "rod", 3)],
                         ids=["rods", "rope", "3d", "split-rope", "cold-3d"])
def test_packed_sweeps_equal_rollout(solver, kind, dim):
    """A batch run in one piece (chunk >= batch) carries PGS's sweeps packed in one array: the results are
    rollout's, to rounding (rods, a rope, 2-D and 3-D, both stabilizations, with and without warm start)."""
    model, state = _two_link(kind, dim)
    states = _states(state, 4)
    assert batch.batch_minor_topology(model.topology, 4, packed=True).packed
    ref = jax.vmap(lambda s: jc.rollout(model, s, solver, 1 / 240, 12, save_every=3))(states)
    got = jc.batched_rollout(model, states, solver, 1 / 240, 12, save_every=3, chunk=4)
    for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(got)):
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-9)


def test_packing_only_where_it_pays():
    """Packed sweeps need every colour's endpoints to match or miss the next colour's (no padded terms), and
    only run in one piece: the CPU default (pieces) and larger models keep the plain sweeps."""
    assert batch.packing_pays(jc.scenes.double_pendulum()[0].topology)
    for model, _ in (jc.scenes.chain(7), jc.scenes.chain(5, kind="rope"), jc.scenes.cloth(4, 4)):
        assert not batch.packing_pays(model.topology)
        assert not batch.batch_minor_topology(model.topology, 4, packed=True).packed
    cpu = jax.devices("cpu")
    assert batch.sweep_mode(None, cpu) == "plain" and batch.sweep_mode(8, cpu) == "packed"


def test_accelerators_unroll_the_sweeps():
    """On a GPU or TPU the loop over sweeps is unrolled (plain sweeps, never packed), with or without `chunk`."""
    class Dev:
        platform = "gpu"
    assert batch.sweep_mode(None, [Dev()]) == batch.sweep_mode(64, [Dev()]) == "unrolled"
    assert batch.batch_minor_topology(jc.scenes.double_pendulum()[0].topology, 4, unroll=True).unroll


def _loops(jaxpr):
    """The trip counts of the loops that stay loops in `jaxpr` and the jaxprs inside it: every `scan` that is not
    fully unrolled, and every `while` (counted as 0 trips, unknown)."""
    out = []
    for e in jaxpr.eqns:
        if e.primitive.name == "scan" and e.params["unroll"] < e.params["length"]:
            out.append(e.params["length"])
        elif e.primitive.name == "while":
            out.append(0)
        for p in e.params.values():
            for q in p if isinstance(p, (tuple, list)) else (p,):
                inner = getattr(q, "jaxpr", q)                      # a ClosedJaxpr's jaxpr, or a Jaxpr
                if hasattr(inner, "eqns"):
                    out += _loops(inner)
    return out


@pytest.mark.parametrize("solver", [jc.PGS(4), jc.Jacobi(4), jc.XPBD(substeps=4), jc.SoftStep(substeps=2)],
                         ids=["pgs", "jacobi", "xpbd", "softstep"])
def test_unrolled_sweeps_equal_the_loop(solver):
    """What an accelerator runs (`Topology.unroll`): the same sweeps and substeps, unrolled, give the loop's
    results and gradients to rounding on gather blocks with ropes (the irregular graph), and for PGS its results on
    the strided cloth. Only the time loop stays a loop, counted in the jaxpr: how a loop of one trip lowers
    differs between JAX versions (jax 0.11.2 on an H200 lowered the unrolled XPBD's to more `stablehlo.while`
    than the loop's), and XLA removes such loops when it compiles."""
    for name, (model, state) in _scenes():
        if name == "rope_chain" or name == "cloth" and not isinstance(solver, jc.PGS):
            continue
        states = _states(state, 3)

        def loss(rest, unroll):
            final, tr = batch._minor(model.replace(rest_length=rest), states, solver, 1 / 240, 8, 4, unroll=unroll)
            return jnp.mean(tr.x ** 2) + jnp.mean(final.lam ** 2), (final, tr)

        out = {}
        for u in (False, True):
            fn = jax.value_and_grad(loss, has_aux=True) if name == "graph" else loss     # gradients: the graph's
            rolled = [n for n in _loops(jax.make_jaxpr(fn, static_argnums=1)(model.rest_length, u).jaxpr)
                      if n != 1]
            out[u] = rolled, jax.jit(fn, static_argnums=1)(model.rest_length, u)
        time_loop = {8 // 4, 4}                                      # 8 steps, a record every 4
        assert out[True][0] and set(out[True][0]) <= time_loop, out[True][0]    # only the time loop stays
        assert len(out[True][0]) < len(out[False][0]), (out[True][0], out[False][0])
        for a, b in zip(jax.tree.leaves(out[False][1]), jax.tree.leaves(out[True][1])):
            np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-11)


def test_gradient_through_packed_sweeps():
    model, state = jc.scenes.double_pendulum(angles=(0.5, 0.5))
    states = _states(state, 3)

    def loss(rest, beta, run):
        final, tr = run(model.replace(rest_length=rest), jc.PGS(10, beta=beta))
        return jnp.mean(tr.x ** 2) + jnp.mean(final.lam ** 2)

    packed = lambda m, s: jc.batched_rollout(m, states, s, 1 / 240, 12, chunk=3)       # noqa: E731
    ref = lambda m, s: jax.vmap(lambda o: jc.rollout(m, o, s, 1 / 240, 12))(states)     # noqa: E731
    for a, b in zip(jax.grad(loss, argnums=(0, 1))(model.rest_length, 0.2, packed),
                    jax.grad(loss, argnums=(0, 1))(model.rest_length, 0.2, ref)):
        np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-12)


@pytest.mark.optimised
def test_one_piece_kernels_per_step_against_the_reference():
    """jc.batched_rollout in one piece on the CPU (packed sweeps) compiles the double pendulum's time step to at
    most 1.3x the kernels (fusions and copies, loops within a step counted per trip) of the plain batch-minor
    reference, as the bench counts them (float32, PGS(10)). The counts do not depend on the batch size (the
    same from 8 to 131072); this counts HLO, it times nothing."""
    from jaxcon.bench.kernels import step_kernels
    from jaxcon.bench.throughput import _batch, _timed_fn
    cpu = jax.devices("cpu")[0]          # XLA CPU's kernels, also where the suite runs on a GPU
    with jax.default_device(cpu):
        model, states = _batch("double_pendulum", 256, np.float32)
        counts = {}
        for mode in ("one_piece", "reference"):
            f = _timed_fn(mode, model, jc.PGS(), 1 / 240, 12, None, [cpu])
            counts[mode] = step_kernels(jax.jit(f).lower(jax.device_put(states, cpu)).compile().as_text(), 12)
    one, ref = counts["one_piece"], counts["reference"]
    assert one["copy"] == 0 and ref["total"] > 0, counts
    assert one["total"] <= 1.3 * ref["total"], counts


def test_constraint_sets_are_batched_with_vmap():
    """A model with a jc.Constraint set takes the vmap path (the batch-minor copies have no set blocks), and a
    batch of it equals vmap of rollout."""
    x = np.array([[0.0, 0.0], [0.8, -0.6], [1.6, -0.6]])
    con = jc.Constraint(lambda xs, p: p["L"] - jnp.linalg.norm(xs[1] - xs[0]), [(0, 1), (1, 2)], {"L": [1.0, 0.8]})
    model, state = jc.build(x, [1.0, 1.0, 0.5], constraints=[con], fixed=[0])
    assert not batch.layout_generic(jc.PGS(), model)
    states = _states(state, 3)
    ref = jax.vmap(lambda s: jc.rollout(model, s, jc.PGS(), 1 / 240, 6))(states)
    got = jc.batched_rollout(model, states, jc.PGS(), 1 / 240, 6, chunk=3)
    for a, b in zip(jax.tree.leaves(ref), jax.tree.leaves(got)):
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=1e-12)
