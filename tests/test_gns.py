"""GNS (baselines/gns): architecture, invariances, batching, the noise and target bookkeeping, the simulator's
state handling, training and the plugin path (seconds)."""

from contextlib import nullcontext
from importlib import metadata
from types import SimpleNamespace

import h5py
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf
from torch_geometric.data import Batch, Data

from baselines.gns.graph import bounds_features, build_graph
from baselines.gns.network import GNSNet, InteractionNetwork
from baselines.gns.simulator import SHIPPED, GNSSimulator, build_simulator
from baselines.gns.trainable import GNSTrainable, random_walk_noise, step_acceleration, symmetric_batch
from benchmarks.gns_edge_layer import concatenated_first_layer
from lagfluid.data.symmetry import HorizontalSymmetry
from lagfluid.errors import ConfigError, LagfluidError, RolloutError
from lagfluid.integrate import acceleration_from_positions, semi_implicit_euler
from lagfluid.models.mps_simulator import build_mps
from lagfluid.models.simulator import check_simulator
from lagfluid.registry import available_simulators, trainable_models
from lagfluid.rollout import rollout
from lagfluid.run import CONF_DIR
from lagfluid.state import ParticleState, ParticleType
from lagfluid.tasks.config import at_simulator_time_step, build_initial_state, initial_history, run_guard
from lagfluid.tasks.generate import generate
from lagfluid.tasks.train import train

SMALL = {"latent": 16, "hidden": 16, "mlp_layers": 2, "blocks": 3, "history": 5, "radius": 2.1}
L0 = 0.05


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


def _net(seed=0, dtype=torch.float64, **options):
    """A small GNS with non-trivial statistics (so a wrong normalisation shows)."""
    torch.manual_seed(seed)
    net = GNSNet(**{**SMALL, **options}).to(dtype)
    net.velocity.set([0.1, -0.2, 0.3], [0.5, 0.7, 0.9])
    net.acceleration.set([1.0, 2.0, -9.0], [20.0, 30.0, 40.0])
    net.frame_dt.fill_(0.008)
    net.solver_dt.fill_(0.002)
    return net.eval()


def _scene(seed=0, nx=5, dtype=torch.float64):
    """A jittered fluid block over a two-layer floor: pos (P, 3), fluid mask, frames (Nf, 6, 3), bounds."""
    g = torch.Generator().manual_seed(seed)
    idx = torch.stack(torch.meshgrid(*[torch.arange(n) for n in (nx, 4, 3)], indexing="ij"), -1).reshape(
        -1, 3
    )
    fluid = (idx.to(dtype) + torch.tensor([1.0, 1.0, 1.0], dtype=dtype)) * L0
    fluid = fluid + 0.1 * L0 * torch.randn(fluid.shape, generator=g, dtype=dtype)
    fx = torch.stack(
        torch.meshgrid(torch.arange(-1, nx + 3), torch.arange(-1, 7), indexing="ij"), -1
    ).reshape(-1, 2)
    floor = torch.cat([torch.cat([fx, torch.full((len(fx), 1), -k)], 1) for k in (0, 1)]).to(dtype) * L0
    pos = torch.cat([fluid, floor])
    is_fluid = torch.arange(len(pos)) < len(fluid)
    steps = 0.004 * torch.randn(len(fluid), 5, 3, generator=g, dtype=dtype)
    frames = torch.cat([fluid.unsqueeze(1) - steps.flip(1).cumsum(1).flip(1), fluid.unsqueeze(1)], dim=1)
    bounds = torch.tensor([[0.0, 0.0, 0.0], [(nx + 2) * L0, 6 * L0, 2.0]], dtype=dtype)
    return pos, is_fluid, frames, bounds


def _acc(net, pos, fluid, frames, bounds, batch=None):
    return step_acceleration(net, pos, fluid, frames, 0.008, L0, bounds, batch)


# ------------------------------------------------------------------------------------------ architecture
def test_paper_size_has_deepminds_parameter_count():
    # 22 node inputs (5 x 3 velocities, 6 bounds, 1 type), 4 edge inputs, latent 128, 10 blocks of two
    # 2 x 128 MLPs with LayerNorm, decoder without: DeepMind's configuration, ~1.59M (paper: 1,406,272).
    lin = lambda i, o: i * o + o  # noqa: E731
    mlp = lambda i, o, ln=True: lin(i, 128) + lin(128, 128) + lin(128, o) + (2 * o if ln else 0)  # noqa: E731
    expected = mlp(22, 128) + mlp(4, 128) + 10 * (mlp(384, 128) + mlp(256, 128)) + mlp(128, 3, ln=False)
    count = sum(p.numel() for p in GNSNet().parameters())
    assert count == expected == 1_590_915
    assert sum(p.numel() for p in GNSNet(type_embedding=16).parameters()) == count + 15 * 128 + 2 * 16


