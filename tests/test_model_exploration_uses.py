"""gp_model's uses of the model's uncertainty where the reward must be found (docs/design.md#model),
each against an independent reference: the learnt reward's epistemic standard deviation (its
upper confidence bound, 'optimistic_reward') against an exact GP by Cholesky in NumPy; the
information bonus ('information') against Monte Carlo over functions drawn from the posterior;
the roll-out's sums of both against a NumPy roll-out of the exact GP's mean; optimism finding a
bandit's maximum that the mean model misses; the sparse swing-up's reward against H-UCRL's
formula in NumPy; and the refusal of reward optimism where the reward is not learnt."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gpguided_jax import cli, kernels, rollouts, tasks
from gpguided_jax import config as C
from gpguided_jax import controllers as controllers_lib
from gpguided_jax import model_based as MB
from gpguided_jax import train as T
from gpguided_jax.model_based import uncertainty as U

# two outputs, the dynamics' and the reward's, each its own kernel, on inputs (x1, x2, a)
KERNS = (dict(ls=[0.9, 1.3, 0.7], sf2=1.7, sn2=0.05), dict(ls=[1.1, 0.6, 0.8], sf2=0.6, sn2=0.02))
# the largest error allowed on a latent variance, relative to the signal variance (the exact-GP
# test of test_model_based.py: float32 resolves the variance to about 1e-2 of sigma_f^2)
VAR_TOL = {"float64": 1e-7, "float32": 2e-2}


def _se(a, b, ls, sf2):
    d = (a[:, None, :] - b[None, :, :]) / np.asarray(ls)
    return sf2 * np.exp(-0.5 * np.sum(d * d, axis=-1))


def _stacked_kernels(kerns, dtype):
    ks = [kernels.make_kernel_params(k["ls"], k["sf2"], k["sn2"], dtype=dtype) for k in kerns]
    return jax.tree_util.tree_map(lambda *v: jnp.stack(v), *ks)


def _model(z, xs, ys, kerns, dtype, jitter):
    """The sparse model of every column of ys on inducing inputs z (z = xs: the exact GP)."""
    m = z.shape[0]
    cond = functools.partial(MB.condition, jitter=jitter)
    model = jax.jit(jax.vmap(cond, in_axes=(None, None, 0, None, 1, None)))(
        jnp.asarray(z, dtype), jnp.ones(m, bool), _stacked_kernels(kerns, dtype),
        jnp.asarray(xs, dtype), jnp.asarray(ys, dtype), jnp.ones(xs.shape[0], bool))
    return model._replace(inducing=jnp.asarray(z, dtype), inducing_mask=jnp.ones(m, bool))


def _exact(xs, ys, xt, k):
    """The exact GP's latent mean and variance at xt by Cholesky (float64 NumPy)."""
    chol = np.linalg.cholesky(_se(xs, xs, k["ls"], k["sf2"]) + k["sn2"] * np.eye(len(xs)))
    ks = _se(xt, xs, k["ls"], k["sf2"])
    v = np.linalg.solve(chol, ks.T)
    alpha = np.linalg.solve(chol.T, np.linalg.solve(chol, ys))
    return ks @ alpha, k["sf2"] - np.sum(v * v, axis=0)


def _data(rng, n):
    xs = rng.normal(size=(n, 3))
    ys = np.stack([np.sin(xs @ [0.7, -0.4, 1.0]), np.cos(xs @ [0.2, 0.9, -0.5])], 1)
    return xs, ys + 0.05 * rng.normal(size=ys.shape)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_the_reward_s_upper_confidence_bound_adds_beta_times_the_exact_gp_s_std(dtype):
    """With every input inducing the model is the exact GP: r + beta sigma_r
    (`optimistic_outputs` on `fast_variance`, under jit and vmap) raises the reward output by
    beta times the exact GP's latent standard deviation (NumPy, Cholesky, float64) and leaves the
    dynamics' output alone. sigma_r^2 agrees to `VAR_TOL` of sigma_f^2, so sigma_r to its square
    root (|sqrt a - sqrt b| <= sqrt |a - b|)."""
    rng = np.random.default_rng(0)
    xs, ys = _data(rng, 25)
    jitter = 1e-12 if dtype == "float64" else 1e-6
    model = _model(xs, xs, ys, KERNS, dtype, jitter)
    factors = MB.variance_factors(model)
    xt = np.concatenate([rng.normal(size=(6, 3)), xs[:2] + 0.01, 3.0 + rng.normal(size=(2, 3))])
    beta = 1.7

    @jax.jit
    @jax.vmap
    def bound(x):
        ks = MB.k_star(model, x)
        out = jnp.sum(ks * model.weights, axis=-1)
        var = MB.fast_variance(model, factors, ks)
        return out, U.optimistic_outputs(out, var, 1, jnp.asarray(beta, dtype)), var

    out, ucb, var = (np.asarray(v, np.float64) for v in bound(jnp.asarray(xt, dtype)))
    _, var_ref = _exact(xs, ys[:, 1], xt, KERNS[1])
    tol = VAR_TOL[dtype] * KERNS[1]["sf2"]
    np.testing.assert_allclose(var[:, 1], var_ref, rtol=0, atol=tol)
    np.testing.assert_allclose((ucb[:, 1] - out[:, 1]) / beta, np.sqrt(var_ref), rtol=0,
                               atol=np.sqrt(tol))
    np.testing.assert_array_equal(ucb[:, 0], out[:, 0])
    assert np.sqrt(var_ref).max() > 2 * np.sqrt(tol)  # the bound is resolved, not all noise


