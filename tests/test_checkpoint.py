"""rotlearn.checkpoint: what a checkpoint may make rotlearn allocate or compute. Sizes in its
config are checked against its weights on the meta device before anything is built; weights
must be floating point and finite; missing or extra weights and another net's config are named;
truncated, oversized and decompression-bomb files are refused unread. Each refusal changes
nothing below the test's folder (the crafted file and everything beside it: `unchanged`)."""

from __future__ import annotations

import io
import pickle
import resource
import struct
import zipfile
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

import rotlearn
from rotlearn.checkpoint import (
    UnsafeCheckpointError,
    UntrustedConfigError,
    load_checkpoint,
    load_run,
    saved_config,
)
from rotlearn.io import MAX_BYTES, MAX_NODES
from tests.conftest import doubling, point_pairs, unchanged, within


@pytest.fixture
def crafted(finished_run, tmp_path):
    """edit(checkpoint dict) -> a copy of the finished run's last.ckpt with the edit applied."""

    def make(edit) -> str:
        checkpoint = torch.load(finished_run / "checkpoints" / "last.ckpt", weights_only=True)
        edit(checkpoint)
        path = tmp_path / "checkpoints" / "last.ckpt"
        path.parent.mkdir(exist_ok=True)
        torch.save(checkpoint, path)
        return str(path)

    return make


def _set(key: str, value):
    return lambda c: (
        OmegaConf.update(config := OmegaConf.create(c["rotlearn_config"]), key, value)
        or c.update(rotlearn_config=OmegaConf.to_container(config))
    )


def test_sizes_in_the_config_are_checked_before_anything_is_allocated(crafted, tmp_path):
    """net.head_channels=[1000000, 128] once allocated 4.9 GB before the shapes were checked."""
    path = crafted(_set("net.head_channels", [1_000_000, 128]))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with unchanged(tmp_path), within(20), pytest.raises(ValueError, match="shape") as info:
        rotlearn.load(path)
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert path in str(info.value) and grown_mb < 500


