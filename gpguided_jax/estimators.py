"""Policy-gradient estimators over a batch of episodes (eq. 4, 9) and the ascent step
(design: docs/design.md#estimators).

Scores are the per-step hand-derived gradients grad_theta log pi(a_t | s_t) of
`gpguided_jax.policies`, stacked as a pytree whose leaves have leading (episodes, steps) axes,
e.g. `jax.vmap(jax.vmap(policy.grad_log_prob, in_axes=(None, 0, 0, None, 0)),
in_axes=(None, 0, 0, None, 0))(theta, s, a, ctx, aux)`.

  REINFORCE (eq. 4):   grad J = (1/N) sum_n sum_t score_{n,t} (Ret_{n,t} - b_{n,t})
  GP PG (eq. 9):       grad J = (1/N) sum_n sum_t score_{n,t} (Q_GP(s_{n,t}, a_{n,t}) - b_{n,t})

with N the number of episodes and the baseline b = 0 unless one is given (the paper has none).
The returns are the returns-to-go (`discounted_returns`), or, for gp_critic's GP, lambda-returns
bootstrapped with a critic's values (`lambda_returns`).
"""

from typing import Any

import chex
import jax
import jax.numpy as jnp
import optax

PyTree = Any


def discounted_returns(r_t: jax.Array, discount, ends: jax.Array | None = None) -> jax.Array:
    """Returns-to-go of one episode: Ret_t = sum_{i=0}^{H-1-t} gamma^i R_{t+i}.

    With `ends` ((H,) bool, True at the last step of an episode that ended and was restarted
    within the H steps), each return stops at its own episode's end: Ret_t = R_t +
    gamma (1 - ends_t) Ret_{t+1}.

    The sum stops at the end of the episode (no bootstrap). The paper prints the upper limit as
    H - t, one past the last reward of an episode indexed 0..H-1; the sum ends at H - 1 - t
    (design: docs/design.md#gp-model).

    Args:
      r_t: (H,) rewards R_0 .. R_{H-1}.
      discount: () gamma.
      ends: optional (H,) bool, the steps at which an episode ended (None: one episode).

    Returns:
      (H,) Ret_0 .. Ret_{H-1}.
    """
    chex.assert_rank(r_t, 1)
    discount = jnp.asarray(discount, r_t.dtype)
    if ends is None:
        def backward(ret_tp1, r):
            ret = r + discount * ret_tp1
            return ret, ret

        _, returns = jax.lax.scan(backward, jnp.zeros((), r_t.dtype), r_t, reverse=True)
        return returns

    def backward_to_end(ret_tp1, r_and_end):
        r, end = r_and_end
        ret = r + jnp.where(end, jnp.zeros_like(ret_tp1), discount * ret_tp1)
        return ret, ret

    _, returns = jax.lax.scan(backward_to_end, jnp.zeros((), r_t.dtype), (r_t, ends),
                              reverse=True)
    return returns


def policy_gradient(scores: PyTree, weights: jax.Array, baseline: jax.Array | None = None):
    """(1/N) sum_n sum_t score_{n,t} (weights_{n,t} - baseline_{n,t}): eq. 3 by sample averages.

    Args:
      scores: pytree whose leaves have shape (N, H, ...), the per-step scores.
      weights: (N, H) the per-step value estimates (returns-to-go or Q_GP).
      baseline: optional (N, H) baseline subtracted from the weights; None (default) for none.

    Returns:
      A pytree with the structure of one score (leading axes summed/averaged out).
    """
    chex.assert_rank(weights, 2)
    if baseline is not None:
        chex.assert_equal_shape([weights, baseline])
        weights = weights - baseline
    num_episodes = weights.shape[0]

    def contract(leaf):
        chex.assert_tree_shape_prefix(leaf, weights.shape)
        return jnp.tensordot(weights, leaf, axes=([0, 1], [0, 1])) / num_episodes

    return jax.tree_util.tree_map(contract, scores)


def reinforce_gradient(
    scores: PyTree, rewards: jax.Array, discount, baseline: jax.Array | None = None
):
    """REINFORCE estimate of grad J (eq. 4) with discounted returns-to-go.

    Args:
      scores: pytree with leaves (N, H, ...), grad_theta log pi(a_t | s_t) per step.
      rewards: (N, H) rewards R_t.
      discount: () gamma.
      baseline: optional (N, H) baseline (off by default, as in the paper).
    """
    chex.assert_rank(rewards, 2)
    returns = jax.vmap(discounted_returns, in_axes=(0, None))(rewards, discount)
    return policy_gradient(scores, returns, baseline)


def gp_policy_gradient(scores: PyTree, q_values: jax.Array, baseline: jax.Array | None = None):
    """GP policy gradient (eq. 9): Q_GP(s_t, a_t) in place of the return.

    Args:
      scores: pytree with leaves (N, H, ...).
      q_values: (N, H) GP predictive means Q_GP(s_t, a_t), evaluated after the GP has taken in
        the episodes (Algorithm 1).
      baseline: optional (N, H) baseline, e.g. V(s_t) = Q_GP(s_t, c(s_t)) (off by default).
    """
    return policy_gradient(scores, q_values, baseline)


def ascent_step(
    optimizer: optax.GradientTransformation, params: PyTree, opt_state, gradient: PyTree
):
    """theta <- theta + update(grad J): one ascent step through an optax optimiser.

    optax minimises, so the optimiser is fed -grad J; with `optax.sgd(eta)` this is exactly
    theta + eta grad J (the paper's update).

    Returns:
      (new_params, new_opt_state).
    """
    negated = jax.tree_util.tree_map(jnp.negative, gradient)
    updates, opt_state = optimizer.update(negated, opt_state, params)
    return optax.apply_updates(params, updates), opt_state


def lambda_returns(rewards, q_next, cut, discount, lam):
    """lambda-returns of one episode, bootstrapped with a critic's values (gp_critic's targets):

      G_t = r_t + gamma (1 - cut_t) [(1 - lambda) q_t + lambda G_{t+1}],   G_H = q_{H-1},

    with q_t the critic's value of the step after t and cut_t whether the transition at t ends
    the episode (nothing is bootstrapped past an end). lambda = 1 gives the returns-to-go with
    the critic's value where the episode is cut at its length; lambda = 0 the one-step targets
    r_t + gamma q_t.

    Args:
      rewards, q_next: (H,).
      cut: (H,) bool.
      discount, lam: () gamma and lambda.
    """
    dtype = rewards.dtype
    discount, lam = jnp.asarray(discount, dtype), jnp.asarray(lam, dtype)

    def backward(g_next, x):
        r, q, c = x
        g = r + discount * (1.0 - c) * ((1.0 - lam) * q + lam * g_next)
        return g, g

    _, g = jax.lax.scan(backward, q_next[-1], (rewards, q_next, cut.astype(dtype)), reverse=True)
    return g
