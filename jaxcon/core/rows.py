"""Rows: what a solver needs of one block of constraints, whatever kind made them.

A *row* is one scalar constraint: its value C, its Jacobian J = dC/dx over its particles, their inverse masses
and its effective mass k = 1 / (J M^-1 J^T). Rods and ropes (pair blocks, `layout`) keep their tuned frame
(`solvers.common.Frame`: the unit normal n, wi, wj); a `jc.Constraint` set's block gets a `SetFrame`, with J
from `jax.grad` of the user's C. Solvers go through `rel` and `apply` and never look at which kind a block is:

  rel(v)        the rate at which the row's C_lib grows at velocities v: n . (v_j - v_i) for a rod, -J . v
  apply(v, dl)  v + M^-1 J^T dl: +w_i n dl at i and -w_j n dl at j for a rod, +w_p J_p dl for a set's row

Signs: the solvers use the rods' tension convention, C_lib = |x_j - x_i| - L (> 0 stretched) and lam > 0
pulling. A set's C_lib is -C of the user's function, and its lam the user's (the force is J^T lam): for a rod,
whose user C would be L - |x_j - x_i|, the two agree exactly (docs/constraints.md).
"""
from __future__ import annotations

import functools
from typing import Any, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from jaxcon.core import layout as L

Array = Any


class SetFrame(NamedTuple):
    """A `jc.Constraint` set's rows at some positions, row axes last (`layout.SetRow`): J [dim, k, *shape]
    (dC/dx of the user's C, dim first like a rod's n), w [k, *shape], C (C_lib = -C_user) [*shape],
    s = sum_p w_p |J_p|^2, k = 1 / s (0 where a row is padding, has no mobility or no defined gradient), alpha:
    the compliance [*shape], Jw = J w (M^-1 J^T, what `apply` scales: computed once per frame, not per sweep)."""

    J: Array
    w: Array
    C: Array
    s: Array
    k: Array
    alpha: Array
    Jw: Array


class SetSystem(NamedTuple):
    """A set's leaves in one of its blocks' layout, row axes last: params {name: [..., *block.shape]} and
    compliance [*block.shape] (a table's [C, W], or a colour of its own's [size]). The function and kind are
    static, on the model's `Constraint`."""

    params: dict
    compliance: Array


def set_system(con, block, first: int, dtype) -> SetSystem:
    """`con`'s parameters and compliance in the layout of one of its blocks (a table or a colour of its own; the
    set's constraints start at user constraint index `first`)."""
    local = np.where(block.real.array, block.src.array - first, con.m).astype(np.int32)

    def table(a):
        a = jnp.asarray(a)
        a = a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a
        r = tuple(range(local.ndim))
        return jnp.moveaxis(jnp.take(a, local, axis=0, mode="fill", fill_value=0), r, tuple(i - local.ndim for i in r))

    return SetSystem({k: table(v) for k, v in con.params.items()}, table(con.compliance))


#: Where a row's C or J is not finite at its positions, they are evaluated again at positions moved by this
#: fraction of the row's scale along a fixed pattern, so reverse mode through the (then masked) row sees finite
#: derivatives (the "double where" on the inputs; e.g. |x1 - x0| - L at x1 = x0).
_NUDGE = 1e-3


def evaluate(fn, x, params, grad=None):
    """C and J = dC/dx of rows: x [*rows, k, dim], params {name: [*rows, ...]} -> (C [*rows], J [*rows, k, dim],
    ok [*rows]) (`evaluate_last` with the row axes first)."""
    lead = x.shape[:-2]
    xl = jnp.moveaxis(x.reshape((-1,) + x.shape[-2:]), 0, -1)
    pl = jax.tree.map(lambda a: jnp.moveaxis(a.reshape((xl.shape[-1],) + a.shape[len(lead):]), 0, -1), params)
    C, J, ok = evaluate_last(fn, xl, pl, grad)
    return C.reshape(lead), jnp.moveaxis(J, -1, 0).reshape(lead + J.shape[:2]), ok.reshape(lead)


def evaluate_last(fn, x, params, grad=None):
    """C and J = dC/dx of rows, row axes last: x [k, dim, *rows], params {name: [..., *rows]} -> (C [*rows],
    J [k, dim, *rows], ok [*rows]); J from `grad(x, p)` where the kind supplies it (`Constraint.grad`), else
    from `jax.grad(fn)`. Rows whose C or J is not finite are reported not ok, with C and J 0; their
    derivatives are taken at nudged positions (so no NaN reaches reverse mode through them; e.g. |x1 - x0| - L
    at x1 = x0).

    The rows stay last so the vectorised C and J run along them (on CPU, with rows first, a 4-particle hinge's
    [rows, 4, 3] arrays made XPBD's bending 1.9x slower). They are evaluated once (`_rows`, a custom JVP): only
    a derivative of C and J with respect to x or the parameters evaluates them again, at the nudged positions
    where needed."""
    rows = x.shape[2:]
    xf = x.reshape(x.shape[:2] + (-1,))
    pf = jax.tree.map(lambda a: a.reshape(a.shape[: a.ndim - len(rows)] + (-1,)), params)
    C, J, ok = _rows((fn, grad), xf, pf)
    return C.reshape(rows), J.reshape(J.shape[:2] + rows), ok.reshape(rows)


