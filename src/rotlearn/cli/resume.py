"""Continuing a run: `rotlearn-train ckpt_path=<run dir | .ckpt | last>`.

`plan_resume` turns the command line into the one Hydra runs: the run's own saved overrides
(checked as untrusted data: `rotlearn.cli.replay`), the new ones, the checkpoint and the run
directory (quoted, so a path with any characters resumes). The run directory is untrusted too.
Every check happens there, before Hydra writes anything, so a refused resume leaves the run
byte-identical:

- the run tree holds only files and folders, no symlink or hard link out of it, at most 32
  folders deep (`rundir.check_run_tree`);
- no other process holds the run's lock (`rotlearn.locks`; the holder is named);
- a COMPLETED run only trains longer;
- the config that will run, composed exactly as Hydra will compose it (one run, even where
  its experiment sweeps), validates, writes only inside the run (`rundir.check_placement`) and
  opens no file and sets no number of processes or devices that only the saved overrides name
  (`rundir.FILE_KEYS`, `rundir.MACHINE_KEYS`), and asks for no accelerator this machine lacks;
- the checkpoint is a whole, bounded checkpoint (`rotlearn.checkpoint.load_checkpoint`) whose
  checkpoint callbacks' states name only the run's own checkpoint files, and whose training
  and random states restore (`rotlearn.lit.boundary.checked_checkpoint_states`).

`keep_earlier_records` moves an attempt's records into `history/<n>/` (whole or not at all)
before a resume trains, and `checkpoint_to_resume` picks the checkpoint `fit` starts from (a
requeued SLURM job continues its own run).
"""

from __future__ import annotations

import contextlib
import logging
import os
import secrets
import shlex
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

from lightning.fabric.plugins.environments import SLURMEnvironment
from omegaconf import DictConfig, OmegaConf

from rotlearn.checkpoint import (
    UnsafeCheckpointError,
    check_weights,
    load_checkpoint,
    resolve_checkpoint,
)
from rotlearn.cli.replay import (
    quoted,
    replayed_config,
    resume_word,
    saved_overrides,
)
from rotlearn.cli.rundir import (
    MACHINE_KEYS,
    check_placement,
    check_run_tree,
    files_to_open,
    machine_overrides,
    refuse_an_absent_accelerator,
    runs_a_sweep,
    user_keys,
)
from rotlearn.errors import ConfigError
from rotlearn.io import UnreadableFileError, read_bytes, read_record, write_bytes_atomic
from rotlearn.locks import RunLockedError, check_free
from rotlearn.paths import CSV_LOG, HISTORY_DIR, earlier_attempts
from rotlearn.report.tensorboard import SESSION_RUN, event_runs
from rotlearn.trust import UntrustedConfigError

__all__ = [
    "Resume",
    "checkpoint_to_resume",
    "keep_earlier_records",
    "plan_resume",
    "requeued_on_slurm",
    "resume_arguments",
    "run_of",
]

log = logging.getLogger("rotlearn")


def requeued_on_slurm() -> bool:
    """A SLURM job that was requeued (preemption, time-out) and runs again in its own directory:
    it continues that run (Lightning's hpc checkpoint, else last.ckpt) instead of refusing it."""
    restarts = os.environ.get("SLURM_RESTART_COUNT", "0")
    return restarts.isdigit() and int(restarts) > 0 and SLURMEnvironment.detect()


def checkpoint_to_resume(cfg: DictConfig, run_dir: Path) -> str | None:
    """The checkpoint `fit` starts from (None: a fresh run, or Lightning's own hpc checkpoint);
    refuses a finished run or a run directory that already holds another run."""
    if (run_dir / "metrics.json").exists():
        raise FileExistsError(
            f"{run_dir} holds a finished run (metrics.json); it is never rewritten"
        )
    resume = cfg.get("ckpt_path")
    if resume:
        resume = str(resolve_checkpoint(resume))
        log.info("resuming from %s", resume)
        return resume
    if (run_dir / "checkpoints").exists():
        if requeued_on_slurm():
            if list(run_dir.glob("hpc_ckpt_*.ckpt")):
                return None  # Lightning restores its SIGUSR1 (hpc) checkpoint itself
            last = run_dir / "checkpoints" / "last.ckpt"
            return str(last) if last.is_file() else None
        raise FileExistsError(
            f"{run_dir} already holds a run; rotlearn never overwrites one (to continue it: "
            f"{resume_word(run_dir)})"
        )
    return None


