"""rotlearn.io: bounded reads (regular files only, a size cap per kind, depth limits, no YAML
aliases) and the one atomic write: whole or nothing, durable (temp file beside the target, fsync,
rename), the mode the umask allows, a failed write naming the file and leaving the previous one."""

from __future__ import annotations

import errno
import os
import pickle
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from rotlearn import io
from rotlearn.io import (
    MAX_BYTES,
    UnreadableFileError,
    WriteError,
    atomic_write,
    cache_manifest,
    folder_entries,
    read_bytes,
    read_json,
    read_number_array,
    read_record,
    read_yaml,
    remove_stale_temporaries,
    rewrite_in_place,
    write_bytes_atomic,
    write_json_atomic,
    write_text_atomic,
)
from tests.conftest import doubling, within


def test_a_named_pipe_is_refused_at_once(tmp_path):
    fifo = tmp_path / "status.json"
    os.mkfifo(fifo)
    with within(5), pytest.raises(UnreadableFileError, match=r"status\.json: a named pipe"):
        read_record(fifo)
    with within(5):
        assert read_json(fifo) is None  # the tolerant reader goes on without it


def test_a_device_and_a_folder_are_refused(tmp_path):
    link = tmp_path / "metrics.json"
    link.symlink_to("/dev/zero")
    with within(5), pytest.raises(UnreadableFileError, match="a character device"):
        read_bytes(link, "JSON record")
    with pytest.raises(UnreadableFileError, match="a folder"):
        read_bytes(tmp_path, "JSON record")


def test_a_symlink_out_of_its_root_is_refused(tmp_path):
    outside = tmp_path / "outside.json"
    outside.write_text("{}")
    run = tmp_path / "run"
    run.mkdir()
    (run / "status.json").symlink_to(outside)
    with pytest.raises(UnreadableFileError, match="outside"):
        read_record(run / "status.json", root=run)
    assert read_record(run / "status.json") == {}  # without a root, a symlink is followed


def test_each_kind_has_its_cap(tmp_path, monkeypatch):
    path = tmp_path / "x.json"
    path.write_text(" " * 100 + "{}")
    monkeypatch.setitem(MAX_BYTES, "JSON record", 64)
    with pytest.raises(UnreadableFileError, match=r"too large for a JSON record \(over 64 bytes"):
        read_record(path)
    monkeypatch.setitem(MAX_BYTES, "JSON record", 102)
    assert read_record(path) == {}


@pytest.mark.parametrize(
    ("name", "text", "reason"),
    [
        ("status.json", "[" * 100_000 + "]" * 100_000, "nested too deeply"),
        (
            "status.json",
            "[" * 100 + "]" * 100,
            "nested too deeply",
        ),  # parses, deeper than MAX_DEPTH
        ("status.json", "{not json", "not JSON"),
        ("status.json", b"\xff\xfe", "not UTF-8"),
        ("config.yaml", "[" * 100 + "]" * 100, "nested too deeply"),
        ("config.yaml", "[" * 10_000 + "]" * 10_000, "not plain YAML data"),  # the parser's limit
        ("config.yaml", "!!python/object/apply:os.system ['true']", "not plain YAML data"),
        ("config.yaml", "a: [unclosed", "not plain YAML data"),
        ("config.yaml", "pad: [" + "0," * 70_000 + "0]", r"more than 65536 YAML values"),
    ],
)
def test_a_malformed_record_or_config_is_named(tmp_path, name, text, reason):
    path = tmp_path / name
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    read = read_record if name.endswith(".json") else read_yaml
    with within(10), pytest.raises(UnreadableFileError, match=reason) as info:
        read(path)
    assert str(path) in str(info.value)


def _npy(array: np.ndarray, **kwargs) -> bytes:
    import io as bytes_io

    buffer = bytes_io.BytesIO()
    np.save(buffer, array, **kwargs)
    return buffer.getvalue()


