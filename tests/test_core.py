"""Core: PGS against independent references, rope semantics, transformations, gradients."""
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.core import sim as _sim
from reference import double_pendulum_positions

G = 9.81


# ---- accuracy against the reduced-coordinate ODE ------------------------------------------------------------
def test_double_pendulum_converges_to_reduced_ode():
    """Position error at t = 1 s against SciPy DOP853 (rtol 1e-12) falls first-order as dt falls."""
    angles, lengths, masses = (0.5, 0.5), (1.0, 1.0), (1.0, 1.0)
    ref = double_pendulum_positions(angles, lengths, masses, [1.0])[0]
    model, state = jc.scenes.double_pendulum(lengths, masses, angles, dtype=np.float64)
    solver = jc.PGS(iterations=50, beta=0.2)
    errors = []
    dts = [1 / 240, 1 / 480, 1 / 960, 1 / 1920]
    for dt in dts:
        final, _ = jc.rollout(model, state, solver, dt, int(round(1.0 / dt)))
        errors.append(np.max(np.abs(np.asarray(final.x[1:]) - ref)))
    slope = np.polyfit(np.log(dts), np.log(errors), 1)[0]
    assert 0.8 < slope < 1.3, (errors, slope)          # symplectic Euler + velocity-level PGS: first order
    assert errors[-1] < 3e-3, errors
    assert all(b < a for a, b in zip(errors, errors[1:])), errors


def test_double_pendulum_energy_and_drift_bounded_float32():
    model, state = jc.scenes.double_pendulum(angles=(1.5708, 1.5708), dtype=np.float32)
    _, tr = jc.rollout(model, state, jc.PGS(iterations=10, beta=0.2), 1 / 240, 2400)
    assert tr.x.dtype == jnp.float32
    assert float(jnp.max(jc.violation(model, tr.x))) < 5e-3
    assert abs(float(jc.energy_drift(model, state, tr))) < 0.1


# ---- multipliers are forces --------------------------------------------------------------------------------
@pytest.mark.parametrize("mass", [1.0, 2.5])
@pytest.mark.parametrize("substeps", [1, 4])
def test_hanging_mass_tension_is_mg(mass, substeps):
    model, state = jc.scenes.pendulum(length=0.7, mass=mass, angle=0.0, dtype=np.float64)
    dt = 1 / 240
    _, tr = jc.rollout(model, state, jc.PGS(iterations=5, substeps=substeps), dt, 50)
    np.testing.assert_allclose(np.asarray(tr.lam) / dt, mass * G, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(tr.x[-1]), np.asarray(state.x), atol=1e-12)


@pytest.mark.parametrize("kind", ["rod", "rope"])
def test_hanging_chain_tensions_carry_the_weight_below(kind):
    """Link k of a chain at rest carries the weight of every bob below it (the 10 kg end mass included).
    The 100:1 mass ratio makes PGS converge slowly (200 iterations leave the first step 68% off), hence the
    many iterations here."""
    model, state = jc.scenes.chain(n_links=6, length=1.2, mass=0.6, end_mass=10.0, angle=0.0, kind=kind,
                                   dtype=np.float64)
    dt = 1 / 240
    _, tr = jc.rollout(model, state, jc.PGS(iterations=3000), dt, 30)
    masses = 1 / np.asarray(model.inv_mass[1:])
    expected = G * np.cumsum(masses[::-1])[::-1]
    np.testing.assert_allclose(np.asarray(tr.lam[-1]) / dt, expected, rtol=1e-6)


# ---- rope semantics ----------------------------------------------------------------------------------------
def _tether(kind, dtype=np.float64):
    x = np.array([[0.0, 0.0], [0.0, -0.5]], dtype)
    pairs = [(0, 1)]
    return jc.build(x, [1.0, 2.0], rods=pairs if kind == "rod" else None, ropes=pairs if kind == "rope" else None,
                    fixed=[0], rest_lengths=[1.0])


def test_slack_rope_is_exact_free_fall_then_catches():
    model, state = _tether("rope")
    dt, steps = 1 / 240, 120
    _, tr = jc.rollout(model, state, jc.PGS(iterations=10), dt, steps)
    y = np.asarray(tr.x[:, 1, 1])
    n = np.arange(1, steps + 1)
    free = -0.5 - G * dt * dt * n * (n + 1) / 2          # symplectic Euler free fall, exactly
    slack = free > -1.0 - G * dt * dt                    # steps in which even a free fall keeps the rope slack
    assert slack.sum() > 60
    np.testing.assert_allclose(y[slack], free[slack], rtol=0, atol=1e-12)
    assert np.all(np.asarray(tr.lam[slack]) == 0)
    # once taut it holds: no stretch beyond what Baumgarte corrects, and it pulls (lam > 0)
    assert np.all(y > -1.0 - 0.02)
    assert np.all(np.asarray(tr.lam) >= 0) and np.asarray(tr.lam)[~slack].max() > 0


