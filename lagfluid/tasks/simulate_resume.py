"""``task=simulate resume=true``: continue a killed or stopped run from its last checkpoint.

While a run goes, :class:`RolloutCheckpoint` saves ``out_dir/resume.pt`` at a stored frame at most every
``checkpoint_every_s`` seconds (atomically: a kill -9 mid-save keeps the previous one): the state at full
precision, the ``history_length`` states before it (GNS's velocity history), the frames written so far, the
per-step record and the frame metrics. A run stopped by Ctrl-C or SIGTERM saves its last stored frame before
it exits (:meth:`RolloutCheckpoint.save_latest`), so it continues even when it stopped before its first
periodic save. A resumed run

1. refuses a command that would compute something else (every config key but ``steps``, ``resume``,
   ``progress``, ``threads``, ``checkpoint_every_s`` and ``out_dir`` must match; the message names the keys),
2. resets the simulator at the scene's start as the uninterrupted run did (constants such as
   ``n0_from=initial`` come from frame 0), then, for a simulator with a history, at the checkpoint's state
   with the states before it and what it carried between steps (``rollout_memory``, see
   :class:`~lagfluid.models.simulator.Simulator`),
3. reopens the partial trajectory (``rollout.part.h5.part`` after a kill -9, ``rollout.h5`` with
   ``complete=false`` after Ctrl-C, SIGTERM or a guard stop), drops frames written after the checkpoint, and
   steps on: frames and guard checks fall on the same steps as one run's, so the result is the same file
   (``tests/test_simulate_resume.py`` kills a run with SIGKILL and compares).

The checkpoint is removed when the run completes.
"""

from __future__ import annotations

import json
import os
import time
from collections import deque
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from lagfluid.errors import RolloutError
from lagfluid.models.exact_after import ExactAfterOptions
from lagfluid.state import ParticleState

CHECKPOINT = "resume.pt"
# keys a resumed run may change: they do not change what is computed (steps may grow to extend a run)
FREE_KEYS = ("steps", "resume", "progress", "threads", "checkpoint_every_s", "out_dir")
_STATE_FIELDS = ("pos", "vel", "pressure")


def run_settings(cfg: DictConfig) -> dict[str, Any]:
    """The resolved config of a run without :data:`FREE_KEYS`: what a resumed run must repeat.

    ``model.exact_after`` is left out while no stage is on: a run checkpointed before the key existed
    computes the same and resumes.
    """
    settings = OmegaConf.to_container(cfg, resolve=True)
    assert isinstance(settings, dict)
    for key in FREE_KEYS:
        settings.pop(key, None)
    model = settings.get("model")
    if isinstance(model, dict) and not ExactAfterOptions.from_config(model.get("exact_after")).enabled:
        model.pop("exact_after", None)
    return settings


def _flatten(value: Any, prefix: str = "") -> dict[str, Any]:
    if isinstance(value, dict):
        out: dict[str, Any] = {}
        for key, item in value.items():
            out.update(_flatten(item, f"{prefix}{key}."))
        return out
    return {prefix.rstrip("."): value}


