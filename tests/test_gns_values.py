"""GNS (baselines/gns) by value: the features of a hand-computed graph, the noise-corrected target and the
pushforward's windows on a trajectory of known acceleration, the simulator's step (seconds).

Every expected number is written out here, worked by hand from the positions (no helper of the package
computes an expectation): a change of sign, frame, feature or window shows as a wrong number.
"""

import math

import pytest
import torch
from omegaconf import OmegaConf
from torch_geometric.data import Batch, Data

import baselines.gns.trainable as gns_trainable
from baselines.gns.network import GNSNet
from baselines.gns.simulator import GNSSimulator
from baselines.gns.trainable import GNSTrainable, step_acceleration
from lagfluid.errors import ConfigError
from lagfluid.state import ParticleState, ParticleType, SceneParams

F64 = torch.float64
FLUID, WALL = int(ParticleType.FLUID), int(ParticleType.WALL)


def _t(rows):
    return torch.tensor(rows, dtype=F64)


# ------------------------------------------------------------------------------------------ the hand graph
# R = radius 2 x l0 0.1 = 0.2 m, frames 0.1 s apart, history H = 2, domain [0, 0.75] x [0, 0.6] x [0, 1].
# Particle rows: A, B fluid; W2 a wall out of everyone's reach; W1 a wall within R of A only
# (|W1 - A| = sqrt(0.05^2 + 0.15^2) = 0.158, |W1 - B| = sqrt(0.15^2 + 0.15^2) = 0.212, |A - B| = 0.1).
L0, DT = 0.1, 0.1
HAND_POS = _t([[0.50, 0.50, 0.10], [0.60, 0.50, 0.10], [0.10, 0.50, -0.05], [0.45, 0.50, -0.05]])
HAND_FLUID = torch.tensor([True, True, False, False])
HAND_BOUNDS = _t([[0.0, 0.0, 0.0], [0.75, 0.6, 1.0]])
# the fluid's frames t-2, t-1, t: velocities A (0.1, 0, -0.2), (0.2, 0, -0.3); B (0, 0.1, 0), (-0.1, 0.1, 0.4)
HAND_FRAMES = _t(
    [
        [[0.47, 0.50, 0.15], [0.48, 0.50, 0.13], [0.50, 0.50, 0.10]],
        [[0.61, 0.48, 0.06], [0.61, 0.49, 0.06], [0.60, 0.50, 0.10]],
    ]
)
VEL_MEAN, VEL_STD = [0.1, 0.0, -0.1], [0.5, 0.25, 2.0]
ACC_MEAN, ACC_STD = [1.0, 0.5, -2.0], [2.0, 4.0, 0.5]
# nodes: A, B, then W1 (particle row 3); W2 is not modelled
HAND_NODE_ROWS = [0, 1, 3]
HAND_NODES = _t(
    [
        # standardised velocities (v - mean) / std, oldest first | bounds: (x - lower) / R, (upper - x) / R,
        # clipped to [-1, 1] | type
        [0.0, 0.0, -0.05, 0.2, 0.0, -0.1, 1.0, 1.0, 0.5, 1.0, 0.5, 1.0, 0.0],  # A
        [-0.2, 0.4, 0.05, -0.4, 0.4, 0.25, 1.0, 1.0, 0.5, 0.75, 0.5, 1.0, 0.0],  # B
        [-0.2, 0.0, 0.05, -0.2, 0.0, 0.05, 1.0, 1.0, -0.25, 1.0, 0.5, 1.0, 1.0],  # W1: 0 m/s, below the floor
    ]
)
# (sender, receiver) in node indices -> (x_sender - x_receiver) / R and its norm; W1 receives nothing
HAND_EDGES = {
    (1, 0): [0.5, 0.0, 0.0, 0.5],  # B -> A
    (0, 1): [-0.5, 0.0, 0.0, 0.5],  # A -> B
    (2, 0): [-0.25, 0.0, -0.75, math.sqrt(0.625)],  # W1 -> A
}


