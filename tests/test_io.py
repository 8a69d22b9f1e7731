"""rotlearn.io's one atomic write: whole or nothing, and the mode the umask allows."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest
import torch

from rotlearn.io import atomic_write, write_json_atomic, write_text_atomic


@pytest.fixture
def umask():
    """Set the process umask for a test, restored afterwards."""
    old = os.umask(0o022)
    os.umask(old)
    yield lambda mask: os.umask(mask)
    os.umask(old)


@pytest.mark.parametrize("mask", [0o022, 0o027, 0o077])
def test_every_kind_of_writer_creates_the_mode_the_umask_allows(tmp_path, umask, mask):
    umask(mask)
    write_text_atomic(tmp_path / "a.md", "text")
    write_json_atomic(tmp_path / "b.json", {"x": 1})
    with atomic_write(tmp_path / "c.npy") as tmp:
        np.save(tmp, np.arange(3))
    with atomic_write(tmp_path / "d.ckpt") as tmp:
        torch.save({"w": torch.ones(2)}, tmp)
    with atomic_write(tmp_path / "e.npy") as tmp:
        array = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.uint8, shape=(2, 2))
        array[:] = 7
        array.flush()
        del array
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.md", "b.json", "c.npy", "d.ckpt",
                                                          "e.npy"]  # fmt: skip
    for path in tmp_path.iterdir():
        assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask, path.name
    assert np.load(tmp_path / "c.npy").tolist() == [0, 1, 2]
    assert np.load(tmp_path / "e.npy").sum() == 28


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    path = write_text_atomic(tmp_path / "metrics.json", "old")
    with pytest.raises(RuntimeError, match="disk full"), atomic_write(path) as tmp:
        tmp.write_text("half")
        raise RuntimeError("disk full")
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["metrics.json"]
    write_text_atomic(path, "new")
    assert path.read_text() == "new" and len(list(tmp_path.iterdir())) == 1
