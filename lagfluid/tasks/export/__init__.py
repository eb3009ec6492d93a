"""Looking at rollouts outside lagfluid: a ParaView time series, a GIF or an MP4.

``python -m lagfluid.run task=export run=DIR [format=vtu|gif|mp4]`` reads ``DIR/rollout.h5`` (or the rollout
file ``run`` names) and writes, beside it,

* ``format=vtu`` (:mod:`lagfluid.tasks.export.vtk`): ``DIR/paraview/rollout.pvd``, one ``frame_NNNNN.vtu`` per
  stored frame (fluid points with velocity, speed, pressure, number density n/n0 and particle type) and
  ``boundary.vtu`` (the static wall and dummy particles, written once): open the ``.pvd`` in ParaView;
* ``format=gif`` / ``mp4`` (:mod:`lagfluid.tasks.export.animation`): ``DIR/rollout.gif`` (``.mp4`` needs
  ffmpeg), the fluid coloured by ``animation.color`` (pressure or speed) over the tank's walls.

``task=simulate export=vtu`` (or gif, mp4) exports the run it has just written; ``task=evaluate`` writes
``side_by_side.gif``, the model beside the MPS reference
(:func:`lagfluid.tasks.export.animation.side_by_side`).
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from lagfluid.errors import ConfigError

FORMATS = ("vtu", "gif", "mp4")


def rollout_path(run: str | Path) -> Path:
    """The rollout file of ``run``: the file itself, or ``run/rollout.h5`` for a run folder.

    Raises:
        ConfigError: ``run`` is neither (the message names it).
    """
    path = Path(run)
    if path.is_dir():
        path = path / "rollout.h5"
    if not path.is_file():
        raise ConfigError(
            f"run={run}: no rollout there (a run folder with rollout.h5, or a rollout .h5 file)"
        )
    return path


def check_format(fmt: object) -> str:
    """``fmt`` when it is an export format this machine can write.

    Raises:
        ConfigError: an unknown format, or mp4 without ffmpeg (checked before a run, not after it).
    """
    if fmt not in FORMATS:
        raise ConfigError(f"export format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if fmt == "mp4":
        import shutil

        if shutil.which("ffmpeg") is None:
            raise ConfigError("format mp4 needs ffmpeg on the PATH (not found here); gif works without it")
    return str(fmt)


def export_rollout(path: Path, fmt: str, cfg: DictConfig) -> Path:
    """Export the rollout file ``path`` as ``fmt`` beside it; returns what was written (.pvd, .gif, .mp4).

    Raises:
        ConfigError: an unknown format, an unknown colour or fps, or mp4 without ffmpeg.
    """
    check_format(fmt)
    if fmt == "vtu":
        from lagfluid.tasks.export.vtk import write_paraview

        return write_paraview(path, path.parent / "paraview")
    from lagfluid.tasks.export.animation import animate

    options = cfg.animation
    return animate(
        [path], path.with_suffix(f".{fmt}"), str(options.color), int(options.fps), int(options.max_frames)
    )


def export_task(cfg: DictConfig) -> Path:
    """``task=export``: export ``cfg.run`` as ``cfg.format``; logs and returns the file written."""
    import logging

    if cfg.get("run") is None:
        raise ConfigError("task=export needs run=DIR (a run folder with rollout.h5) or run=FILE.h5")
    from lagfluid.tasks.locks import hold_outputs

    path, fmt = rollout_path(str(cfg.run)), check_format(cfg.format)
    with hold_outputs(path.parent, "export", what="run"):  # it writes beside the rollout, as its run did
        out = export_rollout(path, fmt, cfg)
    logging.getLogger(__name__).info("wrote %s", out)
    return out