def _hand_net(**options):
    """A GNS of history 2 and radius 2 l0 with the statistics above."""
    torch.manual_seed(0)
    net = GNSNet(latent=8, hidden=8, mlp_layers=1, blocks=1, history=2, radius=2.0, **options).to(F64)
    net.velocity.set(VEL_MEAN, VEL_STD)
    net.acceleration.set(ACC_MEAN, ACC_STD)
    net.frame_dt.fill_(DT)
    net.solver_dt.fill_(DT)
    return net.eval()


def _seen_by(net):
    """Record the network's inputs (nodes, edge_index, edges) of every forward call."""
    calls = []
    net.register_forward_pre_hook(lambda module, args: calls.append(args))
    return calls


def _assert_hand_graph(nodes, edge_index, edges):
    """The inputs of one forward call are the hand graph's (edges in any order)."""
    torch.testing.assert_close(nodes, HAND_NODES, rtol=0, atol=1e-12)
    got = {tuple(pair): edges[k] for k, pair in enumerate(edge_index.t().tolist())}
    assert set(got) == set(HAND_EDGES) and edge_index.shape[1] == len(HAND_EDGES)
    for pair, expected in HAND_EDGES.items():
        torch.testing.assert_close(got[pair], _t(expected), rtol=0, atol=1e-12, msg=f"edge {pair}")


def test_the_training_step_feeds_the_hand_graphs_node_and_edge_features():
    net = _hand_net()
    calls = _seen_by(net)
    step_acceleration(net, HAND_POS, HAND_FLUID, HAND_FRAMES, DT, L0, HAND_BOUNDS)
    assert len(calls) == 1
    _assert_hand_graph(*calls[0])


def test_the_network_sums_each_receivers_incoming_edges():
    """One block on the hand graph, written per node: A receives B's and W1's messages, W1 none."""
    net = _hand_net()
    calls = _seen_by(net)
    out = step_acceleration(net, HAND_POS, HAND_FLUID, HAND_FRAMES, DT, L0, HAND_BOUNDS)
    nodes, edge_index, edges = calls[0]
    pairs = [tuple(p) for p in edge_index.t().tolist()]
    v, e = net.node_encoder(nodes), net.edge_encoder(edges)
    block = net.processor[0]
    # phi_e([e, v_receiver, v_sender]) of each edge
    message = {(s, r): block.edge_mlp(torch.cat([e[k], v[r], v[s]])) for k, (s, r) in enumerate(pairs)}
    incoming = {
        0: message[(1, 0)] + message[(2, 0)],  # A <- B, W1
        1: message[(0, 1)],  # B <- A
        2: torch.zeros(8, dtype=F64),  # W1 <- nothing
    }
    latent = torch.stack([v[n] + block.node_mlp(torch.cat([v[n], incoming[n]])) for n in range(3)])
    torch.testing.assert_close(out, net.decoder(latent)[:2])


def test_the_simulator_feeds_the_same_features_and_steps_by_semi_implicit_euler():
    net = _hand_net()
    calls = _seen_by(net)
    # the network answers standardised accelerations: A (0.5, -0.25, 2) -> (2, -0.5, -1) m/s^2,
    # B (-1, 0, -2) -> (-1, 0.5, -3) m/s^2 (a * std + mean)
    answer = _t([[0.5, -0.25, 2.0], [-1.0, 0.0, -2.0], [9.0, 9.0, 9.0]])
    net.register_forward_hook(lambda module, args, out: answer)
    ptype = torch.tensor([FLUID, FLUID, WALL, WALL])
    params = SceneParams(dt=DT, l0=L0)

    def state_at(k, step):
        pos = HAND_POS.clone()
        pos[:2] = HAND_FRAMES[:, k]
        return ParticleState(pos, torch.zeros(4, 3, dtype=F64), ptype, params, bounds=HAND_BOUNDS, step=step)

    sim = GNSSimulator(net, None, "hand")
    sim.reset(state_at(2, 2), [state_at(0, 0), state_at(1, 1)])
    new = sim.step(state_at(2, 2))
    _assert_hand_graph(*calls[0])
    # v' = v + a dt: A (0.2, 0, -0.3) + (0.2, -0.05, -0.1), B (-0.1, 0.1, 0.4) + (-0.1, 0.05, -0.3);
    # x' = x + v' dt
    v_new = _t([[0.4, -0.05, -0.4], [-0.2, 0.15, 0.1]])
    torch.testing.assert_close(new.pos[:2], _t([[0.54, 0.495, 0.06], [0.58, 0.515, 0.11]]))
    torch.testing.assert_close(new.vel[:2], v_new)
    assert torch.equal(new.pos[2:], HAND_POS[2:])  # the walls never move
    history = sim.rollout_memory()["velocities"]  # the last H velocities, oldest first
    torch.testing.assert_close(history, torch.stack([_t([[0.2, 0.0, -0.3], [-0.1, 0.1, 0.4]]), v_new], 1))


