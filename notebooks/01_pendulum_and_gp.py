# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 01 · The pendulum and the sparse GP model of Q
#
# The task of Jakab & Csató (IJCNN 2012, §VI): a torque-limited pendulum at 200 Hz, and a sparse
# online Gaussian process (Csató–Opper) that models the action value Q(s, a) from discounted
# returns-to-go. This notebook
#
# 1. simulates the pendulum (eq. 23–24),
# 2. collects (state–action, return) pairs with the initial policy, as the paper does before learning,
# 3. fits the kernel hyperparameters by maximising the exact marginal likelihood,
# 4. feeds the pairs to the sparse GP and compares its predictions of Q with the exact GP's,
# 5. watches the basis-vector (BV) set change over policy updates: every BV carries the index of
#    the update that added it (eq. 12), and the age penalty λ·g(t) of eq. 13–15 decides which
#    ones are exchanged.
#
# `QUICK` (set `GPGUIDED_NOTEBOOK_QUICK=1`) shrinks every size so the tests can run it in seconds.

# %%
import os

QUICK = os.environ.get("GPGUIDED_NOTEBOOK_QUICK") == "1"

FIT_SAMPLES = 300 if QUICK else 2000  # (x, return) pairs from the initial policy (paper: 2000)
FIT_SUBSET = 300 if QUICK else 500  # pairs in the marginal likelihood (library default: 500)
FIT_STEPS = 20 if QUICK else 100  # Adam steps of the hyperparameter fit
CAPACITY = 20 if QUICK else 50  # M, the BV budget of the GP in section 4
NUM_UPDATES = 6 if QUICK else 60  # policy updates in section 5 (budget M = 20)

# %%
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import gpguided_jax
from gpguided_jax import config, hyperfit, kernels, pendulum, sparse_gp, train

gpguided_jax.enable_x64()  # float64: the package leaves this choice to its user

key = jax.random.PRNGKey(0)
key_sim, key_collect, key_fit, key_train = jax.random.split(key, 4)

# %% [markdown]
# ## 1. The pendulum
#
# φ is measured from the hanging position (target: upright, φ = π). The torque is clipped to ±5 N·m,
# less than m·g·l = 9.81 N·m, so the pendulum cannot be lifted directly. Below: the free swing from
# 0.5 rad off upright, and a bang–bang energy-pumping controller u = 5·sign(ω) started at rest
# near the bottom. The reward (eq. 24, sign restored) is taken on the state after each step; its
# maximum is 0, upright at rest. RK4 at 200 Hz keeps the energy of the free swing almost constant.

# %%
params = pendulum.make_params(reward_noise_std=0.0)
seconds = 4.0
steps = int(seconds / float(params.dt))
rollout = jax.jit(pendulum.rollout, static_argnums=(2, 3))


def free(key, s):
    return 0.0


def pump(key, s):
    return 5.0 * jnp.sign(s[1] + 1e-3)


traj_free = rollout(key_sim, params, free, steps, jnp.array([np.pi - 0.5, 0.0]))
traj_pump = rollout(key_sim, params, pump, steps, jnp.array([0.1, 0.0]))
t = np.arange(steps) * float(params.dt)
energy_free = np.asarray(jax.vmap(pendulum.energy, (0, None))(traj_free.states, params))

fig, axes = plt.subplots(1, 3, figsize=(13, 3.2))
for traj, label in [(traj_free, "free swing"), (traj_pump, "u = 5 sign(ω)")]:
    axes[0].plot(t, traj.states[:, 0], label=label)
    axes[1].plot(t, traj.rewards, label=label)
axes[0].axhline(np.pi, color="k", lw=0.5, ls="--")
axes[0].set(xlabel="time [s]", ylabel="φ [rad]", title="angle (π = upright)")
axes[1].set(xlabel="time [s]", ylabel="reward", title="reward per step (eq. 24)")
axes[0].legend()
axes[2].plot(t, energy_free - energy_free[0])
axes[2].set(xlabel="time [s]", ylabel="H(t) − H(0) [J]", title="energy drift of the free swing (RK4)")
fig.tight_layout()
plt.show()

