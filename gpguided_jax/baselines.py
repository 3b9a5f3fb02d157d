"""Baselines beside the paper's methods: brax PPO on the same pendulum, and swing-up success.

`train_ppo` runs `brax.training.agents.ppo.train` on `brax_env.PendulumEnv` (same physics, reward,
start-state distribution and episode length as a preset) and returns its learning curve in the
units of Fig. 5: environment steps against average reward per step of an episode.

`swingup_success` (= `swingup.success`) is the success criterion of the swing-up preset: the
pendulum stays within `tolerance` rad of upright (|phi - pi| < 0.3, phi wrapped to [0, 2 pi)) at
every control step of the last `hold_time` seconds (1 s) of the episode. An episode that swings
through upright, or reaches it and falls, fails. `policy_success_rate` (= `swingup.success_rate`)
applies it to fresh episodes of any policy.

A budget of environment steps is brax's `num_timesteps`, which brax rounds up to whole iterations
between evaluations (and, for SAC, counts the replay buffer's prefill in). `evaluation_steps` and
`steps_run` give the steps brax 0.14.2 runs for a budget, `smallest_budget` the smallest budget it
can run; the trainers here refuse a smaller one with `BudgetError` before brax compiles anything.

PPO hyperparameters (`PPO_DEFAULTS`) are generic choices for a one-dimensional continuous-control
task with tens of thousands to a few million steps, fixed before any run and never tuned on the
reported seeds:
  - networks: policy and value MLPs with two hidden layers of 64 (swish), tanh-squashed Gaussian;
  - 16 parallel environments, unrolls of 25 steps, 5 minibatches of 16 unrolls (2000 environment
    steps per PPO iteration), 8 epochs per batch, Adam with learning rate 3e-4;
  - discount 0.99 (the GP methods' gamma), GAE lambda 0.95, clipping 0.2, entropy cost 1e-3,
    normalised advantages, no gradient clipping;
  - no observation normalisation: (sin phi, cos phi, omega) is already of order one, and with
    brax's running normaliser on (seed 0, paper preset, a diagnostic run) PPO drove the torque
    against the target (reward per step -0.29 -> -0.43 in 60 000 steps) while without it it
    improved; the cause was not pinned down;
  - reward scaling 1 - gamma, so the value network's targets (discounted returns) are of the size
    of a per-step reward (the policy loss does not depend on it: advantages are normalised);
  - the learning curve is brax's evaluator on 64 fresh episodes with the *stochastic* policy
    (`deterministic_eval=False`), which is what the GP methods' curves measure too (their own
    exploring policy on the update's episodes).

PPO runs under `jax.enable_x64(False)`: brax's wrappers mix float32 and default-dtype arrays, which
breaks under x64 (and the package turns x64 on at import).

What the studies share about the baselines: their names (`NAMES`), their settings as trainer
arguments (`trainer_settings`: a horizon in seconds as brax's discount) and the evaluations
after learning started (`after_initial_evaluation`: brax's trainers evaluate the initial policy
first, at 0 steps). `gpguided_jax.study.run_baseline` runs one with a study's budget.
"""

from __future__ import annotations

import functools
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gpguided_jax import pendulum, swingup

# brax's trainers beside the methods, in the order the studies' tables list them
NAMES = ("ppo", "sac")

PPO_DEFAULTS = dict(
    num_envs=16,
    unroll_length=25,
    batch_size=16,
    num_minibatches=5,
    num_updates_per_batch=8,
    learning_rate=3e-4,
    entropy_cost=1e-3,
    discounting=0.99,
    gae_lambda=0.95,
    clipping_epsilon=0.2,
    normalize_observations=False,
    num_eval_envs=64,
    deterministic_eval=False,
)
HIDDEN_LAYERS = (64, 64)


SAC_DEFAULTS = dict(
    num_envs=16,
    learning_rate=3e-4,
    discounting=0.99,
    batch_size=256,
    reward_scaling=1.0,
    tau=0.005,
    min_replay_size=2000,
    max_replay_size=200_000,
    grad_updates_per_step=1,
    normalize_observations=False,
    num_eval_envs=64,
    deterministic_eval=False,
)
SAC_HIDDEN_LAYERS = (64, 64)


