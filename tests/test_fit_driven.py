"""jc.fit on driven experiments: the experiment's known `forces` and `targets` reach every
rollout of the fit, sliced like the observations.

References: SciPy's DOP853 solution (1e-12) of a pendulum in its angle coordinate, on a pivot moving as
x = A sin(w t) or pushed by a known force (`jaxcon.bench.references.scipy_ode.driven_pendulum`), recorded at
30 Hz with 1 mm of Gaussian noise and fitted with RATTLE at 120 Hz (its forward error there is well under the
noise). The window and batch slicing is checked against the undivided rollout: at the true parameters the
loss of a windowed, batched fit is 0 to rounding."""
import warnings

import jax.numpy as jnp
import numpy as np
import pytest
from reference import driven_pendulum

import jaxcon as jc

HZ, EVERY, T = 120, 4, 2.0            # 240 steps, a frame every 4 (30 Hz), t = 0 observed
DT, N = 1 / HZ, int(round(T * HZ))
SS = np.arange(N // EVERY + 1) * EVERY
TF = SS * DT
NOISE = 1e-3


def _noisy(bob, seed):
    return bob[:, None] + NOISE * np.random.default_rng(seed).standard_normal(bob[:, None].shape)


# ---- a pendulum on a pivot moving as x = A sin(w t) (targets) ----------------------------------------------------
L, A, W, ANGLE, OMEGA = 0.8, 0.1, 5.0, 0.4, 0.5


def _pivot(s):
    return (np.array([A * np.sin(W * s), 0.0]), np.array([A * W * np.cos(W * s), 0.0]),
            np.array([-A * W * W * np.sin(W * s), 0.0]))


def moving_pivot_setup(theta, model, state, solver):
    """The rod length, the initial angle and angular velocity; the bob starts moving with the pivot (A w) plus
    its swing."""
    a, w, length = theta["angle"], theta["omega"], theta["length"]
    e, ea = jnp.stack([jnp.sin(a), -jnp.cos(a)]), jnp.stack([jnp.cos(a), jnp.sin(a)])
    v = jnp.array([A * W, 0.0]) + length * w * ea
    return (model.replace(rest_length=length[None]), state.replace(x=state.x.at[1].set(length * e),
                                                                   v=state.v.at[1].set(v)), solver)


@pytest.mark.optimised          # ~90 Levenberg-Marquardt updates over 240 steps
def test_fit_of_a_pendulum_on_a_moving_pivot_recovers_its_length():
    """The bob's recorded positions (the pivot's path is the known input, `targets`), fitted for the length,
    the initial angle and the unknown angular velocity from a length 12.5% short and no angular velocity.
    Measured (float64, 2-core AMD EPYC VM, jax 0.10.2): length +0.025% (1-sigma 0.013%), RMS error 0.89 mm,
    converged after 90 updates. The same fit without `targets` (a pivot that stays put) ends not converged, a
    misfit of 34.5 mm RMS."""
    bob, _ = driven_pendulum(TF, L, ANGLE, OMEGA, pivot=_pivot)
    obs = _noisy(bob, 5)
    ts = np.arange(1, N + 1) * DT
    targets = np.stack([A * np.sin(W * ts), 0 * ts], -1)[:, None, :]           # [steps, 1 fixed, 2]
    a0 = float(np.arctan2(obs[0, 0, 0], -obs[0, 0, 1]))                          # read off the first frame
    model, state = jc.scenes.pendulum(length=0.7, angle=a0)
    theta0 = {"angle": np.array(a0), "omega": np.array(0.0), "length": np.array(0.7)}
    with warnings.catch_warnings():
        warnings.simplefilter("error")          # no identifiability or misfit warning
        res = jc.fit(model, state, jc.RATTLE(10), DT, obs, theta0, setup=moving_pivot_setup, observed_particles=[1],
                     sample_steps=SS, targets=targets, transforms={"length": "log"}, progress=False)
    assert res.converged and res.reason == "tolerance", res.reason
    got = {k: float(v) for k, v in res.params.items()}
    assert abs(got["length"] / L - 1) < 1e-3, got
    for name, true in (("length", L), ("angle", ANGLE), ("omega", OMEGA)):
        assert abs(got[name] - true) < 3 * float(res.std[name]), (name, got[name], true, res.std[name])
    assert 0.8 * NOISE < res.rms < 1.2 * NOISE, res.rms


# ---- a pendulum pushed by a known force (forces): its mass is identifiable -------------------------------------
M = 0.5
PUSHES = ((0.3, lambda s: np.array([2.0 * np.sin(3.0 * s), 0.0])),
          (-0.2, lambda s: np.array([1.0, 1.5 * np.cos(5.0 * s)])))


def test_fit_of_a_pushed_pendulum_recovers_its_mass_from_two_recordings():
    """Two recordings of the same pendulum (0.8 m, 0.5 kg, fixed pivot), released from rest at two angles and
    pushed by two known forces (N, held during each step at its midpoint value): one batched fit, one force
    sequence per recording. With positions alone the mass scale is not identifiable; the known force sets it.
    From 1 kg: measured 0.500016 kg (+0.003%, 1-sigma 0.025%), converged, no IdentifiabilityWarning."""
    mid = (np.arange(N) + 0.5) * DT
    obs, forces, x0 = [], [], []
    for k, (angle, push) in enumerate(PUSHES):
        bob, _ = driven_pendulum(TF, L, angle, 0.0, force=push, mass=M)
        obs.append(_noisy(bob, 7 + k))
        f = np.zeros((N, 2, 2))
        f[:, 1] = np.stack([push(s) for s in mid])
        forces.append(f)
        x0.append([[0.0, 0.0], [L * np.sin(angle), -L * np.cos(angle)]])
    model, _ = jc.build(np.array(x0[0]), [1.0, 1.0], rods=[(0, 1)], fixed=[0])
    states = jc.State(jnp.asarray(x0), jnp.zeros((2, 2, 2)), jnp.zeros((2, 1)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = jc.fit(model, states, jc.RATTLE(10), DT, np.stack(obs), ("inv_mass",), observed_particles=[1],
                     sample_steps=SS, forces=np.stack(forces), horizon="full", progress=False)
    assert res.converged and res.reason == "tolerance", res.reason
    w, sd = float(res.params["inv_mass"][1]), float(res.std["inv_mass"][1])
    assert abs(1 / w / M - 1) < 1e-3 and abs(w - 1 / M) < 3 * sd, (1 / w, sd)
    assert float(res.params["inv_mass"][0]) == 0.0                               # the pivot stays fixed


# ---- windows and batches slice the drive like the observations --------------------------------------------------
def test_windows_and_batches_slice_the_drive_with_the_observations():
    """Two recordings made by jc.rollout itself, each on its own pivot path (`targets` [B, steps, 1, 2]) under
    one force sequence shared by both (`forces` [steps, n, 2], no batch axis), observed every 3rd step from
    t = 0: a fit started at the truth, with windows of 12 steps, has a loss of 0 to rounding (4e-32 m^2),
    and the windows' fixed particles start on their targets (known, not fitted). With the forces one step out
    of place it is 1.1e-6 m^2; with every window given the first window's drive, 1.2e-3 m^2."""
    steps, dt = 48, 1 / 120
    rng = np.random.default_rng(3)
    model, state = jc.scenes.double_pendulum(lengths=(0.5, 0.4), angles=(0.6, -0.3))
    n = model.n_particles
    forces = rng.normal(scale=2.0, size=(steps, n, 2))
    targets = np.cumsum(rng.normal(scale=0.004, size=(2, steps, 1, 2)), 1)
    states = jc.State(jnp.stack([state.x, state.x.at[2, 0].add(0.1)]), jnp.zeros((2, n, 2)), jnp.zeros((2, 2)))
    ss = np.arange(0, steps + 1, 3)
    obs = []
    for b in range(2):
        s = jc.State(states.x[b], states.v[b], states.lam[b])
        _, tr = jc.rollout(model, s, jc.RATTLE(10), dt, steps, forces=forces, targets=targets[b])
        obs.append(np.concatenate([np.asarray(s.x)[None], np.asarray(tr.x)])[ss])
    kw = dict(sample_steps=ss, steps=1, progress=False, window=12, optimizer="adam", targets=targets)
    res = jc.fit(model, states, jc.RATTLE(10), dt, np.stack(obs), ("rest_length",), forces=forces, **kw)
    assert res.history[0] < 1e-26, res.history[0]
    ws = np.asarray(res.window_states.x)                                          # [B, 3 windows, n, 2]
    np.testing.assert_array_equal(ws[:, :, 0], targets[:, [11, 23, 35], 0])
    shifted = jc.fit(model, states, jc.RATTLE(10), dt, np.stack(obs), ("rest_length",), forces=np.roll(forces, 1, 0),
                     **kw)
    assert shifted.history[0] > 1e-9, shifted.history[0]


# ---- bad input, refused before tracing, naming the argument -----------------------------------------------------
def test_fit_refuses_a_bad_drive_naming_the_argument():
    model, state = jc.scenes.pendulum(length=1.0, angle=0.3)
    obs = np.zeros((5, 2, 2))
    fit = lambda **kw: jc.fit(model, state, jc.PGS(5), 1 / 60, obs, progress=False, **kw)   # noqa: E731
    with pytest.raises(ValueError, match=r"`forces` must have shape \(max\(sample_steps\), n, dim\) = \(5, 2, 2\)"):
        fit(forces=np.zeros((4, 2, 2)))
    with pytest.raises(ValueError, match=r"`targets` must have shape \(max\(sample_steps\), n_fixed, dim\) = \(10, 1"):
        fit(targets=np.zeros((5, 1, 2)), sample_steps=np.arange(0, 10, 2) + 2)
    with pytest.raises(ValueError, match="`targets`.*finite"):
        fit(targets=np.full((5, 1, 2), np.nan))
    with pytest.raises(TypeError, match="`forces`"):
        fit(forces=np.zeros((5, 2, 2), complex))
    free, free_state = jc.build([[0.0, 0.0], [1.0, 0.0]], [1.0, 1.0], rods=[(0, 1)])
    with pytest.raises(ValueError, match="`targets`.*no fixed"):
        jc.fit(free, free_state, jc.PGS(5), 1 / 60, obs, targets=np.zeros((5, 0, 2)), progress=False)
    batch = jc.State(jnp.stack([state.x] * 2), jnp.zeros((2, 2, 2)), jnp.zeros((2, 1)))
    with pytest.raises(ValueError, match=r"`forces` must have shape \(batch, max\(sample_steps\), n, dim\) = "
                                         r"\(2, 5, 2, 2\) or .* shared by every recording"):
        jc.fit(model, batch, jc.PGS(5), 1 / 60, np.stack([obs] * 2), forces=np.zeros((3, 5, 2, 2)), progress=False)