def settings_differences(saved: dict[str, Any], now: dict[str, Any]) -> list[str]:
    """``key: saved -> now`` for every config value that differs (dotted keys, sorted)."""
    a, b = _flatten(saved), _flatten(now)
    return [f"{k}: {a.get(k)!r} -> {b.get(k)!r}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]


def _state_fields(state: ParticleState) -> dict[str, Any]:
    fields = {name: getattr(state, name).detach().cpu().clone() for name in _STATE_FIELDS}
    return {**fields, "time": float(state.time), "step": int(state.step)}


def _lengths(value: Any) -> Any:
    """The length of every list and the keys of every dict in ``value`` (nested): what :func:`_cut` keeps."""
    if isinstance(value, dict):
        return {k: _lengths(v) for k, v in value.items()}
    if isinstance(value, list):
        return len(value)
    return None


def _cut(value: Any, lengths: Any) -> Any:
    """``value`` as it was when :func:`_lengths` measured it, for lists that have only grown since."""
    if isinstance(value, dict):
        return {k: _cut(value[k], n) for k, n in lengths.items()}
    if isinstance(value, list):
        return value[:lengths]
    return value


def _plain(value: Any) -> Any:
    """``value`` with numpy and 0-d tensor scalars as numbers (``torch.load(weights_only=True)`` reads it)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, torch.Tensor):
        return value.item()
    if isinstance(value, torch.Tensor) and value.dim() == 0:
        return value.item()
    return value


class RolloutCheckpoint:
    """Saves a running simulation's ``resume.pt`` and restores one.

    Args:
        out_dir: the run's folder.
        settings: :func:`run_settings` of the run.
        history_length: the simulator's ``history_length`` H (states kept before the checkpoint's).
        every_s: seconds between saves (0: at every stored frame).
    """

    def __init__(self, out_dir: Path, settings: dict[str, Any], history_length: int, every_s: float) -> None:
        if not every_s >= 0:
            raise RolloutError(f"checkpoint_every_s must be >= 0 seconds, got {every_s}")
        self.path = out_dir / CHECKPOINT
        self.settings, self.every_s = settings, float(every_s)
        self.history_length = int(history_length)
        self.before: deque[ParticleState] = deque(maxlen=max(self.history_length, 1))
        self.memory: Any = None  # the simulator's rollout_memory(), if it has one (see Simulator)
        self.stepped = False  # a step was taken in this process: the start itself is never saved
        self.last_save = time.perf_counter()
        # The last frame that could be saved, as maybe_save saw it, for save_latest; and the frames of the
        # last save. States are kept by reference: a step makes a new state (the history relies on it too).
        self.latest: dict[str, Any] | None = None
        self.saved_frames = -1

    def on_step(self, before: ParticleState, after: ParticleState, fields: Any) -> None:
        """Remember the states before the current one (a rollout ``on_step`` hook)."""
        self.stepped = True
        if self.history_length:
            self.before.append(before)

    def maybe_save(self, state: ParticleState, frames: int, extra: dict[str, Any]) -> None:
        """Save after a stored frame when ``every_s`` has passed (and the history is complete).

        Otherwise remember the frame for :meth:`save_latest`.

        Args:
            state: the frame just stored.
            frames: frames in the trajectory file, this one included.
            extra: what the task restores besides the state (the record, its metrics' state); its lists may
                grow after this call (the rollout's record does), dicts may gain keys: what they hold now is
                what is saved.
        """
        if not self.stepped or len(self.before) < self.history_length:  # never the start itself
            return
        memory = self.memory() if self.memory else {}
        self.latest = {
            "state": state,
            "frames": int(frames),
            "history": list(self.before)[-self.history_length :] if self.history_length else [],
            "memory": {k: v.detach().clone() for k, v in memory.items()},  # a step may change it in place
            "extra": extra,
            "lengths": _lengths(extra),
        }
        if time.perf_counter() - self.last_save >= self.every_s:
            self.save_latest()

    def save_latest(self) -> None:
        """Save the last frame :meth:`maybe_save` saw, unless saved already (also on Ctrl-C and SIGTERM)."""
        latest = self.latest
        if latest is None or latest["frames"] == self.saved_frames:
            return
        payload = {
            "settings": json.dumps(self.settings, sort_keys=True, default=str),
            "frames": latest["frames"],
            "state": _state_fields(latest["state"]),
            "history": [_state_fields(s) for s in latest["history"]],
            "memory": {k: v.cpu() for k, v in latest["memory"].items()},
            "extra": _plain(_cut(latest["extra"], latest["lengths"])),
        }
        tmp = self.path.with_name(self.path.name + ".part")
        torch.save(payload, tmp)
        os.replace(tmp, self.path)  # a kill mid-save keeps the previous checkpoint
        self.saved_frames = latest["frames"]
        self.last_save = time.perf_counter()

    def remove(self) -> None:
        """Forget the checkpoint (the run completed, or a fresh run starts in its folder)."""
        self.path.unlink(missing_ok=True)
        self.path.with_name(self.path.name + ".part").unlink(missing_ok=True)

    def load(
        self, start: ParticleState
    ) -> tuple[ParticleState, list[ParticleState], dict[str, Any], int, dict[str, Any]]:
        """The checkpoint's state and history (``start`` with the saved fields), memory, frames and extra.

        Raises:
            RolloutError: no checkpoint in the folder, an unreadable one, or one of a run with other settings.
        """
        if not self.path.is_file():
            raise RolloutError(
                f"resume=true: nothing to resume in {self.path.parent}: no {CHECKPOINT} (the run there "
                "completed, or stopped before it stored a frame after its start and its history: run it "
                "again without resume=true)"
            )
        try:
            saved = torch.load(self.path, map_location="cpu", weights_only=True)
            saved_settings = json.loads(saved["settings"])
        except Exception as err:  # a damaged file, whatever the failure inside torch
            raise RolloutError(f"resume=true: cannot read {self.path}: {type(err).__name__}: {err}") from err
        now = json.loads(json.dumps(self.settings, sort_keys=True, default=str))
        differences = settings_differences(saved_settings, now)
        if differences:
            raise RolloutError(
                f"resume=true: the run in {self.path.parent} was made with other settings "
                f"({'; '.join(differences[:5])}{' ...' if len(differences) > 5 else ''}); "
                "repeat its command (steps may change) or start a fresh run without resume=true"
            )

        def restored(fields: dict[str, Any]) -> ParticleState:
            tensors = {k: fields[k].to(device=start.device, dtype=start.dtype) for k in _STATE_FIELDS}
            return ParticleState(
                tensors["pos"],
                tensors["vel"],
                start.ptype,
                start.params,
                tensors["pressure"],
                time=float(fields["time"]),
                step=int(fields["step"]),
                bounds=start.bounds,
                check=False,
            )

        history = [restored(h) for h in saved["history"]]
        memory = saved.get("memory", {})
        return restored(saved["state"]), history, memory, int(saved["frames"]), saved["extra"]