def _block_and_graph(dtype, n=40, edges=1200, latent=16, hidden=24, seed=0):
    """A random block (non-zero biases, LayerNorm affine) and a random graph of ``n`` nodes in ``dtype``."""
    torch.manual_seed(seed)
    block = InteractionNetwork(latent=latent, hidden=hidden, mlp_layers=2).to(dtype)
    with torch.no_grad():
        for p in block.parameters():
            p.add_(0.1 * torch.randn_like(p))  # LayerNorm's weight 1 and bias 0 are not generic
    x, e = torch.randn(n, latent, dtype=dtype), torch.randn(edges, latent, dtype=dtype)
    return block, x, e, torch.randint(0, n, (2, edges))


def _block_outputs_and_grads(block, x, e, edge_index, concatenated):
    """The block's (x', e') and the gradients of a fixed projection of them wrt parameters, x and e."""
    x, e = x.clone().requires_grad_(), e.clone().requires_grad_()
    block.zero_grad(set_to_none=True)
    with concatenated_first_layer() if concatenated else nullcontext():
        x_new, e_new = block(x, edge_index, e)
    g = torch.Generator().manual_seed(1)  # drawn in float64 whatever the dtype: the same numbers
    loss = (x_new * torch.randn(x_new.shape, generator=g, dtype=torch.float64).to(x_new)).sum()
    loss = loss + (e_new * torch.randn(e_new.shape, generator=g, dtype=torch.float64).to(e_new)).sum()
    loss.backward()
    grads = {name: p.grad.clone() for name, p in block.named_parameters()}
    return (x_new.detach(), e_new.detach()), {**grads, "x": x.grad, "e": e.grad}


def test_edge_update_applied_by_parts_is_the_concatenated_mlp_in_value_and_gradient():
    # float64: the two forms differ only in the order of the first layer's sums (3 partial dot products
    # and the bias, against one of 3L terms): ~1e-15 here, far below 1e-12
    block, x, e, edge_index = _block_and_graph(torch.float64)
    by_parts = block.edge_update(e, edge_index, x)
    full = block.edge_mlp(torch.cat([e, x[edge_index[1]], x[edge_index[0]]], dim=1))
    torch.testing.assert_close(by_parts, full, rtol=0, atol=1e-12)
    (x_new, e_new), grads = _block_outputs_and_grads(block, x, e, edge_index, concatenated=False)
    summed = torch.zeros_like(x).index_add_(0, edge_index[1], full)
    torch.testing.assert_close(x_new, x + block.node_mlp(torch.cat([x, summed], 1)), rtol=0, atol=1e-12)
    torch.testing.assert_close(e_new, e + full, rtol=0, atol=1e-12)
    # gradients (training differentiates the by-parts form): every parameter's, the first layer's weight by
    # column block included, and the inputs'
    _, reference = _block_outputs_and_grads(block, x, e, edge_index, concatenated=True)
    assert grads.keys() == reference.keys() and "edge_mlp.0.weight" in grads
    for name, grad in grads.items():
        torch.testing.assert_close(grad, reference[name], rtol=0, atol=1e-12, msg=name)


def test_edge_update_by_parts_in_float32_is_the_concatenated_form_to_rounding():
    # float32: the forms round differently. Per output and gradient: they agree to 16 ulps of its largest
    # entry (measured: <= 8, sums over 1,200 edges in the gradients), and the by-parts form is as close to
    # the float64 value as the concatenated one (within 3x; measured <= 1.8x): rounding, not a change
    block, x, e, edge_index = _block_and_graph(torch.float64)
    exact = _block_outputs_and_grads(block, x, e, edge_index, concatenated=True)
    block.float()
    x, e = x.float(), e.float()
    by_parts = _block_outputs_and_grads(block, x, e, edge_index, concatenated=False)
    reference = _block_outputs_and_grads(block, x, e, edge_index, concatenated=True)
    flat = lambda r: {"x'": r[0][0], "e'": r[0][1], **r[1]}  # noqa: E731
    exact, by_parts, reference = flat(exact), flat(by_parts), flat(reference)
    eps = torch.finfo(torch.float32).eps
    for name, value in exact.items():
        scale = float(value.abs().max())
        difference = float((by_parts[name] - reference[name]).abs().max())
        assert difference <= 16 * eps * scale, (name, difference, scale)
        error, ref_error = (float((r[name].double() - value).abs().max()) for r in (by_parts, reference))
        assert error <= 3 * ref_error, (name, error, ref_error)


