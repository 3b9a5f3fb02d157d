"""Training throughput: the paper-preset run as one compiled program vs a per-seed NumPy loop.

    python experiments/bench_train.py [--seeds 10] [--methods ...] [--numpy-updates 4]

For each method: compile time and run time of `jit(vmap(train))` over the seeds (the run timed on
a second call with other keys), and seed-steps per second (seeds x updates x episodes x steps /
run time). The NumPy baseline does the same work as `gp_pg` for one seed — pendulum RK4 steps,
the fixed-noise linear policy and its score, the online GP (`gp_reference.OnlineGP`) update with
every (x, return) pair, Q predictions and the SGD step — for `--numpy-updates` updates, and is
extrapolated linearly to all updates and seeds (the hyperparameter fit is excluded from both).
Output: JSON on stdout.
"""

import argparse
import json
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import gpguided_jax
from gpguided_jax import config as C
from gpguided_jax import gp_reference
from gpguided_jax import train as T

gpguided_jax.enable_x64()  # float64 (the package leaves the choice to its user)


def numpy_gp_pg_updates(cfg, prior, num_updates, rng):
    """Per-seed NumPy Algorithm 1 (method gp_pg, linear controller): returns wall seconds.

    `prior` is the seed's `train.GPPrior`; the reference GP has a zero prior mean, so it is fed
    centred returns and its predictions are shifted back, as the JAX GP does internally."""
    kernel, m0 = prior.kernel, float(prior.mean)
    p = cfg.pendulum
    m, l, g, dt = float(p.mass), float(p.length), float(p.gravity), float(p.dt)
    b, umax, noise = float(p.friction), float(p.max_torque), float(p.reward_noise_std)
    gamma, lr = float(cfg.discount), float(cfg.learning_rate)
    w, log_std = np.zeros(4), float(cfg.init_log_std)
    gp = gp_reference.OnlineGP(
        cfg.gp_capacity, 4, np.asarray(kernel.lengthscales), float(kernel.signal_variance),
        float(kernel.noise_variance), novelty_tol=float(cfg.novelty_tol),
        age_penalty=float(cfg.age_penalty), age_scale=float(cfg.age_scale), age_fn=cfg.age_fn)

    def f(y, u):
        return np.array([y[1], (u - b * y[1] - m * g * l * math.sin(y[0])) / (m * l * l)])

    t0 = time.perf_counter()
    for t in range(num_updates):
        scores, feats = [], []
        for _ in range(cfg.episodes_per_update):
            s = np.asarray(p.start_mean, float) + np.asarray(p.start_std, float) * rng.normal(size=2)
            s[0] %= 2 * math.pi
            rewards = []
            for _ in range(cfg.episode_length):
                psi = np.array([math.sin(s[0]), math.cos(s[0]), s[1], 1.0])
                z = math.tanh(w @ psi)
                c = 5.0 * z
                sigma = math.exp(log_std)
                a = c + sigma * rng.normal()
                dc = 5.0 * (1 - z * z) * psi
                scores.append(np.append((a - c) / sigma**2 * dc, (a - c) ** 2 / sigma**2 - 1.0))
                feats.append(np.array([psi[0], psi[1], s[1], a]))
                u = min(max(a, -umax), umax)
                k1 = f(s, u)
                k2 = f(s + 0.5 * dt * k1, u)
                k3 = f(s + 0.5 * dt * k2, u)
                k4 = f(s + dt * k3, u)
                s = s + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
                s[0] %= 2 * math.pi
                rewards.append(-(s[0] - math.pi) ** 2 - (s[1] / 4) ** 2 + noise * rng.normal())
            ret = np.zeros(len(rewards))
            acc = 0.0
            for i in reversed(range(len(rewards))):
                acc = rewards[i] + gamma * acc
                ret[i] = acc
            for x, y in zip(feats[-cfg.episode_length:], ret):
                gp.update(x, y - m0, t)
        q = m0 + np.array([gp.predict(x)[0] for x in feats])
        grad = (np.array(scores) * q[:, None]).sum(0) / cfg.episodes_per_update
        w = w + lr * grad[:4]
        log_std = log_std + lr * grad[4]
    return time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--methods", nargs="+", default=list(C.METHODS))
    ap.add_argument("--numpy-updates", type=int, default=20)
    args = ap.parse_args(argv)

    out = {"benchmark": "train", "preset": args.preset, "seeds": args.seeds,
           "jax_version": jax.__version__, "gpguided_jax_version": gpguided_jax.__version__,
           "device": str(jax.devices()[0]), "device_count": jax.device_count(), "methods": {}}
    total_wall = 0.0
    kernel_batch = None
    for method in args.methods:
        cfg = C.preset(args.preset, method=method)
        train = T.make_train(cfg)
        keys = jnp.stack([jax.random.PRNGKey(s) for s in range(args.seeds)])
        if cfg.uses_gp and kernel_batch is None:
            t0 = time.perf_counter()
            kernel_batch = jax.block_until_ready(jax.jit(jax.vmap(train.fit_kernel_for_seed))(keys))
            out["hyperfit_s"] = round(time.perf_counter() - t0, 3)
            total_wall += out["hyperfit_s"]
        kern = kernel_batch if cfg.uses_gp else None
        if kern is not None:
            init = jax.jit(jax.vmap(lambda k, kk, train=train, cfg=cfg: train.init(k, cfg, kk)))
            args_init = (keys, kern)
        else:
            init = jax.jit(jax.vmap(train.init))
            args_init = (keys,)
        run = jax.jit(jax.vmap(lambda s, train=train, cfg=cfg: train.run_chunk(s, cfg, cfg.num_updates)))
        state = jax.block_until_ready(init(*args_init))
        t0 = time.perf_counter()
        compiled = run.lower(state).compile()
        compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        _, rec = compiled(state)
        jax.block_until_ready(rec)
        run_s = time.perf_counter() - t0
        steps = args.seeds * cfg.num_updates * cfg.episodes_per_update * cfg.episode_length
        out["methods"][method] = {"compile_s": round(compile_s, 3), "run_s": round(run_s, 3),
                                  "seed_steps_per_s": round(steps / run_s, 1)}
        total_wall += compile_s + run_s

    out["total_wall_s_all_methods"] = round(total_wall, 2)
    if "gp_pg" in out["methods"] and kernel_batch is not None:
        cfg = C.preset(args.preset, method="gp_pg")
        kernel0 = jax.tree_util.tree_map(lambda x: np.asarray(x)[0], kernel_batch)
        secs = numpy_gp_pg_updates(cfg, kernel0, args.numpy_updates, np.random.default_rng(0))
        per_update = secs / args.numpy_updates
        np_total = per_update * cfg.num_updates * args.seeds
        steps = args.seeds * cfg.num_updates * cfg.episodes_per_update * cfg.episode_length
        out["numpy_gp_pg"] = {
            "measured_updates": args.numpy_updates, "seconds_per_update_one_seed": round(per_update, 4),
            "extrapolated_run_s": round(np_total, 1), "seed_steps_per_s": round(steps / np_total, 1)}
        out["ratio_jax_over_numpy_gp_pg"] = round(np_total / out["methods"]["gp_pg"]["run_s"], 1)
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
