"""`rotlearn-make-demo-data`: small datasets in the real on-disk layouts, for tests and demos.

Each module `rotlearn.data.demo.<name>` that defines `write_demo(out, seed) -> list[Path]` writes
the dataset `<name>` under `<out>/<name>` in the layout its reader (`rotlearn.data.<name>`)
expects; see that module for the layout. The same seed writes the same files. Each dataset
appears under its final name only when complete, and replaces an existing `<out>/<name>` only if
this command wrote it (it holds `.rotlearn-demo`); anything else there is refused, untouched.
"""

from __future__ import annotations

import argparse
import importlib
import inspect
import pkgutil
import sys
import time
from collections.abc import Callable
from pathlib import Path

import rotlearn.data.demo

__all__ = ["demo_writers", "main"]


def demo_writers() -> dict[str, Callable[..., list[Path]]]:
    """{dataset name: write_demo} of every `rotlearn.data.demo` module that defines one, by
    name."""
    writers = {}
    for info in sorted(pkgutil.iter_modules(rotlearn.data.demo.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"rotlearn.data.demo.{info.name}")
        if callable(getattr(module, "write_demo", None)):
            writers[info.name] = module.write_demo
    return writers


def main(argv: list[str] | None = None) -> int:
    writers = demo_writers()

    def dataset_list(text: str) -> list[str]:
        names = [n.strip() for n in text.split(",") if n.strip()]
        unknown = sorted(set(names) - set(writers))
        if unknown or not names:
            raise argparse.ArgumentTypeError(f"choose from {', '.join(writers)}; got {text!r}")
        return names

    def integer(low: int, high: int):
        def parse(text: str) -> int:
            try:
                value = int(text)
            except ValueError:
                raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
            if not low <= value <= high:
                raise argparse.ArgumentTypeError(f"must be in [{low}, {high}], got {value}")
            return value

        return parse

    parser = argparse.ArgumentParser(
        prog="rotlearn-make-demo-data",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", default="data/demo", help="where to write (default data/demo)")
    parser.add_argument(
        "--seed", type=integer(0, 2**32 - 1), default=0, help="the worlds' seed (default 0)"
    )
    parser.add_argument(
        "--scale",
        default="demo",
        help="size of the datasets whose writer has sizes (kitti: demo, or paper for "
        "experiment=kitti_ood_paper_scale: ~16k training pairs); default demo",
    )
    parser.add_argument(
        "--workers",
        type=integer(1, 256),
        default=1,
        help="processes per writer that takes them (kitti; default 1)",
    )
    parser.add_argument(
        "--no-street-camera",
        action="store_true",
        help="write the exact renders, without the street camera's exposure, noise and traffic "
        "(kitti: rotlearn.data.demo.camera), as the KITTI demo was written before it",
    )
    parser.add_argument(
        "--only",
        type=dataset_list,
        default=list(writers),
        help=f"comma-separated subset of {','.join(writers)} (default: all)",
    )
    args = parser.parse_args(argv)
    chosen = {}  # every chosen writer's options, checked before the first one writes
    for name in (n for n in writers if n in args.only):
        given = (("scale", args.scale), ("workers", args.workers),
                 ("street_camera", not args.no_street_camera))  # fmt: skip
        options = {k: v for k, v in given if k in inspect.signature(writers[name]).parameters}
        if args.scale != "demo" and "scale" not in options:
            parser.error(f"--scale {args.scale}: the {name} writer has only the demo size")
        if args.no_street_camera and "street_camera" not in options:
            parser.error(f"--no-street-camera: the {name} writer has no street camera")
        chosen[name] = options
    for name, options in chosen.items():
        start = time.perf_counter()
        try:
            roots = writers[name](args.out, seed=args.seed, **options)
        except ValueError as exc:
            parser.error(f"{name}: {exc}")
        except OSError as exc:  # an --out that cannot be written, or holds other data
            print(f"rotlearn-make-demo-data: {name}: {exc}", file=sys.stderr)
            return 1
        seconds = time.perf_counter() - start
        print(f"{name}: {', '.join(map(str, roots))} ({seconds:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
