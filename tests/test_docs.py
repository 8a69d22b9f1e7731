"""The worked examples of docs/architecture.md run as written: a new head, a new dataset and a
new OOD score, each trained or evaluated end to end; the head and the dataset are validated like
rotlearn's own components with no file touched but their module and their one YAML file."""

from __future__ import annotations

import importlib.util
import re
import shutil
import sys
from pathlib import Path

import pytest
import torch

from tests.conftest import CONFIG_DIR, SMALL_NET

DOC = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"


def examples(name: str) -> list[tuple[str, str]]:
    """(language, code) of each block marked `<!-- example: name -->` in the document."""
    pattern = rf"<!-- example: {name} -->\n```(\w+)\n(.*?)```"
    return re.findall(pattern, DOC.read_text(), flags=re.S)


def load_module(name: str, code: str, tmp_path: Path):
    """Import `code` as the module `name` (as if it were a file of the package)."""
    path = tmp_path / f"{name.rsplit('.', 1)[-1]}.py"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(code)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture
def cleanup():
    from rotlearn.heads import HEADS
    from rotlearn.scores import SCORES

    before = (dict(HEADS), dict(SCORES), set(sys.modules))
    yield
    for registry, saved in ((HEADS, before[0]), (SCORES, before[1])):
        registry.clear()
        registry.update(saved)
    for name in set(sys.modules) - before[2]:
        if name.startswith("rotlearn."):
            del sys.modules[name]


@pytest.fixture
def conf(tmp_path: Path) -> Path:
    """A copy of conf/, for the example's one YAML file (nothing else is added or changed)."""
    return Path(shutil.copytree(CONFIG_DIR, tmp_path / "conf"))


def _compose(conf: Path, tmp_path: Path, overrides: list[str]):
    from rotlearn.config import compose

    quiet = ["trainer=cpu", "trainer.enable_progress_bar=false", "logger=none", *SMALL_NET]
    return compose([*quiet, *overrides], root=conf, output_dir=tmp_path / "run")


def test_the_head_example_is_validated_and_trains(conf, tmp_path, cleanup):
    from rotlearn.cli.train import train
    from rotlearn.config import ConfigError

    (_, code), (_, yaml) = examples("head")
    load_module("rotlearn.heads.rotvec", code, tmp_path)
    (conf / "rep" / "rotvec.yaml").write_text(yaml)
    with pytest.raises(ConfigError, match=r"rep\.out_dimm: unknown key; did you mean rep\.out_dim"):
        _compose(conf, tmp_path, ["rep=rotvec", "data=tiny", "rep.out_dimm=3"])
    with pytest.raises(ConfigError, match=r"rep\.out_dim: is 4 but the 'rotvec' head outputs 3"):
        _compose(conf, tmp_path, ["rep=rotvec", "data=tiny", "rep.out_dim=4"])
    cfg = _compose(conf, tmp_path, ["rep=rotvec", "data=tiny", "trainer.fast_dev_run=true"])
    metrics = train(cfg)
    assert metrics["rep"] == "rotvec" and 0.0 <= metrics["test/err_mean"] <= 180.0


def test_the_dataset_example_is_validated_writes_its_demo_and_trains(conf, tmp_path, cleanup):
    from rotlearn.cli.train import train
    from rotlearn.config import ConfigError
    from rotlearn.trust import is_trusted_target

    (_, code), (_, writer), (_, yaml) = examples("dataset")
    module = load_module("rotlearn.data.npz_pairs", code, tmp_path)
    demo = load_module("rotlearn.data.demo.npz_pairs", writer, tmp_path / "demo")
    (conf / "data" / "npz_pairs.yaml").write_text(yaml)
    (root,) = demo.write_demo(tmp_path, seed=0)
    assert root == tmp_path / "npz_pairs" and len(list(root.glob("*/*.npz"))) == 24
    assert is_trusted_target("rotlearn.data.npz_pairs.NpzPairsDataModule")
    with pytest.raises(FileNotFoundError, match=r"no \.npz files"):
        module.read_split(tmp_path / "nowhere", "train")
    data = ["data=npz_pairs", f"data.root={root}"]
    refused = {
        "data.batch_sise=4": r"data\.batch_sise: unknown key; did you mean data\.batch_size\?",
        "data.batch_size=0": r"data\.batch_size: should be greater than 0, got 0",
        f"data.root={tmp_path / 'nowhere'}": r"data\.root: no directory .*nowhere; it must hold "
        r"train, test",
        f"data.root={root / 'train'}": r"data\.root: .*train lacks train, test",
    }
    for override, message in refused.items():
        with pytest.raises(ConfigError, match=message):
            _compose(conf, tmp_path, [*data, override])
    metrics = train(_compose(conf, tmp_path, [*data, "trainer.max_epochs=1"]))
    assert 0.0 <= metrics["test/err_mean"] <= 180.0


def test_the_score_example_is_evaluated(cleanup):
    from rotlearn.heads import make_head
    from rotlearn.ood import OODEvaluation
    from rotlearn.ood.evaluation import evaluate
    from rotlearn.scores import SCORES, available_scores

    ((_, code),) = examples("score")
    exec(compile(code, str(DOC), "exec"), {})
    head = make_head("a")
    g = torch.Generator().manual_seed(0)
    batch = {"input": torch.randn(64, 10, generator=g), "R": torch.eye(3).expand(64, 3, 3)}
    flags = {"clean": torch.zeros(64, dtype=torch.bool)}
    flags["clean"][32:] = True
    scores = available_scores(["dt", "gap_ratio"], True, False)
    frame = evaluate(head, {"val": [batch], "clean": [batch]}, flags, scores, [0.5])
    rows = frame[frame["score"] == "gap_ratio"]
    assert len(rows) == 1 and rows["kept_pct"].iloc[0] == pytest.approx(50.0, abs=2.0)
    assert SCORES["gap_ratio"].keep_below is False
    OODEvaluation(scores=["dt", "gap_ratio"])  # the callback accepts its name


def test_file_names_and_placeholders_in_a_docstring_are_shown_as_written():
    """The docstrings' default role (docs/conf.py) shows `.hydra/config.yaml` and `<out>/<name>`
    as written; with Python's `obj` role the docs site read the dot as a relative lookup and
    showed "hydra/config.yaml", and read `<name>` as a link target and showed "<out>/"."""
    spec = importlib.util.spec_from_file_location("docs_conf", DOC.parent / "conf.py")
    conf = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(conf)
    assert conf.default_role == "code-or-xref"
    for text in (".hydra/config.yaml", "<out>/<name>", "rotlearn.data.<name>"):  # placeholders:
        (node,), messages = conf._code_or_xref("", f"`{text}`", text, 1, None)  # were dropped
        assert node.astext() == text and node.tagname == "literal" and messages == []


def test_no_documented_class_names_a_private_base():
    """The API pages show each class's bases ("Bases: ..."); a private base (`_Open`, once the
    report layout's) is shown as a name the reader can neither look up nor import."""
    modules = re.findall(r"\.\. automodule:: (\S+)", "".join(
        page.read_text() for page in sorted((DOC.parent / "api").glob("*.rst"))))  # fmt: skip
    private = []
    for name in modules:
        module = importlib.import_module(name)
        public = [
            v for k, v in vars(module).items() if not k.startswith("_") and isinstance(v, type)
        ]
        for cls in (c for c in public if c.__module__.startswith("rotlearn")):
            bases = [b for b in cls.__bases__ if b.__module__.startswith("rotlearn")]
            private += [f"{cls.__qualname__}({b.__name__})" for b in bases if b.__name__[0] == "_"]
    assert modules and not private, private
