"""Sparse online Gaussian process (Csato & Opper) with fixed-size basis-vector buffers (SPEC §2).

Convention: the latent predictive variance is sigma^2(x) = k(x, x) + k(x)^T C k(x) with C negative
semi-definite (Csato-Opper sign; the paper writes C with the opposite sign).

Buffers have M + 1 slots (capacity M, plus one slot so that a new point can be inserted before the
KL-optimal deletion). An inactive slot has mask False, alpha 0 and zero rows/columns in C and Q.

float32: the recursion keeps Q = K_B^{-1} and C ~ -(K_B + sigma_n^2 I)^{-1} by rank-one updates, so
Q + C (whose diagonal enters the deletion score) is a difference of nearly equal numbers when
sigma_n^2 << sigma_f^2 and K_B is ill-conditioned. In float32 this loses positive
semi-definiteness after a few thousand updates on pendulum-like data and the state stops being
accurate; the guards in `update` keep it finite (no inf/NaN ever enters the state), but float64,
the package default, is what gives correct numbers.
"""

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from gpguided_jax import kernels


class SparseGPState(NamedTuple):
    """State of the online sparse GP. S = capacity + 1 slots, D = input dimension.

    Attributes:
      basis_vectors: (S, D) inputs of the basis vectors (rows of inactive slots are ignored).
      alpha: (S,) posterior mean coefficients; mu(x) = k(B, x)^T alpha.
      C: (S, S) negative semi-definite posterior covariance correction.
      Q: (S, S) inverse Gram matrix K_B^{-1} of the active basis vectors.
      timestamps: (S,) int32 index of the policy update during which each BV was added.
      mask: (S,) bool, True for active slots.
      prior_mean: () constant prior mean m0 of the GP: mu(x) = m0 + k(B, x)^T alpha. Returns
        here are all negative; with a zero prior mean the GP would revert to 0 (an optimistic
        value) away from the data, which biases a Q-based gradient towards unexplored actions.
    """

    basis_vectors: jax.Array
    alpha: jax.Array
    C: jax.Array
    Q: jax.Array
    timestamps: jax.Array
    mask: jax.Array
    prior_mean: jax.Array = 0.0


def init(capacity: int, input_dim: int, dtype=None, prior_mean=0.0) -> SparseGPState:
    """An empty GP with room for `capacity` basis vectors (static) and a constant prior mean."""
    dtype = dtype or jnp.result_type(float)
    slots = capacity + 1
    return SparseGPState(
        basis_vectors=jnp.zeros((slots, input_dim), dtype),
        alpha=jnp.zeros((slots,), dtype),
        C=jnp.zeros((slots, slots), dtype),
        Q=jnp.zeros((slots, slots), dtype),
        timestamps=jnp.zeros((slots,), jnp.int32),
        mask=jnp.zeros((slots,), bool),
        prior_mean=jnp.asarray(prior_mean, dtype),
    )


def masked_kernel_vector(state: SparseGPState, x: jax.Array, hyper: kernels.KernelParams):
    """k(B, x) with inactive slots set to 0: (S,)."""
    k = kernels.cross_covariance(state.basis_vectors, x, hyper)
    return jnp.where(state.mask, k, jnp.zeros_like(k))


def predict(state: SparseGPState, x: jax.Array, hyper: kernels.KernelParams):
    """Predictive mean (eq. 5) and latent variance (eq. 6, Csato-Opper sign) at one input x (D,).

    Returns:
      (mean, latent_variance), both scalars; the variance is clipped to [0, k(x, x)].
    """
    k = masked_kernel_vector(state, x, hyper)
    kxx = kernels.kernel_diag(x, hyper)
    mean = state.prior_mean + k @ state.alpha
    var = kxx + k @ (state.C @ k)
    return mean, jnp.clip(var, 0.0, kxx)


AGE_FUNCTIONS = ("exp", "logit")


def default_novelty_tol(dtype) -> float:
    """1e-6 of k(x, x) in float64 (Csato's usual value), 1e-3 in float32 (keeps Q conditioned)."""
    return 1e-6 if jnp.dtype(dtype) == jnp.float64 else 1e-3


def default_variance_floor(dtype) -> float:
    """Absolute floor on the latent variance: 1e-12 (float64) or 1e-6 (float32)."""
    return 1e-12 if jnp.dtype(dtype) == jnp.float64 else 1e-6


