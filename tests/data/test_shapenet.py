"""ShapeNet: the 6D paper's .pts clouds and ShapeNetCore meshes, read from the demo copies."""

from __future__ import annotations

import json
import os
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from rotlearn.cli.train import train
from rotlearn.data import ShapeNetDataModule, read_point_file, sample_meshes
from rotlearn.geometry import quat_to_rotmat
from tests.conftest import SMALL_NET, tree_hashes, within

TRAIN, VAL, TEST = 0, 1, 2


def _module(root, **kw) -> ShapeNetDataModule:
    dm = ShapeNetDataModule(str(root), **{"rotations_per_cloud": 4, "test_rotations": 5, **kw})
    dm.setup("fit")
    return dm


def test_point_files_are_read_and_bad_lines_named(tmp_path):
    good = tmp_path / "a.pts"
    good.write_text("0 0 1\n1 2 3 extra\n\n-1e-3 4 5\n")
    assert np.allclose(read_point_file(good), [[0, 0, 1], [1, 2, 3], [-1e-3, 4, 5]])
    bad = tmp_path / "b.xyz"
    bad.write_text("0 0 1\n0 1\n")
    with pytest.raises(ValueError, match=r"b\.xyz:2: expected 3 numbers \(x y z\)"):
        read_point_file(bad)
    bad.write_text("0 0 one\n")
    with pytest.raises(ValueError, match=r"b\.xyz:1: not a number"):
        read_point_file(bad)


def test_pts_layout_gives_clouds_under_exact_rotations(demo_data):
    dm = _module(demo_data["pts"], num_val=1)
    assert len(dm.clouds[TRAIN]) == 5 and len(dm.clouds[TEST]) == 3 and len(dm.clouds[VAL]) == 1
    assert dm.clouds[TRAIN][0].shape == (96, 3)  # point_fraction 0.5 of the file's 192 points
    batch = dm.draw(TRAIN, 0, 4)
    x, y = batch["input"][..., :3], batch["input"][..., 3:]
    assert batch["input"].shape == (4, 96, 6)
    assert torch.allclose(y, x @ batch["R"].transpose(-1, -2), atol=1e-6)
    assert torch.allclose(quat_to_rotmat(batch["q"]), batch["R"], atol=1e-6)
    assert len(list(dm.test_dataloader())) == 3


def test_training_draws_change_with_the_epoch_and_test_draws_do_not(demo_data):
    def at_epoch(epoch):
        dm = _module(demo_data["pts"])
        dm.trainer = SimpleNamespace(current_epoch=epoch, lightning_module=None)
        return dm

    assert not torch.allclose(
        at_epoch(0).draw(TRAIN, 1, 4)["R"], at_epoch(1).draw(TRAIN, 1, 4)["R"]
    )
    assert torch.equal(at_epoch(0).draw(TRAIN, 1, 4)["R"], at_epoch(0).draw(TRAIN, 1, 4)["R"])
    assert torch.equal(at_epoch(0).draw(TEST, 2, 5)["R"], at_epoch(7).draw(TEST, 2, 5)["R"])


def test_meshes_are_sampled_once_and_cached(demo_data, tmp_path):
    dm = _module(demo_data["mesh"], format="mesh", num_train=6, num_test=3, num_points=64,
                 cache_dir=str(tmp_path))  # fmt: skip
    assert dm.clouds[TRAIN][0].shape == (64, 3) and len(dm.clouds[TEST]) == 3
    cache = next(tmp_path.glob("*.npy"))
    stamp = cache.stat().st_mtime_ns
    again = _module(demo_data["mesh"], format="mesh", num_train=6, num_test=3, num_points=64,
                    cache_dir=str(tmp_path))  # fmt: skip
    assert cache.stat().st_mtime_ns == stamp
    assert torch.equal(again.clouds[TEST][1], dm.clouds[TEST][1])
    paths = sorted(demo_data["mesh"].glob("*/*/models/model_normalized.obj"))[:2]
    other = sample_meshes(paths, 32, tmp_path / "other", seed=1)
    assert other.shape == (2, 32, 3) and np.isfinite(other).all()