def test_the_epistemic_std_passes_a_finite_gradient_where_the_variance_is_zero():
    """sqrt of a variance clipped to 0 (a data point of a noiseless model) has the gradient 0, not
    inf times 0; elsewhere it is 1 / (2 sigma)."""
    grad = jax.grad(lambda v: U.epistemic_std(jnp.maximum(v, 0.0)))
    assert float(grad(jnp.asarray(0.0))) == 0.0 and float(grad(jnp.asarray(-1e-9))) == 0.0
    assert float(grad(jnp.asarray(0.25))) == pytest.approx(1.0)


@pytest.mark.slow
def test_the_information_bonus_is_the_variance_of_functions_drawn_from_the_posterior():
    """lambda sum_e sigma_e^2 over the dynamics' outputs (`information_bonus` on `fast_variance`,
    a sparse model, M = 8 < N = 60) against Monte Carlo: the sample variance of 40,000 functions
    drawn from the posterior (`sample_weights`), summed over the same outputs. A drawn function
    k(x, Z) w is the projected process's (its variance k Sigma k, the inducing values'
    posterior); the model's variance adds the prior's residual k(x, x) - k K_ZZ^-1 k (0 at an
    inducing input, sigma_f^2 far from them), added here from NumPy. Within 5 Monte-Carlo
    standard errors (a Gaussian sample variance's is v sqrt(2 / (S - 1)), 0.7% here), at three
    inducing inputs (where the draws alone are the reference) and two other inputs. A third
    output (a learnt reward, its variance large) does not enter the bonus."""
    rng = np.random.default_rng(1)
    xs, ys = _data(rng, 60)
    ys = np.concatenate([ys, 30.0 * rng.normal(size=(60, 1))], 1)  # the reward: noise, sf2 large
    kerns = KERNS + (dict(ls=[0.5, 0.5, 0.5], sf2=900.0, sn2=1.0),)
    z = xs[:8]
    model = _model(z, xs, ys, kerns, "float64", MB.JITTER)
    factors = MB.variance_factors(model)
    xt = np.concatenate([z[:3], rng.normal(size=(2, 3))])
    lam = 0.6
    var = np.asarray(jax.vmap(lambda x: MB.fast_variance(model, factors, MB.k_star(model, x)))(
        jnp.asarray(xt)))
    bonus = np.asarray(jax.vmap(lambda v: U.information_bonus(v, 2, lam))(jnp.asarray(var)))
    s = 40_000
    w = MB.sample_weights(model, jax.random.key(0), (s,))  # (S, E, M)
    ks = jax.vmap(lambda x: MB.k_star(model, x))(jnp.asarray(xt))  # (T, E, M)
    sample_var = np.asarray(jnp.einsum("sem,tem->ste", w, ks)).var(axis=0, ddof=1)  # (T, E)
    residual = np.stack([k["sf2"] - np.sum(
        _se(xt, z, k["ls"], k["sf2"]).T * np.linalg.solve(
            _se(z, z, k["ls"], k["sf2"]) + MB.JITTER * k["sf2"] * np.eye(8),
            _se(z, xt, k["ls"], k["sf2"])), axis=0) for k in kerns], 1)  # (T, E)
    assert np.all(residual[:3, :2] < 1e-5) and np.all(residual[3:, :2] > 1e-2)
    mc = lam * (sample_var + residual)[:, :2].sum(1)
    se = lam * np.sqrt(np.sum(2.0 * sample_var[:, :2] ** 2 / (s - 1), axis=1))
    assert np.all(np.abs(bonus - mc) < 5 * se + 1e-9), (bonus, mc, se)
    # the reward's variance, larger than the dynamics' everywhere, is left out
    assert np.all(var[:, 2] > var[:, :2].sum(1))
    np.testing.assert_allclose(bonus, lam * var[:, :2].sum(1), rtol=1e-15)


