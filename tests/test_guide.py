"""The user guide (docs/guide/) stays true: every code block is run.

`make test` checks each page's blocks quickly: every command composes and validates as a config
(no training), and the Python blocks that need no trained run are executed. `make test-full`
walks the guide from its first page to its last in one folder, as a reader would: every command
runs (rotlearn-train at a tiny size: the tiny synthetic data or a small KITTI demo, one or two
epochs) and every Python block is executed against the runs the commands made. A block preceded
by `<!-- not run: <why> -->` is skipped, and must say why.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import SMALL_NET, make_data_layout

GUIDE = Path(__file__).resolve().parents[1] / "docs" / "guide"
BLOCK = re.compile(
    r"(<!-- not run: (?P<why>[^>]*)-->\n)?```(?P<lang>bash|python)\n(?P<code>.*?)```", re.S
)
# Python blocks that read a run the guide's commands make (run by the walk only)
NEEDS_RUNS = re.compile(r"rotlearn\.load|outputs/")
TINY = ["data=tiny", "trainer=cpu", "trainer.enable_progress_bar=false", "trainer.max_epochs=1",
        *SMALL_NET]  # fmt: skip
TINY_KITTI = ["data.train_sequences=[02]", "data.test_sequences=[00]", "data.image_size=16",
              "data.num_workers=0", "data.eval_batch_size=4", "net.channels=[8,8,8,8]",
              "net.hidden=16", "trainer=cpu", "trainer.enable_progress_bar=false",
              "trainer.max_epochs=1", "callbacks.ood.noise_pairs=4"]  # fmt: skip


def pages() -> list[Path]:
    """The guide's pages in the order of its table of contents."""
    toc = (GUIDE / "index.md").read_text().split("```{toctree}")[1].split("```")[0]
    names = [line.strip() for line in toc.splitlines() if line.strip() and ":" not in line]
    return [GUIDE / f"{name}.md" for name in names]


def blocks(page: Path) -> list[tuple[str, str, str | None]]:
    """(language, code, why not run or None) of each bash and python block of a page."""
    return [(m["lang"], m["code"], m["why"]) for m in BLOCK.finditer(page.read_text())]


def commands(code: str) -> list[list[str]]:
    """The command lines of a bash block, comments dropped."""
    lines = [line.split(" #", 1)[0].strip() for line in code.splitlines()]
    return [shlex.split(line) for line in lines if line and not line.startswith("#")]


def _key(arg: str) -> str:
    return arg.lstrip("+~").split("=", 1)[0]


def sized(args: list[str]) -> list[str]:
    """A guide's rotlearn-train arguments at test size: the tiny settings it does not set
    itself, at most two epochs. A resume (ckpt_path=) replays its run's settings: epochs only."""
    args = [f"trainer.max_epochs={min(2, int(a.split('=')[1]))}"
            if a.startswith("trainer.max_epochs=") else a for a in args]  # fmt: skip
    if any(a.startswith("ckpt_path=") for a in args):
        return args
    extra = TINY_KITTI if "data=kitti" in args else TINY
    if "data=kitti" in args:
        extra = [a for a in extra if not a.startswith("data=")]
    return [*args, *[a for a in extra if _key(a) not in {_key(b) for b in args}]]


def test_every_block_of_the_guide_is_run_or_says_why_not():
    seen = 0
    for page in pages():
        assert page.is_file(), page
        for language, code, why in blocks(page):
            seen += 1
            assert why is None or len(why.strip()) > 10, (page.name, code)
            if language == "python":
                compile(code, str(page), "exec")
            else:
                for line in commands(code) if why is None else []:
                    assert line[0].startswith("rotlearn-"), (page.name, line)
    assert seen > 20


