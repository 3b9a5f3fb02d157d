"""Plain NumPy reference of the sparse online GP (SPEC §2): the test oracle and benchmark baseline.

One point at a time, variable-size arrays, no masks, no vectorisation over seeds. It follows the
SPEC §2 equations literally (concatenate a row and column on insertion, ``np.delete`` on deletion),
so it is an implementation independent of the fixed-slot, rank-one formulation in
`gpguided_jax.sparse_gp`. The numerical guards are the same as there (see `sparse_gp.update`):

* a non-finite input or target is skipped (the GP is left unchanged);
* the latent variance is floored: v = max(k** + k^T C k, gamma, variance_floor);
* the denominators Q_jj and Q_jj + C_jj are floored at eps / k** and 100 eps Q_jj;
* a point is added as a basis vector iff gamma >= max(novelty_tol, 10 eps) * k**;
* in the projected update gamma is clipped to [0, v] (exact arithmetic gives 0 <= gamma <= v);
* the age penalty g_exp has its exponent capped at log(finfo.max) / 2, and g_logit uses
  tau = t / max(t_max, 1) clipped to [logit_eps, 1 - logit_eps].

Convention: sigma^2(x) = k(x, x) + k^T C k with C negative semi-definite (Csato-Opper sign).
"""

from __future__ import annotations

import numpy as np


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
        novelty_tol: float | None = None,
        age_penalty: float = 0.0,
        age_scale: float = 1.0,
        age_fn: str = "exp",
        variance_floor: float | None = None,
        logit_eps: float = 1e-3,
        dtype=np.float64,
    ):
        self.capacity = int(capacity)
        self.dtype = np.dtype(dtype)
        eps = self.eps = float(np.finfo(self.dtype).eps)
        self.lengthscales = np.asarray(lengthscales, self.dtype)
        self.signal_variance = self.dtype.type(signal_variance)
        self.noise_variance = self.dtype.type(noise_variance)
        self.novelty_tol = default_novelty_tol(self.dtype) if novelty_tol is None else novelty_tol
        self.novelty_tol = max(float(self.novelty_tol), 10.0 * eps)
        self.variance_floor = (
            default_variance_floor(self.dtype) if variance_floor is None else variance_floor
        )
        self.age_penalty = float(age_penalty)
        self.age_scale = float(age_scale)
        self.age_fn = age_fn
        self.logit_eps = float(logit_eps)
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
        """(mean, latent variance clipped to [0, k(x, x)]) at one input x (D,)."""
        x = np.asarray(x, self.dtype)
        k = self.kernel_vector(x)
        var = self.signal_variance + k @ self.C @ k
        return float(k @ self.alpha), float(np.clip(var, 0.0, self.signal_variance))

    def update(self, x, y, timestamp: int) -> str:
        """Takes in one pair; returns ``"skipped"``, ``"projected"``, ``"added"`` or ``"exchanged"``."""
        x = np.asarray(x, self.dtype)
        y = self.dtype.type(y)
        if not (np.all(np.isfinite(x)) and np.isfinite(y)):
            return "skipped"
        k = self.kernel_vector(x)
        kxx = self.signal_variance
        Ck = self.C @ k
        mean = k @ self.alpha
        e_hat = self.Q @ k
        gamma = kxx - k @ e_hat
        v = max(kxx + k @ Ck, gamma, self.variance_floor)
        q = (y - mean) / (self.noise_variance + v)
        r = -1.0 / (self.noise_variance + v)
        if gamma >= self.novelty_tol * kxx:
            s = np.append(Ck, 1.0)
            self.alpha = np.append(self.alpha, 0.0) + q * s
            self.C = np.pad(self.C, ((0, 1), (0, 1))) + r * np.outer(s, s)
            u = np.append(e_hat, -1.0)
            self.Q = np.pad(self.Q, ((0, 1), (0, 1))) + np.outer(u, u) / gamma
            self.basis_vectors = np.vstack([self.basis_vectors, x[None, :]])
            self.timestamps = np.append(self.timestamps, int(timestamp))
            outcome = "added"
            if self.size > self.capacity:
                self.delete(int(np.argmin(self.scores())))
                outcome = "exchanged"
        else:
            gamma = min(max(gamma, 0.0), v)
            eta = 1.0 / (1.0 + gamma * r)
            s = Ck + e_hat
            self.alpha = self.alpha + q * eta * s
            self.C = self.C + r * eta * np.outer(s, s)
            outcome = "projected"
        self.C = 0.5 * (self.C + self.C.T)
        self.Q = 0.5 * (self.Q + self.Q.T)
        return outcome

    def scores(self) -> np.ndarray:
        """eq. 13: alpha_i^2 / (Q_ii + C_ii) + lambda g(t_i)."""
        tiny = np.finfo(self.dtype).eps / self.signal_variance
        q_diag = np.diag(self.Q)
        kl = self.alpha**2 / np.maximum(q_diag + np.diag(self.C), 100 * self.eps * q_diag + tiny)
        if self.age_penalty == 0.0:
            return kl
        g = age_function(self.timestamps, self.age_scale, self.age_fn, self.logit_eps, self.dtype)
        return kl + self.age_penalty * g

    def delete(self, j: int) -> None:
        """KL-optimal removal of basis vector j (SPEC §2)."""
        tiny = np.finfo(self.dtype).eps / self.signal_variance
        a_star = self.alpha[j]
        c_star = self.C[j, j]
        q_star = max(self.Q[j, j], tiny)
        qc_star = max(self.Q[j, j] + self.C[j, j], 100 * self.eps * q_star + tiny)
        del c_star
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


def default_novelty_tol(dtype) -> float:
    """1e-6 of k(x, x) in float64 (Csato's usual value), 1e-3 in float32 (keeps Q conditioned)."""
    return 1e-6 if np.dtype(dtype) == np.float64 else 1e-3


def default_variance_floor(dtype) -> float:
    """Absolute floor on the latent variance: 1e-12 (float64) or 1e-6 (float32)."""
    return 1e-12 if np.dtype(dtype) == np.float64 else 1e-6
