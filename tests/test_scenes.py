"""Scenes: counts, lattice, layers, obstacles, random draws, grid files and every bad-input error."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from lagfluid.scenes import (
    SCENES,
    Box,
    Container,
    Cylinder,
    FluidBlock,
    Scene,
    Sphere,
    Wedge,
    build_scene,
    load_grid,
    random_layout,
    save_grid,
    waterfall_layout,
)
from lagfluid.state import ParticleType, SceneError, SceneParams

L0 = SceneParams().l0
AUTHORS_DAM = {"fluid": 4000, "wall": 12740, "dummy": 15796}
SMALL = {"tank_size": (40, 40), "wall_height": 20, "fluid_size": (10, 10, 5)}  # a quick random scene


def lattice(state) -> np.ndarray:
    """(N, 3) integer lattice coordinates of a state built at spacing l0."""
    coords = state.pos.double().numpy() / state.params.l0
    assert np.abs(coords - np.rint(coords)).max() < 1e-4
    return np.rint(coords).astype(np.int64)


def counts(state) -> dict[str, int]:
    return {
        "fluid": state.n_fluid,
        "wall": int(state.wall_mask.sum()),
        "dummy": int(state.dummy_mask.sum()),
    }


def small_dam(**options):
    return build_scene("dam", fluid_size=(4, 5, 6), tank_size=(9, 7), **options)


# ------------------------------------------------------------------------------------------ dam
def test_dam_has_the_authors_fluid_and_fewer_boundary_particles():
    state = build_scene("dam")
    c = counts(state)
    # Walls to 2 h = 40 l0 (flat rim): per z level 2 rings of wall (124 + 132) and dummy (140 + 148);
    # floor 2 full wall layers of 44 x 24 and 2 dummy layers of 48 x 28.
    assert c == {"fluid": 4000, "wall": 2 * 44 * 24 + 40 * 256, "dummy": 2 * 48 * 28 + 42 * 288}
    assert c["wall"] < AUTHORS_DAM["wall"] and c["dummy"] < AUTHORS_DAM["dummy"]


def test_dam_fluid_is_a_lattice_one_l0_from_the_inner_walls():
    state = build_scene("dam")
    xyz = lattice(state)
    fluid = xyz[: state.n_fluid]
    expected = np.stack(np.meshgrid(np.arange(1, 11), np.arange(1, 21), np.arange(1, 21), indexing="ij"), -1)
    assert sorted(map(tuple, fluid.tolist())) == sorted(map(tuple, expected.reshape(-1, 3).tolist()))
    spacing = cKDTree(state.pos[: state.n_fluid].double().numpy()).query(
        state.pos[: state.n_fluid].double().numpy(), k=2
    )[0][:, 1]
    np.testing.assert_allclose(spacing, L0, rtol=1e-5)
    walls = xyz[state.n_fluid :][state.ptype[state.n_fluid :].numpy() == ParticleType.WALL]
    # The inner wall layers are the planes x = 0, x = 41, y = 0, y = 21, z = 0.
    assert {0, 41} <= set(walls[:, 0].tolist()) and {0, 21} <= set(walls[:, 1].tolist())
    assert walls[:, 2].min() == -1 and (walls[:, 2] == 0).sum() == 44 * 24


def test_dam_column_moves_with_its_initial_velocity_and_fluid_lower():
    small = {"fluid_size": (4, 4, 4), "tank_size": (11, 9)}
    state = build_scene("dam", velocity=(-5.0, 0.0, 1.0), fluid_lower=(3, 2, 1), **small)
    xyz = lattice(state)[: state.n_fluid]
    assert xyz.min(axis=0).tolist() == [3, 2, 1] and xyz.max(axis=0).tolist() == [6, 5, 4]
    np.testing.assert_array_equal(state.vel[: state.n_fluid].numpy(), np.tile([-5.0, 0.0, 1.0], (64, 1)))
    assert float(state.vel[state.n_fluid :].abs().max()) == 0.0  # boundaries stay at rest
    with pytest.raises(SceneError, match=r"lies in or beyond a wall"):  # a fluid layer on the wall's
        build_scene("dam", fluid_lower=(0, 1, 1), **small)
    with pytest.raises(SceneError, match=r"from fluid_lower \(8, 1, 1\) does not fit"):
        build_scene("dam", fluid_lower=(8, 1, 1), **small)


def test_dam_respects_l0_and_dtype():
    state = build_scene(
        "dam", SceneParams(l0=0.02), dtype=torch.float64, fluid_size=(3, 3, 3), tank_size=(5, 4)
    )
    assert state.pos.dtype == torch.float64 and state.params.l0 == 0.02
    assert state.n_fluid == 27
    assert torch.allclose(
        state.pos[: state.n_fluid].min(0).values, torch.full((3,), 0.02, dtype=torch.float64)
    )


def test_default_wall_height_is_the_runup_bound():
    state = small_dam()
    top = lattice(state)[state.n_fluid :, 2].max()
    assert top == 2 * 6
    assert lattice(small_dam(wall_height=20))[:, 2].max() == 20


def test_dam_boundary_is_exactly_two_wall_and_two_dummy_layers():
    state = build_scene("dam")
    xyz = lattice(state)[state.n_fluid :]
    ptype = state.ptype[state.n_fluid :].numpy()
    x, y, z = xyz.T
    depth = np.max([-x, x - 41, -y, y - 21, -z], axis=0)  # Chebyshev layer index behind the inner wall
    assert set(depth[ptype == ParticleType.WALL].tolist()) == {0, 1}
    assert set(depth[ptype == ParticleType.DUMMY].tolist()) == {2, 3}
    assert z.max() == 40  # nothing above the wall top
    # and no hole: every lattice point of the 4-layer shell up to the rim is there
    grid = np.stack(np.meshgrid(np.arange(-3, 45), np.arange(-3, 25), np.arange(-3, 41), indexing="ij"), -1)
    g = grid.reshape(-1, 3)
    shell = np.max([-g[:, 0], g[:, 0] - 41, -g[:, 1], g[:, 1] - 21, -g[:, 2]], axis=0) >= 0
    assert shell.sum() == len(xyz)


def test_layer_counts_are_options():
    state = small_dam(n_wall=1, n_dummy=0)
    xyz = lattice(state)[state.n_fluid :]
    assert state.dummy_mask.sum() == 0 and xyz.min() == 0  # the inner layer only
    thick = small_dam(n_wall=3, n_dummy=3)
    assert lattice(thick)[:, 0].min() == -5


def test_stepped_rim_reproduces_the_authors_dam_grid(authors_dam_grid):
    ours = build_scene("dam", wall_height=41, rim="stepped")
    data = np.load(authors_dam_grid)
    theirs = set(zip(*np.rint(data["pos"] / L0).astype(int).T.tolist(), data["ptype"].tolist(), strict=True))
    mine = set(zip(*lattice(ours).T.tolist(), ours.ptype.tolist(), strict=True))
    assert counts(ours) == AUTHORS_DAM
    assert mine == theirs


def test_dam_large_has_40k_fluid():
    state = build_scene("dam_large")
    assert state.n_fluid == 40_000
    assert lattice(state)[:, 2].max() == 80  # 2 x the 40 l0 column


# ------------------------------------------------------------------------------------------ every scene
@pytest.mark.parametrize(
    ("name", "options"),
    [
        ("dam", {}),
        ("random", {"seed": 0}),
        ("random", {"seed": 11, "n_obstacles": 2, **SMALL}),
        ("waterfall", {"scale": 0.25}),
    ],
)
def test_scenes_are_sorted_overlap_free_and_inside_bounds(name, options):
    state = build_scene(name, **options)
    assert bool((state.ptype[1:] >= state.ptype[:-1]).all())
    assert state.n_fluid > 0 and state.bounds is not None
    assert state.fluid_outside_bounds().numel() == 0
    pos = state.pos.double().numpy()
    nearest = cKDTree(pos).query(pos, k=2)[0][:, 1]
    assert nearest.min() >= L0 * (1 - 1e-5)
    assert torch.equal(state.vel[state.n_fluid :], torch.zeros_like(state.vel[state.n_fluid :]))


def test_scene_registry_names():
    assert set(SCENES) == {"dam", "dam_large", "waterfall", "random", "file", "trajectory", "mesh"}


# ------------------------------------------------------------------------------------------ obstacles
def _tank_scene(*obstacles, fluid=None):
    return Scene(
        name="t",
        fluid=(fluid or FluidBlock(lower=(1, 1, 1), size=(2, 2, 2)),),
        container=Container(size=(40, 40), height=30),
        obstacles=obstacles,
    )


def _interior(xyz: np.ndarray) -> np.ndarray:
    return (xyz[:, 0] > 0) & (xyz[:, 0] < 40) & (xyz[:, 1] > 0) & (xyz[:, 1] < 40) & (xyz[:, 2] > 0)


@pytest.mark.parametrize(
    ("shape", "depth"),
    [
        # independent depth formulas (distance below the surface) for interior lattice points
        (Sphere(center=(20, 20, 15), radius=7.5), lambda p: 7.5 - np.linalg.norm(p - [20, 20, 15], axis=1)),
        (
            Box(lower=(10, 12, 5), upper=(25, 22, 18)),
            lambda p: np.min(
                [p[:, 0] - 10, 25 - p[:, 0], p[:, 1] - 12, 22 - p[:, 1], p[:, 2] - 5, 18 - p[:, 2]], 0
            ),
        ),
        (
            Cylinder(start=(20, 20, 4), end=(20, 20, 20), radius=6),
            lambda p: np.minimum(
                6 - np.hypot(p[:, 0] - 20, p[:, 1] - 20), np.minimum(p[:, 2] - 4, 20 - p[:, 2])
            ),
        ),
        (
            Wedge(lower=(8, 8, 3), upper=(32, 30, 15), axis=0, descending=True),
            # top plane z = 15 - 12 (x - 8) / 24, i.e. x/2 + z = 19; distance = (19 - x/2 - z) / sqrt(1.25)
            lambda p: np.min(
                [
                    p[:, 0] - 8,
                    32 - p[:, 0],
                    p[:, 1] - 8,
                    30 - p[:, 1],
                    p[:, 2] - 3,
                    (19 - p[:, 0] / 2 - p[:, 2]) / np.sqrt(1.25),
                ],
                0,
            ),
        ),
    ],
    ids=["sphere", "box", "cylinder", "wedge"],
)
def test_obstacle_is_a_two_plus_two_layer_shell(shape, depth):
    state = _tank_scene(shape).build()
    xyz = lattice(state)
    inside_tank = _interior(xyz) & (state.ptype.numpy() != ParticleType.FLUID)
    got = {t: set(map(tuple, xyz[inside_tank & (state.ptype.numpy() == t)].tolist())) for t in (2, 3)}
    grid = np.stack(np.meshgrid(*(np.arange(1, 40),) * 2, np.arange(1, 31), indexing="ij"), -1).reshape(-1, 3)
    d = depth(grid.astype(float))
    expect_wall = set(map(tuple, grid[(d > -1e-9) & (d < 2 - 1e-9)].tolist()))
    expect_dummy = set(map(tuple, grid[(d >= 2 - 1e-9) & (d < 4 - 1e-9)].tolist()))
    assert got[2] == expect_wall and got[3] == expect_dummy
    assert len(expect_wall) > 100 and len(expect_dummy) > 0  # the shape is big enough to test anything


def test_fluid_inside_an_obstacle_is_removed():
    fluid = FluidBlock(lower=(1, 1, 1), size=(10, 10, 10))
    state = _tank_scene(Box(lower=(6, -8, -8), upper=(30, 30, 5)), fluid=fluid).build()
    assert state.n_fluid == 1000 - 5 * 10 * 5  # x 6..10, y 1..10, z 1..5 are inside the box
    fluid_xyz = lattice(state)[: state.n_fluid]
    assert not ((fluid_xyz[:, 0] >= 6) & (fluid_xyz[:, 2] <= 5)).any()


def test_sunk_obstacles_leave_no_hidden_floor():
    scene = _tank_scene(Box(lower=(10, 10, -8), upper=(20, 20, 6)))
    xyz = lattice(scene.build())
    under = (xyz[:, 0] >= 14) & (xyz[:, 0] <= 16) & (xyz[:, 1] >= 14) & (xyz[:, 1] <= 16) & (xyz[:, 2] <= 2)
    assert not under.any()  # deeper than 4 layers below every surface the fluid can reach


def _boundary_inside_tank(state, size) -> np.ndarray:
    """(N,) True for boundary particles strictly inside the tank's inner wall planes (obstacles)."""
    x, y, z = lattice(state).T
    boundary = state.ptype.numpy() != ParticleType.FLUID
    return boundary & (x > 0) & (x < size[0]) & (y > 0) & (y < size[1]) & (z > 0)


