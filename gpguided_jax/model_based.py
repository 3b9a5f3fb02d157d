"""gp_model: the GP as a model of the task, the controller optimised through simulated roll-outs
(design: docs/design.md#model).

Where the paper's GP models Q(s, a), this method's GPs model the task's dynamics, as PILCO
(Deisenroth & Rasmussen 2011) and its particle successors (PIPPS, MC-PILCO) do. Each update of
Algorithm 1's loop (steps 1-2 roll out the episodes with the current controller and the
exploration noise, as for every method) then does three things:

1. **The model takes the transitions in.** One GP per coordinate e of the normalised observation z
   models its change, Delta z_e = z'_e - z_e (an angle's change taken modulo one turn), on the
   input (z, a) (`Task.features`). The transitions go into a fixed-size ring buffer of
   `model_capacity` (`ModelData`), with a mask for the slots not yet written and for the steps
   after an episode's end.
2. **The hyperparameters are refitted** by exact marginal likelihood (`hyperfit`), one kernel per
   coordinate, on a random subset of `model_fit_subset` buffered transitions, `model_fit_steps`
   Adam steps warm-started from the previous update's kernels.
3. **The controller is optimised through the model**: `model_steps` Adam steps on the mean return
   of `model_particles` simulated roll-outs of `model_horizon` seconds from the task's own start
   distribution (`Task.reset`), with the task's reward and its end where it has one
   (`Task.end_fn`). The gradient is the reparameterised one through the roll-outs (autodiff), with
   common random numbers: the particles' start states and the model's samples are drawn once per
   update.

The reward (`model_reward`) is the task's own statement as a function of the transition
(`Task.reward_fn`), or, for a task that does not state it, learnt: one more GP output on the same
input (z, a), whose target is the reward of a decision (its control steps' rewards summed), in the
same buffer, refit and conditioning as the dynamics' outputs. The simulated roll-outs then read a
decision's reward from that output (its mean, or the particle's drawn function under 'sample' and
'thompson'; no transition noise, whose mean is 0).

The model is the sparse GP of Titsias (2009) / DTC with `model_inducing` inducing inputs Z chosen
from the buffered inputs by farthest-point sampling in the kernel's length-scales, conditioned on
every buffered transition (`condition`); with Z the whole data it is the exact GP (tests compare
it with a Cholesky GP). Its posterior over the inducing values, in whitened coordinates v =
L^-1 u (L L^T = K_ZZ), is N(m, B^-1) with B = I + A A^T, A = L^-1 K_ZX / sigma_n, m = B^-1 A y /
sigma_n. A function drawn from it is f(x) = k(x, Z) L^-T v: smooth, and as cheap to evaluate as
the mean.

The GP's uncertainty guides exploration through the simulated roll-outs, one choice of
`model_exploration`:

  mean        every particle follows the posterior mean (the greedy, certainty-equivalent model);
  sample      each particle follows its own function drawn from the posterior, plus the learnt
              transition noise (uncertainty propagated through the roll-outs by sampling, as
              PILCO's moment matching propagates it analytically);
  thompson    one function drawn per update, followed by every particle (posterior sampling);
  optimistic  H-UCRL's hallucinated control (Curi et al. 2020): the next state is mu(x) +
              beta sigma(x) eta(z), eta in [-1, 1]^E a second controller optimised jointly with
              the policy to maximise the same return (optimism within the model's confidence).

With `hold_time` > 0 the model is of one decision of `prog.hold` control steps (`decisions`), and
the simulated roll-outs step one decision at a time (`simulate`).

The controller acts deterministically in the simulated roll-outs. In the real ones it acts with
the policy's Gaussian noise: exp(init_log_std) on the first update (the exploratory episode that
gives the model its first data), the floor `min_std` from then on.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from gpguided_jax import config, hyperfit, kernels, methods

EXPLORATIONS = config.MODEL_EXPLORATIONS
OPTIMIZERS = config.MODEL_OPTIMIZERS
JITTER = 1e-6  # relative diagonal jitter of K_ZZ (at least `jitter_floor`)
RECORDS = ("model_return", "model_gain", "model_error", "model_reward_error", "model_std",
           "model_lengthscale_action", "model_data")


class ModelData(NamedTuple):
    """The transitions the model is conditioned on, in a ring buffer of C slots.

    Attributes:
      inputs: (C, D) GP inputs (z, a).
      targets: (C, E) changes of the normalised observation (and, for a learnt reward, a last
        column: the decision's reward).
      valid: (C,) bool, the slots that hold a transition before its episode's end.
      count: () int32, transitions written so far (the next slot is count mod C).
      log_kernels: `hyperfit.LogParams` with a leading (E,) axis (one per column of `targets`): the
        current kernels, in logs.
      hallucination: (obs_dim,) controller parameters of the optimistic exploration's eta (zeros
        for the other choices).
    """

    inputs: jax.Array
    targets: jax.Array
    valid: jax.Array
    count: jax.Array
    log_kernels: hyperfit.LogParams
    hallucination: object


class SparseModel(NamedTuple):
    """The GP model conditioned on the data (`condition`), one GP per output e (leading (E,) axis).

    Attributes:
      inducing: (M, D) inducing inputs Z (shared by the outputs).
      inducing_mask: (M,) bool, the inducing inputs in use (fewer than M distinct data).
      kernels: `KernelParams` with leading (E,).
      chol_zz: (E, M, M) L, L L^T = K_ZZ (+ jitter; identity rows for unused inducing inputs).
      chol_b: (E, M, M) L_B, L_B L_B^T = B.
      mean_v: (E, M) m, the whitened posterior mean of the inducing values.
      weights: (E, M) L^-T m: the mean is mu_e(x) = k_e(x, Z) . weights_e.
    """

    inducing: jax.Array
    inducing_mask: jax.Array
    kernels: kernels.KernelParams
    chol_zz: jax.Array
    chol_b: jax.Array
    mean_v: jax.Array
    weights: jax.Array


# ------------------------------------------------------------------------------------------------
# Transitions: the GP's inputs and targets, and the buffer.
# ------------------------------------------------------------------------------------------------


def wrap(x):
    """An angle difference wrapped to [-pi, pi)."""
    return jnp.mod(x + jnp.pi, 2.0 * jnp.pi) - jnp.pi


def targets_of(task, obs, next_obs):
    """Delta z = (next_obs - obs) / scale, the angles' differences wrapped to [-pi, pi)."""
    d = next_obs - obs
    if task.angles:
        idx = jnp.asarray(task.angles)
        d = d.at[..., idx].set(wrap(d[..., idx]))
    return d / jnp.asarray(task.obs_scale, obs.dtype)


