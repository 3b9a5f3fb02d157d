"""Tests for gpguided_jax.pendulum against hand computations and scipy's ODE solver."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from gpguided_jax import pendulum as P


def _free_flight(s0, params, num_steps, torque=0.0):
    def body(s, _):
        y = P.integrate(s, jnp.asarray(torque, s.dtype), params)
        return y, y

    return jax.lax.scan(body, s0, None, length=num_steps)[1]


_free_flight_jit = jax.jit(_free_flight, static_argnums=2)

START_STATES = [(0.5, 0.0), (3.0, 0.0), (0.0, 6.0), (1.0, 6.5), (2.0, -4.0)]


def test_energy_drift_rk4_is_below_bound_and_scales_as_h4():
    """Zero torque, no friction, 10 s: |H(t) - H(0)| < 1e-7 J.

    RK4 is not symplectic: its global error, energy included, grows like T * C * h^4. With
    h = 5e-3 (h^4 = 6.3e-10), T = 10 s and the fastest start here (|omega| up to 6.5 rad/s, beyond
    the separatrix 2*sqrt(g/l) = 6.26 rad/s, i.e. full rotations), the measured
    drift is ~1.5e-8 J; 1e-7 J leaves a margin of ~7x while still being 8 orders of magnitude
    below the energies involved (~10 J). Halving h must cut the drift by ~16x (order 4); we
    require > 8x.
    """
    p1 = P.make_params(reward_noise_std=0.0)
    p2 = P.make_params(reward_noise_std=0.0, substeps=2)
    steps = int(round(10.0 / 0.005))
    for s in START_STATES:
        s0 = jnp.array(s)
        e0 = P.energy(s0, p1)
        drift1 = float(jnp.max(jnp.abs(P.energy(_free_flight_jit(s0, p1, steps), p1) - e0)))
        drift2 = float(jnp.max(jnp.abs(P.energy(_free_flight_jit(s0, p2, steps), p2) - e0)))
        assert drift1 < 1e-7, (s, drift1)
        if drift1 > 1e-9:  # below this, round-off dominates and the ratio means nothing
            assert drift1 / drift2 > 8.0, (s, drift1, drift2)


@pytest.mark.parametrize("seed", range(6))
def test_matches_scipy_solve_ivp_after_one_second(seed):
    """Random state, torque (some beyond the limit) and friction vs DOP853 at rtol 1e-10.

    Tolerance 1e-7 on phi and omega after 1 s (200 RK4 steps): RK4's global error is
    O(h^4) ~ 1e-9 here (measured 0.4e-9 to 3e-9).
    """
    rng = np.random.default_rng(seed)
    s0 = np.array([rng.uniform(0, 2 * np.pi), rng.uniform(-6, 6)])
    u = rng.uniform(-8, 8)
    b = rng.uniform(0, 0.5)
    m, l = rng.uniform(0.5, 2.0), rng.uniform(0.5, 2.0)
    p = P.make_params(reward_noise_std=0.0, friction=b, mass=m, length=l)
    y = _free_flight_jit(jnp.array(s0), p, 200, float(np.clip(u, -5, 5)))[-1]
    uc = float(np.clip(u, -5, 5))

    def f(t, y):
        return [y[1], (uc - b * y[1] - m * 9.81 * l * np.sin(y[0])) / (m * l * l)]

    sol = solve_ivp(f, (0.0, 1.0), s0, rtol=1e-10, atol=1e-12, method="DOP853")
    np.testing.assert_allclose(np.asarray(y), sol.y[:, -1], atol=1e-7, rtol=0)


def test_step_clips_torque():
    p = P.make_params(reward_noise_std=0.0)
    s = jnp.array([1.0, 0.3])
    key = jax.random.key(0)
    s_big, _ = P.step(key, s, 100.0, p)
    s_lim, _ = P.step(key, s, 5.0, p)
    s_neg, _ = P.step(key, s, -100.0, p)
    s_nlim, _ = P.step(key, s, -5.0, p)
    np.testing.assert_array_equal(s_big, s_lim)
    np.testing.assert_array_equal(s_neg, s_nlim)
    s_in, _ = P.step(key, s, 4.0, p)
    assert not np.allclose(s_in, s_lim)


def test_angle_wrapping():
    np.testing.assert_allclose(P.wrap_angle(jnp.array(-0.1)), 2 * math.pi - 0.1, rtol=1e-12)
    np.testing.assert_allclose(P.wrap_angle(jnp.array(7.0)), 7.0 - 2 * math.pi, rtol=1e-12)
    assert float(P.wrap_angle(jnp.array(-1e-300))) < 2 * math.pi
    assert float(P.wrap_angle(jnp.array(-1e-9, jnp.float32))) < 2 * math.pi
    # a fast pendulum that crosses phi = 0 downward and 2*pi upward stays in [0, 2*pi)
    p = P.make_params(reward_noise_std=0.0)
    step = jax.jit(P.step)  # op by op, each of the 80 steps would dispatch every operation anew
    for s0 in ([0.01, -6.0], [6.27, 6.0]):
        s = jnp.array(s0)
        for _ in range(40):
            s, _ = step(jax.random.key(0), s, 0.0, p)
            assert 0.0 <= float(s[0]) < 2 * math.pi


@pytest.mark.parametrize(
    "state,expected",
    [
        ((math.pi, 0.0), 0.0),  # upright at rest: the maximum
        ((0.0, 0.0), -(math.pi**2)),  # hanging at rest
        ((math.pi + 1.0, 2.0), -1.0 - 0.25),
        ((math.pi - 0.5, -4.0), -0.25 - 1.0),
    ],
)
def test_reward_at_hand_computed_states(state, expected):
    np.testing.assert_allclose(P.reward_mean(jnp.array(state)), expected, rtol=1e-12, atol=1e-14)


def test_step_reward_is_taken_on_the_next_state():
    p = P.make_params(reward_noise_std=0.0)
    s = jnp.array([2.0, 1.0])
    s_next, r = P.step(jax.random.key(3), s, 2.0, p)
    np.testing.assert_allclose(r, P.reward_mean(s_next), rtol=1e-14)


def test_reward_noise_statistics():
    sigma = 0.7
    p = P.make_params(reward_noise_std=sigma)
    s = jnp.array([2.0, 1.0])
    keys = jax.random.split(jax.random.key(11), 20000)
    s_next, r = jax.vmap(P.step, in_axes=(0, None, None, None))(keys, s, 1.0, p)
    noise = np.asarray(r - P.reward_mean(s_next[0]))
    n = noise.size
    # mean within 4 standard errors; sample variance within 4 s.e. (s.e. of s^2 is sigma^2*sqrt(2/n))
    assert abs(noise.mean()) < 4 * sigma / math.sqrt(n)
    assert abs(noise.var() - sigma**2) < 4 * sigma**2 * math.sqrt(2 / n)
    # zero noise std: deterministic
    p0 = P.make_params(reward_noise_std=0.0)
    _, r0 = jax.vmap(P.step, in_axes=(0, None, None, None))(keys[:10], s, 1.0, p0)
    assert np.all(np.asarray(r0) == np.asarray(r0[0]))


def test_start_state_distribution():
    p = P.make_params(start_mean=(math.pi, 0.5), start_std=(0.2, 0.3))
    states = jax.vmap(P.reset, in_axes=(0, None))(jax.random.split(jax.random.key(0), 20000), p)
    s = np.asarray(states)
    assert np.all((s[:, 0] >= 0) & (s[:, 0] < 2 * math.pi))
    np.testing.assert_allclose(s.mean(0), [math.pi, 0.5], atol=0.02)
    np.testing.assert_allclose(s.std(0), [0.2, 0.3], rtol=0.03)


def _policy(key, s):
    return 3.0 * jnp.sin(s[0]) - 0.5 * s[1] + jax.random.normal(key)


@pytest.mark.slow
def test_jit_vmap_and_plain_agree_and_are_reproducible():
    p = P.make_params(reward_noise_std=0.2)
    key = jax.random.key(42)
    plain = P.rollout(key, p, _policy, 30)
    jitted = jax.jit(P.rollout, static_argnums=(2, 3))(key, p, _policy, 30)
    again = jax.jit(P.rollout, static_argnums=(2, 3))(key, p, _policy, 30)
    keys = jnp.stack([key, jax.random.key(7)])
    batched = P.batch_rollout(keys, p, _policy, 30)
    for a, b in zip(plain, jitted):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    for a, b in zip(jitted, again):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(plain, batched):
        np.testing.assert_allclose(a, b[0], rtol=1e-12, atol=1e-12)
    assert not np.allclose(batched.states[0], batched.states[1])


def test_params_vmap_over_physics():
    masses = jnp.array([1.0, 2.0])
    p = P.make_params()
    ps = jax.vmap(lambda m: P.PendulumParams(**{**p.__dict__, "mass": m}))(masses)
    out = jax.vmap(P.step, in_axes=(None, None, None, 0))(
        jax.random.key(0), jnp.array([1.0, 0.0]), 2.0, ps
    )[0]
    # with a torque the mass matters (zero torque would not show it)
    assert not np.allclose(out[0], out[1])


@pytest.mark.parametrize(
    "field,value",
    [
        ("mass", -1.0),
        ("mass", 0.0),
        ("length", 0.0),
        ("dt", -0.005),
        ("dt", 0.0),
        ("max_torque", 0.0),
        ("gravity", float("nan")),
        ("friction", float("inf")),
        ("reward_noise_std", -0.1),
        ("start_std", (0.1, -0.1)),
        ("start_mean", (float("nan"), 0.0)),
        ("substeps", 0),
        ("substeps", 1.5),
    ],
)
def test_bad_params_are_refused_naming_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        P.make_params(**{field: value})


def test_unknown_field_is_refused():
    with pytest.raises(TypeError, match="masss"):
        P.make_params(masss=1.0)
