"""Plain NumPy reference of the sparse online GP: the test oracle and benchmark baseline
(design: docs/design.md#sparse-gp).

One point at a time, variable-size arrays, no masks, no vectorisation over seeds. It follows the
equations of Csato & Opper literally, in their own parametrisation: the inverse Gram matrix
Q = K_B^{-1} and the covariance correction C, each updated by rank-one terms (concatenate a row and
column on insertion, ``np.delete`` on deletion). So it is independent of the square-root,
fixed-slot formulation of `gpguided_jax.sparse_gp`, and run in ``np.longdouble`` (80-bit on x86)
it is the high-precision oracle for long and ill-conditioned streams, on which the literal
recursion loses accuracy in float64.

It takes the same decisions as `sparse_gp.update` (so that both can be compared point by point):

* a non-finite input or target is skipped (the GP is left unchanged);
* x joins the set iff gamma >= gamma_min = max(max(novelty_tol, resolution) k**,
  noise_novelty sigma_n^2) and the insertion leaves at most one BV with a leave-one-out
  precision Q_ii above 1 / (collapse_fraction gamma_min);
* after the update one BV is deleted if the set is over capacity or a BV has collapsed: the most
  collapsed one (largest Q_ii) if any, otherwise the lowest score of eq. 13;
* the age penalty g_exp has its exponent capped at log(finfo.max) / 2, and g_logit uses
  tau = t / max(t_max, 1) clipped to [logit_eps, 1 - logit_eps].

Convention: sigma^2(x) = k(x, x) + k^T C k with C negative semi-definite (Csato-Opper sign).
"""

from __future__ import annotations

import numpy as np


def resolution(dtype) -> float:
    """The relative novelty the dtype resolves (as `sparse_gp.resolution`): 1e-3 for float32 and
    narrower, 1e-6 for float64 and wider."""
    return 1e-3 if np.finfo(dtype).bits <= 32 else 1e-6


def se_ard(xs: np.ndarray, x: np.ndarray, lengthscales, signal_variance) -> np.ndarray:
    """k(xs_i, x) for the rows of xs (n, D) and one point x (D,)."""
    z = (xs - x[None, :]) / np.asarray(lengthscales)[None, :]
    return signal_variance * np.exp(-0.5 * np.sum(z * z, axis=1))


def age_function(t: np.ndarray, age_scale: float, age_fn: str, logit_eps: float, dtype) -> np.ndarray:
    """g(t_i) of eq. 14 (``"exp"``) or eq. 15 (``"logit"``) over the current BV timestamps."""
    t = np.asarray(t, dtype)
    if age_fn == "exp":
        cap = 0.5 * np.log(np.finfo(dtype).max)
        return np.exp(np.minimum(age_scale * (t - t.min()), cap))
    if age_fn == "logit":
        tau = np.clip(t / max(t.max(), 1.0), logit_eps, 1.0 - logit_eps)
        return age_scale * np.log(tau / (1.0 - tau))
    raise ValueError(f"unknown age_fn {age_fn!r}")