# %% [markdown]
# ## 2. Collecting data with the initial policy
#
# The paper preset's initial policy is c(s) = 0 with fixed Gaussian noise σ = 1.5 N·m; episodes are
# 50 steps (0.25 s) from φ ≈ π − 0.5. Each pair is x = (sin φ, cos φ, ω, a) with target the
# discounted return-to-go within the episode. `train.make_train(cfg).collect` is the same function
# the training loop uses before its hyperparameter fit.

# %%
cfg = config.preset("paper", method="gp_pg", hyperfit_samples=FIT_SAMPLES, gp_capacity=20)
run = train.make_train(cfg)
xs, ys = jax.jit(run.collect)(key_collect)
print(f"{xs.shape[0]} pairs, inputs {xs.shape[1]}-dimensional; returns in [{ys.min():.2f}, {ys.max():.2f}]")

phi = np.arctan2(np.asarray(xs[:, 0]), np.asarray(xs[:, 1])) % (2 * np.pi)
fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
sc = axes[0].scatter(phi, xs[:, 2], c=ys, s=4, cmap="viridis")
fig.colorbar(sc, ax=axes[0], label="return-to-go")
axes[0].set(xlabel="φ [rad]", ylabel="ω [rad/s]", title="visited states")
axes[1].scatter(xs[:, 3], ys, s=3, alpha=0.5)
axes[1].set(xlabel="action a [N m]", ylabel="return-to-go", title="targets vs action")
fig.tight_layout()
plt.show()

# %% [markdown]
# ## 3. Fitting the hyperparameters
#
# ARD squared-exponential kernel over the four inputs, signal variance σ_f² and noise σ_n², fitted by
# Adam on the log-parameters against the exact negative log marginal likelihood (one Cholesky per
# step, float64). As in the training loop, a random subset of the pairs enters the likelihood, and
# the GP's prior mean is the mean return m0 (returns are all negative: a zero prior mean would make
# unvisited state-actions look good), so the kernel is fitted to the centred returns y − m0.

# %%
prior_mean = jnp.mean(ys)
idx = jax.random.choice(key_fit, xs.shape[0], (min(FIT_SUBSET, xs.shape[0]),), replace=False)
fit = jax.jit(hyperfit.fit, static_argnames="num_steps")(xs[idx], ys[idx] - prior_mean, num_steps=FIT_STEPS)
hyper = fit.params
print(f"prior mean m0 = {float(prior_mean):.3f}")
names = ["sin φ", "cos φ", "ω", "a"]
print("length-scales:", {n: round(float(v), 3) for n, v in zip(names, hyper.lengthscales)})
print(f"signal variance σ_f² = {float(hyper.signal_variance):.4f}, "
      f"noise variance σ_n² = {float(hyper.noise_variance):.2e}")

plt.figure(figsize=(5, 3))
plt.plot(fit.losses)
plt.xlabel("Adam step")
plt.ylabel("−log p(y | X)")
plt.title("marginal-likelihood fit")
plt.tight_layout()
plt.show()

# %% [markdown]
# ## 4. The sparse GP predicting Q
#
# The pairs of the first 80% of the episodes are fed one by one to the online GP with a budget of
# M basis vectors (`sparse_gp.update_batch`, with the training loop's novelty threshold: a pair
# joins the set only if k** − kᵀK_B⁻¹k ≥ 10⁻⁴·k**); the rest are held out. The exact GP on the
# same training pairs is the reference: with a budget as large as the data, and every pair
# admitted, the sparse GP would reproduce it.

