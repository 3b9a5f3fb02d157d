"""Hand-derived policy gradients vs autodiff over random cases (eq. 1, 17-19, 21-22).

For each policy/equation and controller, draws `--cases` random cases (state, controller
weights, log sigma, an exact GP on up to 8 basis vectors around the state with some slots masked
off, lambda_v, floors, beta, sigma_e, candidate scale, and the action: sampled or at the torque
limit), vmapped, and reports the largest norm-wise relative difference
max|hand - autodiff| / max|autodiff| against reverse-mode (jax.grad) and forward-mode
(jax.jacfwd) autodiff, in float64.

The Gibbs score is written relative to the selected candidate (both `log_prob` and the hand
score), so it stays accurate relative to its own size even when pi_J -> 1.

Writes the rows as JSON to --out (the documentation's gradient-check table is generated from
docs/results/gradient_check.json) and prints them as a Markdown table.

Usage: python experiments/gradient_check.py [--cases 1000] [--seed 0]
                                            [--out docs/results/gradient_check.json]
"""

import argparse
import json
import os

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

import gpguided_jax
from gpguided_jax import controllers, kernels, policies, sparse_gp

gpguided_jax.enable_x64()

SLOTS = 8
NUM_CANDIDATES = 16
CONTROLLER_NAMES = ("linear", "rbf")


def _exact_gp(key, state, action_centre, n_active, alpha_scale):
    k_state, k_action, k_y, k_hyper = jax.random.split(key, 4)
    states = state + jax.random.normal(k_state, (SLOTS, 2)) * jnp.array([0.5, 1.0])
    actions = action_centre + 2.0 * jax.random.normal(k_action, (SLOTS,))
    basis = jax.vmap(kernels.state_action_features)(states, actions)
    lengthscales = jnp.exp(jax.random.uniform(k_hyper, (4,), minval=jnp.log(0.3), maxval=1.1))
    hyper = kernels.make_kernel_params(lengthscales, 2.0, 0.1)
    y = 3.0 * jax.random.normal(k_y, (SLOTS,)) - 5.0
    gp = sparse_gp.exact_state(basis, y, hyper, capacity=SLOTS, num_active=n_active)
    return gp._replace(alpha=alpha_scale * gp.alpha), hyper


def _random_case(key, policy, controller):
    keys = jax.random.split(key, 16)

    def uniform(i, lo, hi):
        return jax.random.uniform(keys[i], (), minval=lo, maxval=hi)

    state = jnp.array([uniform(0, -10.0, 10.0), uniform(1, -15.0, 15.0)])
    flat, unravel = ravel_pytree(controller.init())
    weights = jnp.exp(uniform(2, -7.0, 4.0)) * jax.random.normal(keys[3], flat.shape)
    theta = policies.PolicyParams(controller=unravel(weights), log_std=uniform(4, -9.0, 4.0))
    n_active = jax.random.randint(keys[5], (), 0, SLOTS + 1)
    alpha_scale = jax.random.choice(keys[6], jnp.array([0.0, 1.0, 30.0]))
    gp, hyper = _exact_gp(
        keys[7], state, controller.apply(theta.controller, state), n_active, alpha_scale
    )
    ctx = policies.make_context(
        gp,
        hyper,
        variance_scale=jnp.exp(uniform(8, jnp.log(1e-8), jnp.log(1e6))),
        variance_floor=jnp.exp(uniform(9, jnp.log(1e-12), jnp.log(1e2))),
        inverse_temperature=uniform(10, 0.1, 100.0),
        energy_width=jnp.exp(uniform(11, jnp.log(0.05), jnp.log(20.0))),
        candidate_scale=jnp.exp(uniform(12, jnp.log(1e-3), jnp.log(1e3))),
        candidate_floor=jnp.exp(uniform(13, jnp.log(1e-6), jnp.log(10.0))),
    )
    action, aux = policy.sample(keys[14], theta, state, ctx)
    mode = jax.random.randint(keys[15], (), 0, 4)  # 0, 1: sampled; 2: +u_max; 3: -u_max
    u_max = controller.u_max
    action = jnp.select([mode == 2, mode == 3], [u_max, -u_max], action)
    return theta, state, action, ctx, aux


def _flat(tree):
    return ravel_pytree(tree)[0]


def _relative_difference(hand, auto):
    """max|hand - auto| / max|auto| over the flattened pytree (0 when both are exactly 0)."""
    diff = jnp.max(jnp.abs(_flat(hand) - _flat(auto)))
    scale = jnp.max(jnp.abs(_flat(auto)))
    return jnp.where(diff == 0.0, 0.0, diff / jnp.maximum(scale, 1e-300))


def _compare(hand, reverse, forward):
    return _relative_difference(hand, reverse), _relative_difference(hand, forward)


def _score_check(policy, controller):
    def one(key):
        theta, state, action, ctx, aux = _random_case(key, policy, controller)
        hand = policy.grad_log_prob(theta, state, action, ctx, aux)
        reverse = jax.grad(policy.log_prob)(theta, state, action, ctx, aux)
        forward = jax.jacfwd(policy.log_prob)(theta, state, action, ctx, aux)
        return _compare(hand, reverse, forward)

    return one


