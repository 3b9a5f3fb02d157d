"""Type-II maximum likelihood for the kernel hyperparameters (paper §VI; design:
docs/design.md#gp-model).

The exact GP negative log marginal likelihood of N pairs (about 2000 in the paper's protocol) under
the zero-mean ARD squared-exponential prior with Gaussian noise,

  -log p(y | X) = 1/2 y^T (K + sigma_n^2 I)^{-1} y + sum_i log L_ii + N/2 log(2 pi),

with L the Cholesky factor of K + sigma_n^2 I, is minimised over the log-parameters
(log l_1..l_D, log sigma_f^2, log sigma_n^2) in a `lax.scan`, so one fit is one compiled program and
`jax.vmap(fit)` fits several seeds' data sets at once. `fit`'s default optimiser is L-BFGS (optax) with
a backtracking (Armijo) line search, on a smooth box parametrisation: each log-parameter is
lo + (hi - lo) sigmoid(u), u unconstrained. The line search needs only the likelihood (one
Cholesky) at trial points and the closed-form gradient at accepted ones, so 15 iterations cost
a fraction of 100 Adam steps and end at a higher likelihood. Adam (`optimizer="adam"`) remains
available, and training uses it by default (`TrainConfig.hyperfit_optimizer`, 100 steps): on the
paper preset the L-BFGS fit changes guided_direction's results and makes them dtype-dependent
(design: docs/design.md#decisions).

The prior mean is zero, as in the online GP (`sparse_gp`), which has no mean function: the fitted
signal variance therefore also absorbs the targets' offset. Centre the targets first if the online
GP will be given centred targets.

Guards: the log-parameters stay in a box around the data scales (L-BFGS: by the parametrisation;
Adam: clipped after every step), so no parameter can run to 0 or infinity; a relative jitter is
added to the diagonal; a trial point whose likelihood is not finite is rejected by the line search
(Adam: a step whose loss or gradient is not finite is rejected).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax

from gpguided_jax import kernels


class LogParams(NamedTuple):
    """Unconstrained parameterisation of `kernels.KernelParams`.

    Attributes:
      log_lengthscales: (D,) log l_d.
      log_signal_variance: () log sigma_f^2.
      log_noise_variance: () log sigma_n^2.
    """

    log_lengthscales: jax.Array
    log_signal_variance: jax.Array
    log_noise_variance: jax.Array


class FitResult(NamedTuple):
    """Output of `fit`.

    Attributes:
      params: the fitted `kernels.KernelParams` (natural, positive values).
      losses: (num_steps,) negative log marginal likelihood before each step (the loss curve).
      final_loss: () negative log marginal likelihood at the returned parameters.
    """

    params: kernels.KernelParams
    losses: jax.Array
    final_loss: jax.Array


def to_log(hyper: kernels.KernelParams) -> LogParams:
    return LogParams(
        jnp.log(hyper.lengthscales), jnp.log(hyper.signal_variance), jnp.log(hyper.noise_variance)
    )


def from_log(log_hyper: LogParams) -> kernels.KernelParams:
    return kernels.KernelParams(
        lengthscales=jnp.exp(log_hyper.log_lengthscales),
        signal_variance=jnp.exp(log_hyper.log_signal_variance),
        noise_variance=jnp.exp(log_hyper.log_noise_variance),
    )


def negative_log_marginal_likelihood(
    hyper: kernels.KernelParams, xs: jax.Array, ys: jax.Array, jitter: float = 1e-8
) -> jax.Array:
    """Exact GP -log p(y | X, hyper) by Cholesky (zero prior mean).

    Args:
      hyper: kernel hyperparameters.
      xs: (N, D) inputs.
      ys: (N,) targets.
      jitter: added to the diagonal, relative to the signal variance.

    Returns:
      Scalar negative log marginal likelihood.
    """
    n = xs.shape[0]
    K = kernels.gram(xs, xs, hyper)
    K = K + (hyper.noise_variance + jitter * hyper.signal_variance) * jnp.eye(n, dtype=K.dtype)
    L = jnp.linalg.cholesky(K)
    z = jax.scipy.linalg.solve_triangular(L, ys, lower=True)
    return 0.5 * z @ z + jnp.sum(jnp.log(jnp.diagonal(L))) + 0.5 * n * math.log(2 * math.pi)


def nlml_log(log_hyper: LogParams, xs: jax.Array, ys: jax.Array, jitter: float = 1e-8):
    """`negative_log_marginal_likelihood` as a function of the log-parameters."""
    return negative_log_marginal_likelihood(from_log(log_hyper), xs, ys, jitter)


def nlml_and_grad(log_hyper: LogParams, xs: jax.Array, ys: jax.Array, jitter: float = 1e-8):
    """`nlml_log` and its gradient with respect to the log-parameters, in closed form.

    With A = K + (sigma_n^2 + jitter sigma_f^2) I, a = A^{-1} y and W = A^{-1} - a a^T,
    d(-log p)/d theta = 1/2 tr(W dA/d theta), where dA/d log l_d = K * (x_id - x_jd)^2 / l_d^2,
    dA/d log sigma_f^2 = K + jitter sigma_f^2 I and dA/d log sigma_n^2 = sigma_n^2 I. This costs one
    Cholesky and the inverse A^{-1} from it (`cholesky_inverse`, 4/3 N^3 flops in matrix products),
    several times less than reverse-mode autodiff through the Cholesky; `tests/test_hyperfit.py`
    checks it against `jax.grad(nlml_log)`.

    Returns:
      (loss, grads) with grads a `LogParams`.
    """
    hyper = from_log(log_hyper)
    n = xs.shape[0]
    K = kernels.gram(xs, xs, hyper)
    diag_add = hyper.noise_variance + jitter * hyper.signal_variance
    L = jnp.linalg.cholesky(K + diag_add * jnp.eye(n, dtype=xs.dtype))
    z = jax.scipy.linalg.solve_triangular(L, ys, lower=True)
    a = jax.scipy.linalg.solve_triangular(L, z, lower=True, trans=1)
    A_inv = _gram_of_lower(_lower_inverse(L), assemble=False)
    loss = 0.5 * z @ z + jnp.sum(jnp.log(jnp.diagonal(L))) + 0.5 * n * math.log(2 * math.pi)
    # W = A^{-1} - a a^T. sum_ij (W * K)_ij (x_id - x_jd)^2 = 2 sum_i x_id^2 (WK 1)_i
    # - 2 x_d^T (W * K) x_d (symmetric), which avoids an (N, N, D) tensor: both come from
    # (W * K) [x, 1], formed block by block of A^{-1} without assembling it.
    both, trace_a_inv = _hadamard_times(A_inv, a, K, jnp.concatenate([xs, jnp.ones((n, 1), xs.dtype)], 1))
    trace_w = trace_a_inv - a @ a
    quad, row_sums = jnp.sum(xs * both[:, :-1], axis=0), both[:, -1]
    sq_sums = 2.0 * (row_sums @ (xs * xs)) - 2.0 * quad
    grad_ls = 0.5 * sq_sums / hyper.lengthscales**2
    grad_sf = 0.5 * (jnp.sum(row_sums) + jitter * hyper.signal_variance * trace_w)
    grad_sn = 0.5 * hyper.noise_variance * trace_w
    return loss, LogParams(grad_ls, grad_sf, grad_sn)


# ------------------------------------------------------------------------------------------------
# A^{-1} from the Cholesky factor, in matrix products (LAPACK's potri, which jaxlib does not
# expose). A lower-triangular matrix is inverted by 2 x 2 blocks,
#   [[L11, 0], [L21, L22]]^{-1} = [[X11, 0], [X21, X22]],  X21 = -X22 L21 X11,
# recursively down to blocks of at most `_INVERSE_BLOCK` rows (inverted by a triangular solve), and
# A^{-1} = X^T X is formed block by block; no product touches the zero triangle. That is about
# 4/3 N^3 flops against 3 N^3 for a triangular solve with the identity and a full product X^T X,
# and they run at the matrix-product rate (design: docs/design.md#decisions). The gradient reads
# A^{-1} block by block without assembling it (`_hadamard_times`). The accuracy is that of the
# triangular solve it replaced (both are set by the conditioning of A; tests/test_hyperfit.py
# checks it against an 80-bit inverse).
# ------------------------------------------------------------------------------------------------

_INVERSE_BLOCK = 128  # fewer recursion levels compile faster than smaller blocks, and run as fast


def _lower_inverse(L):
    """L^{-1} of a lower-triangular L as nested blocks: a matrix, or (X11, X21, X22)."""
    n = L.shape[0]
    if n <= _INVERSE_BLOCK:
        return jax.scipy.linalg.solve_triangular(L, jnp.eye(n, dtype=L.dtype), lower=True)
    h = n // 2
    X11 = _lower_inverse(L[:h, :h])
    X22 = _lower_inverse(L[h:, h:])
    return X11, -_lower_times(X22, _times_lower(L[h:, :h], X11)), X22


def _size(X) -> int:
    """Rows of a nested block matrix."""
    return _size(X[0]) + _size(X[2]) if isinstance(X, tuple) else X.shape[0]


def _times_lower(M, X):
    """M X for a nested lower-triangular X."""
    if not isinstance(X, tuple):
        return M @ X
    X11, X21, X22 = X
    h = _size(X11)
    return jnp.concatenate([_times_lower(M[:, :h], X11) + M[:, h:] @ X21,
                            _times_lower(M[:, h:], X22)], axis=1)


def _lower_times(X, M):
    """X M for a nested lower-triangular X."""
    if not isinstance(X, tuple):
        return X @ M
    X11, X21, X22 = X
    h = _size(X11)
    return jnp.concatenate([_lower_times(X11, M[:h]), X21 @ M[:h] + _lower_times(X22, M[h:])],
                           axis=0)


def _lower_transpose_times(X, M):
    """X^T M for a nested lower-triangular X."""
    if not isinstance(X, tuple):
        return X.T @ M
    X11, X21, X22 = X
    h = _size(X11)
    return jnp.concatenate([_lower_transpose_times(X11, M[:h]) + X21.T @ M[h:],
                            _lower_transpose_times(X22, M[h:])], axis=0)


def _gram_of_lower(X, assemble=True):
    """X^T X for a nested lower-triangular X (symmetric), formed by blocks: one matrix, or with
    `assemble=False` nested blocks (top_left, bottom_left, bottom_right) of the lower half."""
    if not isinstance(X, tuple):
        return X.T @ X
    X11, X21, X22 = X
    top_left = _add(_gram_of_lower(X11, assemble), X21.T @ X21)
    bottom_left = _lower_transpose_times(X22, X21)
    bottom_right = _gram_of_lower(X22, assemble)
    if not assemble:
        return top_left, bottom_left, bottom_right
    return jnp.block([[top_left, bottom_left.T], [bottom_left, bottom_right]])


def _add(S, M):
    """S + M for a nested symmetric S (as `_gram_of_lower(..., assemble=False)` makes it)."""
    if not isinstance(S, tuple):
        return S + M
    h = _size(S[0])
    return _add(S[0], M[:h, :h]), S[1] + M[h:, :h], _add(S[2], M[h:, h:])


def _hadamard_times(S, a, K, V):
    """((S - a a^T) * K) V and trace(S) for a nested symmetric S, block by block."""
    if not isinstance(S, tuple):
        return ((S - jnp.outer(a, a)) * K) @ V, jnp.trace(S)
    h = _size(S[0])
    W21 = (S[1] - jnp.outer(a[h:], a[:h])) * K[h:, :h]
    top, trace_top = _hadamard_times(S[0], a[:h], K[:h, :h], V[:h])
    bottom, trace_bottom = _hadamard_times(S[2], a[h:], K[h:, h:], V[h:])
    return (jnp.concatenate([top + W21.T @ V[h:], bottom + W21 @ V[:h]]),
            trace_top + trace_bottom)


def cholesky_inverse(L: jax.Array) -> jax.Array:
    """A^{-1} = L^{-T} L^{-1} from the lower Cholesky factor L of A (N, N), by blocked matrix
    products (LAPACK's potri; see the notes above)."""
    return _gram_of_lower(_lower_inverse(L))


def initial_guess(xs: jax.Array, ys: jax.Array) -> kernels.KernelParams:
    """A data-driven starting point.

    Lengthscales: the per-dimension standard deviation of the inputs (a floor of 1e-3 keeps a
    constant feature usable). Signal variance: the mean square of the targets (zero-mean prior).
    Noise variance: a tenth of that.
    """
    second_moment = jnp.maximum(jnp.mean(ys**2), 1e-12)
    return kernels.KernelParams(
        lengthscales=jnp.maximum(jnp.std(xs, axis=0), 1e-3),
        signal_variance=second_moment,
        noise_variance=0.1 * second_moment,
    )


def parameter_bounds(xs: jax.Array, ys: jax.Array) -> tuple[LogParams, LogParams]:
    """Box on the log-parameters, from the data scales.

    l_d in [1e-2, 1e2] x std(x_d); sigma_f^2 in [1e-4, 1e2] x mean(y^2);
    sigma_n^2 in [1e-8, 1] x mean(y^2).
    """
    x_scale = jnp.maximum(jnp.std(xs, axis=0), 1e-3)
    y_scale = jnp.maximum(jnp.mean(ys**2), 1e-12)
    log_x, log_y = jnp.log(x_scale), jnp.log(y_scale)
    lower = LogParams(log_x + math.log(1e-2), log_y + math.log(1e-4), log_y + math.log(1e-8))
    upper = LogParams(log_x + math.log(1e2), log_y + math.log(1e2), log_y)
    return lower, upper


OPTIMIZERS = ("lbfgs", "adam")


def fit(
    xs: jax.Array,
    ys: jax.Array,
    *,
    num_steps: int = 15,
    optimizer: str = "lbfgs",
    learning_rate: float = 0.05,
    init: kernels.KernelParams | None = None,
    jitter: float = 1e-8,
) -> FitResult:
    """Minimises the exact negative log marginal likelihood over the log-parameters.

    A pure function of its array arguments: wrap it in `jax.jit` (``num_steps``, ``optimizer``
    static) and `jax.vmap` over seeds (leading axis of xs, ys, and of init if given). Use float64
    inputs where possible (the Cholesky of an N = 500-2000 Gram matrix); float32 works with the
    jitter.

    Args:
      xs: (N, D) inputs.
      ys: (N,) targets.
      num_steps: L-BFGS iterations or Adam steps (static).
      optimizer: ``"lbfgs"`` (default) or ``"adam"`` (static).
      learning_rate: Adam's step size (traceable; unused by L-BFGS).
      init: starting hyperparameters; default `initial_guess(xs, ys)`.
      jitter: relative diagonal jitter.

    Returns:
      `FitResult` with the fitted parameters and the loss curve.
    """
    if optimizer not in OPTIMIZERS:
        raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {optimizer!r}")
    lower, upper = parameter_bounds(xs, ys)
    init = initial_guess(xs, ys) if init is None else init
    init = jax.tree.map(lambda a: jnp.asarray(a, xs.dtype), init)
    params0 = jax.tree.map(jnp.clip, to_log(init), lower, upper)
    if optimizer == "adam":
        params, losses = _fit_adam(params0, xs, ys, lower, upper, num_steps, learning_rate, jitter)
    else:
        params, losses = _fit_lbfgs(params0, xs, ys, lower, upper, num_steps, jitter)
    final_loss = nlml_log(params, xs, ys, jitter)
    return FitResult(params=from_log(params), losses=losses, final_loss=final_loss)


def _fit_lbfgs(params0, xs, ys, lower, upper, num_steps, jitter):
    """L-BFGS with a backtracking line search on u, log-params = lo + (hi - lo) sigmoid(u)."""
    margin = 1e-6  # start strictly inside the box (sigmoid^-1 of 0 or 1 is infinite)

    def to_u(p):
        def one(v, lo, hi):
            t = jnp.clip((v - lo) / (hi - lo), margin, 1.0 - margin)
            return jnp.log(t) - jnp.log1p(-t)

        return jax.tree.map(one, p, lower, upper)

    def from_u(u):
        return jax.tree.map(lambda v, lo, hi: lo + (hi - lo) * jax.nn.sigmoid(v), u, lower, upper)

    def value_and_grad(u):
        p, pullback = jax.vjp(from_u, u)
        loss, grads = nlml_and_grad(p, xs, ys, jitter)
        return loss, pullback(grads)[0]

    def value(u):
        loss = nlml_log(from_u(u), xs, ys, jitter)
        return jnp.where(jnp.isfinite(loss), loss, jnp.inf)  # the line search then backs off

    optimiser = optax.lbfgs(
        memory_size=10,
        linesearch=optax.scale_by_backtracking_linesearch(
            max_backtracking_steps=20, increase_factor=math.inf, max_learning_rate=1.0),
    )

    def step(carry, _):
        u, opt_state = carry
        loss, grads = value_and_grad(u)
        updates, new_state = optimiser.update(grads, opt_state, u, value=loss, grad=grads,
                                              value_fn=value)
        new_u = optax.apply_updates(u, updates)
        finite = jnp.isfinite(loss) & jnp.all(
            jnp.stack([jnp.all(jnp.isfinite(g)) for g in jax.tree.leaves(new_u)]))
        u = jax.tree.map(lambda a, b: jnp.where(finite, a, b), new_u, u)
        opt_state = jax.tree.map(lambda a, b: jnp.where(finite, a, b), new_state, opt_state)
        return (u, opt_state), loss

    u0 = to_u(params0)
    (u, _), losses = jax.lax.scan(step, (u0, optimiser.init(u0)), None, length=num_steps)
    return from_u(u), losses


def _fit_adam(params0, xs, ys, lower, upper, num_steps, learning_rate, jitter):
    optimiser = optax.adam(learning_rate)

    def step(carry, _):
        params, opt_state = carry
        loss, grads = nlml_and_grad(params, xs, ys, jitter)
        updates, new_opt_state = optimiser.update(grads, opt_state, params)
        new_params = optax.apply_updates(params, updates)
        new_params = jax.tree.map(jnp.clip, new_params, lower, upper)
        finite = jnp.isfinite(loss) & jnp.all(
            jnp.stack([jnp.all(jnp.isfinite(g)) for g in jax.tree.leaves(grads)])
        )
        # Reject a step whose loss or gradient is not finite (e.g. a failed Cholesky).
        params = jax.tree.map(lambda a, b: jnp.where(finite, a, b), new_params, params)
        opt_state = jax.tree.map(lambda a, b: jnp.where(finite, a, b), new_opt_state, opt_state)
        return (params, opt_state), loss

    (params, _), losses = jax.lax.scan(
        step, (params0, optimiser.init(params0)), None, length=num_steps
    )
    return params, losses
