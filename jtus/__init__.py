"""jtus: neural temporal upsampling (DLCTUS and its baselines) in JAX."""

__version__ = "0.1.0"