def test_weights_that_repeat_one_stored_value_are_refused_before_anything_is_allocated(
    crafted, tmp_path
):
    """A file of kilobytes whose weights are views of one stored value (stride 0) would pass
    the shape check for any size its config names: with net.head_channels=[20000, 128] an 8 kB
    file made rotlearn.load allocate 3.2 GB."""
    from rotlearn.nets import PointNet

    def edit(c):
        net = c["rotlearn_config"]["net"]
        net["point_channels"][-1] = net["head_channels"][0] = 20_000
        with torch.device("meta"):
            built = PointNet(**{k: v for k, v in net.items() if k != "_target_"})
        for name, want in built.state_dict().items():
            c["state_dict"][f"net.{name}"] = torch.zeros(1, dtype=want.dtype).expand(want.shape)

    path = crafted(edit)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with (
        unchanged(tmp_path),
        within(60),
        pytest.raises(ValueError, match=r"its weights hold 16\d{8} bytes but store \d{2,3}:"),
    ):
        rotlearn.load(path)
    assert (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024 < 500


def test_weights_that_share_one_storage_are_refused(crafted, tmp_path):
    """Names that view one storage would each be built from it: a file of one weight's bytes
    for a model of many."""

    def edit(c):
        weights = {k: v for k, v in c["state_dict"].items() if k.startswith("net.")}
        shared = torch.zeros(max(v.numel() for v in weights.values()))
        for name, weight in weights.items():
            c["state_dict"][name] = shared[: weight.numel()].view(weight.shape)

    path = crafted(edit)
    with unchanged(tmp_path), pytest.raises(ValueError, match="names sharing storage") as info:
        rotlearn.load(path)
    assert path in str(info.value)


@pytest.mark.parametrize("kind", ["sparse", "meta"])
def test_weights_must_be_dense_tensors_with_data(crafted, tmp_path, kind):
    """A sparse weight (any size it declares) or one on the meta device (no data) gave a
    traceback from the storage check ('Cannot access storage of SparseTensorImpl', 'item()
    cannot be called on meta tensors'); it is refused, naming the file and the weight."""
    names = []

    def edit(c):
        name = next(n for n, v in c["state_dict"].items() if v.ndim == 2)
        weight = c["state_dict"][name]
        names.append(name)
        c["state_dict"][name] = (weight.to_sparse() if kind == "sparse"
                                 else torch.empty(weight.shape, device="meta"))  # fmt: skip

    path = crafted(edit)
    with unchanged(tmp_path), pytest.raises(ValueError, match="dense tensors") as info:
        rotlearn.load(path)
    assert path in str(info.value) and names[0] in str(info.value)


@pytest.mark.parametrize("dtype", [torch.int64, torch.bool, torch.complex64])
def test_weights_must_be_floating_point(crafted, tmp_path, dtype):
    def edit(c):
        name = next(iter(c["state_dict"]))
        c["state_dict"][name] = c["state_dict"][name].to(dtype)

    path = crafted(edit)
    with unchanged(tmp_path), pytest.raises(ValueError, match=f"is stored as {dtype}; it must"):
        rotlearn.load(path)


@pytest.mark.parametrize("value", [float("nan"), float("inf"), 1e300])
def test_weights_must_be_finite_in_the_models_dtype(crafted, tmp_path, value):
    def edit(c):
        name = next(iter(c["state_dict"]))
        weight = c["state_dict"][name].double()
        weight.view(-1)[0] = value
        c["state_dict"][name] = weight  # 1e300 is finite in float64, not in the net's float32

    path = crafted(edit)
    with unchanged(tmp_path), pytest.raises(ValueError, match="NaN or infinite"):
        rotlearn.load(path)


def test_missing_and_unexpected_weights_are_named(crafted, tmp_path):
    def edit(c):
        name = sorted(c["state_dict"])[0]
        c["state_dict"]["net.extra.weight"] = c["state_dict"].pop(name)

    path = crafted(edit)
    with (
        unchanged(tmp_path),
        pytest.raises(ValueError, match=r"missing net\..*; unexpected net\.extra\.weight") as info,
    ):
        rotlearn.load(path)
    assert "Traceback" not in str(info.value)


def test_another_allowed_net_in_the_config_is_named_not_a_traceback(crafted, tmp_path):
    path = crafted(_set("net._target_", "rotlearn.nets.PairCNN"))
    with unchanged(tmp_path), pytest.raises(ValueError, match=r"net cannot be built") as info:
        rotlearn.load(path)
    assert path in str(info.value)


def test_a_truncated_or_inflating_or_oversized_file_is_refused_unread(tmp_path, monkeypatch):
    path = tmp_path / "last.ckpt"
    torch.save({"epoch": 0, "state_dict": {"w": torch.ones(1000)}}, path)
    whole = path.read_bytes()
    path.write_bytes(whole[: len(whole) // 2])
    with unchanged(tmp_path), pytest.raises(UnsafeCheckpointError, match="not a whole PyTorch"):
        load_checkpoint(path)
    path.unlink()
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("archive/data.pkl", b"\0" * 50_000_000)  # 50 MB from about 50 kB
    with (
        unchanged(tmp_path),
        within(10),
        pytest.raises(UnsafeCheckpointError, match="would decompress to 50000000"),
    ):
        load_checkpoint(path)
    path.write_bytes(whole)
    monkeypatch.setitem(MAX_BYTES, "checkpoint", 1000)
    with unchanged(tmp_path), pytest.raises(UnsafeCheckpointError, match="larger than a checkp"):
        load_checkpoint(path)


def test_torch_loads_the_file_that_was_checked_not_one_swapped_in_after(tmp_path, monkeypatch):
    """The bounded check and torch's load read one open file: a checkpoint renamed over it in
    between (it could hold what the check refuses) is not the one loaded."""
    import rotlearn.checkpoint as checkpoint

    path, other = tmp_path / "last.ckpt", tmp_path / "other.ckpt"
    torch.save({"epoch": 1, "state_dict": {"w": torch.ones(3)}}, path)
    torch.save({"epoch": 2, "state_dict": {"w": torch.zeros(3)}}, other)
    check = checkpoint._plain_checkpoint

    def check_then_swap(*args):
        found = check(*args)
        other.replace(path)  # after the check, before torch reads
        return found

    monkeypatch.setattr(checkpoint, "_plain_checkpoint", check_then_swap)
    loaded = load_checkpoint(path)
    assert loaded["epoch"] == 1 and torch.equal(loaded["state_dict"]["w"], torch.ones(3))
    assert torch.load(path, weights_only=True)["epoch"] == 2  # the swap took place


def test_the_evaluation_runs_on_the_devices_its_command_line_gives(finished_run, tmp_path):
    """A checkpoint's trainer.devices=6 once launched six processes in rotlearn-eval."""
    from hydra import compose, initialize_config_dir

    from rotlearn.cli.evaluate import evaluation_config
    from rotlearn.paths import config_dir

    saved = load_run(finished_run)
    OmegaConf.update(saved.config, "trainer.devices", 6)
    OmegaConf.update(saved.config, "trainer.accelerator", "gpu")
    OmegaConf.update(saved.config, "trainer.strategy", "ddp")
    for given, devices in (([], 1), (["trainer.devices=2"], 2)):
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose("eval", [f"ckpt={finished_run}", f"paths.output_dir={tmp_path}", *given])
        trainer = evaluation_config(cfg, saved).trainer
        assert trainer.devices == devices and trainer.accelerator == "auto"
        assert "strategy" not in trainer


def test_the_evaluation_runs_the_loader_processes_its_command_line_gives(finished_run, tmp_path):
    """A checkpoint's data.num_workers=64 made rotlearn-eval run 317 processes at once."""
    from hydra import compose, initialize_config_dir

    from rotlearn.cli.evaluate import evaluation_config
    from rotlearn.paths import config_dir

    saved = load_run(finished_run)
    OmegaConf.update(saved.config, "data.num_workers", 64, force_add=True)
    for given, workers in (([], None), (["data.num_workers=3"], 3)):
        with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
            cfg = compose("eval", [f"ckpt={finished_run}", f"paths.output_dir={tmp_path}", *given])
        data = evaluation_config(cfg, saved).data
        assert data.get("num_workers") == workers  # None: the datamodule's own default


def test_a_run_cannot_send_the_loader_outside_it_through_a_symlink(finished_run, tmp_path):
    from rotlearn.checkpoint import TEMPERATURE_FILE
    from tests.conftest import copy_run

    outside = tmp_path / "elsewhere.ckpt"
    outside.write_bytes((finished_run / "checkpoints" / "last.ckpt").read_bytes())
    run = copy_run(finished_run, tmp_path / "run")
    (run / "checkpoints" / "last.ckpt").unlink()
    (run / "checkpoints" / "last.ckpt").symlink_to(outside)
    with unchanged(tmp_path), pytest.raises(UnsafeCheckpointError, match=r"a symlink to .*outside"):
        rotlearn.load(run)
    (run / "checkpoints" / "last.ckpt").unlink()
    (run / "checkpoints" / "last.ckpt").write_bytes(outside.read_bytes())
    record = tmp_path / "temperature.json"
    record.write_text('{"temperature": 2.0}')
    (run / "checkpoints" / TEMPERATURE_FILE).unlink(missing_ok=True)  # calibrate: auto wrote one
    (run / "checkpoints" / TEMPERATURE_FILE).symlink_to(record)
    with pytest.raises(ValueError, match="outside"):
        rotlearn.load(run)


def test_a_run_directory_loads_the_weights_its_test_scored(finished_run, tmp_path, caplog):
    """A run trained with test_ckpt=best was loaded from last.ckpt: other weights than its test
    scored, and its temperature (fitted for best.ckpt) left out with a warning."""
    import json

    from tests.conftest import copy_run

    run = copy_run(finished_run, tmp_path / "run")
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["tested_checkpoint"] == "last.ckpt"
    assert load_run(run).path == run / "checkpoints" / "last.ckpt"
    best = load_checkpoint(run / "checkpoints" / "last.ckpt")
    best["state_dict"] = {k: v + 1 for k, v in best["state_dict"].items()}  # told apart
    torch.save(best, run / "checkpoints" / "best.ckpt")

    def loads_with(**record):
        (run / "metrics.json").write_text(json.dumps({**metrics, **record}))
        with unchanged(tmp_path):  # the loader writes nothing
            return load_run(run)

    for record in (
        {"tested_checkpoint": "best.ckpt"},  # what a test_ckpt=best run records
        {"tested_checkpoint": None, "tested_weights": "best"},
    ):  # runs recorded before
        loaded = loads_with(**record)
        assert loaded.path == run / "checkpoints" / "best.ckpt"
        for name, value in best["state_dict"].items():
            torch.testing.assert_close(loaded.state_dict[name], value, rtol=0, atol=0)
    # a name that is not a file in checkpoints/: the last weights, with a warning naming it
    for name in ("../../metrics.json", "../last.ckpt", "missing.ckpt", 3):
        caplog.clear()
        assert loads_with(tested_checkpoint=name).path.name == "last.ckpt"
        assert f"tested checkpoint {name!r} is not a file in" in caplog.text
    outside = tmp_path / "elsewhere.ckpt"
    (run / "checkpoints" / "best.ckpt").rename(outside)
    (run / "checkpoints" / "best.ckpt").symlink_to(outside)
    with pytest.raises(UnsafeCheckpointError, match=r"a symlink to .*outside"):
        loads_with(tested_checkpoint="best.ckpt")


def test_loggers_and_training_callbacks_of_a_saved_config_are_neither_checked_nor_built(
    finished_run, tmp_path
):
    """A run trained with a callback or logger of the user's own was refused as untrusted,
    although no load builds those nodes; now they are dropped unread (the OOD evaluation's
    `callbacks.ood`, which rotlearn-eval reuses, is kept and checked)."""
    from tests.conftest import copy_run

    run = copy_run(finished_run, tmp_path / "run")
    path = run / "checkpoints" / "last.ckpt"
    checkpoint = load_checkpoint(path)
    config = checkpoint["rotlearn_config"]
    config["callbacks"]["mine"] = {"_target_": "os.system", "command": "touch pwned"}
    config["logger"] = {"wandb": {"_target_": "lightning.pytorch.loggers.WandbLogger"}}
    torch.save(checkpoint, path)
    saved = load_run(run)
    assert "logger" not in saved.config and "mine" not in saved.config.callbacks
    assert rotlearn.load(run)(point_pairs(2)).R.shape == (2, 3, 3)
    assert not (tmp_path / "pwned").exists() and not (run / "pwned").exists()
    config["callbacks"]["ood"] = {"_target_": "os.system", "command": "touch pwned"}
    torch.save(checkpoint, path)
    with pytest.raises(UntrustedConfigError, match=r"callbacks\.ood\._target_: 'os.system'"):
        load_run(run)


def _with_pickle(checkpoint: Path, data: bytes) -> None:
    """Replace the pickle record of the torch checkpoint at `checkpoint` with `data`."""
    with zipfile.ZipFile(checkpoint) as archive:
        records = [(info, archive.read(info)) for info in archive.infolist()]
    with zipfile.ZipFile(checkpoint, "w") as archive:
        for info, record in records:
            archive.writestr(info, data if info.filename.endswith("/data.pkl") else record)


@pytest.mark.parametrize("place", ["rotlearn_config", "optimizer_states", "a key"])
def test_a_checkpoint_whose_shared_references_expand_without_bound_is_refused(
    finished_run, tmp_path, capsys, place
):
    """A file of a few kilobytes whose config (or optimizer state, which Lightning's restore
    walks) holds 2**40 values through pickle's memo, or a pickle of 220 bytes whose one dict key
    is such a tuple (torch's own unpickler hashed it for ever): every loader refuses it at once,
    naming the file."""
    from rotlearn.cli.evaluate import _checked
    from rotlearn.cli.predict import main as predict_main

    checkpoint = torch.load(finished_run / "checkpoints" / "last.ckpt", weights_only=True)
    if place == "rotlearn_config":
        checkpoint["rotlearn_config"]["data"]["bomb"] = doubling(["leaf"])
    elif place == "optimizer_states":
        checkpoint["optimizer_states"] = [{"state": doubling(["leaf"])}]
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    torch.save(checkpoint, run / "checkpoints" / "last.ckpt")
    if place == "a key":  # pickle [key] with the list's opcodes made a dict's: {key: 1}
        data = pickle.dumps([doubling(("leaf",), 40, tuple)], protocol=2)
        _with_pickle(run / "checkpoints" / "last.ckpt", data[:2] + b"}" + data[3:-2] + b"K\x01s.")
    (run / "pairs.txt").write_text("0 0 1 0 0 1\n")
    expected = f"more than {MAX_NODES} values"
    with unchanged(tmp_path), within(60):
        for load in (load_checkpoint, load_run, rotlearn.load):
            with pytest.raises(UnsafeCheckpointError, match=expected) as info:
                load(run)
            assert str(run / "checkpoints" / "last.ckpt") in str(info.value)
        with pytest.raises(SystemExit, match=expected):
            _checked([f"ckpt={run}", f"hydra.run.dir={tmp_path / 'eval'}"])
        assert predict_main([str(run), str(run / "pairs.txt")]) == 2
        assert expected in capsys.readouterr().err


def test_a_damaged_pickle_record_is_refused_not_raised_as_a_zip_error(tmp_path):
    """A byte flipped in the pickle record fails its CRC when read: refused like any damaged
    archive (it once escaped the loaders as zipfile.BadZipFile, a traceback)."""
    path = tmp_path / "last.ckpt"
    torch.save({"rotlearn_config": {"a": 1}, "epoch": 0}, path)
    with zipfile.ZipFile(path) as archive:
        record = next(i for i in archive.infolist() if i.filename.endswith("/data.pkl"))
    data = bytearray(path.read_bytes())
    data[data.index(b"rotlearn_config", record.header_offset)] ^= 0xFF  # inside the record
    path.write_bytes(data)
    for read in (load_checkpoint, saved_config):
        with unchanged(tmp_path), pytest.raises(UnsafeCheckpointError, match="Bad CRC-32"):
            read(path)


def test_the_config_read_without_torch_is_the_one_torch_reads(finished_run, tmp_path):
    """`saved_config` (the first look of rotlearn-eval, before torch loads) reads a checkpoint's
    config as `torch.load(weights_only=True)` does, and refuses what `load_checkpoint` refuses."""
    ckpt = finished_run / "checkpoints" / "last.ckpt"
    assert saved_config(ckpt) == load_checkpoint(ckpt)["rotlearn_config"]
    broken = tmp_path / "last.ckpt"
    broken.write_bytes(ckpt.read_bytes()[:-100])
    with pytest.raises(UnsafeCheckpointError, match="not a whole PyTorch checkpoint"):
        saved_config(broken)
    torch.save({"rotlearn_config": {"bomb": doubling(["leaf"])}}, broken)
    with within(30), pytest.raises(UnsafeCheckpointError, match=f"more than {MAX_NODES} values"):
        saved_config(broken)


def _zip(records: list[tuple[str, bytes]], start: int = 0) -> tuple[bytes, bytes]:
    """A stored zip of `records` as (its records, its central directory), the records' offsets
    counted from `start` (where the records will lie in the file)."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as archive:
        for name, data in records:
            archive.writestr(name, data)
    whole = buffer.getvalue()
    size, offset = struct.unpack("<II", whole[-10:-2])
    directory = bytearray(whole[offset : offset + size])
    at = 0
    while at < len(directory):  # each header: 46 bytes, then its name, extra and comment
        lengths = struct.unpack("<3H", directory[at + 28 : at + 34])
        (header,) = struct.unpack("<I", directory[at + 42 : at + 46])
        directory[at + 42 : at + 46] = struct.pack("<I", header + start)
        at += 46 + sum(lengths)
    return whole[:offset], bytes(directory)


def _zip64_record(count: int, directory: bytes, offset: int) -> bytes:
    """A zip64 end record: `count` records in `directory`, which begins at `offset`."""
    return struct.pack("<4sQ2H2I4Q", b"PK\x06\x06", 44, 45, 45, 0, 0, count, count,
                       len(directory), offset)  # fmt: skip


def _zip64_end(where: int) -> bytes:
    """A zip64 locator naming the zip64 end record at `where`, then the end record deferring to
    it, as torch writes them."""
    return struct.pack("<4sIQI", b"PK\x06\x07", 0, where, 1) + struct.pack(
        "<4s4H2IH", b"PK\x05\x06", 0, 0, 0xFFFF, 0xFFFF, 0xFFFFFFFF, 0xFFFFFFFF, 0
    )


def _two_readings(layout: str, genuine: dict[str, bytes], other: bytes) -> bytes:
    """A checkpoint whose `<folder>/data.pkl` zipfile reads as `genuine`'s and torch (miniz) as
    `other`, by `layout`."""
    pkl = "archive/data.pkl"
    rest = [(name, data) for name, data in genuine.items() if name != pkl]
    if layout in ("one name twice", "a name in another case", "a name cut at a NUL"):
        first = {"one name twice": pkl, "a name in another case": "archive/DATA.pkl",
                 "a name cut at a NUL": pkl}[layout]  # fmt: skip
        last = "archive/data.pkl#" if layout == "a name cut at a NUL" else pkl
        records, directory = _zip([(first, other), *rest, (last, genuine[pkl])])
        count = len(rest) + 2
        data = records + directory + struct.pack("<4s4H2IH", b"PK\x05\x06", 0, 0, count, count,
                                                 len(directory), len(records), 0)  # fmt: skip
        return data.replace(b"data.pkl#", b"data.pkl\0")  # zipfile ends the name at the NUL
    # miniz reads the central directory the end records name, zipfile the one just before them
    count = len(rest) + 1
    if layout == "data before the directory":  # zipfile adds its directory's start to offsets
        theirs, their_directory = _zip([(pkl, other), *rest])
        pad = b"\0" * max(0, len(their_directory) - len(theirs))
        at = len(theirs) + len(pad) - len(their_directory)
        ours, our_directory = _zip([(pkl, genuine[pkl]), *rest], start=at)
        data = theirs + pad + ours + their_directory
        end = struct.pack("<4s4H2IH", b"PK\x05\x06", 0, 0, count, count, len(our_directory),
                          len(data) - len(their_directory), 0)  # fmt: skip
        return data + our_directory + end
    theirs, their_directory = _zip([(pkl, other), *rest])  # "a zip64 locator elsewhere"
    ours, our_directory = _zip([(pkl, genuine[pkl]), *rest], start=len(theirs))
    data = theirs + ours + their_directory
    named = len(data)  # miniz reads the zip64 record the locator names, zipfile the last one
    data += _zip64_record(count, their_directory, len(theirs) + len(ours)) + our_directory
    return data + _zip64_record(count, our_directory, named + 56) + _zip64_end(named)


@pytest.mark.filterwarnings("ignore:Duplicate name")
@pytest.mark.parametrize(
    "layout",
    [
        "one name twice",
        "a name in another case",
        "a name cut at a NUL",
        "data before the directory",
        "a zip64 locator elsewhere",
    ],
)
def test_a_checkpoint_torch_would_read_otherwise_than_the_bounded_check_is_refused(
    tmp_path, layout
):
    """Two `<folder>/data.pkl` records (torch's reader, miniz, reads the first, zipfile the last;
    miniz ignores case, zipfile cuts a name at a NUL), or two central directories (miniz reads
    the one the end records name, zipfile the one that ends before them): the bounded pre-check
    read the genuine pickle while torch unpickled the other one, a 210-byte hash bomb that hung
    every loader. Refused before torch reads it, naming the file; here the other record is
    harmless, so that the check's absence fails the test instead of hanging it."""
    buffer = io.BytesIO()
    torch.save({"rotlearn_config": {"a": 1}, "epoch": 0}, buffer)  # records in archive/
    with zipfile.ZipFile(buffer) as archive:
        genuine = {info.filename: archive.read(info) for info in archive.infolist()}
    path = tmp_path / "last.ckpt"
    path.write_bytes(_two_readings(layout, genuine, pickle.dumps({"other": 1}, protocol=2)))
    assert torch.load(path, weights_only=True) == {"other": 1}  # what torch reads
    assert zipfile.ZipFile(path).read("archive/data.pkl") == genuine["archive/data.pkl"]
    for read in (load_checkpoint, saved_config):
        with unchanged(tmp_path), pytest.raises(UnsafeCheckpointError) as info:
            read(path)
        assert str(info.value).startswith(f"{path}: ") and "\n" not in str(info.value)