def test_rod_of_same_length_pushes_the_particle_out():
    model, state = _tether("rod")
    _, tr = jc.rollout(model, state, jc.PGS(iterations=10, beta=0.2), 1 / 240, 120)
    d = np.linalg.norm(np.asarray(tr.x[:, 1]), axis=-1)
    assert d[0] > 0.5 + 0.05                  # pushed out on the very first step, faster than free fall
    assert abs(d[-1] - 1.0) < 1e-2
    assert np.asarray(tr.lam).min() < 0       # a rod pushes: negative (compressive) impulse


def test_rope_lambda_never_negative_and_slack_ropes_exert_nothing():
    model, state = jc.scenes.chain(n_links=8, length=2.0, mass=0.8, angle=1.2, kind="rope", dtype=np.float64)
    v = jnp.asarray(np.random.default_rng(0).normal(scale=3.0, size=state.v.shape)).at[0].set(0.0)
    _, tr = jc.rollout(model, state.replace(v=v), jc.PGS(iterations=10), 1 / 240, 480)
    lam = np.asarray(tr.lam)
    assert lam.min() >= 0.0
    d = np.linalg.norm(np.asarray(tr.x[:, model.pairs[:, 1]] - tr.x[:, model.pairs[:, 0]]), axis=-1)
    slack = d < np.asarray(model.rest_length) * 0.9   # clearly slack at the end of the step
    assert slack.any() and (~slack).any()
    assert np.all(lam[slack] == 0)


def test_rope_code_traced_only_when_ropes_exist():
    """A scene with no ropes traces no rope code: the projection (a `max`) appears only with ropes."""
    def jaxpr_text(kind):
        model, state = jc.scenes.chain(n_links=4, kind=kind)
        return str(jax.make_jaxpr(lambda s: _sim._rollout_jit(model, s, jc.PGS(), 1 / 240, 2, 1))(state))
    assert not re.search(r"\bmax\b", jaxpr_text("rod"))
    assert re.search(r"\bmax\b", jaxpr_text("rope"))


# ---- layouts agree -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("solver", [jc.PGS(iterations=4), jc.Jacobi(iterations=4), jc.XPBD(substeps=3),
                                    jc.Penalty(stiffness=1e3, substeps=4), jc.Direct(), jc.SoftStep(substeps=3),
                                    jc.RATTLE(iterations=4)], ids=lambda s: type(s).__name__)
def test_strided_gather_and_compact_layouts_agree(solver):
    """The same cloth through the parity-split strided layout, through gathers in user order and through the
    compact table (every colour in one table, swept row by row in a scan): every solver gives the same
    trajectory, in the user's particle order. (The compact table is compared here for Penalty and Direct, which
    treat it as one block; the solvers that sweep it row by row are compared on both layouts by
    `test_compact_layout_with_mixed_ropes_agrees`, on a cloth that also mixes ropes into the colours.)

    The layouts sum the same terms in different orders, so they agree to rounding, amplified by how the
    method conditions the problem (not by a machine: on an H100 the dense solve's impulses differed by 3.6e-11,
    4e-6 relative, where the CPU happens to agree to the last bit). Tolerances: `_layout_tolerances`."""
    model, state = jc.scenes.cloth(6, 5, dtype=np.float64, layout="unrolled")
    pairs, colour = jc.scenes.cloth_edges(6, 5)
    general, gstate = jc.build(state.x, 1 / 30 * np.ones(30), rods=pairs, fixed=[0, 5], colouring=colour,
                               layout="unrolled")
    compact, cstate = jc.scenes.cloth(6, 5, dtype=np.float64, layout="compact")
    t = model.topology
    assert all(b.strided for b in t.blocks) and t.view == (5, 6) and t.order is not None
    assert not all(b.strided for b in general.topology.blocks) and not general.topology.compact
    assert compact.topology.compact and len(compact.topology.blocks) == 1
    assert compact.topology.n_colours == t.n_colours == 8
    dt = 1 / 240
    _, a = jc.rollout(model, state, solver, dt, 40)
    tol = _layout_tolerances(model, solver, a, dt)
    others = ((general, gstate), (compact, cstate)) if isinstance(solver, (jc.Penalty, jc.Direct)) else (
        (general, gstate),)
    for other, ostate in others:
        _, b = jc.rollout(other, ostate, solver, dt, 40)
        for name in ("x", "v", "lam"):
            np.testing.assert_allclose(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), rtol=0,
                                       atol=tol[name], err_msg=f"{name}, {other.topology!r}")
        assert np.asarray(b.x)[-1, 0, 0] == 0.0 and np.asarray(b.x)[-1, 5, 0] == 1.0     # pinned corners stay put
    assert np.asarray(a.x)[-1, 0, 0] == 0.0 and np.asarray(a.x)[-1, 5, 0] == 1.0