def test_the_networks_loss_gradients_by_parts_equal_the_concatenated_forms():
    # the whole training path (graph, 3 blocks, decoder): the same loss and gradients to 1e-12 in float64
    net = _net().train()
    pos, fluid, frames, bounds = _scene()
    results = []
    for form in (nullcontext(), concatenated_first_layer()):
        net.zero_grad(set_to_none=True)
        with form:
            loss = (_acc(net, pos, fluid, frames, bounds) ** 2).mean()
        loss.backward()
        results.append((loss.detach(), {n: p.grad.clone() for n, p in net.named_parameters()}))
    (loss, grads), (ref_loss, ref_grads) = results
    torch.testing.assert_close(loss, ref_loss, rtol=0, atol=1e-12)
    for name, grad in grads.items():
        torch.testing.assert_close(grad, ref_grads[name], rtol=0, atol=1e-12, msg=name)


def test_updated_edge_latents_reach_the_next_block():
    net = _net()
    pos, fluid, frames, bounds = _scene()
    seen = {}

    def after_block0(module, args, out):
        seen["out0"] = out[1]

    def before_block1(module, args):
        seen["in1"] = args[2]

    net.processor[0].register_forward_hook(after_block0)
    net.processor[1].register_forward_pre_hook(before_block1)
    _acc(net, pos, fluid, frames, bounds)
    assert torch.equal(seen["out0"], seen["in1"])


def test_graph_has_every_neighbour_of_the_fluid_and_only_the_boundary_in_reach():
    pos, fluid, _, _ = _scene()
    radius = 2.1 * L0
    g = build_graph(pos, fluid, radius)
    d = torch.cdist(pos, pos)
    expected = {
        (j, i)
        for i in torch.nonzero(fluid).flatten().tolist()
        for j in range(len(pos))
        if j != i and d[i, j] < radius
    }
    src, dst = g.nodes[g.edge_index[0]].tolist(), g.nodes[g.edge_index[1]].tolist()
    assert set(zip(src, dst, strict=True)) == expected and len(src) == len(expected)
    in_reach = {j for j, _ in expected} | set(torch.nonzero(fluid).flatten().tolist())
    assert set(g.nodes.tolist()) == in_reach
    assert bool(fluid[g.nodes[: g.n_fluid]].all()) and not bool(fluid[g.nodes[g.n_fluid :]].any())
    assert len(in_reach) < len(pos)  # the floor's far corners are not modelled


def test_bounds_features_are_clipped_distances_over_the_radius():
    pos = torch.tensor([[0.05, 0.5, 0.95]])
    f = bounds_features(pos, torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]), 0.1)
    torch.testing.assert_close(f, torch.tensor([[0.5, 1.0, 1.0, 1.0, 1.0, 0.5]]))
    assert torch.equal(bounds_features(pos, None, 0.1), torch.ones(1, 6))


# ------------------------------------------------------------------------------------------ invariances
def test_permutation_invariance():
    net = _net()
    pos, fluid, frames, bounds = _scene()
    nf = int(fluid.sum())
    perm_f = torch.randperm(nf, generator=torch.Generator().manual_seed(1))
    perm_b = nf + torch.randperm(len(pos) - nf, generator=torch.Generator().manual_seed(2))
    perm = torch.cat([perm_f, perm_b])
    out = _acc(net, pos, fluid, frames, bounds)
    out_perm = _acc(net, pos[perm], fluid[perm], frames[perm_f], bounds)
    torch.testing.assert_close(out_perm, out[perm_f])


def test_translation_invariance():
    net = _net()
    pos, fluid, frames, bounds = _scene()
    shift = torch.tensor([1.3, -0.7, 2.1], dtype=torch.float64)
    out = _acc(net, pos, fluid, frames, bounds)
    torch.testing.assert_close(_acc(net, pos + shift, fluid, frames + shift, bounds + shift), out)


def _item(seed, nx):
    pos, fluid, frames, bounds = _scene(seed, nx, torch.float32)
    nf = int(fluid.sum())
    return Data(
        pos=pos,
        ptype=torch.where(fluid, int(ParticleType.FLUID), int(ParticleType.WALL)),
        history=frames[:, :-1].contiguous(),
        y=frames[:, -1] + 0.003 * torch.randn(nf, 3, generator=torch.Generator().manual_seed(seed)),
        frame_dt=torch.tensor([0.008]),
        dt=torch.tensor([0.002]),
        l0=torch.tensor([L0]),
        bounds=bounds.unsqueeze(0),
    )


def _trainable(**train):
    cfg = OmegaConf.create({"model": {"gns": SMALL}, "train": train})
    return GNSTrainable(cfg)


