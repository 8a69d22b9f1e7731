"""rotlearn.geometry.eigen4.cpu: building, caching and loading the fused CPU kernel.

The kernel is compiled on first use into a per-user cache, keyed by source, compiler and flags,
and loaded only from private files; without a compiler (or disabled) the A layer runs its eager
path with one warning. Each test resets the process's loaded state and uses its own cache dir.
"""

from __future__ import annotations

import os
import stat
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

from rotlearn.geometry import sym4_eigh_min
from rotlearn.geometry.eigen4 import cpu
from tests.conftest import gen

needs_compiler = pytest.mark.skipif(not cpu.available(), reason="no CPU kernel here")


@pytest.fixture
def fresh(monkeypatch, tmp_path):
    """No kernel loaded in this process yet, and an empty private cache directory."""
    monkeypatch.setattr(cpu, "_state", {})
    monkeypatch.setattr(cpu, "_warned", False)
    monkeypatch.setenv("ROTLEARN_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.delenv(cpu.DISABLE_ENV, raising=False)
    return tmp_path / "cache" / "kernels"


def _sym(n: int) -> torch.Tensor:
    x = torch.randn(n, 4, 4, generator=gen(0))
    return (x + x.mT) / 2


@pytest.fixture(scope="module")
def built():
    """The library in the session's cache (tests/conftest.py: built once, at collection)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(cpu, "_state", {})
        return Path(cpu.library()._name)


@needs_compiler
def test_builds_once_into_a_private_cache_then_loads(built, monkeypatch):
    """The first use built one library in a private directory; a later process (the state
    reset) loads it without compiling again."""
    directory = built.parent
    assert built.suffix == ".so" and stat.S_IMODE(directory.stat().st_mode) == 0o700
    assert not built.stat().st_mode & (stat.S_IWGRP | stat.S_IWOTH)
    monkeypatch.setattr(cpu, "_state", {})
    monkeypatch.setenv("ROTLEARN_CACHE_DIR", str(directory.parent))

    def no_compile(*args):
        raise AssertionError("compiled again")

    monkeypatch.setattr(cpu, "_compile", no_compile)
    before = sorted(directory.iterdir())
    assert Path(cpu.library()._name) == built
    assert sorted(directory.iterdir()) == before


@needs_compiler
def test_a_changed_source_or_flag_gets_its_own_library():
    sources, compiler, version = b"int x;", "/usr/bin/cc", "cc 1"
    key = cpu._key(sources, compiler, version, cpu.FLAGS)
    assert key != cpu._key(sources + b" ", compiler, version, cpu.FLAGS)
    assert key != cpu._key(sources, compiler, "cc 2", cpu.FLAGS)
    assert key != cpu._key(sources, compiler, version, (*cpu.FLAGS, cpu.CLONES))


@needs_compiler
def test_refuses_a_cache_others_can_write(fresh):
    fresh.mkdir(parents=True)
    fresh.chmod(0o777)
    with pytest.raises(cpu.KernelUnavailableError, match="not private"):
        cpu.library()


@needs_compiler
def test_refuses_a_library_others_can_write(fresh, built):
    fresh.mkdir(parents=True, mode=0o700)
    planted = fresh / built.name  # where this build would be looked up
    planted.write_bytes(built.read_bytes())
    planted.chmod(0o777)
    with pytest.raises(cpu.KernelUnavailableError, match="writable by others"):
        cpu.library()


@pytest.mark.parametrize("cause", ["no_compiler", "compile_fails", "disabled"])
def test_without_the_kernel_auto_falls_back_to_eager_with_one_warning(
    fresh, monkeypatch, tmp_path, cause
):
    if cause == "no_compiler":
        monkeypatch.setenv("CC", "")
        monkeypatch.setenv("PATH", str(tmp_path))  # no cc, gcc or clang there
        expected = "no C compiler"
    elif cause == "compile_fails":
        fake = tmp_path / "broken-cc"
        fake.write_text("#!/bin/sh\necho 'broken-cc: error: cannot compile' >&2\nexit 1\n")
        fake.chmod(0o755)
        monkeypatch.setenv("CC", str(fake))
        expected = "cannot compile"
    else:
        monkeypatch.setenv(cpu.DISABLE_ENV, "0")
        expected = "disabled"
    with pytest.raises(cpu.KernelUnavailableError, match=expected):
        cpu.library()
    with pytest.raises(RuntimeError, match=expected):
        sym4_eigh_min(_sym(4), kernel="cpu")
    A = _sym(64)
    with pytest.warns(RuntimeWarning, match=expected):
        eigenvalues, q = sym4_eigh_min(A)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # once per process
        again = sym4_eigh_min(A)
    reference = sym4_eigh_min(A, kernel="eager")
    for x, y, z in zip((eigenvalues, q), again, reference, strict=True):
        assert torch.equal(x, z) and torch.equal(y, z)


@pytest.mark.slow
@needs_compiler
def test_concurrent_first_builds_all_succeed(tmp_path):
    """Processes that build at the same time (DDP ranks, test workers) each end with a working
    kernel: the library is compiled to a temporary name and renamed into place."""
    env = {**os.environ, "ROTLEARN_CACHE_DIR": str(tmp_path), "PYTHONWARNINGS": "ignore"}
    code = (
        "import torch; from rotlearn.geometry.eigen4 import cpu; "
        "A = torch.eye(4).expand(3, 4, 4); print(cpu.forward(A, 12)[0].sum().item())"
    )
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", code], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        for _ in range(3)
    ]
    outputs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), [err[-500:] for _, err in outputs]
    assert all(float(out) == 12.0 for out, _ in outputs)
    assert len([p for p in (tmp_path / "kernels").iterdir() if p.suffix == ".so"]) == 1
