"""Stochastic policies around a controller: fixed noise (eq. 1), GP-guided exploratory noise
(eq. 16-19) and the Gibbs policy over GP-scored candidate actions (eq. 20-22).
Design: docs/design.md#policies.

All three share one calling convention, so that a training loop can pick one by a static name
(`make_policy`) and run it inside `lax.scan`:

  action, aux = policy.sample(key, theta, state, ctx)
  log_pi      = policy.log_prob(theta, state, action, ctx, aux)
  score       = policy.grad_log_prob(theta, state, action, ctx, aux)   # pytree like theta
  std         = policy.exploration_std(theta, state, ctx, aux)
  action, aux, score, std = policy.act(key, theta, state, ctx)   # all four at once

`act` is what a training loop calls at every step: the same numbers as `sample`, `grad_log_prob`
and `exploration_std` (to rounding), with the GP and the controller evaluated once instead of in
each of them.

* `theta` is a `PolicyParams` (controller parameters, log sigma). Every policy takes the same
  `theta`; only the fixed-noise policy uses `log_std` (its score is 0 for the other two).
* `ctx` is a `PolicyContext`: the GP state, the kernel hyperparameters and the traced policy
  hyperparameters (lambda_v, beta, sigma_e, candidate scale, floors).
* `aux` is a `PolicyAux`, the by-products of sampling that the score needs (the Gibbs candidates,
  their normalised Q values and the selected index; the sampling variance).
* The number K of Gibbs candidates is static (closed over by `gibbs_policy`).

Everything is written for one state (an observation vector; the pendulum's is [phi, omega]) and
one scalar action; batch with `jax.vmap`. Sampled
actions are NOT clipped (the environment clips the torque); log-probabilities and scores are those
of the unclipped sample.

GP convention (gpguided_jax.sparse_gp): latent variance sigma^2(x) = k** + k^T C k with C negative
semi-definite (the paper writes k** - k^T C k with C of the opposite sign), computed in square-root
form as max(k** - |T k|^2, 0) + |Z k|^2, which is >= 0 by construction.
"""

import math
from collections.abc import Callable
from typing import Any, NamedTuple

import chex
import jax
import jax.numpy as jnp

from gpguided_jax import _random, kernels, sparse_gp
from gpguided_jax import controllers as controllers_lib

_LOG_2PI = 1.8378770664093453  # log(2 pi)
_PENDULUM_FEATURES = kernels.state_action_features  # the GP input unless a task gives its own


class PolicyParams(NamedTuple):
    """Policy parameters theta = (theta_c, log sigma) (design: docs/design.md#policies).

    Attributes:
      controller: pytree of controller parameters theta_c (see gpguided_jax.controllers).
      log_std: () log sigma of the fixed exploratory noise (eq. 1); unused by the GP-guided
        policies, whose score with respect to it is 0.
    """

    controller: Any
    log_std: jax.Array


class PolicyContext(NamedTuple):
    """Everything a policy reads besides theta: the GP critic and traced hyperparameters.

    All fields are arrays (traced), so a sweep over them is one compiled program.

    Attributes:
      gp: `sparse_gp.SparseGPState`, the current Q_GP model.
      kernel: `kernels.KernelParams` of the GP.
      variance_scale: () lambda_v in sigma^2_GP = lambda_v sigma^2(x*) (eq. 16).
      variance_floor: () lower bound on the guided-noise variance sigma^2_GP.
      inverse_temperature: () beta of the Gibbs policy (eq. 20).
      energy_width: () sigma_e, width of the Gaussian neighbourhood term in the energy.
      candidate_scale: () factor on the GP variance giving the candidate variance.
      candidate_floor: () lower bound on the candidate variance sigma^2_cand.
    """

    gp: sparse_gp.SparseGPState
    kernel: kernels.KernelParams
    variance_scale: jax.Array
    variance_floor: jax.Array
    inverse_temperature: jax.Array
    energy_width: jax.Array
    candidate_scale: jax.Array
    candidate_floor: jax.Array