def test_obstacles_only_where_requested():
    assert not _boundary_inside_tank(build_scene("dam"), (41, 21)).any()
    assert not _boundary_inside_tank(build_scene("random", seed=4, n_obstacles=0, **SMALL), (40, 40)).any()
    layout = random_layout(seed=4, n_obstacles=2, **SMALL)
    state = layout.build()
    inner = lattice(state)[_boundary_inside_tank(state, (40, 40))]
    assert len(layout.obstacles) == 2 and len(inner) > 0
    inside_any = np.zeros(len(inner), dtype=bool)
    for shape in layout.obstacles:
        lo, hi = shape.bbox()
        in_box = ((inner >= np.floor(lo)) & (inner <= np.ceil(hi))).all(axis=1)
        assert in_box.any()  # every requested obstacle is there
        inside_any |= in_box
    assert inside_any.all()  # and nothing else is


def test_waterfall_scaled_and_full_geometry():
    small = waterfall_layout(scale=0.25)
    state = small.build()
    assert state.n_fluid == int(np.prod(small.fluid[0].size)) == 10 * 10 * 12
    assert len(small.obstacles) == 4 and _boundary_inside_tank(state, (20, 20)).sum() > 100
    full = waterfall_layout()
    assert int(np.prod(full.fluid[0].size)) == 80_000
    assert full.container.height == full.fluid[0].upper[2] == 80  # walls up to the released fluid's top
    sites = full.fluid[0].sites().astype(float)
    assert not any((shape.depth(sites) > -1e-6).any() for shape in full.obstacles)  # released above them


