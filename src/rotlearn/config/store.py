"""Each component's defaults as a Hydra config node, so that a YAML holds only what differs.

`register_schemas` stores, for every component marked `@config_target` in rotlearn, the node
`schema/<dotted name where it is defined>`: its `_target_` and one key per constructor argument
with its default (`???` where required), read from the source (`rotlearn.config.source`). A YAML
under conf/ starts from it in its defaults list, e.g. conf/data/kitti.yaml:

    defaults:
      - /schema/rotlearn.data.kitti.KittiOdometryDataModule@data

so that every argument can be overridden without `+`. The nodes live in their own group, never
among a group's options. Hydra finds them wherever it composes conf/: rotlearn's Hydra plugin
(`hydra_plugins.rotlearn`) registers them when Hydra builds its config search path, so a plain
`hydra.compose` works without importing anything of rotlearn's first. Types are not part of the
node: `rotlearn.config.validate` checks every value against the annotated signature.
"""

from __future__ import annotations

from functools import cache

from rotlearn.config.source import marked, parameters

__all__ = ["SCHEMA_GROUP", "register_schemas", "schema"]

SCHEMA_GROUP = "schema"


def schema(target: str) -> dict:
    """The defaults node of the component `target`: `_target_` and each argument's default."""
    found = parameters(target)
    if found is None:
        raise LookupError(f"no source found for {target}")
    return {"_target_": target, **{p.name: p.default for p in found[0]}}


@cache
def register_schemas() -> tuple[str, ...]:
    """Store `schema/<target>` in Hydra's ConfigStore for every marked component (once per
    process); returns their names."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for target in marked():
        store.store(group=SCHEMA_GROUP, name=target, node=schema(target))
    return marked()