_ROWS = np.arange(30, dtype=np.float32).reshape(5, 6)
_NAN = np.zeros((2, 3, 6))
_NAN[1, 2, 4] = np.nan
_GENUINE = _npy(_ROWS)


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (_npy(np.array([[object()] * 6], dtype=object), allow_pickle=True), "Python objects"),
        (b"\x80\x04\x95" + bytes(40), r"not a \.npy array \(the magic string"),  # a pickle
        (b"PK\x03\x04" + bytes(40), r"a \.npz archive, not one \.npy array"),
        (_GENUINE[:-8], r"says \(5, 6\) float32 \(120 bytes\) but 112 bytes follow"),
        (_GENUINE + bytes(8), r"but 128 bytes follow"),
        (_GENUINE.replace(b"(5, 6)", b"(9**99,)"), "not a .npy array"),  # no literal shape
        (
            _GENUINE.replace(b"(5, 6), ", b"(99999999999, 6),"),
            r"\(99999999999, 6\) float32 \(2399999999976 bytes\) but",
        ),
        (_GENUINE.replace(b"(5, 6), ", b"(2**62+2, 6),"), "not a .npy array"),
        (
            _GENUINE.replace(b"(5, 6), ", b"(4611686018427387906, 6),"),  # int64 would wrap
            r"\(110680464442257309744 bytes\) but",
        ),
        (_GENUINE.replace(b"'<f4'", b"'<c8'"), r"holds complex64 values, not real numbers"),
        (_npy(np.ones((2, 6), bool)), "holds bool values"),
        (_npy(np.array([["a"] * 6])), "holds <U1 values"),
        (_npy(np.ones((4, 5))), r"shape \(N, 6\) or \(B, N, 6\), got \(4, 5\)"),
        (_npy(np.ones(6)), r"got \(6,\)"),
        (_npy(_NAN), r"row \[1, 2\] is not finite \(x\): \[0\.0, 0\.0, 0\.0, 0\.0, nan, 0\.0\]"),
        (_npy(np.full((1, 6), 1e300)), None),  # genuine: large, finite
    ],
)
def test_a_number_array_file_is_read_bounded_and_never_unpickled(tmp_path, data, reason):
    path = tmp_path / "pairs.npy"
    path.write_bytes(data)
    if reason is None:
        assert read_number_array(path, 6, "x").shape == (1, 6)
        return
    with within(5), pytest.raises(ValueError, match=reason) as info:
        read_number_array(path, 6, "x")
    assert str(path) in str(info.value)


def test_a_number_array_is_bounded_as_the_float64_array_it_becomes(tmp_path, monkeypatch):
    """int8 numbers become 8 times as many bytes as float64: a file within the cap could
    allocate 8 times the cap (2 GiB from a 256 MiB file)."""
    monkeypatch.setitem(io.MAX_BYTES, "number array", 1000)
    path = tmp_path / "pairs.npy"
    path.write_bytes(_npy(np.ones((20, 6), np.float32)))  # 960 bytes as float64: read
    assert read_number_array(path, 6, "x").shape == (20, 6)
    path.write_bytes(_npy(np.ones((30, 6), np.int8)))  # a 308-byte file, 1440 bytes as float64
    assert path.stat().st_size < 1000
    with pytest.raises(
        UnreadableFileError, match=r"\(30, 6\) numbers take 1440 bytes as float64, over"
    ):
        read_number_array(path, 6, "x")


def test_a_genuine_number_array_reads_in_either_order_as_float64(tmp_path):
    for order in ("C", "F"):
        path = tmp_path / f"{order}.npy"
        path.write_bytes(_npy(np.asarray(_ROWS, order=order)))
        read = read_number_array(path, 6, "x")
        assert read.dtype == np.float64 and np.array_equal(read, _ROWS)
    fifo = tmp_path / "fifo.npy"
    os.mkfifo(fifo)
    with within(5), pytest.raises(UnreadableFileError, match="a named pipe"):
        read_number_array(fifo, 6, "x")