def next_of(task, obs, delta):
    """The observation after a change Delta z (the inverse of `targets_of`): angles wrapped the
    way the task wraps them ([0, 2 pi) for the paper's pendulum)."""
    nxt = obs + delta * jnp.asarray(task.obs_scale, obs.dtype)
    if task.angles:
        idx = jnp.asarray(task.angles)
        nxt = nxt.at[..., idx].set(jnp.mod(nxt[..., idx], 2.0 * jnp.pi))
    return nxt


def learns_reward(task, static) -> bool:
    """Whether gp_model learns the task's reward (`TrainConfig.model_reward`): asked to, or 'auto'
    for a task that does not state it."""
    return static.model_reward == "learned" or (static.model_reward == "auto"
                                                 and task.reward_fn is None)


def decision_rewards(hold: int, rewards):
    """(N, T) rewards summed over each decision of `hold` control steps: (N, T // hold) (a last,
    incomplete hold dropped, as `decisions` drops it)."""
    n, t = rewards.shape
    k = t // hold
    return jnp.sum(rewards[:, : k * hold].reshape(n, k, hold), axis=-1)


def stated_reward(task, hold: int, obs, action, nxt, end=None):
    """A decision's reward from the task's statement (`Task.reward_fn`): `hold` times the reward of
    the transition to the decision's end, of which only the last control step can end the episode
    (an end's bonus counts once). `end`: the end's indicator or probability (None: a task that
    never ends early)."""
    if end is None:
        return hold * task.reward_fn(obs, action, nxt)
    r = task.reward_fn(obs, action, nxt, end)
    if hold > 1:  # the hold's other steps do not end it
        r = r + (hold - 1) * task.reward_fn(obs, action, nxt, jnp.zeros_like(end))
    return r


