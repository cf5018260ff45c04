"""safecdt-jax: Safe-CDT deployment of constrained decision transformers, in JAX."""

__version__ = "0.1.0"