def test_metrics_may_hold_nan(tmp_path):
    path = tmp_path / "metrics.json"
    path.write_text('{"test/nll": NaN}')
    assert read_record(path)["test/nll"] != read_record(path)["test/nll"]


def test_a_yaml_alias_bomb_is_refused_unexpanded(tmp_path):
    """890 bytes that expand to 9^9 = 387 million strings (7.5 GB in the report's flattening)."""
    lines = ["a: &a [x, x, x, x, x, x, x, x, x]"]
    pairs = zip("abcdefgh", "bcdefghi", strict=True)
    lines += [f"{c}: &{c} [" + ", ".join([f"*{p}"] * 9) + "]" for p, c in pairs]
    path = tmp_path / "config.yaml"
    path.write_text("\n".join(lines) + "\n")
    assert path.stat().st_size < 1000
    with within(5), pytest.raises(UnreadableFileError, match=r"config\.yaml:2: YAML alias \*a"):
        read_yaml(path)


def test_genuine_yaml_reads(tmp_path):
    path = tmp_path / "overrides.yaml"
    path.write_text("- data=tiny\n- optim.lr=0.001\n")
    assert read_yaml(path, "overrides file") == ["data=tiny", "optim.lr=0.001"]


# ---- pickles read as data -----------------------------------------------------------------------

_PLAIN = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(),
    lambda inner: (
        st.lists(inner, max_size=4)
        | st.tuples(inner, inner)
        | st.dictionaries(st.text(max_size=5) | st.integers(), inner, max_size=4)
    ),
    max_leaves=30,
)


@settings(max_examples=300, deadline=None)
@given(value=_PLAIN, protocol=st.integers(0, pickle.HIGHEST_PROTOCOL))
def test_a_pickle_of_plain_data_reads_as_pickle_loads_it(value, protocol):
    """`plain_pickle` reads what `pickle.loads` would, for plain data in every protocol, without
    an unpickler."""
    from rotlearn.io import plain_pickle

    assert plain_pickle(pickle.dumps(value, protocol=protocol)) == value


def test_a_pickle_that_would_run_code_runs_nothing_and_reads_opaque(tmp_path):
    """What unpickling builds by calling code is never called: a payload, a tensor, a set and
    an OrderedDict (a state_dict) read as OPAQUE."""
    import collections

    from rotlearn.io import OPAQUE, plain_pickle

    marker = tmp_path / "pwned"
    payload = type("Payload", (), {"__reduce__": lambda self: (os.system, (f"touch {marker}",))})
    data = {"run": payload(), "state_dict": collections.OrderedDict(w=torch.ones(2)), "n": 1,
            "set": {1, 2}}  # fmt: skip
    assert plain_pickle(pickle.dumps(data, protocol=2)) == {
        "run": OPAQUE, "state_dict": OPAQUE, "n": 1, "set": OPAQUE
    }  # fmt: skip
    assert not marker.exists()


@pytest.mark.parametrize(
    "where", ["the value", "a dict key", "a set", "an OrderedDict's keys", "a dict thrown away"]
)
def test_a_pickle_of_2_to_the_40_values_is_refused_before_anything_hashes_or_walks_them(where):
    """A few hundred bytes whose shared references hold 2**40 values: as a value, walking it
    never ends; as a key or in a set (torch's unpickler builds sets and OrderedDicts), hashing
    it never ends. `plain_pickle` hashes nothing before `tree_problem` has counted it all."""
    from rotlearn.io import MAX_NODES, plain_pickle

    kind = list if where == "the value" else tuple
    tree = pickle.dumps(doubling(kind(["leaf"]), 40, kind), protocol=2)
    body = tree[2:-1]  # the tree's opcodes, without PROTO and STOP
    wrapped = {
        "the value": tree,
        "a dict key": b"\x80\x02}" + body + b"K\x01s.",
        "a set": b"\x80\x02cbuiltins\nset\n]" + body + b"a\x85R.",
        "an OrderedDict's keys": b"\x80\x02ccollections\nOrderedDict\n)R" + body + b"K\x01s.",
        "a dict thrown away": b"\x80\x02}" + body + b"K\x01s0K\x01.",  # POP, then 1
    }[where]
    assert len(wrapped) < 400
    with within(30), pytest.raises(ValueError, match=f"more than {MAX_NODES} values"):
        plain_pickle(wrapped)