# ------------------------------------------------------------------------------------------ noise, targets
# One fluid particle moving at constant acceleration a = (4, 0, -2) m/s^2, frames dt = 0.5 s apart:
# x_k = x0 + v0 t + a t^2 / 2 with x0 = (0, 0.3, 1), v0 = (1, 0, 0): x = 0.5 k + 0.5 k^2, z = 1 - 0.25 k^2
TRAJECTORY = _t(
    [
        [0.0, 0.3, 1.0],
        [1.0, 0.3, 0.75],
        [3.0, 0.3, 0.0],
        [6.0, 0.3, -1.25],
        [10.0, 0.3, -3.0],
        [15.0, 0.3, -5.25],
    ]
)
FRAME_DT = 0.5
WALL_POS = [5.0, 5.0, 5.0]  # out of reach: the graph does not matter here


def _window_item(last):
    """A training window whose last input frame is ``TRAJECTORY[last]``: history the frames before, the
    target ``TRAJECTORY[last + 1]``."""
    return Data(
        pos=torch.cat([TRAJECTORY[last : last + 1], _t([WALL_POS])]),
        ptype=torch.tensor([FLUID, WALL]),
        history=TRAJECTORY[:last].unsqueeze(0),
        y=TRAJECTORY[last + 1 : last + 2],
        frame_dt=_t([FRAME_DT]),
        dt=_t([0.1]),
        l0=_t([0.1]),
    )


def _trainable(**train):
    options = {"latent": 8, "hidden": 8, "mlp_layers": 1, "blocks": 1, "history": 2, "radius": 2.0}
    return GNSTrainable(OmegaConf.create({"model": {"gns": options}, "train": train}))


def _standardised(acc):
    return (_t(acc) - _t(ACC_MEAN)) / _t(ACC_STD)


def _record_steps(monkeypatch, net):
    """Replace the network step of training by one that records its (pos, window) and answers a = 0 m/s^2."""
    calls = []

    def step(net_, pos, fluid, frames, dt, l0, bounds, batch=None):
        assert dt == FRAME_DT and l0 == 0.1
        calls.append((pos.clone(), frames.clone()))
        return net.acceleration(torch.zeros(frames.shape[0], 3, dtype=F64))

    monkeypatch.setattr(gns_trainable, "step_acceleration", step)
    return calls


def test_the_target_of_a_clean_window_is_the_trajectorys_acceleration(monkeypatch):
    net = _hand_net()
    calls = _record_steps(monkeypatch, net)
    _, target = _trainable().predict(net, Batch.from_data_list([_window_item(2)]))
    torch.testing.assert_close(target, _standardised([[4.0, 0.0, -2.0]]))
    torch.testing.assert_close(calls[0][1], TRAJECTORY[None, 0:3])


