"""Demo ShapeNet airplanes in both layouts that `rotlearn.data.shapenet` reads
(`rotlearn-make-demo-data`, tests).

Random "airplanes" (`rotlearn.data.demo.synth.airplane_mesh`: fuselage, wings, tail fin of random
sizes, no rotational symmetry) written as ShapeNetCore v2 meshes
`<out>/shapenet/02691156/<id>/models/model_normalized.obj` and as the 6D paper's clouds
`<out>/shapenet/{train,test}/<id>.pts` ("x y z" lines).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rotlearn.data.demo.synth import airplane_mesh, staged
from rotlearn.data.shapenet import AIRPLANE_SYNSET
from rotlearn.extras import import_extra

__all__ = ["write_demo", "write_shapenet_demo"]


def write_shapenet_demo(
    out: str | Path, num_train: int = 12, num_test: int = 4, points: int = 512, seed: int = 0
) -> dict[str, Path]:
    """Write the demo ShapeNet in both layouts under one root, `<out>/shapenet` (data.format=mesh
    reads `<root>/02691156/...`, data.format=pts reads `<root>/{train,test}`); returns
    {"mesh": root, "pts": root}.

    The `.pts` files hold 2 * `points` points: the paper's point_fraction 0.5 keeps `points`.
    """
    trimesh = import_extra("trimesh", "the ShapeNet demo writer")

    out = Path(out)
    names = {"mesh": "shapenet", "pts": "shapenet"}
    rng = np.random.default_rng(seed)
    with staged(out, "shapenet", ["shapenet"]) as stage:
        for i in range(num_train + num_test):
            model_id = f"demo{seed:02d}{i:04d}"
            mesh = airplane_mesh(rng)
            folder = stage / names["mesh"] / AIRPLANE_SYNSET / model_id / "models"
            folder.mkdir(parents=True, exist_ok=True)
            mesh.export(folder / "model_normalized.obj")
            cloud, _ = trimesh.sample.sample_surface(mesh, 2 * points, seed=seed * 100003 + i)
            split = stage / names["pts"] / ("train" if i < num_train else "test")
            split.mkdir(parents=True, exist_ok=True)
            lines = "\n".join(f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in cloud)
            (split / f"{model_id}.pts").write_text(lines + "\n")
    return {key: out / name for key, name in names.items()}


def write_demo(out: str | Path, seed: int = 0) -> list[Path]:
    """The default-size demo (`rotlearn-make-demo-data`): the roots written."""
    return sorted(set(write_shapenet_demo(out, seed=seed).values()))
