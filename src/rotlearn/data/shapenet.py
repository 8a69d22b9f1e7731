"""ShapeNet airplanes (paper Fig. 5, section VI-B): point clouds under random rotations.

Reads either the 6D paper's prepared clouds, `<root>/train/*.pts` and `<root>/test/*.pts` (or
`.xyz`: one "x y z" point per line), or ShapeNetCore v2 meshes,
`<root>/<synset>/<model_id>/models/model_normalized.obj` (read by `read_obj`, bounded), sampled
once with trimesh to a fixed number of surface points and cached as `.npy` beside a manifest
(with a progress bar).

Training: each step takes one training cloud (drawn by the data seed) under `rotations_per_cloud`
rotations C = Exp(phi), phi ~ N(0, I); input rows are (x_i, C x_i). Test: every held-out cloud
under `test_rotations` fixed, seeded rotations.
"""

from __future__ import annotations

import array as pyarray
import json
import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import DataLoader

from rotlearn.data.draws import SPLITS, DrawDataModule
from rotlearn.data.heteroscedastic import (
    check_range,
    difficulty,
    keep_random_rows,
    log_uniform,
)
from rotlearn.extras import import_extra
from rotlearn.geometry import quat_to_rotmat, so3_exp_quat
from rotlearn.io import (
    atomic_write,
    cache_file,
    cache_manifest,
    parse_number_rows,
    plain_name,
    read_cached_array,
    read_manifest,
    read_number_rows,
    read_text_file,
    remove_stale_temporaries,
    resolve_inside,
    strict_int,
    word_rows,
    write_text_atomic,
)
from rotlearn.trust import config_target

if TYPE_CHECKING:  # constraints of the config values, checked by rotlearn.config
    from annotated_types import Ge, Gt, Le

__all__ = ["AIRPLANE_SYNSET", "ShapeNetDataModule", "read_mesh", "read_point_file", "sample_meshes"]

log = logging.getLogger("rotlearn")

AIRPLANE_SYNSET = "02691156"
POINT_SUFFIXES = (".pts", ".xyz")
# Points a cloud may use (the 6D paper's have about 2.4k-2.9k, half used): every draw holds each
# point 6 times a sample, so a file of 100k short lines made a batch of 100 take 240 MB.
MAX_CLOUD_POINTS = 2**16
MAX_POINT_ROWS = 2**20  # rows of a point file: past them it is not read further (any fraction)
# A point or vertex coordinate's largest magnitude: a rotated cloud, with noise, squared in a
# distance, stays finite in float32 (3e38 is finite there, and overflowed once rotated).
MAX_COORDINATE = 1e6
# A mesh's vertices and triangles (polygons fanned): memory stays bounded (a 7 MB file of two
# 2-million-corner faces took 1.2 GB through trimesh's reader).
MAX_MESH_VERTICES = 2**22
MAX_MESH_TRIANGLES = 2**22


def read_point_file(path: str | os.PathLike) -> np.ndarray:
    """Points of a `.pts`/`.xyz` file: (N, 3) float32, one "x y z" line each (extra columns, such
    as normals, are ignored).

    Raises:
        ValueError: naming the file and line of the first malformed row (not 3 numbers, or a
            NaN / infinity or a coordinate beyond `MAX_COORDINATE`), or of the row past
            `MAX_POINT_ROWS` (read no further).
    """
    return read_number_rows(path, 3, "x y z", extra_ok=True, dtype=np.float32,
                            bound=MAX_COORDINATE, max_rows=MAX_POINT_ROWS)  # fmt: skip


