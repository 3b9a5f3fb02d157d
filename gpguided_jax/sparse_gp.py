"""Sparse online Gaussian process (Csato & Opper) in square-root form, on fixed-size buffers
(design: docs/design.md#sparse-gp).

The model (paper eq. 5-8, 10-15)
--------------------------------
The GP over inputs x in R^D has a constant prior mean m0 and the ARD squared-exponential kernel k.
Its posterior is represented through a set B of at most M basis vectors (BVs) b_1..b_n:

    mean      mu(x)      = m0 + k(x)^T alpha
    variance  sigma^2(x) = k** + k(x)^T C k(x),       k(x) = k(B, x),  k** = k(x, x),

with alpha the mean coefficients and C the (negative semi-definite) covariance correction in
Csato & Opper's sign convention (the paper writes C with the opposite sign). Q = K_B^{-1} is the
inverse Gram matrix of the BVs. alpha = K_B^{-1} f_B is the BV values mapped to coefficients, so
the posterior over alpha is Gaussian with covariance Q + C. That is what this module stores:

    T  ("gram_inv_root"):  T^T T = Q = K_B^{-1}
    Z  ("alpha_cov_root"): Z^T Z = Q + C = Cov[alpha]  (the posterior covariance of alpha)

so that, with w = T k and z = Z k,

    sigma^2(x) = gamma(x) + |z|^2,      gamma(x) = k** - |w|^2 = k** - k^T Q k >= 0,

the Nystrom residual of x (the prior variance of f(x) that the BVs do not explain, eq. 10-11) plus
a sum of squares. The variance is non-negative by construction: gamma is a difference of two
numbers, so it is clipped at 0 (its exact value is >= 0 and its rounding error is a few ulps of
k**), and |z|^2 is a sum of squares. Neither T nor Z is triangular; any square roots will do, and
orthogonal transformations of their rows leave every prediction unchanged. C = Z^T Z - T^T T and
Q = T^T T are available for analysis (`covariance_correction`, `gram_inverse`), never needed.

One update with a pair (x, y), in the paper's named steps:

1. project (eq. 10-11): k = k(B, x), w = T k, gamma = k** - |w|^2, e = Q k = T^T w (the
   coefficients of the projection of x onto the BVs).
2. insert (if x is novel, see below): x goes into a free slot j. In the new BV set,
   T gains the row t = (e_j - e)/sqrt(gamma) (then T^T T is the inverse of the bordered Gram
   matrix, Q_new = [[Q, 0], [0, 0]] + (e, -1)(e, -1)^T / gamma, Csato-Opper's), and so does Z:
   the value of f at x is not yet observed, so Cov[alpha] grows by exactly the same t t^T
   (C is padded with zeros in Csato-Opper). The kernel vector of x becomes k + k** e_j.
3. observe (eq. 7-8): the GP takes in y = f(x) + noise, f(x) ~ k^T alpha. This is a Bayesian
   update of the Gaussian over alpha with a scalar observation, done in Potter's square-root form:
       z = Z k, d = sigma_n^2 + |z|^2, g = Z^T z = Cov[alpha] k,
       alpha <- alpha + g (y - mu(x)) / d,
       Z     <- (I - beta z z^T) Z,       beta = 1 / (d + sqrt(d sigma_n^2)),
   which gives Z^T Z <- Z^T Z - g g^T / d exactly. The gain 1/d is at most 1/sigma_n^2 whatever
   rounding does, the prediction at x moves towards y by the fraction |z|^2/d < 1 (it cannot
   overshoot), and (I - beta z z^T) is a contraction, so Z never grows. This is the
   Csato-Opper update: after an insertion d = sigma_n^2 + sigma^2(x) (their q, r); for a
   projected point d = sigma_n^2 + sigma^2(x) - gamma (their eta = 1/(1 + gamma r)).
4. score (eq. 12-15): eps_i = alpha_i^2 / (Q + C)_ii + lambda g(t_i), with (Q + C)_ii = |Z e_i|^2
   the posterior variance of alpha_i.
5. delete (KL-optimal, eq. 13): removing BV j is conditioning the posterior over alpha on
   alpha_j = 0 (Csato-Opper's alpha_hat, C_hat and Q_hat are exactly that conditioning applied to
   Cov[alpha] = Q + C and to the prior covariance Q), then dropping slot j:
       alpha <- alpha - Cov[alpha] e_j alpha_j / Cov[alpha]_jj,
       X <- H X, then row j and column j of X set to 0   (X = Z and X = T),
   where H is the Householder reflection taking the unit vector X e_j / |X e_j| to +-e_j: the
   conditioning leaves X with a null direction, H turns it into row j, which is freed for the next
   insertion. This is an O(M^2) rank-one write, orthogonal, so it cannot amplify rounding errors.

Novelty and conditioning (what keeps K_B well conditioned; design: docs/design.md#sparse-gp)
-----------------------------------------------------------------------------------------
x joins the set only if gamma >= gamma_min, where
    gamma_min = max(novelty_tol * k**, resolution(dtype) * k**, noise_novelty * sigma_n^2):
a relative tolerance; the dtype's resolution (1e-6 in float64, 1e-3 in float32: gamma is a
difference of numbers of size k**, so a threshold near the rounding level would admit duplicates);
and a fraction of the noise variance (a point whose residual is far below the noise adds almost
nothing as a BV that its projection does not already give). Every BV also keeps a leave-one-out
residual 1/Q_ii >= collapse_fraction * gamma_min: an insertion that would push one existing BV
below it deletes that BV (it has "collapsed" onto the others) instead of the lowest-scoring one,
and an insertion that would push two or more below it is refused (the point gets the projected
update). So after every update 1/Q_ii >= collapse_fraction * gamma_min for every BV, hence
lambda_min(K_B) >= collapse_fraction * gamma_min / n and cond(K_B) <= n^2 k** /
(collapse_fraction * gamma_min), a bound the tests check.

Buffers have M + 1 slots (room for an insertion before the deletion); an inactive slot has mask
False, alpha 0 and zero rows and columns in T and Z. Non-finite x or y (or valid=False) leaves the
state unchanged. Everything is branch-free (`jnp.where`), jit- and vmap-able, O(M^2) per update.

Inside `update_batch`'s loops the buffers are widened to a multiple of 8 slots (`padded_slots`:
104 for M = 100) and narrowed again on the way out. The extra slots are inactive and never
written: the first free slot, where an insertion goes, is always among the first M + 1 (at most M
are active before it). The state the caller sees has M + 1 slots. The GP update is faster so on
the CPU, although the buffers hold more numbers: rows whose length is a multiple of the vector
width presumably keep XLA:CPU's loops out of their remainder code (design:
docs/design.md#decisions). The extra zeros change only the rounding of some sums, so `update_batch` equals
`update_with_info` applied pair by pair (which does not pad) in its decisions and to rounding in
its numbers. Its two loops equal each other bit for bit on a stream taken in alone; inside a larger
program XLA may compile their padded surroundings differently, and they then agree to rounding.
"""

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import custom_batching

