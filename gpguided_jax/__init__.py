"""gpguided_jax: guided policy search with sparse online Gaussian processes in JAX.

A JAX implementation of Jakab & Csato, "Reinforcement learning with guided policy search using
Gaussian processes" (IJCNN 2012).

Importing the package does NOT change JAX's global configuration. Runs are float64 by default
(`TrainConfig.dtype`), which needs JAX's 64-bit mode: call `gpguided_jax.enable_x64()` first, or
choose `dtype="float32"`. The `gpguided` command line does this for you (`--dtype`).
"""

# critic, model_based and policy_gradient declare the built-in methods, registered as their
# modules are imported (`gpguided_jax.methods`): the paper's four, gp_critic and gp_model
from gpguided_jax import critic, kernels, model_based, pendulum, policy_gradient, sparse_gp
from gpguided_jax._x64 import enable_x64, x64_enabled

__version__ = "0.2.0"

__all__ = ["critic", "enable_x64", "kernels", "model_based", "pendulum", "policy_gradient",
           "sparse_gp", "x64_enabled", "__version__"]
