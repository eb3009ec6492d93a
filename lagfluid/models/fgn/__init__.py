"""FGN (Fluid Graph Networks): the MPS split-step scheme with three learned stages.

* :mod:`~lagfluid.models.fgn.networks`: the three PyG networks, :func:`build_network`, :func:`load_network`;
* :mod:`~lagfluid.models.fgn.inputs`: one function per network building its inputs (training and inference);
* :mod:`~lagfluid.models.fgn.learned_stages`: the networks behind the split-step scheme's stage protocols;
* :mod:`~lagfluid.models.fgn.simulator`: ``model=fgn``, ``hybrid``, ``fgn_original`` (registry builders);
* :mod:`~lagfluid.models.fgn.original`: the authors' published weights;
* :mod:`~lagfluid.models.fgn.trainables`: the three networks as trainables for ``task=train``.
"""
