"""The README's examples run as written: the drop-in layer, composing a config in Python."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

README = Path(__file__).resolve().parents[1] / "README.md"
HEADING = "## Use the A layer in your own model"


def section_code(heading: str) -> str:
    """The first ```python block after `heading` (and before the next section)."""
    text = README.read_text()
    assert heading in text, f"README has no section {heading!r}"
    section = text.split(heading, 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```python\n(.*?)```", section, flags=re.S)
    assert blocks, f"README section {heading!r} has no python block"
    return blocks[0]


def test_drop_in_example_runs_and_trains():
    code = section_code(HEADING)
    assert len(code.strip().splitlines()) <= 16  # stays a short example
    namespace: dict = {}
    torch.manual_seed(0)
    exec(compile(code, str(README), "exec"), namespace)
    model, q, loss = namespace["model"], namespace["q"], namespace["loss"]
    assert q.shape == (8, 4) and bool(torch.isfinite(loss))
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(8), atol=1e-5, rtol=0)
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None and bool(torch.isfinite(g).all()) for g in grads)
    assert any(bool(g.abs().sum() > 0) for g in grads)


def test_the_compose_example_builds_a_validated_config(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # compose writes nothing; a run of it would go to outputs/
    namespace: dict = {}
    exec(compile(section_code("### Compose a config in Python"), str(README), "exec"), namespace)
    cfg, model = namespace["cfg"], namespace["model"]
    assert cfg.loss._target_ == "rotlearn.losses.BinghamNLLLoss" and model.head.name == "a"
    assert cfg.paths.output_dir.startswith("outputs/runs/") and not list(tmp_path.iterdir())


GROUP_TABLES = [README, README.parent / "docs" / "guide" / "commands.md"]
CONF = README.parent / "conf"


def table_options(cell: str) -> set[str]:
    """The options a cell names: each `name`; `x` (+ `_s`) also x_s, `x`, `y` (each + `_s`)
    also x_s and y_s (the names since the last such note); other parentheses are comments."""
    names, since = set(), []
    for m in re.finditer(r"\((each )?\+ `(\w+)`\)|\([^)]*\)|`(\w+)`", cell):
        if m[2]:
            names |= {n + m[2] for n in (since if m[1] else since[-1:])}
            since = []
        elif m[3]:
            names.add(m[3])
            since.append(m[3])
    return names


@pytest.mark.parametrize("doc", GROUP_TABLES, ids=lambda p: p.name)
def test_the_config_group_tables_list_every_option_and_no_other(doc):
    """The group table (`| group | options | ...`) of the README and of the guide names exactly
    the options in conf/<group>/ for each group, and has a row for every group of conf/."""
    table = doc.read_text().split("\n| group ", 1)[1].split("\n\n", 1)[0]
    listed = {}
    for groups, cell in re.findall(r"^\| ((?:`\w+`(?: / )?)+) \| ([^|]*) \|", table, flags=re.M):
        for group, part in zip(re.findall(r"`(\w+)`", groups), cell.split(" / "), strict=True):
            listed[group] = table_options(part)
    real = {p.name: {f.stem for f in p.glob("*.yaml")} for p in CONF.iterdir() if p.is_dir()}
    del real["hydra"]  # launcher plugins' configs, not a group of train.yaml
    assert listed == real
