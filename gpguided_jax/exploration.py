"""Exploration noise processes and their likelihoods (design: docs/design.md#exploration).

The paper explores with white noise: a new, independent draw at every control step. At 200 Hz
that averages out over the pendulum's inertia. This module gives the training loop temporally
correlated exploration, each with the exact likelihood that REINFORCE and the GP gradient need:

* ``white``: eps_t independent N(0, 1) (the paper);
* ``ou``: an Ornstein-Uhlenbeck process sampled at the decision points, i.e. the AR(1) process
  eps_t = rho eps_{t-1} + sqrt(1 - rho^2) xi_t with rho = exp(-dt / tau), tau its correlation
  time in seconds, started from its stationary law;
* ``coloured``: stationary Gaussian noise with power spectrum S(f) ~ f^-beta (beta = 1 pink,
  2 red), the law of Eberhard et al.'s FFT sampler truncated to one episode.

Each is a zero-mean stationary Gaussian process with unit variance, eps ~ N(0, C) over an
episode's D decision points, written eps = L xi with C = L L^T (L lower triangular) and xi
standard normal: xi = W eps, W = L^-1, is the sequence of *innovations*, xi_t the part of eps_t
that the past eps_<t does not predict.

A Gaussian policy acts a_t = m_t + s_t eps_t, with m_t = c(s_t; theta) (and s_t its exploration
standard deviation: sigma, or sigma_GP(s_t) of the guided-variance policy). Given the visited
states, eps_t = (a_t - m_t) / s_t and the map from eps to a is triangular with diagonal s_t, so

  log p(a_0..a_t) = sum_{i<=t} [ -xi_i^2 / 2 - log s_i - log L_ii ] + const,

and the score of step t, the gradient of log p(a_t | a_<t), is (`correlated_scores`)

  score_t = xi_t sum_{i<=t} W_ti (J_m,i + eps_i J_s,i) - J_s,t,
  J_m,i = grad m_i / s_i,   J_s,i = grad s_i / s_i.

With W = I (white noise) this is the familiar eps_t J_m,t + (eps_t^2 - 1) J_s,t. The sum over t
is the gradient of the joint density, so a REINFORCE estimate with returns-to-go stays unbiased
(each score_t has zero mean given the past).

Held actions (`hold_steps`) are a separate choice: the policy decides every k-th step and the
action is held in between; the noise processes above then live on the decision points, with
dt replaced by k dt.

``parameter`` is state-dependent exploration in the controller's parameters (Rueckstiess et al.
2008; Raffin et al.'s gSDE; per episode, the parameter noise of PGPE and Plappert et al.): the
controller c(s; theta_c) = u_max tanh(<theta_c, psi(s)>) acts with perturbed weights
theta_c + (sigma / u_max) eps_j, i.e. the pre-activation noise (sigma / u_max) <eps_j, psi(s)>,
where eps_j ~ N(0, I) is drawn afresh every `block` decisions (once per episode by default).
Given the states the actions are a deterministic function of the perturbed weights, whose
density is Gaussian, so the score of block j (`parameter_scores`) is

  d/dtheta_c = eps_j u_max / sigma,   d/dlog sigma = |eps_j|^2 - d,

d the number of weights; it sits at the block's first decision, and each has zero mean given the
past, so REINFORCE with returns-to-go from that decision stays unbiased.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gpguided_jax import _random

NOISES = ("white", "ou", "coloured", "parameter")


class NoiseProcess(NamedTuple):
    """A unit-variance stationary Gaussian noise over `length` decision points (static), or the
    controller's parameter noise ('parameter').

    Attributes:
      name: 'white', 'ou', 'coloured' or 'parameter'.
      length: D, the decision points per episode.
      rho: the AR(1) coefficient exp(-dt / tau) ('ou'; 0 otherwise).
      cholesky: (D, D) L with C = L L^T ('coloured'; None otherwise), float64 NumPy.
      whitener: (D, D) W = L^-1 ('coloured'; None otherwise), float64 NumPy.
      block: decisions per draw of the parameter noise ('parameter'; 0 otherwise).
    """

    name: str
    length: int
    rho: float = 0.0
    cholesky: np.ndarray | None = None
    whitener: np.ndarray | None = None
    block: int = 0

    @property
    def num_blocks(self) -> int:
        """Draws of the parameter noise per episode ('parameter')."""
        return -(-self.length // self.block)

    def correlation(self) -> np.ndarray:
        """(D, D) the correlation matrix C of the process (float64, for tests and figures)."""
        if self.name == "parameter":
            raise ValueError("parameter noise has no action-noise correlation of its own: it "
                             "depends on the visited states")
        d = self.length
        if self.name == "white":
            return np.eye(d)
        if self.name == "ou":
            lag = np.abs(np.arange(d)[:, None] - np.arange(d)[None, :])
            return self.rho ** lag
        return self.cholesky @ self.cholesky.T

    def sample(self, key, dtype):
        """(eps, xi): one episode's noise (D,) and its innovations (D,), xi = W eps."""
        xi = _random.normal(key, (self.length,), dtype)
        return self.colour(xi), xi

    def colour(self, xi):
        """eps = L xi along the leading axis."""
        if self.name == "white":
            return xi
        if self.name == "ou":
            rho = jnp.asarray(self.rho, xi.dtype)
            scale = jnp.sqrt(1.0 - rho * rho)

            def step(prev, x):
                e = rho * prev + scale * x
                return e, e

            first = xi[0]
            _, rest = jax.lax.scan(step, first, xi[1:])
            return jnp.concatenate([first[None], rest])
        return jnp.asarray(self.cholesky, xi.dtype) @ xi

    def whiten(self, x):
        """W x along the leading axis of an array (D, ...)."""
        if self.name == "white":
            return x
        if self.name == "ou":
            rho = jnp.asarray(self.rho, x.dtype)
            prev = jnp.concatenate([jnp.zeros_like(x[:1]), x[:-1]])
            rest = (x - rho * prev) / jnp.sqrt(1.0 - rho * rho)
            return jnp.concatenate([x[:1], rest[1:]])
        w = jnp.asarray(self.whitener, x.dtype)
        return jnp.tensordot(w, x, axes=1)


