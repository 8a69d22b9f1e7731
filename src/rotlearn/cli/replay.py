"""Replaying a run directory's saved overrides on resume, through the same allowlist as checkpoints.

`rotlearn-train ckpt_path=<run>` continues a run with the overrides it was started with, read
from `<run>/.hydra/overrides.yaml`. That file is data someone may have sent: an override such as
`net._target_=torch.load`, `+net.f._target_=builtins.open` or `hydra.callbacks.x._target_=...`
would run code when Hydra composes and instantiates the run. `saved_overrides` reads the file as
plain YAML (nothing resolved), refuses Hydra's own keys and sweeps (a run's saved overrides hold
neither), composes the run's config from them, and checks the whole composed config with
`rotlearn.trust.check_config` BEFORE Hydra starts: nothing is written and nothing is built from a
refused file.
"""

from __future__ import annotations

from pathlib import Path

import yaml

from rotlearn.paths import config_dir
from rotlearn.trust import UntrustedConfigError, trusted_config

__all__ = ["saved_overrides"]


def _parse(overrides: list[str], source: Path) -> None:
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except HydraException as exc:
        raise UntrustedConfigError(f"{source}: not a list of Hydra overrides: {exc}") from None
    for override in parsed:
        key = override.key_or_group
        if key == "hydra" or key.startswith(("hydra.", "hydra/")):
            raise UntrustedConfigError(
                f"{source}: override {override.input_line!r} sets Hydra's own config key {key}; "
                "a run's saved overrides never do"
            )
        if override.is_sweep_override():
            raise UntrustedConfigError(
                f"{source}: override {override.input_line!r} is a sweep, not one run's value"
            )


def saved_overrides(run_dir: str | Path, config_name: str = "train") -> list[str]:
    """The overrides a run was started with, checked as untrusted data.

    Args:
        run_dir: the run directory (holding `.hydra/overrides.yaml`).
        config_name: the primary config the run was composed from.

    Returns:
        The saved overrides, in order, as strings.

    Raises:
        FileNotFoundError: the run has no `.hydra/overrides.yaml`.
        UntrustedConfigError: naming the file and the key path or override at fault: not a list
            of strings, a Hydra key or a sweep, an override that does not compose, or a composed
            config with a `_target_` off the allowlist or an interpolation it brought in.
    """
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    import rotlearn.cli.resolvers  # noqa: F401  (the configs' own resolvers)

    source = Path(run_dir) / ".hydra" / "overrides.yaml"
    if not source.is_file():
        raise FileNotFoundError(f"{run_dir} is not a rotlearn run (no {source})")
    try:
        overrides = yaml.safe_load(source.read_text()) or []
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise UntrustedConfigError(f"{source}: not YAML: {exc}") from None
    if not isinstance(overrides, list) or not all(isinstance(o, str) for o in overrides):
        raise UntrustedConfigError(f"{source}: expected a list of override strings")
    _parse(overrides, source)
    try:
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose(
                config_name=config_name,
                overrides=[*overrides, f"paths.output_dir={Path(run_dir).resolve()}"],
            )
    except (HydraException, OmegaConfBaseException) as exc:
        raise UntrustedConfigError(f"{source}: the overrides do not compose: {exc}") from None
    trusted_config(cfg, source)
    return overrides