# %%
H = cfg.episode_length
n_train = int(0.8 * (xs.shape[0] // H)) * H
x_tr, y_tr, x_te, y_te = xs[:n_train], ys[:n_train], xs[n_train:], ys[n_train:]

gp = jax.jit(sparse_gp.update_batch, static_argnames="age_fn")(
    sparse_gp.init(CAPACITY, 4, prior_mean=prior_mean), x_tr, y_tr, hyper, 0, age_fn="exp",
    novelty_tol=cfg.novelty_tol,
)
predict = jax.jit(jax.vmap(sparse_gp.predict, (None, 0, None)))
mean_sparse, var_sparse = predict(gp, x_te, hyper)


def exact_gp_mean(x_train, y_train, x_test, hyper):
    """Exact GP posterior mean by Cholesky, with the same constant prior mean (the reference)."""
    K = kernels.gram(x_train, x_train, hyper) + hyper.noise_variance * jnp.eye(x_train.shape[0])
    weights = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(K), y_train - prior_mean)
    return prior_mean + kernels.gram(x_test, x_train, hyper) @ weights


mean_exact = jax.jit(exact_gp_mean)(x_tr, y_tr, x_te, hyper)


def rmse(a, b):
    return float(jnp.sqrt(jnp.mean((a - b) ** 2)))


print(f"{int(sparse_gp.num_basis_vectors(gp))} BVs out of {n_train} training pairs")
print(f"held-out RMSE: sparse GP {rmse(mean_sparse, y_te):.3f}, exact GP {rmse(mean_exact, y_te):.3f}, "
      f"predicting the mean return {rmse(jnp.mean(y_tr), y_te):.3f}")

fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
lo, hi = float(y_te.min()), float(y_te.max())
axes[0].scatter(y_te, mean_exact, s=6, alpha=0.5, label="exact GP")
axes[0].scatter(y_te, mean_sparse, s=6, alpha=0.5, label=f"sparse GP, M = {CAPACITY}")
axes[0].plot([lo, hi], [lo, hi], "k", lw=0.7)
axes[0].set(xlabel="held-out return-to-go", ylabel="predicted Q", title="Q on held-out pairs")
axes[0].legend()

# Q over actions at one start state: mean ± 2 std of the latent GP.
s0 = jnp.array([np.pi - 0.5, 0.0])
actions = jnp.linspace(-6.0, 6.0, 121)
x_grid = jax.vmap(kernels.state_action_features, (None, 0))(s0, actions)
m, v = predict(gp, x_grid, hyper)
sd = jnp.sqrt(v)
axes[1].plot(actions, m, label="Q_GP(s, a)")
axes[1].fill_between(actions, m - 2 * sd, m + 2 * sd, alpha=0.3, label="± 2 σ(x)")
axes[1].plot(actions, jax.jit(exact_gp_mean)(x_tr, y_tr, x_grid, hyper), "k--", lw=0.8, label="exact GP")
axes[1].set(xlabel="action a [N m]", ylabel="Q", title="Q_GP at s = (π − 0.5, 0)")
axes[1].legend(fontsize=8)
fig.tight_layout()
plt.show()

# %% [markdown]
# The fitted length-scale of the action coordinate is long compared with the torque range: over a
# 0.25 s episode the initial policy's actions change the return-to-go little, and most of its
# variation comes from the state. This is the signal the GP critic gives the policy gradient (eq. 9).

# %% [markdown]
# ## 5. Watching the basis-vector set change over policy updates
#
# In training (Algorithm 1) the GP takes in every episode, and each pair is stamped with the index t
# of the current policy update. When a novel pair arrives at a full set, the BV with the lowest score
#
# ε(i) = α_i² / (Q_ii + C_ii) + λ·g(t_i),   g(t_i) = exp(c·(t_i − min_j t_j))   (eq. 13–14)
#
# is removed, so with λ > 0 the BVs from old policies are the ones exchanged. First the age
# functions themselves (eq. 14 and 15) for a set stamped 0..9:

# %%
stamps = jnp.arange(10)
mask = jnp.ones(10, bool)
plt.figure(figsize=(5, 3))
for fn in sparse_gp.AGE_FUNCTIONS:
    plt.plot(stamps, sparse_gp.age_function(stamps, mask, 1.0, fn), "o-", label=f"g_{fn}")
plt.yscale("symlog")
plt.xlabel("timestamp t_i (policy update)")
plt.ylabel("g(t_i)")
plt.title("age functions, c = 1: old BVs score low")
plt.legend()
plt.tight_layout()
plt.show()

# %% [markdown]
# Now the training loop itself (`gp_pg`, the fitted kernel and prior mean from section 3, a budget
# of M = 20 as in `experiments/fig1_bv_composition.py`, so that the set is full and novel pairs
# force exchanges), one update at a time, for λ = 0 (plain KL sparsification) and λ = 100, as one
# vmapped program. After each update we record the timestamps of the BVs in the set.

# %%
lambdas = np.array([0.0, 100.0])
cfgs = [cfg.replace(age_penalty=lam) for lam in lambdas]
cfgs = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *cfgs)
prior = train.GPPrior(kernel=hyper, mean=prior_mean)
init = jax.jit(jax.vmap(lambda c: run.init(key_train, c, prior)))
step = jax.jit(jax.vmap(lambda s, c: run.run_chunk(s, c, 1)))