def read_obj(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """The vertices (V, 3) float32 and triangles (F, 3) int64 (0-based) of an OBJ file (UTF-8
    text), read by rotlearn alone, a line at a time (`rotlearn.io.word_rows`).

    Read: "v x y z" lines (more numbers, a w or a colour, ignored); "f" lines of 3 or more
    corners `i`, `i/t`, `i//n` or `i/t/n` (1-based, or negative: counted back from the last
    vertex so far), polygons fanned into triangles (0, j, j + 1). Every other line (vt, vn,
    usemtl, mtllib, g, o, s, l, p, ...) is skipped: no file it names is read.

    Raises:
        FileNotFoundError: no such file.
        ValueError: "<file>:<line>: ..." for a line continued with a backslash, a vertex that is
            not 3 numbers, finite and within `MAX_COORDINATE`, a corner that is no vertex index
            (0, not an integer, or no such vertex), a face of fewer than 3 corners, or more than
            `MAX_MESH_VERTICES` vertices or `MAX_MESH_TRIANGLES` triangles; "<file>: ..." for a
            mesh with no faces.
    """
    where = str(path)
    text = read_text_file(path).removeprefix("\ufeff")  # a byte-order mark would hide line 1
    corners, sizes, face_lines = pyarray.array("q"), pyarray.array("q"), []
    count = triangles = 0  # vertices so far (a negative corner counts back from there)

    def vertex_rows():  # the "v" rows, for parse_number_rows; the faces on the way
        nonlocal count, triangles
        for lineno, words in word_rows(text, where):
            if words[-1].endswith("\\"):
                raise ValueError(f"{where}:{lineno}: a line continued with '\\' (not read; "
                                 "write it on one line)")  # fmt: skip
            if words[0] == "v":
                count += 1
                yield lineno, words[1:]
            elif words[0] == "f":
                if len(words) < 4:
                    raise ValueError(f"{where}:{lineno}: a face of {len(words) - 1} corners (3 or "
                                     "more make a face)")  # fmt: skip
                if (triangles := triangles + len(words) - 3) > MAX_MESH_TRIANGLES:
                    raise ValueError(f"{where}:{lineno}: more than {MAX_MESH_TRIANGLES} triangles")
                for word in words[1:]:
                    index = strict_int(word.partition("/")[0], f"{where}:{lineno}")
                    if index == 0 or not -count <= index <= MAX_MESH_VERTICES:
                        raise ValueError(f"{where}:{lineno}: corner {word!r} names no vertex (1, "
                                         f"2, ... or -1 to -{count}, counted back)")  # fmt: skip
                    corners.append(index - 1 if index > 0 else count + index)
                sizes.append(len(words) - 1)
                face_lines.append(lineno)

    vertices = parse_number_rows(vertex_rows(), where, 3, "v x y z", extra_ok=True,
                                 dtype=np.float32, bound=MAX_COORDINATE,
                                 max_rows=MAX_MESH_VERTICES)  # fmt: skip
    if not sizes:
        raise ValueError(f"{where}: the mesh has no faces ({len(vertices)} vertices; an OBJ "
                         "mesh's faces are its 'f' lines)")  # fmt: skip
    index, size = np.frombuffer(corners, np.int64), np.frombuffer(sizes, np.int64)
    if len(past := np.flatnonzero(index >= len(vertices))):  # a vertex the file lacks
        face = int(np.searchsorted(np.cumsum(size), past[0], side="right"))
        raise ValueError(f"{where}:{face_lines[face]}: a corner names vertex {index[past[0]] + 1},"
                         f" but the file has {len(vertices)}")  # fmt: skip
    return vertices, _fan(index, size)


def _fan(corners: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Triangles (T, 3) of polygons given as their corners, concatenated, and their sizes (each
    >= 3): polygon (c_0, ..., c_k-1) -> (c_0, c_j, c_j+1), j = 1 .. k - 2."""
    fans = sizes - 2
    first = np.repeat(np.cumsum(sizes) - sizes, fans)  # each triangle's polygon's first corner
    j = np.arange(int(fans.sum())) - np.repeat(np.cumsum(fans) - fans, fans) + 1
    return np.stack((corners[first], corners[first + j], corners[first + j + 1]), axis=-1)


def read_mesh(path: str | os.PathLike):
    """A mesh file (OBJ, `read_obj`) as a trimesh.Trimesh (unprocessed), checked for sampling: a
    positive total area once its vertices are float32 (the clouds' dtype).

    Raises:
        FileNotFoundError: no such file.
        ValueError: naming the file (and the line, as `read_obj`).
    """
    trimesh = import_extra("trimesh", "reading meshes")

    vertices, faces = read_obj(path)
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    area = np.asarray(mesh.area_faces).sum()
    if not (np.isfinite(area) and area > 0):
        raise ValueError(
            f"{path}: the mesh's total area is {area} ({len(faces)} degenerate faces): "
            "no surface to sample"
        )
    return mesh


def sample_meshes(paths: list[Path], num_points: int, cache: Path, seed: int = 0) -> np.ndarray:
    """Surface samples of meshes, (M, num_points, 3) float32, cached in `cache` (.npy + .json).

    The cache is reused only if its manifest (read bounded) lists the same files, each of the same
    size, modification time and inode change time (`rotlearn.io.cache_manifest`: an edited mesh
    is sampled again, a cache shipped with the dataset rebuilt), point count, seed and reader,
    and its array holds (M, num_points, 3) float32 within `MAX_COORDINATE`; anything else in the
    cache folder (a named pipe, a huge or foreign file) is rebuilt over. Each mesh is checked by
    `read_mesh`; an error leaves no cache behind.
    """
    recipe = {"num_points": num_points, "seed": seed, "reader": "rotlearn.data.shapenet.read_obj"}
    manifest = cache_manifest(paths, recipe, "mesh")
    array_path, manifest_path = cache.with_suffix(".npy"), cache.with_suffix(".json")
    if read_manifest(manifest_path) == manifest:
        cached = read_cached_array(array_path, np.float32, (len(paths), num_points, 3))
        if cached is not None and (np.abs(cached) <= MAX_COORDINATE).all():  # NaN: not <=
            return np.array(cached)
    trimesh = import_extra("trimesh", "reading meshes")
    from tqdm import tqdm

    clouds = np.empty((len(paths), num_points, 3), dtype=np.float32)
    for i, path in enumerate(tqdm(paths, desc="sampling ShapeNet meshes", unit="mesh")):
        points, _ = trimesh.sample.sample_surface(read_mesh(path), num_points, seed=seed + i)
        clouds[i] = points
    remove_stale_temporaries(array_path)  # a killed build's
    with atomic_write(array_path) as tmp:
        np.save(tmp, clouds)
    write_text_atomic(manifest_path, json.dumps(manifest))
    return clouds


@config_target
class ShapeNetDataModule(DrawDataModule):
    """ShapeNet clouds under random rotations (paper section VI-B).

    Args:
        root: dataset root (layout in the module docstring and data/README.md).
        format: "pts" (the 6D paper's clouds) or "mesh" (ShapeNetCore v2 meshes).
        synset: ShapeNet category for "mesh" (airplanes by default).
        num_train, num_test: clouds per split (paper: 2290 / 400); fewer are used if fewer exist.
        point_fraction: for "pts", the leading fraction of each file's points used (paper: 0.5).
        num_points: for "mesh", surface points sampled per mesh.
        rotations_per_cloud: rotations of the one cloud in each training step (paper: 10).
        iterations_per_epoch: training steps per epoch (paper: 200).
        test_rotations: fixed rotations per held-out cloud (paper: 100).
        num_val: training clouds held out for validation (the last ones of the training
            split, at most a fifth of them; never trained on, never test clouds), each under
            `test_rotations` fixed rotations: they select the best checkpoint and fit the
            belief's temperature.
        seed: the data seed.
        cache_dir: where sampled meshes are cached (default: <root>/.rotlearn_cache).
        noise_range: [lo, hi], 0 < lo <= hi: each rotated cloud gets isotropic Gaussian noise
            on its rotated points, of a std drawn log-uniformly in [lo, hi] per sample (issue 17:
            heteroscedastic data); null: no noise (the paper's setting).
        keep_range: [lo, hi] fractions in (0, 1]: each sample keeps ceil(f N) of its N points,
            f uniform in [lo, hi], chosen at random; its other rows repeat the kept ones, which a
            max-pooling net cannot tell apart from the kept points alone; null: all points.
            With either range, batches carry "sigma" (B,) (the noise std, 0 without
            noise_range), "num_points" (B,) (distinct points, int64) and "difficulty" (B,):
            sigma / sqrt(num_points) (`rotlearn.data.heteroscedastic`), with sigma read as 1
            without noise_range so that it still ranks samples by their number of points.
    """

    # What data.root holds, checked when a config is validated (rotlearn.config): the split
    # folders of the 6D paper's clouds (format=pts) or the category's folder of meshes.
    layout = ("format=pts: train", "format=pts: test", "format=mesh: {synset}")

    def __init__(
        self,
        root: str,
        format: Literal["pts", "mesh"] = "pts",
        synset: str = AIRPLANE_SYNSET,
        num_train: Annotated[int, Gt(0)] = 2290,
        num_test: Annotated[int, Gt(0)] = 400,
        point_fraction: Annotated[float, Gt(0), Le(1)] = 0.5,
        num_points: Annotated[int, Gt(0)] = 1024,
        rotations_per_cloud: Annotated[int, Gt(0)] = 10,
        iterations_per_epoch: Annotated[int, Gt(0)] = 200,
        test_rotations: Annotated[int, Gt(0)] = 100,
        num_val: Annotated[int, Ge(0)] = 20,
        seed: Annotated[int, Ge(0)] = 0,
        cache_dir: str | None = None,
        noise_range: list[float] | None = None,
        keep_range: list[float] | None = None,
    ) -> None:
        super().__init__()
        self.root, self.format = Path(root), format
        self.synset = plain_name(synset, key="synset")
        self.num_train, self.num_test = int(num_train), int(num_test)
        self.point_fraction, self.num_points = float(point_fraction), int(num_points)
        self.rotations_per_cloud = int(rotations_per_cloud)
        self.iterations_per_epoch = int(iterations_per_epoch)
        self.test_rotations, self.num_val = int(test_rotations), int(num_val)
        self.seed = int(seed)
        self.noise_range = check_range("noise_range", noise_range, minimum=0.0, strict=True)
        self.keep_range = check_range(
            "keep_range", keep_range, minimum=0.0, strict=True, maximum=1.0
        )
        self.cache_dir = Path(cache_dir) if cache_dir else self.root / ".rotlearn_cache"
        self.clouds: dict[int, list[Tensor]] = {}

    def _load_pts(self, split: str, limit: int) -> list[Tensor]:
        folder = self.root / split
        resolve_inside(self.root, folder, "data.root")
        files = sorted(p for p in folder.glob("*") if p.suffix in POINT_SUFFIXES)[:limit]
        if not files:
            raise FileNotFoundError(
                f"no {'/'.join(POINT_SUFFIXES)} files in {folder} (data.root={self.root}, "
                "data.format=pts expects <root>/train and <root>/test)"
            )
        clouds = []
        for path in files:
            plain_name(path.name, str(folder))  # a name that would garble a message: refused
            points = read_point_file(resolve_inside(self.root, path, "data.root"))
            keep = max(1, int(len(points) * self.point_fraction))
            if keep > MAX_CLOUD_POINTS:
                raise ValueError(
                    f"{path}: {keep} points used (data.point_fraction={self.point_fraction:g} of "
                    f"{len(points)}), over the {MAX_CLOUD_POINTS} a cloud may use; subsample the "
                    "file or lower data.point_fraction"
                )
            clouds.append(torch.from_numpy(points[:keep]))
        return clouds

    def _load_meshes(self) -> tuple[list[Tensor], list[Tensor]]:
        folder = self.root / self.synset
        resolve_inside(self.root, folder, "data.synset")
        models = sorted(folder.glob("*/models"))
        for model in models:  # a name that would garble a message: refused
            plain_name(model.parent.name, str(folder))
        paths = [model / "model_normalized.obj" for model in models]
        paths = [path for path in paths if os.path.lexists(path)]  # a dangling link: refused
        for path in paths:
            resolve_inside(self.root, path, "data.synset")
        if not paths:
            raise FileNotFoundError(
                f"no meshes {folder}/<model_id>/models/model_normalized.obj "
                f"(data.root={self.root}, data.synset={self.synset})"
            )
        order = np.random.default_rng(self.seed).permutation(len(paths))
        train = [paths[i] for i in order[: self.num_train]]
        test = [paths[i] for i in order[self.num_train : self.num_train + self.num_test]]
        if not test:
            raise ValueError(f"{folder} holds {len(paths)} meshes: none left for the test split")
        stem = f"{self.synset}_{self.num_points}_seed{self.seed}"
        cache = cache_file(self.cache_dir, stem, "data.cache_dir (data.synset)", self.root)
        clouds = torch.from_numpy(sample_meshes(train + test, self.num_points, cache, self.seed))
        return list(clouds[: len(train)]), list(clouds[len(train) :])

    def setup(self, stage: str | None = None) -> None:
        if self.clouds:
            return
        if self.format == "pts":
            train = self._load_pts("train", self.num_train)
            test = self._load_pts("test", self.num_test)
        else:
            train, test = self._load_meshes()
        num_val = min(self.num_val, len(train) // 5)
        if num_val < self.num_val:
            log.info("ShapeNet: %d training clouds: %d held out for validation (data.num_val=%d "
                     "is capped at a fifth)", len(train), num_val, self.num_val)  # fmt: skip
        cut = len(train) - num_val
        self.clouds = {SPLITS["train"]: train[:cut], SPLITS["val"]: train[cut:],
                       SPLITS["test"]: test}  # fmt: skip

    def train_dataloader(self) -> DataLoader:
        return self.requests("train", [self.rotations_per_cloud] * self.iterations_per_epoch)

    def val_dataloader(self) -> DataLoader:
        return self.requests("val", [self.test_rotations] * len(self.clouds[SPLITS["val"]]))

    def test_dataloader(self) -> DataLoader:
        return self.requests("test", [self.test_rotations] * len(self.clouds[SPLITS["test"]]))

    def draw(
        self,
        split: int,
        index: int,
        size: int,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ) -> dict[str, Tensor]:
        """One cloud under `size` rotations: {"input": (size, N, 6), "R", "q"}, and with
        `noise_range` or `keep_range` also "sigma", "num_points" and "difficulty" (size,)."""
        generator = self.generator(split, index, device)
        clouds = self.clouds[split]
        if split == SPLITS["train"]:  # which cloud, from the same seeded stream
            pick = torch.randint(len(clouds), (), generator=generator, device=generator.device)
            cloud = clouds[int(pick)]
        else:
            cloud = clouds[index]
        phi = torch.randn(size, 3, generator=generator, device=generator.device, dtype=dtype)
        q = so3_exp_quat(phi)
        R = quat_to_rotmat(q).to(device)
        x = cloud.to(device, dtype).expand(size, -1, -1)
        if self.noise_range is None and self.keep_range is None:
            points = torch.cat((x, x @ R.transpose(-1, -2)), dim=-1)
            return {"input": points, "R": R, "q": q.to(device)}
        return {"R": R, "q": q.to(device), **self._degrade(x, R, generator)}

    def _degrade(self, x: Tensor, R: Tensor, generator: torch.Generator) -> dict[str, Tensor]:
        """Per-sample noise on the rotated points and per-sample point dropout (by repetition)."""
        (size, N), device, dtype = x.shape[:2], x.device, x.dtype
        gen = {"generator": generator, "device": generator.device}
        if self.noise_range is not None:
            sigma = log_uniform(size, *self.noise_range, dtype=dtype, **gen).to(device)
        else:
            sigma = torch.zeros(size, device=device, dtype=dtype)
        if self.keep_range is not None:
            lo, hi = self.keep_range
            fraction = lo + (hi - lo) * torch.rand(size, dtype=torch.float64, **gen)
            counts = (fraction * N).ceil().long().clamp(1, N).to(device)
        else:
            counts = torch.full((size,), N, device=device, dtype=torch.long)
        noise = torch.randn(x.shape, dtype=dtype, **gen).to(device)
        points = torch.cat((x, x @ R.transpose(-1, -2) + sigma[:, None, None] * noise), dim=-1)
        if self.keep_range is not None:
            points = keep_random_rows(points, counts, generator=generator)
        level = sigma if self.noise_range is not None else torch.ones_like(sigma)
        return {"input": points, "sigma": sigma, "num_points": counts,
                "difficulty": difficulty(level, counts)}  # fmt: skip
