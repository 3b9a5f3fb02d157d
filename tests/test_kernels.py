"""Tests of the ARD squared-exponential kernel and the state-action features
(design: docs/design.md#gp-model)."""

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.test_util import check_grads  # noqa: E402

from gpguided_jax import kernels  # noqa: E402


def _numpy_se(x1, x2, ls, sf2):
    return sf2 * np.exp(-0.5 * np.sum(((x1 - x2) / ls) ** 2))


def test_se_ard_matches_formula():
    rng = np.random.default_rng(0)
    ls = np.array([0.5, 1.0, 2.0])
    hyper = kernels.make_kernel_params(ls, 1.7, 0.1)
    for _ in range(5):
        x1, x2 = rng.normal(size=3), rng.normal(size=3)
        np.testing.assert_allclose(
            kernels.se_ard(jnp.array(x1), jnp.array(x2), hyper), _numpy_se(x1, x2, ls, 1.7),
            rtol=1e-12,
        )
    x = jnp.array(rng.normal(size=3))
    np.testing.assert_allclose(kernels.se_ard(x, x, hyper), 1.7, rtol=1e-14)
    np.testing.assert_allclose(kernels.kernel_diag(x, hyper), 1.7, rtol=1e-14)


def test_gram_symmetric_psd_and_consistent():
    rng = np.random.default_rng(1)
    xs = rng.normal(size=(20, 4))
    hyper = kernels.make_kernel_params([0.7, 1.1, 1.3, 2.0], 2.0, 0.1)
    K = np.asarray(kernels.gram(jnp.array(xs), jnp.array(xs), hyper))
    expected = np.array([[_numpy_se(a, b, hyper.lengthscales, 2.0) for b in xs] for a in xs])
    np.testing.assert_allclose(K, expected, rtol=1e-12)
    np.testing.assert_allclose(K, K.T, rtol=0, atol=0)
    assert np.linalg.eigvalsh(K).min() > -1e-10
    kvec = kernels.cross_covariance(jnp.array(xs), jnp.array(xs[3]), hyper)
    np.testing.assert_allclose(kvec, K[:, 3], rtol=1e-12)
    K2 = kernels.gram(jnp.array(xs[:5]), jnp.array(xs[5:12]), hyper)
    assert K2.shape == (5, 7)


def test_gradients_including_zero_distance():
    hyper = kernels.make_kernel_params([0.7, 1.3], 1.5, 0.1)
    x1 = jnp.array([0.3, -0.2])
    check_grads(lambda a: kernels.se_ard(a, x1, hyper), (x1,), order=2, modes=("fwd", "rev"))
    check_grads(
        lambda a: kernels.se_ard(a, x1, hyper), (x1 + 0.4,), order=2, modes=("fwd", "rev")
    )


def test_state_action_features_and_transforms():
    s = jnp.array([np.pi / 3, -1.5])
    x = kernels.state_action_features(s, 2.0)
    np.testing.assert_allclose(x, [np.sin(np.pi / 3), np.cos(np.pi / 3), -1.5, 2.0], rtol=1e-14)
    # Periodic in the angle.
    x2 = kernels.state_action_features(s + jnp.array([2 * np.pi, 0.0]), 2.0)
    np.testing.assert_allclose(x, x2, atol=1e-12)
    states = jnp.array(np.random.default_rng(0).normal(size=(6, 2)))
    actions = jnp.arange(6.0)
    batched = jax.vmap(kernels.state_action_features)(states, actions)
    jitted = jax.jit(jax.vmap(kernels.state_action_features))(states, actions)
    np.testing.assert_allclose(batched, jitted, rtol=1e-14)
    assert batched.shape == (6, 4)