# ------------------------------------------------------------------------------------------ random
def test_random_is_deterministic_per_seed():
    a, b = build_scene("random", seed=7, **SMALL), build_scene("random", seed=7, **SMALL)
    assert torch.equal(a.pos, b.pos) and torch.equal(a.vel, b.vel) and torch.equal(a.ptype, b.ptype)


def test_random_seeds_give_different_scenes():
    layouts = [random_layout(seed=s) for s in range(12)]
    signatures = {(lay.fluid[0].lower, lay.fluid[0].velocity, lay.obstacles) for lay in layouts}
    assert len(signatures) == 12
    kinds = {type(o).__name__ for lay in layouts for o in lay.obstacles}
    assert kinds == {"Box", "Cylinder", "Sphere", "Wedge"}
    assert {len(lay.obstacles) for lay in layouts} == {1, 2}
    axes = {int(np.flatnonzero(lay.fluid[0].velocity)[0]) for lay in layouts if any(lay.fluid[0].velocity)}
    assert len(axes) >= 2


@pytest.mark.parametrize("seed", range(6))
def test_random_velocity_is_along_one_axis_and_at_most_0_1(seed):
    layout = random_layout(seed=seed)
    vel = np.asarray(layout.fluid[0].velocity)
    assert np.count_nonzero(vel) <= 1 and 0.0 <= np.linalg.norm(vel) <= 0.1
    fluid_xyz, _ = layout.fluid_sites()
    assert len(fluid_xyz) == 25 * 25 * 10  # obstacles never cut into the block
    f_lo, f_hi = np.array(layout.fluid[0].lower), np.array(layout.fluid[0].upper)
    for shape in layout.obstacles:
        lo, hi = shape.bbox()
        assert (hi < f_lo).any() or (np.maximum(lo, 0) > f_hi).any()  # not touching the block
    assert f_hi[2] <= 20  # top at most half the 40 l0 wall


