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
# # 05 · gp_model: the GP as a model of the task
#
# `gp_model` models the task's dynamics with one GP per observation coordinate and optimises the
# controller through simulated roll-outs of that model, inside Algorithm 1's loop (design: the
# model section of docs/design.md; results: docs/model_based.md). Here it learns the swing-up:
# the paper's pendulum starting near the bottom, 4.5 s episodes, a decision every 0.1 s held in
# between, and success when the pendulum stays within 0.3 rad of upright for the last second.
#
# After training with the swing-up preset's settings, this notebook looks inside the model:
#
# 1. its one-step predictions along a real episode, with their confidence band;
# 2. the controller's simulated roll-outs through the model beside its real episode;
# 3. the swing-up itself: a strip of frames and the phase portrait of several starts.

# %%
import os

QUICK = os.environ.get("GPGUIDED_NOTEBOOK_QUICK") == "1"

# the preset's budget (11 updates of one episode) at full size; a smoke run in quick mode
SIZE = (dict(num_updates=2, episode_length=300, model_steps=10, model_inducing=40,
             model_fit_steps=5, model_particles=4, eval_episodes=2) if QUICK else {})
SEED = 1007
PARTICLES = 4 if QUICK else 16  # simulated roll-outs drawn in part 2
STARTS = 2 if QUICK else 8  # real episodes from random starts in part 3

# %%
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import gpguided_jax
from gpguided_jax import config, model_based, rollouts, train

gpguided_jax.enable_x64()  # float64: the package leaves this choice to its user

cfg = config.preset("swingup", method="gp_model", **SIZE)
own = cfg.settings  # gp_model's own settings (model_based.ModelSettings)
print(f"{cfg.num_updates} updates x {cfg.episodes_per_update} episode x {cfg.episode_length} steps, "
      f"a decision every {cfg.hold_time} s; the model's uncertainty used as '{own.exploration}', "
      f"{own.particles} particles over {own.horizon} s")

state, rec = jax.jit(train.make_train(cfg))(jax.random.key(SEED))
for u in range(cfg.num_updates):
    print(f"update {u:2d}: evaluation success rate {float(rec.eval_success_rate[u]):.2f} "
          f"(before it), simulated return {float(rec.model_return[u]):8.1f}, "
          f"model error 1 - R^2 {float(rec.model_error[u]):.3f}")

# %% [markdown]
# ## The model's predictions along a real episode
#
# The model is the one the last update planned with: conditioned on every transition the
# buffer holds (`model_based.build`). A transition is one decision: the state it was taken in,
# its action, and the state at the end of its hold. Below, a fresh episode of the learnt
# controller, and at each of its decisions the model's prediction of the next state from the
# real one (one step ahead), with two standard deviations of the prediction (the GP's latent
# variance plus the learnt transition noise).

# %%
prog = train.make_program(cfg)
task, controller, hold = prog.task, prog.controller, prog.hold
model, target_mean = model_based.build(state.method_state, own.inducing)


def act(key, obs):
    del key
    return controller.apply(state.theta.controller, obs), ()


@jax.jit
def real_episode(key):
    obs, nxt, actions, _, _, _ = rollouts.run_episode(prog, key, act, cfg, cfg.episode_length, hold)
    return obs, nxt, actions


@jax.jit
def one_step(obs, action):
    """The predicted next observation and its standard deviation per coordinate."""
    x = task.features(obs, action)
    mean, var = model_based.predict(model, x)
    e = task.obs_dim
    nxt = model_based.next_of(task, obs, mean[:e] + target_mean[:e])
    sd = jnp.sqrt(var[:e] + model.kernels.noise_variance[:e]) * jnp.asarray(task.obs_scale)
    return nxt, sd


def from_upright(phi):
    """The pendulum's angle (0: hanging down) as the angle from upright, unwrapped along the
    episode and shifted by whole turns so that its end lies in (-pi, pi]."""
    a = np.unwrap(np.asarray(phi)) - np.pi
    return a - 2 * np.pi * np.round(a[-1] / (2 * np.pi))


obs, nxt, actions = real_episode(jax.random.key(SEED + 1))
d_obs, d_nxt, d_act, _ = model_based.decisions(hold, obs[None], nxt[None], actions[None])
d_obs, d_nxt, d_act = d_obs[0], d_nxt[0], d_act[0]
pred, sd = jax.vmap(one_step)(d_obs, d_act)
pred, sd, d_nxt = np.asarray(pred), np.asarray(sd), np.asarray(d_nxt)
t_dec = (np.arange(len(d_obs)) + 1) * hold * float(task.dt)  # the time each decision ends
# the errors of the predictions, the angle's taken the short way round
error = pred - d_nxt
error[:, 0] = np.mod(error[:, 0] + np.pi, 2 * np.pi) - np.pi
real = np.stack([from_upright(d_nxt[:, 0]), d_nxt[:, 1]], axis=1)

fig, axes = plt.subplots(2, 2, figsize=(11, 5), sharex=True)
for i, label in enumerate(("angle from upright [rad]", "omega [rad/s]")):
    ax = axes[i, 0]
    ax.plot(t_dec, real[:, i], "k-", lw=1, label="real episode")
    ax.plot(t_dec, real[:, i] + error[:, i], "C0.", ms=5, label="model's prediction")
    ax.set_ylabel(label)
    ax = axes[i, 1]
    ax.fill_between(t_dec, -2 * sd[:, i], 2 * sd[:, i], color="C0", alpha=0.3, label="± 2 sd")
    ax.plot(t_dec, error[:, i], "C0.-", ms=4, lw=0.8, label="prediction - real")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_ylabel(f"error, {label.split(' [')[0]}")