class PolicyAux(NamedTuple):
    """By-products of `sample` that `log_prob`/`grad_log_prob` need. K = number of candidates
    (0 for the Gaussian policies).

    Attributes:
      mean_action: () c(s; theta) when the action was sampled.
      variance: () the variance the action (Gaussian policies) or the candidates (Gibbs) were
        drawn with: sigma^2 (eq. 1), sigma^2_GP (eq. 16) or sigma^2_cand.
      candidates: (K,) Gibbs candidate actions a_j (held constant in the score).
      normalised_q: (K,) min-max normalised Q_GP(s, a_j) in [0, 1] (held constant in the score).
      probs: (K,) the Gibbs selection probabilities pi_j = softmax(beta E)_j at sampling time.
      index: () int32 index J of the selected candidate (0 for the Gaussian policies).
    """

    mean_action: jax.Array
    variance: jax.Array
    candidates: jax.Array
    normalised_q: jax.Array
    probs: jax.Array
    index: jax.Array


class Policy(NamedTuple):
    """A stochastic policy as a bundle of pure functions sharing one calling convention.

    Attributes:
      sample: (key, theta, state, ctx) -> (action, aux).
      log_prob: (theta, state, action, ctx, aux) -> () log pi(action | state).
      grad_log_prob: (theta, state, action, ctx, aux) -> PolicyParams, hand-derived score.
      exploration_std: (theta, state, ctx, aux) -> () a standard deviation of the exploration.
      act: (key, theta, state, ctx) -> (action, aux, score, std): `sample`, then the score and
        the exploration std of that action, sharing their GP and controller evaluations.
      name: the policy's name (static).
      gaussian: (theta, state, ctx) -> (mean, std, j_mean, j_std) for a Gaussian policy (None for
        the Gibbs policy): its action is mean + std * eps, and j_mean = grad mean / std and j_std =
        grad std / std are pytrees like theta. A training loop that supplies eps from a
        correlated process (`gpguided_jax.exploration`) builds the scores from these.
      reads_gp: whether the policy reads the GP in `ctx` (static). One that does not acts the
        same whatever the GP has taken in, so a training loop may roll out all episodes of an
        update at once, before the GP takes any of them in.
      memory: `memory(theta, ctx) -> m`, the policy's memory at an episode's start (a pytree of
        fixed shapes, carried from one decision to the next: a planner's previous plan); with
        one, `act` takes it last and returns the next one last, `act(key, theta, state, ctx, m)
        -> (action, aux, score, std, m)`. None: a memoryless policy (the three here).
    """

    sample: Callable[..., tuple[jax.Array, PolicyAux]]
    log_prob: Callable[..., jax.Array]
    grad_log_prob: Callable[..., PolicyParams]
    exploration_std: Callable[..., jax.Array]
    act: Callable[..., tuple[jax.Array, PolicyAux, PolicyParams, jax.Array]]
    name: str
    reads_gp: bool = True
    gaussian: Callable[..., tuple] | None = None
    memory: Callable[..., Any] | None = None


def init_params(controller: controllers_lib.Controller, log_std: float = 0.0, dtype=None):
    """Deterministic initial theta: zero controller weights (c = 0) and the given log sigma."""
    dtype = dtype or jnp.result_type(float)
    return PolicyParams(controller=controller.init(dtype), log_std=jnp.asarray(log_std, dtype))


def make_context(
    gp: sparse_gp.SparseGPState,
    kernel: kernels.KernelParams,
    *,
    variance_scale=1.0,
    variance_floor=1e-6,
    inverse_temperature=10.0,
    energy_width=1.0,
    candidate_scale=1.0,
    candidate_floor=1e-2,
) -> PolicyContext:
    """Builds a `PolicyContext`, casting the hyperparameters to the GP's dtype.

    Defaults: lambda_v = 1, variance floor 1e-6 (N m)^2, beta = 10 (the paper's Fig. 3),
    sigma_e = 1 N m, candidate variance = max(1 * sigma^2(x*), 1e-2).
    """
    dtype = gp.alpha.dtype

    def cast(value):
        return jnp.asarray(value, dtype)

    return PolicyContext(
        gp=gp,
        kernel=kernel,
        variance_scale=cast(variance_scale),
        variance_floor=cast(variance_floor),
        inverse_temperature=cast(inverse_temperature),
        energy_width=cast(energy_width),
        candidate_scale=cast(candidate_scale),
        candidate_floor=cast(candidate_floor),
    )


def _empty_gibbs_fields(dtype):
    empty = jnp.zeros((0,), dtype)
    return dict(candidates=empty, normalised_q=empty, probs=empty, index=jnp.zeros((), jnp.int32))


def _scale_tree(tree, scalar):
    return jax.tree_util.tree_map(lambda leaf: scalar * leaf, tree)


