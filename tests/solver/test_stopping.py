"""The iterations' stopping rule (``solver._kernel.remaining_error``,
``solver._mixed.iteration_converged``)."""

import jax.numpy as jnp
import pytest

from hartrao_jax.solver._kernel import next_rate, remaining_error
from hartrao_jax.solver._mixed import iteration_converged


def test_remaining_error_is_the_rest_of_a_geometric_series():
    """Steps 3.1, 0.082 sigma (a full-resolution position): rate 0.026, the rest after the
    second step 0.0022 sigma (the third step measured 4.5e-5); a slow contraction (rate >= 0.5)
    leaves the step itself."""
    rate = float(next_rate(1.0, 3.119, 0.08194, False))
    assert rate == pytest.approx(0.02627, rel=1e-3)
    assert float(remaining_error(0.08194, rate)) == pytest.approx(0.08194 * rate / (1 - rate))
    assert float(remaining_error(0.06, float(next_rate(1.0, 0.1, 0.06, False)))) == 0.06
    assert float(next_rate(1.0, 0.0, 0.5, False)) == 1.0  # no previous step: no extrapolation
    assert float(next_rate(1.0, float("inf"), 0.5, False)) == 1.0
    assert float(next_rate(0.02, 0.1, 0.5, True)) == 0.02  # a restart keeps the rate


def test_random_effect_stops_on_the_prediction_only_with_settled_variances():
    """A predicted rest below tol ends the iteration only when no variance component's rest
    of change (its change times the contraction, as the steps') is 0.5 % or more; the step
    itself below tol always does. Without a measured contraction the change itself counts."""
    var0 = (jnp.asarray(1.0), jnp.ones(3), jnp.ones(0))
    var = (jnp.asarray(1.0), jnp.ones(3), jnp.ones(0))
    moved = (jnp.asarray(1.02), jnp.ones(3), jnp.ones(0))
    far = (jnp.asarray(1.5), jnp.ones(3), jnp.ones(0))
    rate = next_rate(1.0, 0.5, 0.01, False)  # 0.02: the rest is 2e-4 sigma
    assert bool(iteration_converged(0.01, rate, 1e-3, var, var, var0))
    # 2 % moved at rate 0.02: 4e-4 of it left; 50 % moved: 0.83 % left
    assert bool(iteration_converged(0.01, rate, 1e-3, var, moved, var0))
    assert not bool(iteration_converged(0.01, rate, 1e-3, var, far, var0))
    assert bool(iteration_converged(5e-4, rate, 1e-3, var, far, var0))
    # a warm start's first step (7 sigma at the start's contraction 5.3e-4, the tilts' start
    # values 1e-8 against their 6e-9 here): 3.7e-3 sigma and 0.03 % left
    tilts = (jnp.asarray(1.0), jnp.asarray([1.0, 0.6, 0.6]), jnp.ones(0))
    assert bool(iteration_converged(7.0, 5.3e-4, 1e-2, tilts, var, var0))
    assert not bool(iteration_converged(7.0, 1.0, 1e-2, tilts, var, var0))


def test_a_measured_start_rate_is_kept_until_the_iteration_measures_its_own():
    """An adjustment started from another's solution of the same problem begins with that
    one's contraction (``rate0``): no previous step keeps it, the second step replaces it."""
    assert float(next_rate(0.02, 0.0, 0.5, False)) == 0.02
    assert float(next_rate(0.02, 0.1, 0.05, False)) == pytest.approx(0.5)


def test_the_rule_is_the_same_traced_and_on_the_host():
    """The rule serves the compiled loops (traced: ``jax.numpy``) and the host's (NumPy, no
    JAX program per call shape: ``_kernel.array_namespace``): the same values either way."""
    import jax
    import numpy as np

    var0 = (np.asarray(1.0), np.ones(3), np.full(2, 1e-9))
    cases = [((0.01, 0.02, 1e-3), (np.asarray(1.0), np.ones(3), np.full(2, 1e-17)),
              (np.asarray(1.003), np.ones(3) * 1.001, np.full(2, 1e-17))),
             ((0.01, 0.02, 1e-3), (np.asarray(1.0), np.ones(3), np.ones(2)),
              (np.asarray(1.02), np.ones(3), np.ones(2))),
             ((0.3, 0.7, 1e-3), (np.asarray(1.0), np.ones(3), np.ones(2)),
              (np.asarray(1.0), np.ones(3), np.ones(2)))]
    traced = jax.jit(iteration_converged, static_argnums=2)
    for (step, rate, tol), var, prev in cases:
        host = iteration_converged(step, rate, tol, var, prev, var0)
        assert isinstance(host, (bool, np.bool_, np.ndarray))
        assert bool(host) == bool(traced(step, rate, tol, var, prev, var0))
    for args in [(1.0, 3.119, 0.08194, False), (0.02, 0.1, 0.5, True), (1.0, 0.0, 0.5, False)]:
        host = next_rate(*args)
        assert isinstance(host, np.ndarray)
        assert float(host) == float(jax.jit(next_rate)(*args))
        assert float(remaining_error(0.08, host)) == float(jax.jit(remaining_error)(0.08, host))