def hold_steps(hold_time: float, dt: float) -> int:
    """Control steps per decision for a hold of `hold_time` seconds (0: every step): the nearest
    whole number of steps, at least 1."""
    if hold_time <= 0:
        return 1
    return max(1, int(round(hold_time / dt)))


def num_decisions(episode_length: int, hold: int) -> int:
    """Decision points of an episode of `episode_length` steps with actions held `hold` steps."""
    return -(-episode_length // hold)


def ou_coefficient(correlation_time: float, dt: float) -> float:
    """rho = exp(-dt / tau) of an OU process of correlation time tau seen every dt seconds."""
    return math.exp(-dt / correlation_time)


def power_law_autocovariance(length: int, exponent: float) -> np.ndarray:
    """Autocovariance r_0..r_{D-1} (r_0 = 1) of stationary noise with spectrum S(f) ~ f^-exponent.

    The law of the FFT sampler of Eberhard et al. (the `colorednoise` package, which follows Timmer
    & Koenig 1995) on 2D points, the first D of which are kept: frequencies f = k / 2D, S(0) set
    to S(1 / 2D), and r = the inverse real FFT of S. A principal block of a circulant covariance
    with a positive spectrum, so positive definite.
    """
    n = 2 * length
    f = np.fft.rfftfreq(n)
    f[0] = f[1]
    spectrum = f ** (-float(exponent))
    r = np.fft.irfft(spectrum, n)
    return r[:length] / r[0]


@functools.lru_cache(maxsize=32)
def make_noise(name: str, length: int, dt: float, correlation_time: float = 0.5,
               exponent: float = 1.0, resample_time: float = 0.0) -> NoiseProcess:
    """The noise process `name` over `length` decision points `dt` seconds apart.

    Args:
      name: 'white', 'ou', 'coloured' or 'parameter'.
      length: D, decision points per episode.
      dt: seconds between decision points (the control interval times the hold).
      correlation_time: tau of 'ou', seconds.
      exponent: beta of 'coloured' (0 white, 1 pink, 2 red).
      resample_time: seconds between draws of 'parameter' (rounded to whole decisions, at least
        one); 0 or more than an episode: one draw per episode.
    """
    if name == "white":
        return NoiseProcess("white", length)
    if name == "parameter":
        if not resample_time >= 0:
            raise ValueError(f"the parameter noise's resample time must be >= 0 seconds, got "
                             f"{resample_time}")
        block = length if resample_time == 0 else min(length, max(1, round(resample_time / dt)))
        return NoiseProcess("parameter", length, block=block)
    if name == "ou":
        if not correlation_time > 0:
            raise ValueError(f"the OU correlation time must be > 0 seconds, got {correlation_time}")
        return NoiseProcess("ou", length, rho=ou_coefficient(correlation_time, dt))
    if name == "coloured":
        if not 0 <= exponent <= 3:
            raise ValueError(f"the coloured-noise exponent must be in [0, 3], got {exponent}")
        r = power_law_autocovariance(length, exponent)
        lag = np.abs(np.arange(length)[:, None] - np.arange(length)[None, :])
        chol = np.linalg.cholesky(r[lag])
        whitener = np.linalg.solve(chol, np.eye(length))  # triangular, float64
        whitener = np.tril(whitener)
        return NoiseProcess("coloured", length, cholesky=chol, whitener=whitener)
    raise ValueError(f"unknown exploration noise {name!r}; choose from {NOISES}")


def correlated_scores(noise: NoiseProcess, eps, xi, j_mean, j_std):
    """Per-decision scores grad log p(a_t | a_<t) of a Gaussian policy driven by `noise`.

    Args:
      noise: the process.
      eps: (D,) the noise that was used, a_t = m_t + s_t eps_t.
      xi: (D,) its innovations W eps.
      j_mean: pytree, leaves (D, ...): grad m_t / s_t.
      j_std: pytree like j_mean: grad s_t / s_t.

    Returns:
      The scores, a pytree like j_mean: xi_t (W (J_m + eps J_s))_t - J_s,t (module notes).
    """
    def one(jm, js):
        e = eps.reshape((-1,) + (1,) * (jm.ndim - 1))
        x = xi.reshape(e.shape)
        return x * noise.whiten(jm + e * js) - js

    return jax.tree_util.tree_map(one, j_mean, j_std)


def log_density(noise: NoiseProcess, eps, std):
    """log p of the actions a_t = m_t + s_t eps_t, t < D, given the states: the joint Gaussian
    density of eps under C, minus sum log s_t (the independent reference of `correlated_scores`:
    its gradient through eps = (a - m)/s and s)."""
    c = jnp.asarray(noise.correlation(), eps.dtype)
    chol = jnp.linalg.cholesky(c)
    z = jax.scipy.linalg.solve_triangular(chol, eps, lower=True)
    d = eps.shape[0]
    return (-0.5 * z @ z - jnp.sum(jnp.log(jnp.diagonal(chol))) - jnp.sum(jnp.log(std))
            - 0.5 * d * math.log(2 * math.pi))


def sample_parameter_noise(noise: NoiseProcess, key, like):
    """eps: standard normal draws shaped like the pytree `like` with a leading (num_blocks,) axis."""
    leaves, treedef = jax.tree_util.tree_flatten(like)
    keys = jax.random.split(key, len(leaves))
    return jax.tree_util.tree_unflatten(treedef, [
        _random.normal(k, (noise.num_blocks,) + jnp.shape(x), jnp.result_type(x))
        for k, x in zip(keys, leaves)])


def perturbed_parameters(params, eps_block, scale):
    """theta_c + scale * eps_j for one block's draw `eps_block` (a pytree like params)."""
    return jax.tree_util.tree_map(lambda w, e: w + scale * e, params, eps_block)


def parameter_scores(noise: NoiseProcess, eps, std, u_max: float):
    """Per-decision scores of the parameter noise: at each block's first decision
    (eps_j u_max / sigma, |eps_j|^2 - d), 0 at the other decisions (module notes).

    Args:
      noise: the 'parameter' process.
      eps: pytree of (num_blocks, ...) draws (`sample_parameter_noise`).
      std: () sigma, so that the weights move by sigma / u_max per unit of eps.
      u_max: the controller's torque limit.

    Returns:
      (controller scores, a pytree like eps with a leading (D,) axis of decisions; log-sigma
      scores (D,)).
    """
    d = noise.length
    block_of = np.arange(d) // noise.block
    first = jnp.asarray(np.arange(d) % noise.block == 0)

    def at_decisions(per_block):
        per_decision = per_block[block_of]
        mask = first.reshape((-1,) + (1,) * (per_block.ndim - 1))
        return jnp.where(mask, per_decision, jnp.zeros_like(per_decision))

    leaves = jax.tree_util.tree_leaves(eps)
    num_weights = sum(int(np.prod(x.shape[1:])) for x in leaves)
    sq = sum(jnp.sum(x.reshape(x.shape[0], -1) ** 2, axis=1) for x in leaves)
    controller = jax.tree_util.tree_map(lambda e: at_decisions(e * (u_max / std)), eps)
    return controller, at_decisions(sq - num_weights)
