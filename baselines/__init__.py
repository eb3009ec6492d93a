"""lagfluid's baseline models, each a plugin package (``baselines.gns``, ...).

A baseline is four things (``docs/architecture.md#a-model-in-the-zoo``): a simulator, its trainables, a
config folder and entry points (``pyproject.toml``: ``lagfluid.simulators``, ``lagfluid.trainables``,
``lagfluid.configs``).
``lagfluid`` never imports this package; its registry finds the baselines through those entry points.
The baselines import lagfluid only through its plugin surface, :mod:`lagfluid.zoo` (``tests/test_layers.py``).
"""
