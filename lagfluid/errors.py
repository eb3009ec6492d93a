"""Exceptions that the command line reports as one clear line (no traceback from deep inside torch)."""

from __future__ import annotations


class LagfluidError(Exception):
    """Base class of every error lagfluid raises on purpose for bad input or a failed run."""


class SceneError(LagfluidError, ValueError):
    """A scene or particle state is invalid (raised early, naming the bad value)."""


class ConfigError(LagfluidError, ValueError):
    """A configuration value is invalid (the message names the key and the value)."""


class RolloutError(LagfluidError, RuntimeError):
    """A rollout stopped by its guard: NaN/inf, a particle leaving the domain, Courant number too high.

    Attributes:
        kind: which guard test stopped it (``"non_finite"``, ``"left_domain"``, ``"courant"``), or None for
            other refusals (bad arguments, a resume that cannot continue).
    """

    GUARD_KINDS = ("non_finite", "left_domain", "courant")

    def __init__(self, message: str, kind: str | None = None) -> None:
        super().__init__(message)
        if kind is not None and kind not in self.GUARD_KINDS:
            raise ValueError(f"RolloutError kind must be one of {self.GUARD_KINDS} or None, got {kind!r}")
        self.kind = kind


class MetricInputError(LagfluidError, ValueError):
    """Arrays given to a metric have the wrong shape, are empty or do not correspond."""


class Terminated(KeyboardInterrupt):
    """The process received SIGTERM (a timeout, SLURM, ``docker stop``): stopped like Ctrl-C.

    A :class:`KeyboardInterrupt`, so every path that keeps a stopped run's outputs (``complete=false`` with
    the reason, metrics, preview) handles it the same way.
    """