def _expand(args: list[str]) -> list[list[str]]:
    """The jobs of a `-m` command line, each swept key's values as Hydra's parser reads them
    (`a,b`, `range(3,5)`, ...)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    options = []
    for arg in (a for a in args if a != "-m"):
        override = OverridesParser.create().parse_override(arg)
        if override.is_sweep_override():
            key = override.get_key_element()
            options.append([f"{key}={v}" for v in override.sweep_string_iterator()])
        else:
            options.append([arg])
    return [list(job) for job in itertools.product(*options)]


@pytest.mark.parametrize("page", pages(), ids=lambda p: p.stem)
def test_each_page_composes_its_commands_and_runs_its_standalone_code(page, tmp_path, monkeypatch):
    from rotlearn.config import command_line, command_line_config, compose

    monkeypatch.chdir(tmp_path)  # where the commands' data folders are laid out (empty)

    for language, code, why in blocks(page):
        if why is not None:
            continue
        if language == "python":
            if not NEEDS_RUNS.search(code):
                _exec(code, page, tmp_path)
            continue
        for line in commands(code):
            if line[0] == "rotlearn-train" and not any(a.startswith("ckpt_path=") for a in line):
                if "-m" in line:  # the sweep as written (a sweep of a `hydra.*` key is refused)
                    command_line_config(line[1:], str(tmp_path / "run"))
                for job in _expand(line[1:]):
                    args = [a for a in sized(job) if not a.startswith("-")]
                    make_data_layout(compose(args, output_dir=tmp_path / "run", check=False))
                    command_line(sized(job), str(tmp_path / "run"))


def _exec(code: str, page: Path, cwd: Path) -> None:
    old = Path.cwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            exec(compile(code, str(page), "exec"), {"__name__": f"guide_{page.stem}"})
    finally:
        os.chdir(old)


def _run(line: list[str], cwd: Path) -> str:
    """One guide command in `cwd`: rotlearn-train and -eval in a subprocess (Hydra apps),
    rotlearn-report and -predict in this process. Returns what it printed."""
    if line[0] in ("rotlearn-report", "rotlearn-predict"):
        from rotlearn.cli import predict, report

        main = {"rotlearn-report": report.main, "rotlearn-predict": predict.main}[line[0]]
        out = io.StringIO()
        old = Path.cwd()
        os.chdir(cwd)
        try:
            with contextlib.redirect_stdout(out):
                assert main(line[1:]) == 0, line
        finally:
            os.chdir(old)
        return out.getvalue()
    script = Path(sys.executable).parent / line[0]  # the installed console script
    args = sized(line[1:]) if line[0] == "rotlearn-train" else line[1:]
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "PYTHONWARNINGS": "ignore"}
    result = subprocess.run([str(script), *args], cwd=cwd, env=env, capture_output=True,
                            text=True, timeout=600)  # fmt: skip
    assert result.returncode == 0, (line, result.stderr[-3000:])
    return result.stdout + result.stderr


@pytest.mark.slow
def test_the_guide_runs_from_its_first_page_to_its_last(tmp_path):
    from rotlearn.data.demo.kitti import write_kitti_demo

    # what `rotlearn-make-demo-data --only kitti` writes, smaller
    write_kitti_demo(tmp_path / "data" / "demo", sequences=("00", "02"), frames=6, width=62,
                     height=19)  # fmt: skip
    printed = {}
    for page in pages():
        for language, code, why in blocks(page):
            if why is not None:
                continue
            if language == "python":
                _exec(code, page, tmp_path)
                continue
            for line in commands(code):
                printed[" ".join(line)] = _run(line, tmp_path)
    predicted = printed["rotlearn-predict outputs/first outputs/pairs.txt"]
    assert "rotation" in predicted and "90 % of the belief lies within it" in predicted
    assert "note:" not in predicted  # the example's u_i are unit vectors, as in training
    assert (tmp_path / "outputs" / "grid" / "curves.png").is_file()
    assert "| a |" in (tmp_path / "outputs" / "grid-by-rep" / "report.md").read_text()
    assert (tmp_path / "outputs" / "ood" / "ood.md").is_file()
    assert (tmp_path / "outputs" / "belief" / "checkpoints" / "temperature.json").is_file()
    seeds = tmp_path / "outputs" / "seeds-3-4"  # trial='range(3,5)': two jobs, trials 3 and 4
    for job, trial in (("0", 3), ("1", 4)):
        assert f"- trial={trial}\n" in (seeds / job / ".hydra" / "overrides.yaml").read_text()
    assert not (seeds / "2").exists()
