"""The Simulator contract: what a plugin must provide, and what the rollout and the tasks honour."""

import json

import pytest
import torch
from hydra import compose, initialize_config_dir

from lagfluid import registry
from lagfluid.errors import ConfigError
from lagfluid.models.mps_simulator import build_mps
from lagfluid.models.simulator import check_simulator
from lagfluid.physics.step_context import SplitStepFields
from lagfluid.rollout import rollout
from lagfluid.run import CONF_DIR
from lagfluid.scenes import build_scene
from lagfluid.state import ParticleState
from lagfluid.tasks.config import build_simulator
from lagfluid.tasks.simulate import simulate


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        return compose(config_name="config", overrides=list(overrides))


class FreeFall:
    """A minimal end-to-end simulator: exact free fall of the fluid at its own time step."""

    name = "free_fall"
    history_length = 2
    max_courant = None
    parameters = 0
    last_fields = None

    def __init__(self, dt=0.004):
        self.dt = dt
        self.last_info, self.last_timings, self.histories = {}, {}, []

    def reset(self, state, history=()):
        self.histories.append(list(history))

    def step(self, state, *, record=False):
        nf, dt = state.n_fluid, state.params.dt
        g = torch.tensor(state.params.gravity, dtype=state.dtype)
        pos, vel = state.pos.clone(), state.vel.clone()
        vel[:nf] += g * dt
        pos[:nf] += vel[:nf] * dt
        return ParticleState(
            pos=pos,
            vel=vel,
            ptype=state.ptype,
            params=state.params,
            time=state.time + dt,
            step=state.step + 1,
            check=False,
        )

    def attributes(self):
        return {}


def test_a_plugin_lacking_part_of_the_contract_is_named(monkeypatch):
    class Half:
        name, dt = "half", None

        def step(self, state):
            return state

    lacks = r"model 'half' built a Half that lacks history_length, max_courant, parameters"
    with pytest.raises(ConfigError, match=lacks):
        check_simulator(Half(), "half")
    monkeypatch.setitem(registry._REGISTERED, "half", lambda cfg: Half())
    with pytest.raises(ConfigError, match="lacks"):
        build_simulator(_compose("model.name=half"))
    bad = FreeFall(dt=-1.0)
    with pytest.raises(ConfigError, match=r"dt must be a time step > 0 \(s\) or None, got -1.0"):
        check_simulator(bad, "free_fall")


def test_the_rollout_hands_history_to_reset_and_fields_to_on_step():
    state = build_scene("dam", fluid_size=[3, 3, 3], tank_size=[8, 6])
    sim = FreeFall()
    earlier = [state, state]
    rollout(sim, state, 2, history=earlier)
    assert len(sim.histories[-1]) == 2 and sim.histories[-1][0] is state

    mps = build_mps(_compose())
    seen = []
    rollout(
        mps,
        state,
        4,
        on_step=lambda before, after, fields: seen.append((before.step, after.step, fields)),
        record_when=lambda s: s.step % 2 == 1,
    )
    assert [(b, a) for b, a, _ in seen] == [(0, 1), (1, 2), (2, 3), (3, 4)]
    assert [f is None for _, _, f in seen] == [True, False, True, False]
    assert isinstance(seen[1][2], SplitStepFields) and seen[1][2].pos_star.shape == (state.n_fluid, 3)


def test_simulate_runs_a_model_at_its_own_time_step(tmp_path, monkeypatch):
    monkeypatch.setitem(registry._REGISTERED, "free_fall", lambda cfg: FreeFall(dt=0.004))
    cfg = _compose("experiment=debug", "model.name=free_fall", "steps=5", f"out_dir={tmp_path}")
    metrics = simulate(cfg)
    assert metrics["dt"] == 0.004 and metrics["steps"] == 5 and metrics["parameters"] == 0
    assert json.loads((tmp_path / "metrics.json").read_text())["dt"] == 0.004
    with pytest.raises(ConfigError, match=r"steps by its own dt=0.004 s.*dt=0.001 cannot change that"):
        simulate(_compose("experiment=debug", "model.name=free_fall", "dt=0.001", f"out_dir={tmp_path}"))


def test_a_broken_plugin_is_one_clear_error(monkeypatch, tmp_path):
    import subprocess
    import sys
    from importlib import metadata

    from lagfluid.registry import ENTRY_POINT_GROUP, PluginError, get_simulator_factory

    ghost = metadata.EntryPoint(name="ghost", value="no_such_module:build", group=ENTRY_POINT_GROUP)
    real = metadata.entry_points
    monkeypatch.setattr(
        registry.metadata,
        "entry_points",
        lambda **kw: metadata.EntryPoints([ghost]) if kw.get("group") == ENTRY_POINT_GROUP else real(**kw),
    )
    with pytest.raises(PluginError, match=r"plugin 'ghost' \(lagfluid.simulators = 'no_such_module:build'\)"):
        get_simulator_factory("ghost")
    # a plugin whose config package is missing: the command line says so in one line, exit 2
    dist = tmp_path / "ghost-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: ghost\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[lagfluid.configs]\nghost = no_such_package.conf\n")
    env = {**__import__("os").environ, "PYTHONPATH": str(tmp_path)}
    out = subprocess.run(
        [sys.executable, "-m", "lagfluid.run", "model=mps", "--cfg", "job"],
        capture_output=True,
        text=True,
        env=env,
    )
    assert out.returncode == 2 and "plugin 'ghost': config package 'no_such_package.conf'" in out.stderr
    assert "Traceback" not in out.stderr
