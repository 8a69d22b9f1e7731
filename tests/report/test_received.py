"""A sweep or run received from someone else is hostile data: rotlearn-report writes nothing
outside its report folder, reads nothing outside the sweep, and answers a crafted file with one
line that names it (a refused report writes nothing; a damaged file of one run is warned about
and left out)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml

from rotlearn.cli.report import main
from rotlearn.report import collect_runs, make_report
from tests.cli.test_report_ood import _fabricate_run


def _run(run: Path, report: dict | None = None, seed: int = 0, error: float = 1.0) -> Path:
    """A completed run directory: its config (with `report` as its report node), metrics and
    status."""
    (run / ".hydra").mkdir(parents=True)
    config = {"rep": {"name": "a"}, "seed": seed, "report": report}
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    metrics = {"test/err_mean": error, "test/err_median": error}
    (run / "metrics.json").write_text(json.dumps(metrics))
    (run / "status.json").write_text(json.dumps({"status": "COMPLETED"}))
    return run


def _ood_run(run: Path) -> Path:
    """A completed run with the ood.csv and ood_samples.csv of an OOD evaluation (DT only)."""
    _fabricate_run(run, "a", "BinghamNLLLoss", report={})
    return run


def _one_line(err: str, *parts: str) -> None:
    assert err.count("\n") == 1 and err.startswith("rotlearn-report: "), err
    assert "Traceback" not in err and all(p in err for p in parts), err


@pytest.mark.parametrize(
    ("plot", "key"),
    [
        ({"kind": "curves", "file": "{outside}/victim.txt"}, "report.plots[0].file"),
        ({"kind": "curves", "file": "../outside/new_dir/dropped.png"}, "report.plots[0].file"),
        ({"kind": "box", "x": "seed", "label": "../../outside/x"}, "report.plots[0].label"),
        ({"kind": "curves", "file": "metrics.json"}, "report.plots[0].file"),
        # a pooled report goes into the first run's folder: it replaced that run's own figure
        ({"kind": "curves", "file": "ood_examples.png"}, "report.plots[0].file"),
    ],
)
def test_a_plot_file_a_received_config_names_stays_in_the_report_folder(
    tmp_path, capsys, plot, key
):
    """`report.plots[].file` (or a box plot's label, which names its file) of a run's config was
    joined to the report folder as it was: an absolute path or `../` overwrote any file and
    made folders outside; a run's own records could be overwritten with a PNG. Now the report
    is refused in one line naming the config file and the key, before anything is written."""
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "victim.txt").write_text("precious\n")
    plot = {k: v.format(outside=outside) for k, v in plot.items()}
    sweep = tmp_path / "sweep"
    for seed in (0, 1):
        _run(sweep / str(seed), report={"plots": [plot]}, seed=seed, error=1.0 + seed)
    records = (sweep / "0" / "metrics.json").read_text()
    assert main([str(sweep)]) == 2
    _one_line(capsys.readouterr().err, str(sweep / "0" / ".hydra" / "config.yaml"), key)
    assert (outside / "victim.txt").read_text() == "precious\n"
    assert sorted(p.name for p in outside.iterdir()) == ["victim.txt"]
    assert sorted(p.name for p in sweep.iterdir()) == ["0", "1"]  # no summary.csv, no PNG
    assert (sweep / "0" / "metrics.json").read_text() == records


def test_a_failed_runs_long_error_is_cut_in_the_report_saying_where_the_whole_is(tmp_path):
    """A received status.json with 10 MB of error text put all of it into report.md and
    summary.csv; the report shows MAX_ERROR characters and names the file that holds it all."""
    from rotlearn.report.runs import MAX_ERROR

    sweep = tmp_path / "sweep"
    _run(sweep / "0")
    failed = _run(sweep / "1", seed=1)
    (failed / "metrics.json").unlink()
    said = "boom " * 2_000_000
    (failed / "status.json").write_text(json.dumps({"status": "FAILED", "error": said}))
    assert main([str(sweep)]) == 0
    for name in ("report.md", "summary.csv"):
        text = (sweep / name).read_text()
        assert len(text) < 20 * MAX_ERROR, name
        assert f"({len(said)} characters; the whole in {failed / 'status.json'})" in text, name


def test_received_config_text_reads_as_written_in_the_report(tmp_path):
    """Settings and keys come from the runs' configs: `<img onerror=...>` and a key holding
    `<script>` reached report.md as raw HTML, `[x](javascript:...)` as a link, and line breaks
    in a value as new rows and headings. Rendered, the report shows them as text."""
    from markdown_it import MarkdownIt

    sweep = tmp_path / "sweep"
    hostile = {
        "rep": {"name": "a <img src=x onerror=alert(1)>"},
        "optim": {"lr": "[click me](javascript:alert(document.cookie))"},
        "zz\n\n<script>alert(2)</script>\n\n# Heading from a key": "x\r\r<script>alert(3)</script>",
    }
    for seed in (0, 1):
        run = _run(sweep / str(seed), seed=seed, error=1.0 + seed)
        config = yaml.safe_load((run / ".hydra" / "config.yaml").read_text())
        config.update(hostile if seed == 0 else {})
        (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    assert main([str(sweep)]) == 0
    html = MarkdownIt("commonmark").enable("table").render((sweep / "report.md").read_text())
    assert "<script" not in html and "<img src=x" not in html
    assert 'href="javascript' not in html and html.count("<h1>") == 1
    assert "onerror=alert(1)" in html  # shown, as text


def test_a_job_folder_or_file_that_leads_out_of_the_sweep_is_not_read(tmp_path, caplog):
    """A received sweep's job folder that is a symlink to a run elsewhere (`sweep/1 -> victim`)
    was read as one of its jobs: the other run's metrics were copied into summary.csv. So was an
    ood_samples.csv that is a symlink out of its run. Now neither is read; a warning names it."""
    victim = _ood_run(tmp_path / "victim")
    metrics = json.loads((victim / "metrics.json").read_text())
    (victim / "metrics.json").write_text(json.dumps({**metrics, "secret_value": 4242}))
    sweep = tmp_path / "sweep"
    _ood_run(sweep / "0")
    (sweep / "1").symlink_to(victim, target_is_directory=True)
    (sweep / "0" / "ood_samples.csv").unlink()
    (sweep / "0" / "ood_samples.csv").symlink_to(victim / "ood_samples.csv")
    with caplog.at_level("WARNING", logger="rotlearn"):
        assert list(collect_runs(sweep)["job"]) == ["0"]
        files = make_report(sweep)
    summary = files["summary"].read_text()
    assert "secret_value" not in summary and "4242" not in summary and "victim" not in summary
    warnings = [r.getMessage() for r in caplog.records]
    assert any(f"{sweep / '1'} resolves to {victim}" in w and "not read" in w for w in warnings)
    assert any(str(sweep / "0" / "ood_samples.csv") in w and "outside" in w for w in warnings)
    assert "ood_pr" not in files  # the samples (its figures) were not read


def test_a_listed_job_whose_folder_leads_out_of_the_sweep_is_reported_as_not_read(tmp_path):
    """Its folder is not read (above); the job jobs.json lists was not shown at all ("2 jobs: 1
    completed" and nothing more). Now report.md lists it as NOT READ, saying where it leads."""
    victim, sweep = _run(tmp_path / "victim", seed=1), tmp_path / "sweep"
    _run(sweep / "0")
    (sweep / "1").symlink_to(victim, target_is_directory=True)
    jobs = [{"num": n, "dir": str(sweep / str(n)), "status": "COMPLETED",
             "overrides": [f"seed={n}"]} for n in (0, 1)]  # fmt: skip
    (sweep / "jobs.json").write_text(json.dumps({"jobs": jobs}))
    rows = collect_runs(sweep).set_index("job")
    assert list(rows["status"]) == ["COMPLETED", "NOT READ"]
    assert f"{sweep / '1'} resolves to {victim}" in rows.loc["1", "error"]
    report = make_report(sweep)["report"].read_text()
    assert "2 jobs: 1 completed, 1 not read." in report
    assert "| 1 | NOT READ | seed=1 | job folder:" in report


def test_a_received_report_layout_of_the_wrong_kind_is_refused_in_one_line(tmp_path, capsys):
    """`report: {trial_keys: 5}` failed with a TypeError traceback; now one line names the
    config file and the key, and nothing is written."""
    sweep = tmp_path / "sweep"
    _run(sweep / "0", report={"trial_keys": 5})
    assert main([str(sweep)]) == 2
    _one_line(capsys.readouterr().err, str(sweep / "0" / ".hydra" / "config.yaml"),
              "report.trial_keys: should be a valid list, got 5")  # fmt: skip
    assert sorted(p.name for p in sweep.iterdir()) == ["0"]


def test_a_folder_where_the_report_goes_is_refused_before_anything_is_written(tmp_path, capsys):
    """A received sweep holding a folder named report.md failed with a WriteError traceback
    after summary.csv and the figures were written; now one line names it, nothing written."""
    sweep = tmp_path / "sweep"
    _run(sweep / "0")
    (sweep / "report.md").mkdir()
    assert main([str(sweep)]) == 2
    _one_line(capsys.readouterr().err, str(sweep / "report.md"), "a folder")
    assert sorted(p.name for p in sweep.iterdir()) == ["0", "report.md"]


def _jobs_status(sweep: Path) -> str:
    (sweep / "jobs.json").write_text(json.dumps({"jobs": [{"num": 1, "status": {"x": 1}}]}))
    return f"{sweep / 'jobs.json'}: jobs[0].status is not a string"


def _metrics_csv(sweep: Path) -> str:
    (sweep / "0" / "csv").mkdir()
    (sweep / "0" / "csv" / "metrics.csv").write_text("epoch,val/err_mean\n1,abc\n")
    return f"{sweep / '0' / 'csv' / 'metrics.csv'}: column val/err_mean is not numeric"


def _huge_metrics_csv(sweep: Path) -> str:
    """Just under the CSV cap of 256 MiB, rows of zeros took 3.3 GB to parse (a traceback after
    summary.csv); a metrics log has its own cap, far below, and only two columns are parsed."""
    (sweep / "0" / "csv").mkdir()
    with open(sweep / "0" / "csv" / "metrics.csv", "w") as f:
        f.write("epoch,val/err_mean,x\n" + "0,0,0\n" * (2**26 // 6 + 1))
    return f"{sweep / '0' / 'csv' / 'metrics.csv'}: too large for a metrics log"


def _ood_csv(sweep: Path) -> str:
    (sweep / "0" / "ood.csv").write_text("a,b\n1,2\n")
    return f"{sweep / '0' / 'ood.csv'} unreadable (not an OOD table (no column score"


def _ood_samples(sweep: Path) -> str:
    _ood_run(sweep / "1")
    (sweep / "1" / "ood_samples.csv").write_text("set,error\nclean,1\n")
    return f"{sweep / '1' / 'ood_samples.csv'} unreadable (no set corrupted"


@pytest.mark.parametrize(
    "craft", [_jobs_status, _metrics_csv, _huge_metrics_csv, _ood_csv, _ood_samples]
)
def test_a_crafted_file_of_a_run_is_named_in_a_warning_and_left_out(tmp_path, capsys, caplog,
                                                                    craft):  # fmt: skip
    """A jobs.json whose status is a mapping (AttributeError), a metrics.csv with text for a
    number, a foreign ood.csv (KeyError 'in_table'), an ood_samples.csv without the test sets
    (a ValueError naming no file) crashed the report after summary.csv was written. Now the
    file is named in one warning, with what is wrong, and the report is written without it."""
    sweep = tmp_path / "sweep"
    _run(sweep / "0")
    warning = craft(sweep)
    with caplog.at_level("WARNING", logger="rotlearn"):
        assert main([str(sweep)]) == 0
    assert "Traceback" not in capsys.readouterr().err
    assert any(warning in r.getMessage() for r in caplog.records), caplog.text
    assert (sweep / "report.md").is_file() and (sweep / "summary.csv").is_file()


def test_a_report_that_fails_midway_leaves_the_folder_as_it_was(tmp_path, monkeypatch):
    """The report was written file by file: an error midway (a figure, here) left a new
    summary.csv beside an old report.md. It is written in a folder of its own inside the
    report's and moved into place only whole; the folder goes either way."""
    from rotlearn.report import document

    sweep = tmp_path / "sweep"
    for seed in (0, 1):
        _run(sweep / str(seed), seed=seed, error=1.0 + seed)
    make_report(sweep)
    before = {p.name: p.read_bytes() for p in sweep.iterdir() if p.is_file()}
    assert {"summary.csv", "report.md"} <= set(before)
    _run(sweep / "2", seed=2, error=5.0)  # a third run: every file would change

    def broken(*args, **kwargs):
        raise RuntimeError("a figure that cannot be drawn")

    monkeypatch.setattr(document, "_beliefs", broken)
    with pytest.raises(RuntimeError, match="cannot be drawn"):
        make_report(sweep)
    assert {p.name: p.read_bytes() for p in sweep.iterdir() if p.is_file()} == before
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1", "2"]
    monkeypatch.undo()
    files = make_report(sweep)
    assert files["report"] == sweep / "report.md"
    assert (sweep / "summary.csv").read_bytes() != before["summary.csv"]  # the third run in it
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1", "2"]


def test_a_plot_named_like_another_output_is_written_beside_it(tmp_path):
    """A received layout may name a plot `summary.png`: the report's record of its files is
    keyed by stem, so the staged summary.csv went unlisted and was never moved into place.
    Every staged file is."""
    sweep = tmp_path / "sweep"
    for job, lr in enumerate((0.1, 0.01)):
        layout = {"plots": [{"kind": "box", "x": "optim.lr", "file": "summary.png"}]}
        run = _run(sweep / str(job), report=layout, error=1.0 + job)
        config = yaml.safe_load((run / ".hydra" / "config.yaml").read_text())
        (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump({**config, "optim": {"lr": lr}}))
        (run / "test_errors.json").write_text(json.dumps([1.0 + job, 2.0 + job]))
    make_report(sweep)
    assert (sweep / "summary.csv").is_file() and (sweep / "summary.png").is_file()


def test_a_sweep_whose_report_is_refused_ends_with_a_warning_and_its_results(tmp_path, caplog):
    """The report at a multirun's end (`ReportCallback`) raised the layout's refusal past Hydra
    once the jobs were done; it now warns, naming the file and the command to run again."""
    from omegaconf import OmegaConf

    from rotlearn.cli.callbacks import ReportCallback

    sweep = tmp_path / "sweep"
    _run(sweep / "0", report={"plots": [{"kind": "curves", "file": "../out.png"}]})
    config = OmegaConf.create({"hydra": {"sweep": {"dir": str(sweep)}}})
    ReportCallback().on_multirun_end(config)
    assert "no report:" in caplog.text and "report.plots[0].file" in caplog.text
    assert sorted(p.name for p in sweep.iterdir()) == ["0"] and not (tmp_path / "out.png").exists()


def test_a_runs_tensorboard_folder_is_read_only_within_its_bounds(tmp_path, caplog, monkeypatch):
    """TensorBoard's reader lists a folder again for each file in it: 4,000 empty event files (0
    bytes, under the byte cap) took 79 s for one run's curve. A folder with more files than a run
    writes, more bytes than the cap, or a file leading out of the run is not read, and a warning
    names it; a run within them is read."""
    from torch.utils.tensorboard import SummaryWriter

    from rotlearn.io import MAX_BYTES
    from rotlearn.report.tensorboard import MAX_EVENT_FILES, read_curve

    run = _run(tmp_path / "run")
    with SummaryWriter(str(run / "tensorboard" / "tb" / "val")) as writer:
        for epoch in range(3):
            writer.add_scalar("error/mean", 3.0 - epoch, epoch)
    assert read_curve(run, "val/err_mean").tolist() == [3.0, 2.0, 1.0]
    many = tmp_path / "many"
    shutil.copytree(run, many)
    for i in range(MAX_EVENT_FILES):
        (many / "tensorboard" / "tb" / "val" / f"events.out.tfevents.{i}.x").touch()
    outside = tmp_path / "outside"
    shutil.copytree(run, outside)
    (outside / "tensorboard" / "tb" / "val" / "events.out.tfevents.0.y").symlink_to(
        next((run / "tensorboard" / "tb" / "val").iterdir())
    )
    deep = tmp_path / "deep"  # 1100 levels ended the report in a RecursionError (rglob)
    shutil.copytree(run, deep)
    (deep / "tensorboard" / "tb" / Path(*["d"] * 20)).mkdir(parents=True)
    for bad, said in ((many, f"over {MAX_EVENT_FILES} files"), (outside, "not a regular file"),
                      (deep, "folders nested more than 8 deep")):  # fmt: skip
        caplog.clear()
        assert read_curve(bad, "val/err_mean") is None
        assert said in caplog.text and str(bad / "tensorboard") in caplog.text
    monkeypatch.setitem(MAX_BYTES, "TensorBoard events", 16)
    caplog.clear()
    assert read_curve(run, "val/err_mean") is None and "over 16 bytes" in caplog.text


def test_the_report_says_which_weights_were_tested(tmp_path):
    """report.md's error table did not say whether the last or the best validation epoch's
    weights were tested (`test_ckpt`); a received metrics.json's other text is not shown."""
    from rotlearn.report.document import make_report

    sweep = tmp_path / "sweep"
    for seed, weights in enumerate(["last", "best", "last", "<script>"]):
        run = _run(sweep / str(seed), seed=seed, error=1.0 + seed)
        metrics = json.loads((run / "metrics.json").read_text())
        (run / "metrics.json").write_text(json.dumps({**metrics, "tested_weights": weights}))
    report = make_report(sweep)["report"].read_text()
    assert ("Weights tested: the last epoch's (2 runs), the best validation epoch's (1 run), "
            "not recorded (1 run) (test_ckpt).") in report  # fmt: skip
    assert "<script>" not in report


def test_the_report_names_the_runs_that_diverged(tmp_path):
    """A diverged run (metrics.json's `diverged`) lifted the error table's percentiles with
    nothing in report.md or summary.csv to say so; a received file's other value is not one."""
    import pandas as pd

    from rotlearn.report.document import make_report

    sweep = tmp_path / "sweep"
    for seed, diverged in enumerate([False, True, "yes", 1]):
        run = _run(sweep / str(seed), seed=seed, error=1.0 + 100 * (seed == 1))
        metrics = json.loads((run / "metrics.json").read_text())
        (run / "metrics.json").write_text(json.dumps({**metrics, "diverged": diverged}))
    files = make_report(sweep)
    report = files["report"].read_text()
    assert "Diverged (1 of 4: test error above predicting the identity's" in report
    assert "in the table): 1." in report
    summary = pd.read_csv(files["summary"], dtype={"job": str}).set_index("job")["diverged"]
    assert summary.astype(object).where(summary.notna(), None).to_dict() == {
        "0": False, "1": True, "2": None, "3": None
    }  # fmt: skip