def test_the_noisy_target_corrects_for_the_noise_of_the_last_input_frame(monkeypatch):
    """DeepMind's bookkeeping: inputs x + n, target frame y + n_last, so the target acceleration is
    a - (n_last - n_before_last) / dt^2 and the update from the noisy frames gives the true next velocity."""
    noise = _t([[[0.0, 0.0, 0.0], [0.01, -0.02, 0.005], [0.03, 0.01, -0.015]]])  # (Nf, H + 1, 3)
    asked = []

    def fixed_noise(shape, std_last, generator=None):
        asked.append((shape, std_last))
        return noise.float()  # as random_walk_noise: float32, cast to the window's dtype by the caller

    monkeypatch.setattr(gns_trainable, "random_walk_noise", fixed_noise)
    trainable = _trainable(noise_std=0.5)
    net = _hand_net()
    calls = _record_steps(monkeypatch, net)
    batch = Batch.from_data_list([_window_item(2)])
    _, clean = trainable.predict(net, batch)  # eval: no noise
    torch.testing.assert_close(clean, _standardised([[4.0, 0.0, -2.0]]))
    net.train()
    _, target = trainable.predict(net, batch)
    assert asked == [((1, 3, 3), 0.5 * 0.1)]  # noise_std in l0, at the last input frame
    # (y + n2 - 2 (x2 + n2) + x1 + n1) / dt^2 = a - (n2 - n1) / dt^2 = (4 - 0.02 / 0.25, 0 - 0.03 / 0.25,
    # -2 + 0.02 / 0.25)
    torch.testing.assert_close(target, _standardised([[3.92, -0.12, -1.92]]), rtol=0, atol=1e-6)
    pos, window = calls[-1]
    noisy = _t([[[0.0, 0.3, 1.0], [1.01, 0.28, 0.755], [3.03, 0.31, -0.015]]])
    torch.testing.assert_close(window, noisy, rtol=0, atol=1e-7)
    torch.testing.assert_close(pos, _t([[3.03, 0.31, -0.015], WALL_POS]), rtol=0, atol=1e-7)


@pytest.mark.parametrize(
    ("unroll", "windows", "target"),
    [
        # no unroll: the last H + 1 stored frames
        (0, [[3, 6, 10]], [4.0, 0.0, -2.0]),
        # one step from frames 1..3 (a = 0: x' = 2 x_t - x_{t-1} = 9, z' = -2.5), then the learning step
        (1, [[1, 3, 6], [3, 6, 9]], [(15 - 18 + 6) / 0.25, 0.0, (-5.25 + 5 - 1.25) / 0.25]),
        # two steps from frames 0..2: x 5, 7; z -0.75, -1.5
        (2, [[0, 1, 3], [1, 3, 5], [3, 5, 7]], [(15 - 14 + 5) / 0.25, 0.0, (-5.25 + 3 - 0.75) / 0.25]),
    ],
)
def test_the_pushforward_starts_unroll_frames_before_the_last(monkeypatch, unroll, windows, target):
    """Windows of H + K + 1 = 5 frames (x 0, 1, 3, 6, 10), K = 2; the model's steps answer a = 0 m/s^2.

    ``windows`` lists the x of each network call's window (the unrolled ones, then the learning step); the
    target is the true next frame (x 15, z -5.25) against the model's own last two frames.
    """
    # z of each frame by its x: the stored frames', then the model's (z' = 2 z_t - z_{t-1})
    z_of = {0: 1.0, 1: 0.75, 3: 0.0, 6: -1.25, 10: -3.0, 5: -0.75, 7: -1.5, 9: -2.5}
    probs = [float(unroll == k) for k in range(3)]  # always this unroll
    trainable = _trainable(pushforward={"unrolls": [0, 1, 2], "probs": probs})
    net = _hand_net().train()
    calls = _record_steps(monkeypatch, net)
    _, got = trainable.predict(net, Batch.from_data_list([_window_item(4)]))
    assert len(calls) == len(windows)
    for (pos, window), xs in zip(calls, windows, strict=True):
        expected = _t([[[x, 0.3, z_of[x]] for x in xs]])
        torch.testing.assert_close(window, expected, msg=f"window {xs}")
        torch.testing.assert_close(pos, _t([[xs[-1], 0.3, z_of[xs[-1]]], WALL_POS]))
    torch.testing.assert_close(got, _standardised([target]))