def empty_data(capacity: int, input_dim: int, output_dim: int, dtype, hallucination) -> ModelData:
    log_k = hyperfit.LogParams(jnp.zeros((output_dim, input_dim), dtype),
                               jnp.zeros((output_dim,), dtype), jnp.full((output_dim,), -4.0, dtype))
    return ModelData(jnp.zeros((capacity, input_dim), dtype), jnp.zeros((capacity, output_dim), dtype),
                     jnp.zeros((capacity,), bool), jnp.zeros((), jnp.int32), log_k, hallucination)


def take_in(data: ModelData, inputs, targets, valid) -> ModelData:
    """Writes (n, D) inputs, (n, E) targets and (n,) valid flags into the ring buffer (the oldest
    slots first once it is full)."""
    capacity = data.inputs.shape[0]
    slots = (data.count + jnp.arange(inputs.shape[0])) % capacity
    return data._replace(inputs=data.inputs.at[slots].set(inputs),
                         targets=data.targets.at[slots].set(targets),
                         valid=data.valid.at[slots].set(valid),
                         count=data.count + inputs.shape[0])


# ------------------------------------------------------------------------------------------------
# The hyperparameters and the sparse GP.
# ------------------------------------------------------------------------------------------------


def subset(key, valid, n: int):
    """n indices of valid slots, without repetition while there are n of them (then with)."""
    p = valid.astype(jnp.float32)
    enough = jnp.sum(p) >= n
    scores = jnp.where(valid, jax.random.uniform(key, valid.shape), -1.0)
    without = jnp.argsort(-scores)[:n]
    with_ = jax.random.choice(key, valid.shape[0], (n,), replace=True, p=p / jnp.maximum(jnp.sum(p), 1.0))
    return jnp.where(enough, without, with_)


def refit(key, data: ModelData, *, subset_size: int, num_steps: int, first) -> hyperfit.LogParams:
    """The kernels refitted on a random subset of the buffer, one per output: from the data-driven
    guess on the first update (`first`), warm-started from the current kernels after it."""
    idx = subset(key, data.valid, min(subset_size, data.valid.shape[0]))
    xs, ys = data.inputs[idx], data.targets[idx]

    def one(y, log_k):
        ys_c = y - jnp.mean(y)
        guess = hyperfit.to_log(hyperfit.initial_guess(xs, ys_c))
        start = jax.tree_util.tree_map(lambda g, k: jnp.where(first, g, k), guess, log_k)
        return hyperfit.to_log(hyperfit.fit(xs, ys_c, num_steps=num_steps, optimizer="adam",
                                            init=hyperfit.from_log(start)).params)

    return jax.vmap(one, in_axes=(1, 0))(ys, data.log_kernels)


def farthest_points(xs, valid, lengthscales, m: int):
    """m of the valid rows of xs chosen greedily, each the farthest (in the length-scales) from
    those chosen before, the first the first valid row. Returns (m, D) and a (m,) mask, False for
    a choice that repeats an earlier one (fewer than m distinct valid rows) or with no valid row."""
    scaled = xs / lengthscales
    first = jnp.argmax(valid)
    dist0 = jnp.where(valid, jnp.sum((scaled - scaled[first]) ** 2, axis=-1), -1.0)

    def body(dist, _):
        j = jnp.argmax(dist)
        new = dist[j] > 1e-12
        d = jnp.sum((scaled - scaled[j]) ** 2, axis=-1)
        return jnp.where(valid, jnp.minimum(dist, d), -1.0), (j, new)

    _, (idx, new) = jax.lax.scan(body, dist0, None, length=m - 1)
    idx = jnp.concatenate([first[None], idx])
    mask = jnp.concatenate([jnp.any(valid)[None], new])
    return xs[idx], mask


