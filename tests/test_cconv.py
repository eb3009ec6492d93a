"""CConv (baselines/cconv): the continuous convolution against analytic cases and Open3D's op (an optional
oracle: ``pip install open3d-cpu==0.20.0``), DeepLagrangianFluids' network and weights, the boundary
surface, invariances, batching and the ``model=cconv_original`` rollout (seconds)."""

import hashlib
import math
from importlib import metadata
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
from hydra import compose, initialize_config_dir

from baselines.cconv import load_dlf_network
from baselines.cconv.boundary import surface_points
from baselines.cconv.conv import (
    MAPPINGS,
    ContinuousConv,
    ball_to_cube_volume_preserving,
    conv_geometry,
    conv_pairs,
    filter_coordinates,
)
from baselines.cconv.network import CConvNet
from baselines.cconv.oracle import open3d_layer
from baselines.cconv.simulator import DLF_WEIGHTS, SHIPPED, Y_UP, build_original, build_simulator
from lagfluid.errors import ConfigError, LagfluidError, RolloutError
from lagfluid.models.checkpoint import CheckpointError, MissingWeightsError
from lagfluid.models.simulator import check_simulator
from lagfluid.registry import available_simulators
from lagfluid.rollout import rollout
from lagfluid.run import CONF_DIR
from lagfluid.tasks.config import at_simulator_time_step, build_initial_state, run_guard

SHARED = Path(__file__).resolve().parents[2] / "shared"
# their published network as the package ships it; the copy beside the checkout, where present, is the source
DLF_REFERENCE = SHARED / "reference" / "cconv_original" / "pretrained_model_weights.pt"


def _open3d():
    """Skip without Open3D (the oracle is an optional extra)."""
    if open3d_layer(torch.zeros(2, 2, 2, 1, 1)) is None:
        pytest.skip("open3d-cpu (the optional CConv oracle) is not installed")


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def _cloud(n=300, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, generator=g, dtype=dtype), torch.Generator().manual_seed(seed + 1)


def _block_and_floor(dtype=torch.float32, seed=0, shift=(0.0, 0.0, 0.0)):
    """DeepLagrangianFluids' units (y up): a jittered 6^3 fluid block over a 12 x 12 surface floor."""
    g = torch.Generator().manual_seed(seed)
    a = torch.arange(6, dtype=dtype) * 0.05
    pos = torch.stack(torch.meshgrid(a, a + 0.05, a, indexing="ij"), -1).reshape(-1, 3)
    pos = pos + 0.004 * torch.randn(pos.shape, generator=g, dtype=dtype)
    vel = 0.5 * torch.randn(pos.shape, generator=g, dtype=dtype)
    b = torch.arange(-3, 9, dtype=dtype) * 0.05
    bx, bz = torch.meshgrid(b, b, indexing="ij")
    box = torch.stack([bx, torch.zeros_like(bx), bz], -1).reshape(-1, 3)
    normals = torch.tensor([0.0, 1.0, 0.0], dtype=dtype).expand_as(box).contiguous()
    s = torch.tensor(shift, dtype=dtype)
    return pos + s, vel, box + s, normals


# ------------------------------------------------------------------------------------------ the operator
def test_volume_preserving_mapping_keeps_axes_and_fills_the_cube():
    pts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [0.3, 0.3, 0.0]])
    cube = ball_to_cube_volume_preserving(pts)
    # the centre and the axes stay (the axis ends are the face centres); a point on the xy diagonal goes out
    # to the cube's diagonal at its own distance from the z axis
    assert torch.allclose(cube[:4], pts[:4], atol=1e-6)
    assert torch.allclose(cube[4], torch.tensor([0.3 * math.sqrt(2), 0.3 * math.sqrt(2), 0.0]), atol=1e-6)
    # volume preserving: uniform points in the ball are uniform in the cube (mean |coordinate| 1/2)
    g = torch.Generator().manual_seed(0)
    u = torch.randn(200_000, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=1, keepdim=True) * torch.rand(200_000, 1, generator=g, dtype=torch.float64) ** (1 / 3)
    c = ball_to_cube_volume_preserving(u)
    assert c.abs().max() <= 1 + 1e-9
    assert torch.allclose(c.abs().mean(0), torch.full((3,), 0.5, dtype=torch.float64), atol=5e-3)


