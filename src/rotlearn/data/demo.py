"""Small datasets in the real on-disk layouts, for tests and demos (`rotlearn-make-demo-data`).

ShapeNet: random "airplanes" (fuselage, wings, tail fin of random sizes: no rotational symmetry)
written as ShapeNetCore v2 meshes `<out>/shapenet_core/02691156/<id>/models/model_normalized.obj`
and as the 6D paper's clouds `<out>/shapenet_pts/{train,test}/<id>.pts` ("x y z" lines).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from rotlearn.data.shapenet import AIRPLANE_SYNSET

__all__ = ["main", "write_shapenet_demo"]


def _airplane(rng: np.random.Generator):
    import trimesh

    length, radius = rng.uniform(1.6, 2.2), rng.uniform(0.12, 0.2)
    fuselage = trimesh.creation.cylinder(radius=radius, height=length, sections=24)
    fuselage.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    span, chord = rng.uniform(1.4, 2.2), rng.uniform(0.25, 0.4)
    wings = trimesh.creation.box(extents=[chord, span, 0.04])
    wings.apply_translation([rng.uniform(-0.2, 0.3), 0.0, rng.uniform(-0.05, 0.05)])
    fin = trimesh.creation.box(extents=[0.25, 0.04, rng.uniform(0.3, 0.5)])
    fin.apply_translation([-length / 2 + 0.15, 0.0, radius + 0.15])
    tail = trimesh.creation.box(extents=[0.18, rng.uniform(0.5, 0.8), 0.03])
    tail.apply_translation([-length / 2 + 0.1, 0.0, 0.0])
    mesh = trimesh.util.concatenate([fuselage, wings, fin, tail])
    mesh.apply_translation(-mesh.bounding_box.centroid)
    mesh.apply_scale(1.0 / np.linalg.norm(mesh.extents))  # ShapeNet "normalized": unit diagonal
    return mesh


def write_shapenet_demo(
    out: str | Path, num_train: int = 12, num_test: int = 4, points: int = 512, seed: int = 0
) -> dict[str, Path]:
    """Write the demo ShapeNet in both layouts; returns their roots {"mesh": ..., "pts": ...}.

    The `.pts` files hold 2 * `points` points: the paper's point_fraction 0.5 keeps `points`.
    """
    import trimesh

    out = Path(out)
    rng = np.random.default_rng(seed)
    roots = {"mesh": out / "shapenet_core", "pts": out / "shapenet_pts"}
    for i in range(num_train + num_test):
        model_id = f"demo{seed:02d}{i:04d}"
        mesh = _airplane(rng)
        folder = roots["mesh"] / AIRPLANE_SYNSET / model_id / "models"
        folder.mkdir(parents=True, exist_ok=True)
        mesh.export(folder / "model_normalized.obj")
        cloud, _ = trimesh.sample.sample_surface(mesh, 2 * points, seed=seed * 100003 + i)
        split = "train" if i < num_train else "test"
        (roots["pts"] / split).mkdir(parents=True, exist_ok=True)
        lines = "\n".join(f"{x:.6f} {y:.6f} {z:.6f}" for x, y, z in cloud)
        (roots["pts"] / split / f"{model_id}.pts").write_text(lines + "\n")
    return roots


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="rotlearn-make-demo-data", description=__doc__)
    parser.add_argument("--out", default="data/demo", help="where to write (default data/demo)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    for name, root in write_shapenet_demo(args.out, seed=args.seed).items():
        print(f"shapenet ({name}): {root}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