# --------------------------------------------------------------------------------------------
# GP quantities at x* = (s, a*) and their derivative along the action coordinate (eq. 18-19).
# --------------------------------------------------------------------------------------------


def gp_latent_variance(gp, kernel, state, action, features=_PENDULUM_FEATURES):
    """sigma^2(x*) = max(gamma, 0) + |Z k|^2 at x* = features(s, a*) (eq. 6; `sparse_gp.predict`)."""
    x = features(state, action)
    return sparse_gp.predict(gp, x, kernel)[1]


def gp_latent_variance_and_grad(gp, kernel, state, action, features=_PENDULUM_FEATURES):
    """sigma^2(x*) and d sigma^2 / d a* at x* = features(s, a*) (eq. 18-19, C held constant).

    In the square-root form of `gpguided_jax.sparse_gp`, sigma^2 = k** - |T k|^2 + |Z k|^2 (the
    Csato-Opper k** + k^T C k with C = Z^T Z - T^T T), so with T and Z held constant (the paper's
    "we consider C constant"):
      d sigma^2/d a* = d k**/d a* - 2 (T k)^T (T dk/d a*) + 2 (Z k)^T (Z dk/d a*)
                     = d k**/d a* + 2 k^T C dk/d a*,
    d k**/d a* = 0 for the stationary SE kernel, and for the SE-ARD kernel
      dk_i/d a* = -k_i (a* - b_{i,a}) / l_a^2,
    with b_{i,a} the action coordinate of basis vector i and l_a its length-scale (the action is
    the last coordinate of `features`, `kernels.state_action_features` by default). Where the
    residual k** - |T k|^2 is clipped at 0 (rounding only) its derivative is 0.

    Returns:
      (variance, d_variance_d_action), scalars.
    """
    x = features(state, action)
    kernel = jax.tree.map(lambda a: jnp.asarray(a, gp.alpha.dtype), kernel)
    k = sparse_gp.masked_kernel_vector(gp, x, kernel)
    kxx = kernels.kernel_diag(x, kernel)
    action_lengthscale = kernel.lengthscales[-1]
    dk = -k * (x[-1] - gp.basis_vectors[:, -1]) / (action_lengthscale * action_lengthscale)
    T, Z = gp.gram_inv_root, gp.alpha_cov_root
    # four matrix-vector products: XLA:CPU runs T [k, dk] as one 2-column product, or as rows
    # times T^T, slower inside the training loop (design: docs/design.md#decisions)
    w, z = T @ k, Z @ k
    w_d, z_d = T @ dk, Z @ dk
    gamma = kxx - w @ w
    positive = gamma > 0.0
    variance = jnp.where(positive, gamma, jnp.zeros_like(gamma)) + z @ z
    dvariance = jnp.where(positive, -2.0 * (w @ w_d), 0.0) + 2.0 * (z @ z_d)
    return variance, dvariance


def gp_mean(gp, kernel, state, action, features=_PENDULUM_FEATURES):
    """Q_GP(s, a) = m0 + k(x)^T alpha, the GP predictive mean (eq. 5; m0 the prior mean)."""
    x = features(state, action)
    return gp.prior_mean + sparse_gp.masked_kernel_vector(gp, x, kernel) @ gp.alpha


def gp_means_over_actions(gp, kernel, state, actions, features=_PENDULUM_FEATURES):
    """Q_GP(s, a_j) for K actions at one state: (K,). The kernel's state part
    sum_d<3 ((x_d - b_id) / l_d)^2 is computed once for all actions (`gp_mean` for each a_j,
    to rounding)."""
    kernel = jax.tree.map(lambda a: jnp.asarray(a, gp.alpha.dtype), kernel)
    x = features(state, jnp.zeros((), state.dtype))
    z_state = (x[:-1] - gp.basis_vectors[:, :-1]) / kernel.lengthscales[:-1]
    state_part = jnp.sum(z_state * z_state, axis=1)  # (S,)
    z_action = (actions[:, None] - gp.basis_vectors[None, :, -1]) / kernel.lengthscales[-1]
    k = kernel.signal_variance * jnp.exp(-0.5 * (state_part[None, :] + z_action * z_action))
    return gp.prior_mean + k @ jnp.where(gp.mask, gp.alpha, 0.0)


def _floored(value, floor):
    # `where`, not `maximum`: at a tie jnp.maximum splits the gradient in halves, and we want the
    # hand gradient (0 on the floor) and autodiff to agree everywhere.
    return jnp.where(value > floor, value, floor)