axes[0, 0].axhline(0, color="grey", lw=0.5, ls="--")
axes[0, 0].legend(loc="lower right", fontsize=8)
axes[0, 1].legend(loc="upper right", fontsize=8)
for ax in axes[1]:
    ax.set_xlabel("time [s]")
fig.suptitle("One step ahead: the model's prediction of each decision's next state, and its band")
fig.tight_layout()
plt.show()
inside = np.mean(np.abs(error) <= 2 * sd, axis=0)
print(f"within two standard deviations: the angle at {inside[0]:.0%}, omega at {inside[1]:.0%} "
      f"of the {len(d_obs)} decisions")

# %% [markdown]
# ## Simulated roll-outs beside the real episode
#
# The controller was optimised on particle roll-outs of the model. Here the same controller is
# rolled out through the model from the real episode's start: each particle follows its own
# function drawn from the GP posterior plus the learnt transition noise (the 'sample' use of the
# uncertainty), one decision per step, as `model_based.simulate` steps its particles. Where the
# particles agree with each other and with the real episode (the thick grey line), the model is
# sure and right; where they fan out, the controller was planned through the model's doubt.

# %%
@jax.jit
def simulated_paths(key, obs0):
    k_w, k_n = jax.random.split(key)
    weights = model_based.sample_weights(model, k_w, (PARTICLES,))  # (P, E, M)
    steps = cfg.episode_length // hold
    noise = jax.random.normal(k_n, (PARTICLES, steps, task.obs_dim))
    noise_sd = jnp.sqrt(model.kernels.noise_variance[: task.obs_dim])

    def particle(w, eps):
        def step(o, eps_t):
            a = controller.apply(state.theta.controller, o)
            out = jnp.sum(model_based.k_star(model, task.features(o, a)) * w, axis=-1) + target_mean
            o = model_based.next_of(task, o, out[: task.obs_dim] + noise_sd * eps_t)
            return o, o

        return jax.lax.scan(step, obs0, eps)[1]

    return jax.vmap(particle)(weights, noise)


paths = np.asarray(simulated_paths(jax.random.key(SEED + 2), obs[0]))
t_real = (np.arange(len(obs)) + 1) * float(task.dt)
fig, axes = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
for i, (ax, label) in enumerate(zip(axes, ("angle from upright [rad]", "omega [rad/s]"))):
    real = from_upright(nxt[:, 0]) if i == 0 else np.asarray(nxt[:, 1])
    ax.plot(t_real, real, "k-", lw=3, alpha=0.35, label="real episode")
    for p in range(PARTICLES):
        path = from_upright(paths[p, :, 0]) if i == 0 else paths[p, :, 1]
        ax.plot(t_dec, path, color="C1", lw=0.8, label="simulated (model)" if p == 0 else None)
    ax.set_ylabel(label)
axes[0].axhline(0, color="grey", lw=0.5, ls="--")
axes[0].legend(loc="lower right")
axes[1].set_xlabel("time [s]")
fig.suptitle("The learnt controller through the model and in the real task, from one start")
fig.tight_layout()
plt.show()

# %% [markdown]
# ## The swing-up
#
# A strip of frames of the real episode above (the pendulum every 0.5 s, its pivot at the
# centre, upright at the top), and the phase portrait (angle from upright, angular velocity) of
# the learnt controller from several random starts: a swing-up pumps energy in a few swings and
# ends at the upright point (0, 0).

# %%
dt = float(task.dt)
frames = np.arange(0, len(obs), int(round(0.5 / dt)))
fig, axes = plt.subplots(1, len(frames), figsize=(1.1 * len(frames), 1.6))
for ax, k in zip(axes, frames):
    phi = float(obs[k, 0])
    ax.plot([0, np.sin(phi)], [0, -np.cos(phi)], "k-", lw=2)
    ax.plot(np.sin(phi), -np.cos(phi), "o", color="C3", ms=7)
    ax.plot(0, 0, "ko", ms=3)
    ax.set_xlim(-1.2, 1.2)
    ax.set_ylim(-1.2, 1.2)
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(f"{k * dt:.1f} s", fontsize=8)
fig.suptitle("The learnt controller's swing-up, a frame every 0.5 s", fontsize=10)
fig.tight_layout()
plt.show()

keys = jax.random.split(jax.random.key(SEED + 3), STARTS)
many_obs, many_nxt, _ = jax.vmap(real_episode)(keys)
fig, ax = plt.subplots(figsize=(6, 4.5))
for j in range(STARTS):
    angle = np.mod(np.asarray(many_nxt[j, :, 0]), 2 * np.pi) - np.pi  # from upright, (-pi, pi]
    omega = np.asarray(many_nxt[j, :, 1])
    wraps = np.flatnonzero(np.abs(np.diff(angle)) > np.pi) + 1  # no line across a whole turn
    ax.plot(np.insert(angle, wraps, np.nan), np.insert(omega, wraps, np.nan), lw=0.9)
    ax.plot(angle[0], omega[0], "ko", ms=3)
ax.plot(0, 0, "r*", ms=12, label="upright, at rest")
ax.set_xlabel("angle from upright [rad]")
ax.set_ylabel("omega [rad/s]")
ax.set_title(f"Phase portrait of {STARTS} real episodes (dots: starts)")
ax.legend(loc="upper right")
fig.tight_layout()
plt.show()
