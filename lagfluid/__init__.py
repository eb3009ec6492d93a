"""lagfluid: a PyTorch Geometric model zoo for learned Lagrangian fluid simulation."""

__version__ = "0.1.0"
