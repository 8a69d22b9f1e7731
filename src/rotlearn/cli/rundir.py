"""The run directory as the boundary, checked from the command line before Hydra writes anything.

- `check_run_tree`: a run directory someone may have sent holds only regular files (no hard
  link to a file outside it) and folders, and no symlink that resolves outside it.
- `output_paths` / `check_placement`: every place a run writes (`paths.*`,
  `trainer.default_root_dir`, each logger's folder, each checkpoint callback's folder and file
  name, `data.cache_dir`) lies inside the run; a resume refuses a config that would write
  elsewhere, unless the user's own command line set that key.
- `refuse_an_existing_output_dir`: a new run or sweep never writes into an existing, non-empty
  directory, nor names a folder Hydra would not use (refused before Hydra creates or writes
  anything).
- `is_child_rank`: a process started by Lightning or SLURM for another rank of a distributed run,
  which repeats its rank 0's command line and must not repeat its checks.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shlex
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from rotlearn.cli.replay import resume_word, shell_word
from rotlearn.errors import ConfigError
from rotlearn.io import UnreadableFileError, folder_entries
from rotlearn.report.identity import select

__all__ = [
    "FILE_KEYS",
    "MACHINE_KEYS",
    "check_placement",
    "check_run_tree",
    "files_to_open",
    "is_child_rank",
    "keys_to_give_again",
    "machine_overrides",
    "output_paths",
    "place_output_dir",
    "refuse_an_absent_accelerator",
    "refuse_an_existing_output_dir",
    "runs_a_sweep",
    "user_keys",
]

MAX_RUN_ENTRIES = 100_000  # files and folders a run directory may hold (a scan is bounded)
MAX_RUN_DEPTH = 32  # levels of folders in a run (its own go a handful deep)
_RANK_VARIABLES = ("LOCAL_RANK", "RANK", "SLURM_PROCID", "JSM_NAMESPACE_RANK")
_LONE_PATH_KEYS = ("output_dir", "default_root_dir", "cache_dir", "log_dir", "root_dir")
_LOGGER_PARTS = ("save_dir", "name", "version", "sub_dir")


def is_child_rank() -> bool:
    """Whether this process is a rank other than 0 of a distributed run (its launcher set one of
    LOCAL_RANK, RANK, SLURM_PROCID, JSM_NAMESPACE_RANK to a value other than 0)."""
    return any(os.environ.get(name, "0") not in ("", "0") for name in _RANK_VARIABLES)


def hydra_flags(argv: list[str]) -> argparse.Namespace | None:
    """Hydra's flags in a command line, read by Hydra's own parser (`-m`, `--multirun`, `-mc
    job`, `--multi`: as Hydra reads them), or None where Hydra would refuse them (it says why)."""
    from hydra._internal.utils import get_args_parser

    parser = get_args_parser()
    parser.exit_on_error = False
    try:
        return parser.parse_known_args(argv)[0]
    except argparse.ArgumentError:
        return None


def runs_a_sweep(argv: list[str], cfg: DictConfig | None = None) -> bool:
    """Whether a command line runs a sweep: `-m` (`hydra_flags`), or (given its composed config
    with the `hydra` node) an experiment that sets `hydra.mode: MULTIRUN`."""
    if (flags := hydra_flags(argv)) is not None and flags.multirun:
        return True
    from hydra.types import RunMode

    return cfg is not None and cfg.hydra.mode == RunMode.MULTIRUN


def check_run_tree(run_dir: str | os.PathLike) -> None:
    """Refuse a run directory that holds a symlink resolving outside it, a file with names
    outside it (a hard link: a resume writing its config or log would write through to them;
    names inside it are a resume's own, `keep_earlier_records`, killed midway), or
    anything but regular files and folders (a named pipe, a device, a socket), or more than
    `MAX_RUN_ENTRIES` entries or `MAX_RUN_DEPTH` levels of folders. Symlinks are not followed
    while scanning.

    Raises:
        UnreadableFileError: naming the entry at fault.
    """
    run = Path(os.path.realpath(run_dir))
    try:
        entries = list(folder_entries(run, MAX_RUN_ENTRIES, MAX_RUN_DEPTH))
    except UnreadableFileError as exc:
        raise UnreadableFileError(f"{exc}; not a run directory") from None
    files = {
        e.path: e.stat(follow_symlinks=False) for e in entries if e.is_file(follow_symlinks=False)
    }
    names = Counter((found.st_dev, found.st_ino) for found in files.values())  # names in the run
    for entry in entries:
        path = Path(entry.path)
        if entry.is_symlink():
            target = Path(os.path.realpath(path))
            if not target.is_relative_to(run):
                raise UnreadableFileError(
                    f"{path}: a symlink to {target}, outside the run {run}; refused"
                )
        elif entry.is_dir(follow_symlinks=False):
            continue
        elif not entry.is_file(follow_symlinks=False):
            raise UnreadableFileError(
                f"{path}: neither a regular file nor a folder (a FIFO, device or socket); "
                "a run directory holds only files and folders"
            )
        elif (found := files[entry.path]).st_nlink > names[found.st_dev, found.st_ino]:
            raise UnreadableFileError(
                f"{path}: a hard link to a file outside the run ({found.st_nlink} names), "
                "which the run would write through; copy the run (cp -r) to resume the copy"
            )


# Keys that name a file a run opens (beyond its dataset, data.root): on a resume only the user's
# own command line names one, as rotlearn-eval takes `ood.autoencoder_ckpt` from its own.
FILE_KEYS = ("callbacks.ood.autoencoder_ckpt",)


# Keys of the machine that runs, how many processes and devices: on a resume only the user's own
# command line sets one (a received run's saved `trainer.devices=4096` started 4096 processes),
# as rotlearn-eval takes them from its own.
MACHINE_KEYS = ("data.num_workers", "trainer.devices", "trainer.num_nodes")


def files_to_open(config: Mapping[str, Any]) -> dict[str, str]:
    """The `FILE_KEYS` a config (a DictConfig or plain data) sets, with their values."""
    return {key: str(value) for key in FILE_KEYS if (value := select(config, key))}


def refuse_an_absent_accelerator(values: Mapping[str, Any]) -> None:
    """ConfigError where a config (plain data or a DictConfig) asks for an accelerator this
    machine does not have (`trainer=gpu` on a laptop: Lightning refused it once the run's
    folder was made, which was left FAILED). A config may name one, to be composed and
    validated anywhere (`rotlearn.config.validate` does not ask the machine); a command that
    runs it here asks this. A name Lightning does not know is validation's to refuse."""
    name = select(values, "trainer.accelerator")
    if name in (None, "auto", "cpu"):
        return
    from lightning.pytorch.accelerators import AcceleratorRegistry

    kinds = ["cuda", "mps"] if name == "gpu" else [name]  # Lightning's meaning of gpu
    if not all(k in AcceleratorRegistry for k in kinds):
        return
    if not any(AcceleratorRegistry[k]["accelerator"].is_available() for k in kinds):
        how = "on its CPU: trainer=cpu or trainer.accelerator=auto"
        raise ConfigError("trainer.accelerator", f"{name} asks for a device this machine does "
                          f"not have; {how}")  # fmt: skip


def machine_overrides(overrides: Iterable[str]) -> dict[str, str]:
    """{key: override} of the `MACHINE_KEYS` that `overrides` set, each its last one (a resumed
    run's saved overrides hold its earlier values too), without a `+` (a resume's command
    line gets one where the YAML lacks the key); a deletion (`~key`) sets none."""
    found = {}
    for text in (o for o in overrides if not o.startswith(("-", "~"))):
        for key in user_keys([text]) & {*MACHINE_KEYS}:
            found[key] = text.lstrip("+")
    return found


def keys_to_give_again(config: Mapping[str, Any], overrides: Iterable[str]) -> list[str]:
    """What a resume of a run takes from its command line only, as shell words for the resume
    command a stopped run prints: the `FILE_KEYS` its config sets and the overrides of its
    command line (`overrides`) that set `MACHINE_KEYS` (`machine_overrides`)."""
    words = [shell_word(key, value) for key, value in files_to_open(config).items()]
    return words + [shlex.quote(text) for text in machine_overrides(overrides).values()]


def _text(value: Any) -> str | None:
    return None if value is None or value == "" else str(value)


def output_paths(cfg: DictConfig) -> list[tuple[tuple[str, ...], str]]:
    """Every place the config makes a run write, as (the config keys that make up the path, the
    path), values resolved: each `paths.*` value; every node's `output_dir`,
    `default_root_dir`, `cache_dir`, `log_dir`, `root_dir`; a logger's
    `save_dir/name/version/sub_dir`; a checkpoint callback's `dirpath` and `dirpath/filename`
    (also with the file name's braces dropped, as Lightning formats `{name}`), where it has no
    `dirpath` `<paths.output_dir>/checkpoints/filename`.
    The `hydra` node is Hydra's own and left out."""
    tree = {
        str(k): OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v
        for k, v in cfg.items_ex(resolve=True)
        if k != "hydra"
    }
    found: list[tuple[tuple[str, ...], str]] = []
    output_dir = (tree.get("paths") or {}).get("output_dir")
    for name, value in (tree.get("paths") or {}).items():
        if _text(value) is not None:
            found.append(((f"paths.{name}",), str(value)))
    stack = [(key, node) for key, node in tree.items() if key not in ("hydra", "paths")]
    while stack:
        key, node = stack.pop()
        if isinstance(node, list):
            stack.extend((f"{key}.{i}", v) for i, v in enumerate(node))
        if not isinstance(node, dict):
            continue
        stack.extend((f"{key}.{k}", v) for k, v in node.items())
        for part in _LONE_PATH_KEYS:
            if _text(node.get(part)) is not None:
                found.append(((f"{key}.{part}",), str(node[part])))
        if _text(node.get("save_dir")) is not None:
            parts = [p for p in _LOGGER_PARTS if _text(node.get(p)) is not None]
            found.append((tuple(f"{key}.{p}" for p in parts),
                          os.path.join(*(str(node[p]) for p in parts))))  # fmt: skip
        if (folder := _text(node.get("dirpath"))) is not None:
            found.append(((f"{key}.dirpath",), folder))
        if _text(node.get("filename")) is not None and (folder or "_target_" in node):
            # no dirpath: Lightning's <default_root_dir or logger folder>/checkpoints, the
            # shallowest of which is the run's checkpoints/
            keys = (f"{key}.dirpath",) * bool(folder) + (f"{key}.filename",)
            folder = folder or os.path.join(str(output_dir), "checkpoints")
            name = str(node["filename"])  # as written, and as formatted: `{name}` becomes
            for form in dict.fromkeys([name, name.replace("{", "").replace("}", "")]):
                found.append((keys, os.path.join(folder, form)))  # `name=<value>` ({/x}: /x)
    return found


def user_keys(overrides: Iterable[str]) -> set[str]:
    """The config keys that value overrides set (group choices, `hydra.*` and flags left out)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    keys = set()
    for text in overrides:
        if text.startswith("-"):
            continue
        parsed = OverridesParser.create().parse_overrides([text])[0]
        key = parsed.key_or_group
        if "." in key and not key.startswith("hydra."):
            keys.add(key)
    return keys


def check_placement(
    cfg: DictConfig, run_dir: str | os.PathLike, trusted: Iterable[str] = ()
) -> None:
    """Refuse a config that writes outside `run_dir` (a resume continues in its own directory).

    Args:
        cfg: the composed config, `paths.output_dir` resolved.
        run_dir: the run directory.
        trusted: config keys the user's own command line set; a path made only of such keys
            may lie anywhere.

    Raises:
        ConfigError: naming the key(s), the path and where it resolves (symlinks and `..`
            followed, and also `..` taken lexically, as Lightning normalises a folder); a path
            with a `$` or a leading `~` (past the run directory's own path), which Lightning
            expands; also when `paths.output_dir` is not the run directory itself.
    """
    run = Path(os.path.realpath(run_dir))
    trusted = set(trusted)

    def set_by_user(key: str) -> bool:
        return any(key == t or key.startswith(f"{t}.") for t in trusted)

    output_dir = OmegaConf.select(cfg, "paths.output_dir")
    if output_dir is None or Path(os.path.realpath(output_dir)) != run:
        raise ConfigError(
            "paths.output_dir", f"is {output_dir!r}; a resumed run's outputs go to its own "
            f"directory {run}"
        )  # fmt: skip
    for keys, path in output_paths(cfg):
        if all(set_by_user(k) for k in keys):
            continue
        tail = path.removeprefix(str(output_dir))  # the run's own path is the user's
        if "$" in tail or tail.startswith("~"):
            raise ConfigError(" + ".join(keys), f"{path} holds '$' or a leading '~', which "
                              "Lightning expands from this machine's environment (set the key "
                              "on your own command line to use it)")  # fmt: skip
        for form in (path, os.path.normpath(path)):  # Lightning normalises default_root_dir
            real = Path(os.path.realpath(form))
            if not real.is_relative_to(run):
                raise ConfigError(
                    " + ".join(keys),
                    f"{path} resolves to {real}, outside the run {run}; a resumed run writes "
                    "only inside its own directory (set the key on your own command line to "
                    "write elsewhere)",
                )


@contextlib.contextmanager
def _hydra_config(cfg: DictConfig) -> Iterator[None]:
    """`hydra:` interpolations resolve against `cfg` inside the block (Hydra's own global is
    restored after it)."""
    from hydra.core.hydra_config import HydraConfig

    holder = HydraConfig.instance()
    previous = holder.cfg
    holder.set_config(cfg)
    try:
        yield
    finally:
        holder.cfg = previous


def _non_empty(path: Path) -> bool:
    try:
        return path.is_dir() and any(path.iterdir())
    except OSError:
        return True
    return False


def refuse_an_existing_output_dir(
    cfg: DictConfig,
    argv: list[str],
    config_name: str,
    prog: str,
    allow: bool | Callable[[], bool] = False,
) -> None:
    """Refuse (SystemExit, one line) a command line whose run or sweep directory already exists
    and is not empty (a new run never writes into another's directory), or that sets the folder
    of the mode it does not run.

    Args:
        cfg: the command line's config with its `hydra` node
            (`rotlearn.config.command_line_config`).
        argv: the command line (no `ckpt_path`: resumes are `rotlearn.cli.resume`'s).
        config_name: the primary config ("train", "eval").
        prog: the command's name, for the message.
        allow: skip the refusal (a SLURM job requeued into its own directory); a callable is
            asked only when the directory is taken.
    """
    from rotlearn.report.identity import set_keys

    multirun = runs_a_sweep(argv, cfg)
    for key in (k for k in ("hydra.run.dir", "hydra.sweep.dir") if k in set_keys(argv)):
        if (key == "hydra.run.dir") == multirun:  # Hydra would write elsewhere, silently
            other, mode = (
                ("hydra.sweep.dir", "a sweep") if multirun else ("hydra.run.dir", "one run")
            )
            how = "; for one run: hydra.mode=RUN" if multirun and "-m" not in argv else ""
            raise SystemExit(
                f"{prog}: {key} is not used: this command runs {mode}, whose folder is {other}"
                f"{how}; nothing was written"
            )
    with _hydra_config(cfg):
        folder = Path(cfg.hydra.sweep.dir if multirun else cfg.hydra.run.dir)
    if _non_empty(folder) and not (allow() if callable(allow) else allow):
        what = "sweep" if multirun else "run" if config_name == "train" else "evaluation"
        hint = ""
        if what == "run" and os.path.lexists(folder / "metrics.json"):  # it finished
            longer = f"{prog} {resume_word(folder)} trainer.max_epochs=<more>"
            hint = f" (it holds a finished run; to train it longer: {longer})"
        elif what == "run":
            hint = f" (to continue the run in it: {prog} {resume_word(folder)})"
        raise SystemExit(
            f"{prog}: {folder} already exists and is not empty; a new {what} never writes into "
            f"an existing directory{hint}; nothing was written"
        )


def place_output_dir(cfg: DictConfig, run_dir: str | os.PathLike) -> DictConfig:
    """Set `paths.output_dir` as Hydra will resolve it when the run starts in `run_dir` (its
    default, `${hydra:runtime.output_dir}`, only resolves inside a running Hydra app); a value
    an override set is left as it is. Returns `cfg`, changed in place."""
    node = cfg.paths._get_node("output_dir") if "paths" in cfg else None
    if node is not None and node._value() == "${hydra:runtime.output_dir}":
        cfg.paths.output_dir = str(run_dir)
    return cfg
