"""lagfluid: a PyTorch Geometric model zoo for learned Lagrangian fluid simulation."""

import warnings

__version__ = "0.1.0"

# lagfluid builds sparse CSR matrices every step (kernel sums, the pressure Poisson matrix); torch warns
# once per process that CSR support is "beta". The operations we use are tested here, so the notice is
# noise in every run's log. Only that exact message is silenced.
warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta", category=UserWarning)


def _register_config_resolvers() -> None:
    """Resolvers used by ``conf/config.yaml``; registered on import so every way of composing it works.

    ``${lagfluid.if_task:TASK,NAME,A,B}`` is ``A`` when ``TASK == NAME``, else ``B``: ``steps`` is the data
    profile's for ``task=generate`` and 500 otherwise, and ``steps=N`` on the command line still sets it.
    ``${lagfluid.plugin_configs:}`` is the plugins' config folders (:mod:`lagfluid.plugin_configs`).
    (``${lagfluid.config_groups:}``, read only by ``--help``, is registered by :mod:`lagfluid.run`.)
    """
    from omegaconf import OmegaConf

    if not OmegaConf.has_resolver("lagfluid.if_task"):
        OmegaConf.register_new_resolver("lagfluid.if_task", lambda task, name, a, b: a if task == name else b)
    if not OmegaConf.has_resolver("lagfluid.plugin_configs"):

        def plugin_configs() -> list[str]:
            from lagfluid.plugin_configs import plugin_search_path

            return plugin_search_path()

        OmegaConf.register_new_resolver("lagfluid.plugin_configs", plugin_configs)


_register_config_resolvers()