# ----------------------------------------------------------- the roll-out reads the plan's fields

U_MAX = 2.0
X0 = 0.2


def _drift_task() -> tasks.Task:
    """x' = x + 0.3 a from x0 = 0.2, the linear controller; the reward is learnt."""

    def reset(key, cfg):
        del key
        x = jnp.full((1,), X0, cfg.dtype)
        return x, x

    def step(key, x, u, cfg):
        del key
        nxt = x + 0.3 * u
        return nxt, nxt, -x[0] ** 2, jnp.zeros((), bool)

    def make_controller(name, units=0):
        del name, units
        return controllers_lib.make_squashed(
            lambda x: controllers_lib.LinearParams(jnp.concatenate([x, jnp.ones((1,), x.dtype)])),
            lambda dtype: controllers_lib.LinearParams(jnp.zeros((2,), dtype)), U_MAX, state_dim=1)

    return tasks.Task(
        name="test:drift", obs_dim=1, dt=1.0, max_action=U_MAX, episode_length=10,
        terminates=False, threshold=None, reset=reset, step=step,
        features=lambda x, u: jnp.concatenate([x, jnp.reshape(u, (1,))]), feature_dim=2,
        make_controller=make_controller, obs_centre=np.zeros(1), obs_scale=np.ones(1))


@pytest.fixture
def drift():
    tasks.register(_drift_task())
    try:
        yield
    finally:
        tasks._REGISTERED.pop("test:drift", None)
        tasks.make_task.cache_clear()


def test_the_roll_out_adds_the_reward_s_bound_and_the_information_bonus_along_its_path(drift):
    """A model of x' = x + 0.3 a and of a reward, exact GPs (every input inducing), the reward
    learnt: along the particles' common path (the mean's; x0 fixed, the controller
    2 tanh(0.3 x + 0.2)), the simulated return is the NumPy roll-out's sum of the exact GP's
    reward; 'optimistic_reward' adds beta sum_t sigma_r(x_t), 'information' lambda sum_t
    sigma_x^2(x_t) (the dynamics' output alone), and 'optimistic_joint' with eta = 0 is
    'optimistic_reward'. Each plan carries the fields its use declares."""
    beta, lam, steps = 1.7, 0.6, 6
    kerns = (dict(ls=[1.0, 1.5], sf2=0.2, sn2=1e-4), dict(ls=[0.8, 1.2], sf2=1.0, sn2=1e-3))
    cfg = C.make_config(env="test:drift", method="gp_model", controller="linear",
                        episode_length=10, num_updates=1, episodes_per_update=1,
                        model_reward="learned", model_beta=beta, model_information_weight=lam,
                        model_particles=2, model_horizon=float(steps), model_inducing=30)
    prog = rollouts.make_program(cfg)
    rng = np.random.default_rng(2)
    xs = np.c_[rng.uniform(-1, 1, 30), rng.uniform(-U_MAX, U_MAX, 30)]
    ys = np.c_[0.3 * xs[:, 1], np.sin(2 * xs[:, 0]) - 0.3 * xs[:, 1] ** 2]
    mean = ys.mean(0)
    model = _model(xs, xs, ys - mean, kerns, "float64", 1e-12)
    params = controllers_lib.LinearParams(jnp.asarray([0.3, 0.2]))
    # the NumPy roll-out of the exact GP's mean
    x, ret, sd_r, var_x = X0, 0.0, 0.0, 0.0
    for _ in range(steps):
        z = np.array([[x, U_MAX * np.tanh(0.3 * x + 0.2)]])
        (dx,), (vx,) = _exact(xs, ys[:, 0] - mean[0], z, kerns[0])
        (r,), (vr,) = _exact(xs, ys[:, 1] - mean[1], z, kerns[1])
        ret, sd_r, var_x = ret + r + mean[1], sd_r + np.sqrt(vr), var_x + vx
        x = x + dx + mean[0]
    expected = {"mean": ret, "optimistic_reward": ret + beta * sd_r,
                "information": ret + lam * var_x}
    run = jax.jit(lambda plan, h: MB.simulate(prog, model, jnp.asarray(mean), plan, params, h,
                                              cfg.settings.beta))
    got = {}
    for use in ("mean", "optimistic_reward", "information", "optimistic_joint"):
        plan = MB.make_plan(prog, cfg, model, jax.random.key(0), use, 2, steps)
        declared = MB.USES[use]
        assert (plan.variance is not None) == declared.reads_variance, use
        assert (plan.reward_bonus is not None) == declared.reward_optimism, use
        assert (plan.information is not None) == declared.information, use
        zeros = jax.tree_util.tree_map(lambda a: jnp.zeros((1,) + a.shape, a.dtype), params)
        got[use] = float(run(plan, zeros if declared.hallucinates else None))
    for use, value in expected.items():
        assert got[use] == pytest.approx(value, rel=1e-7, abs=1e-9), use
    assert got["optimistic_joint"] == got["optimistic_reward"]
    assert beta * sd_r > 0.05 and lam * var_x > 1e-3  # the differences are not rounding


