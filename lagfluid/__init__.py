"""lagfluid: a PyTorch Geometric model zoo for learned Lagrangian fluid simulation."""

import warnings

__version__ = "0.1.0"

# lagfluid builds sparse CSR matrices every step (kernel sums, the pressure Poisson matrix); torch warns
# once per process that CSR support is "beta". The operations we use are tested here, so the notice is
# noise in every run's log. Only that exact message is silenced.
warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta", category=UserWarning)
