"""The command lines start without the training stack when they do not need it: `--help` of
rotlearn-train, -eval and -predict and `rotlearn-report` never import Lightning, and each help
lists what its command takes (checked in a fresh interpreter)."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from rotlearn.cli.train import usage
from rotlearn.paths import config_dir
from tests.conftest import doubling


def _modules_after(code: str) -> tuple[str, set[str]]:
    """Run `code` in a fresh interpreter; its stdout and the top-level modules it imported."""
    listing = "print('MODULES', *sorted({m.split('.')[0] for m in sys.modules}))"
    script = f"{code}\nimport sys\n{listing}"
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=300, check=True
    )
    out, _, modules = result.stdout.rpartition("MODULES ")
    return out, set(modules.split())


def test_train_help_lists_the_config_without_importing_lightning():
    out, modules = _modules_after(
        "import sys\nsys.argv = ['rotlearn-train', '--help']\n"
        "from rotlearn.cli.train import main\nmain()"
    )
    assert "lightning" not in modules and "hydra" in modules
    assert re.search(r"^  rep +a, fisher, quat, sixd, svd9d$", out, re.MULTILINE)
    assert "  seed: 0" in out and "--cfg job" in out


def test_the_help_lists_every_config_group_and_option():
    text = usage()
    for group in ("model", "rep", "net", "data", "loss", "optim", "trainer", "logger"):
        options = sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))
        assert f"  {group:<10}  {', '.join(options)}" in text
    assert "_schema" not in text and "hydra/" not in text  # internal nodes stay out
    # a key's comment is shown whole (calibrate's stopped at "for the tested weights:")
    assert "# belief (rep=a, fisher); true: required; false: off" in text
    assert "output_dir" not in text  # paths: its comment lines stay out with it


def test_eval_help_lists_what_it_takes_without_the_training_stack():
    out, modules = _modules_after(
        "import sys\nsys.argv = ['rotlearn-eval', '--help']\n"
        "from rotlearn.cli.evaluate import main\nmain()"
    )
    assert "lightning" not in modules and "torch" not in modules
    assert out.startswith("rotlearn-eval: ") and "usage: rotlearn-eval ckpt=" in out
    for key in ("ckpt: ???", "expect_rep:", "quantiles:", "root:", "accelerator:", "ood_quantile",
                "'ckpt=[outputs/sweep/0,"):  # fmt: skip
        assert key in out, key
    assert out.count("test a trained") == 1  # said once
    for option in ("svd9d", "pointnet", "experiment"):  # the train config's groups do not apply
        assert option not in out, option


def test_predict_help_lists_what_it_takes_without_torch():
    out, modules = _modules_after(
        "from rotlearn.cli.predict import main\ntry:\n    main(['--help'])\n"
        "except SystemExit:\n    pass"
    )
    assert "torch" not in modules
    for item in ("checkpoint", "input", "--device", "--json", "run directory", ".npy"):
        assert item in out, item


def test_report_imports_without_lightning():
    _, modules = _modules_after(
        "import rotlearn.cli.report\nfrom rotlearn.report import make_report"
    )
    assert "lightning" not in modules and "pandas" in modules


def test_the_ood_callback_still_imports_from_its_package():
    from rotlearn.ood import OODEvaluation
    from rotlearn.ood.callback import OODEvaluation as direct

    assert OODEvaluation is direct


def test_a_refused_value_is_answered_before_torch_loads():
    """A value whose annotation its source tells (a rotlearn component's, or one rotlearn
    narrows for a library class) is refused before torch or Lightning is imported: in a second,
    where importing them took 5-8 s (`make bench ARGS=cli_errors` measures it)."""
    out, modules = _modules_after(
        "from rotlearn.config import ConfigError, compose\n"
        "for override in ('data.batch_size=0', 'optim.lr=abc', 'trainer.max_epochs=0'):\n"
        "    try:\n"
        "        compose([override])\n"
        "    except ConfigError as exc:\n"
        "        print(exc)"
    )
    assert "torch" not in modules and "lightning" not in modules
    assert out.splitlines() == [
        "config key data.batch_size: should be greater than 0, got 0",
        "config key optim.lr: should be a valid number, got 'abc'",
        "config key trainer.max_epochs: must be a positive integer (Lightning reads -1 as 'train "
        "forever', 0 as no training), got 0",
    ]


@pytest.mark.parametrize("run_kind", ["synthetic data", "a pickle past the bounds"])
def test_eval_refuses_a_run_it_cannot_use_before_torch_loads(tmp_path, run_kind):
    """rotlearn-eval reads a checkpoint's config without torch (`saved_config`), so OOD
    callbacks on a synthetic run, or a file whose pickle holds 2**40 values through shared
    references, are refused in a second or two, not after torch's import (2 s on 2 cores), and
    nothing is written."""
    import torch

    from rotlearn.config import compose
    from rotlearn.config.checks import plain
    from rotlearn.io import MAX_NODES

    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    config = plain(compose(["data=tiny"], output_dir=run))
    if run_kind == "a pickle past the bounds":
        config["data"] = doubling(config["data"])  # one object per level, memoised once
    torch.save({"rotlearn_config": config, "state_dict": {}}, run / "checkpoints" / "last.ckpt")
    out, modules = _modules_after(
        "from rotlearn.cli.evaluate import _checked\n"
        "try:\n"
        f"    _checked(['ckpt={run}', 'hydra.run.dir={tmp_path / 'eval'}'])\n"
        "except SystemExit as exc:\n"
        "    print(exc)"
    )
    assert "torch" not in modules and "lightning" not in modules
    expected = {
        "synthetic data": f"config key ckpt: {run} is no image-pair run: rotlearn-eval tests a "
        "run again with the OOD evaluation, which needs an image-pair datamodule",
        "a pickle past the bounds": f"config key ckpt: {run}: {run / 'checkpoints' / 'last.ckpt'} "
        f"is not a checkpoint rotlearn reads: more than {MAX_NODES} values",
    }[run_kind]
    assert expected in out
    assert not (tmp_path / "eval").exists()