# ------------------------------------------------------------------------------- the bandit

BANDIT_MAX = 3.0  # the action's bound
LOCAL, PEAK = 0.0, 2.0  # where the first episodes act (a local maximum, 0.5) and the maximum (1)


def _bandit_reward(a):
    a = jnp.clip(a, -BANDIT_MAX, BANDIT_MAX)
    return (0.5 * jnp.exp(-0.5 * ((a - LOCAL) / 0.6) ** 2)
            + jnp.exp(-0.5 * ((a - PEAK) / 0.4) ** 2))


def _bandit_task() -> tasks.Task:
    """One step an episode from a fixed observation (0); the reward a function of the action
    alone, stated nowhere (it is learnt): a local maximum 0.5 at 0, where the initial controller
    acts, the maximum 1 at 2, and next to nothing between -3 and -1.5 and past 3."""

    def reset(key, cfg):
        del key
        x = jnp.zeros((1,), cfg.dtype)
        return x, x

    def step(key, x, a, cfg):
        del key
        return x, x, _bandit_reward(a).astype(cfg.dtype), jnp.zeros((), bool)

    def make_controller(name, units=0):
        del name, units

        def apply(p, x):
            del x
            return BANDIT_MAX * jnp.tanh(p.weights[0])

        return controllers_lib.Controller(
            init=lambda dtype=None: controllers_lib.LinearParams(
                jnp.zeros((1,), dtype or jnp.result_type(float))),
            apply=apply, u_max=BANDIT_MAX, value_and_grad=jax.value_and_grad(apply))

    return tasks.Task(
        name="test:bandit", obs_dim=1, dt=1.0, max_action=BANDIT_MAX, episode_length=1,
        terminates=False, threshold=0.9, reset=reset, step=step,
        features=lambda x, a: jnp.concatenate([x, jnp.reshape(a, (1,))]), feature_dim=2,
        make_controller=make_controller, obs_centre=np.zeros(1), obs_scale=np.ones(1))


@pytest.mark.training
def test_optimism_about_a_learnt_reward_finds_the_maximum_the_mean_model_misses():
    """A one-dimensional bandit (`_bandit_task`), 4 one-step episodes an update, the first with
    the exploration noise 0.3 about the initial controller's action 0 (a local maximum), 0.05
    after; the controller's search restarted from 8 starts spread over the actions
    (`model_restarts`), the best by the simulated return kept. With the mean model the learnt
    reward reverts to the mean of the rewards seen (about 0.47) away from them, below the local
    maximum, and on every one of 6 seeds the controller stays there (its return at most 0.55)
    for 8 updates. Optimism about the learnt reward (beta 2: the reward's upper confidence bound
    away from the data, about 0.47 + 2 sigma_f, is above 0.5) brings it to the maximum (a return
    of at least 0.9) within 7 updates (28 episodes) on every seed."""
    tasks.register(_bandit_task())
    try:
        returns = {}
        for use in ("mean", "optimistic_reward"):
            cfg = C.make_config(
                env="test:bandit", method="gp_model", controller="linear", episode_length=1,
                num_updates=8, episodes_per_update=4, eval_episodes=1,
                init_log_std=float(np.log(0.3)), min_std=0.05, model_reward="learned",
                model_exploration=use, model_beta=2.0, model_particles=1, model_horizon=1.0,
                model_inducing=32, model_steps=100, model_learning_rate=0.05,
                model_fit_steps=50, model_fit_subset=32, model_restarts=8)
            keys = jax.vmap(jax.random.key)(jnp.arange(6))
            _, rec = jax.jit(jax.vmap(T.make_train(cfg)))(keys)
            returns[use] = np.asarray(rec.eval_return)  # (seeds, updates): before each update
        assert returns["mean"].max() <= 0.55, returns["mean"]
        assert np.all(returns["optimistic_reward"].max(axis=1) >= 0.9), returns["optimistic_reward"]
    finally:
        tasks._REGISTERED.pop("test:bandit", None)
        tasks.make_task.cache_clear()