def test_random_column_collapses_stand_at_rest_against_a_side_wall():
    layouts = [random_layout(seed=s, column_probability=1.0) for s in range(24)]
    walls, places = set(), set()
    for layout in layouts:
        block = layout.fluid[0]
        lo, hi = np.array(block.lower), np.array(block.upper)
        assert sorted(block.size) == [10, 20, 25] and block.size[2] == 20 and lo[2] == 1
        assert block.velocity == (0.0, 0.0, 0.0)
        touching = [(a, side) for a in (0, 1) for side, at in ((0, lo[a] == 1), (1, hi[a] == 79)) if at]
        normal = 0 if block.size[0] == 10 else 1
        assert (normal, 0) in touching or (normal, 1) in touching  # its thin side against a wall
        walls |= {t for t in touching if t[0] == normal}
        places.add(len(touching))  # 2: in a corner
        for shape in layout.obstacles:
            o_lo, o_hi = shape.bbox()
            assert (o_hi < lo).any() or (np.maximum(o_lo, 0) > hi).any()
    assert walls == {(0, 0), (0, 1), (1, 0), (1, 1)} and places == {1, 2}
    # Off by default, and a seed's other draws stay the paper scene's when it is 0
    assert random_layout(seed=3).description == random_layout(seed=3, column_probability=0.0).description
    mixed = [random_layout(seed=s, column_probability=0.5).fluid[0].size for s in range(12)]
    assert 0 < sum(size[2] == 20 for size in mixed) < 12