def test_a_crafted_mesh_cache_is_rebuilt_not_trusted_and_never_hangs(demo_data, tmp_path):
    """A dataset may ship its cache folder: a manifest that is a named pipe (it used to hang the
    unbounded read), or a matching manifest beside an array of another shape or with NaN, is
    sampled again; the meshes are not touched."""
    paths = sorted(demo_data["mesh"].glob("*/*/models/model_normalized.obj"))[:2]
    meshes = tree_hashes(demo_data["mesh"])
    genuine = sample_meshes(paths, 16, tmp_path / "genuine")
    cache = tmp_path / "cache"
    manifest = {"files": [str(p) for p in paths], "num_points": 16, "seed": 0}
    for craft in (
        lambda: (
            cache.with_suffix(".json").unlink(),
            os.mkfifo(cache.with_suffix(".json")),
            np.save(cache.with_suffix(".npy"), genuine),
        ),
        lambda: np.save(cache.with_suffix(".npy"), np.zeros((2, 8, 3), np.float32)),
        lambda: np.save(cache.with_suffix(".npy"), np.full((2, 16, 3), np.nan, np.float32)),
        lambda: np.save(cache.with_suffix(".npy"), genuine.astype(np.float64)),
    ):
        for suffix in (".json", ".npy"):
            cache.with_suffix(suffix).unlink(missing_ok=True)
        cache.with_suffix(".json").write_text(json.dumps(manifest))
        craft()
        with within(60):
            clouds = sample_meshes(paths, 16, cache)
        np.testing.assert_array_equal(clouds, genuine)
        assert np.load(cache.with_suffix(".npy")).dtype == np.float32
    assert tree_hashes(demo_data["mesh"]) == meshes


def test_a_missing_dataset_names_the_root(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"data\.root="):
        _module(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"data\.synset="):
        _module(tmp_path, format="mesh")


def test_shapenet_trains_end_to_end(make_cfg, demo_data):
    cfg = make_cfg(["data=shapenet", f"data.root={demo_data['pts']}", "data.iterations_per_epoch=3",
                    "data.test_rotations=4", "data.rotations_per_cloud=4", "trainer=cpu",
                    "trainer.max_epochs=1", "trainer.enable_progress_bar=false", "logger=none",
                    *SMALL_NET])  # fmt: skip
    metrics = train(cfg)
    assert metrics["global_step"] == 3 and 0.0 <= metrics["test/err_mean"] <= 180.0


TRIANGLE = ["# a triangle", "v 0 0 0", "v 1 0 0", "v 0 1 0", "f 1 2 3"]


@pytest.mark.parametrize("newline", ["\n", "\r\n", "\r", "\x85", "\u2028"])
def test_a_mesh_reads_the_same_whatever_its_line_breaks(tmp_path, newline):
    """Every line break that `str.splitlines` knows splits the vertex check's lines and the
    mesh parser's alike (a line the check reads is a line trimesh reads)."""
    pytest.importorskip("trimesh")
    from rotlearn.data.shapenet import read_mesh

    path = tmp_path / "m.obj"
    path.write_bytes(newline.join(TRIANGLE).encode())
    mesh = read_mesh(path)
    assert np.asarray(mesh.vertices).tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    path.write_bytes(newline.join([*TRIANGLE, "v nan 0 0"]).encode())
    with pytest.raises(ValueError, match=r"m\.obj:6: not finite \(v x y z\)"):
        read_mesh(path)


def test_the_vertex_check_holds_a_few_times_the_text_not_a_string_per_line(tmp_path):
    """A hostile OBJ of short vertex lines: the check of its "v" rows peaks at a few times the
    file's size in Python memory (it held two lists of strings per line: ~45x)."""
    import tracemalloc

    from rotlearn.data.shapenet import _obj_vertices

    text = "v 0 0 0\n" * 400_000 + "f 1 2 3\n"
    tracemalloc.start()
    try:
        vertices = _obj_vertices(tmp_path / "m.obj", text)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert vertices.shape == (400_000, 3)
    assert peak < 15 * len(text), f"peak {peak / len(text):.1f} x the text"


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet="v0 #\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029", max_size=60))
def test_the_mesh_text_breaks_lines_where_splitlines_does(text):
    """What trimesh parses (every break written as "\\n") has the lines `str.splitlines` reads."""
    from rotlearn.data.shapenet import _LINE_BREAKS

    written = _LINE_BREAKS.sub("\n", text)
    assert (
        written.split("\n")[: len(text.splitlines())] == text.splitlines() == written.splitlines()
    )
