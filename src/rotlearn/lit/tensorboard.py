"""TensorBoard laid out for comparing runs: learning curves against the epoch, train / val / test
as sub-runs of one run, the one-shot results in the HPARAMS view and one text table.

`TensorBoardRunLogger` (`logger=tensorboard`) writes below `<save_dir>/<name>/<version>/`, the
version being the run's name (`rotlearn-train` names it by its overrides, e.g.
`rep=a,optim.lr=0.001`):

- `train/`, `val/`, `test/`: one sub-run per stage, so a card draws the training and validation
  curves of a run together and the test value as one point at the tested weights' epoch (the
  last, or with `test_ckpt=best` the best's: `tested_epochs`). A metric logged
  as `<stage>/<name>` is drawn in its stage's sub-run under a tag shared by the stages:
  `<stage>/err_<stat>` as `error/<stat>` (degrees), `train/loss` and `val/loss` as
  `learning/loss`, ... (the table of `rotlearn.report.tensorboard`, which reads them back).
- The x-axis is the epoch: a value logged at the end of epoch e (Lightning's 0-based
  `current_epoch`) is drawn at step e + 1, the number of epochs trained, so runs with any number
  of batches per epoch line up; a resumed run continues its curves.
- `log_results` ends a run: its headline results as points in `test/`, its HPARAMS record (the
  session lives in the `test/` sub-run, so the HPARAMS view's metrics are exactly the test
  results: TensorBoard takes every scalar of a session's run as a metric), and one text table.

Time Series groups cards by the tag's first part, in alphabetical order, and opens the first two
groups: `error` and `learning`, the curves.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.loggers import TensorBoardLogger
from lightning.pytorch.utilities import rank_zero_only

from rotlearn.report.tensorboard import SESSION_RUN, tensorboard_place
from rotlearn.trust import config_target

__all__ = ["TensorBoardRunLogger"]


def _session_summaries(hparams: Mapping[str, Any]) -> list[Any]:
    """The summaries that open and close one HPARAMS session with these hyper-parameters (bool,
    number or text each; TensorBoard's own writers turn booleans into 1.0 / 0.0)."""
    from tensorboard.compat.proto.summary_pb2 import Summary
    from tensorboard.plugins.hparams import api_pb2, metadata, plugin_data_pb2

    def summary(tag: str, **data: Any) -> Summary:
        content = plugin_data_pb2.HParamsPluginData(version=metadata.PLUGIN_DATA_VERSION, **data)
        value = Summary.Value(tag=tag, metadata=metadata.create_summary_metadata(content))
        return Summary(value=[value])

    start = plugin_data_pb2.SessionStartInfo(start_time_secs=time.time())
    for key, value in hparams.items():
        if isinstance(value, bool):
            start.hparams[key].bool_value = value
        elif isinstance(value, (int, float)):
            start.hparams[key].number_value = float(value)
        else:
            start.hparams[key].string_value = str(value)
    end = plugin_data_pb2.SessionEndInfo(status=api_pb2.STATUS_SUCCESS, end_time_secs=time.time())
    return [
        summary(metadata.SESSION_START_INFO_TAG, session_start_info=start),
        summary(metadata.SESSION_END_INFO_TAG, session_end_info=end),
    ]


@config_target
class TensorBoardRunLogger(TensorBoardLogger):
    """Lightning's TensorBoard logger with rotlearn's layout (module docstring).

    Args:
        save_dir: the run directory.
        name: the folder below it (`tensorboard`).
        version: the run's name, the folder of its events (null: Lightning's version_<n>;
            `rotlearn-train` gives the run's name).
        **kwargs: as Lightning's `TensorBoardLogger` (e.g. `default_hp_metric`), and the
            `SummaryWriter`'s.
    """

    def __init__(
        self,
        save_dir: str | Path,
        name: str = "tensorboard",
        version: int | str | None = None,
        **kwargs: Any,
    ) -> None:
        super().__init__(save_dir, name=name, version=version, **kwargs)
        self._runs: dict[str, Any] = {}

    @property
    def experiment(self) -> Any:
        """The run's own `SummaryWriter`, made when first written to (Lightning asks for it when
        setting up, which would leave an empty event file, an extra run in TensorBoard)."""
        return _LazyWriter(self)

    def writer(self, run: str = "") -> Any:
        """The `SummaryWriter` of a sub-run ("": the run itself), made on first use."""
        if run not in self._runs:
            from torch.utils.tensorboard import SummaryWriter

            folder = Path(self.log_dir) / run if run else Path(self.log_dir)
            self._runs[run] = SummaryWriter(str(folder), **self._kwargs)
        return self._runs[run]

    @rank_zero_only
    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        """Each metric as a scalar in its sub-run under its shared tag (`tensorboard_place`), at
        the epoch: Lightning adds `epoch` (0-based) to what a module logs, drawn at epoch + 1."""
        metrics = dict(metrics)
        epoch = metrics.pop("epoch", None)
        if epoch is not None:
            step = int(epoch) + 1
        for key, value in metrics.items():
            run, tag = tensorboard_place(key)
            if isinstance(value, torch.Tensor):
                value = value.item()
            self.writer(run).add_scalar(tag, float(value), step)

    @rank_zero_only
    def log_figure(self, tag: str, figure: Any, step: int, run: str = SESSION_RUN) -> None:
        """A matplotlib figure as an image card (in the test sub-run: one-shot figures)."""
        self.writer(run).add_figure(tag, figure, step, close=False)

    @rank_zero_only
    def log_results(
        self,
        hparams: Mapping[str, Any],
        results: Mapping[str, float],
        step: int,
        text: str | None = None,
    ) -> None:
        """End the run's record: `results` (metric keys as logged, e.g. `test/err_mean`,
        `ood/auroc_dt`) as points at `step` (the epochs the tested weights trained, as the epoch
        series are drawn), the HPARAMS session with
        `hparams` in the test sub-run, whose scalars are the session's metrics, and `text` (a
        markdown table) in the Text tab."""
        self.log_metrics(dict(results), step)
        writer = self.writer(SESSION_RUN)
        for summary in _session_summaries(hparams):
            writer._get_file_writer().add_summary(summary, step)
        if text:
            writer.add_text("results", text, step)
        self.save()

    @rank_zero_only
    def save(self) -> None:
        """Flush every writer made."""
        for writer in self._runs.values():
            writer.flush()

    @rank_zero_only
    def finalize(self, status: str) -> None:
        for writer in self._runs.values():
            writer.flush()
            writer.close()
        self._runs.clear()


class _LazyWriter:
    """Stands for a logger's own `SummaryWriter` until an attribute of it is used."""

    def __init__(self, logger: TensorBoardRunLogger) -> None:
        self._logger = logger

    def __getattr__(self, name: str) -> Any:
        return getattr(self._logger.writer(""), name)
