"""GNS, the graph network simulator (Sanchez-Gonzalez et al. 2020), as lagfluid's paper A.5 baseline.

``model=gns``: an encoder-processor-decoder of interaction-network blocks that predicts each fluid
particle's acceleration from its last velocities and its neighbourhood, stepped by semi-implicit Euler at
the spacing of its training frames. The package is a lagfluid plugin (entry points in ``pyproject.toml``):

* :mod:`baselines.gns.network`: the PyG modules (:class:`~baselines.gns.network.GNSNet`);
* :mod:`baselines.gns.graph`: the graph and its inputs, one function for training and rollouts;
* :mod:`baselines.gns.trainable`: ``task=train model=gns`` (noise, pushforward, statistics);
* :mod:`baselines.gns.simulator`: ``model=gns`` rollouts (MPS warm start, explicit velocities);
* ``conf/``: the config groups (``model/gns``, ``train/gns_cpu``, ``train/gns_paper``, table rows);
* ``weights/``: the shipped weights and their model card.
"""