def _layout_tolerances(model, solver, traj, dt, c=64):
    """Absolute tolerances for two float64 evaluations of one method that differ only in summation order.

    A rounding of eps |x| in a position becomes eps |x| / h in a velocity (XPBD sets v = (p - x) / h) and
    eps m |x| / h in an impulse; a linear solve (Direct) multiplies relative errors by the condition number of
    its matrix, J M^-1 J^T with its regularisation, computed here from the trajectory's geometry. c is a
    small safety factor for the 40 steps. A layout bug shows as an error of order the motion itself (1e-3 and
    up), far above these."""
    eps = np.finfo(np.float64).eps
    h = dt / getattr(solver, "substeps", 1)
    x = np.asarray(traj.x)
    kappa = 1.0
    if isinstance(solver, jc.Direct):
        from jaxcon.solvers.direct import _regularisation
        w = np.asarray(model.inv_mass)
        i, j = model.pairs.T
        reg = float(_regularisation(solver.regularisation, jnp.float64))
        for frame in (x[0], x[-1]):
            d = frame[j] - frame[i]
            n = d / np.linalg.norm(d, axis=1, keepdims=True)
            J = np.zeros((len(i), x.shape[1] * x.shape[2]))
            for k in range(x.shape[2]):
                J[np.arange(len(i)), i * x.shape[2] + k] = -n[:, k]
                J[np.arange(len(i)), j * x.shape[2] + k] = n[:, k]
            A = (J * np.repeat(w, x.shape[2])) @ J.T
            A += np.diag(reg * np.diag(A))
            kappa = max(kappa, float(np.linalg.cond(A)))
    x_scale = np.abs(x).max()
    m_max = 1 / np.asarray(model.inv_mass)[np.asarray(model.inv_mass) > 0].min()
    return {"x": c * eps * kappa * x_scale,
            "v": c * eps * kappa * (np.abs(np.asarray(traj.v)).max() + x_scale / h),
            "lam": c * eps * kappa * (np.abs(np.asarray(traj.lam)).max() + m_max * x_scale / h)}


def test_parity_split_only_where_it_helps():
    """The last grid axis is parity-split only when it is even and some colour steps by 2 along it."""
    odd, _ = jc.scenes.cloth(7, 5)
    assert odd.topology.order is None and odd.topology.view == (5, 7)
    even_chain, _ = jc.scenes.chain(n_links=21)                  # 22 particles, colours step by 2
    assert even_chain.topology.order is not None and even_chain.topology.view == (22,)
    # stored even positions first: both colours are then contiguous runs (unit steps)
    assert all(b.strided and set(b.i_box[1]) == {1} for b in even_chain.topology.blocks)
    odd_chain, _ = jc.scenes.chain(n_links=20)
    assert odd_chain.topology.order is None
    # the user's order survives: positions in = positions out, through one zero-length rollout step
    model, state = jc.scenes.cloth(8, 4)
    final, _ = jc.rollout(model, state, jc.PGS(), 1e-9, 1)
    np.testing.assert_allclose(np.asarray(final.x), np.asarray(state.x), atol=1e-6)