def guided_variance(controller, controller_params, state, ctx, features=_PENDULUM_FEATURES):
    """sigma^2_GP(s) = max(lambda_v sigma^2(x*), floor), x* = (s, c(s; theta_c)) (eq. 16)."""
    mean_action = controller.apply(controller_params, state)
    # the value of gp_latent_variance_and_grad (equal to gp_latent_variance up to rounding), so
    # that sampling, log_prob and the score all use the same sigma^2_GP bit for bit
    latent = gp_latent_variance_and_grad(ctx.gp, ctx.kernel, state, mean_action, features)[0]
    return _floored(ctx.variance_scale * latent, ctx.variance_floor)


def guided_variance_and_grad(controller, controller_params, state, ctx, features=_PENDULUM_FEATURES):
    """sigma^2_GP, its gradient with respect to theta_c (eq. 18-19), and c, dc/dtheta_c.

    grad sigma^2_GP = lambda_v d sigma^2/d a* |_{a* = c(s)} * dc/dtheta_c, with C constant.
    The floor: where lambda_v sigma^2(x*) <= floor the variance is the constant floor and this
    gradient is exactly 0 (the policy then behaves like the fixed-noise policy with sigma^2 =
    floor).

    Returns:
      (variance, grad_variance, mean_action, grad_mean_action); the gradients are pytrees like
      controller_params.
    """
    mean_action, grad_mean = controllers_lib.mean_and_grad(controller, controller_params, state)
    latent, dlatent_da = gp_latent_variance_and_grad(ctx.gp, ctx.kernel, state, mean_action, features)
    scaled = ctx.variance_scale * latent
    variance = _floored(scaled, ctx.variance_floor)
    dvariance_da = jnp.where(
        scaled > ctx.variance_floor, ctx.variance_scale * dlatent_da, jnp.zeros_like(scaled)
    )
    return variance, _scale_tree(grad_mean, dvariance_da), mean_action, grad_mean


def _gaussian_log_prob(action, mean, variance):
    diff = action - mean
    return -0.5 * (_LOG_2PI + jnp.log(variance) + diff * diff / variance)


# --------------------------------------------------------------------------------------------
# (1) Fixed Gaussian noise, eq. 1.
# --------------------------------------------------------------------------------------------


def fixed_noise_policy(controller: controllers_lib.Controller) -> Policy:
    """a ~ N(c(s; theta_c), sigma^2), sigma = exp(log_std) (eq. 1).

    Score: d log pi/d theta_c = (a - c)/sigma^2 dc/dtheta_c,
           d log pi/d log sigma = (a - c)^2/sigma^2 - 1.
    """

    def sample(key, theta, state, ctx):
        chex.assert_rank(state, 1)
        mean_action = controller.apply(theta.controller, state)
        std = jnp.exp(theta.log_std)
        action = mean_action + std * _random.normal(key, (), mean_action.dtype)
        aux = PolicyAux(
            mean_action=mean_action, variance=std * std, **_empty_gibbs_fields(state.dtype)
        )
        return action, aux

    def log_prob(theta, state, action, ctx, aux):
        del ctx, aux
        mean_action = controller.apply(theta.controller, state)
        return _gaussian_log_prob(action, mean_action, jnp.exp(2.0 * theta.log_std))

    def grad_log_prob(theta, state, action, ctx, aux):
        del ctx, aux
        chex.assert_rank(state, 1)
        mean_action, grad_mean = controllers_lib.mean_and_grad(controller, theta.controller, state)
        variance = jnp.exp(2.0 * theta.log_std)
        diff = action - mean_action
        return PolicyParams(
            controller=_scale_tree(grad_mean, diff / variance),
            log_std=diff * diff / variance - 1.0,
        )

    def exploration_std(theta, state, ctx, aux):
        del state, ctx, aux
        return jnp.exp(theta.log_std)

    def act(key, theta, state, ctx):
        del ctx
        chex.assert_rank(state, 1)
        mean_action, grad_mean = controllers_lib.mean_and_grad(controller, theta.controller, state)
        std = jnp.exp(theta.log_std)
        action = mean_action + std * _random.normal(key, (), mean_action.dtype)
        variance = std * std
        aux = PolicyAux(mean_action=mean_action, variance=variance,
                        **_empty_gibbs_fields(state.dtype))
        diff = action - mean_action
        score = PolicyParams(controller=_scale_tree(grad_mean, diff / variance),
                             log_std=diff * diff / variance - 1.0)
        return action, aux, score, std

    def gaussian(theta, state, ctx):
        del ctx
        chex.assert_rank(state, 1)
        mean_action, grad_mean = controllers_lib.mean_and_grad(controller, theta.controller, state)
        std = jnp.exp(theta.log_std)
        j_mean = PolicyParams(controller=_scale_tree(grad_mean, 1.0 / std),
                              log_std=jnp.zeros_like(theta.log_std))
        j_std = PolicyParams(controller=_scale_tree(grad_mean, 0.0),
                             log_std=jnp.ones_like(theta.log_std))
        return mean_action, std, j_mean, j_std

    return Policy(sample, log_prob, grad_log_prob, exploration_std, act, "fixed_noise",
                  reads_gp=False, gaussian=gaussian)