def jitter_floor(dtype, m: int) -> float:
    """The least relative jitter with which K_ZZ + jitter sigma_f^2 I of m inducing inputs has a
    Cholesky factor in `dtype` however close the inputs are (in the length-scales): 4 m eps.
    Measured in float32 on inputs whose kernel matrix is nearly sigma_f^2 11^T (length-scales
    10-10^4 times the inputs' spread), the factorisation fails below about m eps / 2 (m = 100-400);
    in float64 the floor is far below `JITTER`."""
    return 4.0 * m * float(jnp.finfo(dtype).eps)


def condition(inducing, inducing_mask, kern: kernels.KernelParams, xs, ys, valid, *,
              jitter: float = JITTER) -> SparseModel:
    """The sparse GP of one output conditioned on (xs, ys) where `valid` (module notes); vmap over
    outputs. ys is the (N,) target, its prior mean 0; `jitter` is relative to sigma_f^2 (raised
    to `jitter_floor`).

    B = I + A A^T has condition number up to 1 + N sigma_f^2 / sigma_n^2: with a task's nearly
    deterministic transitions that is past float32's resolution, and its Cholesky factor fails.
    In float32 L_B is therefore the triangular factor of the QR decomposition of [I; A^T]
    (R^T R = B, without forming B); float64 resolves B and factors it directly."""
    m = inducing.shape[0]
    dtype = xs.dtype
    jitter = max(jitter, jitter_floor(dtype, m))
    pair = inducing_mask[:, None] & inducing_mask[None, :]
    kzz = kernels.gram(inducing, inducing, kern)
    kzz = jnp.where(pair, kzz, jnp.eye(m, dtype=dtype))
    kzz = kzz + jitter * kern.signal_variance * jnp.eye(m, dtype=dtype)
    chol = jnp.linalg.cholesky(kzz)
    kzx = kernels.gram(inducing, xs, kern)
    kzx = jnp.where(inducing_mask[:, None] & valid[None, :], kzx, 0.0)
    sn = jnp.sqrt(kern.noise_variance)
    a = jax.scipy.linalg.solve_triangular(chol, kzx, lower=True) / sn
    if dtype == jnp.float64:
        chol_b = jnp.linalg.cholesky(jnp.eye(m, dtype=dtype) + a @ a.T)
    else:
        r = jnp.linalg.qr(jnp.concatenate([jnp.eye(m, dtype=dtype), a.T]), mode="r")
        chol_b = (r * jnp.where(jnp.diagonal(r) < 0, -1.0, 1.0).astype(dtype)[:, None]).T
    c = jax.scipy.linalg.solve_triangular(chol_b, a @ jnp.where(valid, ys, 0.0), lower=True) / sn
    mean_v = jax.scipy.linalg.solve_triangular(chol_b.T, c, lower=False)
    weights = jax.scipy.linalg.solve_triangular(chol.T, mean_v, lower=False)
    return SparseModel(inducing, inducing_mask, kern, chol, chol_b, mean_v, weights)


def build(data: ModelData, num_inducing: int) -> tuple[SparseModel, jax.Array]:
    """The model of every output conditioned on the buffer, and the outputs' data means (the
    GPs model the centred targets)."""
    kern = jax.vmap(hyperfit.from_log)(data.log_kernels)
    ls = jnp.exp(jnp.mean(jnp.log(kern.lengthscales), axis=0))
    z, zmask = farthest_points(data.inputs, data.valid, ls, num_inducing)
    w = data.valid.astype(data.targets.dtype)
    mean = jnp.sum(data.targets * w[:, None], axis=0) / jnp.maximum(jnp.sum(w), 1.0)
    model = jax.vmap(condition, in_axes=(None, None, 0, None, 1, None))(
        z, zmask, kern, data.inputs, data.targets - mean, data.valid)
    return model._replace(inducing=z, inducing_mask=zmask), mean


def _k_star(model: SparseModel, x):
    """(E, M) k_e(x, Z), 0 for unused inducing inputs."""
    def one(kern):
        k = kernels.cross_covariance(model.inducing, x, kern)
        return jnp.where(model.inducing_mask, k, 0.0)
    return jax.vmap(one)(model.kernels)


