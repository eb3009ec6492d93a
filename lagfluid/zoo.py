"""The public surface for a model plugin: everything a model outside lagfluid imports from it.

A plugin (``baselines/gns``, ``baselines/cconv``, the test plugin in ``tests/plugins/``, a third-party
package) imports lagfluid from here only; ``tests/test_layers.py`` holds the baselines and the test plugin to
it. What is not here is internal and may move. Nothing in lagfluid imports this module: it re-exports from
the layers below the tasks (``docs/architecture.md``). README's "Adding a model" says how the pieces are
registered.

The simulator (entry point ``lagfluid.simulators``: ``factory(cfg) -> Simulator``)
    ``Simulator``            the protocol a simulator implements: ``reset``, ``step``, ``dt``,
                             ``history_length``, ``max_courant``, ``parameters``, ``last_timings``,
                             ``last_info``, ``last_fields``, ``attributes``
    ``check_simulator``      the check the tasks run on a factory's simulator, naming what it lacks
    ``ParticleState``        what a step maps to the next: positions, velocities, pressure, types, params
    ``ParticleType``         particle classes of ``ParticleState.ptype`` (fluid, wall, dummy)
    ``SceneParams``          a scene's parameters: gravity, viscosity, density, ``dt``, ``l0``, ``dim``
    ``scene_params``         ``cfg`` -> the run's :class:`SceneParams` (``scene=`` with ``dt=`` applied)
    ``StageTimer``           seconds per named stage of a step, for ``last_timings`` (CUDA events on a GPU)

The rollout's hooks (optional simulator methods the tasks call when present; see :class:`Simulator`)
    ``rollout_memory()`` and ``restore_rollout_memory(state, memory)``: what a step carries beyond the state,
    so that ``resume=true`` continues bit for bit; ``amend_last_step(before, after)`` and
    ``last_step_learned``: ``model.exact_after`` replaced the step's result; ``memory_needed(state)``: peak
    bytes of a CPU rollout, for the memory check; ``predicts_pressure = False``: pictures colour by speed.
    ``rollout``              the one rollout loop (guard, timings, ``on_frame``/``on_step`` hooks)
    ``Guard``                the loop's checks: non-finite values, fluid leaving the domain, Courant number
    ``StepHook``             the type of ``on_step(before, after, fields)``
    ``memory_needed``        a simulator's own ``memory_needed`` if it has one, else MPS's estimate
    ``rollout_bytes``        peak bytes of a rollout with a neighbour radius and measured bytes per pair
    ``pair_bytes``           the bytes of the neighbour pairs alone

Exact stages after a model's step (``model.exact_after``, or called by a model itself)
    ``CollisionRule``        MPS's collision rule (velocity change of approaching close pairs)
    ``ExactPressure``        MPS's pressure projection: PPE and minimum-pressure gradient correction
    ``SplitStepSimulator``   the split-step scheme; ``exact_stages(state, pressure, iterations, relaxation)``
                             runs its collision and pressure stages on a model's positions and velocities
    ``SolverSettings``       the solver's coefficients (``cfg.solver``): radii, restitution, PPE settings
    ``ExactAfter``           a simulator followed by exact stages after each of its steps
    ``ExactAfterOptions``    which stages, how often, how relaxed (the ``model.exact_after`` node)
    ``with_exact_after``     a simulator wrapped as ``cfg.model.exact_after`` asks (itself when none is on)
    ``build_mps``            the MPS simulator of ``cfg`` (a warm start, a reference step)

Training (entry point ``lagfluid.trainables``: ``factory(cfg) -> {name: Trainable}``)
    ``Trainable``            the protocol of one trainable network: datasets, network, statistics, predict
    ``StepWindows``          a dataset of one-step pairs of the generated trajectories
    ``TrajectoryWindows``    a dataset of history windows (GNS-style) of the generated trajectories
    ``trajectory_windows``   :class:`TrajectoryWindows` of a split, expert datasets (DAgger) included
    ``step_windows``         :class:`StepWindows` of a split (a state and its next K solver steps), DAgger
                             datasets included (``ExpertStepWindows``: the model's states, MPS's steps)
    ``ExpertStepWindows``    those windows of a DAgger dataset
    ``HorizontalSymmetry``   one of a tank's 8 horizontal symmetries (x/y reflections, x/y swap): augmentation

Building blocks of a network and its step
    ``Standardizer``         ``(x - mean) / std`` with the statistics as buffers (in every ``state_dict``)
    ``make_mlp``             a shared MLP laid out as FGN's authors' (``0.weight``, ``2.weight``, ...)
    ``activation``           an activation module by name (``silu``, ``relu``, ...)
    ``parameter_count``      trainable parameters of a module
    ``semi_implicit_euler``  ``v += a dt; x += v dt``, the update a rollout applies
    ``acceleration_from_positions``  its inverse over three positions, a training target
    ``radius_graph``         the ``(2, E)`` edges of every ordered pair closer than a radius
    ``radius_graph_between``  the ``(2, E)`` pairs closer than a radius from one point set into another
    ``edge_vectors``         relative positions and distances of a graph's edges
    ``kernel``               the MPS weight ``re / r - 1`` of pair distances (0 beyond ``re``)
    ``device_constant``      a small constant tensor, cached per device and dtype
    ``pair_kernels``         compiled (numba) kernels: ``register(name, compiled=, torch=, module=)`` a
                             plugin's kernel with its two bodies, ``backend_for(name, *tensors)`` the body
                             that serves these tensors; ``load(module)`` and ``set_threads()`` in a
                             compiled body

Checkpoints (one file per network, tensors and plain values only)
    ``read_checkpoint``      load and check a checkpoint (format, model, kind, finite weights)
    ``save_checkpoint``      write one atomically
    ``network_payload``      the fields of a network's checkpoint
    ``export_weights``       a training run's checkpoints without optimizer state, to ship
    ``checkpoint_range``     the training range (``dt``, ``l0``, gravity, viscosity) a checkpoint records
    ``RangeWarner``          warns once per quantity of a scene outside a network's training range

Errors (each becomes one line on the command line)
    ``LagfluidError``        the base of all below
    ``ConfigError``          a bad option, naming the key and the value
    ``SceneError``           a scene that cannot be built
    ``RolloutError``         a rollout that cannot go on (blow-up, particle out of the domain, ...)
    ``CheckpointError``      a checkpoint that is unreadable, foreign or of another network
    ``MissingWeightsError``  a weights file that does not exist (the tables skip such a row, naming it)
"""