# --------------------------------------------------------------------------------------------
# (2) GP-guided exploratory noise, eq. 16-19.
# --------------------------------------------------------------------------------------------


def guided_variance_policy(controller: controllers_lib.Controller, features=_PENDULUM_FEATURES) -> Policy:
    """a ~ N(c(s), sigma^2_GP(s)), sigma^2_GP = max(lambda_v sigma^2(s, c(s)), floor) (eq. 16).

    Score (eq. 17, with the factor 1/2 that the printed equation lacks; design:
    docs/design.md#deviations):
      d log pi/d theta_c = (a - c)/sigma^2_GP dc/dtheta_c
                           + ((a - c)^2 - sigma^2_GP)/(2 sigma^4_GP) grad sigma^2_GP,
      grad sigma^2_GP = lambda_v (2 k^T C dk/da*) dc/dtheta_c  (eq. 18-19, C constant; 0 on the
      floor),
      d log pi/d log sigma = 0 (sigma is not used).
    log_prob and the score evaluate sigma^2_GP with the GP in `ctx`: pass the GP that the action
    was sampled with to get the score of the behaviour distribution.
    """

    def sample(key, theta, state, ctx):
        chex.assert_rank(state, 1)
        mean_action = controller.apply(theta.controller, state)
        variance = guided_variance(controller, theta.controller, state, ctx, features)
        action = mean_action + jnp.sqrt(variance) * _random.normal(
            key, (), mean_action.dtype
        )
        aux = PolicyAux(
            mean_action=mean_action, variance=variance, **_empty_gibbs_fields(state.dtype)
        )
        return action, aux

    def log_prob(theta, state, action, ctx, aux):
        del aux
        mean_action = controller.apply(theta.controller, state)
        variance = guided_variance(controller, theta.controller, state, ctx, features)
        return _gaussian_log_prob(action, mean_action, variance)

    def score(theta, action, variance, grad_variance, mean_action, grad_mean):
        diff = action - mean_action
        mean_weight = diff / variance
        variance_weight = (diff * diff - variance) / (2.0 * variance * variance)
        grad_controller = jax.tree_util.tree_map(
            lambda gm, gv: mean_weight * gm + variance_weight * gv, grad_mean, grad_variance
        )
        return PolicyParams(controller=grad_controller, log_std=jnp.zeros_like(theta.log_std))

    def grad_log_prob(theta, state, action, ctx, aux):
        del aux
        variance, grad_variance, mean_action, grad_mean = guided_variance_and_grad(
            controller, theta.controller, state, ctx, features
        )
        return score(theta, action, variance, grad_variance, mean_action, grad_mean)

    def exploration_std(theta, state, ctx, aux):
        # sigma_GP of the distribution the action was drawn from (the same number that
        # guided_variance(controller, theta.controller, state, ctx) recomputes).
        del theta, state, ctx
        return jnp.sqrt(aux.variance)

    def act(key, theta, state, ctx):
        chex.assert_rank(state, 1)
        variance, grad_variance, mean_action, grad_mean = guided_variance_and_grad(
            controller, theta.controller, state, ctx, features
        )
        std = jnp.sqrt(variance)
        action = mean_action + std * _random.normal(key, (), mean_action.dtype)
        aux = PolicyAux(mean_action=mean_action, variance=variance,
                        **_empty_gibbs_fields(state.dtype))
        return action, aux, score(theta, action, variance, grad_variance, mean_action, grad_mean), std

    def gaussian(theta, state, ctx):
        chex.assert_rank(state, 1)
        variance, grad_variance, mean_action, grad_mean = guided_variance_and_grad(
            controller, theta.controller, state, ctx, features
        )
        std = jnp.sqrt(variance)
        zero = jnp.zeros_like(theta.log_std)
        return (mean_action, std,
                PolicyParams(controller=_scale_tree(grad_mean, 1.0 / std), log_std=zero),
                PolicyParams(controller=_scale_tree(grad_variance, 0.5 / variance), log_std=zero))

    return Policy(sample, log_prob, grad_log_prob, exploration_std, act, "guided_variance",
                  gaussian=gaussian)