def _variance(model: SparseModel, ks):
    """The latent predictive variance of every output, (E,), from its kernel row ks (E, M)."""
    def var(k, chol, chol_b, kern):
        p = jax.scipy.linalg.solve_triangular(chol, k, lower=True)
        q = jax.scipy.linalg.solve_triangular(chol_b, p, lower=True)
        return kern.signal_variance - jnp.sum(p * p) + jnp.sum(q * q)

    v = jax.vmap(var)(ks, model.chol_zz, model.chol_b, model.kernels)
    return jnp.maximum(v, 0.0)


def variance_factors(model: SparseModel):
    """(L^-1, L_B^-1 L^-1), (E, M, M) each: with them the latent variance at x is
    sf^2 - |L^-1 k|^2 + |L_B^-1 L^-1 k|^2 by two matrix-vector products (`fast_variance`), where
    `_variance` solves two triangular systems; for the simulated roll-outs, which evaluate it at
    every step of every particle with the model fixed."""
    def one(chol, chol_b):
        eye = jnp.eye(chol.shape[0], dtype=chol.dtype)
        inv_l = jax.scipy.linalg.solve_triangular(chol, eye, lower=True)
        return inv_l, jax.scipy.linalg.solve_triangular(chol_b, inv_l, lower=True)
    return jax.vmap(one)(model.chol_zz, model.chol_b)


def fast_variance(model: SparseModel, factors, ks):
    """`_variance` from `variance_factors`: the latent predictive variance of every output, (E,)."""
    inv_l, inv_bl = factors
    p = jnp.einsum("emn,en->em", inv_l, ks)
    q = jnp.einsum("emn,en->em", inv_bl, ks)
    v = model.kernels.signal_variance - jnp.sum(p * p, axis=-1) + jnp.sum(q * q, axis=-1)
    return jnp.maximum(v, 0.0)


def predict(model: SparseModel, x):
    """The latent predictive mean and variance of every output at one input x: (E,), (E,)."""
    ks = _k_star(model, x)
    return jnp.sum(ks * model.weights, axis=-1), _variance(model, ks)


def sample_weights(model: SparseModel, key, shape=()):
    """Weights of functions drawn from the posterior, shape + (E, M): f(x) = k(x, Z) . w with
    w = L^-T (m + L_B^-T eps)."""
    eps = jax.random.normal(key, shape + model.mean_v.shape, model.mean_v.dtype)

    def one(e):
        def out(eps_e, chol, chol_b, m):
            v = m + jax.scipy.linalg.solve_triangular(chol_b.T, eps_e, lower=False)
            return jax.scipy.linalg.solve_triangular(chol.T, v, lower=False)
        return jax.vmap(out)(e, model.chol_zz, model.chol_b, model.mean_v)

    flat = eps.reshape((-1,) + model.mean_v.shape)
    return jax.vmap(one)(flat).reshape(shape + model.mean_v.shape)


# ------------------------------------------------------------------------------------------------
# Simulated roll-outs and the controller's optimisation.
# ------------------------------------------------------------------------------------------------


class Plan(NamedTuple):
    """What one update's simulated roll-outs hold fixed (common random numbers).

    Attributes:
      start: (P, obs_dim) the particles' start observations.
      weights: (P, E, M) each particle's function (the mean's weights for 'mean' and
        'optimistic', one draw for all under 'thompson').
      noise: (P, T, E) standard normals of the transition noise ('sample'; zeros otherwise).
      variance: `variance_factors` of the model ('optimistic'; None otherwise).
    """

    start: jax.Array
    weights: jax.Array
    noise: jax.Array
    variance: tuple | None = None