def test_colour_order_changes_iterates_not_the_converged_solve():
    """Two valid colourings of a chain give different Gauss-Seidel orders; converged, they agree (the chain's
    J M^-1 J^T is positive definite, so lambda is unique). A redundant structure such as the cloth has no
    unique lambda, and there different orders legitimately converge to different multipliers."""
    model, state = jc.scenes.chain(n_links=7, length=1.4, mass=0.7, angle=0.9, dtype=np.float64)
    moving, _ = jc.rollout(model, state, jc.PGS(4), 1 / 240, 40)
    swapped, _ = jc.build(state.x, np.r_[1.0, 1 / np.asarray(model.inv_mass[1:])], rods=model.pairs, fixed=[0],
                          colouring=(np.arange(7) + 1) % 2)
    few, conv = jc.PGS(iterations=2, warm_start=False), jc.PGS(iterations=2000, warm_start=False)
    assert not np.allclose(np.asarray(jc.step(model, moving, few, 1 / 240).lam),
                           np.asarray(jc.step(swapped, moving, few, 1 / 240).lam), rtol=1e-6)
    c, d = jc.step(model, moving, conv, 1 / 240), jc.step(swapped, moving, conv, 1 / 240)
    np.testing.assert_allclose(np.asarray(c.x), np.asarray(d.x), rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.asarray(c.lam), np.asarray(d.lam), rtol=1e-10)


def test_cloth_hangs_from_its_two_corners():
    model, state = jc.scenes.cloth(8, 8, size=1.0, mass=1.0)
    _, tr = jc.rollout(model, state, jc.PGS(iterations=20, substeps=2), 1 / 240, 480)
    x = np.asarray(tr.x)
    np.testing.assert_array_equal(x[:, [0, 7]], np.broadcast_to(np.asarray(state.x)[[0, 7]], (480, 2, 3)))
    assert np.isfinite(x).all()
    assert x[:, :, 2].min() < -0.9              # the free edge swings down to about the side length
    assert x[:, :, 2].min() > -1.0 - 0.05       # ... and the cloth does not stretch much beyond it
    assert float(jnp.max(jc.violation(model, tr.x))) < 0.05


# ---- transformations ---------------------------------------------------------------------------------------
def test_jit_and_vmap_match_unbatched():
    model, state = jc.scenes.chain(n_links=5, length=1.0, mass=0.5, angle=0.8, dtype=np.float64)
    solver = jc.PGS(iterations=8, beta=0.2)
    scales = jnp.array([0.95, 1.0, 1.07])

    def run(scale, x0):
        return jc.rollout(model.replace(rest_length=model.rest_length * scale), state.replace(x=x0), solver,
                          1 / 240, 60)

    x0s = jnp.stack([state.x, state.x.at[1:].add(0.01), state.x.at[1:].add(-0.02)])
    batched_final, batched = jax.vmap(run)(scales, x0s)
    jitted = jax.jit(run)
    for k in range(3):
        f, tr = run(scales[k], x0s[k])
        fj, trj = jitted(scales[k], x0s[k])
        np.testing.assert_allclose(np.asarray(batched.x[k]), np.asarray(tr.x), rtol=0, atol=1e-13)
        np.testing.assert_allclose(np.asarray(batched.lam[k]), np.asarray(tr.lam), rtol=0, atol=1e-13)
        np.testing.assert_allclose(np.asarray(trj.x), np.asarray(tr.x), rtol=0, atol=1e-13)
        np.testing.assert_allclose(np.asarray(batched_final.v[k]), np.asarray(f.v), rtol=0, atol=1e-13)


def test_step_equals_one_rollout_step_and_save_every():
    model, state = jc.scenes.double_pendulum(dtype=np.float64)
    solver = jc.PGS()
    s = state
    for _ in range(4):
        s = jc.step(model, s, solver, 1 / 240)
    final, tr = jc.rollout(model, state, solver, 1 / 240, 4)
    np.testing.assert_allclose(np.asarray(s.x), np.asarray(final.x), atol=1e-14)
    np.testing.assert_allclose(np.asarray(s.lam), np.asarray(tr.lam[-1]), atol=1e-14)
    _, sparse = jc.rollout(model, state, solver, 1 / 240, 4, save_every=2)
    np.testing.assert_allclose(np.asarray(sparse.x), np.asarray(tr.x[1::2]), atol=1e-14)


def test_recorded_impulses_are_in_user_order_on_a_cloth():
    """rollout records each step's impulses flat in the solver's block order and reorders them once at the end;
    on a cloth (8 colour blocks, a non-trivial permutation) every recorded row must equal jc.step's lam."""
    model, state = jc.scenes.cloth(6, 5, dtype=np.float64)
    assert model.topology.n_colours > 2
    for solver in (jc.PGS(), jc.XPBD(substeps=2)):
        final, tr = jc.rollout(model, state, solver, 1 / 120, 3)
        s = state
        for k in range(3):
            s = jc.step(model, s, solver, 1 / 120)
            np.testing.assert_allclose(np.asarray(tr.lam[k]), np.asarray(s.lam), rtol=0, atol=1e-13)
        np.testing.assert_array_equal(np.asarray(tr.lam[-1]), np.asarray(final.lam))
        assert np.abs(np.asarray(final.lam)).max() > 0