# --------------------------------------------------------------------------- the sparse swing-up


def _rllib_tolerance(x, lower, upper, margin):
    """rllib's `tolerance` with its `gaussian` (sebascuri/rllib, rllib/reward/utilities.py) as
    written there, in NumPy: exp(-(d scale)^2 / 2), scale = sqrt(-2 log 0.1), d the distance from
    [lower, upper] over the margin."""
    diff = 0.5 * (upper - lower)
    distance = np.abs(x - (lower + diff)) - diff
    scale = np.sqrt(-2.0 * np.log(0.1))
    return np.exp(-0.5 * (np.maximum(distance / margin, 0.0) * scale) ** 2)


def _hucrl_reward(theta, theta_dot, u, action_cost):
    """H-UCRL's `PendulumReward` (sebascuri/hucrl, exps/inverted_pendulum/util.py) in NumPy, the
    action in units of its bound."""
    state = (_rllib_tolerance(np.cos(theta), 0.95, 1.0, 0.1)
             * _rllib_tolerance(theta_dot, -0.5, 0.5, 0.5))
    return state + action_cost * (_rllib_tolerance(u, -0.1, 0.1, 0.1) - 1.0)


@pytest.mark.parametrize("cost", tasks.SPARSE_PENDULUM_COSTS)
def test_the_sparse_swing_up_s_reward_is_h_ucrl_s(cost):
    """gymnax:Pendulum-v1-sparse-<rho>: its stated reward (`Task.reward_fn`) of (cos theta,
    sin theta, theta_dot) and the torque is H-UCRL's formula in NumPy (its action the torque over
    its bound 2, clipped) to 1e-12, on states over the whole circle and near upright; the
    environment's own step pays it along random-action episodes (float32, 1e-6), which start
    within 0.01 of hanging and still; upright and still pays 1, hanging 0 (1e-40), and the
    threshold is 100 (1 - rho)."""
    name = f"gymnax:Pendulum-v1-sparse-{cost:g}"
    task = tasks.make_task(name)
    assert name in tasks.SUPPORTED and task.threshold == pytest.approx(100.0 * (1.0 - cost))
    rng = np.random.default_rng(3)
    theta = np.concatenate([rng.uniform(-np.pi, np.pi, 200), rng.normal(0.0, 0.4, 200)])
    theta_dot = np.concatenate([rng.uniform(-8, 8, 200), rng.normal(0.0, 0.7, 200)])
    torque = rng.uniform(-3.0, 3.0, 400)
    obs = np.stack([np.cos(theta), np.sin(theta), theta_dot], 1)
    got = np.asarray(jax.vmap(task.reward_fn)(jnp.asarray(obs), jnp.asarray(torque),
                                              jnp.asarray(obs)))
    ref = _hucrl_reward(theta, theta_dot, np.clip(torque, -2.0, 2.0) / 2.0, cost)
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-12)
    assert np.ptp(ref[200:]) > 0.5  # the sample reaches the rewarded region
    upright, hanging = jnp.array([1.0, 0.0, 0.0]), jnp.array([-1.0, 0.0, 0.0])
    assert float(task.reward_fn(upright, jnp.asarray(0.1), upright)) == 1.0
    assert abs(float(task.reward_fn(hanging, jnp.asarray(2.0), hanging)) + cost) < 1e-40
    cfg = C.make_config(env=name, dtype="float32")

    def episode(key):
        k0, ks = jax.random.split(key)
        env_state, o = task.reset(k0, cfg)

        def body(carry, k):
            env_state, o = carry
            ka, ke = jax.random.split(k)
            a = jax.random.uniform(ka, (), jnp.float32, -3.0, 3.0)
            env_state, nxt, r, _ = task.step(ke, env_state, a, cfg)
            return (env_state, nxt), (o, a, r)

        return o, jax.lax.scan(body, (env_state, o), jax.random.split(ks, 100))[1]

    start, (o, a, r) = jax.jit(jax.vmap(episode))(jax.random.split(jax.random.key(4), 4))
    stated = jax.vmap(jax.vmap(task.reward_fn))(o, a, o)
    np.testing.assert_allclose(np.asarray(r), np.asarray(stated), rtol=1e-6, atol=1e-6)
    start = np.asarray(start, np.float64)
    assert np.all(np.abs(np.arctan2(start[:, 1], -start[:, 0])) <= 0.0101)
    assert np.all(np.abs(start[:, 2]) <= 0.0101)