# What a completed run may be resumed with: more epochs, and nothing that changes its results.
_ALLOWED_ON_A_COMPLETED_RUN = ("trainer.max_epochs", "trainer.enable_progress_bar")
# The records of one attempt at a run; a resume keeps the earlier ones in history/<n>/.
_RECORDS = ("metrics.json", "status.json", "timing.json", "test_errors.json")


def _refuse(message: str) -> SystemExit:
    return SystemExit(f"rotlearn-train: {message}")


def _record(run_dir: Path, name: str) -> dict:
    """A record of the run as a dict ({} where it has none), read bounded.

    Raises:
        UnreadableFileError: naming the file: not a regular file, too large, not a JSON object.
    """
    try:
        data = read_record(run_dir / name, root=run_dir)
    except FileNotFoundError:
        return {}
    if not isinstance(data, dict):
        raise UnreadableFileError(
            f"{run_dir / name}: not a JSON object (a {type(data).__name__}); not a run's record"
        )
    return data


def _is_completed(run_dir: Path) -> bool:
    """A run that finished (metrics.json written, or status.json says COMPLETED)."""
    return os.path.lexists(run_dir / "metrics.json") or (
        _record(run_dir, "status.json").get("status") == "COMPLETED"
    )


def _epochs_finished(run_dir: Path) -> int:
    """How many epochs a run trained: metrics.json's `epochs`, else last.ckpt's epoch + 1."""
    epochs = _record(run_dir, "metrics.json").get("epochs")
    if isinstance(epochs, int) and not isinstance(epochs, bool):
        return epochs
    try:
        return int(load_checkpoint(run_dir)["epoch"]) + 1
    except (OSError, RuntimeError, KeyError, ValueError, TypeError):
        return 0


def _skip_reason(run: Path) -> str | None:
    """Why `ckpt_path=last` passes over a run (None: it can be resumed)."""
    try:
        if _is_completed(run):
            return "COMPLETED"
        check_free(run)
        load_checkpoint(run)
    except RunLockedError as exc:
        return str(exc)
    except (OSError, ValueError) as exc:
        return f"cannot be resumed: {exc}"
    return None


def _newest_resumable_run(root: Path) -> Path:
    """The newest run under `root` with a last.ckpt that loads and that is neither COMPLETED nor
    in use by another process; the pick and the runs skipped on the way are named on stderr."""
    runs = sorted(p.parent.parent for p in root.glob("*/checkpoints/last.ckpt"))
    skipped: list[tuple[Path, str]] = []
    for run in reversed(runs):  # run directories are named by their start time
        reason = _skip_reason(run)
        if reason is None:
            completed = sum(r == "COMPLETED" for _, r in skipped)
            notes = [f"skipped {completed} newer COMPLETED run(s)"] if completed else []
            notes += [f"skipped {p}: {r}" for p, r in skipped if r != "COMPLETED"]
            note = f"; {'; '.join(notes)}" if notes else ""
            print(f"rotlearn-train: ckpt_path=last: resuming {run}{note}", file=sys.stderr)
            return run
        skipped.append((run, reason))
    completed = [p for p, r in skipped if r == "COMPLETED"]
    others = [f"{p}: {r}" for p, r in skipped if r != "COMPLETED"]
    why = (
        f"; {len(completed)} have one but are COMPLETED (newest: {completed[0]})"
        if completed
        else ""
    )
    why += "".join(f"; skipped {o}" for o in others)
    raise _refuse(
        f"ckpt_path=last, but no run under {root} can be resumed (a last.ckpt that loads, not "
        f"COMPLETED, not in use){why}. A run made elsewhere (hydra.run.dir=...) resumes by its "
        "folder: ckpt_path=<run dir>; a completed run only trains longer: "
        "ckpt_path=<run dir> trainer.max_epochs=<more epochs>"
    )


def _checkpoint_of(value: str, runs_root: Path) -> Path:
    """The checkpoint file that `ckpt_path=<value>` names (`last`: the newest resumable run)."""
    if value == "last":
        return resolve_checkpoint(_newest_resumable_run(runs_root))
    try:
        return resolve_checkpoint(value)
    except (FileNotFoundError, UnsafeCheckpointError) as exc:
        raise _refuse(f"ckpt_path: {exc}") from None