from __future__ import annotations

from lagfluid.data.datasets import StepWindows, TrajectoryWindows
from lagfluid.data.expert_windows import ExpertStepWindows, step_windows, trajectory_windows
from lagfluid.data.symmetry import HorizontalSymmetry
from lagfluid.device_constants import device_constant
from lagfluid.errors import ConfigError, LagfluidError, RolloutError, SceneError
from lagfluid.integrate import acceleration_from_positions, semi_implicit_euler
from lagfluid.memory import memory_needed, pair_bytes, rollout_bytes
from lagfluid.models.checkpoint import (
    CheckpointError,
    MissingWeightsError,
    checkpoint_range,
    export_weights,
    network_payload,
    read_checkpoint,
    save_checkpoint,
)
from lagfluid.models.exact_after import ExactAfter, ExactAfterOptions, with_exact_after
from lagfluid.models.layers import Standardizer, activation, make_mlp, parameter_count
from lagfluid.models.mps_simulator import build_mps
from lagfluid.models.simulator import Simulator, check_simulator
from lagfluid.models.trainable import Trainable
from lagfluid.models.training_range import RangeWarner
from lagfluid.neighbors import edge_vectors, pair_kernels, radius_graph, radius_graph_between
from lagfluid.physics.mps import CollisionRule, ExactPressure
from lagfluid.physics.operators import kernel
from lagfluid.physics.scheme import SplitStepSimulator
from lagfluid.physics.settings import SolverSettings
from lagfluid.physics.timing import StageTimer
from lagfluid.rollout import Guard, StepHook, rollout
from lagfluid.scenes import scene_params
from lagfluid.state import ParticleState, ParticleType, SceneParams

__all__ = [
    "CheckpointError",
    "CollisionRule",
    "ConfigError",
    "ExactAfter",
    "ExactAfterOptions",
    "ExactPressure",
    "ExpertStepWindows",
    "Guard",
    "HorizontalSymmetry",
    "LagfluidError",
    "MissingWeightsError",
    "ParticleState",
    "ParticleType",
    "RangeWarner",
    "RolloutError",
    "SceneError",
    "SceneParams",
    "Simulator",
    "SolverSettings",
    "SplitStepSimulator",
    "StageTimer",
    "Standardizer",
    "StepHook",
    "StepWindows",
    "Trainable",
    "TrajectoryWindows",
    "acceleration_from_positions",
    "activation",
    "build_mps",
    "check_simulator",
    "checkpoint_range",
    "device_constant",
    "edge_vectors",
    "export_weights",
    "kernel",
    "make_mlp",
    "memory_needed",
    "network_payload",
    "pair_bytes",
    "pair_kernels",
    "parameter_count",
    "radius_graph",
    "radius_graph_between",
    "read_checkpoint",
    "rollout",
    "rollout_bytes",
    "save_checkpoint",
    "scene_params",
    "semi_implicit_euler",
    "step_windows",
    "trajectory_windows",
    "with_exact_after",
]
