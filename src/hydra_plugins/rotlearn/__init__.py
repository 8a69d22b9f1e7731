"""rotlearn's Hydra plugin: its config schemas are there wherever Hydra composes conf/.

Hydra imports every module of the `hydra_plugins` namespace package when it builds a config search
path; this one registers rotlearn's component schemas (`rotlearn.config.register_schemas`)
in Hydra's ConfigStore at that moment, so that `hydra.compose` on conf/ needs no rotlearn import
first. The search path itself is left as it is.
"""

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class RotlearnSchemas(SearchPathPlugin):
    """Registers rotlearn's schemas; adds no search path."""

    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        from rotlearn.config import register_schemas

        register_schemas()
