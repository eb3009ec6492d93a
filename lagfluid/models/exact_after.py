"""``model.exact_after``: MPS's exact collision rule and/or pressure projection after an end-to-end step.

Any simulator (GNS, CConv, DeepLagrangianFluids' CConv, a plugin) can be followed, step by step, by the
exact stages of the split-step scheme, run on the positions and velocities its step returned::

    x, v   = network step(x^n, v^n, ...)                      the model's own step, by its own dt
    repeat K times:
        v' = collision(x, v) ;  x += (v' - v) dt ;  v = v'    collision: true  (the MPS rule)
        p  = PPE(x, v) ;  a_p = -grad_min(p) / rho            pressure: true   (PPE + minimum-pressure
        v += w a_p dt ;  x += w a_p dt^2                                         gradient correction)

It is the MPS form of Neural SPH's relaxation (Toshev et al., ICML 2024), which shifts a learned step's
positions by a few SPH pressure iterations. The stages are the solver's own (:class:`CollisionRule`,
:class:`ExactPressure` and the updates of :class:`~lagfluid.physics.scheme.SplitStepSimulator`, through its
:meth:`~lagfluid.physics.scheme.SplitStepSimulator.exact_stages`): no second copy of the rule or the PPE.

**The time step.** The stages use the ``dt`` the model steps by (GNS 8 ms, CConv 2 ms, DeepLagrangian-
Fluids' CConv 20 ms). The PPE's source is ``-gamma_div div(v)/dt + gamma_n (n - n0)/(dt^2 n0)``, so its
pressure scales as ``1/dt^2``: the correction's displacement ``a_p dt^2`` does not depend on ``dt`` (one
projection removes the same share of a density error whatever ``dt``), the velocity it leaves,
``a_p dt``, is that displacement over ``dt``. What a longer step costs is reach: the stages see the
particles where the network left them, so a step that carries a particle past the collision radius
(0.92 l0) or into a wall's layers before they run is not undone, and a pair left very close can get the
minimum-pressure gradient's ``1/r^2`` push in one piece (the collision rule, run first, slows approaching
pairs). Measured on the dam at 20 ms: the projection alone after DeepLagrangianFluids' CConv threw a
particle out of the tank at step 19; with the collision rule before it the run completes
(``benchmarks/results/exact_after.md``). ``iterations`` K > 1 repeat
the stages at the corrected state; with MPS's source, whose divergence term sees the velocity the last
projection left, a second projection in the same step finds little or nothing to do (on a compressed
block at rest its pressure clamps to 0), so a relaxation ``w`` < 1 mostly scales the one correction.

**The model's memory.** A model that carries state between steps beyond the particles (GNS's history of
velocities ``(x_t - x_{t-1}) / dt``) is told of the correction by ``amend_last_step(before, after)``, so
its next step sees the rollout's stored positions (a model with ``rollout_memory`` and no
``amend_last_step`` is refused). A step that is not the model's own (GNS's MPS warm-start frames:
``last_step_learned`` false) is left as it is. CConv carries nothing beyond the state.

**Labels.** The wrapper's ``name`` is the model's with what runs after it (``gns + exact collision + MPS
pressure (K=3, w=0.5)``): rollout.h5, metrics.json and the tables never show such a run as the plain model.
Its timings add the stages' (``exact_collision``, ``exact_pressure_assembly``, ``exact_pressure_solve``,
``exact_correction``; their neighbour search adds to ``neighbors``), so Table 2 prices it with them.

Config (``conf/config.yaml``, every model)::

    model.exact_after: {collision: false, pressure: false, iterations: 1, relaxation: 1.0}
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from lagfluid.errors import ConfigError, RolloutError
from lagfluid.models.simulator import Simulator
from lagfluid.physics.mps import CollisionRule, ExactPressure
from lagfluid.physics.scheme import SplitStepSimulator
from lagfluid.physics.settings import MPSConstants, SolverSettings
from lagfluid.state import ParticleState

KEY = "model.exact_after"
_CONSTANTS = "exact_after_constants"  # rollout_memory's key of the exact stages' n0, n0_lap, lambda


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


@dataclass(frozen=True)
class ExactAfterOptions:
    """Which exact stages run after each step of a model, and how often.

    Attributes:
        collision: the MPS collision rule (:class:`~lagfluid.physics.mps.CollisionRule`).
        pressure: the PPE and the minimum-pressure gradient correction
            (:class:`~lagfluid.physics.mps.ExactPressure`).
        iterations: K, how many times the stages run after each step (>= 1).
        relaxation: w in (0, 1], the factor of the pressure correction.
    """

    collision: bool = False
    pressure: bool = False
    iterations: int = 1
    relaxation: float = 1.0

    def __post_init__(self) -> None:
        """Refuse a bad value, naming the key."""
        for key in ("collision", "pressure"):
            if not isinstance(getattr(self, key), bool):
                raise ConfigError(f"{KEY}.{key} must be true or false, got {getattr(self, key)!r}")
        k, w = self.iterations, self.relaxation
        if not (isinstance(k, int) and not isinstance(k, bool) and k >= 1):
            raise ConfigError(f"{KEY}.iterations must be a whole number >= 1, got {k!r}")
        if not (_is_number(w) and 0 < w <= 1):
            raise ConfigError(f"{KEY}.relaxation must be a number in (0, 1], got {w!r}")
        if not self.enabled and (k != 1 or w != 1):
            raise ConfigError(
                f"{KEY}.iterations={k} / relaxation={w} repeat or scale exact stages, but none is on: set "
                f"{KEY}.collision=true and/or {KEY}.pressure=true"
            )
        if not self.pressure and w != 1:
            raise ConfigError(
                f"{KEY}.relaxation={w} scales the pressure correction, but {KEY}.pressure is false"
            )

    @classmethod
    def from_config(cls, node: Any) -> ExactAfterOptions:
        """The options of a ``model.exact_after`` node (a mapping; absent or null: all off).

        Raises:
            ConfigError: not a mapping, an unknown key or a bad value.
        """
        if node is None:
            return cls()
        if isinstance(node, DictConfig):
            node = OmegaConf.to_container(node, resolve=True)
        if not isinstance(node, Mapping):
            raise ConfigError(f"{KEY} must be a mapping of {', '.join(cls.keys())}, got {node!r}")
        unknown = sorted(set(node) - set(cls.keys()))
        if unknown:
            names = ", ".join(map(repr, unknown))
            raise ConfigError(f"{KEY} has no key {names}; keys: {', '.join(cls.keys())}")
        values = dict(node)
        if _is_number(values.get("relaxation")):
            values["relaxation"] = float(values["relaxation"])  # YAML's 1 is an int
        return cls(**values)

    @staticmethod
    def keys() -> tuple[str, ...]:
        """The keys of the node, in order."""
        return tuple(f.name for f in dataclasses.fields(ExactAfterOptions))

    @property
    def enabled(self) -> bool:
        """Whether any exact stage runs."""
        return self.collision or self.pressure

    def describe(self) -> str:
        """What runs after the step: ``exact collision + MPS pressure (K=3, w=0.5)``; '' when nothing."""
        named = ((self.collision, "exact collision"), (self.pressure, "MPS pressure"))
        stages = [name for on, name in named if on]
        text = " + ".join(stages)
        if self.iterations != 1 or self.relaxation != 1:
            text += f" (K={self.iterations}, w={self.relaxation:g})"
        return text

    def label(self, base: str) -> str:
        """``base`` with what runs after it: ``gns + exact collision``; ``base`` itself when nothing does."""
        return f"{base} + {self.describe()}" if self.enabled else base

    def attributes(self) -> dict[str, Any]:
        """The options as rollout attributes (``exact_after_collision``, ...)."""
        return {f"exact_after_{k}": v for k, v in dataclasses.asdict(self).items()}


class ExactAfter:
    """A :class:`~lagfluid.models.simulator.Simulator` that runs exact stages after each step of another.

    See the module doc. ``dt``, ``history_length``, ``max_courant`` and ``parameters`` are the model's.

    Args:
        model: the end-to-end simulator.
        options: the stages to run (at least one).
        settings: the solver's coefficients (``cfg.solver``): the stages' radii, restitution, PPE.

    Raises:
        ConfigError: no stage is on, or the model carries memory between steps (``rollout_memory``) but
            cannot be told of a correction (no ``amend_last_step``).
    """

    def __init__(self, model: Simulator, options: ExactAfterOptions, settings: SolverSettings) -> None:
        if not options.enabled:
            raise ConfigError(f"{KEY}: no exact stage is on (collision, pressure)")
        if hasattr(model, "rollout_memory") and not hasattr(model, "amend_last_step"):
            raise ConfigError(
                f"{KEY} cannot run after model '{model.name}': it carries memory between steps "
                "(rollout_memory) and has no amend_last_step(before, after) to update it after a correction"
            )
        self.model = model
        self.options = options
        self.name = options.label(model.name)
        self.dt = model.dt
        self.history_length = model.history_length
        self.max_courant = model.max_courant
        self.last_fields: Any | None = None
        collision = CollisionRule() if options.collision else None
        pressure = ExactPressure() if options.pressure else None
        self.exact = SplitStepSimulator(self.name, settings, None, collision, pressure)
        self._ran = False  # whether the last step ran the exact stages

    @property
    def parameters(self) -> int:
        """The model's trainable parameters (the exact stages have none)."""
        return self.model.parameters

    @property
    def last_step_learned(self) -> bool:
        """Whether the last step was the model's own, followed by the stages (GNS's MPS warm start is not).

        A DAgger rollout of this hybrid labels only such steps (:mod:`lagfluid.tasks.generate.expert`).
        """
        return self._ran

    @property
    def last_timings(self) -> dict[str, float]:
        """The model's timings, the exact stages' added (``exact_<stage>``; their search to ``neighbors``)."""
        timings = dict(self.model.last_timings)
        if self._ran:
            for name, seconds in self.exact.last_timings.items():
                key = name if name == "neighbors" else f"exact_{name}"
                timings[key] = timings.get(key, 0.0) + seconds
        return timings

    @property
    def last_info(self) -> dict[str, float]:
        """The model's diagnostics and the exact stages' (``collisions``, ``ppe_iterations``, ...)."""
        return {**self.model.last_info, **(self.exact.last_info if self._ran else {})}

    def reset(self, state: ParticleState, history: Sequence[ParticleState] = ()) -> None:
        """Reset the model and the exact stages (constants, neighbour list) for ``state``."""
        self.model.reset(state, history)
        self.exact.reset(state)
        self._ran = False

    @torch.no_grad()
    def step(self, state: ParticleState, *, record: bool = False) -> ParticleState:
        """The model's step, then the exact stages on its positions and velocities (module doc)."""
        new = self.model.step(state, record=record)
        self.last_fields = self.model.last_fields
        self._ran = bool(getattr(self.model, "last_step_learned", True))
        if not self._ran:
            return new
        o = self.options
        # the PPE starts from the last solved pressure, which the state the step began from carries
        corrected = self.exact.exact_stages(new, state.pressure, o.iterations, o.relaxation)
        amend = getattr(self.model, "amend_last_step", None)
        if amend is not None:
            amend(state, corrected)
        return corrected

    def attributes(self) -> dict[str, Any]:
        """The model's attributes, its name (``base_model``) and the options (``exact_after_*``)."""
        return {**self.model.attributes(), "base_model": self.model.name, **self.options.attributes()}

    # A resumed run resets a simulator with a history at the checkpoint's state: the stages' constants
    # (n0_from=initial: the first frame's) travel with the model's memory so that it continues bit for bit.
    def rollout_memory(self) -> dict[str, torch.Tensor]:
        """The model's ``rollout_memory()`` (if any) and the exact stages' constants."""
        memory = dict(self.model.rollout_memory()) if hasattr(self.model, "rollout_memory") else {}
        c = self.exact.constants
        if c is not None:
            memory[_CONSTANTS] = torch.tensor([c.n0, c.n0_lap, c.lam], dtype=torch.float64)
        return memory

    def restore_rollout_memory(self, state: ParticleState, memory: dict[str, torch.Tensor]) -> None:
        """Take :meth:`rollout_memory`'s ``memory`` back (after :meth:`reset`).

        Raises:
            RolloutError: the memory holds the model's part but the model cannot take it back.
        """
        own = {k: v for k, v in memory.items() if k != _CONSTANTS}
        if own:
            restore = getattr(self.model, "restore_rollout_memory", None)
            if restore is None:
                raise RolloutError(f"model '{self.model.name}' cannot restore its rollout memory")
            restore(state, own)
        if _CONSTANTS in memory:
            n0, n0_lap, lam = memory[_CONSTANTS].tolist()
            self.exact.constants = MPSConstants(n0, n0_lap, lam)


def with_exact_after(simulator: Simulator, cfg: Any) -> Simulator:
    """``simulator`` followed by the exact stages of ``cfg.model.exact_after``; itself when none is on.

    Raises:
        ConfigError: a bad ``model.exact_after`` (:meth:`ExactAfterOptions.from_config`).
    """
    options = ExactAfterOptions.from_config(cfg.model.get("exact_after"))
    if not options.enabled:
        return simulator
    return ExactAfter(simulator, options, SolverSettings.from_config(cfg.solver))