def make_plan(prog, cfg, model: SparseModel, key, exploration: str, num_particles: int,
              num_steps: int) -> Plan:
    task = prog.task
    k_start, k_w, k_n = jax.random.split(key, 3)
    start = jax.vmap(lambda k: task.reset(k, cfg)[1])(jax.random.split(k_start, num_particles))
    e, m = model.weights.shape
    if exploration == "sample":
        weights = sample_weights(model, k_w, (num_particles,))
        noise = jax.random.normal(k_n, (num_particles, num_steps, e), model.weights.dtype)
    else:
        if exploration == "thompson":
            one = sample_weights(model, k_w)
        else:
            one = model.weights
        weights = jnp.broadcast_to(one, (num_particles, e, m))
        noise = jnp.zeros((num_particles, num_steps, e), model.weights.dtype)
    factors = variance_factors(model) if exploration == "optimistic" else None
    return Plan(start, weights, noise, factors)


def simulate(prog, model: SparseModel, target_mean, plan: Plan, controller_params,
             hallucination=None, beta=None, end_softness=0.1):
    """The mean over particles of the simulated returns: undiscounted sums of the task's reward
    over the plan's steps, each weighed by the particle's probability of being alive. A model step
    is one decision of k = `prog.hold` control steps, whose steps in between are not simulated:
    its reward is the learnt reward's output (`learns_reward`), or `stated_reward`. A task
    with an end margin (`Task.end_margin`) ends a step with probability sigmoid(margin /
    `end_softness`), a smoothed end whose gradient reaches the controller where the hard end's
    is 0 (its reward, where the end enters it, takes that probability too); a task with only
    `end_fn` ends hard. `hallucination`: eta's controller parameters, (E,)-batched (the
    optimistic choice)."""
    task, controller = prog.task, prog.controller
    if hallucination is not None and plan.variance is None:
        raise ValueError("an optimistic roll-out reads the model's variance factors: make its plan "
                         "with exploration 'optimistic'")
    noise_std = jnp.sqrt(model.kernels.noise_variance)  # (E,)
    hold, e = prog.hold, task.obs_dim
    learned = learns_reward(task, prog.config)

    def end_probability(nxt):
        if task.end_margin is not None:
            return jax.nn.sigmoid(task.end_margin(nxt) / end_softness)
        return task.end_fn(nxt).astype(nxt.dtype)

    def particle(obs0, w, eps):
        def step(carry, eps_t):
            obs, alive = carry
            a = controller.apply(controller_params, obs)
            x = task.features(obs, a)
            ks = _k_star(model, x)
            out = jnp.sum(ks * w, axis=-1) + target_mean
            delta = out[:e] + noise_std[:e] * eps_t[:e]
            if hallucination is not None:
                var = fast_variance(model, plan.variance, ks)[:e]
                eta = jax.vmap(lambda p: controller.apply(p, obs))(hallucination) / controller.u_max
                delta = delta + beta * jnp.sqrt(var) * eta
            nxt = next_of(task, obs, delta)
            p_end = None if task.end_fn is None else end_probability(nxt)
            r = out[e] if learned else stated_reward(task, hold, obs, a, nxt, p_end)
            if p_end is None:
                return (nxt, alive), r
            return (nxt, alive * (1.0 - p_end)), alive * r

        _, rewards = jax.lax.scan(step, (obs0, jnp.ones((), obs0.dtype)), eps)
        return jnp.sum(rewards)

    return jnp.mean(jax.vmap(particle)(plan.start, plan.weights, plan.noise))