def num_basis_vectors(state: SparseGPState) -> jax.Array:
    """Number of active basis vectors (int32 scalar)."""
    return jnp.sum(state.mask, dtype=jnp.int32)


def capacity(state: SparseGPState) -> int:
    """The static budget M (the buffers have M + 1 slots)."""
    return state.alpha.shape[-1] - 1


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


def update(
    state: SparseGPState,
    x: jax.Array,
    y: jax.Array,
    hyper: kernels.KernelParams,
    timestamp,
    *,
    novelty_tol=None,
    age_penalty=0.0,
    age_scale=1.0,
    age_fn: str = "exp",
    variance_floor=None,
    logit_eps=1e-3,
    valid=True,
) -> SparseGPState:
    """Takes in one pair (x, y): the Csato-Opper online update with age-penalised sparsification.

    SPEC §2 / paper eq. 5-8 and 10-15. With k = k(B, x), m = k^T alpha, v = max(k** + k^T C k,
    floor), q = (y - m)/(sigma_n^2 + v), r = -1/(sigma_n^2 + v), e = Q k, gamma = k** - k^T e:

    * if gamma >= tol k** the point joins the BV set in the first free slot j:
      s = C k + 1_j, alpha += q s, C += r s s^T, Q += (e - 1_j)(e - 1_j)^T / gamma
      (the SPEC's [alpha; 0] + q [Ck; 1] etc. written on fixed buffers); if the set then holds
      M + 1 vectors, the one with the lowest score alpha_i^2/(Q_ii + C_ii) + lambda g(t_i)
      (eq. 13) is removed by the KL-optimal deletion, the new point included among the candidates;
    * otherwise the projected update: s = C k + e, eta = 1/(1 + gamma r), alpha += q eta s,
      C += r eta s s^T.

    The insertion and the deletion are fused into one pass over C and Q: the deletion's column j*
    and diagonals are taken from the rank-one-updated matrices without forming them, so an update
    costs two matrix-vector products and one rank-three write of C and Q, O(M^2), no O(M^3) work.

    Guards (all branch-free): a non-finite x or y, or ``valid=False``, leaves the state unchanged
    (the pair is SKIPPED; it never reaches alpha or C); v is floored at max(gamma, floor) (exact
    arithmetic gives v >= gamma since Q + C is PSD); gamma is compared with
    max(novelty_tol, 10 eps) k** so that 1/gamma stays finite; in the projected update gamma is
    clipped to [0, v] (exact arithmetic gives 0 <= gamma <= v, and this keeps eta in
    [1, (sigma_n^2+v)/sigma_n^2]); a projected update along which Q + C has lost positive
    semi-definiteness (v_raw < gamma, rounding only) leaves C unchanged; the denominators Q_jj and
    Q_jj + C_jj of the score and the deletion are floored at eps / k** and 100 eps Q_jj; an entry of
    alpha, C or Q that would overflow keeps its old value; inactive slots are zeroed after every
    update. C and Q are kept bitwise symmetric by construction (every change is a sum of
    +-a a^T terms formed elementwise), which is what an explicit symmetrisation would achieve,
    without its extra pass over both matrices.

    Args:
      state: the current `SparseGPState` (its dtype is the computation dtype).
      x: (D,) input.
      y: () target.
      hyper: kernel hyperparameters (cast to the state's dtype).
      timestamp: int, the policy-update index stored with x if it becomes a BV (traceable).
      novelty_tol: relative novelty threshold (traceable); None: `default_novelty_tol(dtype)`.
      age_penalty: lambda of eq. 13 (traceable); 0 is plain KL sparsification.
      age_scale: the constant c of eq. 14/15 (traceable).
      age_fn: ``"exp"`` (eq. 14) or ``"logit"`` (eq. 15); static.
      variance_floor: absolute floor on v (traceable); None: `default_variance_floor(dtype)`.
      logit_eps: clipping of tau in eq. 15 (traceable).
      valid: bool (traceable); False skips the pair (for padded batches).

    Returns:
      The updated state.
    """
    if age_fn not in AGE_FUNCTIONS:
        raise ValueError(f"age_fn must be one of {AGE_FUNCTIONS}, got {age_fn!r}")
    dtype = state.alpha.dtype
    eps = float(jnp.finfo(dtype).eps)
    num_slots = state.alpha.shape[0]
    if novelty_tol is None:
        novelty_tol = default_novelty_tol(dtype)
    if variance_floor is None:
        variance_floor = default_variance_floor(dtype)
    hyper = jax.tree.map(lambda a: jnp.asarray(a, dtype), hyper)
    x = jnp.asarray(x, dtype)
    y = jnp.asarray(y, dtype)
    novelty_tol = jnp.maximum(jnp.asarray(novelty_tol, dtype), 10.0 * eps)

    ok = jnp.asarray(valid, bool) & jnp.all(jnp.isfinite(x)) & jnp.isfinite(y)
    x = jnp.where(ok, x, jnp.zeros_like(x))
    y = jnp.where(ok, y, jnp.zeros_like(y))

    C, Q, alpha, mask = state.C, state.Q, state.alpha, state.mask
    k = masked_kernel_vector(state, x, hyper)
    kxx = kernels.kernel_diag(x, hyper)
    tiny = eps / kxx
    Ck = C @ k
    e_hat = Q @ k
    gamma = kxx - k @ e_hat
    # Q + C is PSD in exact arithmetic, so v >= gamma; flooring v there stops the feedback loop in
    # which a rounding-negative v gives a huge r that drives C further negative (seen in float32).
    v_raw = kxx + k @ Ck
    v = jnp.maximum(jnp.maximum(v_raw, gamma), variance_floor)
    # v_raw < gamma means rounding has made Q + C indefinite along k; shrinking C further along
    # that direction feeds the divergence, so C is then left as it is for this projected update
    # (alpha is still updated). Exact arithmetic never takes this branch.
    psd_ok = v_raw >= gamma
    denom = hyper.noise_variance + v
    q = (y - state.prior_mean - k @ alpha) / denom
    r = -1.0 / denom

    add = ok & (gamma >= novelty_tol * kxx)
    slots = jnp.arange(num_slots)
    new_slot = jnp.argmin(mask)  # first free slot; one always exists (at most M of M+1 active)
    onehot_new = (slots == new_slot) & add
    # Full update: s = Ck + 1_j; projected: s = Ck + e with q, r scaled by eta.
    gamma_proj = jnp.clip(gamma, 0.0, v)
    eta = 1.0 / (1.0 + gamma_proj * r)
    s = Ck + jnp.where(add, onehot_new.astype(dtype), e_hat)
    q_eff = jnp.where(ok, jnp.where(add, q, q * eta), 0.0)
    r_eff = jnp.where(ok & (psd_ok | add), jnp.where(add, r, r * eta), 0.0)
    u = e_hat - onehot_new.astype(dtype)
    w_q = jnp.where(add, 1.0 / jnp.where(add, gamma, 1.0), 0.0)

    alpha1 = alpha + q_eff * s
    mask1 = mask | onehot_new
    timestamps1 = jnp.where(onehot_new, jnp.asarray(timestamp, jnp.int32), state.timestamps)

    # Deletion (eq. 13 scores on the post-insertion GP, computed from diagonals only).
    do_delete = add & (jnp.sum(mask) >= num_slots - 1)
    diag_c1 = jnp.diagonal(C) + r_eff * s * s
    diag_q1 = jnp.diagonal(Q) + w_q * u * u
    # Q_ii + C_ii > 0 in exact arithmetic but is a difference of nearly equal numbers when the
    # noise is small (C ~ -Q); it is floored at 100 eps Q_ii so that the deletion below never
    # divides by a rounding-sized or negative number (this is what keeps float32 finite).
    rel_floor = 100.0 * eps
    score = alpha1 * alpha1 / jnp.maximum(diag_q1 + diag_c1, rel_floor * diag_q1 + tiny)
    g = age_function(timestamps1, mask1, jnp.asarray(age_scale, dtype), age_fn, logit_eps)
    score = score + jnp.asarray(age_penalty, dtype) * g
    score = jnp.where(mask1, score, jnp.inf)
    j_del = jnp.argmin(score)
    # Column j* of the post-insertion Q and C (read as a row: contiguous, and C, Q are symmetric).
    q_col = Q[j_del] + (w_q * u[j_del]) * u
    c_col = C[j_del] + (r_eff * s[j_del]) * s
    a_star = alpha1[j_del]
    qc_col = q_col + c_col
    w_del_q = jnp.where(do_delete, 1.0 / jnp.maximum(q_col[j_del], tiny), 0.0)
    qc_floor = rel_floor * jnp.maximum(q_col[j_del], tiny) + tiny
    w_del_qc = jnp.where(do_delete, 1.0 / jnp.maximum(qc_col[j_del], qc_floor), 0.0)
    keep = mask1 & ~(do_delete & (slots == j_del))

    alpha2 = jnp.where(keep, alpha1 - (a_star * w_del_qc) * qc_col, 0.0)
    keep2 = keep[:, None] & keep[None, :]
    # One fused pass each: insertion (rank one) + deletion (rank two for C, one for Q). Every
    # weight has a known sign (r <= 0, 1/gamma >= 0, 1/q* > 0, 1/(q* + c*) > 0 after the guards),
    # so each term is written as +-(a_i a_j) with a = sqrt(|w|) u: a product a_i a_j equals a_j a_i
    # bitwise and no scalar factor is left for the compiler to re-associate, so C and Q stay
    # exactly symmetric. This replaces the SPEC's explicit 0.5 (A + A^T), which would cost a
    # transposed pass over both matrices (a third of the step time in the benchmark);
    # `tests/test_sparse_gp.py` checks C == C^T and Q == Q^T bitwise after 5000 updates.
    a_ins = jnp.sqrt(-r_eff) * s
    b_del = jnp.sqrt(w_del_q) * q_col
    c_del = jnp.sqrt(w_del_qc) * qc_col
    d_ins = jnp.sqrt(w_q) * u
    C2 = (
        C
        - a_ins[:, None] * a_ins[None, :]
        + b_del[:, None] * b_del[None, :]
        - c_del[:, None] * c_del[None, :]
    )
    Q2 = Q + d_ins[:, None] * d_ins[None, :] - b_del[:, None] * b_del[None, :]
    # Last-resort guard, fused into the same pass: an entry that would overflow keeps its old
    # value, so no inf/NaN can enter the state even when float32 rounding has made the
    # recursion diverge (see the module notes on float32).
    C2 = jnp.where(keep2, jnp.where(jnp.isfinite(C2), C2, C), 0.0)
    Q2 = jnp.where(keep2, jnp.where(jnp.isfinite(Q2), Q2, Q), 0.0)
    alpha2 = jnp.where(jnp.isfinite(alpha2), alpha2, jnp.where(keep, alpha, 0.0))
    basis_vectors = jnp.where(onehot_new[:, None], x[None, :], state.basis_vectors)
    return SparseGPState(
        basis_vectors=basis_vectors,
        alpha=alpha2,
        C=C2,
        Q=Q2,
        timestamps=timestamps1,
        mask=keep,
        prior_mean=state.prior_mean,
    )