def test_rollout_compiles_once_for_new_parameter_values():
    model, state = jc.scenes.chain(n_links=3)
    jc.rollout(model, state, jc.PGS(beta=0.2), 1 / 240, 7)
    before = _sim._rollout_jit._cache_size()
    for k in range(3):
        jc.rollout(model.replace(rest_length=model.rest_length * (1 + 0.01 * k)), state, jc.PGS(beta=0.1 + 0.05 * k),
                   1 / (200 + k), 7)
    assert _sim._rollout_jit._cache_size() == before


def test_dtypes_follow_inputs():
    for dtype in (np.float32, np.float64):
        model, state = jc.scenes.pendulum(dtype=dtype)
        final, tr = jc.rollout(model, state, jc.PGS(), 1 / 240, 3)
        assert final.x.dtype == dtype and tr.lam.dtype == dtype and model.rest_length.dtype == dtype


# ---- gradients ---------------------------------------------------------------------------------------------
def _fd(f, x, eps=1e-6):
    x = np.asarray(x, np.float64)
    g = np.zeros_like(x)
    for idx in np.ndindex(x.shape):
        e = np.zeros_like(x)
        e[idx] = eps
        g[idx] = (f(x + e) - f(x - e)) / (2 * eps)
    return g


def test_gradients_match_central_finite_differences():
    model, state = jc.scenes.chain(n_links=3, length=1.5, mass=0.6, angle=0.7, dtype=np.float64)
    state = state.replace(x=state.x.at[1:].multiply(1.03))      # start off the constraint manifold
    target = np.asarray(jc.rollout(model, state, jc.PGS(8), 1 / 120, 40)[1].x) + 0.05

    def loss(rest, beta, inv_mass, x0, v0, gravity):
        m = model.replace(rest_length=rest, inv_mass=inv_mass, gravity=gravity)
        _, tr = jc.rollout(m, state.replace(x=x0, v=v0), jc.PGS(iterations=8, beta=beta), 1 / 120, 40)
        return jnp.mean((tr.x - target) ** 2)

    args = [model.rest_length, jnp.asarray(0.2), model.inv_mass, state.x, state.v + 0.1, model.gravity]
    grads = jax.jit(jax.grad(loss, argnums=tuple(range(6))))(*args)
    floss = jax.jit(loss)
    for k, (a, g) in enumerate(zip(args, grads)):
        def f(val, k=k):
            b = list(args)
            b[k] = jnp.asarray(val)
            return float(floss(*b))
        fd = _fd(f, a)
        if k in (2, 3, 4):       # the fixed pivot's inverse mass / position: gradient masked by design
            fd, g = fd[1:], np.asarray(g)[1:]
        np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-5, atol=1e-9, err_msg=f"argument {k}")


def test_forward_and_reverse_mode_agree():
    model, state = jc.scenes.double_pendulum(angles=(0.4, 0.9), dtype=np.float64)

    def f(rest):
        return jc.rollout(model.replace(rest_length=rest), state, jc.PGS(6), 1 / 240, 30)[0].x

    t = jnp.array([0.3, -0.7])
    _, jvp = jax.jvp(f, (model.rest_length,), (t,))
    y, vjp = jax.vjp(f, model.rest_length)
    ct = jnp.asarray(np.random.default_rng(1).normal(size=y.shape))
    np.testing.assert_allclose(float(jnp.vdot(ct, jvp)), float(jnp.vdot(vjp(ct)[0], t)), rtol=1e-10)


@pytest.mark.parametrize("kind", ["rod", "rope"])
def test_coincident_particles_give_finite_values_and_gradients(kind):
    x = np.array([[0.0, 0.0], [0.3, 0.0], [0.3, 0.0]])     # particles 1 and 2 coincide
    pairs = [(0, 1), (1, 2)]
    model, state = jc.build(x, [1.0, 1.0, 1.0], rods=pairs if kind == "rod" else None,
                            ropes=pairs if kind == "rope" else None, fixed=[0], rest_lengths=[0.3, 0.2])

    def loss(rest, beta):
        _, tr = jc.rollout(model.replace(rest_length=rest), state, jc.PGS(5, beta=beta), 1 / 240, 20)
        return jnp.sum(tr.x ** 2) + jnp.sum(tr.lam ** 2)

    vg = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))
    val, grads = vg(model.rest_length, 0.2)
    assert np.isfinite(float(val))
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grads)
    # zero-length rest lengths too
    _, (g0, _) = vg(jnp.zeros(2), 0.2)
    assert np.all(np.isfinite(np.asarray(g0)))