class PPOResult(NamedTuple):
    """What `train_ppo` and `train_sac` return.

    Attributes:
      env_steps: (E,) environment steps at each evaluation (0 for the initial policy).
      reward_per_step: (E,) average reward per step of an evaluation episode (mean over episodes).
      wall_time: seconds for the whole `train` call, compilation and evaluations included.
      make_policy: brax's `make_policy(params, deterministic=False) -> policy(obs, key)`.
      params: (normaliser, policy, ...) parameters of the final policy.
      success_rate: (E,) share of the evaluation episodes that end in a held swing-up (the
        environment's `success` metric; 0 if the episodes are shorter than the hold time).
    """

    env_steps: np.ndarray
    reward_per_step: np.ndarray
    wall_time: float
    make_policy: Callable
    params: tuple
    success_rate: np.ndarray | None = None


SACResult = PPOResult


def trainer_settings(settings: dict, dt: float) -> dict:
    """A baseline's settings as its trainer's keyword arguments: a 'horizon' in seconds becomes
    brax's `discounting` at `dt` seconds per step (`tasks.discount_for_horizon`), and
    `grad_updates_per_step` a whole number."""
    from gpguided_jax import tasks

    out = {k: v for k, v in settings.items() if k != "horizon"}
    if "horizon" in settings:
        out["discounting"] = tasks.discount_for_horizon(settings["horizon"], dt)
    if "grad_updates_per_step" in out:
        out["grad_updates_per_step"] = int(out["grad_updates_per_step"])
    return out


def after_initial_evaluation(env_steps: np.ndarray, curves: np.ndarray):
    """The evaluations after learning started: brax's trainers evaluate the initial policy first,
    at 0 steps, which the methods' curves do not hold, so a final 10% or a first step to a
    threshold is taken over the others, as for the methods.

    Args:
      env_steps: (E,) environment steps of the evaluations.
      curves: (..., E) an evaluation record.

    Returns:
      (env_steps[1:], curves[..., 1:]).
    """
    return np.asarray(env_steps)[1:], np.asarray(curves)[..., 1:]


def float32_params(params: pendulum.PendulumParams) -> pendulum.PendulumParams:
    """The same pendulum with float32 leaves (brax's networks and wrappers run in float32)."""
    return jax.tree_util.tree_map(lambda x: np.asarray(x, np.float32), params)


def ppo_steps_per_iteration(num_envs, unroll_length, batch_size, num_minibatches,
                            action_repeat=1) -> int:
    """Environment steps per PPO iteration (one batch of unrolls), as brax counts them."""
    del num_envs  # the batch is collected by num_envs in sequential unrolls
    return batch_size * unroll_length * num_minibatches * action_repeat


class BudgetError(ValueError):
    """A budget of environment steps that brax's trainer cannot run with the given settings.

    Attributes:
      smallest: the smallest budget it can run with them.
    """

    def __init__(self, message: str, smallest: int):
        super().__init__(message)
        self.smallest = int(smallest)


def _schedule(algorithm: str, settings: dict | None) -> dict:
    """The settings that fix brax's step schedule: `PPO_DEFAULTS` or `SAC_DEFAULTS` under
    `settings`, brax's own defaults for the rest (action_repeat 1, num_resets_per_eval 0)."""
    if algorithm == "ppo":
        s = {**PPO_DEFAULTS, **(settings or {})}
        keys = ("num_envs", "unroll_length", "batch_size", "num_minibatches")
        extra = {"action_repeat": 1, "num_resets_per_eval": 0}
    elif algorithm == "sac":
        s = {**SAC_DEFAULTS, **(settings or {})}
        keys = ("num_envs", "min_replay_size")
        extra = {"action_repeat": 1}
    else:
        raise ValueError(f"unknown baseline {algorithm!r}; choose 'ppo' or 'sac'")
    return {**{k: int(s[k]) for k in keys}, **{k: int(s.get(k, v)) for k, v in extra.items()}}


