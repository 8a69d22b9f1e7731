"""The demo worlds and their writers: small datasets in the real on-disk layouts, written from a
seed (`rotlearn-make-demo-data`, tests, `make demo-data`), apart from the dataset readers.

`synth` (renderer under pure camera rotation, airplane meshes, staged writes), `natural`
(photo-textured street and room panoramas with natural-image statistics) and one writer per
dataset: `kitti`, `mav`, `shapenet`, each with `write_demo(out, seed) -> list[Path]` writing
`<out>/<name>` in the layout `rotlearn.data.<name>` reads.
"""