class OnlineGP:
    """Sparse online GP of Csato & Opper with the age-penalised KL deletion of eq. 13.

    Attributes:
      basis_vectors: (n, D) inputs of the n current basis vectors, in insertion order.
      alpha: (n,) mean coefficients.
      C: (n, n) negative semi-definite covariance correction.
      Q: (n, n) inverse Gram matrix of the basis vectors.
      timestamps: (n,) int policy-update index at which each BV was added.
    """

    def __init__(
        self,
        capacity: int,
        input_dim: int,
        lengthscales,
        signal_variance: float,
        noise_variance: float,
        *,
        novelty_tol: float = 0.0,
        noise_novelty: float = 0.01,
        collapse_fraction: float = 0.5,
        age_penalty: float = 0.0,
        age_scale: float = 1.0,
        age_fn: str = "exp",
        logit_eps: float = 1e-3,
        prior_mean: float = 0.0,
        dtype=np.float64,
        resolution_of=None,
    ):
        """`resolution_of`: the dtype whose `resolution` sets the novelty floor (default `dtype`;
        pass np.float64 to replay a float64 run in np.longdouble with the same decisions)."""
        self.capacity = int(capacity)
        self.dtype = np.dtype(dtype)
        f = self.dtype.type
        self.lengthscales = np.asarray(lengthscales, self.dtype)
        self.signal_variance = f(signal_variance)
        self.noise_variance = f(noise_variance)
        rel = max(f(novelty_tol), f(resolution(resolution_of or self.dtype)))
        self.gamma_min = max(rel * self.signal_variance, f(noise_novelty) * self.noise_variance)
        self.max_precision = 1 / (f(collapse_fraction) * self.gamma_min)
        self.age_penalty = f(age_penalty)
        self.age_scale = f(age_scale)
        self.age_fn = age_fn
        self.logit_eps = f(logit_eps)
        self.prior_mean = f(prior_mean)
        self.basis_vectors = np.zeros((0, input_dim), self.dtype)
        self.alpha = np.zeros((0,), self.dtype)
        self.C = np.zeros((0, 0), self.dtype)
        self.Q = np.zeros((0, 0), self.dtype)
        self.timestamps = np.zeros((0,), np.int64)

    @property
    def size(self) -> int:
        return self.alpha.shape[0]

    def kernel_vector(self, x: np.ndarray) -> np.ndarray:
        return se_ard(self.basis_vectors, x, self.lengthscales, self.signal_variance)

    def predict(self, x) -> tuple[float, float]:
        """(mean, latent variance k** + k^T C k) at one input x (D,), in self.dtype."""
        x = np.asarray(x, self.dtype)
        k = self.kernel_vector(x)
        return self.prior_mean + k @ self.alpha, self.signal_variance + k @ self.C @ k

    def update(self, x, y, timestamp: int, *, force: tuple[bool, int | None] | None = None) -> str:
        """Takes in one pair; returns ``"skipped"``, ``"projected"``, ``"added"``, ``"exchanged"`` or
        ``"collapsed"`` (a projected update followed by the deletion of a collapsed BV).

        `force` = (add, delete_index) overrides the decisions (delete_index into the BV list after
        the insertion, or None): to replay another implementation's path in higher precision.
        """
        x = np.asarray(x, self.dtype)
        y = self.dtype.type(y)
        if not (np.all(np.isfinite(x)) and np.isfinite(y)):
            return "skipped"
        k = self.kernel_vector(x)
        kxx = self.signal_variance
        Ck = self.C @ k
        e_hat = self.Q @ k
        gamma = kxx - k @ e_hat
        v = max(kxx + k @ Ck, gamma)
        q = (y - self.prior_mean - k @ self.alpha) / (self.noise_variance + v)
        r = -1 / (self.noise_variance + v)
        novel = gamma >= self.gamma_min
        if novel:
            after = np.diag(self.Q) + e_hat**2 / gamma
            novel = np.sum(after > self.max_precision) <= 1
        if force is not None:
            novel = force[0]
        if novel:
            s = np.append(Ck, 1)
            self.alpha = np.append(self.alpha, 0) + q * s
            self.C = np.pad(self.C, ((0, 1), (0, 1))) + r * np.outer(s, s)
            u = np.append(e_hat, -1)
            self.Q = np.pad(self.Q, ((0, 1), (0, 1))) + np.outer(u, u) / gamma
            self.basis_vectors = np.vstack([self.basis_vectors, x[None, :]])
            self.timestamps = np.append(self.timestamps, int(timestamp))
            outcome = "added"
        else:
            eta = 1 / (1 + gamma * r)
            s = Ck + e_hat
            self.alpha = self.alpha + q * eta * s
            self.C = self.C + r * eta * np.outer(s, s)
            outcome = "projected"
        self.C = (self.C + self.C.T) / 2
        self.Q = (self.Q + self.Q.T) / 2
        precision = np.diag(self.Q)
        collapsed = precision > self.max_precision
        if force is not None:
            if force[1] is not None:
                self.delete(int(force[1]))
                outcome = "exchanged" if outcome == "added" else "collapsed"
        elif collapsed.any():
            self.delete(int(np.argmax(np.where(collapsed, precision, -1))))
            outcome = "exchanged" if outcome == "added" else "collapsed"
        elif self.size > self.capacity:
            self.delete(int(np.argmin(self.scores())))
            outcome = "exchanged"
        return outcome

    def scores(self) -> np.ndarray:
        """eq. 13: alpha_i^2 / (Q_ii + C_ii) + lambda g(t_i)."""
        kl = self.alpha**2 / (np.diag(self.Q) + np.diag(self.C))
        if self.age_penalty == 0:
            return kl
        g = age_function(self.timestamps, self.age_scale, self.age_fn, self.logit_eps, self.dtype)
        return kl + self.age_penalty * g

    def delete(self, j: int) -> None:
        """KL-optimal removal of basis vector j (design: docs/design.md#sparse-gp)."""
        a_star = self.alpha[j]
        q_star = self.Q[j, j]
        qc_star = self.Q[j, j] + self.C[j, j]
        Q_col = np.delete(self.Q[:, j], j)
        C_col = np.delete(self.C[:, j], j)
        alpha = np.delete(self.alpha, j)
        C = np.delete(np.delete(self.C, j, 0), j, 1)
        Q = np.delete(np.delete(self.Q, j, 0), j, 1)
        self.alpha = alpha - a_star * (Q_col + C_col) / qc_star
        self.C = (
            C
            + np.outer(Q_col, Q_col) / q_star
            - np.outer(Q_col + C_col, Q_col + C_col) / qc_star
        )
        self.Q = Q - np.outer(Q_col, Q_col) / q_star
        self.basis_vectors = np.delete(self.basis_vectors, j, 0)
        self.timestamps = np.delete(self.timestamps, j)
