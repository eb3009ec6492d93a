"""The Hydra config folders: the package's own (:data:`CONF_DIR`) and the plugins' (``lagfluid.configs``).

A plugin (``baselines/gns``, a third-party package) keeps its config group files in a folder of its own
package, laid out as ``conf/`` is (``model/gns.yaml``, ``train/gns_cpu.yaml``, ``experiment/...``), and
names that folder's package in its entry points::

    [project.entry-points."lagfluid.configs"]
    gns = "baselines.gns.conf"

``conf/config.yaml`` puts every such folder on Hydra's search path (``hydra.searchpath:
${lagfluid.plugin_configs:}``), so ``model=gns`` composes with the core groups, in struct mode, from the
command line and from Hydra's compose API alike; lagfluid never imports the plugin's code for it.
"""

from __future__ import annotations

import importlib.util
from importlib import metadata
from pathlib import Path

from lagfluid.errors import ConfigError

CONFIGS_GROUP = "lagfluid.configs"
CONF_DIR = Path(__file__).resolve().parent / "conf"  # in the package: a wheel carries it (conf/ links here)


def plugin_config_dirs() -> dict[str, Path]:
    """Plugin name -> its config folder, for every entry point of ``lagfluid.configs``.

    Raises:
        ConfigError: an entry point names a package that cannot be found or is not a folder.
    """
    dirs: dict[str, Path] = {}
    for ep in metadata.entry_points(group=CONFIGS_GROUP):
        try:
            spec = importlib.util.find_spec(ep.value)
        except (ImportError, ValueError) as err:
            raise ConfigError(
                f"plugin '{ep.name}': config package {ep.value!r} cannot be imported: {err}"
            ) from err
        locations = list(spec.submodule_search_locations or []) if spec is not None else []
        if not locations or not Path(locations[0]).is_dir():
            raise ConfigError(
                f"plugin '{ep.name}': {ep.value!r} (entry point group {CONFIGS_GROUP}) is not a package "
                "folder of config groups"
            )
        dirs[ep.name] = Path(locations[0])
    return dirs


def plugin_search_path() -> list[str]:
    """The plugins' config folders as Hydra search-path entries (``file://...``), sorted by plugin name."""
    return [f"file://{path}" for _, path in sorted(plugin_config_dirs().items())]


def group_options(group: str, core_dir: Path) -> list[str]:
    """Sorted option names of config ``group`` in ``core_dir`` and in every plugin's folder."""
    folders = [core_dir, *plugin_config_dirs().values()]
    return sorted({p.stem for folder in folders for p in (folder / group).glob("*.yaml")})
