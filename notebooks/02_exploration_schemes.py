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
# # 02 · The two guided exploration schemes
#
# The paper's two ways of letting the GP critic steer exploration (§V):
#
# * **guided variance** (eq. 16–19): a ~ N(c(s), σ²_GP(s)) with σ²_GP(s) = λ_v·σ²(s, c(s)), the GP's
#   latent predictive variance at the controller's action: explore where the model is unsure;
# * **guided direction**, the Gibbs policy (eq. 20–22): draw K candidates a_j ~ N(c(s), σ²_cand),
#   score them with the min–max normalised GP mean Q̃_j, energy E_j = Q̃_j·exp(−(a_j − c(s))²/2σ_e²),
#   and pick a_J with probability π_j = softmax(βE)_j: explore towards actions the model rates high.
#
# We train each method (and `gp_pg`, fixed noise with the same GP critic) briefly on the paper
# preset, look at both schemes at one state with the same GP, then compare the runs.
# (At full size this takes a few minutes on a 2-core CPU, most of it compiling.)

# %%
import os

QUICK = os.environ.get("GPGUIDED_NOTEBOOK_QUICK") == "1"

NUM_SEEDS = 2 if QUICK else 5
NUM_UPDATES = 4 if QUICK else 100  # gradient updates of the short run (paper: 400)
NUM_DRAWS = 500 if QUICK else 20_000  # Gibbs selections for the histogram
GRID = 15 if QUICK else 60  # resolution of the (φ, ω) surface
SIZE = dict(hyperfit_samples=200, hyperfit_steps=10, gp_capacity=30) if QUICK else {}

# %%
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import gpguided_jax
from gpguided_jax import config, policies, train

gpguided_jax.enable_x64()  # float64: the package leaves this choice to its user

# gp_pg (fixed noise, same GP critic) is the reference; the quick test run skips it to save a compile.
METHODS = ("guided_variance", "guided_direction") + (() if QUICK else ("gp_pg",))
keys = jax.random.split(jax.random.PRNGKey(0), NUM_SEEDS)
cfgs = {m: config.preset("paper", method=m, num_updates=NUM_UPDATES, **SIZE) for m in METHODS}
runs = {m: train.make_train(c) for m, c in cfgs.items()}

# %% [markdown]
# ## A short run of each method
#
# The GP prior (kernel hyperparameters and prior mean) depends only on the seed (it is fitted on the
# initial policy's data), so it is fitted once per seed and shared by the methods. Each method is one compiled
# program over all seeds.

# %%
priors = jax.jit(jax.vmap(runs["guided_variance"].fit_kernel_for_seed))(keys)
results = {}
for m, run in runs.items():
    go = jax.jit(jax.vmap(lambda k, prior, run=run: run.run_chunk(run.init(k, run.config, prior))))
    results[m] = go(keys, priors)
    print(f"{m:17s} final mean reward per step {float(results[m][1].mean_reward[:, -1].mean()):.3f}")

# %% [markdown]
# ## Both schemes at one state
#
# Take seed 0's guided-variance run after its last update: its controller θ and its GP. The
# training loop gives λ_v and the candidate scale in (N·m)² where the GP knows nothing, i.e.
# divided by the fitted signal variance σ_f²; the context below is built the same way.

# %%
final_state = jax.tree_util.tree_map(lambda x: x[0], results["guided_variance"][0])
cfg = cfgs["guided_variance"]
theta, gp, kern = final_state.theta, final_state.gp, final_state.kernel
ctx = train.policy_context(cfg, gp, kern)  # exactly what the training loop gives its policy
controller = runs["guided_variance"].controller
# A visited state (the paper preset's mean start) and one the policy has not been to.
STATES = {"visited": jnp.array([np.pi - 0.5, 0.0]), "novel": jnp.array([np.pi - 0.5, 2.5])}
mean_actions = {name: controller.apply(theta.controller, st) for name, st in STATES.items()}
actions = jnp.linspace(-6.0, 6.0, 241)
print(f"{int(gp.mask.sum())} basis vectors; "
      + ", ".join(f"c(s_{n}) = {float(c):.3f} N m" for n, c in mean_actions.items()))

