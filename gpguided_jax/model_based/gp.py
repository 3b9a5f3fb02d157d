"""gp_model's GPs: the sparse GP of every output conditioned on the buffer, its refit and its
predictions (design: docs/design.md#model).

The model is the sparse GP of Titsias (2009) / DTC with `num_inducing` inducing inputs Z chosen
from the buffered inputs by farthest-point sampling in the kernel's length-scales, conditioned on
every buffered transition (`condition`); with Z the whole data it is the exact GP (tests compare
it with a Cholesky GP). Its posterior over the inducing values, in whitened coordinates v =
L^-1 u (L L^T = K_ZZ), is N(m, B^-1) with B = I + A A^T, A = L^-1 K_ZX / sigma_n, m = B^-1 A y /
sigma_n. A function drawn from it is f(x) = k(x, Z) L^-T v: smooth, and as cheap to evaluate as
the mean. The kernels are refitted by exact marginal likelihood (`hyperfit`), one per output, on
a random subset of the buffer, warm-started from the previous update's (`refit`).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero

from gpguided_jax import hyperfit, kernels
from gpguided_jax.model_based.data import ModelData, subset

JITTER = 1e-6  # relative diagonal jitter of K_ZZ (at least `jitter_floor`)


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



def k_star(model: SparseModel, x):
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



class ScaledInducing(NamedTuple):
    """The model's inducing inputs in each output's length-scales, for `mean_at` (`scaled`).

    Attributes:
      inducing: (E, M, D) Z / l_e, each output's inducing inputs divided by its length-scales.
      inverse_lengthscales: (E, D) 1 / l_e.
      signal_variance: (E,) sigma_f,e^2.
      mask: (M,) bool, the inducing inputs in use (`SparseModel.inducing_mask`).
    """

    inducing: jax.Array
    inverse_lengthscales: jax.Array
    signal_variance: jax.Array
    mask: jax.Array


def scaled(model: SparseModel) -> ScaledInducing:
    """`model`'s inducing inputs scaled once for the many evaluations of `mean_at`."""
    inv = 1.0 / model.kernels.lengthscales
    return ScaledInducing(model.inducing[None] * inv[:, None, :], inv,
                          model.kernels.signal_variance, model.inducing_mask)


def _scaled_rows(zs, inv_l, sf2, mask, x):
    """d_em = z_m / l_e - x / l_e, (E, M, D), and the kernel rows k_em, (E, M), 0 where unused."""
    d = zs - (x * inv_l)[:, None, :]
    return d, jnp.where(mask, sf2[:, None] * jnp.exp(-0.5 * jnp.sum(d * d, axis=-1)), 0.0)


@jax.custom_jvp
def _mean_row(zs, inv_l, sf2, mask, weights, x):
    return jnp.sum(_scaled_rows(zs, inv_l, sf2, mask, x)[1] * weights, axis=-1)


def _mean_row_jvp(primals, tangents):
    """The derivative of f_e = sum_m w_em k_e(x, z_m), k_e = sf_e^2 exp(-|d_em|^2 / 2), d_em =
    z_m / l_e - x / l_e, in closed form: df_e/dx = (sum_m w_em k_em d_em) / l_e, a (E, D) matrix
    made in the forward pass, so that reverse mode keeps it instead of the (E, M) kernel rows."""
    zs, inv_l, sf2, mask, weights, x = primals
    t_zs, t_inv, t_sf2, _, t_w, t_x = tangents
    d, k = _scaled_rows(zs, inv_l, sf2, mask, x)
    wk = k * weights
    out = jnp.sum(wk, axis=-1)
    g = jnp.einsum("em,emd->ed", wk, d)  # sum_m w_em k_em d_em
    zero = lambda t: isinstance(t, SymbolicZero)  # noqa: E731
    t_out = jnp.zeros_like(out)
    if not zero(t_x):
        t_out = t_out + (g * inv_l) @ t_x
    if not zero(t_inv):
        t_out = t_out + jnp.sum(g * x * t_inv, axis=-1)
    if not zero(t_zs):
        t_out = t_out - jnp.einsum("emd,emd->e", wk[..., None] * d, t_zs)
    if not zero(t_sf2):
        t_out = t_out + out * t_sf2 / sf2
    if not zero(t_w):
        t_out = t_out + jnp.sum(k * t_w, axis=-1)
    return out, t_out


_mean_row.defjvp(_mean_row_jvp, symbolic_zeros=True)


def mean_at(s: ScaledInducing, weights, x):
    """(E,) sum_m w_em k_e(x, z_m), the mean (`SparseModel.weights`) or a drawn function's value
    (`sample_weights`) of every output at one input x, from `scaled`: the same function as
    `k_star(model, x) . weights`, with its derivative in closed form (`_mean_row_jvp`), which the
    simulated roll-outs' reverse mode keeps as (E, D) per step instead of the (E, M) kernel rows:
    at hundreds of inducing inputs the gradient then costs a few times less. Tests compare it
    with autodiff through `k_star`."""
    return _mean_row(s.inducing, s.inverse_lengthscales, s.signal_variance, s.mask, weights, x)


def predict(model: SparseModel, x):
    """The latent predictive mean and variance of every output at one input x: (E,), (E,)."""
    ks = k_star(model, x)
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