def test_a_constant_kernel_sums_the_window_over_the_neighbours():
    pos, _ = _cloud(200)
    r = 0.25
    pairs = conv_pairs(pos, None, r)
    geo = conv_geometry(pos, pos, pairs, r)
    conv = ContinuousConv(1, 1)
    with torch.no_grad():
        conv.kernel.fill_(1.0)
    out = conv(torch.ones(200, 1), geo)[:, 0]
    d2 = ((pos[:, None] - pos[None]) ** 2).sum(-1)
    # DeepLagrangianFluids' window written out, not the package's function
    expected = torch.where((d2 < r * r) & (d2 > 0), (1 - d2 / r**2) ** 3, 0.0).sum(1)
    assert torch.allclose(out, expected, atol=1e-5)
    assert torch.equal(geo.num_neighbors, ((d2 < r * r) & (d2 > 0)).sum(1).float())


def test_a_kernel_linear_in_the_grid_coordinate_reads_back_the_mapped_offset():
    # K(cell) = x index: trilinear interpolation is exact for a linear function, so each pair contributes
    # its filter x coordinate (identity mapping: (rel_x / R + 1) / 2 * 3)
    pos = torch.tensor([[0.0, 0.0, 0.0], [0.07, 0.02, -0.01]])
    r = 0.1
    geo = conv_geometry(pos, pos, conv_pairs(pos, None, r), r, mapping="identity", window=None)
    conv = ContinuousConv(1, 1, mapping="identity", window=None)
    with torch.no_grad():
        conv.kernel.copy_(torch.arange(4.0).view(1, 1, 4, 1, 1).expand(4, 4, 4, 1, 1))
    out = conv(torch.ones(2, 1), geo)[:, 0]
    expected = (torch.tensor([0.07, -0.07]) / r + 1) / 2 * 3
    assert torch.allclose(out, expected, atol=1e-6)
    coord = filter_coordinates(pos[1:] - pos[:1], r, (4, 4, 4), "identity")
    assert torch.allclose(coord[0], (torch.tensor([0.07, 0.02, -0.01]) / r + 1) / 2 * 3, atol=1e-6)


def test_coincident_points_are_ignored_in_either_set_as_open3d_does():
    pos = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.05, 0.0, 0.0]])
    geo = conv_geometry(pos, pos, conv_pairs(pos, None, 0.1), 0.1)
    assert geo.num_neighbors.tolist() == [1.0, 1.0, 2.0]  # the duplicates do not see each other
    box = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.05, 0.0]])
    geo = conv_geometry(box, pos[:1], conv_pairs(box, pos[:1], 0.1), 0.1)
    assert geo.num_neighbors.tolist() == [1.0]


def test_chunks_of_kernel_cells_give_the_same_result_and_gradients():
    pos, g = _cloud(150)
    feats = torch.randn(150, 5, generator=g, requires_grad=True)
    pairs = conv_pairs(pos, None, 0.3)
    conv = ContinuousConv(5, 7)
    outs, grads = [], []
    for chunk in (None, 5, 16):
        geo = conv_geometry(pos, pos, pairs, 0.3, chunk_cells=chunk)
        assert len(geo.chunks) == (1 if chunk is None else math.ceil(64 / chunk))
        out = conv(feats, geo)
        (k_grad, f_grad) = torch.autograd.grad((out * out).sum(), [conv.kernel, feats])
        outs.append(out.detach())
        grads.append((k_grad, f_grad))
    for o, (k, f) in zip(outs[1:], grads[1:], strict=False):
        assert torch.allclose(o, outs[0], atol=1e-5)
        assert torch.allclose(k, grads[0][0], atol=1e-4) and torch.allclose(f, grads[0][1], atol=1e-4)


def test_bad_options_are_named():
    with pytest.raises(ConfigError, match="mapping 'ball'"):
        ContinuousConv(1, 1, mapping="ball")
    pos, _ = _cloud(10)
    geo = conv_geometry(pos, pos, conv_pairs(pos, None, 0.3), 0.3)
    with pytest.raises(ValueError, match=r"features of shape \(10, 2\)"):
        ContinuousConv(3, 1)(torch.ones(10, 2), geo)