# %% [markdown]
# ### Guided variance (eq. 16)
#
# Left: λ_v·σ²(s, a*) as a function of the action coordinate a* of the GP input, at both states.
# The policy evaluates it at a* = c(s) (stars) and draws a ~ N(c(s), σ²_GP(s)); eq. 18–19
# differentiate it along a*, which is how the score pushes θ towards less explored actions.
# Right: σ_GP(s) = sqrt(σ²_GP(s, c(s))) over the state plane for this controller, with the states
# visited by the final policy (white) and the two states (red).


# %%
@jax.jit
def scaled_variance(state, a):
    return ctx.variance_scale * policies.gp_latent_variance(gp, kern, state, a)


phis = jnp.linspace(0.0, 2 * np.pi, GRID)
omegas = jnp.linspace(-4.0, 4.0, GRID)
P, W = jnp.meshgrid(phis, omegas)
states = jnp.stack([P.ravel(), W.ravel()], -1)
std_surface = jax.jit(jax.vmap(
    lambda st: jnp.sqrt(policies.guided_variance(controller, theta.controller, st, ctx))
))(states)
episodes = jax.jit(runs["guided_variance"].episodes, static_argnames="num_episodes")
visited = episodes(jax.random.PRNGKey(1), final_state, num_episodes=10).states.reshape(-1, 2)

fig, axes = plt.subplots(1, 2, figsize=(12, 3.8))
for name, st in STATES.items():
    variances = jax.vmap(scaled_variance, (None, 0))(st, actions)
    (line,) = axes[0].plot(actions, variances, label=f"λ_v σ²(s_{name}, a*)")
    var_at_c = policies.guided_variance(controller, theta.controller, st, ctx)
    axes[0].plot([float(mean_actions[name])], [float(var_at_c)], "*", ms=12, color=line.get_color(),
                 label=f"σ²_GP(s_{name}) = {float(var_at_c):.3g}")
axes[0].axhline(float(cfg.guided_variance_floor), color="gray", ls=":", label="floor")
axes[0].set(yscale="log", xlabel="action a* [N m]", ylabel="variance [(N m)²]",
            title="guided variance along the action")
axes[0].legend(fontsize=8)
im = axes[1].pcolormesh(P, W, std_surface.reshape(P.shape), shading="auto", cmap="viridis")
fig.colorbar(im, ax=axes[1], label="σ_GP(s) [N m]")
axes[1].scatter(visited[:, 0], visited[:, 1], s=2, c="w", alpha=0.6)
for st in STATES.values():
    axes[1].plot(float(st[0]), float(st[1]), "r+", ms=12, mew=2)
axes[1].set(xlabel="φ [rad]", ylabel="ω [rad/s]", title="exploration std over states, visited states")
fig.tight_layout()
plt.show()

# %% [markdown]
# ### Guided direction: the Gibbs policy (eq. 20–22)
#
# Left: one draw of the policy at each state: the K candidates, their normalised GP means Q̃_j,
# energies E_j and selection probabilities π_j (the grey curve is the GP mean over actions,
# min–max normalised over the plotted range, so it is comparable with Q̃). Right: the actions
# selected in many independent draws (each with fresh candidates) against the candidates' proposal
# density N(c(s), σ²_cand); the candidate variance also follows the GP's confidence at (s, c(s)).

# %%
gibbs = runs["guided_direction"].policy
sample = jax.jit(gibbs.sample)
sample_many = jax.jit(jax.vmap(gibbs.sample, (0, None, None, None)))
q_mean = jax.jit(jax.vmap(policies.gp_mean, (None, None, None, 0)))