def test_solver_built_with_traced_beta_and_vmap_over_beta():
    model, state = jc.scenes.pendulum(angle=0.5, dtype=np.float64)
    model = model.replace(rest_length=model.rest_length * 0.9)     # Baumgarte has work to do

    def loss(beta):
        return jc.rollout(model, state, jc.PGS(iterations=4, beta=beta), 1 / 240, 30)[1].x[-1, 1, 1]

    g = jax.jit(jax.grad(loss))(0.2)
    floss = jax.jit(loss)
    fd = (floss(0.2 + 1e-6) - floss(0.2 - 1e-6)) / 2e-6
    np.testing.assert_allclose(float(g), float(fd), rtol=1e-5)
    vals = jax.vmap(loss)(jnp.array([0.1, 0.2, 0.3]))
    np.testing.assert_allclose(np.asarray(vals), [float(floss(b)) for b in (0.1, 0.2, 0.3)], atol=1e-13)


def test_full_warm_start_with_baumgarte_explodes_a_long_chain_and_the_factor_fixes_it():
    """A documented property of the textbook method: a 50-link chain hanging at rest, 10 iterations, beta 0.2,
    gains energy through warm starting until it explodes (a naive per-constraint loop does the same); a
    warm-start factor of 0.85 keeps it bounded."""
    model, state = jc.scenes.chain(n_links=50, length=5.0, mass=0.5, angle=0.0, dtype=np.float64)

    def worst(factor):
        _, tr = jc.rollout(model, state, jc.PGS(10, beta=0.2, warm_start_factor=factor), 1 / 240, 240)
        return float(jnp.max(jc.violation(model, tr.x)))

    assert worst(1.0) > 1.0
    assert worst(0.85) < 0.05


def test_stopping_warm_start_gradients_keeps_the_forward_pass():
    model, state = jc.scenes.chain(n_links=4, length=1.0, mass=0.4, angle=0.6, dtype=np.float64)

    def run(rest, flag):
        return jc.rollout(model.replace(rest_length=rest), state, jc.PGS(3, warm_start_gradient=flag), 1 / 240, 60)[0].x

    np.testing.assert_array_equal(np.asarray(run(model.rest_length, True)), np.asarray(run(model.rest_length, False)))
    g_full = jax.grad(lambda r: jnp.sum(run(r, True) ** 2))(model.rest_length)
    g_stop = jax.grad(lambda r: jnp.sum(run(r, False) ** 2))(model.rest_length)
    assert np.all(np.isfinite(np.asarray(g_stop))) and not np.allclose(np.asarray(g_full), np.asarray(g_stop))


def test_batched_rollout_equals_vmap_and_checks_its_input():
    model, state = jc.scenes.double_pendulum(dtype=np.float64)
    x0 = jnp.stack([state.x, state.x.at[1:].multiply(0.99), state.x.at[2, 0].add(0.1)])
    states = jc.State(x0, jnp.zeros_like(x0), jnp.zeros((3, 2)))
    solver = jc.PGS(6)
    finals, trajs = jc.batched_rollout(model, states, solver, 1 / 240, 20, chunk=2, save_every=5)
    ref_f, ref_t = jax.vmap(lambda s: jc.rollout(model, s, solver, 1 / 240, 20, save_every=5))(states)
    np.testing.assert_allclose(np.asarray(trajs.x), np.asarray(ref_t.x), rtol=0, atol=1e-13)
    np.testing.assert_allclose(np.asarray(finals.lam), np.asarray(ref_f.lam), rtol=0, atol=1e-13)
    assert trajs.x.shape == (3, 4, 3, 2)
    with pytest.raises(ValueError, match="states.x"):
        jc.batched_rollout(model, state, solver, 1 / 240, 20)
    with pytest.raises(ValueError, match="chunk"):
        jc.batched_rollout(model, states, solver, 1 / 240, 20, chunk=0)
    with pytest.raises(ValueError, match="states.v"):
        jc.batched_rollout(model, states.replace(v=states.v.at[1, 1, 0].set(jnp.inf)), solver, 1 / 240, 20)