def test_a_pickle_of_opcodes_that_build_nothing_is_refused_in_seconds():
    """Six million marks (6 MB) build nothing that `tree_problem` counts; reading them all would
    take seconds per megabyte of a larger file. A few opcodes per value of the bound are read."""
    from rotlearn.io import MAX_NODES, plain_pickle

    with within(30), pytest.raises(ValueError, match=f"more than {5 * MAX_NODES} opcodes"):
        plain_pickle(b"\x80\x02" + b"(" * 6_000_000 + b"N.")


def test_shared_references_come_out_as_copies_and_cycles_are_refused():
    from rotlearn.io import plain_pickle, tree_problem

    part = [1, 2]
    read = plain_pickle(pickle.dumps({"a": part, "b": part}, protocol=2))
    assert read == {"a": [1, 2], "b": [1, 2]} and read["a"] is not read["b"]
    cycle: list = []
    cycle.append(cycle)
    with pytest.raises(ValueError, match="nested too deeply"):
        plain_pickle(pickle.dumps(cycle, protocol=2))
    assert tree_problem([[[1]]]) is None


@pytest.mark.parametrize(
    "data",
    [b"", b"\x80\x02", pickle.dumps([1, 2])[:-1], b"\x80\x02a.", b"\x80\x02}(]K\x01u."],
    ids=["empty", "no opcodes", "no STOP", "stack underflow", "a list as a key"],
)
def test_a_broken_pickle_is_refused(data):
    from rotlearn.io import plain_pickle

    with pytest.raises(ValueError, match="pickle"):
        plain_pickle(data)


# ---- durable writes -----------------------------------------------------------------------------


