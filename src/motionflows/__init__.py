"""motionflows: probabilistic, controllable human-motion models in JAX."""

__version__ = "0.1.0"