@pytest.mark.parametrize("use", ["optimistic_reward", "optimistic_joint"])
def test_reward_optimism_where_the_reward_is_stated_is_refused_in_one_line(use):
    """A use optimistic about the learnt reward on a task planned with its stated reward: one
    line naming the setting and the remedy, from the config and from the command line; with the
    reward learnt it is taken."""
    with pytest.raises(ValueError, match=f"model_exploration: '{use}' is optimistic about a "
                       r"learnt reward.*set model_reward='learned'") as exc:
        C.make_config(method="gp_model", model_exploration=use)
    assert "\n" not in str(exc.value)
    with pytest.raises(SystemExit) as exc:
        cli.main(["reproduce", "--preset", "tiny", "--methods", "gp_model", "--compile-cache",
                  "none", "--set", f"model_exploration={use}"])
    assert "model_reward='learned'" in str(exc.value.code) and "\n" not in str(exc.value.code)
    C.make_config(method="gp_model", model_exploration=use, model_reward="learned")


def test_the_presets_of_the_exploration_uses_study_are_the_tasks_it_asks_about():
    """`--preset mountaincar-continuous-learned` and `swingup-learned` are the car and the swing-up
    (their tasks and budgets) with gp_model's reward learnt; `pendulum-sparse-<rho>` the sparse
    swing-up with Pendulum-v1's preset's budget."""
    for learned, base in (("mountaincar-continuous-learned", "mountaincar-continuous"),
                          ("swingup-learned", "swingup")):
        cfg, ref = C.preset(learned, method="gp_model"), C.preset(base, method="gp_model")
        assert cfg.env == ref.env and cfg.episode_length == ref.episode_length
        assert cfg.settings.reward == "learned" and MB.learns_reward(tasks.make_task(cfg.env), cfg)
        C.preset(learned, method="gp_pg")  # another method ignores the reward's setting
    for cost in tasks.SPARSE_PENDULUM_COSTS:
        cfg = C.preset(f"pendulum-sparse-{cost:g}", method="gp_model")
        assert cfg.env == f"gymnax:Pendulum-v1-sparse-{cost:g}" and cfg.num_updates == 21


def _exploration_uses_study():
    from conftest import experiment

    return experiment("exploration_uses_study")  # it imports model_study and planning_study


def test_the_study_s_grid_covers_every_use_from_the_model_study_s_settings():
    """experiments/exploration_uses_study.py: on every task every use of the uncertainty, the
    optimistic ones at 3 values of beta and the information bonus at 3 weights (and on the sparse
    swing-up H-UCRL's stated-reward pair); every configuration a valid config in which the
    preset's placeholders are replaced by the model study's tuned settings (on the sparse
    swing-up by Pendulum-v1's gp_model preset as it stands), the reward learnt where the choice
    does not say otherwise; its budget's updates, and its held-out seeds."""
    study = _exploration_uses_study()
    assert set(study.TASKS) == {"mountaincar-continuous-learned", "swingup-learned",
                                "pendulum-sparse-0", "pendulum-sparse-0.1", "pendulum-sparse-0.2"}
    for task in study.TASKS:
        grid = study.grid(task)
        assert set(MB.EXPLORATIONS) <= set(grid)
        for use in ("optimistic", "optimistic_reward", "optimistic_joint", "information"):
            assert len(grid[use]) == 3 and all(c["model_exploration"] == use for c in grid[use])
        assert ("optimistic_stated" in grid) == task.startswith("pendulum-sparse")
        if task.startswith("pendulum-sparse"):
            today = {k: v for k, v in C.METHOD_PRESETS["pendulum-v1"]["gp_model"].items()
                     if k != "num_updates"}
        else:
            today = study.PS.today(study.BASE_TASK[task])
        for choice, configs in grid.items():
            for c in configs:
                cfg = C.preset(task, method="gp_model", **study.overrides(task, c))
                assert cfg.settings.exploration == c["model_exploration"]
                assert cfg.settings.reward == c.get("model_reward", "learned")
                assert cfg.num_updates == {"mountaincar-continuous-learned": 11,
                                           "swingup-learned": 11}.get(task, 21)
                for k, v in today.items():
                    if k not in c and k not in study.FIXED[task]:
                        assert cfg.value(k) == pytest.approx(v), (task, choice, k)
        assert len(study.heldout_seeds(task)) == (20 if task == "swingup-learned" else 10)


