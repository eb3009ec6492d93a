"""CConv, continuous convolutions (Ummenhofer et al. 2020), as lagfluid's second paper A.5 baseline.

DeepLagrangianFluids' network in pure PyTorch (no Open3D, no compiled op), so it runs wherever lagfluid
runs, on the CPU and on CUDA. The package is a lagfluid plugin (entry points in ``pyproject.toml``):

* :mod:`baselines.cconv.conv`: the :class:`~baselines.cconv.conv.ContinuousConv` layer and its pair geometry;
* :mod:`baselines.cconv.network`: :class:`~baselines.cconv.network.CConvNet`, their ``MyParticleNetwork``;
* :mod:`baselines.cconv.boundary`: boundary particles -> surface points with normals;
* :mod:`baselines.cconv.simulator`: ``model=cconv_original`` rollouts, :func:`load_dlf_network`, and the
  simulator of ``model=cconv`` (registered once its weights ship);
* :mod:`baselines.cconv.trainable`: ``task=train model=cconv`` (DeepLagrangianFluids' two-step recipe);
* :mod:`baselines.cconv.oracle`: Open3D's op as the optional test oracle;
* ``conf/``: the config groups (``model/cconv_original``, ``model/cconv``, ``train/cconv_*``, table rows).
"""

from typing import Any


def __getattr__(name: str) -> Any:
    """``load_dlf_network``, imported on first use.

    Finding ``baselines.cconv.conf`` (every command line's config search path, ``lagfluid/plugin_configs.py``)
    imports this package, and its simulator imports torch and PyG: 3.8 s of the 5.6 s that
    ``python -m lagfluid.run model=nope`` took to answer (``python -X importtime``; 0.24 s without).
    """
    if name == "load_dlf_network":
        from .simulator import load_dlf_network

        globals()[name] = load_dlf_network  # once: the next lookup finds it without this hook
        return load_dlf_network
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["load_dlf_network"]