def _saved_overrides(run_dir: Path) -> list[str]:
    """The run's own command-line overrides, read from `<run_dir>/.hydra/overrides.yaml`
    (without its ckpt_path): the settings a resume continues with. The run directory is untrusted
    data: they are read bounded and parsed (`rotlearn.cli.replay.saved_overrides`), and composed
    and checked against the allowlist with the new overrides (`replay.replayed_config`)."""
    try:
        return [o for o in saved_overrides(run_dir) if not o.startswith("ckpt_path=")]
    except (FileNotFoundError, UntrustedConfigError) as exc:
        raise _refuse(f"ckpt_path: {exc}") from None


def _refuse_rewriting_a_completed_run(run_dir: Path, previous: list[str], new: list[str]) -> None:
    """A COMPLETED run is resumed only to train longer: `trainer.max_epochs` above the epochs it
    finished, and no override that changes its other settings."""
    if not _is_completed(run_dir):
        return
    done = _epochs_finished(run_dir)
    longer = f"to train it longer: rotlearn-train {resume_word(run_dir)} trainer.max_epochs=<more>"
    head = f"refusing to resume {run_dir}: it is COMPLETED ({done} epochs) and never rewritten"
    changed = [
        o
        for o in new
        if o not in previous and o.split("=", 1)[0].lstrip("+~") not in _ALLOWED_ON_A_COMPLETED_RUN
    ]
    if changed:
        raise _refuse(
            f"{head}; a completed run only trains longer, but this command also sets "
            f"{' '.join(changed)} (start a new run for other settings; {longer})"
        )
    epochs = [o.split("=", 1)[1] for o in new if o.startswith("trainer.max_epochs=")]
    if not epochs or not epochs[-1].isdigit() or int(epochs[-1]) <= done:
        given = f" (trainer.max_epochs={epochs[-1]} is not above {done})" if epochs else ""
        raise _refuse(f"{head}{given}; {longer}, above {done}")


def _model_checkpoints(cfg: DictConfig) -> list:
    """The run's checkpoint callbacks, built from the (validated) config: they build nothing
    on disk, and know the state key and folder of their saved state."""
    from hydra.utils import instantiate
    from lightning.pytorch.callbacks import ModelCheckpoint

    nodes = cfg.get("callbacks") or {}
    built = [instantiate(node) for node in nodes.values() if node and "ModelCheckpoint" in str(
        node.get("_target_", ""))]  # fmt: skip
    return [cb for cb in built if isinstance(cb, ModelCheckpoint)]


def _check_the_weights(cfg: DictConfig, checkpoint: dict, ckpt: Path) -> None:
    """The checkpoint's weights fit the model the config builds (built on the meta device:
    nothing allocated): names, shapes, floating point, finite (`rotlearn.checkpoint.check_weights`);
    and its optimizers' states fit that model's parameters (rotlearn's modules optimize
    `self.parameters()`, numbered in order): a wrong shape failed at the first step, after the
    records had moved.

    Raises:
        UnsafeCheckpointError: naming the checkpoint and the weights or state at fault.
    """
    import torch
    from hydra.utils import instantiate

    state_dict = checkpoint.get("state_dict")
    if not isinstance(state_dict, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state_dict.items()
    ):
        raise UnsafeCheckpointError(f"{ckpt}: state_dict must map names to tensors")
    with torch.device("meta"):
        model = instantiate(cfg.model)
    try:
        check_weights(model.state_dict(), state_dict, str(ckpt))
    except ValueError as exc:
        raise UnsafeCheckpointError(str(exc)) from None
    shapes = [p.shape for p in model.parameters()]
    for i, state in enumerate(checkpoint.get("optimizer_states") or []):  # shapes checked before
        ids = [n for group in state["param_groups"] for n in group.get("params", [])]
        if not all(type(n) is int for n in ids) or sorted(ids) != list(range(len(shapes))):
            raise UnsafeCheckpointError(f"{ckpt}: optimizer_states[{i}] numbers {len(ids)} "
                                        f"parameters; the model has {len(shapes)}")  # fmt: skip
        for n, values in state["state"].items():
            for name, value in values.items() if isinstance(values, dict) else ():
                if (
                    isinstance(value, torch.Tensor)
                    and value.ndim
                    and (n not in range(len(shapes)) or value.shape != shapes[n])
                ):
                    raise UnsafeCheckpointError(
                        f"{ckpt}: optimizer_states[{i}].state[{n!r}].{name} is of shape "
                        f"{tuple(value.shape)}, not its parameter's"
                    )