def _value_and_grad(kernel):
    """(fn, grad or None) -> the rows' (C, J), vectorised along the last axis."""
    fn, grad = kernel
    one = jax.value_and_grad(fn) if grad is None else (lambda x, p: (fn(x, p), grad(x, p)))
    return jax.vmap(one, in_axes=(-1, -1), out_axes=(-1, -1))


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _rows(kernel, x, p):
    """(C, J, ok) of rows x [k, dim, r], params {[..., r]}: `evaluate_last` (`kernel`: (fn, grad))."""
    C, J = _value_and_grad(kernel)(x, p)
    ok = jnp.isfinite(C) & jnp.all(jnp.isfinite(J), axis=(0, 1))
    return jnp.where(ok, C, 0), jnp.where(ok, J, 0), ok


@_rows.defjvp
def _rows_jvp(kernel, primals, tangents):
    x, p = primals
    tx, tp = tangents
    C, J, ok = _rows(kernel, x, p)
    k, dim = x.shape[:2]
    pattern = jnp.asarray((np.arange(k * dim).reshape(k, dim, 1) % 7 + 1) / 7.0, x.dtype)
    scale = 1 + jnp.max(jnp.abs(x), axis=(0, 1))
    x_in = jnp.where(ok, x, x + _NUDGE * scale * pattern)
    _, (dC, dJ) = jax.jvp(_value_and_grad(kernel), (x_in, p), (tx, tp))
    return (C, J, ok), (jnp.where(ok, dC, 0), jnp.where(ok, dJ, 0), np.zeros(ok.shape, jax.dtypes.float0))


def set_frame(topo, block, con, ssys: SetSystem, x, w) -> SetFrame:
    """A set's rows at positions x [dim, *view] (`w`: inverse masses [1, *view]), for its whole block or a
    `SetRow` (then `ssys` holds that colour's rows)."""
    real = block.real.array
    xg = jnp.swapaxes(L.gather_rows(topo, block, x), 0, 1)                         # [k, dim, *rows]
    wg = L.gather_rows(topo, block, w)[0]                                           # [k, *rows]
    C, J, ok = evaluate_last(con.fn, xg, ssys.params, con.grad)
    J = jnp.swapaxes(J, 0, 1)                                                      # [dim, k, *rows]
    s = jnp.sum(wg * jnp.sum(J * J, axis=0), axis=0)
    live = ok & real & (s > L.min_length2(x.dtype))
    return SetFrame(J, wg, -C, s, jnp.where(live, L.safe_reciprocal(jnp.where(live, s, 1)), 0),
                    ssys.compliance, J * wg)


def rel(topo, block, f, v):
    """The rate of the rows' C_lib at velocities v [dim, *view] (module docstring)."""
    if getattr(block, "generic", None) is not None:
        return -L.dot_rows(topo, block, f.J, v)
    vi, vj = L.gather_pair(topo, block, v)
    return L.dot(block, vj - vi, f.n)


def apply(topo, block, f, v, dlam):
    """v + M^-1 J^T dlam for the rows' multiplier changes `dlam` (tension sign; module docstring)."""
    if getattr(block, "generic", None) is not None:
        return L.add_rows(topo, block, v, f.Jw * dlam)
    p = f.n * dlam
    return L.add_pair(topo, block, v, f.wi * p, -f.wj * p)


def compliant(f) -> Optional[Array]:
    """The rows' compliance where some row may be compliant, else None (rods and ropes: None)."""
    return getattr(f, "alpha", None)


# ---- the velocity-level row update, one for every kind and every sequential-impulse solver --------------------
# A colour's rows change their accumulated multipliers by `solve` (rhs: the rows' rel + bias): PGS's sweeps and
# implicit adjoint, Jacobi, SoftStep (which scales the change by its softness) and the contact rows' normal update
# (`solvers.contact`: rel = -vn, bias = the contact's target velocity). Every update, RATTLE's stages and the
# position sweeps included, adds its change and projects unilateral rows through `accumulate`.


def clamp(block, lam):
    """Project accumulated multipliers of a block (or a colour) onto lam >= 0 where its rows are unilateral:
    every row of a block with `all_rope` (ropes only, a unilateral set, contacts), the rope rows of a mixed one."""
    if block.all_rope:
        return jnp.maximum(lam, 0)
    if block.rope is not None:
        return jnp.where(block.rope.array, jnp.maximum(lam, 0), lam)
    return lam


def accumulate(block, lam, step):
    """lam + step, projected onto lam >= 0 where the rows are unilateral (`clamp`)."""
    return clamp(block, lam + step)


class Spring(NamedTuple):
    """A set's rows' implicit spring over a step h (`gamma`): g = alpha / h^2 and the reciprocal of the row's
    J M^-1 J^T + g (0 where the row is inactive), computed once per (sub)step rather than in every sweep."""

    g: Array
    inv: Array


def gamma(f, h):
    """A set's rows' compliance term alpha / h^2 (velocity level: the implicit spring of compliance alpha over a
    step h) with its solve's reciprocal (`Spring`), or None for rods and ropes."""
    a = compliant(f)
    if a is None:
        return None
    g = a / (h * h)
    return Spring(g, L.safe_reciprocal(f.s + g) * (f.k > 0).astype(g.dtype))


def solve(topo, blk, f, rhs, lam, g):
    """The multiplier changes of one colour's rows with right-hand side `rhs` (rel + bias): `layout.block_solve`,
    or for a set's compliant rows (`g`: their `Spring`, g = alpha / h^2) (rhs - g lam) / (J M^-1 J^T + g), the
    implicit spring (XPBD's update at velocity level: at rest, C = alpha * force; its warm start:
    `solvers.common.warm_rows`); a set's stars solve their compliant rows together, g on their diagonal."""
    if g is None:
        return L.block_solve(topo, blk, f, rhs)
    if getattr(blk, "hub_slot", None) is not None:
        return L.block_solve(topo, blk, f, rhs - g.g * lam, g.g)
    return (rhs - g.g * lam) * g.inv