def test_random_edge_blocks_are_released_against_a_wall_with_their_top_at_its_top_edge():
    layouts = [random_layout(seed=s, edge_probability=1.0) for s in range(24)]
    walls = set()
    for layout in layouts:
        block = layout.fluid[0]
        lo, hi = np.array(block.lower), np.array(block.upper)
        assert block.size == (25, 25, 10) and block.velocity == (0.0, 0.0, 0.0)
        assert hi[2] == 40 == layout.container.height and lo[2] == 31  # top level with the walls' top edge
        touching = [(a, side) for a in (0, 1) for side, at in ((0, lo[a] == 1), (1, hi[a] == 79)) if at]
        assert touching  # against at least one side wall
        walls |= set(touching)
        for shape in layout.obstacles:
            o_lo, o_hi = shape.bbox()
            assert (o_hi < lo).any() or (np.maximum(o_lo, 0) > hi).any()
    assert walls == {(0, 0), (0, 1), (1, 0), (1, 1)}
    # Off by default, and a column scene wins the first draw: the other scenes' draws are unchanged
    assert random_layout(seed=3).description == random_layout(seed=3, edge_probability=0.0).description
    both = [random_layout(seed=s, column_probability=1.0, edge_probability=1.0) for s in range(4)]
    assert [b.description for b in both] == [
        random_layout(seed=s, column_probability=1.0).description for s in range(4)
    ]
    with pytest.raises(SceneError, match=r"edge_probability must be in \[0, 1\], got -0.5"):
        random_layout(seed=0, edge_probability=-0.5)


def test_random_state_carries_the_drawn_velocity():
    layout = random_layout(seed=3, **SMALL)
    state = layout.build()
    vel = state.vel[: state.n_fluid]
    assert torch.equal(vel, torch.tensor(layout.fluid[0].velocity, dtype=vel.dtype).expand_as(vel))
    assert float(vel[0].norm()) > 0


# ------------------------------------------------------------------------------------------ grid files
@pytest.mark.parametrize("suffix", [".npz", ".txt"])
def test_grid_file_round_trip(tmp_path, suffix):
    state = build_scene("random", seed=2, tank_size=(20, 16), wall_height=16, fluid_size=(5, 4, 3))
    path = save_grid(state, tmp_path / f"scene{suffix}")
    loaded = build_scene("file", path=str(path))
    assert torch.equal(loaded.ptype, state.ptype)
    atol = 0 if suffix == ".npz" else 1e-6
    torch.testing.assert_close(loaded.pos, state.pos, atol=atol, rtol=0)
    torch.testing.assert_close(loaded.vel, state.vel, atol=atol, rtol=0)
    boundary = state.pos[state.n_fluid :]
    torch.testing.assert_close(loaded.bounds[0], boundary.min(0).values)


def test_txt_in_the_authors_layout(tmp_path):
    # their format: no header, x,y,z,vx,vy,vz,ptype with 4 decimals; here a fluid particle in a
    # 3 x 3 x 3 cube of walls (one dummy outside)
    walls = [(x, y, z) for x in (0, 2) for y in (0, 2) for z in (0, 2)]
    lines = [f"{x * 0.05:.4f},{y * 0.05:.4f},{z * 0.05:.4f},0.0000,0.0000,0.0000,2" for x, y, z in walls]
    lines.insert(3, "0.0500,0.0500,0.0500,0.1000,0.0000,-0.2000,1")
    lines.append("-0.0500,0.0000,0.0000,0.0000,0.0000,0.0000,3")
    path = tmp_path / "tiny.txt"
    path.write_text("\n".join(lines) + "\n")
    state = load_grid(path)
    assert state.ptype.tolist() == [1] + [2] * 8 + [3]
    assert state.pos[0].tolist() == pytest.approx([0.05] * 3)
    assert state.vel[0].tolist() == pytest.approx([0.1, 0.0, -0.2])
    # bounds: the boundary extent, z raised by its height for an open top
    torch.testing.assert_close(state.bounds, torch.tensor([[-0.05, 0.0, 0.0], [0.1, 0.1, 0.2]]))


def test_load_the_authors_dam_grid(authors_dam_grid):
    state = build_scene("file", path=str(authors_dam_grid))
    assert counts(state) == AUTHORS_DAM
    assert torch.allclose(state.bounds[0], torch.full((3,), -0.15))


