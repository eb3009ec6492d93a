"""A tiny end-to-end model, packaged as a third-party lagfluid plugin would be (``tests/test_plugin.py``).

Nothing in ``lagfluid`` or ``benchmarks`` names it, and it imports lagfluid only through the plugin surface
:mod:`lagfluid.zoo`. It registers through three entry-point groups, as a ``pyproject.toml`` of its own would
declare them::

    [project.entry-points."lagfluid.simulators"]
    tiny_mlp = "tinymlp.model:build_simulator"
    [project.entry-points."lagfluid.trainables"]
    tiny_mlp = "tinymlp.model:build_trainables"
    [project.entry-points."lagfluid.configs"]
    tiny_mlp = "tinymlp.conf"
"""