def optimise(prog, model, target_mean, plan, params, hallucination, *, num_steps: int,
             learning_rate, beta, optimistic: bool, optimizer: str = "adam", end_softness=0.1):
    """`num_steps` steps of `optimizer` on the simulated return from `params` (and eta's
    parameters, under optimism): 'adam' (step size `learning_rate`, the gradient clipped to norm
    1e3), or 'lbfgs' (optax's L-BFGS with its zoom line search; the plan's common random numbers
    make the objective deterministic). A step whose value or gradient is not finite is not taken.
    Returns (params, hallucination, return before, return after)."""
    def objective(p):
        c, h = p
        return -simulate(prog, model, target_mean, plan, c, h if optimistic else None, beta,
                         end_softness)

    value_and_grad = jax.value_and_grad(objective)
    p0 = (params, hallucination)
    if optimizer == "lbfgs":
        opt = optax.lbfgs()
    else:
        opt = optax.chain(optax.clip_by_global_norm(1e3), optax.adam(learning_rate))

    def step(carry, _):
        p, opt_state = carry
        value, g = value_and_grad(p)
        if optimizer == "lbfgs":
            updates, new_state = opt.update(g, opt_state, p, value=value, grad=g,
                                            value_fn=objective)
        else:
            updates, new_state = opt.update(g, opt_state, p)
        new_p = optax.apply_updates(p, updates)
        ok = jnp.isfinite(value) & jnp.all(jnp.stack(
            [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves((g, new_p))]))
        keep = lambda a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(ok, x, y), a, b)  # noqa: E731
        return (keep(new_p, p), keep(new_state, opt_state)), value

    (p, _), values = jax.lax.scan(step, (p0, opt.init(p0)), None, length=num_steps)
    return p[0], p[1], -values[0], -objective(p)


# ------------------------------------------------------------------------------------------------
# The method.
# ------------------------------------------------------------------------------------------------


def plan_steps(prog, cfg) -> int:
    """The simulated roll-outs' steps: `model_horizon` seconds in decisions of `prog.hold` control
    intervals."""
    dt = config.control_interval(prog.config) * prog.hold
    return max(1, int(round(prog.config.model_horizon / dt)))


def decisions(hold: int, obs, next_obs, actions, alive=None, ends=None):
    """The transitions the model takes in from a batch of episodes (N, T, ...): one per decision
    of `hold` control steps, from the observation the action was chosen in to the one at the end
    of its hold (a last, incomplete hold is dropped). Returns (obs, next_obs, actions, valid),
    `valid` (N, T // hold) False for a decision not taken wholly before its episode's end, or
    (restarted episodes, `ends`) one across an end, whose next observation is another episode's."""
    n, t = actions.shape[:2]
    k = t // hold
    valid = jnp.ones((n, t), bool) if alive is None else alive
    if ends is not None:  # a restarted episode's last step leads to the next one's start
        valid = valid & ~ends
    if hold == 1:
        return obs, next_obs, actions, valid
    first = lambda v: v[:, : k * hold: hold]  # noqa: E731
    blocks = lambda v: v[:, : k * hold].reshape((n, k, hold) + v.shape[2:])  # noqa: E731
    return (first(obs), blocks(next_obs)[:, :, -1], first(actions),
            jnp.all(blocks(valid), axis=2))


def _relative_error(pred, target, valid):
    """sum (pred - target)^2 / sum target^2 over the valid rows (1 - R^2 about 0)."""
    w = valid.reshape(valid.shape + (1,) * (target.ndim - 1))
    err = jnp.sum((pred - target) ** 2 * w)
    return err / jnp.maximum(jnp.sum(target ** 2 * w), jnp.finfo(target.dtype).tiny)


