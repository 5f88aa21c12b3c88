"""jtus: neural temporal upsampling (DLCTUS and its baselines) in JAX."""

from jtus.frame import Frame, validate

__version__ = "0.1.0"
__all__ = ["Frame", "validate"]