def test_implicit_differentiation_of_converged_multipliers():
    """PGS(implicit=True): same forward values; with converged sweeps its gradient equals the unrolled one and
    central finite differences; ropes are refused."""
    model, state = jc.scenes.chain(n_links=5, length=1.0, mass=0.5, angle=0.7, dtype=np.float64)
    state = state.replace(x=state.x.at[1:].multiply(1.02))

    def loss(rest, solver):
        return jnp.sum(jc.rollout(model.replace(rest_length=rest), state, solver, 1 / 240, 60)[0].x ** 2)

    unrolled, implicit = jc.PGS(200), jc.PGS(200, implicit=True)
    np.testing.assert_allclose(float(loss(model.rest_length, implicit)), float(loss(model.rest_length, unrolled)),
                               rtol=1e-13)
    g_imp = np.asarray(jax.jit(jax.grad(lambda r: loss(r, implicit)))(model.rest_length))
    f = jax.jit(lambda r: loss(r, unrolled))
    fd = _fd(lambda r: float(f(jnp.asarray(r))), model.rest_length)
    np.testing.assert_allclose(g_imp, fd, rtol=1e-7)
    rope_model, rope_state = jc.scenes.chain(n_links=3, kind="rope")
    with pytest.raises(ValueError, match="ropes"):
        jc.rollout(rope_model, rope_state, jc.PGS(implicit=True), 1 / 240, 2)


def test_diagnostics_keep_nan_in_large_maxima():
    """jaxlib 0.10.2's CPU max over 4096+ values skips NaN; the diagnostics must still report it."""
    from jaxcon.diagnostics import nan_max
    a = np.ones((3, 5000), np.float32)
    a[1, 17] = np.nan
    out = np.asarray(nan_max(a, axis=-1))
    assert out[0] == 1.0 and np.isnan(out[1]) and out[2] == 1.0
    assert np.isnan(float(nan_max(a)))
    # a trajectory that turns NaN on a model with > 4096 constraints: per-step violation is NaN, flagged
    model, state = jc.scenes.cloth(33, 33, dtype=np.float32)
    assert model.n_constraints > 4096
    _, tr = jc.rollout(model, state, jc.PGS(iterations=1), 1 / 60, 3)
    x = np.asarray(tr.x).copy()
    x[2] = np.nan
    bad = jc.Trajectory(jnp.asarray(x), tr.v, tr.lam)
    d = jc.diagnose(model, bad)
    assert np.isnan(np.asarray(d.violation)[2]) and bool(d.diverged) and int(d.first_bad) == 2


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_guarded_length_has_finite_gradients_near_zero(dtype):
    """|d| from 0 to 1e-9, including lengths whose |d|^-3 overflows the dtype: finite values and gradients."""
    from jaxcon.core import layout as L
    for s in (0.0, 1e-30, 1e-18, 1e-15, 1e-12, 1e-10, 1e-9):
        d = jnp.asarray([s, 0.0, 0.0], dtype)
        f = lambda d: L.safe_length(d)[0] + L.safe_length(d)[1] * 1e-20 + jnp.sum(L.safe_norm(d)[1])
        assert np.isfinite(float(f(d))) and np.all(np.isfinite(np.asarray(jax.grad(f)(d)))), (dtype, s)
    # through a rollout: two particles 1e-15 m apart, gradient wrt the positions
    model, state = jc.build(np.array([[0.0, 0.0], [1e-15, 0.0]], dtype), [1.0, 1.0], rods=[(0, 1)],
                            rest_lengths=[0.5])
    for solver in (jc.PGS(), jc.XPBD()):
        g = jax.grad(lambda x: jnp.sum(jc.rollout(model, jc.State(x, state.v, state.lam), solver, 1 / 60, 3)[0].x ** 2))(state.x)
        assert np.all(np.isfinite(np.asarray(g))), type(solver).__name__


# ---- the compact layout ------------------------------------------------------------------------------------
def test_layout_auto_picks_compact_for_small_many_coloured_models():
    assert jc.scenes.cloth(16, 16)[0].topology.compact          # 8 colours, at most 128 rods each
    assert not jc.scenes.cloth(32, 32)[0].topology.compact      # colours of up to 512 rods: unrolled
    chain = jc.scenes.chain(20)[0].topology
    assert not chain.compact and chain.unrolled is chain                # 2 colours: nothing to share
    c = jc.scenes.cloth(4, 4, layout="compact")[0].topology
    assert c.unrolled.layout == "unrolled" and c.unrolled.n_colours == c.n_colours
    with pytest.raises(ValueError, match="`layout` must be one of"):
        jc.scenes.cloth(4, 4, layout="fast")
    # a model without rods or ropes has no colours to put in a table: 'compact' leaves it as it is
    ball, b0 = jc.build([[0.0, 1.0]], 1.0, planes=[([0.0, 1.0], 0.0)], radius=0.1, layout="compact")
    assert ball.topology.layout == "unrolled" and ball.topology.n_colours == 0
    assert np.all(np.isfinite(np.asarray(jc.rollout(ball, b0, jc.PGS(), 1 / 60, 5)[0].x)))