# ------------------------------------------------------------------------------------------ errors
def _npz(tmp_path, **arrays):
    path = tmp_path / "g.npz"
    np.savez(path, **arrays)
    return path


def _good_arrays():
    # a fluid particle between a wall and a dummy particle at opposite corners of a 2 l0 cube
    pos = np.array([[0.05, 0.05, 0.05], [0.0, 0, 0], [0.1, 0.1, 0.1]])
    return {"pos": pos, "vel": np.zeros_like(pos), "ptype": np.array([1, 2, 3])}


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"pos": None}, "missing array 'pos'"),
        ({"vel": None}, "missing array 'vel'"),
        ({"pos": np.zeros((3, 2))}, r"pos must have shape \(N, 3\)"),
        ({"vel": np.zeros((2, 3))}, r"vel must have shape \(3, 3\)"),
        ({"ptype": np.array([1, 2])}, r"ptype must have shape \(3,\)"),
        ({"ptype": np.array([1, 4, 3])}, "unknown particle type 4 at particle 1"),
        ({"ptype": np.array([1.0, 2.5, 3.0])}, "unknown particle type 2.5 at particle 1"),
        ({"ptype": np.array([2, 2, 3])}, "no fluid particles"),
        (
            {"pos": np.array([[0.05, 0.05, 0.05], [0.0, np.nan, 0], [0.1, 0.1, 0.1]])},
            "pos of particle 1 is not finite",
        ),
        ({"vel": np.array([[np.inf, 0, 0], [0, 0, 0], [0, 0, 0]])}, "vel of particle 0 is not finite"),
        (
            {"pos": np.array([[0.05, 0.05, 0.05], [0.0, 0, 0], [0.055, 0.05, 0.05]])},
            r"particles 0 \(fluid\) and 2 \(dummy\) overlap: 0.1 l0 apart",
        ),
        (
            {"pos": np.array([[0.3, 0.05, 0.05], [0.0, 0, 0], [0.1, 0.1, 0.1]])},
            "fluid particle 0 .* is outside the tank",
        ),
    ],
)
def test_bad_grid_file_is_a_clear_error(tmp_path, change, message):
    arrays = _good_arrays()
    for key, value in change.items():
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value
    with pytest.raises(SceneError, match=message):
        build_scene("file", path=str(_npz(tmp_path, **arrays)))