# --------------------------------------------------------------------------------------------
# (3) Gibbs policy over GP-scored candidates, eq. 20-22.
# --------------------------------------------------------------------------------------------


def normalise_q(q_values: jax.Array) -> jax.Array:
    """Min-max normalisation of the candidates' Q_GP to [0, 1] (design: docs/design.md#policies).

    Rewards are negative, and with raw Q the energy Q exp(-d^2/2 sigma_e^2) would prefer actions
    far from c(s); the paper's Fig. 3 shows Q in [0, 1]. Guard: when all Q are equal (range at
    most a few ulps of max |Q|, e.g. an empty GP) the Q values carry no preference and Q~ = 1 for
    every candidate, so that E reduces to the Gaussian neighbourhood term around c(s).
    """
    chex.assert_rank(q_values, 1)
    q_min, q_max = jnp.min(q_values), jnp.max(q_values)
    q_range = q_max - q_min
    eps = jnp.finfo(q_values.dtype).eps
    flat = q_range <= 64.0 * eps * jnp.maximum(1.0, jnp.max(jnp.abs(q_values)))
    safe_range = jnp.where(flat, jnp.ones_like(q_range), q_range)
    return jnp.where(flat, jnp.ones_like(q_values), (q_values - q_min) / safe_range)


def gibbs_energy(candidates, normalised_q, mean_action, energy_width):
    """E_j = Q~_j exp(-(a_j - c(s))^2 / (2 sigma_e^2)) (eq. 20)."""
    diff = candidates - mean_action
    return normalised_q * jnp.exp(-0.5 * diff * diff / (energy_width * energy_width))


def candidate_variance(controller, controller_params, state, ctx, features=_PENDULUM_FEATURES):
    """sigma^2_cand = max(candidate_scale * sigma^2(s, c(s)), candidate_floor): the model's
    confidence at (s, c(s)) (paper, text after eq. 22), floored and scaled."""
    mean_action = controller.apply(controller_params, state)
    latent = gp_latent_variance(ctx.gp, ctx.kernel, state, mean_action, features)
    return _floored(ctx.candidate_scale * latent, ctx.candidate_floor)


def gibbs_distribution(candidates, normalised_q, mean_action, ctx):
    """(E, pi) over the candidates: pi = softmax(beta E) (the discrete form of eq. 20)."""
    energy = gibbs_energy(candidates, normalised_q, mean_action, ctx.energy_width)
    return energy, jax.nn.softmax(ctx.inverse_temperature * energy)


def gibbs_select(key, energy, inverse_temperature):
    """J ~ Categorical(softmax(beta E)); the selection step of `gibbs_policy.sample`."""
    return _random.categorical(key, inverse_temperature * energy)


def _gibbs_score(theta, aux: PolicyAux, energy, probs, grad_mean, ctx) -> PolicyParams:
    """The Gibbs policy's score d log pi_J/d theta (eq. 21-22) from the energies E and the
    distribution pi over the candidates in `aux`, and dc/dtheta_c (`grad_mean`)."""
    # dE_j / dc = E_j (a_j - c) / sigma_e^2 (eq. 22)
    denergy_dc = energy * (aux.candidates - aux.mean_action) / (ctx.energy_width**2)
    # beta (dE_J - sum_j pi_j dE_j) written as beta sum_j pi_j (dE_J - dE_j) (sum_j pi_j = 1),
    # with the j = J term an exact 0, so that the score stays accurate relative to its own
    # size, O(1 - pi_J), when pi_J -> 1.
    selected = jnp.arange(aux.candidates.shape[0]) == aux.index
    denergy_gap = jnp.where(selected, 0.0, denergy_dc[aux.index] - denergy_dc)
    dlogpi_dc = ctx.inverse_temperature * (probs @ denergy_gap)
    return PolicyParams(
        controller=_scale_tree(grad_mean, dlogpi_dc), log_std=jnp.zeros_like(theta.log_std)
    )


