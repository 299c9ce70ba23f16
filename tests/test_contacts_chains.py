"""Impacts passed on through touching bodies (`contact_rows.chain_bounces`): a ball hitting a row of touching balls
gives its velocity to the last one, in listed pairs and on the neighbour grid, and no energy is gained. The
cradle, the pyramid and the column over every solver are in the conformance matrix (`cases_piles`)."""
import numpy as np
import pytest

import jaxcon as jc


def _row(collide, e=1.0):
    x0 = np.array([[-0.013, 0.0], [0.3, 0.0], [0.5, 0.0], [0.7, 0.0]])
    v0 = np.array([[3.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    return jc.build(x0, 1.0, velocities=v0, radius=0.1, collide=collide, restitution=e,
                    restitution_threshold=0.0, gravity=np.zeros(2))


@pytest.mark.parametrize("collide", [True, "grid"])
@pytest.mark.parametrize("solver", [jc.PGS(10), jc.XPBD()], ids=lambda s: type(s).__name__)
def test_a_hit_passes_through_a_row_of_touching_balls(collide, solver):
    """Measured: listed pairs [0, 0, 0, 3] to 1e-6 in both; on the grid (slots relaxed by mass splitting) PGS
    leaves up to 0.023 m/s on the middle balls and 2.965 m/s on the last, XPBD [0, 0, 0, 3]."""
    model, state = _row(collide)
    _, traj = jc.rollout(model, state, solver, 1 / 60, 10)
    v = np.asarray(traj.v[-1, :, 0])
    tol = 0.05 if collide == "grid" else 1e-5
    np.testing.assert_allclose(v, [0.0, 0.0, 0.0, 3.0], atol=tol)
    np.testing.assert_allclose(np.asarray(traj.v).sum(1)[:, 0], 3.0, atol=1e-9)           # momentum
    ke = 0.5 * np.sum(np.asarray(traj.v) ** 2, (1, 2))
    assert ke.max() <= 4.5 * (1 + 1e-9)


def _sequential_impacts(v, e):
    """Newton's rule pair by pair along a row of equal balls, in order, until no pair approaches."""
    v = np.array(v, float)
    while True:
        hit = False
        for i in range(len(v) - 1):
            u = v[i] - v[i + 1]
            if u > 0:
                v[i], v[i + 1], hit = v[i] - (1 + e) * u / 2, v[i + 1] + (1 + e) * u / 2, True
        if not hit:
            return v


@pytest.mark.parametrize("solver", [jc.PGS(40), jc.XPBD()], ids=lambda s: type(s).__name__)
def test_partial_restitution_is_the_sequence_of_pairwise_impacts(solver):
    """e = 0.5: PGS ends the row as the sequence of pairwise impacts in order does, [0.521, 0.580, 0.633, 1.266]
    m/s (the first ball hits the second again after the second has hit the third). XPBD meets the balls one pair
    per substep, another order of the same impacts: measured [0.530, 0.565, 0.639, 1.266]; the last ball's
    speed, the momentum and the ordering (no pair approaching) are the same, and energy is lost."""
    model, state = _row(True, 0.5)
    _, traj = jc.rollout(model, state, solver, 1 / 60, 10)
    v = np.asarray(traj.v[-1, :, 0])
    ref = _sequential_impacts([3.0, 0.0, 0.0, 0.0], 0.5)
    if isinstance(solver, jc.PGS):
        np.testing.assert_allclose(v, ref, atol=1e-6)
    else:
        assert abs(v[-1] - ref[-1]) < 1e-6 and np.all(np.diff(v) >= -1e-9)
        assert np.abs(v - ref).max() < 0.02
    assert abs(v.sum() - 3.0) < 1e-9
    assert 0.5 * np.sum(v ** 2) < 4.5