fig, axes = plt.subplots(2, 2, figsize=(12, 7))
draw = {}
for row, (name, st) in enumerate(STATES.items()):
    c_s = float(mean_actions[name])
    action, aux = sample(jax.random.PRNGKey(2), theta, st, ctx)
    energy = policies.gibbs_energy(aux.candidates, aux.normalised_q, aux.mean_action, ctx.energy_width)
    order = jnp.argsort(aux.candidates)
    a_sorted = aux.candidates[order]
    draw[name] = (a_sorted, energy[order])
    cand_std = float(jnp.sqrt(aux.variance))
    lo, hi = c_s - 4 * cand_std, c_s + 4 * cand_std
    grid = jnp.linspace(lo, hi, 200)

    ax = axes[row, 0]
    ax.plot(grid, policies.normalise_q(q_mean(gp, kern, st, grid)), color="gray", lw=0.8,
            label="Q_GP(s, a), normalised")
    ax.plot(a_sorted, aux.normalised_q[order], "o", label="Q̃_j")
    ax.plot(a_sorted, energy[order], "s", label="E_j")
    ax.vlines(a_sorted, 0, aux.probs[order] / aux.probs.max(), color="tab:green",
              label="π_j (scaled to max 1)")
    ax.axvline(c_s, color="k", ls="--", lw=0.8, label="c(s)")
    ax.plot([float(action)], [1.05], "rv", label="selected a_J")
    ax.set(xlim=(lo, hi), xlabel="action [N m]",
           title=f"s_{name}: one draw, K = {cfg.num_candidates}, β = {float(cfg.inverse_temperature):g}")
    ax.legend(fontsize=7)

    draws, _ = sample_many(jax.random.split(jax.random.PRNGKey(3), NUM_DRAWS), theta, st, ctx)
    ax = axes[row, 1]
    ax.hist(np.asarray(draws), bins=np.linspace(lo, hi, 41), density=True, alpha=0.7,
            label="selected actions")
    ax.plot(grid, jnp.exp(-0.5 * ((grid - c_s) / cand_std) ** 2) / (np.sqrt(2 * np.pi) * cand_std),
            "k", lw=1, label="candidate proposal")
    ax.axvline(c_s, color="k", ls="--", lw=0.8)
    ax.set(xlabel="action [N m]", ylabel="density", title=f"s_{name}: {NUM_DRAWS} selections")
    ax.legend(fontsize=8)
    print(f"s_{name}: mean selected action {float(draws.mean()):+.3f} vs c(s) = {c_s:+.3f}; "
          f"candidate std {cand_std:.3f}, selected-action std {float(draws.std()):.3f}")
fig.tight_layout()
plt.show()

# %% [markdown]
# The inverse temperature β sets how strongly the energy picks: β → 0 is a uniform choice among
# the candidates (i.e. the Gaussian proposal), large β is a greedy choice of the highest energy.

# %%
a_sorted, energy_sorted = draw["novel"]
plt.figure(figsize=(6, 3.2))
for beta in (0.0, 1.0, 10.0, 100.0):
    plt.plot(a_sorted, jax.nn.softmax(beta * energy_sorted), "o-", ms=3, label=f"β = {beta:g}")
plt.xlabel("candidate action [N m]")
plt.ylabel("π_j")
plt.title("selection probabilities of the novel state's candidates")
plt.legend()
plt.tight_layout()
plt.show()

# %% [markdown]
# ## Over the run
#
# Mean reward per step (Fig. 5a) and the policy's exploration standard deviation averaged over the
# visited states (Fig. 5b): σ for fixed noise, σ_GP(s) for guided variance, and for the Gibbs policy
# the standard deviation of π over the candidates. Mean over seeds, with the seeds' range shaded.

# %%
fig, axes = plt.subplots(1, 2, figsize=(12, 3.8))
for m in METHODS:
    rec = results[m][1]
    x = np.arange(1, NUM_UPDATES + 1)
    for ax, field in zip(axes, ("mean_reward", "exploration_std")):
        y = np.asarray(getattr(rec, field))
        ax.plot(x, y.mean(0), label=m)
        ax.fill_between(x, y.min(0), y.max(0), alpha=0.2)
axes[0].set(xlabel="gradient update", ylabel="mean reward per step", title="reward")
axes[1].set(xlabel="gradient update", ylabel="exploration std [N m]", title="exploration")
axes[0].legend()
fig.tight_layout()
plt.show()

# %% [markdown]
# Guided variance explores with σ_GP(s), which shrinks as the GP fills in around the visited
# states; the Gibbs policy's spread is set by the candidate variance and β. Fixed noise keeps its
# learnable σ. Whether guided exploration beats fixed noise on reward needs all 400 updates and
# 10 seeds: `gpguided reproduce` (Fig. 5, docs/results.md).
