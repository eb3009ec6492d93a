"""The public plugin surface ``lagfluid.zoo``: every name documented, and the moved layers load old weights.

That the baselines and the test plugin import nothing else of lagfluid is ``tests/test_layers.py``'s check.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

import lagfluid.zoo as zoo
from lagfluid.models.fgn.networks import load_network

REPO = Path(__file__).resolve().parents[1]
FGN_WEIGHTS = REPO / "lagfluid" / "weights" / "fgn"
GNS_WEIGHTS = REPO / "baselines" / "gns" / "weights" / "dagger" / "gns.pt"


def _readme_section(title: str) -> str:
    text = (REPO / "README.md").read_text(encoding="utf-8")
    start = text.index(f"\n## {title}\n")
    return text[start : text.index("\n## ", start + 1)]


def test_every_name_of_the_surface_is_in_its_docstring_and_in_the_readme():
    listed = re.findall(r"^    ``(\w+)``  ", zoo.__doc__, flags=re.MULTILINE)  # the docstring's name column
    assert sorted(listed) == sorted(zoo.__all__)
    assert len(set(listed)) == len(listed)
    readme = _readme_section("Adding a model")
    missing = [name for name in zoo.__all__ if f"`{name}`" not in readme]
    assert not missing, f"README's 'Adding a model' does not name {missing}"
    for name in zoo.__all__:
        assert getattr(zoo, name) is not None


def test_the_shared_layers_keep_their_state_dict_keys():
    # the authors' build_shared_mlp layout: Linear (no bias under LayerNorm), LayerNorm, activation, ...
    mlp = zoo.make_mlp([2, 4, 3], "silu", layer_norm=True)
    assert list(mlp.state_dict()) == ["0.weight", "1.weight", "1.bias", "3.weight", "4.weight", "4.bias"]
    assert list(zoo.make_mlp([2, 4], "relu", act_first=True).state_dict()) == ["1.weight", "1.bias"]
    standardizer = zoo.Standardizer(3)
    standardizer.set([1.0, 2.0, 3.0], [2.0, 0.0, 4.0])  # a constant channel's std becomes 1
    assert list(standardizer.state_dict()) == ["mean", "std"]
    x = torch.tensor([[3.0, 2.0, 7.0]])
    assert standardizer(x).tolist() == [[1.0, 0.0, 1.0]]
    assert standardizer.inverse(standardizer(x)).tolist() == x.tolist()


@pytest.mark.parametrize("kind", ["advection", "collision", "pressure"])
def test_fgns_shipped_weights_load_into_networks_built_on_the_shared_layers(kind):
    net, ckpt = load_network(FGN_WEIGHTS / f"{kind}.pt", kind)  # load_state_dict is strict
    assert set(net.state_dict()) == set(ckpt["state_dict"])
    assert any(key.endswith(".std") for key in net.state_dict())  # Standardizer buffers among them


@pytest.mark.skipif(not GNS_WEIGHTS.is_file(), reason="no GNS weights in the checkout")
def test_gns_weights_load_into_its_network_with_the_shared_standardizer():
    from baselines.gns.simulator import load_gns

    net = load_gns(GNS_WEIGHTS)
    assert isinstance(net.velocity, zoo.Standardizer)
    assert set(net.state_dict()) == set(zoo.read_checkpoint(GNS_WEIGHTS)["state_dict"])