def _variance_check(controller):
    policy = policies.make_policy("guided_variance", controller)

    def one(key):
        theta, state, _, ctx, _ = _random_case(key, policy, controller)
        _, hand, _, _ = policies.guided_variance_and_grad(controller, theta.controller, state, ctx)
        args = (controller, theta.controller, state, ctx)
        reverse = jax.grad(policies.guided_variance, argnums=1)(*args)
        forward = jax.jacfwd(policies.guided_variance, argnums=1)(*args)
        return _compare(hand, reverse, forward)

    return one


def _printed_eq17_check(controller):
    """The score as printed in eq. 17, without the 1/2 on the variance term (expected to fail)."""
    policy = policies.make_policy("guided_variance", controller)

    def one(key):
        theta, state, action, ctx, aux = _random_case(key, policy, controller)
        variance, grad_var, mean_action, grad_mean = policies.guided_variance_and_grad(
            controller, theta.controller, state, ctx
        )
        diff = action - mean_action
        printed = policies.PolicyParams(
            controller=jax.tree_util.tree_map(
                lambda gm, gv: diff / variance * gm + (diff**2 - variance) / variance**2 * gv,
                grad_mean,
                grad_var,
            ),
            log_std=jnp.zeros_like(theta.log_std),
        )
        reverse = jax.grad(policy.log_prob)(theta, state, action, ctx, aux)
        forward = jax.jacfwd(policy.log_prob)(theta, state, action, ctx, aux)
        return _compare(printed, reverse, forward)

    return one


def _controller_check(controller):
    def one(key):
        flat, unravel = ravel_pytree(controller.init())
        k_w, k_scale, k_s = jax.random.split(key, 3)
        scale = jnp.exp(jax.random.uniform(k_scale, (), minval=-7.0, maxval=4.0))
        params = unravel(scale * jax.random.normal(k_w, flat.shape))
        state = jax.random.uniform(k_s, (2,), minval=-10.0, maxval=10.0)
        _, hand = controller.value_and_grad(params, state)
        reverse = jax.grad(controller.apply)(params, state)
        forward = jax.jacfwd(controller.apply)(params, state)
        return _compare(hand, reverse, forward)

    return one


def run(num_cases: int, seed: int):
    rows = []
    for controller_name in CONTROLLER_NAMES:
        controller = controllers.make_controller(controller_name)
        checks = [
            ("controller c(s) = u tanh(theta^T psi)", "dc/dtheta_c", _controller_check(controller)),
            (
                "fixed noise",
                "eq. 1 score",
                _score_check(policies.make_policy("fixed_noise", controller), controller),
            ),
            (
                "guided variance",
                "eq. 18-19: grad sigma^2_GP alone",
                _variance_check(controller),
            ),
            (
                "guided variance",
                "eq. 17-19 score (with the 1/2)",
                _score_check(policies.make_policy("guided_variance", controller), controller),
            ),
            (
                "guided variance",
                "eq. 17 as printed (no 1/2): expected to disagree",
                _printed_eq17_check(controller),
            ),
            (
                "Gibbs",
                "eq. 21-22 score",
                _score_check(
                    policies.make_policy("gibbs", controller, num_candidates=NUM_CANDIDATES),
                    controller,
                ),
            ),
        ]
        for policy_name, equation, check in checks:
            keys = jax.random.split(jax.random.PRNGKey(seed), num_cases)
            rel_rev, rel_fwd = jax.jit(jax.vmap(check))(keys)
            rows.append(
                (
                    policy_name,
                    equation,
                    controller_name,
                    float(jnp.max(rel_rev)),
                    float(jnp.median(rel_rev)),
                    float(jnp.max(rel_fwd)),
                )
            )
    return rows


def to_markdown(rows, num_cases):
    lines = [
        f"Hand-derived vs autodiff gradients, float64, {num_cases} random cases per row "
        "(norm-wise relative difference max|hand - auto| / max|auto|).",
        "",
        "| policy | equation | controller | max rel. diff vs jax.grad | median vs jax.grad "
        "| max rel. diff vs jax.jacfwd |",
        "|---|---|---|---|---|---|",
    ]
    for policy_name, equation, controller_name, mx, med, fwd in rows:
        lines.append(
            f"| {policy_name} | {equation} | {controller_name} | {mx:.1e} | {med:.1e} "
            f"| {fwd:.1e} |"
        )
    return "\n".join(lines) + "\n"


def to_json(rows, num_cases, seed):
    keys = ("policy", "equation", "controller", "max_vs_grad", "median_vs_grad", "max_vs_jacfwd")
    return {
        "cases": num_cases,
        "seed": seed,
        "dtype": "float64",
        "jax": jax.__version__,
        "rows": [dict(zip(keys, row)) for row in rows],
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="docs/results/gradient_check.json")
    args = parser.parse_args()
    rows = run(args.cases, args.seed)
    print(to_markdown(rows, args.cases))
    if os.path.dirname(args.out):
        os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(to_json(rows, args.cases, args.seed), f, indent=2)
        f.write("\n")


if __name__ == "__main__":
    main()