@pytest.mark.parametrize("damage", ["empty", "truncated", "random bytes", "a single .npy array"])
def test_a_damaged_npz_grid_file_is_named_without_numpys_allow_pickle_hint(tmp_path, damage):
    good = _npz(tmp_path, **_good_arrays()).read_bytes()
    path = tmp_path / "damaged.npz"
    if damage == "a single .npy array":
        with path.open("wb") as f:
            np.save(f, np.zeros((4, 3)))
    else:
        path.write_bytes(
            {"empty": b"", "truncated": good[: len(good) // 2], "random bytes": bytes(range(256))}[damage]
        )
    with pytest.raises(SceneError) as err:
        build_scene("file", path=str(path))
    assert str(err.value).startswith(f"{path}: ") and "pos, vel, ptype" in str(err.value)
    assert "allow_pickle" not in str(err.value)


def _tank_with_fluid_at(extra):
    """A 10 x 10 l0 tank (2 wall + 2 dummy layers, walls from x = 0) with a 4^3 fluid block and ``extra``."""
    l0 = 0.05
    k = np.arange(-4, 14)
    lattice = np.stack(np.meshgrid(k, k, np.arange(-4, 8), indexing="ij"), axis=-1).reshape(-1, 3)
    depth = np.maximum(
        np.maximum(-lattice[:, 0], lattice[:, 0] - 9), np.maximum(-lattice[:, 1], lattice[:, 1] - 9)
    )
    depth = np.maximum(depth, -lattice[:, 2])
    boundary = lattice[depth > 0]
    ptype = np.where(depth[depth > 0] <= 2, 2, 3)
    fluid = np.stack(np.meshgrid(*[np.arange(3, 7)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    pos = np.concatenate([fluid, boundary, np.asarray(extra, dtype=float).reshape(-1, 3)]) * l0
    types = np.concatenate(
        [np.ones(len(fluid), int), ptype, np.ones(len(pos) - len(fluid) - len(boundary), int)]
    )
    return {"pos": pos, "vel": np.zeros_like(pos), "ptype": types}


@pytest.mark.parametrize("offset", [(0.5, 0.0, 0.0), (0.5, 0.5, 0.0), (0.5, 0.5, 0.5)])
def test_a_fluid_particle_inside_the_wall_layers_is_refused(tmp_path, offset):
    build_scene("file", path=str(_npz(tmp_path, **_tank_with_fluid_at([]))))  # the tank itself is fine
    inside = np.array([-2.0, 4.0, 3.0]) + np.array(offset)  # between the wall layers at x = -2 and -1
    with pytest.raises(
        SceneError,
        match=r"fluid particle \d+ at \[-0.075\d*, .* number density 1\.[1-4]\d* n0 .*inside the wall",
    ):
        build_scene("file", path=str(_npz(tmp_path, **_tank_with_fluid_at([inside]))))


@pytest.mark.parametrize("offset", [1e3, 1e6])
def test_a_grid_far_from_the_origin_is_refused_in_float32_and_runs_in_float64(tmp_path, offset):
    arrays = _tank_with_fluid_at([])
    arrays["pos"] = arrays["pos"] + offset
    path = str(_npz(tmp_path, **arrays))
    with pytest.raises(
        SceneError, match=r"coordinates reach .* float32 resolves positions only to .*dtype=float64"
    ):
        build_scene("file", path=path)
    state = build_scene("file", path=path, dtype=torch.float64)
    assert state.pos.dtype == torch.float64 and torch.unique(state.pos, dim=0).shape[0] == state.pos.shape[0]
    build_scene(
        "file", path=str(_npz(tmp_path, **_tank_with_fluid_at([])))
    )  # near the origin: float32 is fine


def test_a_scene_too_large_for_memory_is_refused_with_the_estimate_before_it_is_built(monkeypatch):
    from lagfluid.scenes import validation

    with pytest.raises(
        SceneError, match=r"scene 'dam': building it needs ~\d+ GiB, but .* GiB of memory are available"
    ):
        build_scene("dam", tank_size=[3000, 3000], wall_height=1000)  # 9e9 lattice points: never allocated
    monkeypatch.setattr(validation, "available_memory", lambda: 2**30)  # 1 GiB left
    build_scene("dam")  # 31k particles: ~0.25 GiB
    big = {"fluid_size": [100, 100, 100], "tank_size": [120, 120], "wall_height": 110}
    # built, then refused before its checks' neighbour queries (the rollout's estimate: tests/test_memory.py)
    with pytest.raises(
        SceneError,
        match=r"scene 'dam': checking its 1,\d{3},\d{3} particles needs ~\d+\.?\d* GiB, but 1 GiB of "
        r"memory are available; make scene\.fluid_size, scene\.tank_size, scene\.wall_height smaller or "
        r"scene\.params\.l0 larger$",
    ):
        build_scene("dam", **big)
    monkeypatch.setattr(validation, "available_memory", lambda: None)  # unknown: never refused for it
    assert validation.check_memory(1e18, "x", "scene") is None


def test_missing_and_malformed_files_name_the_path(tmp_path):
    missing = tmp_path / "nope.npz"
    with pytest.raises(SceneError, match=f"grid file not found: {missing}"):
        build_scene("file", path=str(missing))
    bad = tmp_path / "bad.txt"
    bad.write_text("0,0,0,0,0,0\n")
    with pytest.raises(SceneError, match="expected 7 columns x,y,z,vx,vy,vz,ptype, got 6"):
        load_grid(bad)
    other = tmp_path / "g.csv"
    other.write_text("1")
    with pytest.raises(SceneError, match=r"unsupported grid file type '\.csv'"):
        load_grid(other)
    with pytest.raises(SceneError, match="needs the option path"):
        build_scene("file")


@pytest.mark.parametrize(
    ("name", "options", "message"),
    [
        (
            "nope",
            {},
            "unknown scene 'nope'; available: dam, dam_large, file, mesh, random, trajectory, waterfall",
        ),
        (
            "dam",
            {"fluid_szie": (1, 1, 1)},
            "unknown option.* fluid_szie for scene 'dam'; available: fluid_size",
        ),
        ("file", {"path": "x.npz", "bogus": 1}, "unknown option.* bogus for scene 'file'; available: path"),
        ("dam", {"fluid_size": (0, 20, 20)}, r"fluid_size must be positive, got \(0, 20, 20\)"),
        ("dam", {"fluid_size": (10.5, 20, 20)}, "fluid_size must be whole numbers"),
        ("dam", {"fluid_size": (10, 20)}, "fluid_size must be 3 numbers"),
        ("dam", {"tank_size": (-41, 21)}, "tank_size must be positive"),
        ("dam", {"wall_height": 0}, "wall_height must be an integer >= 1, got 0"),
        ("dam", {"wall_height": 10}, "wall_height 10 is below the fluid column's top"),
        (
            "dam",
            {"fluid_size": (41, 20, 20)},
            r"fluid_size \(41, 20, 20\) from fluid_lower \(1, 1, 1\) does not fit in tank_size \(41, 21\)",
        ),
        ("dam", {"rim": "round"}, "rim must be one of 'flat', 'stepped'"),
        ("dam", {"n_wall": 0}, "n_wall must be an integer >= 1, got 0"),
        ("dam", {"n_dummy": -1}, "n_dummy must be an integer >= 0"),
        ("waterfall", {"scale": 0}, "scale must be positive"),
        ("random", {"seed": -1}, "seed must be an integer >= 0"),
        ("random", {"obstacle_kinds": ["cone"]}, "obstacle_kinds must be a non-empty subset"),
        ("random", {"max_speed": float("nan")}, "max_speed must be finite"),
        ("random", {"fluid_size": (25, 25, 30)}, "does not fit in tank_size"),
        ("random", {"column_probability": 1.5}, r"column_probability must be in \[0, 1\], got 1.5"),
        ("random", {"column_probability": 1, "column_size": (10, 25, 30)}, "needs walls of 2 x 30 l0"),
        (
            "random",
            {"tank_size": (30, 30), "wall_height": 30, "fluid_size": (29, 29, 15), "n_obstacles": 1},
            "could not place obstacle 1 of 1",
        ),
    ],
)
def test_bad_scene_options_are_clear_errors(name, options, message):
    with pytest.raises(SceneError, match=message):
        build_scene(name, **options)


def test_bad_shapes_and_fluid_outside_the_tank():
    with pytest.raises(SceneError, match=r"Sphere\.radius must be positive"):
        Sphere(center=(0, 0, 0), radius=-1)
    with pytest.raises(SceneError, match=r"Box\.upper must exceed Box\.lower"):
        Box(lower=(0, 0, 0), upper=(5, 0, 5))
    with pytest.raises(SceneError, match=r"Cylinder\.start and Cylinder\.end must differ"):
        Cylinder(start=(1, 1, 1), end=(1, 1, 1), radius=1)
    with pytest.raises(SceneError, match=r"Wedge\.upper must exceed Wedge\.lower"):
        Wedge(lower=(0, 0, 0), upper=(4, 4, -1))
    with pytest.raises(SceneError, match=r"Wedge\.low must lie in"):
        Wedge(lower=(0, 0, 0), upper=(4, 4, 4), low=4)
    with pytest.raises(SceneError, match=r"Wedge\.axis must be 0"):
        Wedge(lower=(0, 0, 0), upper=(4, 4, 4), axis=2)
    scene = _tank_scene(fluid=FluidBlock(lower=(0, 5, 5), size=(3, 3, 3)))
    with pytest.raises(SceneError, match=r"particle at \[0, 5, 5\] l0 lies in or beyond a wall"):
        scene.build()
    overlapping = Scene(
        name="two",
        fluid=(FluidBlock((1, 1, 1), (3, 3, 3)), FluidBlock((3, 3, 3), (3, 3, 3))),
        container=Container(size=(10, 10), height=10),
    )
    with pytest.raises(
        SceneError, match=r"scene 'two': particles \d+ \(fluid\) and \d+ \(fluid\) overlap: 0 l0"
    ):
        overlapping.build()
    swallowed = _tank_scene(Box(lower=(-8, -8, -8), upper=(10, 10, 10)))
    with pytest.raises(SceneError, match="no fluid particle is left outside the obstacles"):
        swallowed.build()


def test_full_waterfall_builds_80k_fluid():
    state = build_scene("waterfall")
    assert state.n_fluid == 80_000
    assert state.num_particles - state.n_fluid < 2 * 80_000  # walls only to the fluid's top, no hidden floor
    x, y, z = lattice(state).T
    under_box = (abs(x - 62) <= 2) & (abs(y - 56) <= 2) & (z <= 0)  # the 12 x 12 box stands there
    assert not under_box.any()  # the box is sunk deep enough that no floor layer remains below it