def _gibbs_spread(candidates, probs):
    """Standard deviation of the discrete distribution pi over the candidates (about its own
    mean sum_j pi_j a_j, not about c(s))."""
    centre = probs @ candidates
    offsets = candidates - centre
    return jnp.sqrt(jnp.maximum(probs @ (offsets * offsets), 0.0))


def candidate_scores(gp, kernel, state, candidates, optimism: float = 0.0,
                     features=_PENDULUM_FEATURES):
    """The Gibbs candidates' scores before normalisation: Q_GP(s, a_j) (the paper), or with
    `optimism` kappa > 0 the optimistic Q_GP(s, a_j) + kappa sigma(s, a_j), sigma^2 the GP's
    latent variance (`gp_latent_variance`; design: docs/design.md#policies). kappa is static: 0
    computes no variance."""
    q = gp_means_over_actions(gp, kernel, state, candidates, features)
    if not optimism:
        return q
    variance = jax.vmap(lambda a: gp_latent_variance(gp, kernel, state, a, features))(candidates)
    return q + optimism * jnp.sqrt(jnp.maximum(variance, 0.0))


def gibbs_policy(controller: controllers_lib.Controller, num_candidates: int = 32,
                 features=_PENDULUM_FEATURES, optimism: float = 0.0) -> Policy:
    """Gibbs policy over K GP-scored candidate actions (eq. 20-22; design: docs/design.md#policies).

    Sampling: a_j ~ N(c(s), sigma^2_cand), j = 1..K; Q~_j = min-max normalised Q_GP(s, a_j)
    (with `optimism` kappa > 0: of Q_GP(s, a_j) + kappa sigma(s, a_j), `candidate_scores`);
    E_j = Q~_j exp(-(a_j - c)^2/(2 sigma_e^2)); pi = softmax(beta E); J ~ pi; action a_J.

    Score (eq. 21-22), with the candidates and Q~ held constant:
      d log pi_J/d theta_c = beta (dE_J - sum_j pi_j dE_j),
      dE_j = E_j (a_j - c)/sigma_e^2 dc/dtheta_c,
      d log pi_J/d log sigma = 0.
    `log_prob` is log pi_J = beta E_J - logsumexp(beta E) of the discrete distribution over the
    candidates in `aux`, with index J = aux.index; its `action` argument is not read (it is
    aux.candidates[aux.index] for an action drawn by `sample`). The density with which the
    candidates themselves were proposed is not part of this log-probability (as in the paper).

    The optimistic score changes which candidates are likely, not the estimator: the scores
    are held constant like Q~, so the score function is eq. 21-22 with the optimistic Q~.

    Args:
      controller: the deterministic controller c(s; theta_c).
      num_candidates: K (static).
      optimism: kappa >= 0 (static); 0, the paper: the candidates are scored by the GP's mean.
    """
    if num_candidates < 1:
        raise ValueError("num_candidates must be positive")
    if not (optimism >= 0 and math.isfinite(optimism)):
        raise ValueError(f"optimism must be finite and >= 0, got {optimism!r}")

    def draw(key, theta, state, ctx):
        """The candidates, their energies and the selection; also (E, dc/dtheta_c) for the score."""
        chex.assert_rank(state, 1)
        key_candidates, key_select = jax.random.split(key)
        mean_action, grad_mean = controllers_lib.mean_and_grad(controller, theta.controller, state)
        latent = gp_latent_variance(ctx.gp, ctx.kernel, state, mean_action, features)
        variance = _floored(ctx.candidate_scale * latent, ctx.candidate_floor)
        candidates = mean_action + jnp.sqrt(variance) * _random.normal(
            key_candidates, (num_candidates,), mean_action.dtype
        )
        normalised_q = normalise_q(candidate_scores(ctx.gp, ctx.kernel, state, candidates,
                                                    optimism, features))
        energy, probs = gibbs_distribution(candidates, normalised_q, mean_action, ctx)
        index = gibbs_select(key_select, energy, ctx.inverse_temperature)
        aux = PolicyAux(mean_action=mean_action, variance=variance, candidates=candidates,
                        normalised_q=normalised_q, probs=probs, index=index)
        return aux, energy, grad_mean

    def sample(key, theta, state, ctx):
        aux = draw(key, theta, state, ctx)[0]
        return aux.candidates[aux.index], aux

    def log_prob(theta, state, action, ctx, aux):
        del action
        mean_action = controller.apply(theta.controller, state)
        # Held constant with respect to theta (eq. 21-22); they are inputs here anyway.
        candidates = jax.lax.stop_gradient(aux.candidates)
        normalised_q = jax.lax.stop_gradient(aux.normalised_q)
        energy = gibbs_energy(candidates, normalised_q, mean_action, ctx.energy_width)
        # log pi_J = beta E_J - logsumexp(beta E) = -logsumexp(beta (E - E_J)): relative to the
        # selected candidate, so that when pi_J -> 1 neither the value nor its (forward-mode)
        # derivative is a difference of two nearly equal numbers. The J-th entry is set to an
        # exact 0 because XLA may recompute E_J in a fusion and differ from E[J] by an ulp.
        selected = jnp.arange(candidates.shape[0]) == aux.index
        relative_energy = jnp.where(selected, 0.0, energy - energy[aux.index])
        return -jax.nn.logsumexp(ctx.inverse_temperature * relative_energy)

    def grad_log_prob(theta, state, action, ctx, aux):
        del action
        chex.assert_rank(state, 1)
        mean_action, grad_mean = controllers_lib.mean_and_grad(controller, theta.controller, state)
        energy, probs = gibbs_distribution(aux.candidates, aux.normalised_q, mean_action, ctx)
        return _gibbs_score(theta, aux._replace(mean_action=mean_action), energy, probs, grad_mean,
                            ctx)

    def exploration_std(theta, state, ctx, aux):
        """`_gibbs_spread` of pi at the current theta."""
        mean_action = controller.apply(theta.controller, state)
        _, probs = gibbs_distribution(aux.candidates, aux.normalised_q, mean_action, ctx)
        return _gibbs_spread(aux.candidates, probs)

    def act(key, theta, state, ctx):
        aux, energy, grad_mean = draw(key, theta, state, ctx)
        return (aux.candidates[aux.index], aux,
                _gibbs_score(theta, aux, energy, aux.probs, grad_mean, ctx),
                _gibbs_spread(aux.candidates, aux.probs))

    return Policy(sample, log_prob, grad_log_prob, exploration_std, act, "gibbs")


