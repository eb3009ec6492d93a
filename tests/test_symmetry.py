"""The horizontal symmetries used for augmentation: group action on points, and MPS commutes with them."""

from __future__ import annotations

import itertools

import pytest
import torch
from hydra import compose, initialize_config_dir

from lagfluid.data.symmetry import HorizontalSymmetry
from lagfluid.models.mps_simulator import build_mps
from lagfluid.run import CONF_DIR
from lagfluid.state import ParticleState
from lagfluid.tasks.config import build_initial_state

ALL = [HorizontalSymmetry(*bits) for bits in itertools.product([False, True], repeat=3)]
BOX = torch.tensor([[0.5, -1.0, 0.0], [2.5, 3.0, 1.5]], dtype=torch.float64)


def _corners(box: torch.Tensor) -> set[tuple[float, ...]]:
    return {tuple(float(box[i, a]) for a, i in enumerate(idx)) for idx in itertools.product([0, 1], repeat=3)}


@pytest.mark.parametrize("symmetry", ALL, ids=str)
def test_each_maps_its_box_onto_the_mapped_box_and_moves_vectors_like_differences(symmetry):
    corners = torch.tensor(sorted(_corners(BOX)), dtype=torch.float64)
    assert _corners(symmetry.bounds(BOX)) == {tuple(p) for p in symmetry.points(corners, BOX).tolist()}
    x, y = torch.rand(2, 10, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(symmetry.points(x, BOX) - symmetry.points(y, BOX), symmetry.vectors(x - y))
    assert torch.equal(symmetry.vectors(x)[:, 2], x[:, 2])  # gravity's axis is never touched


def test_the_eight_are_distinct_and_the_draw_reaches_them_all():
    images = {tuple(s.vectors(torch.tensor([1.0, 2.0, 3.0])).tolist()) for s in ALL}
    assert len(images) == 8
    generator = torch.Generator().manual_seed(0)
    assert {HorizontalSymmetry.draw(generator) for _ in range(200)} == set(ALL)


def test_per_point_boxes_map_each_scene_into_its_own_box():
    boxes = torch.stack([BOX, BOX + torch.tensor([10.0, 0.0, 0.0], dtype=torch.float64)])
    x = torch.stack([BOX.mean(0) + 0.3, boxes[1].mean(0) + 0.3])
    mapped = HorizontalSymmetry(flip_x=True).points(x, boxes)
    torch.testing.assert_close(mapped[:, 0], boxes[:, :, 0].mean(1) - 0.3)


@pytest.mark.parametrize(
    "symmetry", [HorizontalSymmetry(True, False, False), HorizontalSymmetry(False, True, True)]
)
def test_an_mps_step_of_the_mapped_scene_is_the_mapped_step(symmetry):
    """Physics: the solver commutes with a horizontal symmetry, so augmented windows are solutions too."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = compose("config", overrides=["model=mps", "scene=dam_small", "dtype=float64"])
    state = build_initial_state(cfg)
    state = ParticleState(
        pos=state.pos,
        vel=state.vel + torch.tensor([0.3, -0.2, 0.0], dtype=torch.float64),  # an asymmetric flow
        ptype=state.ptype,
        params=state.params,
        bounds=state.bounds,
    )
    mapped = ParticleState(
        pos=symmetry.points(state.pos, state.bounds),
        vel=symmetry.vectors(state.vel),
        ptype=state.ptype,
        params=state.params,
        bounds=symmetry.bounds(state.bounds),
    )
    results = []
    for start in (state, mapped):
        mps = build_mps(cfg)
        mps.reset(start)
        s = start
        for _ in range(3):
            s = mps.step(s)
        results.append(s)
    torch.testing.assert_close(
        results[1].pos, symmetry.points(results[0].pos, state.bounds), atol=1e-9, rtol=0
    )
    torch.testing.assert_close(results[1].vel, symmetry.vectors(results[0].vel), atol=1e-7, rtol=0)