def init(prog, key, cfg):
    del key
    task, static = prog.task, prog.config
    capacity = min(static.model_capacity, static.num_updates * static.episodes_per_update
                   * (static.episode_length // prog.hold))
    zeros = prog.controller.init(prog.dtype)
    hallucination = jax.tree_util.tree_map(lambda a: jnp.zeros((task.obs_dim,) + a.shape, a.dtype), zeros)
    outputs = task.obs_dim + learns_reward(task, static)
    return empty_data(capacity, task.feature_dim, outputs, prog.dtype, hallucination)


def update(prog, cfg, state, batch):
    """Steps 3-4 of gp_model: take in, refit, condition, optimise (module notes)."""
    from gpguided_jax import rollouts

    static, task = prog.config, prog.task
    data: ModelData = state.method_state
    eps = batch.episodes
    obs, nxt, acts = eps.states, eps.next_states, eps.actions
    obs, nxt, acts, valid = decisions(prog.hold, obs, nxt, acts, eps.alive, eps.ends)
    d, e = task.feature_dim, task.obs_dim
    xs = jax.vmap(lambda s, a: rollouts.features(prog, s, a))(obs, acts).reshape(-1, d)
    ys = targets_of(task, obs, nxt).reshape(-1, e)
    rewards = decision_rewards(prog.hold, eps.rewards).reshape(-1)
    valid = valid.reshape(-1)
    learned = learns_reward(task, static)
    if learned:
        ys = jnp.concatenate([ys, rewards[:, None]], axis=1)
    key = jax.random.fold_in(state.key, 7)
    k_fit, k_plan, _ = jax.random.split(key, 3)

    # the model's error on this update's transitions before it takes them in (data it has not
    # seen; 1 on the first update, whose model is the prior: its prediction is 0), and the reward's
    # (the learnt one's before it takes them in, or the stated one's)
    first = data.count == 0
    model_old, mean_old = build(data, static.model_inducing)
    pred = jax.vmap(lambda x: predict(model_old, x)[0])(xs) + mean_old
    model_error = _relative_error(pred[:, :e], ys[:, :e], valid)
    if learned:
        reward_pred = pred[:, e]
    else:
        flat = lambda v: v.reshape((-1,) + v.shape[2:])  # noqa: E731
        o, a, n = flat(obs), flat(acts), flat(nxt)
        end = None if task.end_fn is None else jax.vmap(task.end_fn)(n).astype(o.dtype)
        reward_pred = jax.vmap(functools.partial(stated_reward, task, prog.hold))(o, a, n, end)
    model_reward_error = _relative_error(reward_pred, rewards, valid)

    data = take_in(data, xs, ys, valid)
    data = data._replace(log_kernels=refit(k_fit, data, subset_size=static.model_fit_subset,
                                           num_steps=static.model_fit_steps, first=first))
    model, target_mean = build(data, static.model_inducing)
    steps = plan_steps(prog, cfg)
    plan = make_plan(prog, cfg, model, k_plan, static.model_exploration, static.model_particles, steps)
    optimistic = static.model_exploration == "optimistic"
    params, halluc, before, after = optimise(
        prog, model, target_mean, plan, state.theta.controller, data.hallucination,
        num_steps=static.model_steps, learning_rate=cfg.model_learning_rate, beta=cfg.model_beta,
        optimistic=optimistic, optimizer=static.model_optimizer,
        end_softness=cfg.model_end_softness)
    data = data._replace(hallucination=halluc)
    theta = state.theta._replace(controller=params,
                                 log_std=jnp.log(jnp.asarray(cfg.min_std, prog.dtype)))
    kern = jax.vmap(hyperfit.from_log)(data.log_kernels)
    records = dict(
        model_return=after,
        model_gain=after - before,
        model_error=model_error,
        model_reward_error=model_reward_error,
        model_std=jnp.mean(jnp.sqrt(kern.noise_variance[:e])),
        model_lengthscale_action=jnp.exp(jnp.mean(jnp.log(kern.lengthscales[:e, -1]))),
        model_data=jnp.sum(data.valid).astype(prog.dtype),
    )
    return theta, state.opt_state, data, {k: jnp.asarray(v, prog.dtype) for k, v in records.items()}


def check(cfg) -> None:
    from gpguided_jax import exploration, tasks

    task = tasks.make_task(cfg.env)
    if task.reward_fn is None and cfg.model_reward == "stated":
        raise ValueError(f"TrainConfig.model_reward: 'stated' plans with the task's reward as a "
                         f"function of the transition, which {cfg.env} does not state "
                         f"(tasks.Task.reward_fn); 'learned' or 'auto' learns it")
    hold = exploration.hold_steps(cfg.hold_time, config.control_interval(cfg))
    if hold > cfg.episode_length:
        raise ValueError(f"TrainConfig.hold_time: a hold of {hold} control steps is longer than "
                         f"the episode ({cfg.episode_length}); gp_model models one decision")


methods.register(methods.Method(
    name="gp_model", policy="fixed_noise", prior="none", init=init, update=update, records=RECORDS,
    explorations=("white", "ou", "coloured"), compare_with=("reinforce", "gp_pg"), check=check,
    explain_exploration="'parameter' noise changes the controller the model optimises",
    eval_held=True))
