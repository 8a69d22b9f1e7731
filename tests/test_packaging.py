"""Packaging: the math imports with torch and numpy alone, modules of an extra name it when it is
missing, the extras cover what rotlearn imports, and the version has one source.

The bare install itself (a fresh virtual environment with `pip install .`) is checked by .ci/run;
here a subprocess hides the optional libraries from the import system instead.
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import rotlearn
from rotlearn.extras import EXTRAS

ROOT = Path(__file__).resolve().parents[1]
SRC = Path(rotlearn.__file__).resolve().parents[1]  # the rotlearn under test, for subprocesses

# Every library of an extra, by import name (lightning's own packages too).
OPTIONAL = sorted(
    {
        *EXTRAS["train"],
        *EXTRAS["data"],
        *EXTRAS["gpu"],
        "lightning_fabric",
        "pytorch_lightning",
        "annotated_types",
    }
)
CORE = [
    "rotlearn",
    "rotlearn.geometry",
    "rotlearn.heads",
    "rotlearn.bingham",
    "rotlearn.fisher",
    "rotlearn.losses",
    "rotlearn.nets",
]
HAS_NN = importlib.util.find_spec("rotlearn.nn") is not None
NO_NN = "rotlearn.nn is not in this tree yet (the drop-in layers land separately)"

# import name -> distribution name in pyproject.toml, where they differ
DISTRIBUTIONS = {
    "hydra": "hydra-core",
    "yaml": "pyyaml",
    "cv2": "opencv-python-headless",
    "skimage": "scikit-image",
}


def run_without_extras(code: str) -> subprocess.CompletedProcess:
    """Run `code` in a fresh interpreter where every library of an extra is not installed.

    A `None` in sys.modules is what the import system reads as "not installed": `import x`
    raises ModuleNotFoundError and `importlib.util.find_spec("x")` returns None, as in a bare
    environment (torch probes optional libraries with find_spec, so a finder that raised there
    would break torch itself, not rotlearn).
    """
    prelude = f"import sys\nfor _name in {OPTIONAL!r}:\n    sys.modules[_name] = None\n"
    path = os.pathsep.join([str(SRC), os.environ.get("PYTHONPATH", "")])
    env = {**os.environ, "PYTHONPATH": path}
    return subprocess.run(
        [sys.executable, "-c", prelude + textwrap.dedent(code)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
        check=False,
    )


def assert_ok(result: subprocess.CompletedProcess) -> None:
    assert result.returncode == 0, result.stderr[-3000:]


def test_math_imports_with_torch_and_numpy_only():
    result = run_without_extras(
        f"""
        import importlib
        for name in {CORE!r}:
            importlib.import_module(name)
        loaded = sorted({{m.partition(".")[0] for m in sys.modules if sys.modules[m] is not None}})
        print(" ".join(loaded))
        """
    )
    assert_ok(result)
    loaded = set(result.stdout.split())
    assert "rotlearn" in loaded
    assert not loaded & set(OPTIONAL), loaded & set(OPTIONAL)


@pytest.mark.skipif(not HAS_NN, reason=NO_NN)
def test_nn_layers_import_with_torch_and_numpy_only():
    result = run_without_extras(
        """
        import rotlearn
        import rotlearn.nn
        for name in rotlearn.__all__:
            getattr(rotlearn, name)
        """
    )
    assert_ok(result)


def test_constrained_constructors_work_without_pydantic():
    """The constraints on the nets' and heads' signatures (annotated-types metadata, read by
    rotlearn.config) are never evaluated by the modules themselves."""
    result = run_without_extras(
        """
        import torch
        from rotlearn.heads import make_head
        from rotlearn.nets import ConvAutoEncoder, PairCorrelationNet, PointNet

        raw = PointNet(out_dim=10, point_channels=(8, 16), head_channels=(8,))(torch.randn(2, 5, 6))
        print(make_head("a")(raw).q.shape, PairCorrelationNet(4, image_size=16).radius,
              ConvAutoEncoder(image_size=16, channels=(4, 8)).in_channels)
        """
    )
    assert_ok(result)
    assert result.stdout.split() == ["torch.Size([2,", "4])", "2", "3"]


def test_the_a_layer_runs_without_triton_and_its_kernel_names_the_gpu_extra():
    result = run_without_extras(
        """
        import torch
        from rotlearn.geometry import sym4_eigh_min
        eigenvalues, q = sym4_eigh_min(torch.eye(4).expand(3, 4, 4))  # the CPU paths need no triton
        sym4_eigh_min(torch.eye(4), kernel="triton")
        """
    )
    assert result.returncode != 0
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("rotlearn.extras.MissingExtraError"), last
    assert "pip install 'rotlearn[gpu]'" in last


def test_import_rotlearn_is_light():
    """The top-level names are imported on first use, not by `import rotlearn`."""
    result = run_without_extras(
        """
        import rotlearn
        print(sorted(m for m in sys.modules if m.startswith("rotlearn")))
        """
    )
    assert_ok(result)
    assert result.stdout.strip() == "['rotlearn']"


@pytest.mark.parametrize(
    "module",
    ["rotlearn.lit", "rotlearn.config", "rotlearn.cli.train", "rotlearn.data", "rotlearn.metrics"],
)
def test_modules_of_the_train_extra_name_it(module):
    result = run_without_extras(f"import {module}")
    assert result.returncode != 0
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("rotlearn.extras.MissingExtraError"), last
    assert "pip install 'rotlearn[train]'" in last


def test_load_names_the_train_extra(tmp_path):
    result = run_without_extras(f"import rotlearn; rotlearn.load({str(tmp_path)!r})")
    assert result.returncode != 0
    assert "pip install 'rotlearn[train]'" in result.stderr.strip().splitlines()[-1]


def test_data_writers_name_the_data_extra():
    result = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; sys.modules['cv2'] = None; import rotlearn.data.demo.synth",
        ],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(SRC)},
        timeout=300,
        check=False,
    )
    assert result.returncode != 0
    assert "pip install 'rotlearn[data]'" in result.stderr.strip().splitlines()[-1]


def test_top_level_all_is_what_it_exports():
    assert {"__version__", "load"} <= set(rotlearn.__all__)
    assert len(set(rotlearn.__all__)) == len(rotlearn.__all__)
    with pytest.raises(AttributeError, match="no attribute 'nothing_such'"):
        rotlearn.nothing_such  # noqa: B018


def test_installed_version_is_the_package_version():
    try:
        installed = importlib.metadata.version("rotlearn")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("rotlearn is not installed in this environment (sources on PYTHONPATH only)")
    assert installed == rotlearn.__version__


def pyproject() -> dict:
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def requirement_name(requirement: str) -> str:
    return re.split(r"[\s<>=!~;\[]", requirement, maxsplit=1)[0].lower()


def test_the_package_requires_torch_and_numpy_only():
    project = pyproject()["project"]
    assert sorted(map(requirement_name, project["dependencies"])) == ["numpy", "torch"]
    assert "version" in project["dynamic"]  # read from rotlearn.__version__ (one source)


def test_every_library_of_an_extra_is_declared_in_it():
    extras = pyproject()["project"]["optional-dependencies"]
    for extra, modules in EXTRAS.items():
        declared = set(map(requirement_name, extras[extra]))
        for module in modules:
            assert DISTRIBUTIONS.get(module, module) in declared, (extra, module)
    assert extras["all"] == ["rotlearn[train,data]"]


def test_the_dev_environment_is_pinned_by_constraints():
    constraints = (ROOT / "constraints.txt").read_text()
    assert re.search(r"^torch==\d", constraints, flags=re.M)
    assert "-c constraints.txt" in (ROOT / "Makefile").read_text()


def test_py_typed_is_shipped():
    assert (Path(rotlearn.__file__).parent / "py.typed").is_file()


def _imported_modules(package: str) -> set[str]:
    """Every rotlearn module a package's (or module's) source files import, at any depth of
    the code."""
    import ast

    root = Path(__file__).resolve().parents[1] / "src" / "rotlearn" / package
    names: set[str] = set()
    for path in root.rglob("*.py") if root.is_dir() else [root]:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module:
                names.add(node.module)
            elif isinstance(node, ast.Import):
                names.update(alias.name for alias in node.names)
    return {n for n in names if n.startswith("rotlearn")}


def test_lit_and_ood_never_import_each_other_and_scores_import_neither():
    """The house's one-way rule: the OOD evaluation and the training glue meet only below them
    (`rotlearn.scores`, the data protocol), never in each other's code."""
    assert not {n for n in _imported_modules("lit") if n.startswith("rotlearn.ood")}
    assert not {n for n in _imported_modules("ood") if n.startswith("rotlearn.lit")}
    below = _imported_modules("scores.py")
    assert below and not {n for n in below if n.startswith(("rotlearn.lit", "rotlearn.ood"))}