from gpguided_jax import kernels


class SparseGPState(NamedTuple):
    """State of the online sparse GP. S = capacity + 1 slots, D = input dimension.

    Attributes:
      basis_vectors: (S, D) inputs of the basis vectors (rows of inactive slots are 0).
      alpha: (S,) posterior mean coefficients; mu(x) = m0 + k(B, x)^T alpha.
      gram_inv_root: (S, S) T with T^T T = Q = K_B^{-1} (rows: whitened coordinates, columns: slots).
      alpha_cov_root: (S, S) Z with Z^T Z = Q + C = Cov[alpha], the posterior covariance of alpha.
      timestamps: (S,) int32 index of the policy update during which each BV was added (eq. 12).
      mask: (S,) bool, True for active slots.
      prior_mean: () constant prior mean m0. Returns here are all negative; with a zero prior mean
        the GP would revert to 0 (an optimistic value) away from the data, which biases a Q-based
        gradient towards unexplored actions.
    """

    basis_vectors: jax.Array
    alpha: jax.Array
    gram_inv_root: jax.Array
    alpha_cov_root: jax.Array
    timestamps: jax.Array
    mask: jax.Array
    prior_mean: jax.Array = 0.0


class Projection(NamedTuple):
    """Step 1 (eq. 10-11): x against the current BV set. S = number of slots.

    Attributes:
      k: (S,) k(B, x), 0 on inactive slots.
      kxx: () k(x, x).
      w: (S,) T k, the whitened kernel vector; |w|^2 = k^T Q k.
      gamma: () k** - |w|^2, the novelty (Nystrom residual; unclipped, may be a rounding-level
        negative number).
    """

    k: jax.Array
    kxx: jax.Array
    w: jax.Array
    gamma: jax.Array


AGE_FUNCTIONS = ("exp", "logit")


def init(capacity: int, input_dim: int, dtype=None, prior_mean=0.0) -> SparseGPState:
    """An empty GP with room for `capacity` basis vectors (static) and a constant prior mean."""
    dtype = dtype or jnp.result_type(float)
    slots = capacity + 1
    return SparseGPState(
        basis_vectors=jnp.zeros((slots, input_dim), dtype),
        alpha=jnp.zeros((slots,), dtype),
        gram_inv_root=jnp.zeros((slots, slots), dtype),
        alpha_cov_root=jnp.zeros((slots, slots), dtype),
        timestamps=jnp.zeros((slots,), jnp.int32),
        mask=jnp.zeros((slots,), bool),
        prior_mean=jnp.asarray(prior_mean, dtype),
    )


def num_basis_vectors(state: SparseGPState) -> jax.Array:
    """Number of active basis vectors (int32 scalar)."""
    return jnp.sum(state.mask, dtype=jnp.int32)


def capacity(state: SparseGPState) -> int:
    """The static budget M (the buffers have M + 1 slots)."""
    return state.alpha.shape[-1] - 1


def masked_kernel_vector(state: SparseGPState, x: jax.Array, hyper: kernels.KernelParams):
    """k(B, x) with inactive slots set to 0: (S,)."""
    k = kernels.cross_covariance(state.basis_vectors, x, hyper)
    return jnp.where(state.mask, k, jnp.zeros_like(k))


def _cast_hyper(hyper: kernels.KernelParams, dtype) -> kernels.KernelParams:
    return jax.tree.map(lambda a: jnp.asarray(a, dtype), hyper)


def predict(state: SparseGPState, x: jax.Array, hyper: kernels.KernelParams):
    """Predictive mean (eq. 5) and latent variance (eq. 6) at one input x (D,).

    Returns:
      (mean, latent_variance), scalars; variance = max(k** - |T k|^2, 0) + |Z k|^2 >= 0.
    """
    hyper = _cast_hyper(hyper, state.alpha.dtype)
    k = masked_kernel_vector(state, x, hyper)
    w = state.gram_inv_root @ k
    z = state.alpha_cov_root @ k
    gamma = kernels.kernel_diag(x, hyper) - w @ w
    mean = state.prior_mean + k @ state.alpha
    return mean, jnp.maximum(gamma, 0.0) + z @ z


def gram_inverse(state: SparseGPState) -> jax.Array:
    """Q = K_B^{-1} = T^T T, (S, S), 0 on inactive slots (for analysis and tests; O(M^3))."""
    T = state.gram_inv_root
    return T.T @ T


def alpha_covariance(state: SparseGPState) -> jax.Array:
    """Cov[alpha] = Q + C = Z^T Z, (S, S) (for analysis and tests; O(M^3))."""
    Z = state.alpha_cov_root
    return Z.T @ Z


def covariance_correction(state: SparseGPState) -> jax.Array:
    """Csato-Opper's C = Z^T Z - T^T T (negative semi-definite), (S, S); O(M^3)."""
    return alpha_covariance(state) - gram_inverse(state)


SLOT_MULTIPLE = 8  # 1 turns the padding off (benchmarks compare the two)