def _sac_prefill_steps(sch: dict) -> int:
    """Environment steps of SAC's replay-buffer prefill (brax counts them as training steps)."""
    actor_steps = -(-sch["min_replay_size"] // sch["num_envs"])
    return actor_steps * sch["action_repeat"] * sch["num_envs"]


def smallest_budget(algorithm: str, settings: dict | None = None) -> int:
    """The smallest budget of environment steps (brax's `num_timesteps`) that brax 0.14.2's
    trainer runs and trains with.

    PPO: 1 (at 0 brax returns the initial policy without a step or an evaluation). SAC: one more
    than the steps of its replay-buffer prefill, ceil(min_replay_size / num_envs) * num_envs *
    action_repeat: brax refuses a budget up to min_replay_size, asserts that the budget covers
    the prefill, and at exactly the prefill makes no gradient step.

    Args:
      algorithm: 'ppo' or 'sac'.
      settings: trainer arguments over `PPO_DEFAULTS` / `SAC_DEFAULTS` (as `train_on_task`'s).
    """
    sch = _schedule(algorithm, settings)
    if algorithm == "ppo":
        return 1
    return max(sch["min_replay_size"], _sac_prefill_steps(sch)) + 1


def check_budget(algorithm: str, budget: int, settings: dict | None = None) -> None:
    """Raises `BudgetError` (one line, naming the smallest budget) if brax cannot run `budget`.

    Args:
      algorithm: 'ppo' or 'sac'.
      budget: environment steps asked for (brax's `num_timesteps`).
      settings: trainer arguments over `PPO_DEFAULTS` / `SAC_DEFAULTS`.
    """
    smallest = smallest_budget(algorithm, settings)
    if int(budget) >= smallest:
        return
    if algorithm == "ppo":
        raise BudgetError(f"brax's PPO needs a budget of at least 1 environment step, got "
                          f"{int(budget)}", smallest)
    sch = _schedule(algorithm, settings)
    raise BudgetError(
        f"brax's SAC cannot run a budget of {int(budget)} environment steps: it first fills its "
        f"replay buffer with {_sac_prefill_steps(sch)} steps (min_replay_size "
        f"{sch['min_replay_size']} from {sch['num_envs']} environments) and trains only on the "
        f"steps beyond them; the smallest budget is {smallest}", smallest)


def evaluation_steps(algorithm: str, budget: int, num_evals: int,
                     settings: dict | None = None) -> np.ndarray:
    """The environment steps at which brax 0.14.2's trainer evaluates (the steps its
    `progress_fn` receives), the initial policy's 0 first; the last is the steps run.

    brax counts every environment step of every device, so the count does not depend on the
    device count. With n = max(num_evals - 1, 1) evaluation intervals:
      - PPO (`ppo/train.py`): an iteration is E = batch_size * unroll_length * num_minibatches *
        action_repeat steps; an interval is max(num_resets_per_eval, 1) epochs of
        k = ceil(budget / (n * E * max(num_resets_per_eval, 1))) iterations, so evaluation i is
        at i * k * E * max(num_resets_per_eval, 1), and the run ends at n times that.
      - SAC (`sac/train.py`): the replay-buffer prefill P = ceil(min_replay_size / num_envs) *
        num_envs * action_repeat counts as steps; an interval is
        k = ceil((budget - P) / (n * num_envs * action_repeat)) actor steps of num_envs *
        action_repeat each, so evaluation i is at P + i * k * num_envs * action_repeat.
    The initial evaluation (step 0) takes place when num_evals > 1.

    Args:
      algorithm: 'ppo' or 'sac'.
      budget: environment steps asked for (brax's `num_timesteps`).
      num_evals: brax's `num_evals` (>= 1).
      settings: trainer arguments over `PPO_DEFAULTS` / `SAC_DEFAULTS`.

    Returns:
      (num_evals,) int64 steps (one fewer without the initial evaluation).

    Raises:
      BudgetError: brax cannot run `budget` (`check_budget`).
    """
    if num_evals < 1:
        raise ValueError(f"num_evals must be >= 1, got {num_evals}")
    check_budget(algorithm, budget, settings)
    sch = _schedule(algorithm, settings)
    n = max(num_evals - 1, 1)
    if algorithm == "ppo":
        resets = max(sch["num_resets_per_eval"], 1)
        per_iteration = ppo_steps_per_iteration(sch["num_envs"], sch["unroll_length"],
                                                sch["batch_size"], sch["num_minibatches"],
                                                sch["action_repeat"])
        k = -(-int(budget) // (n * per_iteration * resets))
        start, interval = 0, k * per_iteration * resets
    else:
        per_actor_step = sch["num_envs"] * sch["action_repeat"]
        start = _sac_prefill_steps(sch)
        k = -(-(int(budget) - start) // (n * per_actor_step))
        interval = k * per_actor_step
    steps = start + interval * np.arange(1, n + 1, dtype=np.int64)
    return np.concatenate([[0], steps]) if num_evals > 1 else steps


def steps_run(algorithm: str, budget: int, num_evals: int, settings: dict | None = None) -> int:
    """Environment steps brax 0.14.2's trainer runs for `budget` (`evaluation_steps`' last):
    whole iterations, so at least `budget`.

    Args:
      algorithm: 'ppo' or 'sac'.
      budget: environment steps asked for (brax's `num_timesteps`).
      num_evals: brax's `num_evals`.
      settings: trainer arguments over `PPO_DEFAULTS` / `SAC_DEFAULTS`.

    Raises:
      BudgetError: brax cannot run `budget`.
    """
    return int(evaluation_steps(algorithm, budget, num_evals, settings)[-1])


def budget_note(algorithm: str, budget: int, num_evals: int,
                settings: dict | None = None) -> str | None:
    """One line on how brax rounds `budget` up to whole iterations; None if it runs exactly it.

    Args:
      algorithm: 'ppo' or 'sac'.
      budget: environment steps asked for (brax's `num_timesteps`).
      num_evals: brax's `num_evals`.
      settings: trainer arguments over `PPO_DEFAULTS` / `SAC_DEFAULTS`.
    """
    steps = evaluation_steps(algorithm, budget, num_evals, settings)
    run = int(steps[-1])
    if run == int(budget):
        return None
    sch = _schedule(algorithm, settings)
    n = max(num_evals - 1, 1)
    interval = int(steps[-1] - steps[-2]) if len(steps) > 1 else run
    if algorithm == "ppo":
        per_iteration = ppo_steps_per_iteration(sch["num_envs"], sch["unroll_length"],
                                                sch["batch_size"], sch["num_minibatches"],
                                                sch["action_repeat"])
        how = (f"brax's PPO runs whole iterations of {per_iteration} environment steps, "
               f"{interval // per_iteration} in each of its {n} evaluation intervals")
    else:
        k = interval // (sch["num_envs"] * sch["action_repeat"])
        repeat = f" (action_repeat {sch['action_repeat']})" if sch["action_repeat"] != 1 else ""
        how = (f"brax's SAC fills its replay buffer with {_sac_prefill_steps(sch)} environment "
               f"steps, then steps its {sch['num_envs']} environments{repeat} "
               f"{'once' if k == 1 else f'{k} times'} in each of its {n} evaluation intervals")
    return f"{how}: a budget of {int(budget)} runs {run} steps"


def _quiet_brax() -> None:
    """Imports brax through `brax_env`, which keeps the note mujoco's import prints (its GPU
    backend is missing) off stdout, where the commands write their output: call it before
    importing brax's trainers."""
    from gpguided_jax import brax_env  # noqa: F401


def train_ppo(
    pendulum_params: pendulum.PendulumParams,
    num_timesteps: int,
    episode_length: int,
    seed: int,
    *,
    num_evals: int = 11,
    hidden_layers: tuple = HIDDEN_LAYERS,
    **ppo_kwargs,
) -> PPOResult:
    """brax PPO on `PendulumEnv(pendulum_params)`; returns the learning curve and wall time.

    brax runs whole PPO iterations: the steps done are `num_timesteps` rounded up to a multiple of
    (num_evals - 1) * steps per iteration (`evaluation_steps`), and `env_steps` reports the steps
    actually done.

    Args:
      pendulum_params: physics, reward noise and start-state distribution (any float dtype).
      num_timesteps: environment-step budget (>= 1).
      episode_length: steps per episode (brax truncates; the value is bootstrapped at truncation).
      seed: PPO seed (initialisation, environments, evaluation).
      num_evals: evaluations including the initial one (>= 2).
      hidden_layers: hidden sizes of both the policy and the value MLP.
      **ppo_kwargs: overrides of `PPO_DEFAULTS` or further `ppo.train` arguments.
    """
    _quiet_brax()
    from brax.training.agents.ppo import networks as ppo_networks
    from brax.training.agents.ppo import train as ppo

    if num_evals < 2:
        raise ValueError(f"num_evals must be >= 2, got {num_evals}")
    kwargs = {**PPO_DEFAULTS, **ppo_kwargs}
    check_budget("ppo", num_timesteps, kwargs)
    kwargs.setdefault("reward_scaling", 1.0 - kwargs["discounting"])
    network_factory = functools.partial(
        ppo_networks.make_ppo_networks,
        policy_hidden_layer_sizes=tuple(hidden_layers),
        value_hidden_layer_sizes=tuple(hidden_layers),
    )
    return _run_brax(ppo.train, pendulum_params, num_timesteps, episode_length, seed,
                     num_evals=num_evals, network_factory=network_factory, **kwargs)


def train_sac(
    pendulum_params: pendulum.PendulumParams,
    num_timesteps: int,
    episode_length: int,
    seed: int,
    *,
    num_evals: int = 11,
    hidden_layers: tuple = SAC_HIDDEN_LAYERS,
    **sac_kwargs,
) -> PPOResult:
    """brax SAC (`brax.training.agents.sac.train`) on `PendulumEnv(pendulum_params)`, as
    `train_ppo`. SAC tunes its entropy temperature itself (target entropy -action_size); the reward
    scale sets how much the reward weighs against that entropy. Hyperparameters: `SAC_DEFAULTS`.
    The budget must exceed the replay buffer's prefill (`smallest_budget`; `BudgetError`
    otherwise, before brax compiles anything), and brax rounds it up (`evaluation_steps`)."""
    _quiet_brax()
    from brax.training.agents.sac import networks as sac_networks
    from brax.training.agents.sac import train as sac

    if num_evals < 2:
        raise ValueError(f"num_evals must be >= 2, got {num_evals}")
    kwargs = {**SAC_DEFAULTS, **sac_kwargs}
    check_budget("sac", num_timesteps, kwargs)
    network_factory = functools.partial(sac_networks.make_sac_networks,
                                        hidden_layer_sizes=tuple(hidden_layers))
    return _run_brax(sac.train, pendulum_params, num_timesteps, episode_length, seed,
                     num_evals=num_evals, network_factory=network_factory, **kwargs)


def _run_brax(train_fn, pendulum_params, num_timesteps, episode_length, seed, *, num_evals,
              hold_time: float = 1.0, tolerance: float = 0.3, **kwargs) -> PPOResult:
    """One brax trainer on the pendulum (float32, x64 off), with its evaluations recorded."""
    from gpguided_jax import brax_env

    steps, rewards, success = [], [], []

    def progress(step, metrics):
        steps.append(int(step))
        rewards.append(float(metrics["eval/episode_reward"]) / episode_length)
        success.append(float(metrics.get("eval/episode_success", np.nan)))

    with jax.enable_x64(False):
        p32 = float32_params(pendulum_params)
        env = brax_env.PendulumEnv(
            p32, episode_length=int(episode_length),
            hold_steps=swingup.hold_steps(float(np.asarray(p32.dt)), hold_time), tolerance=tolerance)
        t0 = time.perf_counter()
        make_policy, params, _ = train_fn(
            environment=env,
            num_timesteps=int(num_timesteps),
            episode_length=int(episode_length),
            num_evals=int(num_evals),
            seed=int(seed),
            progress_fn=progress,
            **kwargs,
        )
        jax.block_until_ready(params)
        wall = time.perf_counter() - t0
    return PPOResult(np.asarray(steps), np.asarray(rewards), wall, make_policy, params,
                     np.asarray(success))


class TaskResult(NamedTuple):
    """What `train_on_task` returns.

    Attributes:
      env_steps: (E,) environment steps at each evaluation (0 for the initial policy).
      episode_return: (E,) undiscounted return of an evaluation episode (mean over episodes).
      wall_time: seconds for the whole `train` call, compilation and evaluations included.
    """

    env_steps: np.ndarray
    episode_return: np.ndarray
    wall_time: float


def train_on_task(algorithm: str, env: str, num_timesteps: int, episode_length: int, seed: int, *,
                  num_evals: int = 11, hidden_layers: tuple = (64, 64),
                  on_evaluation: Callable[[int, float], None] | None = None,
                  **kwargs) -> TaskResult:
    """brax's PPO or SAC on a task of `gpguided_jax.tasks` ('gymnax:<id>' or 'brax:<name>'),
    through `brax_env.task_env`; evaluated by brax's evaluator on `num_eval_envs` fresh episodes
    with the deterministic policy (the mean action), as the GP methods' `eval_return` evaluates
    c(s).

    Args:
      algorithm: 'ppo' or 'sac'.
      env: the task's name.
      num_timesteps: environment-step budget: brax rounds it up to whole iterations
        (`evaluation_steps`), and refuses one it cannot run (`BudgetError`, raised here before
        brax compiles anything).
      episode_length: steps per episode (brax's `EpisodeWrapper` truncates there).
      seed: the trainer's seed.
      num_evals: evaluations, the initial one included (>= 2).
      hidden_layers: hidden sizes of every MLP.
      on_evaluation: called with (environment steps, return) as each evaluation ends.
      **kwargs: overrides of `PPO_DEFAULTS` / `SAC_DEFAULTS`, or further `train` arguments.
    """
    _quiet_brax()
    if algorithm == "ppo":
        from brax.training.agents.ppo import networks as nets
        from brax.training.agents.ppo import train as trainer

        kwargs = {**PPO_DEFAULTS, "deterministic_eval": True, **kwargs}
        kwargs.setdefault("reward_scaling", 1.0 - kwargs["discounting"])
        factory = functools.partial(nets.make_ppo_networks,
                                    policy_hidden_layer_sizes=tuple(hidden_layers),
                                    value_hidden_layer_sizes=tuple(hidden_layers))
    elif algorithm == "sac":
        from brax.training.agents.sac import networks as nets
        from brax.training.agents.sac import train as trainer

        kwargs = {**SAC_DEFAULTS, "deterministic_eval": True, **kwargs}
        factory = functools.partial(nets.make_sac_networks, hidden_layer_sizes=tuple(hidden_layers))
    else:
        raise ValueError(f"unknown baseline {algorithm!r}; choose 'ppo' or 'sac'")
    if num_evals < 2:
        raise ValueError(f"num_evals must be >= 2, got {num_evals}")
    check_budget(algorithm, num_timesteps, kwargs)
    from gpguided_jax import brax_env

    steps, returns = [], []

    def progress(step, metrics):
        steps.append(int(step))
        returns.append(float(metrics["eval/episode_reward"]))
        if on_evaluation is not None:
            on_evaluation(steps[-1], returns[-1])

    with jax.enable_x64(False):
        t0 = time.perf_counter()
        _, params, _ = trainer.train(environment=brax_env.task_env(env),
                                     num_timesteps=int(num_timesteps),
                                     episode_length=int(episode_length), num_evals=int(num_evals),
                                     seed=int(seed), progress_fn=progress,
                                     network_factory=factory, **kwargs)
        jax.block_until_ready(params)
        wall = time.perf_counter() - t0
    return TaskResult(np.asarray(steps), np.asarray(returns), wall)


def preset_settings(preset: str, algorithm: str, dt: float) -> dict:
    """The trainer's keyword arguments of `algorithm` as tuned for `preset`
    (`config.BASELINE_PRESETS`; none for a preset without a tuning): a 'horizon' in seconds
    becomes brax's `discounting` at `dt` seconds per step."""
    from gpguided_jax import config

    return trainer_settings(config.BASELINE_PRESETS.get(preset, {}).get(algorithm, {}), dt)


def summarise_returns(env_steps: np.ndarray, returns: np.ndarray, threshold: float | None) -> dict:
    """Final return and steps to the threshold of baseline runs, as `summary.csv` gives them for
    the methods.

    Args:
      env_steps: (E,) environment steps of the evaluations; the first evaluates the initial policy
        and is left out.
      returns: (seeds, E) deterministic evaluation returns.
      threshold: the task's solved-at return (None: no steps to threshold).

    Returns:
      final_return_iqm with its stratified-bootstrap ci95 over seeds (the final return of a seed:
      the mean over its last 10% of evaluations), final_return_mean, and per seed the environment
      steps at which its evaluation first reached the threshold (None if never).
    """
    from gpguided_jax import stats, summaries

    steps, ret = after_initial_evaluation(env_steps, np.asarray(returns, float))
    final = summaries.final_performance(ret)
    lo, hi = stats.bootstrap_ci(final)
    out = dict(seeds=int(ret.shape[0]), final_return_iqm=stats.iqm(final), ci95=[lo, hi],
               final_return_mean=float(final.mean()), threshold=threshold)
    if threshold is not None:
        hit = ret >= threshold
        out["steps_to_threshold"] = [int(steps[h.argmax()]) if h.any() else None for h in hit]
    return out


def plan_preset(algorithm: str, preset: str, *, env: str | None = None,
                num_timesteps: int | None = None, num_evals: int = 26,
                overrides: dict | None = None) -> dict:
    """What `run_preset` would run, checked without compiling anything: the task, the settings and
    the budget, refused if brax cannot run them.

    Args:
      algorithm: 'ppo' or 'sac'.
      preset: a preset of `config.PRESETS`; its environment, episode length and budget of
        environment steps (updates x episodes x episode length) apply, and its tuned settings
        (`preset_settings`).
      env: another task than the preset's ('gymnax:<id>' or 'brax:<name>').
      num_timesteps: another budget of environment steps.
      num_evals: evaluations, the initial policy's included.
      overrides: further trainer arguments, over the tuned ones.

    Returns:
      A dict: env, episode_length, threshold (the task's solved-at return), settings (the trainer
      arguments over `PPO_DEFAULTS` / `SAC_DEFAULTS`), budget (brax's `num_timesteps`) and note
      (`budget_note`: how brax rounds the budget up; None if it runs exactly the budget).

    Raises:
      BudgetError: brax cannot run the budget with these settings.
      ValueError: another argument that cannot run.
    """
    from gpguided_jax import config, tasks

    if algorithm not in NAMES:
        raise ValueError(f"unknown baseline {algorithm!r}; choose 'ppo' or 'sac'")
    if num_evals < 2:
        raise ValueError(f"num_evals must be >= 2, got {num_evals}")
    # the preset's task and budget only (the baselines run in float32)
    cfg = config.preset(preset, dtype="float32", **({"env": env} if env else {}))
    if not cfg.env.startswith(("gymnax:", "brax:")):
        raise ValueError(f"the baselines run on the standard tasks ('gymnax:<id>', 'brax:<name>'); "
                         f"{cfg.env!r} is the paper's pendulum (experiments/swingup_study.py runs "
                         f"PPO and SAC there)")
    task = tasks.make_task(cfg.env)
    settings = {**preset_settings(preset, algorithm, task.dt), **(overrides or {})}
    budget = int(num_timesteps or cfg.num_updates * cfg.episodes_per_update * cfg.episode_length)
    return dict(env=cfg.env, episode_length=int(cfg.episode_length), threshold=task.threshold,
                settings=settings, budget=budget,
                note=budget_note(algorithm, budget, num_evals, settings))


def run_preset(algorithm: str, preset: str, seeds, *, env: str | None = None,
               num_timesteps: int | None = None, num_evals: int = 26,
               hidden_layers: tuple = HIDDEN_LAYERS, overrides: dict | None = None,
               progress=None, on_evaluation=None) -> dict:
    """brax's `algorithm` on a standard task with a preset's budget and tuned settings, one run
    per seed (`gpguided baseline`), after `plan_preset`'s checks.

    Args:
      algorithm: 'ppo' or 'sac'.
      preset: a preset of `config.PRESETS`; its environment, episode length and budget of
        environment steps (updates x episodes x episode length) apply, and its tuned settings
        (`preset_settings`).
      seeds: the trainer's seeds.
      env: another task than the preset's ('gymnax:<id>' or 'brax:<name>').
      num_timesteps: another budget of environment steps.
      num_evals: evaluations, the initial policy's included.
      hidden_layers: hidden sizes of every MLP.
      overrides: further trainer arguments, over the tuned ones.
      progress: called with a line before the first run if brax rounds the budget up
        (`budget_note`), and after each seed.
      on_evaluation: `train_on_task`'s, for every seed.

    Returns:
      A dict: algorithm, preset, env, settings, budget (the environment steps asked for, brax's
      `num_timesteps`), steps_run (the steps brax ran, as its evaluations report them: the
      budget rounded up to whole iterations), seeds, env_steps (E,), returns (seeds, E), wall_s
      per seed, and `summarise_returns`' summary.

    Raises:
      BudgetError: brax cannot run the budget with these settings (before any run).
      ValueError: another argument that cannot run.
    """
    plan = plan_preset(algorithm, preset, env=env, num_timesteps=num_timesteps,
                       num_evals=num_evals, overrides=overrides)
    settings, budget = plan["settings"], plan["budget"]
    if plan["note"] is not None and progress is not None:
        progress(f"[{algorithm}] {plan['note']}")
    runs = []
    for i, seed in enumerate(seeds):
        r = train_on_task(algorithm, plan["env"], budget, plan["episode_length"], seed,
                          num_evals=num_evals, hidden_layers=tuple(hidden_layers),
                          on_evaluation=on_evaluation, **settings)
        runs.append(r)
        if progress is not None:
            progress(f"[{algorithm}] seed {seed} ({i + 1}/{len(seeds)}): final return "
                     f"{float(r.episode_return[-1]):.1f} after {int(r.env_steps[-1])} steps, "
                     f"{r.wall_time:.0f}s")
    returns = np.stack([r.episode_return for r in runs])
    return dict(algorithm=algorithm, preset=preset, env=plan["env"], settings=settings,
                budget=budget, steps_run=int(runs[0].env_steps[-1]), seeds=[int(s) for s in seeds],
                env_steps=np.asarray(runs[0].env_steps), returns=returns,
                wall_s=[float(r.wall_time) for r in runs],
                summary=summarise_returns(runs[0].env_steps, returns, plan["threshold"]))


# Aliases of the swing-up's success criterion and rates (`gpguided_jax.swingup`).
swingup_success = swingup.success
success_flags = swingup.success_flags
policy_success_rate = swingup.success_rate


def ppo_policy_fn(result: PPOResult, params: pendulum.PendulumParams, *, deterministic: bool):
    """A `pendulum.PolicyFn` (key, state) -> torque from a trained PPO policy (call under
    `jax.enable_x64(False)` with float32 pendulum params)."""
    from gpguided_jax import brax_env

    policy = result.make_policy(result.params, deterministic=deterministic)

    def policy_fn(key, state):
        action, _ = policy(brax_env.observe(state)[None], key)
        return jnp.reshape(action, ()) * params.max_torque

    return policy_fn


def ppo_success_rate(
    key: jax.Array,
    result: PPOResult,
    params: pendulum.PendulumParams,
    episode_length: int,
    num_episodes: int,
    *,
    deterministic: bool,
    **success_kwargs,
) -> float:
    """`policy_success_rate` of a trained PPO policy (mean action if `deterministic`, else sampled)."""
    with jax.enable_x64(False):
        p32 = float32_params(params)
        fn = ppo_policy_fn(result, p32, deterministic=deterministic)
        return policy_success_rate(key, p32, fn, episode_length, num_episodes, **success_kwargs)


def matched_budget_value(
    env_steps: np.ndarray, curve: np.ndarray, budget: float, *, window: float = 0.1
) -> np.ndarray:
    """Reward per step of a learning curve at an environment-step budget.

    The mean of the curve's points with env steps in ((1 - window) * budget, budget]; NaN where
    there is none (a run shorter than the budget, or evaluations sparser than the window).

    Args:
      env_steps: (E,) increasing.
      curve: (..., E).
    """
    env_steps = np.asarray(env_steps)
    curve = np.asarray(curve, float)
    sel = (env_steps <= budget * (1 + 1e-9)) & (env_steps > (1 - window) * budget)
    if not sel.any():
        return np.full(curve.shape[:-1], np.nan)
    return curve[..., sel].mean(-1)


__all__ = [
    "NAMES",
    "BudgetError",
    "after_initial_evaluation",
    "trainer_settings",
    "PPO_DEFAULTS",
    "SAC_DEFAULTS",
    "SACResult",
    "train_sac",
    "PPOResult",
    "float32_params",
    "matched_budget_value",
    "policy_success_rate",
    "ppo_policy_fn",
    "ppo_steps_per_iteration",
    "ppo_success_rate",
    "smallest_budget",
    "steps_run",
    "success_flags",
    "swingup_success",
    "train_ppo",
    "TaskResult",
    "budget_note",
    "plan_preset",
    "run_preset",
    "check_budget",
    "evaluation_steps",
    "train_on_task",
]