def update_batch(
    state: SparseGPState,
    xs: jax.Array,
    ys: jax.Array,
    hyper: kernels.KernelParams,
    timestamps,
    *,
    valid=None,
    unroll: int = 1,
    **update_kwargs,
) -> SparseGPState:
    """Takes in N pairs one after the other (`update` under `lax.scan`).

    Args:
      state: the current state.
      xs: (N, D) inputs.
      ys: (N,) targets.
      hyper: kernel hyperparameters.
      timestamps: (N,) int or a scalar int used for every pair.
      valid: optional (N,) bool; pairs with False are skipped (padding). Pairs with a non-finite
        input or target are skipped as well.
      unroll: `lax.scan` unroll factor (static).
      **update_kwargs: keyword arguments of `update` (``age_fn`` static, the rest traceable).

    Returns:
      The state after the N updates.
    """
    n = xs.shape[0]
    timestamps = jnp.broadcast_to(jnp.asarray(timestamps, jnp.int32), (n,))
    valid = jnp.ones((n,), bool) if valid is None else jnp.asarray(valid, bool)

    def body(carry, inputs):
        x, y, t, ok = inputs
        return update(carry, x, y, hyper, t, valid=ok, **update_kwargs), None

    state, _ = jax.lax.scan(body, state, (xs, ys, timestamps, valid), unroll=unroll)
    return state