def _origin(error: Exception, args: list[str], new: list[str], run_dir: Path) -> str:
    """ " (from <run>/.hydra/overrides.yaml: '<override>')" where a `ConfigError`'s key was set by
    one of the run's saved overrides and not by the new command line (the user did not type
    it), else ""."""
    from rotlearn.report.identity import set_keys
    from rotlearn.report.runs import matches

    key = getattr(error, "key", None)
    if key is None or "overrides.yaml" in str(error) or matches(key, set_keys(new)):
        return ""
    found = [(text, saved) for text in args if text not in new for saved in set_keys([text])]
    for text, saved in sorted(found, key=lambda pair: pair[1] != key):  # the key's own first
        if matches(key, [saved]) or matches(saved, [key]):
            return f" (from {run_dir / '.hydra' / 'overrides.yaml'}: {text!r})"
    return ""


def _check_the_config_that_runs(
    run_dir: Path, args: list[str], new: list[str], ckpt: Path
) -> list[str]:
    """Compose the resumed run's config exactly as Hydra will and check it against the allowlist
    (`replay.replayed_config`), then validate it, check that it writes only inside the run, and
    that the checkpoint and its callbacks' states are sound. Returns the arguments for Hydra:
    `+` before a key the YAML does not list, as for a new run, so that validation names a
    misspelt key ("did you mean ...?") and a component argument the YAML leaves out can be set."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from rotlearn.config import command_line_config, validate
    from rotlearn.lit.boundary import checked_checkpoint_states

    try:
        _, args = command_line_config(args, str(run_dir), appendable=new)
    except ConfigError as exc:  # e.g. an option that does not exist: named, with the nearest
        raise _refuse(
            f"refusing to resume {run_dir}: {exc}{_origin(exc, args, new, run_dir)}"
        ) from None
    except (HydraException, OmegaConfBaseException):
        pass  # replayed_config names the file whose overrides do not compose
    try:
        cfg = replayed_config(args, run_dir)
    except UntrustedConfigError as exc:
        raise _refuse(f"ckpt_path: {exc}") from None
    try:
        validate(cfg)
        check_placement(cfg, run_dir, trusted=user_keys(new))  # first: a path out is named so
        _refuse_files_to_open(cfg, new)
        _refuse_machine_keys([a for a in args if a not in new], new)
        refuse_an_absent_accelerator(cfg)  # a received trainer=gpu run on a CPU machine
        _check_it_is_the_config_the_run_trained(cfg, run_dir, new)
        checkpoint = load_checkpoint(ckpt)
        checked_checkpoint_states(checkpoint, _model_checkpoints(cfg), run_dir, ckpt)
        _check_the_weights(cfg, checkpoint, ckpt)
    except (ConfigError, UnsafeCheckpointError, UnreadableFileError) as exc:
        raise _refuse(
            f"refusing to resume {run_dir}: {exc}{_origin(exc, args, new, run_dir)}"
        ) from None
    except Exception as exc:  # a config that does not compose or build: nothing was written
        reason = str(exc).strip().splitlines()
        raise _refuse(
            f"refusing to resume {run_dir}: {reason[0] if reason else type(exc).__name__}"
        ) from None
    return args


def _refuse_files_to_open(cfg: DictConfig, new: list[str]) -> None:
    """ConfigError where the run's saved overrides, not the new command line, name a file to
    open (`rundir.FILE_KEYS`): a received run would make the resume read a checkpoint outside
    it. (The resume command a stopped run prints names them: `RunInterrupted`.)"""
    typed = user_keys(new)
    for key, named in files_to_open(cfg).items():
        if key not in typed:
            raise ConfigError(key, f"the run's saved overrides name {named}; a resume opens a "
                              f"file they name only when your command line names it: {key}="
                              f"{named} to open it, {key}=null to go without")  # fmt: skip


def _refuse_machine_keys(saved: list[str], new: list[str]) -> None:
    """ConfigError where the run's saved overrides set keys of this machine's
    (`rundir.MACHINE_KEYS`) that the new command line does not, naming them all with their
    last values: a received run's `trainer.devices=4096` started 4096 processes (on a CPU each
    device is one, importing torch) and took the machine's memory. rotlearn's own configs'
    values are not refused; a saved one the command line sets again is not replayed
    (`_without_retyped_machine_keys`)."""
    typed = user_keys(new)
    found = {k: v for k, v in machine_overrides(saved).items() if k not in typed}
    if found:
        again = " ".join(map(shlex.quote, found.values()))
        raise ConfigError(next(iter(found)), "how many processes and devices a resume uses is "
                          f"this machine's, taken from your command line only: {again} to use "
                          f"{'them' if len(found) > 1 else 'it'} again")  # fmt: skip


def _without_retyped_machine_keys(saved: list[str], new: list[str]) -> list[str]:
    """The saved overrides less those of a `MACHINE_KEYS` key the new command line sets: its
    value replaces theirs, and the command Hydra runs (and saves for the next resume) holds one
    override per machine key, the one the machine that ran it chose."""
    typed = user_keys(new) & {*MACHINE_KEYS}
    return [o for o in saved if o.startswith("-") or not user_keys([o]) & typed]


def _check_it_is_the_config_the_run_trained(cfg: DictConfig, run_dir: Path, new: list[str]):
    """The run's saved overrides compose to the config it trained (`.hydra/config.yaml`) in
    every key both have, but the paths and what the new command line sets: a damaged overrides
    file (emptied, cut short) would resume the checkpoint under other settings.

    Raises:
        ConfigError: naming the first key that differs, both values and both files.
    """
    from rotlearn.io import read_yaml
    from rotlearn.report.identity import set_keys
    from rotlearn.report.runs import flatten, matches

    source = run_dir / ".hydra" / "config.yaml"
    if not os.path.lexists(source):  # nothing to hold the overrides to (Hydra writes both)
        return
    saved = flatten(read_yaml(source, root=run_dir) or {})
    composed = flatten(OmegaConf.to_container(cfg, resolve=False))
    skipped = ["paths", "ckpt_path", *set_keys(new)]
    shared = sorted(saved.keys() & composed.keys(), key=lambda k: (not k.endswith("_target_"), k))
    for key in (k for k in shared if not matches(k, skipped)):
        if saved[key] != composed[key]:
            why = "the overrides file is damaged, or rotlearn's defaults changed since"
            said = f"{run_dir}/.hydra/overrides.yaml composes {composed[key]!r}"
            raise ConfigError(
                key, f"{said}, but the run trained with {saved[key]!r} ({source}): {why}"
            )


@dataclass(frozen=True)
class Resume:
    """A resume that passed every check: `args` is the command line Hydra runs (the saved
    overrides, the new ones, `ckpt_path=<checkpoint>`, `hydra.run.dir=<run_dir>`)."""

    args: list[str]
    run_dir: Path
    checkpoint: Path


def plan_resume(argv: list[str], runs_root: Path = Path("outputs/runs")) -> Resume | None:
    """The resume a command line with `ckpt_path=...` asks for (None: not a resume).

    Every refusal happens here, before Hydra writes into the run directory (module docstring),
    as a SystemExit of one line naming the run and the file or key at fault: -m, no such
    checkpoint, not a rotlearn run, a symlink out of the run or a special file in it, a run in
    use by another process (naming it), a COMPLETED run resumed with other settings or without
    more `trainer.max_epochs`, a config that does not compose, validate or stay inside the run,
    a checkpoint that does not load or whose state names files outside the run.
    `ckpt_path=last` is the newest run under `runs_root` that has a last.ckpt that loads and is
    neither COMPLETED nor in use (named on stderr)."""
    values = [a.split("=", 1)[1] for a in argv if a.startswith("ckpt_path=")]
    if not values or values[-1] in ("", "null", "None"):
        return None
    if runs_a_sweep(argv):
        raise _refuse("ckpt_path resumes one run; it cannot be used with -m")
    ckpt = _checkpoint_of(values[-1], runs_root)
    run_dir = run_of(ckpt).resolve()
    if "${" in str(ckpt.resolve()):
        raise _refuse(
            f"cannot resume {run_dir}: Hydra reads '${{' in a run directory's path as an "
            "interpolation, even quoted (its runtime.output_dir); rename the folder without '${'"
        )
    new = [a for a in argv if not a.startswith("ckpt_path=")]
    try:
        check_run_tree(run_dir)
        check_free(run_dir)
        previous = _saved_overrides(run_dir)  # read here, in one step, before they are used
        _refuse_rewriting_a_completed_run(run_dir, previous, new)
        previous = _without_retyped_machine_keys(previous, new)
        args = [*previous, *new, f"ckpt_path={quoted(str(ckpt.resolve()))}",
                f"hydra.run.dir={quoted(str(run_dir))}",
                "hydra.mode=RUN"]  # one run, even of an experiment that sweeps  # fmt: skip
        args = _check_the_config_that_runs(run_dir, args, new, ckpt.resolve())
    except RunLockedError as exc:
        raise _refuse(f"refusing to resume: {exc}") from None
    except UnreadableFileError as exc:
        raise _refuse(f"refusing to resume {run_dir}: {exc}") from None
    except SystemExit:
        _refuse_if_in_use(run_dir)  # a resume in another process may be changing the run
        raise
    return Resume(args, run_dir, ckpt.resolve())


def run_of(ckpt: Path) -> Path:
    """The run directory of a checkpoint file (`<run>/checkpoints/<name>.ckpt`, or beside it)."""
    return ckpt.parent.parent if ckpt.parent.name == "checkpoints" else ckpt.parent


def _refuse_if_in_use(run_dir: Path) -> None:
    try:
        check_free(run_dir)
    except RunLockedError as exc:
        raise _refuse(f"refusing to resume: {exc}") from None


def resume_arguments(argv: list[str], runs_root: Path = Path("outputs/runs")) -> list[str]:
    """The command line Hydra runs for `argv`: `plan_resume(argv).args` for a resume,
    `argv` unchanged otherwise."""
    plan = plan_resume(argv, runs_root)
    return argv if plan is None else plan.args


def _copy_bounded(source: Path, target: Path) -> None:
    """Copy a config file of the run (read bounded: a YAML config) durably."""
    write_bytes_atomic(target, read_bytes(source, "YAML config", root=source.parent.parent))


def keep_earlier_records(run_dir: Path) -> Path | None:
    """Before a resume trains (holding the run's lock): move the run's records (metrics.json,
    status.json, timing.json, test_errors.json, and `CSV_LOG`, logger=csv's log, which
    Lightning's CSVLogger deletes when it starts again) and copy its `.hydra/*.yaml` into
    `<run_dir>/history/<n>/` (n = 1, 2, ... per resume), so the new attempt never overwrites
    them. The event files of the earlier test (its results, figures and HPARAMS session: the
    `test` sub-run of `tensorboard/<name>/`) move there too, renamed `events.out.kept.*` so that
    TensorBoard, which reads files named `*tfevents*`, shows one session per run: the latest
    attempt's, with its settings (it showed the first one's beside the new results). The folder
    is assembled under a hidden name and renamed into place, so it appears whole or not at all;
    the records leave the run only after that (an attempt killed midway leaves its hidden
    `.<n>.*.partial` folder, and every record in place). Returns the folder (None when the run
    had no records)."""
    records = [(run_dir / name, Path(name)) for name in _RECORDS if os.path.lexists(run_dir / name)]
    if (log := run_dir / CSV_LOG).is_file() and not log.is_symlink():  # Lightning deletes it
        records.append((log, Path(CSV_LOG)))
    for events in event_runs(run_dir):
        for path in sorted((events / SESSION_RUN).glob("*tfevents*")):
            if path.is_file() and not path.is_symlink():
                kept = path.name.replace("tfevents", "kept")
                records.append((path, path.relative_to(run_dir).with_name(kept)))
    configs = sorted(p for p in (run_dir / ".hydra").glob("*.yaml") if p.is_file())
    if not records and not configs:
        return None
    history = run_dir / HISTORY_DIR
    if os.path.lexists(history) and (history.is_symlink() or not history.is_dir()):
        raise UnreadableFileError(f"{history}: not a folder, where the earlier records are kept")
    history.mkdir(exist_ok=True)
    n = 1 + max((int(p.name) for p in earlier_attempts(run_dir)), default=0)
    target = history / str(n)
    staging = history / f".{n}.{secrets.token_hex(4)}.partial"
    (staging / ".hydra").mkdir(parents=True)  # the mode the umask allows
    try:
        for path in configs:  # copied: the run keeps a config until Hydra writes the new one
            _copy_bounded(path, staging / ".hydra" / path.name)
        for path, kept in records:  # linked, then unlinked from the run once the folder is whole
            (staging / kept).parent.mkdir(parents=True, exist_ok=True)
            os.link(path, staging / kept, follow_symlinks=False)
    except (OSError, ValueError):  # a config over its cap: the run is left as it was
        shutil.rmtree(staging, ignore_errors=True)
        with contextlib.suppress(OSError):  # made here, still empty
            history.rmdir()
        raise
    os.rename(staging, target)
    for path, _ in records:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()
    return target