def test_a_symlink_at_the_target_is_replaced_not_written_through(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    link = tmp_path / "status.json"
    link.symlink_to(victim)
    write_text_atomic(link, "{}")
    assert victim.read_text() == "precious\n" and not link.is_symlink()


def test_a_failed_write_names_the_file_and_keeps_the_previous_one(tmp_path, monkeypatch):
    path = tmp_path / "last.ckpt"
    path.write_bytes(b"epoch 0")
    real_write = os.write

    def full_disk(fd, data):
        real_write(fd, bytes(data[:3]))  # a part reaches the disk, then it is full
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(io.os, "write", full_disk)
    with pytest.raises(WriteError) as info:
        write_bytes_atomic(path, b"epoch 1 and much more")
    assert str(info.value) == (
        f"cannot write {path}: No space left on device; the previous file is unchanged"
    )
    assert info.value.errno == errno.ENOSPC
    assert path.read_bytes() == b"epoch 0"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt"]  # no temporary file


def test_rewrite_in_place_reuses_the_files_blocks(tmp_path):
    path = tmp_path / "status.json"
    path.write_text('{"status": "RUNNING", "padding": "' + "x" * 200 + '"}')
    inode = path.stat().st_ino
    rewrite_in_place(path, b'{"status": "FAILED"}')
    assert path.read_text() == '{"status": "FAILED"}' and path.stat().st_ino == inode
    link = tmp_path / "link.json"
    link.symlink_to(path)
    with pytest.raises(WriteError):
        rewrite_in_place(link, b"{}")  # never written through a symlink


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


@pytest.mark.parametrize("name", ["frames.npy", "[x]*?.npy"])  # glob characters in the name
def test_a_killed_writers_temporary_is_removed_a_live_ones_is_not(tmp_path, name):
    """A write killed mid-way (SIGKILL, the out-of-memory killer) left its temporary file for
    good: a frame cache's is gigabytes. `remove_stale_temporaries` removes those no live writer
    holds; a write in progress (here: in this very process), a link and a FIFO of that name
    stay."""
    path = tmp_path / name
    killed = subprocess.run(  # a writer that dies inside the block, as SIGKILL leaves it
        [sys.executable, "-c", "import os, sys\nfrom rotlearn.io import atomic_write\n"
         "with atomic_write(sys.argv[1]) as tmp:\n    tmp.write_bytes(b'x' * 1000)\n"
         "    os._exit(9)", str(path)],
        check=False,
    )  # fmt: skip
    assert killed.returncode == 9
    [stale] = [p for p in tmp_path.iterdir() if p.name.startswith(f".{name}.")]
    (tmp_path / f".{name}.0000000a.tmp.npy").symlink_to(stale)
    os.mkfifo(tmp_path / f".{name}.0000000b.tmp.npy")
    with atomic_write(path) as live:
        live.write_bytes(b"live")
        remove_stale_temporaries(path)  # as a second writer would, while this one writes
        assert live.read_bytes() == b"live"  # the live writer's temporary was kept
    assert path.read_bytes() == b"live" and not stale.exists()
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([name, f".{name}.0000000a.tmp.npy", f".{name}.0000000b.tmp.npy"])


def test_a_temporary_never_bears_its_name_unlocked(tmp_path, monkeypatch):
    """Between its creation and its `flock` a new temporary file was unlocked: a second
    writer's sweep in that moment removed a live temporary and the first write failed. It is
    made and locked under another name now; here the sweep runs in that very moment."""
    path = tmp_path / "frames.npy"
    flock = io.fcntl.flock

    def sweep_first(fd, operation):
        remove_stale_temporaries(path)  # another writer's sweep, before this lock is taken
        flock(fd, operation)

    monkeypatch.setattr(io.fcntl, "flock", sweep_first)
    with atomic_write(path) as tmp:
        tmp.write_bytes(b"whole")
    assert path.read_bytes() == b"whole"
    assert [p.name for p in tmp_path.iterdir()] == ["frames.npy"]


def test_without_fcntl_writes_go_on_and_nothing_is_swept(tmp_path):
    """Windows has no `fcntl`: rotlearn.io imported it unguarded, so nothing could be read or
    written there."""
    script = "\n".join([
        "import sys", "sys.modules['fcntl'] = None", "from pathlib import Path",
        "from rotlearn.io import remove_stale_temporaries, write_text_atomic",
        "path = Path(sys.argv[1]) / 'a.json'",
        "stale = path.with_name('.a.json.0123abcd.tmp.json')", "stale.write_text('old')",
        "remove_stale_temporaries(path)", "write_text_atomic(path, 'x')",
        "assert stale.exists() and path.read_text() == 'x'",
    ])  # fmt: skip
    done = subprocess.run([sys.executable, "-c", script, str(tmp_path)], capture_output=True)
    assert done.returncode == 0, done.stderr.decode()


@settings(max_examples=300, deadline=None)
@given(
    text=st.text(alphabet="ab #\n\r\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029", max_size=200),
    block=st.integers(1, 30),
)
def test_lines_read_a_block_at_a_time_are_splitlines(text, block):
    """`read_number_rows` reads a file's lines a block at a time (a file of short lines is not
    held as millions of strings); the lines and so the line numbers in messages are
    `str.splitlines`'s, a `\\r\\n` across a block's end included."""
    from rotlearn.io import text_lines

    assert list(text_lines(text, block)) == text.splitlines()


def test_a_file_of_carriage_returns_is_read_a_block_at_a_time_too():
    """Blocks were cut at newlines only: a file whose lines end in "\\r" alone was split whole,
    a string per line at once (+526 MB for a 32 MB point file, against +152 MB)."""
    import tracemalloc

    from rotlearn.io import text_lines

    text = "0 0 1\r" * 4_000_000  # 24 MB
    tracemalloc.start()
    try:
        count = sum(1 for _ in text_lines(text))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert count == 4_000_000 and peak < 50 * 2**20, f"peak {peak / 2**20:.0f} MiB"


def test_a_file_where_a_folder_goes_is_named(tmp_path):
    """A dataset's `.rotlearn_cache` that is a file gave "cannot write <cache>.npy: File
    exists", naming the file the cache would have held, not the file in the way."""
    (tmp_path / ".rotlearn_cache").write_text("")
    target = tmp_path / ".rotlearn_cache" / "sub" / "x.npy"
    pattern = rf"{target}: {tmp_path / '.rotlearn_cache'} is a file, not a folder"
    with pytest.raises(WriteError, match=pattern):
        write_text_atomic(target, "x")


def test_a_csv_table_that_is_not_utf8_is_named_with_its_line(tmp_path):
    """read_table parses the bytes read (no copy as text); a byte that is not UTF-8 is still
    named by the file's line and byte, not by pandas' buffer position."""
    from rotlearn.io import read_table

    path = tmp_path / "ood.csv"
    path.write_bytes(b"a,b\n1,2\n3,\xff\n")
    with pytest.raises(UnreadableFileError, match=r"ood\.csv:3: not UTF-8 text \(byte 10\)$"):
        read_table(path)
    path.write_bytes(b"a,b,c\n1,2,3\n")
    assert list(read_table(path, columns=("a", "c", "missing")).columns) == ["a", "c"]


def test_folder_entries_walks_deep_trees_without_recursion_and_never_follows_a_link(tmp_path):
    """Python 3.11's os.walk and rglob recurse: 1100 nested folders in a received run ended a
    resume and a report in a RecursionError. A link to a folder is listed, not entered."""
    folders = [tmp_path / "t"]
    for _ in range(1100):
        folders.append(folders[-1] / "d")
    try:
        for folder in folders:
            folder.mkdir()
        (folders[0] / "loop").symlink_to(folders[0])
        top = folders[0]
        names = [Path(e.path).relative_to(top) for e in folder_entries(top, 2000, 2000)]
        assert len(names) == 1101 and names[:2] == [Path("d"), Path("loop")]
        with pytest.raises(UnreadableFileError, match=r"/d: folders nested more than 50 deep$"):
            list(folder_entries(top, 2000, 50))
        with pytest.raises(UnreadableFileError, match=r"/t: more than 10 files and folders$"):
            list(folder_entries(top, 10, 2000))
    finally:  # pytest's clean-up (rmtree) recurses too
        (folders[0] / "loop").unlink(missing_ok=True)
        for folder in reversed(folders):
            if folder.is_dir():
                folder.rmdir()


def test_a_cache_manifest_tells_a_retargeted_symlink_apart(tmp_path):
    """A frame that is a symlink, pointed at another file of the same size and times (a ctime
    the file system rounds alike), kept the cache of the first file's pixels."""
    pool = tmp_path / "pool"
    pool.mkdir()
    (pool / "a.ppm").write_bytes(b"P6 1 1 255\n\0\0\0")
    (pool / "b.ppm").write_bytes(b"P6 1 1 255\n\xff\xff\xff")
    times = os.stat(pool / "a.ppm").st_atime_ns, os.stat(pool / "a.ppm").st_mtime_ns
    os.utime(pool / "b.ppm", ns=times)
    frame = tmp_path / "000000.png"
    frame.symlink_to(pool / "a.ppm")
    before = cache_manifest([frame], {})
    frame.unlink()
    frame.symlink_to(pool / "b.ppm")
    after = cache_manifest([frame], {})
    assert before["sizes"] == after["sizes"] and before["mtimes_ns"] == after["mtimes_ns"]
    assert before["inodes"] != after["inodes"] and before != after
