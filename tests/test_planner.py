"""gp_mpc's planner (`gpguided_jax.model_based.planner`): its sequence optimisers' first action on a
linear system with a quadratic cost against the LQR action of scipy's Riccati solver, within the
sampling error their sample counts and iterations give; the planner acting through brax's own
dynamics of its inverted pendulum (a known model) for a whole episode; and gp_mpc trained end to
end through the registry and the command line."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from gpguided_jax import config as C
from gpguided_jax import methods, rollouts
from gpguided_jax import model_based as MB
from gpguided_jax import train as T
from gpguided_jax.model_based import planner as P

# x' = a x + b u, cost sum_{t<T} q x_t^2 + r u_t^2 (no terminal cost), from x0
LQR = dict(a=1.0, b=0.5, q=1.0, r=0.1, x0=1.0, horizon=8)
SEEDS = 32


def _quadratic_form(horizon):
    """The cost as a quadratic in the (T,) actions: J(u) = J* + (u - u*)^T H (u - u*), from the
    roll-out matrix G (x_t = a^t x0 + sum_{s<t} a^(t-1-s) b u_s). Returns (H, u*)."""
    a, b, q, r, x0 = (LQR[k] for k in ("a", "b", "q", "r", "x0"))
    g = np.array([[a ** (t - 1 - s) * b if s < t else 0.0 for s in range(horizon)]
                  for t in range(horizon)])
    free = np.array([a ** t * x0 for t in range(horizon)])
    h = q * g.T @ g + r * np.eye(horizon)
    return h, -np.linalg.solve(h, q * g.T @ free)


def _lqr_first_action():
    """The LQR action -K x0 of scipy's discrete Riccati solver (infinite horizon), and the
    finite-horizon one of the backward Riccati recursion over `horizon` steps (P_T = 0)."""
    a, b, q, r, x0 = (np.array([[LQR[k]]]) for k in ("a", "b", "q", "r", "x0"))
    p = scipy.linalg.solve_discrete_are(a, b, q, r)
    k_inf = np.linalg.solve(r + b.T @ p @ b, b.T @ p @ a)
    p_t = np.zeros((1, 1))
    for _ in range(LQR["horizon"]):
        k_t = np.linalg.solve(r + b.T @ p_t @ b, b.T @ p_t @ a)
        p_t = q + a.T @ p_t @ (a - b @ k_t)
    return float(-(k_inf @ x0)[0, 0]), float(-(k_t @ x0)[0, 0])


def _returns(actions):
    """-J(u) of the exact linear model, in JAX."""
    a, b, q, r = (LQR[k] for k in ("a", "b", "q", "r"))

    def step(x, u):
        return a * x + b * u, -(q * x ** 2 + r * u ** 2)

    return jnp.sum(jax.lax.scan(step, jnp.asarray(LQR["x0"], actions.dtype), actions)[1])


def _mppi_prediction(h, u_star, mean, std, temperature, samples, iterations):
    """MPPI's first action after `iterations` updates from `mean` on R = -(J* + (u - u*)^T H (u -
    u*)): (its expectation, its standard deviation), in NumPy.

    One update's weighed mean over infinitely many samples is the mean of N(mean, std^2 I) times
    exp(R / lambda), a Gaussian: u* + M (mean - u*), M = (I + 2 std^2 H / lambda)^-1. With N
    samples it is a self-normalised importance-sampling estimate, whose covariance is to first
    order (rho / N) (S2 + (m2 - m)(m2 - m)^T): rho = E[w^2] / E[w]^2 (w = exp(R / lambda) under
    the sampling Gaussian, in closed form) and N(m2, S2) the sampling Gaussian times w^2. The
    estimates' errors go through the next updates' contraction M."""
    n = len(u_star)
    eye = np.eye(n)
    contraction = np.linalg.inv(eye + 2 * std ** 2 * h / temperature)

    def log_mean_weight(beta, d):  # log E exp(-beta (u - u*)^T H (u - u*)), u ~ N(u* + d, std^2)
        a = eye + 2 * beta * std ** 2 * h
        return -0.5 * np.linalg.slogdet(a)[1] - beta * d @ h @ np.linalg.solve(a, d)

    cov = np.zeros((n, n))
    for _ in range(iterations):
        d = mean - u_star
        m = u_star + contraction @ d
        s2 = np.linalg.inv(eye / std ** 2 + 4 * h / temperature)
        m2 = s2 @ (mean / std ** 2 + 4 * h @ u_star / temperature)
        rho = np.exp(log_mean_weight(2 / temperature, d) - 2 * log_mean_weight(1 / temperature, d))
        assert samples / rho > 50, "too few effective samples for the first-order variance"
        cov = contraction @ cov @ contraction.T + rho / samples * (s2 + np.outer(m2 - m, m2 - m))
        mean = m
    return mean[0], np.sqrt(cov[0, 0])


def _plan(planner, keys, std, **kw):
    """The sequence optimiser `planner` from the zero sequence, one plan per key (jit, vmap)."""
    n = LQR["horizon"]
    optimiser = P.SEQUENCE_OPTIMISERS[planner]
    run = jax.jit(jax.vmap(lambda k: optimiser.run(
        k, _returns, jnp.zeros((n,)), jnp.full((n,), std), jnp.zeros((0, n)), low=-20.0,
        high=20.0, **kw)))
    return run(keys)


def test_the_planners_first_action_is_the_lqr_action_within_their_sampling_error():
    """x' = x + 0.5 u, cost x^2 + 0.1 u^2 over 8 decisions from x0 = 1, planned from the zero
    sequence with the exact model (no clipping: the bound is 20), 32 seeds under jit and vmap.
    The reference is -K x0 of scipy's Riccati solver; the finite horizon's first action (the
    backward recursion) is within 1e-8 of it (the closed loop's pole, 0.23, to the 16th power).

    MPPI (4,000 samples, lambda 0.3, std 0.5, 20 iterations): its first action's expectation and
    standard deviation follow from the Gaussian-quadratic algebra (`_mppi_prediction`): a bias of
    9e-4 and 0.012 per seed; the seeds' mean is within the bias and 4 standard errors of the LQR
    action (0.009, 0.6%), and the seeds' spread is not above 1.5 times the predicted one (the
    chi-square's 99.99% quantile with 31 degrees of freedom: 1.47).

    CEM (1,000 samples, 100 elites, 10 iterations, std 1) has no such closed form; its answer is
    good to its final sampling spread: each seed's first action is within 3 of its final standard
    deviations of the LQR action, and those are below 5% of it. (An isotropic cost would shrink
    the elites' std by about 0.57 an iteration, the tenth quantile of a chi-square with 8 degrees
    of freedom; this cost's unequal curvatures leave the first action's at 0.01-0.02 after 10.)"""
    k_inf, k_finite = _lqr_first_action()
    assert abs(k_finite - k_inf) < 1e-8
    h, u_star = _quadratic_form(LQR["horizon"])
    assert u_star[0] == pytest.approx(k_finite, abs=1e-10)  # the same problem, two ways
    keys = jax.random.split(jax.random.key(0), SEEDS)

    kw = dict(samples=4000, iterations=20, temperature=0.3, std=0.5)
    expected, sd = _mppi_prediction(h, u_star, np.zeros(LQR["horizon"]), kw["std"],
                                    kw["temperature"], kw["samples"], kw["iterations"])
    first = np.asarray(_plan("mppi", keys, elites=1, **kw).actions[:, 0])
    bias = abs(expected - k_inf)
    assert abs(first.mean() - k_inf) <= bias + 4 * sd / np.sqrt(SEEDS), (first.mean(), k_inf, sd)
    assert first.std(ddof=1) <= 1.5 * sd, (first.std(ddof=1), sd)

    planned = _plan("cem", keys, samples=1000, elites=100, iterations=10, temperature=1.0,
                    std=1.0)
    first, spread = np.asarray(planned.actions[:, 0]), np.asarray(planned.std[:, 0])
    assert np.all(spread < 0.05 * abs(k_inf)), spread
    assert np.all(np.abs(first - k_inf) <= 3 * spread), (first - k_inf, spread)


# ------------------------------------------------------------------------------------------------
# The policy's memory, the settings.
# ------------------------------------------------------------------------------------------------


def _counting_policy(policy):
    """`policy` whose memory counts its decisions and whose action is the count."""
    def act(key, theta, state, ctx, m):
        del key, ctx
        action, aux = m.astype(state.dtype), policy.sample(jax.random.key(0), theta, state,
                                                           None)[1]
        return action, aux, jax.tree_util.tree_map(jnp.zeros_like, theta), jnp.ones(()), m + 1

    return policy._replace(act=act, memory=lambda theta, ctx: jnp.zeros((), jnp.int32))


@pytest.mark.parametrize("hold_time", [0.0, 0.03])
def test_a_policy_s_memory_goes_from_one_decision_to_the_next(hold_time):
    """The roll-outs carry a policy's memory (`Policy.memory`) through an episode: a policy whose
    memory counts its decisions acts 0, 1, 2, ... (each held `prog.hold` steps)."""
    cfg = C.preset("tiny", method="gp_mpc", hold_time=hold_time)
    prog = rollouts.make_program(cfg)
    policy = _counting_policy(prog.behaviour)
    theta = T.initial_theta(prog, cfg)
    ep = jax.jit(lambda k: rollouts.rollout(prog, k, theta, None, policy, cfg))(jax.random.key(0))
    expected = np.repeat(np.arange(cfg.episode_length), prog.hold)[:cfg.episode_length]
    assert prog.policy.memory is not None
    assert prog.hold == max(1, round(hold_time / C.control_interval(cfg)))
    assert (prog.hold > 1) == (hold_time > 0)
    np.testing.assert_array_equal(np.asarray(ep.actions), expected)


def test_gp_mpc_s_settings_extend_gp_model_s_by_their_flat_names():
    """gp_mpc's settings are gp_model's (by their `model_` names) and the planner's (`mpc_`):
    their defaults, overrides, checks and static/traced split; gp_model's config ignores the
    planner's quietly; `planner_steps` converts the horizon's seconds to decisions."""
    cfg = C.make_config(method="gp_mpc", mpc_samples=16, mpc_horizon=0.3, model_horizon=1.0,
                        mpc_temperature=0.2)
    own = cfg.settings
    assert isinstance(own, P.PlannerSettings) and isinstance(own, MB.ModelSettings)
    assert (own.samples, own.plan_horizon, own.horizon, own.elites) == (16, 0.3, 1.0, 8)
    assert cfg.static_dict()["mpc_samples"] == 16 and cfg.to_json_dict()["mpc_temperature"] == 0.2
    assert methods.setting_owners()["model_horizon"] == ("gp_model", "gp_mpc")
    assert methods.setting_owners()["mpc_samples"] == ("gp_mpc",)
    traced = jax.tree_util.tree_leaves(own)
    # gp_model's traced settings and the planner's two
    assert len(traced) == len(P.PlannerSettings.TRACED) == len(MB.ModelSettings.TRACED) + 2
    assert type(C.make_config(method="gp_model", mpc_samples=16).settings) is MB.ModelSettings
    prog = rollouts.make_program(cfg)
    dt = C.control_interval(cfg)
    assert MB.planner_steps(prog, cfg) == round(0.3 / dt)
    assert prog.policy.name == P.POLICY and prog.policy.memory is not None
    for bad, match in ((dict(mpc_elites=17), "mpc_elites: must be at most mpc_samples"),
                       (dict(mpc_planner="random"), "mpc_planner: unknown planner"),
                       (dict(mpc_horizon=0.0), "mpc_horizon: must be > 0"),
                       (dict(mpc_noise_exponent=4.0), "mpc_noise_exponent: must be in"),
                       (dict(mpc_temperature=-1.0), "mpc_temperature: must be > 0"),
                       (dict(model_particles=0), "model_particles: must be a positive")):
        with pytest.raises(ValueError, match=match):
            C.make_config(method="gp_mpc", mpc_samples=16, **bad)
    with pytest.raises(ValueError, match="gp_mpc takes 'white' only"):
        C.make_config(method="gp_mpc", exploration="ou")


# ------------------------------------------------------------------------------------------------
# brax's inverted pendulum with its own dynamics as the known model.
# ------------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_the_planner_through_brax_s_own_dynamics_keeps_the_pole_up_for_a_whole_episode():
    """The planner with a known model: brax's own pipeline step as `model_step`, on its inverted
    pendulum, planning with the saturating objective on the task's target (the tip upright over
    the rail's centre) from an untrained linear controller. It keeps the pole up for the whole
    1,000-step episode (the pole never past the task's end of 0.2 rad, the cart off the rail's
    end); the same policy before its model is ready acts with the controller alone and loses the
    pole within a few dozen steps, so the planner is what holds it."""
    from brax import envs

    cfg = C.make_config(env="brax:inverted_pendulum", method="gp_mpc", controller="linear",
                        episode_length=1000, num_updates=1, episodes_per_update=1, min_std=0.05,
                        model_reward="saturating", mpc_samples=16, mpc_iterations=2,
                        mpc_elites=4, mpc_horizon=0.5)
    prog = rollouts.make_program(cfg)
    env = envs.get_environment("inverted_pendulum")
    low, high = (float(v) for v in np.asarray(env.sys.actuator.ctrl_range[0]))

    def true_step(prog, ctx, obs, action):  # the task's action in [-1, 1] to brax's control
        u = (jnp.clip(action, -1.0, 1.0) + 1.0) * (high - low) * 0.5 + low
        state = env.pipeline_step(env.pipeline_init(obs[:2], obs[2:]), jnp.reshape(u, (1,)))
        nxt = jnp.concatenate([state.q, state.qd]).astype(obs.dtype)
        return nxt, MB.targets_of(prog.task, obs, nxt)

    policy = P.make_policy(prog, true_step)
    own = cfg.settings
    theta = T.initial_theta(prog, cfg)._replace(log_std=jnp.log(jnp.asarray(0.05, cfg.dtype)))
    episodes = {}
    for ready in (True, False):
        ctx = P.PlannerContext(None, None, jnp.asarray(ready), own.temperature, own.init_std,
                               own.end_softness)
        run = jax.jit(lambda k, ctx=ctx: rollouts.rollout(prog._replace(policy=policy), k, theta,
                                                          ctx, policy, cfg))
        episodes[ready] = run(jax.random.key(3))
    planned, alone = episodes[True], episodes[False]
    assert int(planned.alive.sum()) == cfg.episode_length
    assert float(jnp.max(jnp.abs(planned.next_states[:, 1]))) < 0.2
    assert float(jnp.max(jnp.abs(planned.next_states[:, 0]))) < 0.95
    assert int(alone.alive.sum()) < 100


# ------------------------------------------------------------------------------------------------
# End to end.
# ------------------------------------------------------------------------------------------------

TINY = dict(num_updates=3, model_inducing=8, model_steps=2, model_particles=2,
            model_horizon=0.05, model_fit_steps=5, mpc_samples=8, mpc_elites=2,
            mpc_iterations=2, mpc_horizon=0.05)


@pytest.mark.training
def test_gp_mpc_trains_end_to_end_through_the_registry_and_the_command_line(tmp_path):
    """The tiny preset's gp_mpc, 2 seeds under jit and vmap, CEM and MPPI: finite records, the
    model's data growing by the update's decisions (it takes data in once per update) and its
    episodes acting otherwise than gp_model's from the second update on (the first acts with the
    controller and the same draws as gp_model's: the same records, to rounding). Then `gpguided
    reproduce --methods gp_mpc` with the planner's settings given by --set."""
    from gpguided_jax import cli

    keys = jax.random.split(jax.random.key(0), 2)
    runs = {}
    for name, extra in (("gp_model", {}), ("cem", {}), ("mppi", dict(mpc_planner="mppi"))):
        cfg = C.preset("tiny", method="gp_model" if name == "gp_model" else "gp_mpc",
                       **TINY, **extra)
        runs[name] = jax.jit(jax.vmap(T.make_train(cfg)))(keys)[1]
    decisions = cfg.episodes_per_update * cfg.episode_length
    for name in ("cem", "mppi"):
        rec = runs[name]
        for f in rec._fields:
            assert np.all(np.isfinite(np.asarray(getattr(rec, f)))), (name, f)
        np.testing.assert_array_equal(np.asarray(rec.model_data),
                                      np.tile(decisions * np.arange(1, 4), (2, 1)))
        for f in ("mean_return", "model_error", "model_return"):  # compiled apart: to rounding
            np.testing.assert_allclose(getattr(rec, f)[:, 0], getattr(runs["gp_model"], f)[:, 0],
                                       rtol=1e-9)
        assert np.all(rec.mean_return[:, 1:] != runs["gp_model"].mean_return[:, 1:])

    out = tmp_path / "cli"
    sets = [f"{k}={v}" for k, v in TINY.items() if k != "num_updates"]
    assert cli.main(["reproduce", "--preset", "tiny", "--seeds", "1", "--methods", "gp_mpc",
                     "--out", str(out), "--set", "num_updates=2", *sets]) == 0
    import json

    with open(out / "config.json") as f:
        run = json.load(f)["methods"]["gp_mpc"]
    assert run["mpc_samples"] == 8 and run["mpc_horizon"] == 0.05 and run["model_inducing"] == 8
    with np.load(out / "results.npz") as f:
        assert list(f["methods"]) == ["gp_mpc"]
        assert np.all(np.isfinite(f["mean_return"])) and np.all(np.isfinite(f["model_error"]))
