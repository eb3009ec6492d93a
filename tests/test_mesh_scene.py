"""``scene=mesh``: a tank, fluid and obstacles from mesh files, checked against the built dam and by hand."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from hydra import compose, initialize_config_dir

from lagfluid.run import CONF_DIR
from lagfluid.scenes import build_scene
from lagfluid.state import ParticleType, SceneError
from lagfluid.tasks.simulate import simulate

L0 = 0.05


def _box(path, lower, upper):
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    mesh = trimesh.creation.box(extents=upper - lower)
    mesh.apply_translation((lower + upper) / 2)
    mesh.export(path)
    return str(path)


@pytest.fixture
def tank_and_block(tmp_path):
    """The dam_small scene as meshes: an 8 x 8 x 10 l0 column in a 21 x 9 l0 tank (inner walls at 0 and L)."""
    tank = _box(tmp_path / "tank.stl", [0, 0, 0], [21 * L0, 9 * L0, 40 * L0])
    block = _box(tmp_path / "block.stl", [0, 0, 0], [8 * L0, 8 * L0, 10 * L0])
    return tank, block


def _rows(state, kind):
    pos = state.pos[state.ptype == kind].double().numpy() / L0
    return {tuple(p) for p in np.round(pos).astype(int).tolist()}


def test_a_box_tank_and_block_are_the_built_dam(tank_and_block):
    tank, block = tank_and_block
    mesh = build_scene("mesh", container=tank, fluid=block)
    dam = build_scene("dam", fluid_size=[8, 8, 10], tank_size=[21, 9])
    assert _rows(mesh, ParticleType.FLUID) == _rows(dam, ParticleType.FLUID)  # x, y 1..8, z 1..10
    # the inner wall layer lies on the tank's surface: floor z = 0, end walls x = 0 and 21, sides y = 0 and 9
    walls = _rows(mesh, ParticleType.WALL)
    inner = {(x, y, 0) for x in range(1, 21) for y in range(1, 9)}
    inner |= {(0, y, z) for y in range(1, 9) for z in range(1, 21)} | {(21, 4, 5), (10, 0, 3), (10, 9, 3)}
    assert inner <= walls
    assert (10, 4, -1) in walls and (10, 4, -2) in _rows(mesh, ParticleType.DUMMY)  # 2 wall, 2 dummy layers
    assert (10, 4, -4) not in _rows(mesh, ParticleType.DUMMY) | walls
    # open top: the boundary stops at twice the column's height (20 l0), as the dam's walls do
    top = int(mesh.pos[mesh.n_fluid :, 2].max() / L0 + 0.5)
    assert top == 20 == int(dam.pos[dam.n_fluid :, 2].max() / L0 + 0.5)


def test_an_obstacle_is_a_shell_and_keeps_the_fluid_out(tmp_path):
    tank = _box(tmp_path / "tank.stl", [0, 0, 0], [1.0, 0.5, 1.0])
    block = _box(tmp_path / "block.stl", [0, 0, 0], [1.0, 0.5, 0.3])
    rock = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    rock.apply_translation([0.5, 0.25, 0.15])
    rock.export(tmp_path / "rock.stl")
    state = build_scene("mesh", container=tank, fluid=block, obstacles=[str(tmp_path / "rock.stl")])
    pos, ptype = state.pos.double().numpy(), state.ptype.numpy()
    r = np.linalg.norm(pos - [0.5, 0.25, 0.15], axis=1)
    assert (r[ptype == ParticleType.FLUID] > 0.1 + 0.5 * L0 - 1e-3).all()  # no fluid in or on the rock
    shell = ptype[(r < 0.1 + 0.5 * L0 - 1e-3) & (r > 0.1 - 1.5 * L0 + 1e-3)]  # its outer two layers
    assert len(shell) > 0 and (shell == ParticleType.WALL).all()
    assert (r[ptype == ParticleType.DUMMY] > 0.1 - 3.5 * L0 - 1e-3).all()  # hollow beyond four layers


def test_bad_meshes_are_named(tmp_path, tank_and_block):
    tank, block = tank_and_block
    holed = trimesh.creation.box(extents=[1.0, 0.5, 1.0])
    holed.update_faces(np.arange(len(holed.faces)) != 0)
    holed.export(tmp_path / "holed.stl")
    with pytest.raises(SceneError, match=r"holed\.stl is not watertight"):
        build_scene("mesh", container=str(tmp_path / "holed.stl"), fluid=block)
    outside = _box(tmp_path / "outside.stl", [0.5, 0, 0], [1.5, 0.2, 0.2])
    with pytest.raises(SceneError, match=r"outside\.stl .* reaches outside the container"):
        build_scene("mesh", container=tank, fluid=outside)
    # a concave tank, an L extruded 1 m up: fluid in its notch is inside its bounding box, outside the tank
    corners = np.array([[0, 0], [1, 0], [1, 0.4], [0.5, 0.4], [0.5, 1], [0, 1], [0, 0.4]], dtype=float)
    triangles = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 6], [6, 3, 4], [6, 4, 5]])
    ell = trimesh.creation.extrude_triangulation(corners, triangles, height=1.0)
    assert ell.is_watertight
    ell.export(tmp_path / "ell.stl")
    notch = _box(tmp_path / "notch.stl", [0.6, 0.5, 0.0], [0.9, 0.9, 0.3])
    with pytest.raises(
        SceneError, match=r"lattice sites of the fluid .*notch\.stl lie outside the container"
    ):
        build_scene("mesh", container=str(tmp_path / "ell.stl"), fluid=notch)
    millimetres = _box(tmp_path / "mm.stl", [0, 0, 0], [1050, 450, 2000])
    with pytest.raises(SceneError, match=r"is 2000 m across at scale 1.0 .* scene\.scale=0\.001"):
        build_scene("mesh", container=millimetres, fluid=block)
    block_mm = _box(tmp_path / "block_mm.stl", [0, 0, 0], [400, 400, 500])
    fine = build_scene("mesh", container=millimetres, fluid=block_mm, scale=0.001)
    assert fine.n_fluid == 8 * 8 * 10
    with pytest.raises(SceneError, match=r"mesh not found: .*nothing\.stl"):
        build_scene("mesh", container=str(tmp_path / "nothing.stl"), fluid=block)
    with pytest.raises(SceneError, match=r"needs scene\.container=<mesh file> and scene\.fluid"):
        build_scene("mesh", fluid=block)


def test_meshes_too_large_for_memory_point_to_scene_scale_not_to_keys_mesh_lacks(
    tmp_path, tank_and_block, monkeypatch
):
    from lagfluid.scenes import validation

    monkeypatch.setattr(validation, "available_memory", lambda: 16 << 30)  # a 16 GiB machine
    # a 500 x 300 x 400 mm tank read as metres: under the 1 km refusal, a lattice of 1.2e12 sites
    tank_mm = _box(tmp_path / "tank_mm.stl", [0, 0, 0], [500, 300, 400])
    block_mm = _box(tmp_path / "block_mm.stl", [0, 0, 0], [200, 200, 250])
    with pytest.raises(SceneError) as refused:
        build_scene("mesh", container=tank_mm, fluid=block_mm)
    assert str(refused.value) == (
        f"scene 'mesh' ({tank_mm}): the lattice of its 500 m container at l0 = 0.05 m needs ~2.87e+04 GiB, "
        "but 16 GiB of memory are available; meshes in millimetres need scene.scale=0.001 (mesh units -> m); "
        "otherwise make scene.scale or the meshes smaller, or scene.params.l0 larger"
    )
    assert build_scene("mesh", container=tank_mm, fluid=block_mm, scale=0.001).n_fluid == 4 * 4 * 5
    # the rollout's own estimate (after the particles are built) gives the same advice
    tank, block = tank_and_block
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            config_name="config",
            overrides=[
                "scene=mesh",
                f"scene.container={tank}",
                f"scene.fluid={block}",
                f"out_dir={tmp_path}/r",
            ],
        )
    monkeypatch.setattr(validation, "available_memory", lambda: 50 << 20)
    with pytest.raises(
        SceneError,
        match=r"a rollout of model mps \(640 fluid of .* particles\) needs ~.*"
        r"GiB, but 0.0488 GiB .*; meshes in millimetres need scene\.scale=0\.001",
    ) as refused:
        simulate(cfg)
    assert "fluid_size" not in str(refused.value) and "tank_size" not in str(refused.value)


@pytest.mark.parametrize("model", ["mps", "fgn"])
def test_a_mesh_scene_rolls_out(tank_and_block, tmp_path, model):
    tank, block = tank_and_block
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(
            config_name="config",
            overrides=[
                f"model={model}", "scene=mesh", f"scene.container={tank}", f"scene.fluid={block}", "steps=10",
                "progress=false", f"out_dir={tmp_path}",
            ],
        )  # fmt: skip
    metrics = simulate(cfg)
    assert metrics["complete"] and metrics["particles"]["fluid"] == 640
    assert json.loads((tmp_path / "metrics.json").read_text())["scene"] == "mesh"
