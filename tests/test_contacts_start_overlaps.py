"""Particles that start inside an obstacle or another particle: every contact solver pushes them out
in a defined direction (the last axis, up, where the centres coincide: `contact_rows.direction`), at no more than
`contact_rows.PUSH_OUT_SPEED` (Box2D's 3 m/s cap), and never with more kinetic energy than that push-out's.

Before: a particle at a sphere's exact centre fell straight through it (no normal); one 0.3 R off the centre of a
1 m sphere left at beta C / h (38 m/s with PGS(10, substeps=4), z = 58 m after 2 s), and Penalty's spring flung
it at 100 m/s; two colliding particles at the same point were never separated by any solver.

One 3-D scene per solver, without gravity: particle 0 at the centre of one sphere, particle 1 at 0.3 R below the
centre of another, particles 2 and 3 (masses 1 and 3) at the same point far from both, colliding.
"""
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcon as jc
from jaxcon.core.contact_rows import PUSH_OUT_SPEED

R, r = 0.5, 0.05
MASSES = np.array([1.0, 1.0, 1.0, 3.0])

SOLVERS = {
    "PGS": jc.PGS(10),
    "PGS-substeps": jc.PGS(10, substeps=4),          # the worst fling before: beta C / h with h = dt / 4
    "Jacobi": jc.Jacobi(20),
    "XPBD": jc.XPBD(substeps=4),
    "RATTLE": jc.RATTLE(),
    "SoftStep": jc.SoftStep(substeps=4),
    "Penalty": jc.Penalty(stiffness=1e4, substeps=20),
}


def _scene(dim=3, collide=((2, 3),)):
    up = np.eye(dim)[-1]
    centres = np.zeros((2, dim))
    centres[1, 0] = 3.0
    x = np.stack([centres[0], centres[1] - 0.3 * R * up, np.full(dim, 6.0), np.full(dim, 6.0)])
    return jc.build(x, MASSES, gravity=np.zeros(dim), radius=r, spheres=[(c, R) for c in centres],
                    collide=[tuple(p) for p in collide] if not isinstance(collide, str) else collide,
                    restitution=0.5, friction=0.3)


def _check(model, traj, slack=1e-3):
    up = np.eye(traj.x.shape[-1])[-1]
    x, v = np.asarray(traj.x), np.asarray(traj.v)
    centres = np.asarray(model.sphere_centre)
    # out of the spheres (within `slack`; a velocity-level push-out may leave them moving away, as no gravity
    # brings them back), the one at the centre upwards, the off-centre one downwards, by its nearest surface
    for k, sign in ((0, 1), (1, -1)):
        d = x[-1, k] - centres[k]
        assert np.linalg.norm(d) >= (R + r) * (1 - slack) and sign * d @ up > (1 - 1e-9) * np.linalg.norm(d), d
    # the coincident pair apart, the lower-numbered particle below, its momentum unchanged (zero)
    d = x[-1, 3] - x[-1, 2]
    assert np.linalg.norm(d) >= 2 * r * (1 - slack) and d @ up > (1 - 1e-9) * np.linalg.norm(d), d
    np.testing.assert_allclose((MASSES[2:, None] * v[:, 2:]).sum(1), 0, atol=1e-9)
    # pushed out at a bounded speed: no faster than the cap, so never more than the push-out's kinetic energy,
    # (m / 2) cap^2 for an obstacle contact and (m_eff / 2) cap^2 for the pair (m_eff = m_2 m_3 / (m_2 + m_3))
    speed = np.linalg.norm(v, axis=-1)
    assert speed[:, :2].max() <= PUSH_OUT_SPEED * (1 + 1e-9), speed.max(axis=0)
    assert np.linalg.norm(v[:, 3] - v[:, 2], axis=-1).max() <= PUSH_OUT_SPEED * (1 + 1e-9)
    ke = 0.5 * (MASSES * speed ** 2).sum(1)
    m_eff = MASSES[2] * MASSES[3] / (MASSES[2] + MASSES[3])
    assert ke.max() <= 0.5 * PUSH_OUT_SPEED ** 2 * (MASSES[0] + MASSES[1] + m_eff) * (1 + 1e-9)


@pytest.mark.parametrize("name", list(SOLVERS))
def test_start_overlaps_are_pushed_out_at_a_bounded_speed(name):
    model, state = _scene()
    dt = 1 / 60
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)        # Penalty's stability estimate counts 12 contacts
        _, traj = jc.rollout(model, state, SOLVERS[name], dt, 30)
    # SoftStep's soft contacts (30 Hz, damping ratio 10) are overdamped: after 0.5 s the pair still overlaps
    # by 1.3% of a diameter, the spheres by 0.05% of R + r
    _check(model, traj, 0.02 if name == "SoftStep" else 1e-3)


@pytest.mark.parametrize("solver", [jc.PGS(10), jc.Jacobi(20)], ids=["PGS", "Jacobi"])
def test_coincident_particles_separate_in_a_grid_model_in_2d(solver):
    model, state = _scene(dim=2, collide="grid")
    _, traj = jc.rollout(model, state, solver, 1 / 60, 30)
    _check(model, traj)
    assert int(np.max(traj.contact_overflow)) == 0


def test_start_overlap_gradients_are_finite():
    """The fixed direction at coincident centres has a zero derivative; the gradient stays finite (2-D: a
    particle at a circle's centre and a coincident pair)."""
    def loss(p):
        x = jnp.stack([jnp.zeros(2), p, p])
        model, state = jc.build(x, np.ones(3), gravity=np.zeros(2), radius=r, spheres=[(np.zeros(2), R)],
                                collide=[(1, 2)])
        _, traj = jc.rollout(model, state, jc.PGS(4), 1 / 60, 3)
        return (traj.x[-1] ** 2).sum()

    g = jax.grad(loss)(jnp.array([2.0, 2.0]))
    assert np.all(np.isfinite(np.asarray(g)))
