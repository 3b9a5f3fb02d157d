"""gp_critic: many improvement steps per update against the GP critic Q_GP, in a KL trust region
(design: docs/design.md#critic).

After the shared steps 1-2 and gp_pg's own step (eq. 9), the fixed-noise Gaussian policy
a ~ N(c(s; theta_c), sigma^2) takes `critic_steps` Adam steps on the deterministic surrogate

  J(theta) = (1/N) sum_n E_{a ~ N(c(s_n), sigma^2)} mu_Q(s_n, a)

over the N decision states of the update's episodes (with `critic_window` W > 1, of the last W
updates' episodes: the method's state, a `Window`, keeps the W - 1 before), with no new
samples. For the ARD squared-exponential kernel and mu_Q(x) = m0 + k(B, x)^T alpha, the
expectation is closed form (`expected_q`): the kernel's action factor integrates to

  E_a exp(-(a - b_i)^2 / (2 l_a^2)) = (l_a^2 / (l_a^2 + sigma^2))^(1/2)
                                       exp(-(c - b_i)^2 / (2 (l_a^2 + sigma^2))),

with b_i the action coordinate of basis vector i and l_a the action length-scale (the integral
PILCO's moment matching uses). Its gradient in (c, log sigma) is hand-derived
(`expected_q_and_grad`) and reaches theta_c through the controller's own gradient. The critic
holds only near the data, so the steps stay in a trust region: the mean over those states of
KL(pi_data || pi_theta) between the policy that gathered the episodes and the new one is at most
`trust_region`, enforced by a backtracking line search on the whole move of the K steps
(`improve`; the largest fraction 2^-j of it, j = 0..`LINE_SEARCH_HALVINGS`, that keeps the
bound, else none). sigma stays in [min_std, max_std]. With `critic_steps` = 0 the method is gp_pg
bit for bit.

With `critic_optimism` kappa != 0 the surrogate scores each state by E_a mu_Q + kappa (E_a
sigma_Q^2)^(1/2) (kappa > 0 optimistic, < 0 pessimistic): the GP's latent variance k** + k^T C k
(Csato-Opper's C) averaged over the action in closed form as well (`expected_variance`: its
pairs' exponent splits into a part per basis vector and a part shared by every state, so each
state costs O(M) exponentials and a matrix-vector product), its gradient hand-derived
(`expected_variance_and_grad`).

Its GP takes in the paper's returns-to-go, or with `critic_targets='lambda'` lambda-returns
bootstrapped with the mean of the GP the update started from (`bootstrapped_targets`, declared as
the method's `targets`).

The exploration it accepts is every scheme whose marginal action at a decision point is
N(c(s), sigma^2): white, Ornstein-Uhlenbeck and coloured noise, with or without held actions
(the surrogate then runs over the decision states, the GP's own inputs).
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import optax

from gpguided_jax import config, estimators, kernels, methods, policy_gradient, sparse_gp
from gpguided_jax import settings as settings_lib

LINE_SEARCH_HALVINGS = 10
RECORDS = policy_gradient.RECORDS + ("critic_gain", "critic_kl", "critic_step_fraction",
                                     "critic_error", "action_lengthscale")
# its GP targets: the paper's returns-to-go, or lambda-returns bootstrapped with the GP's own mean
TARGETS = ("returns", "lambda")


@settings_lib.declare(static=("steps", "optimism", "targets", "window"), prefix="critic_",
                      aliases={"trust_region": "trust_region"})
class CriticSettings:
    """gp_critic's own settings (flat names `critic_<field>`, and `trust_region`).

    Static:
      steps: K, the surrogate steps against Q_GP per update (0: gp_pg exactly).
      optimism: kappa: the surrogate scores a state by E_a Q_GP + kappa (E_a sigma_Q^2)^(1/2),
        sigma_Q the GP's latent standard deviation (> 0 optimistic, < 0 pessimistic; 0: the mean
        alone). Needs float64.
      targets: its GP targets: 'returns' (the paper's returns-to-go) or 'lambda' (lambda-returns
        bootstrapped with the GP's own mean, `bootstrapped_targets`).
      window: in updates: the surrogate and its trust region run over the decision states of the
        last `window` updates' episodes (1: the update's own).

    Traced:
      learning_rate: Adam's step size on the surrogate.
      trust_region: delta, the bound on the mean KL (nats) between the policy that gathered an
        update's episodes and the improved one, over the update's decision states.
      lambda_horizon: lambda as a horizon (seconds): lambda = exp(-dt / horizon) per control step
        dt, for targets 'lambda' (inf: 1, the returns with the GP's mean where an episode is cut
        at its length; small: one-step targets).
    """

    steps: int = 50
    optimism: float = 0.0
    targets: str = "returns"
    window: int = 1
    learning_rate: Any = 0.01
    trust_region: Any = 0.05
    lambda_horizon: Any = 1.0

    def check(self, cfg) -> None:
        """Raises `settings.SettingError` naming the first setting that makes no sense."""
        flat = type(self).FLAT
        settings_lib.choice(flat["targets"], self.targets, TARGETS, "critic targets")
        settings_lib.integer(flat["window"], self.window, 1)
        settings_lib.integer(flat["steps"], self.steps, 0)
        settings_lib.number(flat["optimism"], self.optimism)
        if self.optimism != 0.0 and cfg.dtype != "float64":
            # its closed form holds the GP's covariance correction C as a matrix, whose entries
            # cancel where the basis vectors' Gram matrix is ill-conditioned (design: critic)
            settings_lib.fail(flat["optimism"], f"needs dtype 'float64', got {cfg.dtype!r}")
        settings_lib.traced(flat["learning_rate"], self.learning_rate, positive=True)
        settings_lib.traced(flat["trust_region"], self.trust_region, positive=True)
        settings_lib.traced(flat["lambda_horizon"], self.lambda_horizon, positive=True,
                            allow_inf=True)


# The settings gp_critic was tuned to, per preset (`Method.presets`): experiments/
# exploration_study.py tune on the swing-up; experiments/standard_tasks.py tune on the standard
# tasks, then the exploration chosen at those settings (experiments/exploration_study.py
# standard-tune); seeds 100-101 (docs/exploration.md, docs/standard_tasks.md).
PRESETS = {
    "swingup": {"learning_rate": 0.03, "use_baseline": True, "init_log_std": math.log(4.0),
                "discount_horizon": 0.5, "hold_time": 0.5, "critic_learning_rate": 0.01},
    "pendulum-v1": {"critic_learning_rate": 0.03, "hold_time": 0.2},
    "mountaincar-continuous": {"critic_learning_rate": 0.01, "exploration": "ou",
                               "noise_correlation_time": 10.0},
    "inverted-pendulum": {"critic_learning_rate": 0.003, "critic_steps": 10,
                          "episode_end": "restart", "hold_time": 0.08},
    "inverted-double-pendulum": {"critic_learning_rate": 0.003, "episode_end": "restart"},
}


def state_factors(gp: sparse_gp.SparseGPState, kernel: kernels.KernelParams, x_state) -> jax.Array:
    """The kernel's state part against every basis vector, sigma_f^2 exp(-1/2 sum_{d<D} ((x_d -
    b_id) / l_d)^2), 0 on inactive slots: (S,). `x_state` is the GP input without its last
    (action) coordinate, (D - 1,)."""
    z = (x_state - gp.basis_vectors[:, :-1]) / kernel.lengthscales[:-1]
    k = kernel.signal_variance * jnp.exp(-0.5 * jnp.sum(z * z, axis=-1))
    return jnp.where(gp.mask, k, jnp.zeros_like(k))


def expected_q(gp: sparse_gp.SparseGPState, kernel: kernels.KernelParams, factors, mean, std):
    """E_{a ~ N(mean, std^2)} mu_Q(s, a) for one state (its `state_factors`), closed form."""
    return expected_q_and_grad(gp, kernel, factors, mean, std)[0]


def expected_q_and_grad(gp, kernel, factors, mean, std):
    """`expected_q` and its hand-derived derivatives in the mean action and in log std.

    With v = l_a^2 + std^2, d = mean - b_i and g_i = (l_a^2 / v)^(1/2) exp(-d^2 / (2 v)):
    dg_i/dmean = -g_i d / v and dg_i/dlog std = g_i std^2 (d^2 / v - 1) / v.

    Returns:
      (value, d value / d mean, d value / d log std), scalars.
    """
    la2 = kernel.lengthscales[-1] ** 2
    var = std * std
    v = la2 + var
    d = mean - gp.basis_vectors[:, -1]
    g = jnp.sqrt(la2 / v) * jnp.exp(-0.5 * d * d / v)
    w = factors * gp.alpha * g
    value = gp.prior_mean + jnp.sum(w)
    return value, -jnp.sum(w * d) / v, jnp.sum(w * (d * d / v - 1.0)) * var / v


def _variance_coupling(gp: sparse_gp.SparseGPState, kernel: kernels.KernelParams, correction, std):
    """The state-independent parts of `expected_variance`: (r, G, H) with w = l_a^2 + 2 std^2,
    r = (l_a^2 / w)^(1/2), G_ij = C_ij exp(-(b_i - b_j)^2 std^2 / (2 l_a^2 w)) and H = dG/dlog std
    = -G (b_i - b_j)^2 std^2 / w^2. Every exponent is <= 0."""
    la2 = kernel.lengthscales[-1] ** 2
    var = std * std
    w = la2 + 2.0 * var
    b = gp.basis_vectors[:, -1]
    gap2 = (b[:, None] - b[None, :]) ** 2
    g = correction * jnp.exp(-0.5 * gap2 * var / (la2 * w))
    return jnp.sqrt(la2 / w), g, -g * gap2 * var / (w * w)


def expected_variance(gp: sparse_gp.SparseGPState, kernel: kernels.KernelParams, correction,
                      factors, mean, std):
    """E_{a ~ N(mean, std^2)} sigma_Q^2(s, a), the GP's latent variance k** + k^T C k averaged over
    the action, closed form, for one state (its `state_factors`); `correction` is C
    (`sparse_gp.covariance_correction`, 0 on inactive slots).

    E_a[k_i k_j] = f_i f_j (l_a^2 / w)^(1/2) exp(-(b_i - b_j)^2 / (4 l_a^2) - (mean - (b_i + b_j) /
    2)^2 / w) with w = l_a^2 + 2 std^2, f the state factors and b the basis vectors' actions (the
    product of two Gaussians in a, integrated against the policy's). Its exponent splits exactly
    into -(mean - b_i)^2 / (2 w) - (mean - b_j)^2 / (2 w) - (b_i - b_j)^2 std^2 / (2 l_a^2 w),
    every part <= 0, so the sum is r v^T G v with v_i = f_i exp(-(mean - b_i)^2 / (2 w)) per
    state and G (`_variance_coupling`) shared by every state: O(M) exponentials per state and
    one matrix-vector product, where the M x M exponentials of the pairs would be O(M^2). C is
    negative semi-definite, so the sum can round below 0 where the GP is sure: clipped at 0."""
    return expected_variance_and_grad(gp, kernel, correction, factors, mean, std)[0]


def expected_variance_and_grad(gp, kernel, correction, factors, mean, std, coupling=None):
    """`expected_variance` and its hand-derived derivatives in the mean action and in log std (0
    where it is clipped). `coupling`: `_variance_coupling`'s (r, G, H), computed here if None.

    With d_i = mean - b_i: dv_i/dmean = -v_i d_i / w, dv_i/dlog std = 2 v_i d_i^2 std^2 / w^2 and
    dr/dlog std = -2 r std^2 / w, so d(r v^T G v) = dr v^T G v + 2 r dv^T G v + r v^T dG v."""
    r, g, h = _variance_coupling(gp, kernel, correction, std) if coupling is None else coupling
    la2 = kernel.lengthscales[-1] ** 2
    var = std * std
    w = la2 + 2.0 * var
    d = mean - gp.basis_vectors[:, -1]
    v = factors * jnp.exp(-0.5 * d * d / w)
    gv = g @ v
    quad = v @ gv
    total = kernel.signal_variance + r * quad
    d_mean = -2.0 * r * jnp.sum(v * d * gv) / w
    d_log = (-2.0 * var / w) * r * quad + 4.0 * r * var * jnp.sum(v * d * d * gv) / (w * w) \
        + r * (v @ (h @ v))
    inside = total > 0
    zero = jnp.zeros_like(total)
    return (jnp.where(inside, total, zero), jnp.where(inside, d_mean, zero),
            jnp.where(inside, d_log, zero))


def _optimism_and_grad(gp, kernel, correction, factors, mean, std, kappa, coupling=None):
    """kappa (E_a sigma_Q^2)^(1/2) and its derivatives in the mean action and in log std (0 where
    the expected variance is 0)."""
    v, dv_mean, dv_log = expected_variance_and_grad(gp, kernel, correction, factors, mean, std,
                                                    coupling)
    root = jnp.sqrt(jnp.maximum(v, jnp.finfo(v.dtype).tiny))
    scale = jnp.where(v > 0, 0.5 * kappa / root, 0.0)
    return kappa * root, scale * dv_mean, scale * dv_log


def gaussian_kl(mean_p, std_p, mean_q, std_q):
    """KL(N(mean_p, std_p^2) || N(mean_q, std_q^2)) = ((mean_p - mean_q)^2 / std_q^2 + e^x - 1 - x)
    / 2 with x = 2 log(std_p / std_q).

    e^x - 1 - x is written as x^2/2 h(x), h from its series where |x| is small, so that a small KL
    (the trust region's regime) keeps its relative precision instead of cancelling."""
    x = 2.0 * (jnp.log(std_p) - jnp.log(std_q))
    small = jnp.abs(x) < 1e-2
    safe = jnp.where(small, 1.0, x)
    h = jnp.where(small, 1.0 + x / 3.0 + x * x / 12.0, 2.0 * (jnp.expm1(safe) - safe) / (safe * safe))
    d = (mean_p - mean_q) / std_q
    return 0.5 * (d * d + 0.5 * x * x * h)


def surrogate_and_grad(controller, gp, kernel, theta, states, factors, weights, optimism=None,
                       correction=None):
    """J(theta) over the states (weighted mean of `expected_q`, plus `optimism` times the root
    of `expected_variance` when it is given: `correction` is then C) and its gradient, a
    `PolicyParams` pytree: the derivatives in the mean action and log std through the
    controller's gradient. `optimism` None: the mean alone (no variance computed); else kappa,
    which may be traced."""
    std = jnp.exp(theta.log_std)
    coupling = None if optimism is None else _variance_coupling(gp, kernel, correction, std)

    def one(s, f):
        c, dc = controller.value_and_grad(theta.controller, s)
        q, dq_dc, dq_dlog = expected_q_and_grad(gp, kernel, f, c, std)
        if optimism is not None:
            u, du_dc, du_dlog = _optimism_and_grad(gp, kernel, correction, f, c, std,
                                                   jnp.asarray(optimism, c.dtype), coupling)
            q, dq_dc, dq_dlog = q + u, dq_dc + du_dc, dq_dlog + du_dlog
        return q, jax.tree_util.tree_map(lambda g: dq_dc * g, dc), dq_dlog

    q, g_c, g_log = jax.vmap(one)(states, factors)
    w = weights / jnp.maximum(jnp.sum(weights), 1.0)
    grad = theta._replace(
        controller=jax.tree_util.tree_map(lambda g: jnp.tensordot(w, g, axes=1), g_c),
        log_std=jnp.sum(w * g_log))
    return jnp.sum(w * q), grad


def mean_kl(controller, theta_p, theta_q, states, weights):
    """The weighted mean over `states` of KL(pi_{theta_p} || pi_{theta_q}), Gaussian policies."""
    mean_p = jax.vmap(lambda s: controller.apply(theta_p.controller, s))(states)
    mean_q = jax.vmap(lambda s: controller.apply(theta_q.controller, s))(states)
    kl = gaussian_kl(mean_p, jnp.exp(theta_p.log_std), mean_q, jnp.exp(theta_q.log_std))
    return jnp.sum(weights * kl) / jnp.maximum(jnp.sum(weights), 1.0)


def improve(controller, gp, kernel, theta_data, theta, states, factors, weights, *, num_steps: int,
            learning_rate, trust_region, min_std, max_std, optimism=None, correction=None):
    """`num_steps` Adam steps on the surrogate from `theta`, then the largest fraction 2^-j of the
    whole move (j = 0..LINE_SEARCH_HALVINGS) whose mean KL from `theta_data` is within
    `trust_region` (none if no fraction is). sigma is clipped to [min_std, max_std]. `optimism`
    and `correction`: `surrogate_and_grad`'s.

    Returns:
      (theta, surrogate gain over `theta`, mean KL from theta_data, the fraction taken).
    """
    optimizer = optax.adam(learning_rate)
    lo, hi = jnp.log(min_std), jnp.log(max_std)

    def clip(t):
        return t._replace(log_std=jnp.clip(t.log_std, lo, hi))

    def step(carry, _):
        t, opt_state = carry
        _, grad = surrogate_and_grad(controller, gp, kernel, t, states, factors, weights,
                                     optimism, correction)
        grad = jax.tree_util.tree_map(lambda g: jnp.where(jnp.isfinite(g), g, 0.0), grad)
        updates, opt_state = optimizer.update(jax.tree_util.tree_map(jnp.negative, grad),
                                              opt_state, t)
        return (clip(optax.apply_updates(t, updates)), opt_state), None

    (moved, _), _ = jax.lax.scan(step, (theta, optimizer.init(theta)), None, length=num_steps)
    fractions = 0.5 ** jnp.arange(LINE_SEARCH_HALVINGS + 1, dtype=theta.log_std.dtype)

    def at(frac):
        return clip(jax.tree_util.tree_map(lambda a, b: a + frac * (b - a), theta, moved))

    kls = jax.vmap(lambda f: mean_kl(controller, theta_data, at(f), states, weights))(fractions)
    ok = jnp.isfinite(kls) & (kls <= trust_region)
    frac = jnp.where(jnp.any(ok), fractions[jnp.argmax(ok)], 0.0)
    new = at(frac)
    start, _ = surrogate_and_grad(controller, gp, kernel, theta, states, factors, weights,
                                  optimism, correction)
    end, _ = surrogate_and_grad(controller, gp, kernel, new, states, factors, weights, optimism,
                                correction)
    return new, end - start, mean_kl(controller, theta_data, new, states, weights), frac


class Window(NamedTuple):
    """gp_critic's own state with `critic_window` W > 1: the decision states of the W - 1 updates
    before, the most recent first, and their weights (0 for a state after an episode's end, and
    for the slots of updates not yet run): (W - 1, N, obs), (W - 1, N)."""
    states: jax.Array
    weights: jax.Array


def init(prog, key, cfg):
    """The empty `Window` (every weight 0), or () with a window of the update alone."""
    del key
    static = prog.config
    if cfg.settings.window == 1:
        return ()
    per_update = static.episodes_per_update * -(-static.episode_length // prog.hold)
    shape = (cfg.settings.window - 1, per_update)
    return Window(states=jnp.zeros(shape + (prog.task.obs_dim,), prog.dtype),
                  weights=jnp.zeros(shape, prog.dtype))


def _decision_states(prog, eps):
    """The update's decision states (every `hold` steps) and their weights (0 after an episode's
    end): (N, obs), (N,)."""
    states = eps.states[:, ::prog.hold]
    flat = states.reshape(-1, states.shape[-1])
    if eps.alive is None:
        weights = jnp.ones(flat.shape[0], flat.dtype)
    else:
        weights = eps.alive[:, ::prog.hold].reshape(-1).astype(flat.dtype)
    return flat, weights


def _window_states(prog, window, eps):
    """The surrogate's states, their GP inputs without the action and their weights, (N', obs),
    (N', D - 1), (N',): the update's decision states, then the window's; and the window the next
    update reads (these states in front, the oldest update's dropped)."""
    states, weights = _decision_states(prog, eps)
    if isinstance(window, Window):
        states = jnp.concatenate([states[None], window.states]).reshape(-1, states.shape[-1])
        weights = jnp.concatenate([weights[None], window.weights]).reshape(-1)
        per_update = window.states.shape[1]
        window = Window(states=states[:-per_update].reshape(window.states.shape),
                        weights=weights[:-per_update].reshape(window.weights.shape))
    x = jax.vmap(lambda s: prog.task.features(s, jnp.zeros((), s.dtype)))(states)[:, :-1]
    return states, x, weights, window


def unseen_error(prog, gp, kernel, eps, returns):
    """The critic's error on returns it has not seen: 1 - R^2 of mu_Q of `gp` (the GP before it
    took the update's episodes in) against the returns-to-go of those episodes, over their steps
    before an end: sum (Ret - mu)^2 / sum (Ret - mean Ret)^2. 0 is a perfect critic, 1 one no
    better than the returns' mean."""
    x = jax.vmap(jax.vmap(prog.task.features))(eps.states, eps.actions)
    mu = jax.vmap(jax.vmap(lambda xi: sparse_gp.predict(gp, xi, kernel)[0]))(x)
    w = jnp.ones_like(returns) if eps.alive is None else eps.alive.astype(returns.dtype)
    n = jnp.maximum(jnp.sum(w), 1.0)
    centre = jnp.sum(w * returns) / n
    spread = jnp.sum(w * (returns - centre) ** 2)
    return jnp.sum(w * (returns - mu) ** 2) / jnp.maximum(spread, jnp.finfo(returns.dtype).tiny)


def bootstrapped_targets(prog, cfg, state, ep, returns):
    """gp_critic's GP targets for one episode (`Method.targets`): its returns-to-go, or with
    targets 'lambda' its `estimators.lambda_returns` with the critic's value Q_GP(s_{t+1}, a_{t+1})
    of the GP the update started from (at the episode's last step, where it is cut at its length,
    the action is the controller's c(s_H)), lambda = exp(-dt / `lambda_horizon`). An
    episode ends (no bootstrap) where it stops being alive, where it restarts, or at the last
    step where the task's stated end (`Task.end_fn`) holds."""
    if cfg.settings.targets == "returns":
        return returns
    task, dtype = prog.task, returns.dtype
    last = prog.controller.apply(state.theta.controller, ep.next_states[-1])
    actions = jnp.concatenate([ep.actions[1:], jnp.reshape(last, (1,)).astype(ep.actions.dtype)])
    x = jax.vmap(task.features)(ep.next_states, actions)
    q = jax.vmap(lambda xi: sparse_gp.predict(state.gp, xi, state.kernel)[0])(x).astype(dtype)
    if ep.ends is not None:
        cut = ep.ends
    elif ep.alive is not None:
        ends_last = (jnp.asarray(task.end_fn(ep.next_states[-1]), bool) if task.end_fn is not None
                     else jnp.zeros((), bool))
        cut = ep.alive & ~jnp.concatenate([ep.alive[1:], (~ends_last)[None]])
    else:
        cut = jnp.zeros(returns.shape, bool)
    lam = jnp.exp(-config.control_interval(prog.config) / jnp.asarray(cfg.settings.lambda_horizon,
                                                                       dtype))
    return estimators.lambda_returns(ep.rewards, q, cut, cfg.discount, lam)


def critic_update(prog, cfg, state, batch):
    """gp_pg's step (eq. 9), then the settings' `steps` surrogate steps in the trust region. Its records
    add the surrogate's gain, the mean KL, the fraction of the move taken, the critic's error on
    the update's episodes before the GP took them in (`unseen_error`) and the action
    length-scale."""
    own = cfg.settings
    theta, opt_state, _, records = policy_gradient.q_gp_update(prog, cfg, state, batch)
    states, x, weights, method_state = _window_states(prog, state.method_state, batch.episodes)
    zero = jnp.zeros((), prog.dtype)
    records = dict(records, critic_error=unseen_error(prog, state.gp, state.kernel,
                                                      batch.episodes, batch.returns),
                   action_lengthscale=state.kernel.lengthscales[-1].astype(prog.dtype))
    if own.steps == 0:
        return theta, opt_state, method_state, dict(
            records, critic_gain=zero, critic_kl=zero, critic_step_fraction=zero)
    kappa = own.optimism or None  # 0: the mean alone, no variance computed
    factors = jax.vmap(lambda xs: state_factors(batch.gp, state.kernel, xs))(x)
    new, gain, kl, frac = improve(
        prog.controller, batch.gp, state.kernel, state.theta, theta, states, factors, weights,
        num_steps=own.steps, learning_rate=own.learning_rate,
        trust_region=own.trust_region, min_std=cfg.min_std, max_std=cfg.max_std, optimism=kappa,
        correction=None if kappa is None else sparse_gp.covariance_correction(batch.gp))
    return new, opt_state, method_state, dict(
        records, critic_gain=gain, critic_kl=kl, critic_step_fraction=frac.astype(prog.dtype))


methods.register(methods.Method(
    name="gp_critic", policy="fixed_noise", prior="q_gp", init=init,
    update=critic_update, records=RECORDS, explorations=("white", "ou", "coloured"),
    compare_with=("reinforce", "gp_pg"), fit_fields=methods.Q_GP_FIT_FIELDS,
    targets=bootstrapped_targets, settings=CriticSettings, presets=PRESETS,
    check=policy_gradient.check_hand_gradient,
    explain_exploration="'parameter' noise makes the action's distribution depend on the state "
                        "through the weights, which the closed-form surrogate does not take"))