@pytest.mark.parametrize(
    ("steps", "windows", "targets"),
    [
        # the one-step loss: the window of the last H + 1 stored frames, the true acceleration
        (1, [[3, 6, 10]], [[4.0, 0.0, -2.0]]),
        # from frames 1..3: the true acceleration, then the model's frame x 9, z -2.5 (a = 0) against the true
        # frame 5: ((15 - 18 + 6) / 0.25, 0, (-5.25 + 5 - 1.25) / 0.25)
        (2, [[1, 3, 6], [3, 6, 9]], [[4.0, 0.0, -2.0], [12.0, 0.0, -6.0]]),
        # from frames 0..2: the model's x 5, 7 (z -0.75, -1.5) against the true frames 4 (x 10) and 5 (x 15)
        (3, [[0, 1, 3], [1, 3, 5], [3, 5, 7]], [[4.0, 0.0, -2.0], [12.0, 0.0, -6.0], [24.0, 0.0, -12.0]]),
        # the window holds H + 2 earlier frames: at most 3 steps
        (5, [[0, 1, 3], [1, 3, 5], [3, 5, 7]], [[4.0, 0.0, -2.0], [12.0, 0.0, -6.0], [24.0, 0.0, -12.0]]),
    ],
)
def test_the_unrolled_loss_steps_the_model_from_u_minus_1_frames_before(monkeypatch, steps, windows, targets):
    """``train.unroll_loss`` U: U network calls, each target the model's last two frames to the true next."""
    z_of = {0: 1.0, 1: 0.75, 3: 0.0, 6: -1.25, 10: -3.0, 5: -0.75, 7: -1.5, 9: -2.5}
    trainable = _trainable(unroll_loss=steps)
    net = _hand_net().train()
    calls = _record_steps(monkeypatch, net)
    _, got = trainable.predict(net, Batch.from_data_list([_window_item(4)]))
    assert len(calls) == len(windows)
    for (pos, window), xs in zip(calls, windows, strict=True):
        torch.testing.assert_close(window, _t([[[x, 0.3, z_of[x]] for x in xs]]), msg=f"window {xs}")
        torch.testing.assert_close(pos, _t([[xs[-1], 0.3, z_of[xs[-1]]], WALL_POS]))
    torch.testing.assert_close(got, _standardised(targets))
    net.eval()  # outside training: the one-step loss
    assert trainable.predict(net, Batch.from_data_list([_window_item(4)]))[1].shape == (1, 3)


def test_the_unrolled_loss_reaches_a_steps_weights_through_the_later_steps_positions():
    """The second step's target is made of the first step's prediction: it carries that step's gradient."""
    net = _hand_net().train()
    _, target = _trainable(unroll_loss=2).predict(net, Batch.from_data_list([_window_item(4)]))
    params = [p for p in net.parameters() if p.requires_grad]

    def gradient(row):
        grads = torch.autograd.grad(target[row].sum(), params, retain_graph=True, materialize_grads=True)
        return sum(float(g.abs().sum()) for g in grads)

    assert gradient(0) == 0.0  # the stored frames' target
    assert gradient(1) > 0  # the model's first step moved the second step's start
    _, one_step = _trainable().predict(net, Batch.from_data_list([_window_item(4)]))
    assert not one_step.requires_grad


@pytest.mark.parametrize("bad", [0, 1.5, True, "2"])
def test_a_bad_unroll_loss_is_refused_by_name(bad):
    with pytest.raises(
        ConfigError, match=f"train.unroll_loss must be a whole number of model steps >= 1: {bad!r}$"
    ):
        _trainable(unroll_loss=bad)
    assert _trainable(unroll_loss=3).identity()["unroll_loss"] == 3
    assert "unroll_loss" not in _trainable().identity()  # earlier checkpoints keep their identity