@pytest.mark.parametrize("mapping", sorted(MAPPINGS))
@pytest.mark.parametrize("channels", [(4, 32), (96, 64)])
def test_the_operator_matches_open3d(mapping, channels):
    _open3d()
    cin, cout = channels
    pos, g = _cloud(400)
    out_pos = torch.rand(250, 3, generator=g)
    r = 0.2
    for same in (True, False):
        queries = pos if same else out_pos
        feats = torch.randn(400, cin, generator=g, requires_grad=True)
        ours = ContinuousConv(cin, cout, (3, 4, 5), mapping)
        with torch.no_grad():
            ours.kernel.copy_(torch.randn(ours.kernel.shape, generator=g))
            ours.bias.copy_(torch.randn(cout, generator=g))
        ref = open3d_layer(ours.kernel.detach(), ours.bias.detach(), mapping)
        expected = ref(feats, pos, queries, 2 * r)
        geo = conv_geometry(
            pos, queries, conv_pairs(pos, None if same else queries, r), r, (3, 4, 5), mapping
        )
        got = ours(feats, geo)
        scale = float(expected.detach().abs().max())
        assert float((got - expected).abs().max()) < 2e-6 * max(scale, 1.0)
        weight = torch.randn(expected.shape, generator=g)
        ref_k, ref_f = torch.autograd.grad((expected * weight).sum(), [ref.kernel, feats])
        our_k, our_f = torch.autograd.grad((got * weight).sum(), [ours.kernel, feats])
        assert torch.allclose(our_k, ref_k, rtol=1e-4, atol=1e-4 * float(ref_k.abs().max()))
        assert torch.allclose(our_f, ref_f, rtol=1e-4, atol=1e-4 * float(ref_f.abs().max()))


# ------------------------------------------------------------------------------------------- the network
def test_network_has_the_papers_parameter_count_and_dlf_state_dict_keys():
    net = CConvNet()
    assert net.trained_parameter_count() == 692_902
    keys = set(net.state_dict())
    assert {
        "gravity",
        "conv0_fluid.kernel",
        "conv0_obstacle.offset",
        "dense0_fluid.weight",
        "conv3.bias",
    } <= keys
    assert tuple(net.conv1.kernel.shape) == (4, 4, 4, 96, 64)


def test_dlf_weights_against_open3d_layers():
    """Their network rebuilt from Open3D's layers with the same weights (their forward, written out)."""
    _open3d()

    net = load_dlf_network(DLF_WEIGHTS)
    assert net.trained_parameter_count() == 692_902
    state = torch.load(DLF_WEIGHTS, weights_only=True)

    def o3d_conv(name, cin, cout):
        return open3d_layer(state[f"{name}.kernel"], state[f"{name}.bias"])

    pos, vel, box, normals = _block_and_floor()
    with torch.no_grad():
        new_pos, new_vel = net((pos, vel, None, box, normals))
        dt, extent = 0.02, 1.5 * 6 * 0.025
        vel2 = vel + dt * state["gravity"]
        pos2 = pos + dt * (vel2 + vel) / 2
        feats = torch.cat([torch.ones_like(pos2[:, :1]), vel2], -1)
        h = torch.cat(
            [
                o3d_conv("conv0_obstacle", 3, 32)(normals, box, pos2, extent),
                o3d_conv("conv0_fluid", 4, 32)(feats, pos2, pos2, extent),
                F.linear(feats, state["dense0_fluid.weight"], state["dense0_fluid.bias"]),
            ],
            -1,
        )
        for k, (cin, cout) in enumerate([(96, 64), (64, 64), (64, 3)], start=1):
            x = F.relu(h)
            out = o3d_conv(f"conv{k}", cin, cout)(x, pos2, pos2, extent)
            out = out + F.linear(x, state[f"dense{k}.weight"], state[f"dense{k}.bias"])
            h = out + h if out.shape == h.shape else out
        expected = pos2 + h / 128
    assert float((new_pos - expected).abs().max()) < 1e-6
    assert torch.allclose(new_vel, (expected - pos) / dt, atol=1e-4)


def test_load_dlf_network_names_a_missing_or_foreign_file(tmp_path):
    with pytest.raises(CheckpointError, match="no DeepLagrangianFluids checkpoint"):
        load_dlf_network(tmp_path / "nope.pt")
    torch.save({"weight": torch.zeros(2)}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="not a MyParticleNetwork state dict"):
        load_dlf_network(tmp_path / "other.pt")


def _net(seed=0, dtype=torch.float64):
    torch.manual_seed(seed)
    net = CConvNet().to(dtype)
    with torch.no_grad():  # larger weights than the init, so that every branch shows in the output
        for p in net.parameters():
            p.mul_(3.0)
    return net.eval()


