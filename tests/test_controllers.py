"""Tests for gpguided_jax.controllers: hand-derived dc/dtheta against autodiff, squashing,
periodicity, jit/vmap."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.flatten_util import ravel_pytree
from jax.test_util import check_grads

import gpguided_jax
from gpguided_jax import controllers

gpguided_jax.enable_x64()

requires_x64 = pytest.mark.skipif(not jax.config.jax_enable_x64, reason="needs float64")

CONTROLLER_NAMES = ("linear", "rbf")
_CONTROLLERS = {name: controllers.make_controller(name) for name in CONTROLLER_NAMES}


def _random_params(controller, key, log_scale):
    zeros = controller.init(jnp.float64)
    flat, unravel = ravel_pytree(zeros)
    return unravel(jnp.exp(log_scale) * jax.random.normal(key, flat.shape, flat.dtype))


def _make_relative_error(controller):
    @jax.jit
    def relative_error(key, log_scale, state):
        params = _random_params(controller, key, log_scale)
        value, grad = controller.value_and_grad(params, state)
        auto_value, auto_grad = jax.value_and_grad(controller.apply)(params, state)
        hand, auto = ravel_pytree(grad)[0], ravel_pytree(auto_grad)[0]
        scale = jnp.maximum(jnp.max(jnp.abs(auto)), 1e-300)
        return jnp.max(jnp.abs(hand - auto)) / scale, jnp.abs(value - auto_value)

    return relative_error


_RELATIVE_ERROR = {name: _make_relative_error(c) for name, c in _CONTROLLERS.items()}


@requires_x64
@pytest.mark.parametrize("name", CONTROLLER_NAMES)
@settings(max_examples=30, deadline=None, derandomize=True)
@given(
    seed=st.integers(0, 2**31 - 1),
    log_scale=st.floats(-7.0, 4.0),  # up to |z| ~ 100: c at the torque limit
    phi=st.floats(-10.0, 10.0),
    omega=st.floats(-15.0, 15.0),
)
def test_value_and_grad_matches_autodiff(name, seed, log_scale, phi, omega):
    rel, value_err = _RELATIVE_ERROR[name](
        jax.random.PRNGKey(seed), jnp.float64(log_scale), jnp.array([phi, omega])
    )
    assert float(rel) <= 1e-8
    assert float(value_err) == 0.0


@pytest.mark.parametrize("name", CONTROLLER_NAMES)
def test_saturated_controller_at_torque_limit(name):
    controller = _CONTROLLERS[name]
    params = jax.tree_util.tree_map(lambda x: x + 50.0, controller.init(jnp.float64))
    state = jnp.array([0.0, 0.0])
    value, grad = controller.value_and_grad(params, state)
    auto = jax.grad(controller.apply)(params, state)
    assert float(value) == pytest.approx(controller.u_max)
    np.testing.assert_allclose(ravel_pytree(grad)[0], ravel_pytree(auto)[0], rtol=1e-8, atol=0)


@pytest.mark.parametrize("name", CONTROLLER_NAMES)
def test_check_grads(name):
    controller = _CONTROLLERS[name]
    params = _random_params(controller, jax.random.PRNGKey(0), jnp.log(0.5))
    state = jnp.array([2.0, -1.0])
    check_grads(lambda p: controller.apply(p, state), (params,), order=2, modes=("fwd", "rev"))


@pytest.mark.parametrize("name", CONTROLLER_NAMES)
def test_init_is_deterministic_zero_and_output_bounded(name):
    controller = _CONTROLLERS[name]
    p1, p2 = controller.init(), controller.init()
    assert jax.tree_util.tree_structure(p1) == jax.tree_util.tree_structure(p2)
    assert all(float(jnp.max(jnp.abs(leaf))) == 0.0 for leaf in jax.tree_util.tree_leaves(p1))
    states = jax.random.uniform(jax.random.PRNGKey(1), (64, 2), minval=-20.0, maxval=20.0)
    assert float(jnp.max(jnp.abs(jax.vmap(controller.apply, (None, 0))(p1, states)))) == 0.0
    big = _random_params(controller, jax.random.PRNGKey(2), jnp.log(100.0))
    values = jax.vmap(controller.apply, (None, 0))(big, states)
    assert float(jnp.max(jnp.abs(values))) <= controller.u_max


@pytest.mark.parametrize("name", CONTROLLER_NAMES)
def test_periodic_in_angle(name):
    controller = _CONTROLLERS[name]
    params = _random_params(controller, jax.random.PRNGKey(3), 0.0)
    s = jnp.array([0.3, 1.2])
    shifted = s.at[0].add(2.0 * jnp.pi)
    np.testing.assert_allclose(
        controller.apply(params, s), controller.apply(params, shifted), rtol=1e-12
    )


@pytest.mark.parametrize("name", CONTROLLER_NAMES)
def test_jit_and_vmap(name):
    controller = _CONTROLLERS[name]
    params = _random_params(controller, jax.random.PRNGKey(4), jnp.log(0.7))
    states = jax.random.normal(jax.random.PRNGKey(5), (7, 2)) * 3.0
    values, grads = jax.jit(jax.vmap(controller.value_and_grad, (None, 0)))(params, states)
    assert values.shape == (7,)
    for i in range(7):
        v, g = controller.value_and_grad(params, states[i])
        np.testing.assert_allclose(values[i], v, rtol=1e-12)
        np.testing.assert_allclose(
            ravel_pytree(jax.tree_util.tree_map(lambda x, i=i: x[i], grads))[0],
            ravel_pytree(g)[0],
            rtol=1e-12,
            atol=1e-300,
        )


def test_rbf_grid_and_features():
    controller = controllers.rbf_controller(num_angles=4, num_velocities=3, max_velocity=2.0)
    centres = controllers.rbf_grid(4, 3, 2.0)
    assert centres.shape == (12, 2)
    params = controller.init()
    assert params.weights.shape == (12,) and params.bias.shape == ()
    # At a centre its basis function is 1.
    psi = controller.features(jnp.asarray(centres[5]))
    assert float(psi.weights[5]) == pytest.approx(1.0)
    assert float(psi.bias) == 1.0
    with pytest.raises(ValueError):
        controllers.make_controller("nope")