def test_two_scenes_batched_equal_each_alone():
    trainable = _trainable()
    net = _net(dtype=torch.float32)
    a, b = _item(0, 5), _item(1, 4)
    b.pos, b.history, b.y = b.pos + 0.02, b.history + 0.02, b.y + 0.02  # overlapping in space
    pred_ab, target_ab = trainable.predict(net, Batch.from_data_list([a, b]))
    alone = [trainable.predict(net, Batch.from_data_list([item])) for item in (a, b)]
    torch.testing.assert_close(pred_ab, torch.cat([p for p, _ in alone]), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(target_ab, torch.cat([t for _, t in alone]))


# ------------------------------------------------------------------------------------------ noise, targets
def test_random_walk_noise_has_the_stated_std_at_the_last_frame():
    torch.manual_seed(0)
    noise = random_walk_noise((20000, 6, 3), 0.01)
    assert torch.equal(noise[:, 0], torch.zeros(20000, 3))
    assert abs(float(noise[:, -1].std()) - 0.01) < 3e-4
    increments = noise[:, 1:] - noise[:, :-1]
    assert abs(float(increments.std()) - 0.01 / 5**0.5) < 2e-4


def test_noisy_inputs_and_corrected_target_give_the_true_next_velocity():
    """The target shifted by the last frame's noise: the update recovers the true next velocity."""
    torch.manual_seed(0)
    frames = torch.cumsum(0.01 * torch.randn(50, 7, 3, dtype=torch.float64), dim=1)
    x, y, dt = frames[:, :-1], frames[:, -1], 0.008
    noise = random_walk_noise((50, 6, 3), 0.005).double()
    noisy = x + noise
    acc = acceleration_from_positions(noisy[:, -2], noisy[:, -1], y + noise[:, -1], dt)
    pos, vel = semi_implicit_euler(noisy[:, -1], (noisy[:, -1] - noisy[:, -2]) / dt, acc, dt)
    torch.testing.assert_close(vel, (y - x[:, -1]) / dt)
    torch.testing.assert_close(pos, y + noise[:, -1])


def test_training_noise_and_pushforward_are_only_in_training():
    trainable = _trainable(noise_std=0.1, pushforward={"start": 0, "unrolls": [0, 2], "probs": [0, 1]})
    net = _net(dtype=torch.float32)
    item = _item(0, 5)
    item.history = torch.cat([item.history[:, :1], item.history[:, :1], item.history], 1)  # H + K = 7 frames
    batch = Batch.from_data_list([item])
    clean = trainable.predict(net, batch)
    torch.testing.assert_close(trainable.predict(net, batch), clean)  # eval: deterministic
    net.train()
    noisy = trainable.predict(net, batch)
    assert int(net.trained_batches) == 1
    assert not torch.allclose(noisy[1], clean[1])  # the target moved with the noise and the unroll


def test_a_horizontal_symmetry_maps_the_windows_target_acceleration_as_a_vector():
    trainable = _trainable()
    net = _net(dtype=torch.float32)
    batch = Batch.from_data_list([_item(0, 5), _item(1, 4)])
    symmetry = HorizontalSymmetry(flip_x=True, flip_y=False, swap=True)
    mapped = symmetric_batch(batch, symmetry)
    _, target = trainable.predict(net, batch)
    _, mapped_target = trainable.predict(net, mapped)
    acc = net.acceleration.inverse
    torch.testing.assert_close(acc(mapped_target), symmetry.vectors(acc(target)), atol=1e-3, rtol=1e-5)
    assert torch.equal(mapped.bounds, batch.bounds[:, :, [1, 0, 2]])
    net.train()
    on = _trainable(horizontal_symmetries=True)
    assert on.identity()["horizontal_symmetries"] and "horizontal_symmetries" not in trainable.identity()
    targets = {tuple(on.predict(net, batch)[1][0].tolist()) for _ in range(40)}
    assert len(targets) > 2  # drawn per batch in training
    no_bounds = _item(0, 5)
    del no_bounds.bounds
    with pytest.raises(LagfluidError, match="horizontal_symmetries needs scenes with a tank"):
        on.predict(net, Batch.from_data_list([no_bounds]))


def test_a_perfect_predictor_reproduces_the_trajectory(tiny_data):
    """The simulator fed the exact accelerations of a stored trajectory rolls the trajectory out."""
    scene = sorted((tiny_data / "scenes").glob("*.h5"))[0]
    with h5py.File(scene, "r") as f:
        truth = torch.from_numpy(f["00000/position"][()]).double()
        frame_dt = float(f["00000"].attrs["dt"]) * int(f["00000"].attrs["sample_every"])

    class Oracle(GNSNet):
        def forward(self, nodes, edge_index, edges):
            k = int(self.frame) + 1
            acc = acceleration_from_positions(truth[k - 1], truth[k], truth[k + 1], frame_dt)
            self.frame += 1
            out = torch.zeros(nodes.shape[0], 3, dtype=nodes.dtype)
            out[: acc.shape[0]] = self.acceleration(acc)
            return out

    net = Oracle(**SMALL).double()
    net.acceleration.set([1.0, 2.0, -9.0], [20.0, 30.0, 40.0])
    net.frame_dt.fill_(frame_dt)
    net.solver_dt.fill_(0.002)
    start = 5
    net.frame = start - 1
    cfg = _compose("scene=trajectory", f"scene.path={scene}", f"scene.frame={start}", "dtype=float64")
    sim = GNSSimulator(net.eval(), None, "oracle")
    state = at_simulator_time_step(build_initial_state(cfg), sim, cfg)
    frames = []
    steps = truth.shape[0] - 1 - start
    rollout(
        sim,
        state,
        steps,
        history=initial_history(cfg, sim),
        on_frame=lambda s: frames.append(s.pos[: s.n_fluid]),
    )
    assert len(frames) == steps + 1 == 8
    for k, pos in enumerate(frames):
        torch.testing.assert_close(pos, truth[start + k], atol=1e-6, rtol=0)


def _free_fall_item(frames=9, dt=0.008, g=9.81):
    """A window of a 3 x 3 x 3 block falling from rest (semi-implicit Euler at -g), in float64.

    ``history`` is frames 0 .. frames - 3, ``pos`` frame frames - 2 and ``y`` the last frame, as a
    :class:`~lagfluid.data.datasets.TrajectoryWindows` item of H + K = frames - 2; no boundary in reach.
    """
    dt = float(torch.tensor(dt, dtype=torch.float32))  # the frame spacing as a dataset stores it
    grid = torch.arange(3, dtype=torch.float64) * L0 + 1.0
    x = torch.stack(torch.meshgrid(grid, grid, grid, indexing="ij"), -1).reshape(-1, 3)
    v, acc, path = torch.zeros_like(x), torch.tensor([0.0, 0.0, -g], dtype=torch.float64), [x]
    for _ in range(frames - 1):
        x, v = semi_implicit_euler(x, v, acc.expand_as(x), dt)
        path.append(x)
    path = torch.stack(path, dim=1)  # (27, frames, 3)
    return Data(
        pos=path[:, -2],
        ptype=torch.full((27,), int(ParticleType.FLUID)),
        history=path[:, :-2],
        y=path[:, -1],
        frame_dt=torch.tensor([dt]),
        dt=torch.tensor([0.002]),
        l0=torch.tensor([L0]),
    )


def test_the_statistics_are_of_the_frames_the_targets_are_made_of():
    """Fitted on free fall, the acceleration mean is -g and its std the noise's: a zero output falls at g.

    The statistics once skipped frame t (history, then t+1): one velocity spanned two frames and the
    shipped weights' acceleration mean and std became -8.2 and 84 m/s^2 (-2.3 and 73 with frame t).
    """
    dt, noise = float(torch.tensor(0.008, dtype=torch.float32)), 0.09
    trainable = _trainable(noise_std=noise, pushforward={"unrolls": [0, 3], "probs": [1, 1]})
    net = _net()
    items = [_free_fall_item(frames) for frames in (9, 12, 15)]
    stats = trainable.fit_statistics(net, items)
    torch.testing.assert_close(
        net.acceleration.mean, torch.tensor([0.0, 0.0, -9.81], dtype=torch.float64), atol=1e-9, rtol=0
    )
    noise_acc = noise * L0 / dt**2
    torch.testing.assert_close(
        net.acceleration.std, torch.full((3,), noise_acc, dtype=torch.float64), atol=0, rtol=1e-6
    )
    speeds = torch.cat(
        [9.81 * dt * torch.arange(1, f, dtype=torch.float64) for f in (9, 12, 15)]
    )  # the frames' |v_z|
    assert stats["velocity_mean"][2] == pytest.approx(-float(speeds.mean()), abs=1e-9)
    # a window padded with copies of frame 0 (frames_before) counts its trajectory frames only
    padded = _free_fall_item(9)
    padded.history = torch.cat([padded.history[:, :1], padded.history[:, :1], padded.history], dim=1)
    padded.frames_before = torch.tensor([7])
    assert trainable.fit_statistics(net, [padded]) == trainable.fit_statistics(net, [_free_fall_item(9)])
    # the window's standardised target is 0: a network whose raw output is 0 steps free fall exactly
    _, target = trainable.predict(net.eval(), Batch.from_data_list([_free_fall_item(11)]))
    torch.testing.assert_close(target, torch.zeros_like(target), atol=1e-9, rtol=0)


def test_the_windows_start_at_the_first_frame_a_warm_started_rollout_steps_from(tiny_data):
    """A rollout from rest steps by the network from frame H (after H MPS frames), so training has it.

    The windows once started at H + K (K the longest pushforward unroll): the shipped weights never saw
    frames 5-7 of a fall and, from the warm start, predicted +0.9 .. -3.2 m/s^2 for a free-falling block.
    """
    h, k = SMALL["history"], 3
    trainable = _trainable(pushforward={"start": 0, "unrolls": [0, 1, 2, 3], "probs": [1, 1, 1, 1]})
    train, _ = trainable.datasets(tiny_data)
    scene = tiny_data / train.metadata["splits"]["train"][0]
    with h5py.File(scene, "r") as f:
        stored = torch.from_numpy(f["00000/position"][()])
        every = int(f["00000"].attrs["sample_every"])
    frames = [int(item.step) // every for item in train]
    assert frames == list(range(h, stored.shape[0] - 1))  # every frame with H before it and one after
    first = train[0]
    assert int(first.frames_before) == h
    assert torch.equal(first.history[:, k:], stored[:h].transpose(0, 1))
    assert torch.equal(first.history[:, :k], stored[:1].transpose(0, 1).expand(-1, k, -1))  # frame 0 copies
    assert torch.equal(first.y, stored[h + 1])
    assert [int(train[j].frames_before) for j in range(k + 1)] == [h, h + 1, h + 2, h + 3]
    # an unroll never starts before frame 0: at frame H + 1 a drawn 3 rolls 1 step
    net = _net(dtype=torch.float32).train()
    batch = Batch.from_data_list([train[1]])
    rolled = [
        _trainable(pushforward={"start": 0, "unrolls": [u], "probs": [1]}).predict(net, batch) for u in (3, 1)
    ]
    torch.testing.assert_close(rolled[0], rolled[1], atol=0, rtol=0)
    plain = _trainable().predict(net, batch)
    assert not torch.equal(rolled[1][0], plain[0])  # the unroll of 1 did run


# ------------------------------------------------------------------------------------------ simulator
@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    out = tmp_path_factory.mktemp("gns_data")
    generate(
        _compose(
            "task=generate",
            "scene=random",
            "data=tiny",
            "data.steps=24",
            f"data.out_dir={out}",
            "progress=false",
        )
    )
    return out


def test_the_warm_start_is_mps_and_a_foreign_state_is_refused():
    cfg = _compose("model=mps", "scene=dam_small")
    state0 = build_initial_state(cfg)
    state = ParticleState(
        pos=state0.pos,
        vel=state0.vel,
        ptype=state0.ptype,
        params=state0.params.with_overrides(dt=0.008),
        bounds=state0.bounds,
    )
    sim = check_simulator(GNSSimulator(_net(dtype=torch.float32), build_mps(cfg), "test"), "gns")
    sim.reset(state)
    warm = state
    for _ in range(5):
        warm = sim.step(warm)
        assert set(sim.last_timings) == {"mps_warm_start"}
    mps = build_mps(cfg)
    ref = state0
    mps.reset(ref)
    for _ in range(20):
        ref = mps.step(ref)
    assert torch.equal(warm.pos, ref.pos)
    assert warm.time == pytest.approx(0.04) and warm.step == 5
    after = sim.step(warm)
    assert set(sim.last_timings) == {"neighbors", "network"}
    assert torch.equal(after.pos[state.n_fluid :], state.pos[state.n_fluid :])  # the boundary never moves
    with pytest.raises(RolloutError, match="does not follow"):
        sim.step(warm)
    with pytest.raises(RolloutError, match="earlier frames"):
        GNSSimulator(_net(dtype=torch.float32), None, "test").reset(state)


@pytest.mark.parametrize("frame_dt", [0.008, 0.016, 0.02])
def test_the_frame_spacing_is_the_decimal_the_float32_buffer_was_stored_from(frame_dt):
    """A 16 ms network's float32 buffer reads 0.016000001: its frames' times would miss the reference's
    2 ms grid from the fourth frame on (``common_frames``' tolerance is 2e-9 s), and an evaluation would
    compare frame 0 only (``benchmarks/results/gns_levers.md``'s first 16 ms rows)."""
    from lagfluid.tasks.evaluate.compare import common_frames

    net = _net(dtype=torch.float32)
    net.frame_dt.fill_(frame_dt)
    sim = GNSSimulator(net, None, "test")
    assert sim.dt == frame_dt and sim.solver_dt == 0.002
    model = SimpleNamespace(times=[k * sim.dt for k in range(0, 60, 2)])
    ref = SimpleNamespace(attrs={"dt": 0.002}, steps=list(range(0, 600, 1)))
    assert len(common_frames(model, ref)) == 30


def test_tiny_training_lowers_the_loss(tiny_data, tmp_path):
    cfg = _compose(
        "task=train",
        "model=gns",
        "train=gns_cpu",
        f"data.out_dir={tiny_data}",
        f"out_dir={tmp_path}",
        *[f"model.gns.{k}={v}" for k, v in SMALL.items()],
        "train.iterations={gns: 40}",
        "train.log_every=5",
        "train.valid_every=5",
        "train.lr_start=3e-3",
        "train.pushforward.start=20",
        "progress=false",
        "threads=1",
    )
    train(cfg)
    rows = np.genfromtxt(tmp_path / "gns_loss.csv", delimiter=",", names=True)
    assert rows["valid_loss"][-1] < 0.7 * rows["valid_loss"][0]


def test_a_resumed_training_ends_with_the_uninterrupted_runs_weights(tiny_data, assert_exact_resume):
    def config_for(out):  # noise and pushforward both inside the 6 iterations
        return _compose(
            "task=train", "model=gns", "train=gns_cpu", f"data.out_dir={tiny_data}", f"out_dir={out}",
            *[f"model.gns.{k}={v}" for k, v in SMALL.items()], "train.iterations={gns: 6}",
            "train.checkpoint_every=2", "train.log_every=1", "train.valid_every=3",
            "train.pushforward.start=3", "progress=false", "threads=1",
        )  # fmt: skip

    assert_exact_resume(config_for, "gns")


# ------------------------------------------------------------------------------------------ plugin path
def test_the_plugin_is_found_by_entry_points_and_composes():
    for group in ("lagfluid.simulators", "lagfluid.trainables", "lagfluid.configs"):
        assert "gns" in {ep.name for ep in metadata.entry_points(group=group)}, group
    assert "gns" in available_simulators() and "gns" in trainable_models()
    cfg = _compose("model=gns", "train=gns_cpu")
    assert cfg.model.name == "gns" and cfg.model.gns.latent == 48 and cfg.train.noise_std > 0
    assert _compose("model=gns", "train=gns_paper").model.gns.latent == 128


@pytest.mark.skipif(not (SHIPPED / "gns.pt").is_file(), reason="no shipped GNS weights")
def test_the_shipped_weights_roll_out_finite_and_inside_the_tank():
    cfg = _compose("model=gns", "scene=dam_small", "dt=0.008")
    sim = build_simulator(cfg)
    state = build_initial_state(cfg)
    final, _ = rollout(sim, state, 20, guard=run_guard(cfg, sim))
    assert bool(torch.isfinite(final.pos).all()) and final.fluid_outside_bounds().numel() == 0
    assert sim.dt == 0.008 and sim.max_courant == 1.0


@pytest.mark.skipif(not (SHIPPED / "gns.pt").is_file(), reason="no shipped GNS weights")
def test_the_shipped_weights_roll_out_the_same_with_the_concatenated_edge_layer():
    # 3 GNS steps of dam_small after the MPS warm start, by parts and concatenated, from the same state and
    # history. float32: the first layer's sums are taken in another order, so accelerations differ by
    # ~1e-6 relative (~1e-9 m of a step's displacement, a dt^2 = 6.4e-5 s^2 factor): positions agree
    # to their own rounding, an ulp or two (1.2e-7 m at 1 m); atol is 4 ulps of the largest coordinate.
    cfg = _compose("model=gns", "scene=dam_small", "dt=0.008")
    sim, state = build_simulator(cfg), build_initial_state(cfg)
    sim.reset(state)
    for _ in range(sim.history_length):  # the warm start: MPS frames
        state = sim.step(state)
    memory = {k: v.clone() for k, v in sim.rollout_memory().items()}
    ends = []
    for form in (nullcontext(), concatenated_first_layer()):
        sim.restore_rollout_memory(state, memory)
        end = state
        with form:
            for _ in range(3):
                end = sim.step(end)
        assert sim.last_step_learned and end.pos.dtype == torch.float32
        ends.append(end.pos)
    moved = (ends[0] - state.pos).abs().max()
    assert moved > 1e-3  # the network's steps moved the fluid (millimetres): compared, not still
    atol = 4 * torch.finfo(torch.float32).eps * float(ends[1].abs().max())
    torch.testing.assert_close(ends[0], ends[1], rtol=0, atol=atol)


def test_trajectory_windows_carry_the_domain_bounds(tiny_data):
    from lagfluid.data.datasets import TrajectoryWindows

    item = TrajectoryWindows(tiny_data, "train", history=5)[0]
    scene = tiny_data / TrajectoryWindows(tiny_data, "train", history=5).metadata["splits"]["train"][0]
    with h5py.File(scene, "r") as f:
        expected = torch.from_numpy(f["00000"].attrs["bounds"]).float()
    assert torch.equal(item.bounds, expected.unsqueeze(0))


@pytest.mark.parametrize("first", [1, 2])
def test_trajectory_windows_with_a_frame_stride_take_every_other_stored_frame(tiny_data, first):
    """Stride 2: history t-4, t-2, frame t, target t+2 of the stored frames (by value, from the file), the
    spacing twice the data's, every stored frame from ``first * 2`` a window; frame 0 pads before frame 0."""
    from lagfluid.data.datasets import TrajectoryWindows

    one = TrajectoryWindows(tiny_data, "train", history=2, first=first)
    two = TrajectoryWindows(tiny_data, "train", history=2, first=first, stride=2)
    with h5py.File(tiny_data / two.metadata["splits"]["train"][0], "r") as f:
        frames = f["00000/position"][()]
    stored = min(len(frames), two._uniform_frames(two.infos[0]))
    assert two._count(two.infos[0]) == stored - 2 * (1 + first) == one._count(one.infos[0]) - 1 - first
    for local in (0, 1, two._count(two.infos[0]) - 1):
        item, t = two[local], local + 2 * first
        nf = item.y.shape[0]
        history = [frames[max(t - 4, 0)], frames[t - 2]]
        np.testing.assert_array_equal(item.history.numpy(), np.stack(history, axis=1))
        np.testing.assert_array_equal(item.pos[:nf].numpy(), frames[t])
        np.testing.assert_array_equal(item.y.numpy(), frames[t + 2])
        assert int(item.frames_before) == min(t // 2, 2)
        assert int(item.step) == t * (int(one[0].step) // first)  # one[0] is stored frame `first`
        torch.testing.assert_close(item.frame_dt, 2 * one[0].frame_dt)
    with pytest.raises(LagfluidError, match="a whole number of stored frames >= 1: 0"):
        TrajectoryWindows(tiny_data, "train", history=2, stride=0)


def test_train_frame_stride_reaches_the_windows_and_a_bad_one_is_refused(tiny_data):
    train_items, valid_items = _trainable(frame_stride=2).datasets(tiny_data)
    assert train_items.stride == valid_items.stride == 2
    assert float(train_items[0].frame_dt) == pytest.approx(
        2 * float(_trainable().datasets(tiny_data)[0][0].frame_dt)
    )
    assert (
        _trainable(frame_stride=2).identity()["frame_stride"] == 2
    )  # a resume with another stride is refused
    assert "frame_stride" not in _trainable().identity()  # earlier checkpoints keep their identity
    for bad in (0, 1.5, True):
        with pytest.raises(ConfigError, match=f"train.frame_stride must be a whole number .*: {bad!r}$"):
            _trainable(frame_stride=bad)


@pytest.mark.skipif(not (SHIPPED / "gns.pt").is_file(), reason="no shipped GNS weights")
def test_the_shipped_weights_warn_once_outside_their_training_range(caplog):
    from lagfluid.models.checkpoint import read_checkpoint
    from lagfluid.tasks.config import build_simulator

    assert read_checkpoint(SHIPPED / "gns.pt")["meta"]["range"]["viscosity"] == [1e-06, 1e-06]
    overrides = ("model=gns", "scene=dam_small", "scene.params.viscosity=0.1")
    sim, state = build_simulator(_compose(*overrides)), build_initial_state(_compose(*overrides))
    sim.reset(state)
    sim.reset(state)
    said = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert said == [
        "model gns: the gns network was trained on viscosity 1e-06 m^2/s; this scene has 0.1: expect larger "
        "errors than its model card states"
    ]  # dt is the network's own frame spacing: never warned about


def test_the_unrolled_loss_windows_hold_u_minus_1_more_frames(tiny_data):
    h = SMALL["history"]
    train_items, _ = _trainable(unroll_loss=4).datasets(tiny_data)
    assert train_items[len(train_items) - 1].history.shape[1] == h + 3
    pushed = _trainable(unroll_loss=2, pushforward={"unrolls": [0, 3], "probs": [1, 1]})
    assert pushed.datasets(tiny_data)[0][0].history.shape[1] == h + 3  # the longer of the two