POLICY_NAMES = ("fixed_noise", "guided_variance", "gibbs")

# Policies that other modules make (a planner that acts, `gpguided_jax.model_based.planner`), by
# name: `make(prog) -> Policy` from the `rollouts.Program` the policy acts in (its task,
# controller, hold and config; its `policy` not yet set).
_MADE_ELSEWHERE: dict[str, Callable[..., Policy]] = {}


def register(name: str, make: Callable[..., Policy]) -> None:
    """Makes the policy that `make(prog)` builds a roll-out policy by `name` (`Method.policy`)."""
    if name in POLICY_NAMES or name == "guided_direction":
        raise ValueError(f"the policy name {name!r} is taken by a built-in policy")
    _MADE_ELSEWHERE[name] = make


def made_elsewhere(name: str) -> Callable[..., Policy] | None:
    """The `make(prog)` registered under `name`, or None for a built-in policy's name."""
    return _MADE_ELSEWHERE.get(name)


def make_policy(
    name: str, controller: controllers_lib.Controller, *, num_candidates: int = 32,
    features=_PENDULUM_FEATURES, optimism: float = 0.0,
) -> Policy:
    """Looks a policy up by its static name.

    Args:
      name: 'fixed_noise' (eq. 1; the REINFORCE and gp_pg methods), 'guided_variance'
        (eq. 16-19) or 'gibbs' (eq. 20-22; alias 'guided_direction').
      controller: the deterministic controller.
      num_candidates: K for the Gibbs policy (static; ignored otherwise).
      optimism: kappa of the Gibbs policy's optimistic score (static; ignored otherwise).
      features: (state, action) -> the GP's input, the action last (`tasks.Task.features`; the
        default is the pendulum's (sin phi, cos phi, omega, a)).
    """
    if name == "fixed_noise":
        return fixed_noise_policy(controller)
    if name == "guided_variance":
        return guided_variance_policy(controller, features)
    if name in ("gibbs", "guided_direction"):
        return gibbs_policy(controller, num_candidates, features, optimism)
    raise ValueError(f"unknown policy {name!r}; choose from {POLICY_NAMES}")