def test_permutation_invariance():
    net = _net()
    pos, vel, box, normals = _block_and_floor(torch.float64)
    perm = torch.randperm(len(pos), generator=torch.Generator().manual_seed(3))
    bperm = torch.randperm(len(box), generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        p1, v1 = net((pos, vel, None, box, normals))
        p2, v2 = net((pos[perm], vel[perm], None, box[bperm], normals[bperm]))
    assert torch.allclose(p2, p1[perm], atol=1e-12) and torch.allclose(v2, v1[perm], atol=1e-9)


def test_translation_invariance():
    net = _net()
    with torch.no_grad():
        p1, v1 = net((*_block_and_floor(torch.float64)[:2], None, *_block_and_floor(torch.float64)[2:]))
        shifted = _block_and_floor(torch.float64, shift=(3.7, -1.25, 20.5))
        p2, v2 = net((*shifted[:2], None, *shifted[2:]))
    assert torch.allclose(p2 - torch.tensor([3.7, -1.25, 20.5], dtype=torch.float64), p1, atol=1e-9)
    assert torch.allclose(v2, v1, atol=1e-7)


def test_two_scenes_batched_equal_each_alone():
    net = _net()
    a = _block_and_floor(torch.float64, seed=0)
    b = _block_and_floor(torch.float64, seed=1)  # overlaps a in space: only the batch ids keep them apart
    with torch.no_grad():
        alone = [net.compute_correction(*net.integrate_pos_vel(s[0], s[1]), None, s[2], s[3]) for s in (a, b)]
        pos, vel = net.integrate_pos_vel(torch.cat([a[0], b[0]]), torch.cat([a[1], b[1]]))
        batch = torch.repeat_interleave(torch.arange(2), torch.tensor([len(a[0]), len(b[0])]))
        box_batch = torch.repeat_interleave(torch.arange(2), torch.tensor([len(a[2]), len(b[2])]))
        both, counts = net.compute_correction(
            pos, vel, None, torch.cat([a[2], b[2]]), torch.cat([a[3], b[3]]), batch, box_batch
        )
    assert torch.allclose(both, torch.cat([alone[0][0], alone[1][0]]), atol=1e-12)
    assert torch.equal(counts, torch.cat([alone[0][1], alone[1][1]]))


# -------------------------------------------------------------------------------- boundary and simulator
def test_surface_points_are_the_inner_faces_with_normals_into_the_fluid():
    l0 = 0.05
    # a 4-layer floor z = 0, -l0, -2 l0, -3 l0 of 10 x 10 particles: the top layer is the surface (the bottom
    # layer is one too, facing down, and the edges; the middle layers are not)
    a = torch.arange(10, dtype=torch.float64) * l0
    layers = [torch.stack(torch.meshgrid(a, a, indexing="ij"), -1).reshape(-1, 2) for _ in range(4)]
    floor = torch.cat([torch.cat([xy, torch.full((len(xy), 1), -k * l0)], 1) for k, xy in enumerate(layers)])
    points, normals, rows = surface_points(floor, l0)
    top = floor[rows][:, 2] == 0
    inner = (floor[rows][:, :2] > 0.5 * l0).all(1) & (floor[rows][:, :2] < 8.5 * l0).all(1)
    assert int((top & inner).sum()) == 64  # every interior particle of the top face
    assert torch.allclose(normals[top & inner], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    assert torch.allclose(points[top & inner][:, 2], torch.full((64,), 0.5 * l0, dtype=torch.float64))
    middle = (floor[rows][:, 2] < -0.5 * l0) & (floor[rows][:, 2] > -2.5 * l0)
    assert int((middle & inner).sum()) == 0


def test_the_plugin_is_found_and_composes():
    assert "cconv_original" in {ep.name for ep in metadata.entry_points(group="lagfluid.simulators")}
    assert "cconv" in {ep.name for ep in metadata.entry_points(group="lagfluid.configs")}
    assert "cconv_original" in available_simulators()
    assert build_original(_compose("model=cconv_original")).weights == str(DLF_WEIGHTS)  # shipped default
    cfg = _compose("model=cconv_original", "model.weights=/nonexistent/pretrained_model_weights.pt")
    with pytest.raises(MissingWeightsError, match=r"no DeepLagrangianFluids checkpoint at /nonexistent/"):
        build_original(cfg)


def test_the_shipped_dlf_weights_are_their_published_file_with_licence_and_card():
    folder = DLF_WEIGHTS.parent
    assert "Community Data License Agreement – Permissive – Version 1.0" in (
        folder / "LICENSE-CDLA-Permissive-1.0"
    ).read_text(encoding="utf-8")
    card = (folder / "MODEL_CARD.md").read_text()
    assert hashlib.sha256(DLF_WEIGHTS.read_bytes()).hexdigest() in card
    assert "Ummenhofer" in card and "isl-org/DeepLagrangianFluids" in card  # the credit the licence keeps
    if not DLF_REFERENCE.is_file():
        pytest.skip("../shared/reference is not present (the shipped file's source)")
    assert DLF_WEIGHTS.read_bytes() == DLF_REFERENCE.read_bytes()


def test_cconv_original_rolls_out_the_small_dam_finite_and_inside_the_tank():
    cfg = _compose("model=cconv_original", "scene=dam_small")
    sim = check_simulator(build_original(cfg), "cconv_original")
    assert sim.dt == 0.02 and sim.history_length == 0 and sim.parameters == 692_902 and sim.max_courant == 5.0
    state = at_simulator_time_step(build_initial_state(cfg), sim, cfg)
    final, _ = rollout(sim, state, 10, guard=run_guard(cfg, sim))
    nf = final.n_fluid
    assert bool(torch.isfinite(final.pos).all()) and final.fluid_outside_bounds().numel() == 0
    front0, front = float(state.pos[:nf, 0].max()), float(final.pos[:nf, 0].max())
    assert front > front0 + 0.05  # the column collapses: its front runs out along the floor
    assert torch.equal(final.pos[nf:], state.pos[nf:])  # the boundary never moves
    moved = (final.pos[:nf] - state.pos[:nf]).norm(dim=1)
    assert float(moved.max()) > 0.05


def test_the_y_up_rotation_maps_gravity_and_is_proper():
    assert torch.allclose(Y_UP @ Y_UP.T, torch.eye(3)) and float(torch.det(Y_UP)) == 1.0
    assert torch.allclose(Y_UP.T @ torch.tensor([0.0, -9.81, 0.0]), torch.tensor([0.0, 0.0, -9.81]))


def test_a_scene_at_another_spacing_is_refused():
    from baselines.cconv.simulator import CConvSimulator

    sim = CConvSimulator(CConvNet(), "cconv_original", "test", Y_UP)
    cfg = _compose("scene=dam_small", "scene.params.l0=0.04")
    with pytest.raises(RolloutError, match=r"l0 = 0\.04"):
        sim.reset(build_initial_state(cfg))


def test_model_cconv_names_missing_weights(tmp_path):
    cfg = _compose("model=cconv", f"model.weights={tmp_path}")
    with pytest.raises(CheckpointError, match=rf"no CConv weights at {tmp_path}/cconv\.pt: train them"):
        build_simulator(cfg)


@pytest.mark.skipif(not (SHIPPED / "cconv.pt").is_file(), reason="no shipped CConv weights")
def test_the_shipped_weights_roll_out_the_small_dam_finite_and_inside_the_tank():
    assert "cconv" in available_simulators()
    cfg = _compose("model=cconv", "scene=dam_small")
    sim = check_simulator(build_simulator(cfg), "cconv")
    assert sim.dt == 0.002 and sim.history_length == 0 and sim.parameters == 692_902
    state = at_simulator_time_step(build_initial_state(cfg), sim, cfg)
    final, _ = rollout(sim, state, 25, guard=run_guard(cfg, sim))
    nf = final.n_fluid
    assert bool(torch.isfinite(final.pos).all()) and final.fluid_outside_bounds().numel() == 0
    assert torch.equal(final.pos[nf:], state.pos[nf:])  # the boundary never moves
    # 50 ms of a collapse: the column has started to fall (free fall would drop its top 12 mm)
    assert float(final.pos[:nf, 2].max()) < float(state.pos[:nf, 2].max()) - 0.002


# --------------------------------------------------------------------------------------------- training
@pytest.fixture(scope="module")
def step_data(tmp_path_factory):
    from lagfluid.tasks.generate import generate

    out = tmp_path_factory.mktemp("cconv_data")
    generate(
        _compose(
            "task=generate",
            "scene=random",
            "data=tiny",
            "data.next_steps=2",
            f"data.out_dir={out}",
            "progress=false",
        )
    )
    return out


def test_the_trainable_predicts_two_steps_and_its_loss_is_dlfs(step_data):
    from torch_geometric.data import Batch

    from baselines.cconv.trainable import CConvTrainable, dlf_loss

    trainable = CConvTrainable(_compose("model=cconv"))
    train, _ = trainable.datasets(step_data)
    net = trainable.build_network()
    stats = trainable.fit_statistics(net, [train[0]])
    assert stats["timestep"] == pytest.approx(0.002) and stats["particle_radius"] == pytest.approx(0.025)
    batch = Batch.from_data_list([train[0], train[1]])
    pred, target = trainable.predict(net, batch)
    nf = int((batch.ptype == 1).sum())
    assert pred.shape == target.shape == (nf, 2, 4) and torch.equal(pred[..., 3], target[..., 3])
    # the loss of a perfect prediction is the epsilon's alone (1e-9 under the root); of a 1 mm error,
    # 128 * w * 1e-3^0.5
    weight = float(target[..., 3].mean())
    assert float(dlf_loss(target, target)) == pytest.approx(128 * weight * 1e-9**0.25, rel=1e-4)
    shifted = target.clone()
    shifted[..., 0] += 1e-3
    expected = 128 * weight * (1e-6 + 1e-9) ** 0.25
    assert float(dlf_loss(shifted, target)) == pytest.approx(expected, rel=1e-4)


def test_training_surface_is_the_whole_tanks_surface_near_the_fluid(step_data):
    # A wall particle at the edge of a window's boundary crop looks one-sided: without the wider crop it
    # became a false surface point inside the wall, which rollouts (the whole tank) never see.
    from baselines.cconv.trainable import REACH, CConvTrainable
    from lagfluid.data.datasets import StepWindows
    from lagfluid.state import ParticleType

    fluid_type = int(ParticleType.FLUID)

    trainable = CConvTrainable(_compose("model=cconv"))
    window = trainable.datasets(step_data)[0][0]
    whole = StepWindows(step_data, "train", steps=2, boundary_radius=None)[0]
    l0 = float(window.l0)
    fluid = window.ptype == fluid_type
    points, _, _ = trainable.surface(window.pos, fluid, torch.zeros_like(window.ptype), l0)
    wall = whole.pos[whole.ptype != fluid_type]
    all_points, _, rows = surface_points(wall, l0, trainable.surface_offset)
    near = torch.cdist(wall[rows], whole.pos[whole.ptype == fluid_type]).min(dim=1).values < REACH * l0
    assert points.shape[0] > 0

    def key(p):
        return {tuple(v) for v in torch.round(p / (0.25 * l0)).long().tolist()}

    assert key(points) == key(all_points[near])  # the whole tank's surface near the fluid, nothing else
    cropped = StepWindows(step_data, "train", steps=2)[0]  # the narrower default crop makes false ones
    crop_points, _, _ = surface_points(cropped.pos[cropped.ptype != fluid_type], l0, trainable.surface_offset)
    assert not key(crop_points) <= key(all_points)


def test_frame_windows_hold_the_next_stored_frames(step_data):
    import h5py

    from lagfluid.data.datasets import StepWindows

    steps = StepWindows(step_data, None, steps=2, boundary_radius=None)
    frames = StepWindows(step_data, None, steps=0, frames=2, boundary_radius=None)
    scene = sorted((step_data / "scenes").glob("*.h5"))[0]
    with h5py.File(scene, "r") as f:
        sample_frames, every = f["samples/frame"][()], int(f["00000"].attrs["sample_every"])
        position = f["00000/position"][()]
    last = len(position) - 1
    kept = int((sample_frames + 2 <= last).sum())
    assert 0 < kept < len(sample_frames)  # the samples 2 frames from the end are left out
    assert len(frames) < len(steps)
    item = frames[kept - 1]  # the last kept sample of the first scene
    frame = int(sample_frames[kept - 1])
    assert torch.equal(item.y_frames, torch.from_numpy(position[frame + 1 : frame + 3]).transpose(0, 1))
    assert int(item.frame_steps) == every == 2
    # data=tiny samples every 2 steps: the second stored next step is the next frame
    torch.testing.assert_close(steps[0].y[:, 1], frames[0].y_frames[:, 0])
    with pytest.raises(LagfluidError, match="steps and frames"):
        StepWindows(step_data, None, steps=0, frames=0)


def test_unrolling_to_a_frame_is_stepping_the_network_to_it(step_data):
    from torch_geometric.data import Batch

    from baselines.cconv.trainable import CConvTrainable

    two_steps = CConvTrainable(_compose("model=cconv"))
    to_frame = CConvTrainable(_compose("model=cconv", "+train.unroll_frames=1"))
    assert to_frame.identity()["unroll_frames"] == 1 and "unroll_frames" not in two_steps.identity()
    net = two_steps.build_network()
    batch = Batch.from_data_list([two_steps.datasets(step_data)[0][1]])
    frame_batch = Batch.from_data_list([to_frame.datasets(step_data)[0][1]])
    with torch.no_grad():
        pred2, target2 = two_steps.predict(net, batch)
        pred_frame, target_frame = to_frame.predict(net, frame_batch)
    assert pred_frame.shape[1] == 1  # one frame, 2 solver steps of data=tiny
    torch.testing.assert_close(pred_frame[:, 0], pred2[:, 1])
    torch.testing.assert_close(target_frame[:, 0], target2[:, 1])


def test_a_gravity_other_than_the_datas_is_refused(step_data):
    from baselines.cconv.trainable import CConvTrainable

    trainable = CConvTrainable(_compose("model=cconv", "model.cconv.gravity=[0.0,-9.81,0.0]"))
    train, _ = trainable.datasets(step_data)
    with pytest.raises(ConfigError, match="gravity"):
        trainable.fit_statistics(trainable.build_network(), [train[0]])


def test_tiny_training_lowers_the_loss(step_data, tmp_path):
    import csv

    from lagfluid.tasks.train import train

    cfg = _compose(
        "task=train",
        "model=cconv",
        "train=cconv_cpu",
        "data=tiny",
        "data.next_steps=2",
        f"data.out_dir={step_data}",
        f"out_dir={tmp_path}",
        "progress=false",
        "train.iterations.cconv=30",
        "train.log_every=10",
        "train.lr_milestones=[20]",
    )
    train(cfg)
    rows = list(csv.DictReader(open(tmp_path / "cconv_loss.csv")))
    losses = [float(r["train_loss"]) for r in rows]
    assert len(losses) == 3 and losses[-1] < losses[0]
    sim = check_simulator(
        __import__("baselines.cconv.simulator", fromlist=["build_simulator"]).build_simulator(
            _compose("model=cconv", f"model.weights={tmp_path}")
        ),
        "cconv",
    )
    assert sim.dt == 0.002 and sim.parameters == 692_902


def test_a_resumed_training_ends_with_the_uninterrupted_runs_weights(step_data, assert_exact_resume):
    def config_for(out):
        return _compose(
            "task=train", "model=cconv", "train=cconv_cpu", "data=tiny", "data.next_steps=2",
            f"data.out_dir={step_data}", f"out_dir={out}", "progress=false", "train.iterations.cconv=6",
            "train.checkpoint_every=2", "train.log_every=1", "train.valid_every=3", "train.lr_milestones=[3]",
        )  # fmt: skip

    assert_exact_resume(config_for, "cconv")


def test_compiled_blocks_of_kernel_cells_equal_the_torch_selection(monkeypatch):
    from lagfluid.neighbors import pair_kernels

    if not pair_kernels.available():
        pytest.skip("numba not installed")
    pos, _ = _cloud(150)
    box = pos[:40] + 0.05
    for inp, out in ((pos, pos), (box, pos)):
        pairs = conv_pairs(inp, None if out is inp else out, 0.3)
        compiled = conv_geometry(inp, out, pairs, 0.3, chunk_cells=5)
        with monkeypatch.context() as m:
            m.setattr(pair_kernels, "applies", lambda *tensors: False)
            plain = conv_geometry(inp, out, pairs, 0.3, chunk_cells=5)
        assert len(compiled.chunks) == len(plain.chunks) == 13
        for a, b in zip(compiled.chunks, plain.chunks, strict=True):
            assert torch.equal(a.crow_indices(), b.crow_indices())
            assert torch.equal(a.col_indices(), b.col_indices()) and torch.equal(a.values(), b.values())
            assert a.values().numel() > 0


# ------------------------------------------------------------------------- fine-tuning DLF's network
FINETUNE = (
    "model=cconv",
    "model.start_from=dlf",
    "model.axes=y_up",
    "model.surface_weight=dlf",
    "model.cconv.timestep=0.004",  # data=tiny's frame: 2 solver steps
    "model.cconv.gravity=[0.0,-9.8065,0.0]",
    "model.cconv.length_unit=1.0",
    "++train.unroll_frames=1",
)


def test_fine_tuning_starts_from_dlfs_weights_with_the_datas_gravity(step_data):
    from baselines.cconv.trainable import CConvTrainable

    trainable = CConvTrainable(_compose(*FINETUNE))
    net = trainable.build_network()
    theirs = load_dlf_network(DLF_WEIGHTS)
    for name, tensor in theirs.state_dict().items():
        if name != "gravity":
            assert torch.equal(net.state_dict()[name], tensor), name
    assert net.gravity.tolist() == pytest.approx([0.0, -9.8065, 0.0])  # the data's, not their 9.81
    stats = trainable.fit_statistics(net, [trainable.datasets(step_data)[0][0]])
    assert stats["gravity"] == pytest.approx([0.0, -9.8065, 0.0], abs=1e-5)  # the data's z, in their y
    assert trainable.identity() == {
        "surface_offset": 0.5, "unroll_frames": 1, "axes": "y_up",
        "surface_weight": pytest.approx(1.9 * 4 / math.pi), "start_from": "dlf",
    }  # fmt: skip
    # a network step that does not divide the frame is refused, naming it
    odd = CConvTrainable(_compose(*FINETUNE, "model.cconv.timestep=0.003"))
    with pytest.raises(ConfigError, match=r"timestep=0\.003"):
        odd.fit_statistics(odd.build_network(), [odd.datasets(step_data)[0][0]])
    with pytest.raises(ConfigError, match=r"model\.axes='x_up'"):
        CConvTrainable(_compose(*FINETUNE, "model.axes=x_up"))
    with pytest.raises(ConfigError, match=r"model\.start_from='nowhere\.pt'"):
        CConvTrainable(_compose(*FINETUNE, "model.start_from=nowhere.pt"))


def test_a_turn_about_gravity_keeps_gravity_and_turns_the_horizontal():
    from baselines.cconv.trainable import CConvTrainable

    turning = CConvTrainable(_compose(*FINETUNE, "++train.rotate_about_gravity=true"))
    torch.manual_seed(3)
    frames = [turning.frame(torch.device("cpu"), torch.float64) for _ in range(3)]
    down = torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    for frame in frames:
        torch.testing.assert_close(frame @ frame.T, torch.eye(3, dtype=torch.float64))
        torch.testing.assert_close(frame @ down, Y_UP.double() @ down)  # gravity stays their -y
    assert not torch.allclose(frames[0], frames[1])  # the horizontal axes turn from batch to batch
    still = CConvTrainable(_compose(*FINETUNE))
    torch.testing.assert_close(still.frame(torch.device("cpu"), torch.float64), Y_UP.double())
    # validation (turn=False: the network in eval mode) sees the data in the network's axes, unturned
    torch.testing.assert_close(turning.frame(torch.device("cpu"), torch.float64, turn=False), Y_UP.double())


def test_a_fine_tuned_checkpoint_rolls_out_as_it_was_trained(step_data, tmp_path):
    # The simulator of model=cconv reads the axes and the wall weighting back from the checkpoint: its
    # step from a window's state is the trainable's first predicted frame (the same network, walls, axes).
    from torch_geometric.data import Batch

    from baselines.cconv.trainable import CConvTrainable
    from lagfluid.data.datasets import StepWindows
    from lagfluid.state import ParticleState, SceneParams
    from lagfluid.tasks.train import train

    overrides = (*FINETUNE, "task=train", "train=cconv_cpu", "data=tiny", f"data.out_dir={step_data}")
    train(_compose(*overrides, f"out_dir={tmp_path}", "progress=false", "train.iterations.cconv=2",
                   "train.lr_milestones=[1]", "train.log_every=1", "train.valid_every=2"))  # fmt: skip
    sim = build_simulator(_compose("model=cconv", f"model.weights={tmp_path}", "dtype=float64"))
    torch.testing.assert_close(sim.axes, Y_UP.double())
    assert sim.surface_weight == pytest.approx(1.9 * 4 / math.pi) and sim.dt == 0.004

    trainable = CConvTrainable(_compose(*overrides))
    window = trainable.datasets(step_data)[0][1]
    whole = StepWindows(step_data, "train", steps=0, frames=1, boundary_radius=None)[1]
    net = sim.net
    batch = Batch.from_data_list([window]).apply(lambda t: t.double() if t.is_floating_point() else t)
    turning = CConvTrainable(_compose(*overrides, "++train.rotate_about_gravity=true"))
    with torch.no_grad():
        pred, _ = trainable.predict(net, batch)
        # validation (the network in eval mode) is not turned, however the training's batches are
        torch.testing.assert_close(turning.predict(net, batch)[0], pred, rtol=0, atol=0)
    params = SceneParams(dt=0.004, l0=float(whole.l0))
    state = ParticleState(whole.pos.double(), whole.vel.double(), whole.ptype, params=params, check=False)
    sim.reset(state)
    moved = sim.step(state)
    nf = state.n_fluid
    # the prediction: displacements in their axes (length unit 1 m)
    torch.testing.assert_close(
        pred[:, 0, :3], (moved.pos[:nf] - state.pos[:nf]) @ Y_UP.double().T, rtol=0, atol=1e-9
    )
    assert not torch.allclose(moved.pos[:nf], state.pos[:nf] + 0.004 * state.vel[:nf], atol=1e-6)
