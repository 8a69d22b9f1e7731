"""Memory of the dataset text readers per byte of file: `make bench ARGS=text_readers`.

A hostile dataset writes the shortest rows a reader accepts ("1,1,0,0,0" poses, "1,2" pairs), so
that each byte of text becomes as many numbers as it can. For each reader (the MAV pose, frame
and pair CSVs, KITTI's pose rows) this writes `--mib` MiB of such rows, reads them in a fresh
process and reports the growth of the process's peak resident memory (VmHWM on Linux, torch's
allocations included) over the file's size, and that ratio at the 256 MiB cap of a "text file"
(`rotlearn.io.MAX_BYTES`). The MAV pose rows repeat each time stamp 12 times (the reader then
compares every repeat), the costliest case. Writes bench/results/text_readers.json.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

from rotlearn.io import MAX_BYTES, write_json_atomic
from timing import PEAK_RSS

RESULTS = Path(__file__).resolve().parent / "results"
ROWS = {  # reader -> (shortest row it accepts, as a format of the row number i)
    "mav pose (read_pose_file)": "{s},1,0,0,0\n",
    "mav frames (read_frame_list)": "{i},{i}\n",  # each row its own frame
    "mav pairs (read_pair_file)": "{i},0\n",
    "kitti poses (read_kitti_poses)": "1 0 0 0 0 1 0 0 0 0 1 0\n",
}
_READ = (
    PEAK_RSS
    + """
import sys
from rotlearn.data.kitti import read_kitti_poses
from rotlearn.data.mav import read_frame_list, read_pair_file, read_pose_file
readers = {"mav pose": read_pose_file, "mav frames": read_frame_list,
           "mav pairs": lambda p: read_pair_file(p, 2**40), "kitti poses": read_kitti_poses}
read = readers[sys.argv[1]]
read(sys.argv[3])  # a file of one row: what the first call loads (torch's SVD) is not counted
before = peak_rss()
read(sys.argv[2])
print(peak_rss() - before)
"""
)


def measure(mib: float) -> dict:
    rows = {}
    cap = MAX_BYTES["text file"]
    with tempfile.TemporaryDirectory() as tmp:
        for name, row in ROWS.items():
            path, size, lines = Path(tmp) / "rows.txt", int(mib * 2**20), []
            written = i = 0
            while written < size:
                lines.append(row.format(i=i, s=i // 12))
                written += len(lines[-1])
                i += 1
            path.write_text("".join(lines))
            one = Path(tmp) / "one.txt"
            one.write_text(lines[0])
            lines.clear()
            reader = name.split(" (")[0]
            done = subprocess.run(
                [sys.executable, "-c", _READ, reader, str(path), str(one)],
                capture_output=True, text=True, check=True,
            )  # fmt: skip
            peak = int(done.stdout.split()[-1])
            ratio = peak / written
            rows[name] = {
                "rows": i,
                "file_bytes": written,
                "peak_bytes": peak,
                "peak_per_file_byte": ratio,
                "at_cap_gib": ratio * cap / 2**30,
            }
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--mib", type=float, default=16.0, help="MiB of rows per reader")
    parser.add_argument("--out", type=Path, default=RESULTS / "text_readers.json")
    args = parser.parse_args(argv)
    rows = measure(args.mib)
    print(f"\nDataset text readers: peak RSS growth per byte of a {args.mib:g} MiB file")
    print(f"{'reader':32s} {'rows':>9s} {'x file':>7s} {'GiB at 256 MiB':>15s}")
    for name, row in rows.items():
        print(f"{name:32s} {row['rows']:9d} {row['peak_per_file_byte']:7.1f} "
              f"{row['at_cap_gib']:15.2f}")  # fmt: skip
    path = write_json_atomic(args.out, {"mib": args.mib, "result": rows})
    print(f"-> {path}")


if __name__ == "__main__":
    main()