def _mixed_rope_cloths():
    """A 5x4 cloth whose shear edges are ropes (rods and ropes in the same colours), in both layouts."""
    pairs, colour = jc.scenes.cloth_edges(5, 4)
    x = np.stack(np.meshgrid(np.linspace(0, 1, 5), np.linspace(0, 0.75, 4)), -1).reshape(-1, 2)
    x = np.concatenate([x, np.zeros((20, 1))], 1)
    d = np.abs(x[pairs[:, 0]] - x[pairs[:, 1]])
    shear = (d[:, 0] > 1e-9) & (d[:, 1] > 1e-9)
    col = np.concatenate([colour[~shear], colour[shear]])
    models = {lay: jc.build(x, np.full(20, 0.05), rods=pairs[~shear], ropes=pairs[shear], fixed=[0, 4],
                            colouring=col, dtype=np.float64, layout=lay) for lay in ("compact", "unrolled")}
    assert models["compact"][0].topology.compact and not models["unrolled"][0].topology.compact
    return models, int((~shear).sum())


def test_compact_layout_with_mixed_ropes_agrees():
    """Every solver that sweeps colours one by one, on both layouts of a cloth with rods and ropes in one colour,
    rest lengths 3% short (ropes taut, then slack as it swings): the same trajectory (float64)."""
    models, n_rods = _mixed_rope_cloths()
    rest = models["compact"][0].rest_length * 0.97
    for solver in (jc.PGS(iterations=6), jc.PGS(iterations=6, stabilization="split"), jc.Jacobi(iterations=6),
                   jc.XPBD(substeps=2), jc.SoftStep(substeps=2), jc.RATTLE(iterations=6)):
        run = {lay: jc.rollout(m.replace(rest_length=rest), s, solver, 1 / 120, 20)[1] for lay, (m, s) in
               models.items()}
        a, b = run["compact"], run["unrolled"]
        assert np.asarray(b.lam)[:, n_rods:].min() >= -1e-12, solver              # ropes only pull
        np.testing.assert_allclose(np.asarray(a.x), np.asarray(b.x), rtol=0, atol=1e-10, err_msg=repr(solver))
        np.testing.assert_allclose(np.asarray(a.lam), np.asarray(b.lam), rtol=0, atol=1e-10, err_msg=repr(solver))


def test_compact_layout_gradient_matches_unrolled_and_differences():
    """The gradient through the compact table's row scan (PGS) equals the unrolled layout's (rods and ropes
    mixed), and float64 central differences along a random direction (rods only)."""
    models, _ = _mixed_rope_cloths()
    rest0 = models["compact"][0].rest_length * 0.97

    def loss(rest, lay):
        model, state = models[lay]
        final, traj = jc.rollout(model.replace(rest_length=rest), state, jc.PGS(6), 1 / 120, 20)
        return jnp.sum(final.x[:, 2] ** 2) + jnp.sum(traj.lam ** 2)

    ga = jax.grad(loss)(rest0, "compact")
    gb = jax.grad(loss)(rest0, "unrolled")
    assert float(jnp.linalg.norm(gb)) > 0
    np.testing.assert_allclose(np.asarray(ga), np.asarray(gb), rtol=1e-7, atol=1e-9 * float(jnp.abs(gb).max()))
    # the ropes' clamps put kinks in that loss; central differences need the rods-only (smooth) cloth
    model, state = jc.scenes.cloth(5, 4, dtype=np.float64)
    assert model.topology.compact

    def smooth(rest):
        final, traj = jc.rollout(model.replace(rest_length=rest), state, jc.PGS(6), 1 / 120, 20)
        return jnp.sum(final.x[:, 2] ** 2) + jnp.sum(traj.lam ** 2)

    r0 = model.rest_length * 0.97
    u = np.random.default_rng(0).normal(size=r0.shape)
    eps = 1e-6
    fd = (smooth(r0 + eps * u) - smooth(r0 - eps * u)) / (2 * eps)
    np.testing.assert_allclose(float(jnp.dot(jax.grad(smooth)(r0), u)), float(fd), rtol=1e-6)
