"""ShapeNet: the 6D paper's .pts clouds and ShapeNetCore meshes, read from the demo copies."""

from __future__ import annotations

import json
import os
from types import SimpleNamespace

import numpy as np
import pytest
import torch

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
    manifest = json.loads((tmp_path / "genuine.json").read_text())  # matches the meshes
    for craft in (
        lambda: (
            cache.with_suffix(".json").unlink(),
            os.mkfifo(cache.with_suffix(".json")),
            np.save(cache.with_suffix(".npy"), genuine),
        ),
        lambda: np.save(cache.with_suffix(".npy"), np.zeros((2, 8, 3), np.float32)),
        lambda: np.save(cache.with_suffix(".npy"), np.full((2, 16, 3), np.nan, np.float32)),
        lambda: np.save(cache.with_suffix(".npy"), genuine.astype(np.float64)),
        lambda: np.save(cache.with_suffix(".npy"), np.full((2, 16, 3), 3e38, np.float32)),
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


def test_an_edited_mesh_is_sampled_again(demo_data, tmp_path):
    """The cache's manifest held the meshes' names only: a mesh edited since kept its old
    clouds. It holds each file's size and modification time too."""
    import shutil

    folder = tmp_path / "meshes"
    shutil.copytree(demo_data["mesh"] / "02691156", folder)
    paths = sorted(folder.glob("*/models/model_normalized.obj"))[:2]
    before = sample_meshes(paths, 16, tmp_path / "cache")
    lines = paths[1].read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("v "))
    lines[first] = "v 0.9 0.9 0.9"  # one vertex moved
    paths[1].write_text("\n".join(lines))
    after = sample_meshes(paths, 16, tmp_path / "cache")
    np.testing.assert_array_equal(after[0], before[0])
    assert not np.array_equal(after[1], before[1])


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


def test_a_mesh_holds_a_few_times_its_text_not_a_string_per_line(tmp_path):
    """A hostile OBJ of short lines: reading it peaks at a few times the file's size in Python
    memory (it held two lists of strings per line: ~45x)."""
    import tracemalloc

    from rotlearn.data.shapenet import read_obj

    path = tmp_path / "m.obj"
    path.write_text("v 0 0 0\n" * 200_000 + "f 1 2 3\n" * 200_000)
    tracemalloc.start()
    try:
        vertices, faces = read_obj(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert vertices.shape == (200_000, 3) and faces.shape == (200_000, 3)
    assert peak < 15 * path.stat().st_size, f"peak {peak / path.stat().st_size:.1f} x the file"


def test_an_obj_file_is_read_as_the_obj_format_says(tmp_path):
    """Corners with texture and normal indices, negative (relative) and forward indices,
    polygons fanned, extra vertex numbers (w, colours) ignored, tabs, a byte-order mark, and
    every line but v and f skipped (no file a line names is read)."""
    from rotlearn.data.shapenet import read_obj

    path = tmp_path / "m.obj"
    text = ("\ufeffv 0 0 0 1\nv\t1 0 0\nmtllib ../../../../etc/passwd\nusemtl a\nvt 0 0\n"
            "v 1 1 0 0.5 0.5 0.5\nv 0 1 0\nf 1/1 2/1/1 3//1 4\ng x\nf -4 -3 5\n"
            "v 0 0 1\n")  # fmt: skip
    path.write_text(text, encoding="utf-8")
    vertices, faces = read_obj(path)
    assert vertices.tolist() == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1]]
    assert faces.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 4]]


def test_the_demo_meshes_read_as_trimesh_reads_them(demo_data):
    """rotlearn's OBJ reader against trimesh's on the demo's meshes: the same vertices and
    triangles, so the sampled clouds are the ones trimesh's reader gave."""
    trimesh = pytest.importorskip("trimesh")
    from rotlearn.data.shapenet import read_obj

    for path in sorted(demo_data["mesh"].glob("02691156/*/models/model_normalized.obj"))[:4]:
        vertices, faces = read_obj(path)
        reference = trimesh.load(path, file_type="obj", force="mesh", process=False)
        np.testing.assert_array_equal(vertices, np.asarray(reference.vertices, np.float32))
        np.testing.assert_array_equal(faces, np.asarray(reference.faces))


def test_a_mesh_of_many_materials_reads_in_one_pass(tmp_path):
    """20,000 `usemtl` lines (0.4 MB) took 138 s in trimesh's reader (a mesh per material, named
    in quadratic time); materials are skipped."""
    from rotlearn.data.shapenet import read_obj

    path = tmp_path / "m.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n" + "usemtl m\nf 1 2 3\n" * 20_000)
    with within(10):
        assert read_obj(path)[1].shape == (20_000, 3)


def test_vertices_triangles_and_line_lengths_are_capped(tmp_path, monkeypatch):
    """Two faces of 2 million corners (7.6 MB) took 1.2 GB through trimesh's reader; a 64 MB line
    is split into words of 24 times its size. Each cap stops reading at the line past it."""
    import rotlearn.data.shapenet as shapenet
    import rotlearn.io as io

    path = tmp_path / "m.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3 4\nf 1 2 3\n")
    monkeypatch.setattr(shapenet, "MAX_MESH_TRIANGLES", 2)
    with pytest.raises(ValueError, match=r"m\.obj:6: more than 2 triangles"):
        shapenet.read_obj(path)
    monkeypatch.setattr(shapenet, "MAX_MESH_VERTICES", 3)
    with pytest.raises(ValueError, match=r"m\.obj:4: more than 3 rows \(v x y z\)"):
        shapenet.read_obj(path)
    monkeypatch.setattr(io, "MAX_LINE_CHARS", 9)
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1.00 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match=r"m\.obj:3: a line of 10 characters, over the 9"):
        shapenet.read_obj(path)


def test_a_point_file_is_read_no_further_than_its_row_cap(tmp_path, monkeypatch):
    import rotlearn.data.shapenet as shapenet

    path = tmp_path / "c.pts"
    path.write_text("0 0 1\n" * 5 + "not numbers\n")
    monkeypatch.setattr(shapenet, "MAX_POINT_ROWS", 4)
    with pytest.raises(ValueError, match=r"c\.pts:5: more than 4 rows \(x y z\)"):
        shapenet.read_point_file(path)
    path.write_text("0 0 1\n0 3e38 0\n")  # finite in float32, inf once rotated
    with pytest.raises(ValueError, match=r"c\.pts:2: not finite .*beyond \+-1e\+06"):
        shapenet.read_point_file(path)
