"""Argument checks shared by the model, the rollouts and the solvers: dtypes, shapes, finite values, scalars."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcon.core.pytree import concrete


def check_int(owner, name, value, minimum):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{owner}: `{name}` must be a Python int (it is static), got {value!r}")
    if value < minimum:
        raise ValueError(f"{owner}: `{name}` must be >= {minimum}, got {value}")


def check_bool(owner, name, value):
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{owner}: `{name}` must be a bool, got {value!r}")


def check_scalar(owner, name, value, lo=None, hi=None, *, positive=False):
    """Scalar, finite, within [lo, hi] and (if `positive`) > 0, for values known now; tracers are skipped."""
    check_real(owner, name, value)
    if np.ndim(value) != 0:
        raise ValueError(f"{owner}: `{name}` must be a scalar, got shape {np.shape(value)}")
    a = concrete(value)
    if a is None:
        return
    a = float(a)
    if not np.isfinite(a):
        raise ValueError(f"{owner}: `{name}` must be finite, got {a}")
    if lo is not None and a < lo:
        raise ValueError(f"{owner}: `{name}` must be >= {lo}, got {a}")
    if hi is not None and a > hi:
        raise ValueError(f"{owner}: `{name}` must be <= {hi}, got {a}")
    if positive and not a > 0:
        raise ValueError(f"{owner}: `{name}` must be > 0, got {a}")


def describe_shape(shape) -> str:
    """'a scalar' for (), else 'shape (..)': what an error message says was passed."""
    shape = tuple(shape)
    return "a scalar" if shape == () else f"shape {shape}"


def check_shape(owner: str, name: str, value, shape: tuple, hint: str = "") -> None:
    got = tuple(np.shape(value))
    if got != tuple(shape):
        want = "be a scalar" if tuple(shape) == () else f"have shape {tuple(shape)}"
        raise ValueError(f"{owner}: `{name}` must {want}, got {describe_shape(got)}{hint}")


def check_values(owner: str, name: str, value, *, nonneg: bool = False, positive: bool = False) -> None:
    """Finite (and optionally >= 0 or > 0) check on values known now; tracers are skipped."""
    a = concrete(value)
    if a is None:
        return
    if a.dtype.kind not in "biuf":
        if not jnp.issubdtype(a.dtype, jnp.floating):
            raise TypeError(f"{owner}: `{name}` must be real numbers, got dtype {a.dtype}")
        a = a.astype(np.float32)        # bfloat16 and other ml_dtypes floats: real numbers, checked in float32
    bad = ~np.isfinite(a)
    if bad.any():
        idx = np.argwhere(bad)[0].tolist()
        raise ValueError(f"{owner}: `{name}` must be finite; entry {idx} is {a[tuple(idx)]}")
    if nonneg and (a < 0).any():
        idx = np.argwhere(a < 0)[0].tolist()
        raise ValueError(f"{owner}: `{name}` must be >= 0; entry {idx} is {a[tuple(idx)]}")
    if positive and (a <= 0).any():
        idx = np.argwhere(a <= 0)[0].tolist()
        raise ValueError(f"{owner}: `{name}` must be > 0; entry {idx} is {a[tuple(idx)]}")


def default_float() -> np.dtype:
    """JAX's default float dtype: float64 when `jax_enable_x64` is on, float32 otherwise."""
    return np.dtype(jnp.result_type(float))


def resolve_dtype(owner: str, dtype, *inputs, names: str = "the float values passed") -> np.dtype:
    """The float dtype an array-building call uses: `dtype` when given (it must be a floating dtype), else the
    promoted dtype of the floating-point arrays among `inputs` (so dtypes follow the inputs), else JAX's
    default float dtype. The result is canonical for the current x64 setting. Half precision is refused
    (`check_simulation_dtype`; `names` says which inputs set it)."""
    if dtype is not None:
        try:
            d = np.dtype(dtype)
        except TypeError:
            raise TypeError(f"{owner}: `dtype` must be a floating-point dtype, got {dtype!r}") from None
        if not jnp.issubdtype(d, jnp.floating):
            raise TypeError(f"{owner}: `dtype` must be a floating-point dtype (float32, float64), got {d}")
        check_simulation_dtype(owner, "dtype", d)
        return np.dtype(jax.dtypes.canonicalize_dtype(d))
    floats = [jnp.result_type(a) for a in inputs
              if hasattr(a, "dtype") and jnp.issubdtype(jnp.result_type(a), jnp.floating)]
    d = np.dtype(jax.dtypes.canonicalize_dtype(jnp.result_type(*floats) if floats else default_float()))
    check_simulation_dtype(owner, names, d, given=False)
    return d


#: The float dtypes a model and state may have. Half-precision values (float16, bfloat16) are real numbers and
#: are accepted as inputs wherever they are cast to the model's dtype, but nothing is simulated in them: a
#: float16 step h must satisfy 7.8 s <= h <= 0.26 s (h^2 and 1 / h^2 normal numbers), an empty range.
SIMULATION_DTYPES = ("float32", "float64")


def check_simulation_dtype(owner: str, name: str, dtype, given: bool = True) -> None:
    """Refuse a float dtype jaxcon does not simulate in (half precision), naming what set it."""
    d = np.dtype(dtype)
    if d.name in SIMULATION_DTYPES:
        return
    how = f"`{name}` is {d.name}" if given else f"{name} are {d.name}, so the model would be {d.name}"
    raise TypeError(f"{owner}: {how}, but jaxcon simulates in float32 or float64 only (half precision cannot "
                    "hold a time step: h^2 and 1 / h^2 leave its normal range); pass dtype=np.float32 (values "
                    "are cast) or cast the inputs")


def check_real(owner: str, name: str, value) -> None:
    """Refuse values that are not real numbers (strings, complex, bool, objects) by their dtype; works on tracers."""
    try:
        dt = jnp.result_type(value) if hasattr(value, "dtype") else np.asarray(value).dtype
    except (TypeError, ValueError):
        raise TypeError(f"{owner}: `{name}` must be real numbers, got {type(value).__name__}") from None
    if dt.kind not in "iuf" and not jnp.issubdtype(dt, jnp.floating):
        what = {"c": "complex", "b": "bool", "U": "str", "S": "bytes", "O": "object"}.get(dt.kind, str(dt))
        raise TypeError(f"{owner}: `{name}` must be real numbers, got {what} values (dtype {dt})")