state = init(cfgs)
stamps_history, mask_history, fresh = [], [], []
for _ in range(NUM_UPDATES):
    state, record = step(state, cfgs)
    stamps_history.append(np.asarray(state.gp.timestamps))
    mask_history.append(np.asarray(state.gp.mask))
    fresh.append(np.asarray(record.fresh_bv_share[:, 0]))
stamps_history = np.stack(stamps_history, 1)  # (lambdas, updates, slots)
mask_history = np.stack(mask_history, 1)
fresh = np.stack(fresh, 1)  # (lambdas, updates)

# counts[l, k, t]: BVs stamped t in the set after update k
counts = np.zeros((len(lambdas), NUM_UPDATES, NUM_UPDATES))
for li in range(len(lambdas)):
    for k in range(NUM_UPDATES):
        counts[li, k] = np.bincount(stamps_history[li, k][mask_history[li, k]], minlength=NUM_UPDATES)

fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
for li, lam in enumerate(lambdas):
    im = axes[li].imshow(counts[li].T, origin="lower", aspect="auto", cmap="magma",
                         extent=(-0.5, NUM_UPDATES - 0.5, -0.5, NUM_UPDATES - 0.5))
    axes[li].set(xlabel="after policy update k", ylabel="timestamp t of the BV",
                 title=f"BVs per timestamp, λ = {lam:g}")
    fig.colorbar(im, ax=axes[li])
    axes[2].plot(np.arange(NUM_UPDATES), 100 * fresh[li], label=f"λ = {lam:g}")
axes[2].set(xlabel="policy update k", ylabel="% of BVs stamped k",
            title="share of BVs from the latest policy", ylim=(0, 100))
axes[2].legend(loc="center right")
fig.tight_layout()
plt.show()

mean_age = (np.arange(NUM_UPDATES) * counts).sum(-1) / counts.sum(-1)  # (lambdas, updates)
for lam, age, f in zip(lambdas, mean_age, fresh):
    print(f"λ = {lam:5g}: mean timestamp of the BVs after the last update {age[-1]:.1f} "
          f"(of {NUM_UPDATES - 1}); mean share from the latest policy {100 * f.mean():.0f}%")

# %% [markdown]
# With λ = 0 the set keeps whichever BVs carry the most information about the targets, however old;
# with λ = 100 the age term dominates the score and the set is renewed from recent policies, which
# is what lets the GP follow a policy that changes (paper §IV, Fig. 1; `experiments/fig1_bv_composition.py`
# reproduces the figure for λ ∈ {0, 10, 100, 400, 1000}).