def test_a_preset_the_study_chose_runs_its_choice_with_the_study_s_settings():
    """Where experiments/exploration_uses_study.py's tuning ran
    (docs/results/exploration_uses/<task>/tuning.json), `--preset <task> --methods gp_model` runs
    the configuration the study runs for the use with the best score on the tuning seeds (each
    use at its chosen value; the stated-reward comparisons are not candidates); where the tuning
    has not run every use, there is no choice yet."""
    import json
    import os

    from conftest import ROOT

    study = _exploration_uses_study()
    checked = 0
    for task in study.TASKS:
        path = os.path.join(ROOT, "docs", "results", "exploration_uses", task, "tuning.json")
        if not os.path.exists(path):
            continue
        with open(path) as f:
            runs = json.load(f)["runs"]
        if any(c not in runs for c in study.grid(task) if not c.endswith("_stated")):
            with pytest.raises(ValueError, match="has not run"):  # a partial tuning: no choice
                study.preset_choice(task, os.path.dirname(path))
            continue
        scored = [(t["score"], t["settings"]) for choice, r in runs.items()
                  if not choice.endswith("_stated") for t in r["tried"]
                  if t["settings"] == r["chosen"]]
        best = max(scored, key=lambda st: st[0])[1]
        cfg = C.preset(task, method="gp_model", **study.overrides(task, best))
        assert cfg.to_json_dict() == C.preset(task, method="gp_model").to_json_dict(), task
        checked += 1
    assert checked, "no task of the study has its tuning record"


def test_an_episode_found_the_reward_where_it_entered_the_paid_region_or_ended_early():
    """`exploration_uses_study.found_reward`, on hand-made buffers of the car (the goal at
    position 0.45 or more, its only end) and of the sparse swing-up (paid within about 18 degrees
    of upright and 0.5 rad/s of still, no end)."""
    study = _exploration_uses_study()
    n = 6
    obs = np.zeros((2, 3, n, 2))
    kept = np.ones((2, 3, n), bool)
    obs[0, 1, 2] = (0.5, 0.0)        # seed 0, update 1: a decision in the goal's region
    kept[1, 2, 4:] = False           # seed 1, update 2: the episode ended after 4 decisions
    obs[0, 2, 3] = (0.5, 0.0)        # seed 0, update 2: in the region, but not kept
    kept[0, 2, 3] = False            # (an update's episode shorter than the others: it ended)
    obs[1, 1, 3] = (0.4, 0.0)        # seed 1, update 1: short of the goal
    found = study.found_reward("mountaincar-continuous-learned", obs, kept)
    assert found.tolist() == [[False, True, True], [False, False, True]]
    sparse = study.SPARSE[0]
    theta = np.array([0.0, 0.2, 0.4, np.pi])  # upright, within the region, outside, hanging
    pend = np.stack([np.cos(theta), np.sin(theta), np.array([0.0, 0.3, 0.0, 0.0])], -1)
    got = study.found_reward(sparse, pend[:, None, None, :], np.ones((4, 1, 1), bool))
    assert got[:, 0].tolist() == [True, True, False, False]
    # an episode the buffer no longer holds (overwritten) has not found it, and is not known
    gone = np.zeros((1, 2, n), bool)
    gone[0, 1] = True
    assert study.found_reward("mountaincar-continuous-learned", np.zeros((1, 2, n, 2)),
                              gone).tolist() == [[False, False]]
    assert study.known_episodes(gone).tolist() == [[False, True]]
