"""Penalty and SoftStep refuse a hard constraint set in a model with contacts (before tracing, naming the solvers
that hold it), and accept the same set with a compliance; the solvers that hold hard sets run it."""
import numpy as np
import pytest

import jaxcon as jc

TRIANGLE = np.array([[0.0, 0.1], [0.3, 0.1], [0.0, 0.4]])


def _model(compliance, planes=True):
    area = jc.constraints.area([[0, 1, 2]], positions=TRIANGLE, compliance=compliance)
    return jc.build(TRIANGLE, 0.1, constraints=[area], planes=[((0.0, 1.0), 0.0)] if planes else None)


@pytest.mark.parametrize("solver", [jc.Penalty(), jc.SoftStep()], ids=["Penalty", "SoftStep"])
def test_a_hard_set_under_contacts_is_refused_with_the_solvers_that_hold_it(solver):
    model, state = _model(0.0)
    with pytest.raises(ValueError, match=r"hard constraint set 'area'.*jc\.PGS, jc\.Direct or jc\.XPBD"):
        jc.rollout(model, state, solver, 1 / 240, 2)
    soft, soft_state = _model(1e-3)                      # a compliant set is a spring there: accepted
    assert np.isfinite(np.asarray(jc.rollout(soft, soft_state, solver, 1 / 240, 2)[1].x)).all()
    free, free_state = _model(0.0, planes=False)         # no contacts to press on it: accepted
    assert np.isfinite(np.asarray(jc.rollout(free, free_state, solver, 1 / 240, 2)[1].x)).all()