def padded_slots(slots: int) -> int:
    """The slot count the update works on: `slots` rounded up to a multiple of `SLOT_MULTIPLE`
    (module notes)."""
    return -(-slots // SLOT_MULTIPLE) * SLOT_MULTIPLE


def _pad_slots(state: SparseGPState, slots: int) -> SparseGPState:
    """`state` (one GP) with inactive slots appended up to `slots`."""
    extra = slots - state.alpha.shape[-1]
    if extra == 0:
        return state

    def vec(a):
        return jnp.pad(a, (0, extra))

    return state._replace(
        basis_vectors=jnp.pad(state.basis_vectors, ((0, extra), (0, 0))),
        alpha=vec(state.alpha),
        gram_inv_root=jnp.pad(state.gram_inv_root, ((0, extra), (0, extra))),
        alpha_cov_root=jnp.pad(state.alpha_cov_root, ((0, extra), (0, extra))),
        timestamps=vec(state.timestamps),
        mask=vec(state.mask),
    )


def _unpad_slots(state: SparseGPState, slots: int) -> SparseGPState:
    """The first `slots` slots of a padded `state` (the others are inactive and zero)."""
    if state.alpha.shape[-1] == slots:
        return state
    return state._replace(
        basis_vectors=state.basis_vectors[:slots],
        alpha=state.alpha[:slots],
        gram_inv_root=state.gram_inv_root[:slots, :slots],
        alpha_cov_root=state.alpha_cov_root[:slots, :slots],
        timestamps=state.timestamps[:slots],
        mask=state.mask[:slots],
    )


def exact_state(
    xs: jax.Array,
    ys: jax.Array,
    hyper: kernels.KernelParams,
    *,
    capacity: int | None = None,
    num_active=None,
    prior_mean=0.0,
    jitter=0.0,
) -> SparseGPState:
    """The full (exact) GP on the points xs as a `SparseGPState`, built by eigendecomposition.

    Independent of the online recursion: alpha = (K + sigma_n^2 I)^{-1} (y - m0),
    Cov[alpha] = K^{-1} - (K + sigma_n^2 I)^{-1} = U diag(sigma_n^2 / (l (l + sigma_n^2))) U^T and
    K^{-1} = U diag(1/l) U^T for K = U diag(l) U^T. For tests, notebooks and figures.

    Args:
      xs: (N, D) inputs (all become basis vectors; K must be non-singular).
      ys: (N,) targets.
      hyper: kernel hyperparameters.
      capacity: buffer capacity M >= N (default N).
      num_active: optional (traceable) number of leading points that are active (default N).
      prior_mean: constant prior mean m0.
      jitter: added to the diagonal of K for T and Z (for nearly singular K; alpha is exact).
    """
    n, d = xs.shape
    dtype = xs.dtype
    hyper = _cast_hyper(hyper, dtype)
    slots = (n if capacity is None else capacity) + 1
    if slots < n + 1:
        raise ValueError(f"capacity must be >= the number of points, got {capacity} < {n}")
    active = jnp.arange(n) < (n if num_active is None else num_active)
    both = active[:, None] & active[None, :]
    eye = jnp.eye(n, dtype=dtype)
    gram = jnp.where(both, kernels.gram(xs, xs, hyper), eye)
    lam, U = jnp.linalg.eigh(gram)
    sn2 = hyper.noise_variance
    r = jnp.asarray(ys, dtype) - prior_mean
    alpha = U @ ((U.T @ jnp.where(active, r, 0.0)) / (lam + sn2))
    lam_j = lam + jitter
    T = jnp.where(both, (U / jnp.sqrt(lam_j)).T, 0.0)
    Z = jnp.where(both, (U * jnp.sqrt(sn2 / (lam_j * (lam_j + sn2)))).T, 0.0)

    def pad(a, shape):
        return jnp.zeros(shape, dtype).at[tuple(slice(0, s) for s in a.shape)].set(a)

    return SparseGPState(
        basis_vectors=pad(jnp.where(active[:, None], xs, 0.0), (slots, d)),
        alpha=pad(jnp.where(active, alpha, 0.0), (slots,)),
        gram_inv_root=pad(T, (slots, slots)),
        alpha_cov_root=pad(Z, (slots, slots)),
        timestamps=jnp.zeros((slots,), jnp.int32),
        mask=jnp.zeros((slots,), bool).at[:n].set(active),
        prior_mean=jnp.asarray(prior_mean, dtype),
    )


# ------------------------------------------------------------------------------------------------
# Novelty threshold and age penalty.
# ------------------------------------------------------------------------------------------------


def resolution(dtype) -> float:
    """The smallest relative novelty gamma / k** the dtype can resolve safely: 1e-6 (float64),
    1e-3 (float32). gamma = k** - |w|^2 is a difference of numbers of size k**."""
    return 1e-6 if jnp.dtype(dtype) == jnp.float64 else 1e-3


def novelty_threshold(hyper: kernels.KernelParams, dtype, novelty_tol=0.0, noise_novelty=0.01):
    """gamma_min = max(novelty_tol k**, resolution(dtype) k**, noise_novelty sigma_n^2).

    A point with gamma >= gamma_min joins the BV set (eq. 10); every BV keeps a leave-one-out
    residual >= collapse_fraction * gamma_min. See the module notes.
    """
    sf2 = jnp.asarray(hyper.signal_variance, dtype)
    rel = jnp.maximum(jnp.asarray(novelty_tol, dtype), resolution(dtype))
    return jnp.maximum(rel * sf2, jnp.asarray(noise_novelty, dtype) * hyper.noise_variance)


def age_function(
    timestamps: jax.Array,
    mask: jax.Array,
    age_scale,
    age_fn: str,
    logit_eps=1e-3,
) -> jax.Array:
    """Age penalty g(t_i) over the active basis vectors (eq. 14 or eq. 15); 0 on inactive slots.

    * ``"exp"`` (eq. 14): g = exp(c (t_i - min_j t_j)). Guard: the exponent is capped at
      log(finfo.max) / 2 (354 in float64, 44 in float32), so that g and lambda * g stay finite.
    * ``"logit"`` (eq. 15): g = c log(tau_i / (1 - tau_i)), tau_i = t_i / max(max_j t_j, 1) clipped
      to [logit_eps, 1 - logit_eps]. While every t_i = 0 (max t = 0) all tau_i = logit_eps, so g is
      the same for every BV and leaves the ranking to the KL term.

    Args:
      timestamps: (S,) int policy-update indices.
      mask: (S,) bool active slots.
      age_scale: the constant c (traceable).
      age_fn: ``"exp"`` or ``"logit"`` (static).
      logit_eps: clipping of tau for the logit (traceable).

    Returns:
      (S,) g values (floating, dtype of `age_scale`'s promotion with the default float).
    """
    dtype = jnp.result_type(age_scale, float)
    t = timestamps.astype(dtype)
    if age_fn == "exp":
        t_min = jnp.min(jnp.where(mask, t, jnp.inf))
        cap = 0.5 * math.log(float(jnp.finfo(dtype).max))
        exponent = jnp.minimum(age_scale * jnp.where(mask, t - t_min, 0.0), cap)
        g = jnp.exp(exponent)
    elif age_fn == "logit":
        t_max = jnp.max(jnp.where(mask, t, -jnp.inf))
        tau = jnp.clip(t / jnp.maximum(t_max, 1.0), logit_eps, 1.0 - logit_eps)
        g = age_scale * jnp.log(tau / (1.0 - tau))
    else:
        raise ValueError(f"age_fn must be one of {AGE_FUNCTIONS}, got {age_fn!r}")
    return jnp.where(mask, g, 0.0)


# ------------------------------------------------------------------------------------------------
# The update, in the paper's steps: project, insert, observe, score, delete.
# ------------------------------------------------------------------------------------------------


class _Pending(NamedTuple):
    """A matrix X = base + sum_r u_r v_r^T whose rank-one terms are not yet written.

    One update's changes of T or Z (the insertion row, the Potter step, the Householder
    reflection) are collected here and written in one fused pass over the buffer (`materialize`);
    every read in between goes through the base and the terms (matvec, rmatvec, row, column).
    """

    base: jax.Array
    us: tuple = ()
    vs: tuple = ()

    def plus(self, u, v) -> "_Pending":
        return _Pending(self.base, self.us + (u,), self.vs + (v,))

    def matvec(self, x):  # X x
        out = self.base @ x
        for u, v in zip(self.us, self.vs):
            out = out + u * (v @ x)
        return out

    def rmatvec(self, y):  # y^T X
        out = y @ self.base
        for u, v in zip(self.us, self.vs):
            out = out + (y @ u) * v
        return out

    def column(self, j):
        out = self.base[:, j]
        for u, v in zip(self.us, self.vs):
            out = out + u * v[j]
        return out

    def row(self, i):
        out = self.base[i]
        for u, v in zip(self.us, self.vs):
            out = out + u[i] * v
        return out

    def materialize(self, keep, use=True, otherwise=None):
        """base + sum_r u_r v_r^T with rows and columns outside `keep` zeroed, written in one pass;
        where `use` is False, `otherwise` (default: base) instead."""
        X = self.base
        for u, v in zip(self.us, self.vs):
            X = X + u[:, None] * v[None, :]
        X = jnp.where(keep[:, None] & keep[None, :], X, 0.0)
        return jnp.where(use, X, self.base if otherwise is None else otherwise)


def project(state: SparseGPState, x: jax.Array, hyper: kernels.KernelParams) -> Projection:
    """Step 1 (eq. 10-11): kernel vector, whitened kernel vector and novelty of x."""
    k = masked_kernel_vector(state, x, hyper)
    kxx = kernels.kernel_diag(x, hyper)
    w = state.gram_inv_root @ k
    return Projection(k=k, kxx=kxx, w=w, gamma=kxx - w @ w)


def leave_one_out_precision(state: SparseGPState) -> jax.Array:
    """Q_ii = |T e_i|^2 = 1 / (residual variance of BV i given the other BVs): (S,), 0 if inactive."""
    T = state.gram_inv_root
    return jnp.sum(T * T, axis=0)


def scores(state: SparseGPState, age_penalty=0.0, age_scale=1.0, age_fn: str = "exp",
           logit_eps=1e-3) -> jax.Array:
    """Step 4 (eq. 13) on a state: eps_i = alpha_i^2 / (Q + C)_ii + lambda g(t_i); +inf on
    inactive slots. (Q + C)_ii = |Z e_i|^2 is the posterior variance of alpha_i."""
    dtype = state.alpha.dtype
    var_alpha = jnp.sum(state.alpha_cov_root**2, axis=0)
    kl = jnp.where(var_alpha > 0, state.alpha**2 / jnp.where(var_alpha > 0, var_alpha, 1.0), jnp.inf)
    g = age_function(state.timestamps, state.mask, jnp.asarray(age_scale, dtype), age_fn,
                     jnp.asarray(logit_eps, dtype))
    return jnp.where(state.mask, kl + jnp.asarray(age_penalty, dtype) * g, jnp.inf)


def _potter(Z: _Pending, alpha, prior_mean, k_obs, y, noise_variance, ok):
    """Step 3 (eq. 7-8): y = k_obs^T alpha + noise, Potter's square-root update (module notes).

    Returns:
      (Z with the update pending, new alpha, g = Cov[alpha] k_obs, d = sigma_n^2 + |Z k_obs|^2).
    """
    z = Z.matvec(k_obs)
    g = Z.rmatvec(z)  # Cov[alpha] k_obs
    d = noise_variance + z @ z
    residual = y - prior_mean - k_obs @ alpha
    gain = jnp.where(ok, residual / d, 0.0)
    beta = jnp.where(ok, 1.0 / (d + jnp.sqrt(d * noise_variance)), 0.0)
    return Z.plus(-beta * z, g), alpha + gain * g, g, d


def _reflect_out(X: _Pending, j, do, col, col_row) -> _Pending:
    """Step 5's rotation: X <- H X, H the Householder reflection taking col / |col| to +-e_j
    (col = X e_j, col_row = col^T X); then row j holds the conditioned-out direction. No-op where
    `do` is False."""
    norm = jnp.sqrt(col @ col)
    safe = jnp.where(norm > 0, norm, 1.0)
    unit = col / safe
    sign = jnp.where(unit[j] < 0, -1.0, 1.0).astype(col.dtype)
    v = unit.at[j].add(sign)  # |v|^2 = 2 (1 + |unit_j|), in [2, 4]
    coef = jnp.where(do & (norm > 0), 1.0 / (1.0 + jnp.abs(unit[j])), 0.0)
    return X.plus(-coef * v, col_row / safe + sign * X.row(j))


class _Work(NamedTuple):
    """One update in progress: the state with T and Z as pending writes, and the diagonals
    Q_ii (`precision`) and Cov[alpha]_ii (`var_alpha`) kept up to date by exact identities."""

    T: _Pending
    Z: _Pending
    alpha: jax.Array
    mask: jax.Array
    timestamps: jax.Array
    precision: jax.Array
    var_alpha: jax.Array


def _insert(state, proj, timestamp, ok, gamma_min, max_precision):
    """Step 2 (eq. 10-11): if x is novel and collapses at most one BV, T and Z gain the row
    t = (e_j - Q k) / sqrt(gamma) in the free slot j (module notes).

    Returns:
      (work, add, j, k_obs): k_obs is x's kernel vector against the new set (k + k** e_j).
    """
    dtype = state.alpha.dtype
    e_hat = proj.w @ state.gram_inv_root  # Q k
    novel = proj.gamma >= gamma_min
    inv_sqrt_gamma = jax.lax.rsqrt(jnp.where(novel, proj.gamma, 1.0))
    j = jnp.argmin(state.mask)  # the first free slot; one always exists (<= M of M+1 active)
    row = (-e_hat * inv_sqrt_gamma).at[j].set(inv_sqrt_gamma)
    precision = leave_one_out_precision(state)  # Q_ii; after an insertion Q_ii + t_i^2
    precision_after = precision + row * row
    add = ok & novel & (jnp.sum(state.mask & (precision_after > max_precision)) <= 1)
    onehot = ((jnp.arange(state.alpha.shape[0]) == j) & add).astype(dtype)
    row = jnp.where(add, row, 0.0)
    work = _Work(
        T=_Pending(state.gram_inv_root).plus(onehot, row),
        Z=_Pending(state.alpha_cov_root).plus(onehot, row),
        alpha=state.alpha,
        mask=state.mask | (onehot > 0),
        timestamps=jnp.where(onehot > 0, jnp.asarray(timestamp, jnp.int32), state.timestamps),
        precision=jnp.where(add, precision_after, precision),
        var_alpha=jnp.sum(state.alpha_cov_root**2, axis=0) + row * row,
    )
    return work, add, j, proj.k + onehot * proj.kxx


def _observe(work: _Work, prior_mean, k_obs, y, noise_variance, ok) -> _Work:
    """Step 3 (eq. 7-8): Potter's update of the Gaussian over alpha with y."""
    Z, alpha, g, d = _potter(work.Z, work.alpha, prior_mean, k_obs, y, noise_variance, ok)
    # diag(Z^T Z) after the Potter step: Cov[alpha] - g g^T / d (exact identity)
    return work._replace(Z=Z, alpha=alpha, var_alpha=work.var_alpha - g * g / d)


def _choose(work: _Work, capacity_m, ok, max_precision, age_penalty, age_scale, age_fn, logit_eps):
    """Step 4 (eq. 13): which BV to delete, and whether to: a collapsed BV if any (1/Q_ii below
    collapse_fraction gamma_min), else the lowest score, if the set is over capacity.

    Returns:
      (j, do, collapse).
    """
    dtype = work.alpha.dtype
    age = age_function(work.timestamps, work.mask, jnp.asarray(age_scale, dtype), age_fn,
                       jnp.asarray(logit_eps, dtype))
    v = work.var_alpha
    kl = jnp.where(v > 0, work.alpha**2 / jnp.where(v > 0, v, 1.0), jnp.inf)
    score = jnp.where(work.mask, kl + jnp.asarray(age_penalty, dtype) * age, jnp.inf)
    collapsed = work.mask & (work.precision > max_precision)
    collapse = jnp.any(collapsed)
    j = jnp.where(collapse, jnp.argmax(jnp.where(collapsed, work.precision, -1.0)),
                  jnp.argmin(score))
    do = ok & ((jnp.sum(work.mask) > capacity_m) | collapse)
    return j, do, do & collapse


def _delete(work: _Work, j, do) -> _Work:
    """Step 5 (KL-optimal deletion): condition alpha on alpha_j = 0; rotate the conditioned-out
    direction into row j of Z and of T (Householder), which are then dropped with slot j."""
    col = work.Z.column(j)
    cov_row = work.Z.rmatvec(col)  # Cov[alpha] e_j
    var_j = col @ col
    shift = jnp.where(do & (var_j > 0), work.alpha[j] / jnp.where(var_j > 0, var_j, 1.0), 0.0)
    tau = work.T.column(j)
    return work._replace(
        alpha=work.alpha - shift * cov_row,
        Z=_reflect_out(work.Z, j, do, col, cov_row),
        T=_reflect_out(work.T, j, do, tau, work.T.rmatvec(tau)),
        mask=work.mask & ~(do & (jnp.arange(work.mask.shape[0]) == j)),
    )


def _full_update(state, projected, x, y, proj, hyper, timestamp, ok, gamma_min, max_precision,
                 age_penalty, age_scale, age_fn, logit_eps, capacity_m):
    """Steps 2-5 for a point that may join the set (see `update_with_info`); `projected` is the
    state after the projected update, the result if x neither joins nor causes a deletion.
    `capacity_m` is the budget M (the state may have padding slots beyond M + 1)."""
    work, add, j_new, k_obs = _insert(state, proj, timestamp, ok, gamma_min, max_precision)
    work = _observe(work, state.prior_mean, k_obs, y, hyper.noise_variance, ok)
    j, do, collapse = _choose(work, capacity_m, ok, max_precision, age_penalty, age_scale,
                              age_fn, logit_eps)
    work = _delete(work, j, do)
    keep = work.mask
    # A member that neither inserts nor deletes takes the projected update's result, bit for bit
    # (written in the same pass as this update's own writes).
    changed = add | do
    new_bv = state.basis_vectors.at[j_new].set(jnp.where(add, x, state.basis_vectors[j_new]))
    new = SparseGPState(
        basis_vectors=jnp.where(keep[:, None], new_bv, 0.0),
        alpha=jnp.where(changed, jnp.where(keep, work.alpha, 0.0), projected.alpha),
        gram_inv_root=work.T.materialize(keep, changed),
        alpha_cov_root=work.Z.materialize(keep, changed, projected.alpha_cov_root),
        timestamps=jnp.where(keep, work.timestamps, 0),
        mask=keep,
        prior_mean=state.prior_mean,
    )
    info = UpdateInfo(
        added=add,
        inserted_slot=jnp.where(add, j_new, -1).astype(jnp.int32),
        deleted_slot=jnp.where(do, j, -1).astype(jnp.int32),
        collapse=collapse,
    )
    return new, info


def _projected_update(state, proj, y, noise_variance, ok) -> SparseGPState:
    """Steps 1 and 3 alone: the projected update of a point that does not join the set."""
    Z, alpha, _, _ = _potter(_Pending(state.alpha_cov_root), state.alpha, state.prior_mean, proj.k,
                             y, noise_variance, ok)
    return state._replace(alpha=alpha, alpha_cov_root=Z.materialize(state.mask))


@custom_batching.custom_vmap
def _any_in_batch(flag):
    """`flag` itself; under `jax.vmap`, whether it is True for any member of the batch (an
    unbatched bool), so that `lax.cond` can skip a branch that no member needs."""
    return flag


@_any_in_batch.def_vmap
def _any_in_batch_vmap(axis_size, in_batched, flag):
    del axis_size
    return (jnp.any(flag) if in_batched[0] else flag), False


class UpdateInfo(NamedTuple):
    """What one `update` did (for diagnostics and tests).

    Attributes:
      added: () bool, x joined the BV set (in slot `inserted_slot`).
      inserted_slot: () int32, the slot x was written to (-1 if not added).
      deleted_slot: () int32, the slot deleted by step 5 (-1 if none; may equal inserted_slot).
      collapse: () bool, the deletion removed a collapsed BV (not the lowest score).
    """

    added: jax.Array
    inserted_slot: jax.Array
    deleted_slot: jax.Array
    collapse: jax.Array


def update(state, x, y, hyper, timestamp, **kwargs) -> SparseGPState:
    """Takes in one pair (x, y); `update_with_info` without the info (see there)."""
    return update_with_info(state, x, y, hyper, timestamp, **kwargs)[0]


def update_with_info(
    state: SparseGPState,
    x: jax.Array,
    y: jax.Array,
    hyper: kernels.KernelParams,
    timestamp,
    *,
    novelty_tol=0.0,
    noise_novelty=0.01,
    collapse_fraction=0.5,
    age_penalty=0.0,
    age_scale=1.0,
    age_fn: str = "exp",
    logit_eps=1e-3,
    valid=True,
):
    """One pair (x, y): project, insert if novel, observe, score, delete, and what it did
    (design: docs/design.md#sparse-gp).

    x is novel if gamma >= gamma_min (`novelty_threshold`) and inserting it would leave at most
    one existing BV with a leave-one-out residual below collapse_fraction * gamma_min. After the
    observation one BV is deleted if the set holds M + 1 vectors or a BV has collapsed: the
    collapsed one if any, otherwise the one with the lowest score (eq. 13; the new point is among
    the candidates). A non-finite x or y, or ``valid=False``, leaves the state unchanged.

    A point that does not join the set takes the projected update (steps 1 and 3), which touches
    only alpha and Z. The insertion and deletion work runs in a `lax.cond` branch that is skipped
    when no member of a `vmap` batch needs it (a member that does not is given the projected
    update's result exactly, so a seed's result never depends on its batch-mates).

    Args:
      state: the current `SparseGPState` (its dtype is the computation dtype).
      x: (D,) input.
      y: () target.
      hyper: kernel hyperparameters (cast to the state's dtype).
      timestamp: int, the policy-update index stored with x if it becomes a BV (traceable).
      novelty_tol: relative novelty tolerance (traceable); see `novelty_threshold`.
      noise_novelty: fraction of sigma_n^2 below which a residual is not novel (traceable).
      collapse_fraction: BVs keep 1/Q_ii >= collapse_fraction * gamma_min (traceable, in (0, 1]).
      age_penalty: lambda of eq. 13 (traceable); 0 is plain KL sparsification.
      age_scale: the constant c of eq. 14/15 (traceable).
      age_fn: ``"exp"`` (eq. 14) or ``"logit"`` (eq. 15); static.
      logit_eps: clipping of tau in eq. 15 (traceable).
      valid: bool (traceable); False skips the pair (for padded batches).

    Returns:
      (state, info): the updated state and an `UpdateInfo`.
    """
    if age_fn not in AGE_FUNCTIONS:
        raise ValueError(f"age_fn must be one of {AGE_FUNCTIONS}, got {age_fn!r}")
    return _update_core(state, x, y, hyper, timestamp, capacity_m=capacity(state),
                        novelty_tol=novelty_tol, noise_novelty=noise_novelty,
                        collapse_fraction=collapse_fraction, age_penalty=age_penalty,
                        age_scale=age_scale, age_fn=age_fn, logit_eps=logit_eps, valid=valid)


def _update_core(state, x, y, hyper, timestamp, *, capacity_m, novelty_tol, noise_novelty,
                 collapse_fraction, age_penalty, age_scale, age_fn, logit_eps, valid):
    """`update_with_info` on a state that may carry padding slots beyond M + 1 = capacity_m + 1
    (`update_batch`'s loops pad; a single update does not)."""
    dtype = state.alpha.dtype
    hyper = _cast_hyper(hyper, dtype)
    x = jnp.asarray(x, dtype)
    y = jnp.asarray(y, dtype)
    ok = jnp.asarray(valid, bool) & jnp.all(jnp.isfinite(x)) & jnp.isfinite(y)
    x = jnp.where(ok, x, jnp.zeros_like(x))
    y = jnp.where(ok, y, jnp.zeros_like(y))
    gamma_min = novelty_threshold(hyper, dtype, novelty_tol, noise_novelty)
    max_precision = 1.0 / (jnp.asarray(collapse_fraction, dtype) * gamma_min)

    proj = project(state, x, hyper)
    projected = _projected_update(state, proj, y, hyper.noise_variance, ok)
    none = UpdateInfo(jnp.zeros((), bool), -jnp.ones((), jnp.int32), -jnp.ones((), jnp.int32),
                      jnp.zeros((), bool))

    def full():
        return _full_update(state, projected, x, y, proj, hyper, timestamp, ok, gamma_min,
                            max_precision, age_penalty, age_scale, age_fn, logit_eps, capacity_m)

    candidate = ok & (proj.gamma >= gamma_min)
    return jax.lax.cond(_any_in_batch(candidate), full, lambda: (projected, none))


def update_batch(
    state: SparseGPState,
    xs: jax.Array,
    ys: jax.Array,
    hyper: kernels.KernelParams,
    timestamps,
    *,
    valid=None,
    unroll: int = 1,
    with_info: bool = False,
    loop: str = "auto",
    **update_kwargs,
):
    """Takes in N pairs one after the other: the result of `update` applied to each in turn (the
    same decisions; the numbers to rounding, since the loops work on buffers padded to a multiple
    of 8 slots, module notes).

    Two loops compute it, with the same arithmetic and so the same result bit for bit (called on
    their own; inside a larger program, to rounding: module notes):

    * one GP (not under `jax.vmap`): `lax.while_loop`s in segments. An inner loop gives the
      projected update (steps 1 and 3) to consecutive pairs for as long as none is a candidate for
      insertion; the full update of a candidate runs between two inner loops. No `lax.cond` sits
      in the per-pair loop, so XLA writes T and Z in place; a `lax.cond` whose branches return the
      matrices made it copy them at every pair, which cost about as much as the update itself.
    * under `jax.vmap` (a batch of GPs): `update` under `lax.scan`, whose `lax.cond` skips the
      full update at a pair where no member of the batch needs it (`update_with_info`).

    Args:
      state: the current state.
      xs: (N, D) inputs.
      ys: (N,) targets.
      hyper: kernel hyperparameters.
      timestamps: (N,) int or a scalar int used for every pair.
      valid: optional (N,) bool; pairs with False are skipped (padding). Pairs with a non-finite
        input or target are skipped as well.
      unroll: `lax.scan` unroll factor of the batched loop (static).
      with_info: also return the stacked `UpdateInfo` of every pair (static).
      loop: ``"auto"`` (segments for one GP, the scanned loop under `jax.vmap`), or ``"segments"``
        or ``"scan"`` to force one (static; for benchmarks and tests: ``"segments"`` under `vmap`
        is correct but runs every segment for as long as the batch's longest).
      **update_kwargs: keyword arguments of `update` (``age_fn`` static, the rest traceable).

    Returns:
      The state after the N updates (and, with `with_info`, an `UpdateInfo` with (N,) leaves).
    """
    if loop not in UPDATE_LOOPS:
        raise ValueError(f"loop must be one of {UPDATE_LOOPS}, got {loop!r}")
    n = xs.shape[0]
    timestamps = jnp.broadcast_to(jnp.asarray(timestamps, jnp.int32), (n,))
    valid = jnp.ones((n,), bool) if valid is None else jnp.broadcast_to(jnp.asarray(valid, bool), (n,))
    age_fn = update_kwargs.pop("age_fn", "exp")
    if age_fn not in AGE_FUNCTIONS:
        raise ValueError(f"age_fn must be one of {AGE_FUNCTIONS}, got {age_fn!r}")
    unknown = set(update_kwargs) - set(_TRACEABLE_DEFAULTS)
    if unknown:
        raise TypeError(f"update_batch got unexpected keyword arguments {sorted(unknown)}")
    params = {k: jnp.asarray(update_kwargs.get(k, v)) for k, v in _TRACEABLE_DEFAULTS.items()}
    args = (state, xs, ys, hyper, timestamps, valid, params)
    if loop == "scan":
        state, infos = _scanned_points(*args, age_fn=age_fn, unroll=unroll)
    elif loop == "segments":
        state, infos = _segmented_points(*args, age_fn=age_fn, with_info=with_info)
    else:
        state, infos = _points_loop(age_fn, unroll, with_info)(*args)
    return (state, infos) if with_info else state


UPDATE_LOOPS = ("auto", "segments", "scan")
_TRACEABLE_DEFAULTS = dict(novelty_tol=0.0, noise_novelty=0.01, collapse_fraction=0.5,
                           age_penalty=0.0, age_scale=1.0, logit_eps=1e-3)


def _scanned_points(state, xs, ys, hyper, timestamps, valid, params, age_fn, unroll):
    """`update_with_info` under `lax.scan` (the loop for a batch of GPs)."""
    slots = state.alpha.shape[-1]

    def body(carry, inputs):
        x, y, t, ok = inputs
        return _update_core(carry, x, y, hyper, t, valid=ok, age_fn=age_fn,
                            capacity_m=slots - 1, **params)

    state = _pad_slots(state, padded_slots(slots))
    state, infos = jax.lax.scan(body, state, (xs, ys, timestamps, valid), unroll=unroll)
    return _unpad_slots(state, slots), infos


class _Next(NamedTuple):
    """The pair the segmented loop takes in next, prepared against the current BV set."""

    index: jax.Array
    x: jax.Array
    y: jax.Array
    ok: jax.Array
    proj: Projection
    candidate: jax.Array


def _segmented_points(state, xs, ys, hyper, timestamps, valid, params, age_fn, with_info=True):
    """The loop for one GP (see `update_batch`): while-loops of projected updates between the
    full updates of candidates. The same operations as `update_with_info`, in the same order.
    Without `with_info` the (N,) info arrays are not carried (they cost a copy per segment)."""
    dtype = state.alpha.dtype
    slots = state.alpha.shape[-1]
    state = _pad_slots(state, padded_slots(slots))
    hyper = _cast_hyper(hyper, dtype)
    n = xs.shape[0]
    xs = jnp.asarray(xs, dtype)
    ys = jnp.asarray(ys, dtype)
    gamma_min = novelty_threshold(hyper, dtype, params["novelty_tol"], params["noise_novelty"])
    max_precision = 1.0 / (jnp.asarray(params["collapse_fraction"], dtype) * gamma_min)

    def prepare(st, i) -> _Next:
        at = jnp.minimum(i, n - 1)
        x, y = xs[at], ys[at]
        ok = (i < n) & valid[at] & jnp.all(jnp.isfinite(x)) & jnp.isfinite(y)
        x = jnp.where(ok, x, jnp.zeros_like(x))
        y = jnp.where(ok, y, jnp.zeros_like(y))
        proj = project(st, x, hyper)
        return _Next(i, x, y, ok, proj, ok & (proj.gamma >= gamma_min))

    def projected_steps(carry):
        """Projected updates until the next pair is a candidate or the pairs run out."""

        def body(c):
            st, nxt, infos = c
            st = _projected_update(st, nxt.proj, nxt.y, hyper.noise_variance, nxt.ok)
            return st, prepare(st, nxt.index + 1), infos

        return jax.lax.while_loop(lambda c: (c[1].index < n) & ~c[1].candidate, body, carry)

    def full_step(carry):
        """The full update of the candidate `nxt`, then projected steps up to the next one."""
        st, nxt, infos = carry
        projected = _projected_update(st, nxt.proj, nxt.y, hyper.noise_variance, nxt.ok)
        st, info = _full_update(st, projected, nxt.x, nxt.y, nxt.proj, hyper,
                                timestamps[nxt.index], nxt.ok, gamma_min, max_precision,
                                params["age_penalty"], params["age_scale"], age_fn,
                                params["logit_eps"], slots - 1)
        if with_info:
            infos = jax.tree.map(lambda a, v: a.at[nxt.index].set(v), infos, info)
        return projected_steps((st, prepare(st, nxt.index + 1), infos))

    infos = (UpdateInfo(jnp.zeros((n,), bool), -jnp.ones((n,), jnp.int32),
                        -jnp.ones((n,), jnp.int32), jnp.zeros((n,), bool)) if with_info else None)
    carry = projected_steps((state, prepare(state, jnp.zeros((), jnp.int32)), infos))
    state, _, infos = jax.lax.while_loop(lambda c: c[1].index < n, full_step, carry)
    return _unpad_slots(state, slots), infos


@functools.lru_cache(maxsize=None)
def _points_loop(age_fn: str, unroll: int, with_info: bool):
    """`update_batch`'s loop for static arguments: segmented for one GP, scanned under vmap."""

    @custom_batching.custom_vmap
    def run(state, xs, ys, hyper, timestamps, valid, params):
        return _segmented_points(state, xs, ys, hyper, timestamps, valid, params, age_fn, with_info)

    @run.def_vmap
    def _run_vmap(axis_size, in_batched, *args):
        del axis_size
        in_axes = tuple(jax.tree.map(lambda b: 0 if b else None, flags) for flags in in_batched)

        def scanned(*a):
            state, infos = _scanned_points(*a, age_fn=age_fn, unroll=unroll)
            return state, (infos if with_info else None)  # the structure of `run`'s output

        out = jax.vmap(scanned, in_axes=in_axes)(*args)
        return out, jax.tree.map(lambda _: True, out)

    return run


# ------------------------------------------------------------------------------------------------
# Health of a state: invariants that hold in exact arithmetic and fail when the GP has diverged.
# ------------------------------------------------------------------------------------------------


class Health(NamedTuple):
    """Invariant checks of a state (each a () bool, True = holds) and the numbers behind them.

    Attributes:
      finite: every entry of alpha, T, Z is finite.
      posterior_below_prior: Cov[alpha]_ii <= (1 + tol) Q_ii for every BV (a posterior variance
        cannot exceed the prior's; tol is 1e3 eps).
      mean_in_range: at the given inputs, |mu(x) - y| <= divergence_factor ((max y - min y) +
        margin_stds sigma_f) for the given targets y, which the GP has just taken in. This is a
        divergence detector, not an accuracy test: a budgeted GP with age-driven exchange
        legitimately misses its latest targets by up to about the data range plus a few sigma_f
        (ratios up to ~1 measured on the paper task at M = 30), while the diverged first
        implementation missed them by 1e3 times the range.
      max_variance_ratio: max_i Cov[alpha]_ii / Q_ii.
      max_mean_error: max |mu(x) - y| over the given pairs.
      mean_error_ratio: max_mean_error over (max y - min y + margin_stds sigma_f), the bound
        without the divergence factor (mean_in_range is mean_error_ratio <= divergence_factor).
    """

    finite: jax.Array
    posterior_below_prior: jax.Array
    mean_in_range: jax.Array
    max_variance_ratio: jax.Array
    max_mean_error: jax.Array
    mean_error_ratio: jax.Array

    @property
    def ok(self) -> jax.Array:
        return self.finite & self.posterior_below_prior & self.mean_in_range


def check(state: SparseGPState, hyper: kernels.KernelParams, xs, ys, valid=None,
          margin_stds: float = 6.0, divergence_factor: float = 10.0) -> Health:
    """Checks the invariants of `state` after it took in (xs, ys) (`Health`). O(N M + M^2).

    A GP that has diverged while staying finite (alpha ~ 1e36) fails `mean_in_range`; one whose
    covariance has lost its meaning fails `posterior_below_prior`.
    """
    dtype = state.alpha.dtype
    hyper = _cast_hyper(hyper, dtype)
    valid = jnp.ones(ys.shape, bool) if valid is None else valid
    finite = (jnp.all(jnp.isfinite(state.alpha)) & jnp.all(jnp.isfinite(state.gram_inv_root))
              & jnp.all(jnp.isfinite(state.alpha_cov_root)))
    q = leave_one_out_precision(state)
    Z = state.alpha_cov_root
    v = jnp.sum(Z * Z, axis=0)
    ratio = jnp.max(jnp.where(state.mask, v / jnp.where(q > 0, q, 1.0), 0.0))
    tol = 1e3 * float(jnp.finfo(dtype).eps)
    means = jax.vmap(lambda x: state.prior_mean + masked_kernel_vector(state, x, hyper) @ state.alpha)(
        jnp.asarray(xs, dtype))
    ys = jnp.asarray(ys, dtype)
    y_hi = jnp.max(jnp.where(valid, ys, -jnp.inf))
    y_lo = jnp.min(jnp.where(valid, ys, jnp.inf))
    err = jnp.max(jnp.where(valid, jnp.abs(means - ys), 0.0))
    margin = jnp.where(jnp.any(valid), y_hi - y_lo, 0.0) + margin_stds * jnp.sqrt(hyper.signal_variance)
    return Health(
        finite=finite,
        posterior_below_prior=ratio <= 1.0 + tol,
        mean_in_range=jnp.isfinite(err) & (err <= divergence_factor * margin),
        max_variance_ratio=ratio,
        max_mean_error=err,
        mean_error_ratio=err / margin,
    )
