"""safecdt-jax: Safe-CDT deployment of constrained decision transformers, in JAX.

The workflow is `safecdt_jax.api` (`collect`, `pretrain`, `load_policy`, `deploy`, `evaluate`);
the subpackages hold the pieces (`envs`, `data`, `model`, `pretrain`, `deploy`, `baselines`,
`theory`, `paper`). Importing the package loads nothing heavy, so the command line starts fast.
"""

__version__ = "0.1.0"
